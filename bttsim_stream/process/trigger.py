"""Raw probe signals to pulse times: the trace cut into pulse windows, the simulator's own
trigger on each window, the counter latch.

Conventions
-----------
One probe's trace is a 1-D array of volts, sample ``i`` taken at ``t = k / f_s`` with
``k = k0 + i`` (``k0 = start_s * f_s``, the digitiser's sample counter, when that is a whole
number; else ``t = start_s + i / f_s`` to rounding). NaN samples were not recorded: a
segmented (windowed) acquisition, such as the windows the simulator publishes, is a trace
with NaN between the windows. Times in s, volts in V.

Windows
-------
The trigger of :mod:`bttsim_stream.sim.signal` works on a window around one blade passage
(:func:`~bttsim_stream.sim.signal.apply_triggers`): it latches the first edge and counts the
later ones as a double pulse. A continuous trace is cut into such windows around its *armed
regions* -- runs of samples at or above ``level_v`` (at or below it for a falling edge):

1. armed regions closer than the hold-off ``H`` (samples; default a quarter of the blade
   passing period at the local shaft speed) and not separated by a gap are one pulse;
2. the window of a pulse whose regions span ``[s, e]`` is ``[max(g0, m-, s - H),
   min(g1, m+, e + H)]``: ``g0, g1`` the recorded segment's ends, ``m-, m+`` the midpoints
   to the neighbouring pulses;
3. the trigger runs on each window; the first edge is the pulse's time of arrival, the
   later ones its double edges; a window with no edge (a threshold trigger never re-armed)
   gives no pulse.

A segment between gaps that holds one pulse is therefore its own window: ingesting the
windows a simulated run publishes re-runs its trigger on the very samples it saw. Then
the counter: ``t = floor(t f_c) / f_c`` (:func:`~bttsim_stream.sim.signal.latch_s`).

:class:`PulseTrigger` takes the trace in blocks of any size, holding back only the samples
of a pulse that may continue in the next block: the result does not depend on the blocks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..sim.signal import SignalWindows, Trigger, apply_triggers, latch_s

__all__ = ["TriggeredPulses", "PulseTrigger", "MAX_PULSE_SAMPLES"]

#: Longest run of samples one pulse may hold (an always-armed trace is not a probe signal).
MAX_PULSE_SAMPLES = 1 << 23


@dataclass(frozen=True, slots=True, eq=False)
class TriggeredPulses:
    """Pulses found in a stretch of trace.

    Attributes
    ----------
    toa_s : ndarray, shape (n,)
        First edge of each pulse window, latched, s (increasing).
    double_pulse : ndarray of int64, shape (m,)
        Index into ``toa_s`` of each later edge (a double pulse).
    double_toa_s : ndarray, shape (m,)
        Its time, latched, s.
    unfired : int
        Armed windows in which the trigger found no edge.
    """

    toa_s: np.ndarray
    double_pulse: np.ndarray
    double_toa_s: np.ndarray
    unfired: int = 0


class PulseTrigger:
    """One probe's trace, block by block, to pulses (see the module notes).

    Parameters
    ----------
    trigger : Trigger
        The trigger (:class:`~bttsim_stream.sim.signal.Trigger`).
    sample_rate_hz : float
    start_s : float
        Time of the first sample, s.
    holdoff_s : float or callable
        Hold-off ``H``, s; a callable maps times (s, shape (n,)) to hold-offs.
    clock_hz : float
        Counter that latches the trigger, Hz; 0: no latch.
    """

    def __init__(self, trigger: Trigger, sample_rate_hz: float, start_s: float = 0.0, holdoff_s=1e-4,
                 clock_hz: float = 0.0) -> None:
        if not (math.isfinite(sample_rate_hz) and sample_rate_hz > 0):
            raise ValueError(f"sample_rate_hz must be > 0, got {sample_rate_hz!r}")
        self.trigger = trigger
        self.fs = float(sample_rate_hz)
        k0 = start_s * self.fs
        self._whole = abs(k0 - round(k0)) <= 1e-6  # on the counter grid (to a millionth of a sample)
        self._k0 = int(round(k0)) if self._whole else 0
        self._start_s = float(start_s)
        self._holdoff = holdoff_s
        self.clock_hz = float(clock_hz)
        self._sign = -1.0 if (trigger.kind == "threshold" and trigger.edge == "falling") else 1.0
        self._carry = np.zeros(0)
        self._carry_at = 0          # sample index (from the trace start) of the carry's first sample
        self._prev_end = None       # last armed sample of the last pulse given out
        self._done = False

    def _time(self, i: np.ndarray) -> np.ndarray:
        return (self._k0 + i) / self.fs if self._whole else self._start_s + i / self.fs

    def _holdoff_samples(self, i: np.ndarray) -> np.ndarray:
        h = self._holdoff(self._time(i)) if callable(self._holdoff) else np.full(i.shape, float(self._holdoff))
        return np.maximum(np.ceil(np.asarray(h, float) * self.fs), 1.0).astype(np.int64)

    def feed(self, volts, final: bool = False) -> TriggeredPulses:
        """The pulses complete after this block (all that are left when ``final``)."""
        if self._done:
            raise RuntimeError("PulseTrigger: fed after the final block")
        y = np.concatenate([self._carry, np.asarray(volts, dtype=float).ravel()])
        at = self._carry_at
        self._done = final
        gap = np.isnan(y)
        armed = np.zeros(y.size, bool)
        ok = ~gap
        armed[ok] = (self._sign * y[ok]) >= self._sign * self.trigger.level_v
        d = np.diff(armed.astype(np.int8), prepend=0, append=0)
        s = np.flatnonzero(d == 1)
        e = np.flatnonzero(d == -1) - 1
        n_gap = np.concatenate([[0], np.cumsum(gap)])  # gaps before index i: n_gap[i]
        h = self._holdoff_samples(at + s)
        # regions merge into one pulse when close and not split by a gap
        if s.size:
            join = (s[1:] - e[:-1] <= h[:-1]) & (n_gap[s[1:]] == n_gap[e[:-1] + 1])
            head = np.r_[True, ~join]
            gi = np.cumsum(head) - 1
            gs = s[head]
            ge = np.zeros(gs.size, np.int64)
            np.maximum.at(ge, gi, e)
            gh = h[head]
        else:
            gs = ge = gh = np.zeros(0, np.int64)
        gap_idx = np.flatnonzero(gap)
        # completeness: a gap after the pulse, or more than 2 H of trace after it
        if final:
            complete = np.ones(gs.size, bool)
        else:
            nxt_gap = np.searchsorted(gap_idx, ge, side="right")
            has_gap = nxt_gap < gap_idx.size
            complete = has_gap | (y.size - 1 - ge > 2 * gh)
            bad = np.flatnonzero(~complete)
            if bad.size:
                complete[bad[0]:] = False
        nc = int(complete.sum())
        # window bounds, in the block's indices
        seg_lo = np.zeros(gs.size, np.int64)
        seg_hi = np.full(gs.size, y.size - 1, np.int64)
        if gap_idx.size:
            p = np.searchsorted(gap_idx, gs)
            seg_lo = np.where(p > 0, gap_idx[np.maximum(p - 1, 0)] + 1, 0)
            q = np.searchsorted(gap_idx, ge)
            seg_hi = np.where(q < gap_idx.size, gap_idx[np.minimum(q, gap_idx.size - 1)] - 1, y.size - 1)
        prev_e = np.r_[(-(1 << 62)) if self._prev_end is None else self._prev_end - at, ge[:-1]]
        mid_lo = (prev_e + gs + 1) // 2
        next_s = np.r_[gs[1:], 1 << 62]
        mid_hi = (ge + next_s + 1) // 2 - 1
        lo = np.maximum.reduce([seg_lo, mid_lo, gs - gh])
        hi = np.minimum.reduce([seg_hi, mid_hi, ge + gh])
        out = self._trigger(y, at, lo[:nc], hi[:nc])
        if nc:
            self._prev_end = at + int(ge[nc - 1])
        # hold back what may continue: from the first incomplete pulse's window, else the last
        # 8 hold-offs (the next pulse's window may reach back that far; the speed does not
        # change 4-fold within a block)
        if final:
            cut = y.size
        elif nc < gs.size:
            cut = int(lo[nc])
        else:
            tail = 8 * int(self._holdoff_samples(np.array([at + y.size]))[0]) + 2
            cut = max(0, y.size - tail)
            if nc:
                cut = max(cut, int(hi[nc - 1]) + 1)
        if y.size - cut > MAX_PULSE_SAMPLES:
            raise ValueError(f"no pulse ends within {MAX_PULSE_SAMPLES} samples after sample {at + cut}: "
                             f"not a probe signal, or the level {self.trigger.level_v:g} V is wrong")
        self._carry = y[cut:].copy()
        self._carry_at = at + cut
        return out

    def _trigger(self, y: np.ndarray, at: int, lo: np.ndarray, hi: np.ndarray) -> TriggeredPulses:
        n = lo.size
        if n == 0:
            return TriggeredPulses(np.zeros(0), np.zeros(0, np.int64), np.zeros(0))
        n_samp = (hi - lo + 1).astype(np.int64)
        rows = lo[None, :] + np.minimum(np.arange(int(n_samp.max()))[:, None], n_samp[None, :] - 1)
        volts = y[rows]
        if self._whole:
            first = self._k0 + at + lo
        else:  # off the counter grid: t_first = first / fs to rounding
            first = self._start_s * self.fs + (at + lo).astype(float)
        win = SignalWindows(first_sample=first, n_samples=n_samp, volts=volts,
                            codes=np.zeros((0, n), np.int32), sample_rate_hz=self.fs)
        res = apply_triggers(win, [self.trigger], np.zeros(n, np.int64))
        toa, ex_p, ex_t = res.toa_s, res.extra_passage, res.extra_toa_s
        if self.clock_hz > 0:
            toa, ex_t = latch_s(toa, self.clock_hz), latch_s(ex_t, self.clock_hz)
        fired = np.isfinite(toa)
        new_index = np.cumsum(fired) - 1
        keep = fired[ex_p]
        return TriggeredPulses(toa[fired], new_index[ex_p[keep]].astype(np.int64), ex_t[keep],
                               unfired=int(n - fired.sum()))

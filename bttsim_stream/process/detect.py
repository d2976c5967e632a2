"""What happens in a run: speed segments, resonance crossings, a quiet reference window.

The processing must not assume a run-up that starts quiet and crosses one resonance. This
module reads the run instead:

1. **Speed segments** (:func:`speed_segments`). The OPR speed (smoothed over a few
   revolutions) is simplified into a polyline (Ramer-Douglas-Peucker, tolerance
   :attr:`DetectOptions.knot_tolerance` of the speed). A segment whose speed changes by less
   than :attr:`DetectOptions.dwell_tolerance` (relative; the half-power bandwidth ``2 zeta``
   of a mode with ``zeta = 0.5 %``) and lasts at least :attr:`DetectOptions.min_dwell_s` is
   a **dwell** (steady state); the other segments are ramps. Consecutive ramps that keep
   the direction of the speed form a **sweep** (a run-up or a run-down); dwells separate
   sweeps.
2. **Resonance crossings** (:func:`detect_crossings`), per engine order and sweep, on the
   amplitude of the Eq. 16 fits (blade RMS, running median then mean over
   :attr:`DetectOptions.filter_revolutions`). A crossing is an interior peak of that curve
   whose

   * **prominence ratio** ``R = A_peak / A_base`` -- ``A_base`` the higher of the two minima
     that separate the peak from higher ground on either side (the prominence's bases) --
     is at least :attr:`DetectOptions.ratio_threshold` (2: the response falls below half the
     peak on *both* sides, so the resonance is crossed, not merely approached), and whose
   * **signal-to-noise ratio** ``(A_peak - A_base) / sigma`` -- ``sigma`` the noise of the
     smoothed curve, from the robust scatter of the unsmoothed one -- is at least
     :attr:`DetectOptions.snr_threshold` (8).

   A peak at the edge of a sweep (a run that starts or stops inside a resonance) is not a
   crossing. The crossing's window is the stretch between its two bases, at most
   :attr:`DetectOptions.window_widths` half-power widths from the peak on each side.
3. **Reference (zeroing) window** (:func:`choose_reference`): ``L`` consecutive ramp
   revolutions where the response predicted from every detected crossing (an SDOF curve of
   the crossing's peak speed and half-power width) is below
   :attr:`DetectOptions.contamination_limit` of that crossing's peak, the slowest such window
   (the noise of Eq. 15 grows with speed). Dwells are never used: at constant speed the
   vibration cannot be told from an offset. When no window qualifies, the least
   contaminated one is used and its predicted contamination is reported.

Everything here works on per-revolution arrays (``(revolution,)`` or ``(revolution,
blade)``), SI units; revolutions are indices into the run's arrays.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from .peak_finding import interior_peaks
from .prep import median_then_mean

__all__ = ["DetectOptions", "SpeedSegment", "Sweep", "RunSegments", "Crossing", "Reference",
           "speed_segments", "detection_curve", "detect_crossings", "choose_reference", "resolve_engine_orders",
           "predicted_contamination", "predicted_response", "block_sigma", "MIN_BLOCKS"]

TWO_PI = 2.0 * np.pi
_SNR_CAP = 1e9  # a noise-free curve: reported as this, not inf (JSON)


@dataclass(frozen=True, slots=True)
class DetectOptions:
    """Parameters of segmentation, crossing detection and the reference window.

    Attributes
    ----------
    dwell_tolerance : float
        A segment is a dwell when its speed changes by less than this fraction of its mean
        speed (the relative half-power bandwidth ``2 zeta`` of a mode of ``zeta = 0.5 %``).
    min_dwell_s : float
        Shortest dwell, s.
    knot_tolerance : float
        Polyline tolerance of the speed profile, as a fraction of the median speed.
    filter_revolutions : int
        Running median and mean of the detection curve, revolutions.
    ratio_threshold : float
        Least prominence ratio ``A_peak / A_base`` of a crossing.
    snr_threshold : float
        Least ``(A_peak - A_base) / sigma`` of a crossing.
    window_widths : float
        A crossing's window extends at most this many half-power widths from its peak.
    exclusion_level, exclusion_margin : float
        The baseline of the data preparation leaves out, around each crossing, the
        revolutions above ``exclusion_level`` of its peak, widened by ``exclusion_margin``
        half-power widths on each side.
    contamination_limit : float
        Largest predicted response in the reference window, as a fraction of each crossing's
        peak.
    reference_revolutions : int
        Length of the reference window.
    dwell_snr_threshold : float
        A dwell's response is reported as detected when its blade-mean amplitude exceeds this
        many standard uncertainties.
    """

    dwell_tolerance: float = 0.01
    min_dwell_s: float = 2.0
    knot_tolerance: float = 0.002
    filter_revolutions: int = 11
    ratio_threshold: float = 2.0
    snr_threshold: float = 8.0
    window_widths: float = 6.0
    exclusion_level: float = 0.1
    exclusion_margin: float = 1.0
    contamination_limit: float = 0.05
    reference_revolutions: int = 64
    dwell_snr_threshold: float = 5.0

    def __post_init__(self) -> None:
        if not self.dwell_tolerance > 0 or not self.min_dwell_s > 0 or not self.knot_tolerance > 0:
            raise ValueError("dwell_tolerance, min_dwell_s and knot_tolerance must be > 0")
        if int(self.filter_revolutions) < 1 or int(self.reference_revolutions) < 1:
            raise ValueError("filter_revolutions and reference_revolutions must be >= 1")
        if not self.ratio_threshold > 1 or not self.snr_threshold > 0:
            raise ValueError("ratio_threshold must be > 1 and snr_threshold > 0")


@dataclass(frozen=True, slots=True)
class SpeedSegment:
    """A piece of the speed profile: revolutions ``[start, stop)``.

    Attributes
    ----------
    start, stop : int
    kind : {"ramp", "dwell"}
    rpm_start, rpm_end : float
        Smoothed speed at the first and last revolution, rpm.
    duration_s : float
    """

    start: int
    stop: int
    kind: str
    rpm_start: float
    rpm_end: float
    duration_s: float

    @property
    def direction(self) -> int:
        """+1 run-up, -1 run-down, 0 flat."""
        if self.kind == "dwell" or self.rpm_end == self.rpm_start:
            return 0
        return 1 if self.rpm_end > self.rpm_start else -1


@dataclass(frozen=True, slots=True)
class Sweep:
    """Consecutive ramp revolutions ``[start, stop)`` in one direction (+1 up, -1 down)."""

    start: int
    stop: int
    direction: int


@dataclass(frozen=True, slots=True, eq=False)
class RunSegments:
    """The run's speed profile read from the OPR: segments, sweeps and dwells.

    Attributes
    ----------
    segments : tuple of SpeedSegment
    sweeps : tuple of Sweep
    dwells : tuple of SpeedSegment
        The dwell segments.
    omega_smooth_rad_s : ndarray, shape (n_rev,)
    """

    segments: tuple
    sweeps: tuple
    dwells: tuple
    omega_smooth_rad_s: np.ndarray

    def dwell_mask(self, n_rev: int) -> np.ndarray:
        """Boolean (n_rev,): revolutions inside a dwell."""
        m = np.zeros(n_rev, bool)
        for d in self.dwells:
            m[d.start:d.stop] = True
        return m


@dataclass(frozen=True, slots=True)
class Crossing:
    """One detected resonance crossing of one engine order.

    Attributes
    ----------
    eo : int
    peak : int
        Revolution of the detection curve's peak.
    lo, hi : int
        The crossing's window, revolutions ``lo .. hi`` inclusive.
    hp_lo, hp_hi : int
        Half-power region of the detection curve (above ``peak / sqrt(2)``).
    excl_lo, excl_hi : int
        Revolutions left out of the data preparation's baseline.
    ratio : float
        Prominence ratio ``A_peak / A_base``.
    snr : float
        ``(A_peak - A_base) / sigma``.
    amp_peak_m, amp_base_m : float
        Detection curve (blade RMS of the pk-pk amplitudes) at the peak and its base, m.
    sweep : int
        Index of the sweep in :attr:`RunSegments.sweeps`.
    direction : int
        +1 run-up, -1 run-down.
    """

    eo: int
    peak: int
    lo: int
    hi: int
    hp_lo: int
    hp_hi: int
    excl_lo: int
    excl_hi: int
    ratio: float
    snr: float
    amp_peak_m: float
    amp_base_m: float
    sweep: int
    direction: int

    @property
    def half_power_width(self) -> int:
        """Revolutions of the half-power region."""
        return self.hp_hi - self.hp_lo + 1

    def damping_estimate(self, omega_rad_s: np.ndarray) -> float:
        """``zeta ~ (Omega_hp_hi - Omega_hp_lo) / (2 Omega_peak)`` (half-power bandwidth); a
        rough value (the detection curve is smoothed and the sweep delays the response)."""
        om = np.asarray(omega_rad_s, dtype=float)
        return max(abs(float(om[self.hp_hi] - om[self.hp_lo])) / (2.0 * float(om[self.peak])), 1e-4)


@dataclass(frozen=True, slots=True)
class Reference:
    """The zeroing reference of the expected arrival times.

    Attributes
    ----------
    start, stop : int or None
        Revolutions ``[start, stop)`` (None: no usable window, nominal geometry).
    contamination : float
        Largest predicted response in the window, as a fraction of a crossing's peak.
    reason : str
        How it was chosen (for the report).
    """

    start: int | None
    stop: int | None
    contamination: float
    reason: str


def _rdp(t: np.ndarray, y: np.ndarray, tol: float) -> list[int]:
    """Indices of a Ramer-Douglas-Peucker polyline of ``(t, y)`` (vertical distance)."""
    n = t.size
    keep = {0, n - 1}
    stack = [(0, n - 1)]
    while stack:
        a, b = stack.pop()
        if b - a < 2:
            continue
        tt = t[a + 1:b]
        line = y[a] + (y[b] - y[a]) * (tt - t[a]) / max(t[b] - t[a], 1e-300)
        dev = np.abs(y[a + 1:b] - line)
        k = 1 + int(np.argmax(dev))  # an interior point: every split shrinks (ends even on NaN)
        if dev[k - 1] > tol:
            keep.add(a + k)
            stack += [(a, a + k), (a + k, b)]
    return sorted(keep)


def speed_segments(opr_s: np.ndarray, omega_rad_s: np.ndarray,
                   options: DetectOptions = DetectOptions()) -> RunSegments:
    """Split the run into ramps and dwells from its OPR speeds.

    Parameters
    ----------
    opr_s : ndarray, shape (n_rev,)
        OPR times, s.
    omega_rad_s : ndarray, shape (n_rev,)
        Mean speed per revolution (Eq. 1's Omega), rad/s.
    options : DetectOptions

    Returns
    -------
    RunSegments
    """
    t = np.asarray(opr_s, dtype=float)
    om = np.asarray(omega_rad_s, dtype=float)
    n = om.size
    if n < 3:
        seg = SpeedSegment(0, n, "ramp", *(float(om[i]) * 60 / TWO_PI for i in (0, -1)),
                           float(t[-1] - t[0]) if n else 0.0)
        return RunSegments((seg,), (Sweep(0, n, seg.direction),), (), om.copy())
    size = min(11, n)
    om_s = median_then_mean(om, size)
    d2 = np.diff(om, 2)
    noise = 1.4826 * float(np.median(np.abs(d2))) / math.sqrt(6.0) if d2.size else 0.0
    tol = max(options.knot_tolerance * float(np.median(om_s)), 4.0 * noise / math.sqrt(size))
    knots = _rdp(t, om_s, tol)
    segs = []
    for a, b in zip(knots[:-1], knots[1:]):
        stop = b + 1 if b == n - 1 else b
        if stop - a < 1:
            continue
        w0, w1 = float(om_s[a]), float(om_s[min(stop, n) - 1])
        mean = max(0.5 * (w0 + w1), 1e-12)
        dur = float(t[min(stop, n - 1)] - t[a])
        flat = abs(w1 - w0) < options.dwell_tolerance * mean
        kind = "dwell" if flat and dur >= options.min_dwell_s and stop - a >= 16 else "ramp"
        if flat and kind == "ramp":
            w1 = w0  # a short flat piece: part of the sweep around it, no direction
        segs.append(SpeedSegment(a, stop, kind, w0 * 60 / TWO_PI, w1 * 60 / TWO_PI, dur))
    # merge neighbours of the same kind and direction (the polyline may split a ramp)
    merged: list[SpeedSegment] = []
    for s in segs:
        if merged and merged[-1].kind == s.kind:
            p = merged[-1]
            same_dwell = s.kind == "dwell" and abs(s.rpm_end - p.rpm_start) < options.dwell_tolerance * 0.5 * (
                s.rpm_end + p.rpm_start)
            same_ramp = s.kind == "ramp" and (s.direction == p.direction or 0 in (s.direction, p.direction))
            if same_dwell or same_ramp:
                merged.pop()
                end = s.rpm_end if s.direction or s.kind == "dwell" else p.rpm_end
                s = SpeedSegment(p.start, s.stop, s.kind, p.rpm_start, end, p.duration_s + s.duration_s)
        merged.append(s)
    sweeps: list[Sweep] = []
    for s in merged:
        if s.kind == "dwell":
            continue
        d = s.direction
        if sweeps and sweeps[-1].stop == s.start and (d == 0 or sweeps[-1].direction in (0, d)):
            p = sweeps.pop()
            sweeps.append(Sweep(p.start, s.stop, p.direction or d))
        else:
            sweeps.append(Sweep(s.start, s.stop, d))
    dwells = tuple(s for s in merged if s.kind == "dwell")
    return RunSegments(tuple(merged), tuple(sweeps), dwells, om_s)


def detection_curve(amp_pkpk_m: np.ndarray) -> np.ndarray:
    """Blade RMS of the per-revolution amplitudes, NaN-safe.

    Parameters
    ----------
    amp_pkpk_m : ndarray, shape (n_rev, n_blades)

    Returns
    -------
    ndarray, shape (n_rev,)
        NaN where no blade has an amplitude.
    """
    a = np.asarray(amp_pkpk_m, dtype=float)
    ok = np.isfinite(a)
    n = ok.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, np.sqrt(np.where(ok, a * a, 0.0).sum(axis=1) / np.maximum(n, 1)), np.nan)


def _smooth(x: np.ndarray, size: int) -> np.ndarray:
    ok = np.isfinite(x)
    if not ok.any():
        return np.zeros_like(x)
    xf = np.where(ok, x, np.interp(np.arange(x.size), np.flatnonzero(ok), x[ok]))
    size = max(1, min(int(size), x.size))
    return median_then_mean(xf, size)


def _run_around(above: np.ndarray, i: int) -> tuple[int, int]:
    """First and last index of the run of True in ``above`` that contains ``i``."""
    lo = i
    while lo > 0 and above[lo - 1]:
        lo -= 1
    hi = i
    while hi < above.size - 1 and above[hi + 1]:
        hi += 1
    return lo, hi


#: The m-revolution means' scatter is measured from at least this many of their second
#: differences (fewer: 0, not measured; the per-revolution noise alone decides).
MIN_BLOCKS = 20
#: The slow scatter counts only where it exceeds the per-revolution noise this many times (on
#: white noise the two are equal, within the block estimate's spread).
SLOW_NOISE_FACTOR = 2.0


def block_sigma(a_raw: np.ndarray, m: int) -> float:
    """The scatter of ``m``-revolution means of a detection curve, from their second
    differences (a trend and a curvature cancel; robust): ``1.4826 MAD(b[k+1] - 2 b[k] +
    b[k-1]) / sqrt(6)``, over the blocks that hold a finite mean (NaN in ``a_raw`` masks
    revolutions, e.g. the crossing candidates' windows). On white noise it equals the
    per-revolution estimate ``sigma / sqrt(m)``; noise correlated over several revolutions (a
    speed fluctuation: the rotor turning unevenly between OPR pulses aliases into every
    order's fit) makes it larger. 0 with fewer than :data:`MIN_BLOCKS` second differences."""
    n = a_raw.size // m
    if n < MIN_BLOCKS + 2:
        return 0.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        b = np.nanmean(a_raw[:n * m].reshape(n, m), axis=1)
    d2 = b[2:] - 2.0 * b[1:-1] + b[:-2]
    d2 = d2[np.isfinite(d2)]
    return 1.4826 * float(np.median(np.abs(d2))) / math.sqrt(6.0) if d2.size >= MIN_BLOCKS else 0.0


def detect_crossings(amp_pkpk_m: np.ndarray, eo: int, segments: RunSegments,
                     options: DetectOptions = DetectOptions(), dropped: list | None = None) -> list[Crossing]:
    """Resonance crossings of one engine order in every sweep of the run.

    Parameters
    ----------
    amp_pkpk_m : ndarray, shape (n_rev, n_blades)
        Per-revolution Eq. 16 amplitudes at this engine order (zeroed on the run's median),
        m.
    eo : int
    segments : RunSegments
    options : DetectOptions
    dropped : list, optional
        Gets ``(revolution, snr, slow_snr)`` of each peak that passed the per-revolution test
        but not the one against the curve's own slow scatter (:func:`block_sigma`).

    Returns
    -------
    list of Crossing
        In revolution order. See the module docstring for the statistic.
    """
    curve = detection_curve(amp_pkpk_m)
    m = int(options.filter_revolutions)
    out = []
    for k, sw in enumerate(segments.sweeps):
        a_raw = curve[sw.start:sw.stop]
        if a_raw.size < 3 * m or not np.isfinite(a_raw).any():
            continue
        a = _smooth(a_raw, m)
        resid = a_raw - a
        resid = resid[np.isfinite(resid)]
        sigma = 1.4826 * float(np.median(np.abs(resid))) / math.sqrt(m) if resid.size else 0.0
        pk = interior_peaks(a)
        found = []  # (p, prom, top, base, ratio, snr, hp_lo, hp_hi, lo, hi) of the peaks that pass
        for p, prom, lb, rb in zip(pk.index, pk.prominence, pk.left_base, pk.right_base):
            top = float(a[p])
            base = top - float(prom)
            ratio = top / base if base > 0 else _SNR_CAP
            snr = float(prom) / sigma if sigma > 0 else _SNR_CAP
            if ratio < options.ratio_threshold or snr < options.snr_threshold:
                continue
            hp_lo, hp_hi = _run_around(a >= top / math.sqrt(2.0), int(p))
            width = hp_hi - hp_lo + 1
            reach = int(math.ceil(options.window_widths * width))
            found.append((int(p), float(prom), top, base, ratio, snr, hp_lo, hp_hi,
                          max(int(lb), int(p) - reach), min(int(rb), int(p) + reach)))
        # the curve's own slow scatter, away from every candidate's window
        masked = a_raw.astype(float, copy=True)
        for f in found:
            masked[f[8]:f[9] + 1] = np.nan
        slow = block_sigma(masked, m)
        if not slow > SLOW_NOISE_FACTOR * sigma:
            slow = 0.0
        for p, prom, top, base, ratio, snr, hp_lo, hp_hi, lo, hi in found:
            if slow > 0 and prom < options.snr_threshold * slow:  # one of the curve's own slow bumps
                if dropped is not None:
                    dropped.append((sw.start + p, min(snr, _SNR_CAP), prom / slow))
                continue
            width = hp_hi - hp_lo + 1
            ex_lo, ex_hi = _run_around(a >= max(options.exclusion_level * top, base), int(p))
            margin = int(math.ceil(options.exclusion_margin * width))
            out.append(Crossing(
                eo=int(eo), peak=sw.start + int(p), lo=sw.start + lo, hi=sw.start + hi,
                hp_lo=sw.start + hp_lo, hp_hi=sw.start + hp_hi,
                excl_lo=max(sw.start, sw.start + ex_lo - margin), excl_hi=min(sw.stop - 1, sw.start + ex_hi + margin),
                ratio=float(min(ratio, _SNR_CAP)), snr=float(min(snr, _SNR_CAP)), amp_peak_m=top,
                amp_base_m=max(base, 0.0), sweep=k, direction=sw.direction))
    return sorted(out, key=lambda c: c.peak)


def resolve_engine_orders(crossings: list[Crossing], misfit: dict) -> list[Crossing]:
    """Keep, among crossings of different engine orders whose half-power regions overlap,
    the one whose fit explains the data best.

    When the engine orders are fitted one at a time (a scan, or a layout that cannot fit
    them jointly), one engine order's resonance leaks into the other orders' fits at the
    same revolutions. The true order leaves the smallest residual.

    Parameters
    ----------
    crossings : list of Crossing
    misfit : dict
        ``{eo: callable(lo, hi) -> float}``: relative misfit of that order's fit (RMS residual
        over RMS amplitude) over revolutions ``lo .. hi``.

    Returns
    -------
    list of Crossing
    """
    order = sorted(crossings, key=lambda c: (misfit[c.eo](c.hp_lo, c.hp_hi), -c.amp_peak_m))
    kept: list[Crossing] = []
    for c in order:
        if any(k.eo != c.eo and not (c.hp_hi < k.hp_lo or c.hp_lo > k.hp_hi) for k in kept):
            continue
        kept.append(c)
    return sorted(kept, key=lambda c: c.peak)


def predicted_response(omega_rad_s: np.ndarray, crossings: list[Crossing]) -> np.ndarray:
    """Complex response predicted at each revolution from the detected crossings, relative to
    each crossing's peak response (summed over crossings).

    Each crossing is an SDOF of peak speed ``Omega_k`` and damping ``zeta_k`` (its half-power
    width); relative to its peak, ``h_k = 2 i zeta_k r / (1 - r^2 + 2 i zeta_k r)``,
    ``r = Omega / Omega_k`` (the engine order multiplies both frequencies): 1 at the peak,
    about ``2 i zeta / (1 - r^2)`` -- in quadrature with the peak, opposite signs below and
    above -- far from it.

    Returns
    -------
    ndarray of complex, shape (n_rev,)
    """
    om = np.asarray(omega_rad_s, dtype=float)
    h = np.zeros(om.size, complex)
    for c in crossings:
        z = c.damping_estimate(om)
        r = om / float(om[c.peak])
        h += 2j * z * r / (1.0 - r * r + 2j * z * r)
    return h


def predicted_contamination(omega_rad_s: np.ndarray, crossings: list[Crossing]) -> np.ndarray:
    """``|h|`` of :func:`predicted_response`, the largest over the crossings.

    Returns
    -------
    ndarray, shape (n_rev,)
    """
    om = np.asarray(omega_rad_s, dtype=float)
    rho = np.zeros(om.size)
    for c in crossings:
        rho = np.maximum(rho, np.abs(predicted_response(om, [c])))
    return rho


def _windows(ramp: np.ndarray, L: int, lo: int = 0, hi: int | None = None) -> np.ndarray:
    """Starts of the windows of ``L`` consecutive ramp revolutions within ``[lo, hi)``."""
    n = ramp.size if hi is None else hi
    if n - lo < L or L < 1:
        return np.zeros(0, np.int64)
    c = np.concatenate([[0], np.cumsum(ramp[lo:n])])
    starts = np.arange(0, n - lo - L + 1)
    return lo + starts[(c[starts + L] - c[starts]) == L]


def choose_reference(omega_rad_s: np.ndarray, segments: RunSegments, crossings: list[Crossing],
                     options: DetectOptions = DetectOptions()) -> Reference:
    """The zeroing reference: away from every detected crossing; never a dwell.

    Without crossings: the slowest window (Eq. 15: the least noise). With crossings: the
    slowest quiet window (predicted response at most :attr:`DetectOptions.contamination_limit`
    of every crossing's peak), else the least contaminated one. A single window is kept on
    purpose: its response lies on the resonance's response circle (SDOF), in quadrature with
    the peak, and the largest distance from a point of the circle is its diameter, so the
    peak amplitude is insensitive to it to first order (the peak's revolution moves by about
    ``zeta x contamination / 2`` in frequency); an average of windows on both sides would sit
    inside the circle and bias the amplitude at first order.

    Returns
    -------
    Reference
    """
    om = np.asarray(omega_rad_s, dtype=float)
    n = om.size
    ramp = ~segments.dwell_mask(n)
    if not ramp.any():
        return Reference(None, None, math.nan, "the run is a dwell: no ramp to zero on (nominal geometry)")
    L = min(int(options.reference_revolutions), n)
    starts = _windows(ramp, L)
    while starts.size == 0 and L > 1:  # ramps shorter than L
        L = max(1, L // 2)
        starts = _windows(ramp, L)
    if starts.size == 0:
        return Reference(None, None, math.nan, "no ramp revolutions to zero on (nominal geometry)")
    mean_om = np.convolve(om, np.ones(L) / L, mode="valid")
    if not crossings:
        s = int(starts[np.argmin(mean_om[starts])])
        return Reference(s, s + L, math.nan, "the slowest window (no crossing detected: its contamination unknown)")
    rho = predicted_contamination(om, crossings)
    rho_win = sliding_window_view(rho, L).max(axis=1)
    quiet = starts[rho_win[starts] <= options.contamination_limit]
    if quiet.size:
        s = int(quiet[np.argmin(mean_om[quiet])])
        return Reference(s, s + L, float(rho_win[s]), "the slowest quiet window")
    s = int(starts[np.argmin(rho_win[starts])])
    return Reference(s, s + L, float(rho_win[s]),
                     f"no window is quiet (below {100 * options.contamination_limit:g} % of a peak): the least "
                     f"contaminated one")

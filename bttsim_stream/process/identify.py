"""Blade identification of unlabelled pulse trains against the OPR (measured data in).

Conventions: those of :mod:`bttsim_stream.process.displacement` -- times in s, angles in rad
anticlockwise from +x (the direction of rotation), arrays ``(revolution, blade)`` per probe.
Revolution ``n`` starts at OPR pulse ``n`` and holds, for each blade, the arrival whose
*rigid* crossing of the probe falls in ``[OPR_n, OPR_n+1)``; blade ``b`` is the blade whose
sensing point sits at rotor angle ``theta_b`` (default ``2 pi b / N_b``) from the OPR sensor
at the OPR pulse, so it reaches probe ``j`` at rotor angle
``psi[b, j] = (theta_probe_j - theta_b - theta_opr) mod 2 pi`` after the pulse
(:meth:`~bttsim_stream.process.displacement.Geometry.nominal_arrival_angles`): the
simulator's numbering, that of ``bttsim export``.

:func:`identify_pulses` labels one probe's pulse train, vectorised over all its pulses:

1. each pulse's total rotor angle ``Phi = 2 pi n + phi_n(t)`` from the quadratic OPR model
   (:func:`~bttsim_stream.process.displacement.rotor_phase_from_opr`: speed fluctuation
   between pulses is followed to second order);
2. the nearest arrival angle (mod 2 pi) names the blade; unless the arrival angles are
   known exactly (``calibrate=False``) they are then re-centred on the median measured
   deviation of each blade (the unknown angle of the sensing point on the blade, a
   static probe angle error) and the labelling repeated;
3. ``m = round((Phi - psi_b) / 2 pi)`` is the revolution; a pulse further than
   ``tolerance`` blade pitches from its blade's angle is *stray*;
4. a cell ``(m, b)`` claimed by several pulses (a double trigger, an extra pulse) keeps the
   one nearest the blade's deviation predicted from its neighbouring revolutions (the
   median of ``m +- 1 .. m +- 3``, when at least 3 of them have a pulse; else the one
   nearest the blade's angle), the others are *extra*; a pulse further than ``outlier``
   robust scales (and ``floor`` pitches) from that prediction (plus the median departure
   of the neighbouring blades ``b +- 1 .. b +- 3`` of the same revolution from theirs: the
   rotor-angle model's error when the speed changes between OPR pulses) is extra too and
   leaves the cell missing -- a spurious pulse where the real one was lost; done twice, the second
   time predicting from the pulses the first accepted;
5. an empty cell is *missing* (NaN), which the processing already handles.

With a K-pulse shaft encoder (:func:`encoder_revolutions`) the rotor angle of step 1 is
interpolated between the encoder pulses (:func:`shaft_angle`: the quadratic through three
consecutive pulses, ``2 pi / K`` apart), which follows speed fluctuation within a revolution.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from .displacement import TWO_PI, RotorPhase, rotor_phase_from_opr

__all__ = ["IdentifiedPulses", "EncoderRevolutions", "IdentifyParams", "identify_pulses", "identify_window",
           "identification_params", "calibration_end", "last_pulse_s", "window_revolutions", "pulses_per_revolution",
           "encoder_revolutions", "shaft_angle", "CALIBRATION_REVOLUTIONS", "HALO_REVOLUTIONS"]

#: Revolutions on each side whose pulses predict a cell's, and how many must be present.
_REACH = 3
_MIN_NEIGHBOURS = 3
#: Revolutions from the probe's first pulse whose pulses calibrate the arrival angles and
#: the robust scales (all of a shorter run).
CALIBRATION_REVOLUTIONS = 6000
#: A cell's labelling depends on the pulses within 2 * _REACH revolutions (two rounds) of it,
#: a pulse lands at most one revolution from its OPR interval: a window of revolutions is
#: labelled from the pulses of its OPR intervals widened by this many on each side.
HALO_REVOLUTIONS = 2 * _REACH + 4
#: Revolution periods after the last OPR pulse beyond which a pulse is outside.
TRAILING_PERIODS = 3


@dataclass(frozen=True, slots=True, eq=False)
class IdentifiedPulses:
    """One probe's pulse train, labelled.

    Attributes
    ----------
    toa_s : ndarray, shape (n_rev, n_blades)
        The pulse of each blade in each revolution, s; NaN: missing.
    extra_revolution, extra_blade : ndarray of int64, shape (n_extra,)
        Cell of every extra pulse (in a blade's window, not kept).
    extra_toa_s : ndarray, shape (n_extra,)
    stray_revolution : ndarray of int64, shape (n_stray,)
        Revolution (OPR interval) of every stray pulse (in no blade's window).
    stray_toa_s : ndarray, shape (n_stray,)
    outside : int
        Pulses before the first OPR pulse or beyond the last revolution, dropped.
    arrival_angles_rad : ndarray, shape (n_blades,)
        The arrival angles used (calibrated unless given exactly), rad.
    """

    toa_s: np.ndarray
    extra_revolution: np.ndarray
    extra_blade: np.ndarray
    extra_toa_s: np.ndarray
    stray_revolution: np.ndarray
    stray_toa_s: np.ndarray
    outside: int
    arrival_angles_rad: np.ndarray

    @property
    def missing(self) -> int:
        """Empty cells (blade passages without a pulse)."""
        return int(np.count_nonzero(np.isnan(self.toa_s)))

    @property
    def extra(self) -> int:
        return int(self.extra_toa_s.size)

    @property
    def stray(self) -> int:
        return int(self.stray_toa_s.size)


def pulses_per_revolution(opr_s: np.ndarray, pulse_s: np.ndarray) -> np.ndarray:
    """Pulses between consecutive OPR pulses.

    Parameters
    ----------
    opr_s : ndarray, shape (n_rev,)
        OPR times, s, increasing.
    pulse_s : ndarray, shape (n_pulses,)
        Pulse times, s.

    Returns
    -------
    ndarray of int64, shape (n_rev - 1,)
        Count of pulses in ``[OPR_n, OPR_n+1)``.
    """
    opr = np.asarray(opr_s, dtype=float)
    idx = np.searchsorted(np.sort(np.asarray(pulse_s, dtype=float)), opr)
    return np.diff(idx).astype(np.int64)


@dataclass(frozen=True, slots=True, eq=False)
class EncoderRevolutions:
    """A K-pulse shaft encoder's train, with its once-per-revolution reference.

    Attributes
    ----------
    opr_s : ndarray, shape (n_rev,)
        Pulse 0 of each revolution, s.
    pulse_s : ndarray, shape (n,)
        Every encoder pulse from the first pulse 0 on, s.
    angle_rad : ndarray, shape (n,)
        Shaft angle of each pulse since the first pulse 0, rad (``2 pi tooth / K``).
    rule : str
        How pulse 0 was chosen (``"missing tooth"`` or ``"index"``).
    """

    opr_s: np.ndarray
    pulse_s: np.ndarray
    angle_rad: np.ndarray
    rule: str


def encoder_revolutions(encoder_s: np.ndarray, pulses_per_revolution: int, index: int | None = None
                        ) -> EncoderRevolutions:
    """Once-per-revolution reference and shaft angles of a K-pulse shaft encoder.

    Parameters
    ----------
    encoder_s : ndarray, shape (n,)
        Encoder pulse times, s, strictly increasing.
    pulses_per_revolution : int
        ``K``: tooth positions per revolution, equally spaced.
    index : int, optional
        Pulse ``index`` of the file is pulse 0 of a revolution, and every K-th after it
        (a wheel without a gap; no encoder pulse may be missing). Without it the wheel
        must have a missing-tooth gap: an interval of 2 or more tooth pitches (against the
        median of its 4 neighbours), once per revolution; the pulse after it is pulse 0.

    Raises
    ------
    ValueError
        No gap and no index, or a revolution whose teeth do not add up to ``K``.
    """
    e = np.asarray(encoder_s, dtype=float)
    k = int(pulses_per_revolution)
    d = np.diff(e)
    if d.size < 5:
        raise ValueError(f"{e.size} encoder pulses: too few")
    pad = np.pad(d, 2, mode="edge")
    ref = np.median(np.stack([pad[0:-4], pad[1:-3], pad[3:-1], pad[4:]]), axis=0)
    step = np.maximum(np.round(d / ref), 1).astype(np.int64)  # tooth pitches per interval
    if index is None:
        gaps = np.flatnonzero(step >= 2)
        if gaps.size < 2:
            raise ValueError(f"no missing-tooth gap in the {k}-pulse encoder train (give the index pulse: "
                             f"--encoder-index)")
        first = int(gaps[0]) + 1
        rule = "missing tooth"
    else:
        if np.any(step != 1):
            i = int(np.flatnonzero(step != 1)[0])
            raise ValueError(f"encoder pulse {i + 1} comes {step[i]} tooth pitches after the previous one: "
                             f"encoder pulses missing (or a missing-tooth wheel: leave out --encoder-index)")
        if not 0 <= index < min(k, e.size):
            raise ValueError(f"--encoder-index {index} must be in [0, {k - 1}]")
        first = int(index)
        rule = "index"
    tooth = np.r_[0, np.cumsum(step[first:])]
    p = e[first:]
    if index is None:  # every gap must close a revolution of exactly K tooth positions
        at_gap = np.r_[False, step[first:] >= 2]
        bad = np.flatnonzero(at_gap & (tooth % k != 0))
        if bad.size:
            raise ValueError(f"encoder pulse {first + int(bad[0])}: a gap after {int(tooth[bad[0]] % k)} tooth "
                             f"positions of the revolution, not {k} (wrong --encoder-pulses, or pulses missing)")
    zero = tooth % k == 0
    return EncoderRevolutions(opr_s=p[zero], pulse_s=p, angle_rad=TWO_PI * tooth / k, rule=rule)


def shaft_angle(opr_s: np.ndarray, t_s: np.ndarray, encoder: EncoderRevolutions | None = None,
                phase: RotorPhase | None = None) -> np.ndarray:
    """Total rotor angle since ``opr_s[0]`` at times ``t_s``, rad.

    Without an encoder: ``2 pi n + phi_n(t)`` from the quadratic OPR model
    (:func:`~bttsim_stream.process.displacement.rotor_phase_from_opr`). With one: the
    quadratic through the three encoder pulses nearest ``t`` (inside the encoder's span;
    the OPR model outside it).

    Parameters
    ----------
    opr_s : ndarray, shape (n_rev,)
    t_s : ndarray, shape (n,)
        Times at or after ``opr_s[0]``, s.
    encoder : EncoderRevolutions, optional
    phase : RotorPhase, optional
        ``rotor_phase_from_opr(opr_s)``, when already computed.
    """
    opr = np.asarray(opr_s, dtype=float)
    t = np.asarray(t_s, dtype=float)
    n = np.clip(np.searchsorted(opr, t, side="right") - 1, 0, opr.size - 1)
    phase = rotor_phase_from_opr(opr) if phase is None else phase
    total = TWO_PI * n + phase.rows(n).angle(t)
    if encoder is None or encoder.pulse_s.size < 3:
        return total
    e, a = encoder.pulse_s, encoder.angle_rad
    inside = (t >= e[0]) & (t <= e[-1])
    i = np.clip(np.searchsorted(e, t[inside], side="right") - 1, 0, e.size - 3)
    # Newton form through (e_i, a_i), (e_i+1, a_i+1), (e_i+2, a_i+2)
    t0, t1, t2 = e[i], e[i + 1], e[i + 2]
    f01 = (a[i + 1] - a[i]) / (t1 - t0)
    f12 = (a[i + 2] - a[i + 1]) / (t2 - t1)
    f012 = (f12 - f01) / (t2 - t0)
    x = t[inside]
    total[inside] = a[i] + (x - t0) * (f01 + (x - t1) * f012)
    return total


def _nearest(total: np.ndarray, psi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Blade of the nearest arrival angle (mod 2 pi) and the signed deviation from it, rad."""
    order = np.argsort(psi)
    ps = psi[order]
    r = np.mod(total, TWO_PI)
    i = np.searchsorted(ps, r)
    lo, hi = order[(i - 1) % ps.size], order[i % ps.size]
    d_lo = np.mod(r - psi[lo] + np.pi, TWO_PI) - np.pi
    d_hi = np.mod(r - psi[hi] + np.pi, TWO_PI) - np.pi
    pick_lo = np.abs(d_lo) <= np.abs(d_hi)
    return np.where(pick_lo, lo, hi), np.where(pick_lo, d_lo, d_hi)


def _first_per_cell(key: np.ndarray, score: np.ndarray) -> np.ndarray:
    """Indices of the lowest ``score`` of every distinct ``key``."""
    srt = np.lexsort((score, key))
    first = np.ones(srt.size, bool)
    first[1:] = key[srt][1:] != key[srt][:-1]
    return srt[first]


@dataclass(frozen=True, slots=True, eq=False)
class IdentifyParams:
    """What :func:`identify_window` needs besides the pulses: found once per probe by
    :func:`identification_params` on the calibration span.

    Attributes
    ----------
    arrival_angles_rad : ndarray, shape (n_blades,)
        Arrival angles, calibrated unless given exactly, rad.
    scale_rad : ndarray, shape (2, n_blades)
        Robust scale per blade of each selection round (NaN: none), rad.
    tolerance, outlier, floor : float
        As :func:`identify_pulses` takes them.
    """

    arrival_angles_rad: np.ndarray
    scale_rad: np.ndarray
    tolerance: float = 0.25
    outlier: float = 20.0
    floor: float = 0.02


def calibration_end(opr_s: np.ndarray, first_pulse_s: float) -> tuple[int, float]:
    """The calibration span: the first :data:`CALIBRATION_REVOLUTIONS` revolutions from the
    one of the probe's first pulse, ``opr_s[:k]`` and the pulses from ``opr_s[0]`` to the
    time returned (``opr_s[k - 1]``, or :func:`last_pulse_s` when ``k == opr_s.size``)."""
    n0 = max(int(np.searchsorted(opr_s, first_pulse_s, side="right")) - 1, 0)
    k = int(min(opr_s.size, n0 + CALIBRATION_REVOLUTIONS + 1))
    return k, (float(opr_s[k - 1]) if k < opr_s.size else last_pulse_s(opr_s))


def last_pulse_s(opr_s: np.ndarray) -> float:
    """Time after which a pulse can only be *outside* (beyond the last revolution): the last
    OPR pulse plus :data:`TRAILING_PERIODS` of its revolution period."""
    return float(opr_s[-1] + TRAILING_PERIODS * (opr_s[-1] - opr_s[-2]))


def window_revolutions(start: int, stop: int, n_rev: int) -> tuple[int, int]:
    """OPR intervals ``[lo, hi)`` whose pulses :func:`identify_window` needs for revolutions
    ``start:stop`` (``lo == 0``: also the pulses before the first OPR pulse; ``hi == n_rev``:
    also those after the last)."""
    lo, hi = start - HALO_REVOLUTIONS, stop + HALO_REVOLUTIONS
    return (0 if lo <= 0 else lo), (n_rev if hi >= n_rev else hi)


def _labels(opr, t, psi, encoder, phase):
    """Revolution interval, total rotor angle, nearest blade and deviation of each pulse."""
    n = np.searchsorted(opr, t, side="right") - 1
    total = shaft_angle(opr, t, encoder, phase)
    blade, dev = _nearest(total, psi)
    return n, total, blade, dev


def _select(m, blade, dev, ci, r0, r1, nb, pitch, outlier, floor, scale):
    """Steps 4 of the module notes on the cell pulses ``ci`` whose revolutions lie in
    ``[r0, r1)``: the kept pulses and the scale of each round (``scale`` None: measured)."""
    key = m[ci] * nb + blade[ci]
    kept = ci[_first_per_cell(key, np.abs(dev[ci]))]
    nw = r1 - r0
    scales = []
    for rnd in range(2):
        dev_cell = np.full((nw + 2 * _REACH, nb), np.nan)
        dev_cell[m[kept] - r0 + _REACH, blade[kept]] = dev[kept]
        neigh = np.stack([dev_cell[k:k + nw] for k in range(2 * _REACH + 1) if k != _REACH])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            pred = np.nanmedian(neigh, axis=0)  # (nw, nb)
        trusted = np.sum(np.isfinite(neigh), axis=0) >= _MIN_NEIGHBOURS
        pred = np.where(trusted, pred, 0.0)
        # what the neighbouring blades of the same revolution share beyond their own trend:
        # the rotor-angle model's error between OPR pulses (a speed change), common to
        # arrivals close in time
        r_cell = dev_cell[_REACH:_REACH + nw] - pred
        side = np.stack([np.roll(r_cell, k, axis=1) for k in range(-_REACH, _REACH + 1) if k])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            common = np.nanmedian(side, axis=0)
        pred = pred + np.where(trusted & np.isfinite(common), common, 0.0)
        resid = np.abs(dev[ci] - pred[m[ci] - r0, blade[ci]])
        keep = ci[_first_per_cell(key, resid)]
        r_keep = np.abs(dev[keep] - pred[m[keep] - r0, blade[keep]])
        tr = trusted[m[keep] - r0, blade[keep]]
        if scale is None:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                sc = 1.4826 * np.array([np.median(r_keep[tr & (blade[keep] == b)])
                                        if np.any(tr & (blade[keep] == b)) else np.nan for b in range(nb)])
        else:
            sc = scale[rnd]
        scales.append(sc)
        limit = np.fmax(outlier * sc, floor * pitch)
        kept = keep[~tr | (r_keep <= limit[blade[keep]])]
    return kept, np.array(scales)


def identification_params(opr_s: np.ndarray, pulse_s: np.ndarray, arrival_angles_rad: np.ndarray, *,
                          calibrate: bool = True, tolerance: float = 0.25, outlier: float = 20.0,
                          floor: float = 0.02, encoder: EncoderRevolutions | None = None,
                          phase: RotorPhase | None = None) -> IdentifyParams:
    """Arrival angles (step 2) and robust scales (step 4) of one probe, from its pulses of the
    calibration span (:func:`calibration_end`): the steps of :func:`identify_pulses` on
    ``opr_s[:k]`` and those pulses alone.

    Parameters
    ----------
    opr_s : ndarray, shape (n_rev,)
        All the OPR times, s.
    pulse_s : ndarray
        The probe's pulses, sorted, s: at least those of the calibration span; others are
        ignored.
    arrival_angles_rad, calibrate, tolerance, outlier, floor, encoder
        As :func:`identify_pulses`.
    phase : RotorPhase, optional
        ``rotor_phase_from_opr(opr_s)``, when already computed.
    """
    opr = np.asarray(opr_s, dtype=float)
    t = np.asarray(pulse_s, dtype=float).ravel()
    psi = np.mod(np.asarray(arrival_angles_rad, dtype=float).ravel(), TWO_PI)
    nb = psi.size
    pitch = TWO_PI / nb
    if t.size:
        k, end = calibration_end(opr, float(t[0]))
        t = t[np.searchsorted(t, opr[0], side="left"):np.searchsorted(t, end)]
        if k < opr.size:
            opr, phase, encoder = opr[:k], None, _encoder_until(encoder, opr[k - 1])
    nr = opr.size
    phase = rotor_phase_from_opr(opr) if phase is None else phase
    n, total, blade, dev = _labels(opr, t, psi, encoder, phase)
    after = n >= 0
    if calibrate and after.any():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            shift = np.array([np.median(dev[after & (blade == b)]) if np.any(after & (blade == b)) else 0.0
                              for b in range(nb)])
        psi = np.mod(psi + np.where(np.abs(shift) < 0.5 * pitch, shift, 0.0), TWO_PI)
        blade, dev = _nearest(total, psi)
    m = np.round((total - dev - psi[blade]) / TWO_PI).astype(np.int64)
    ci = np.flatnonzero(after & (m >= 0) & (m < nr) & (np.abs(dev) <= tolerance * pitch))
    _, scale = _select(m, blade, dev, ci, 0, nr, nb, pitch, outlier, floor, None)
    return IdentifyParams(arrival_angles_rad=psi, scale_rad=scale, tolerance=tolerance, outlier=outlier,
                          floor=floor)


def _encoder_until(encoder: EncoderRevolutions | None, end_s: float) -> EncoderRevolutions | None:
    if encoder is None:
        return None
    k = int(np.searchsorted(encoder.pulse_s, end_s, side="right"))
    return EncoderRevolutions(opr_s=encoder.opr_s[encoder.opr_s <= end_s], pulse_s=encoder.pulse_s[:k],
                              angle_rad=encoder.angle_rad[:k], rule=encoder.rule)


def identify_window(opr_s: np.ndarray, pulse_s: np.ndarray, params: IdentifyParams, start: int, stop: int, *,
                    encoder: EncoderRevolutions | None = None, phase: RotorPhase | None = None
                    ) -> IdentifiedPulses:
    """Revolutions ``start:stop`` of one probe's labelling (steps 1-5 with ``params``).

    Parameters
    ----------
    opr_s : ndarray, shape (n_rev,)
        All the OPR times, s.
    pulse_s : ndarray
        The probe's pulses, sorted, s: those of OPR intervals
        :func:`window_revolutions(start, stop, n_rev) <window_revolutions>` (more do no harm).
    params : IdentifyParams
    start, stop : int
        Revolutions to label, ``0 <= start < stop <= n_rev``.
    encoder : EncoderRevolutions, optional
    phase : RotorPhase, optional
        ``rotor_phase_from_opr(opr_s)``, when already computed.

    Returns
    -------
    IdentifiedPulses
        ``toa_s`` of shape ``(stop - start, n_blades)``; the extra pulses of those
        revolutions; the stray and outside pulses of OPR intervals ``start:stop`` (with the
        pulses given before the first OPR pulse when ``start == 0``). Windows that tile
        ``0:n_rev`` give, joined, exactly what one window ``0:n_rev`` gives. The pulses
        before ``opr_s[0]`` and after :func:`last_pulse_s` can only be outside: a caller
        may count them instead of passing them.
    """
    opr = np.asarray(opr_s, dtype=float)
    t = np.asarray(pulse_s, dtype=float).ravel()
    psi = params.arrival_angles_rad
    nr, nb = opr.size, psi.size
    pitch = TWO_PI / nb
    phase = rotor_phase_from_opr(opr) if phase is None else phase
    n, total, blade, dev = _labels(opr, t, psi, encoder, phase)
    before = n < 0
    m = np.round((total - dev - psi[blade]) / TWO_PI).astype(np.int64)
    outside = ~before & ((m < 0) | (m >= nr))
    stray = ~before & ~outside & (np.abs(dev) > params.tolerance * pitch)
    cell = ~before & ~outside & ~stray
    r0 = max(start - HALO_REVOLUTIONS - 1, 0)
    r1 = min(stop + HALO_REVOLUTIONS + 1, nr)
    ci = np.flatnonzero(cell & (m >= r0) & (m < r1))
    kept, _ = _select(m, blade, dev, ci, r0, r1, nb, pitch, params.outlier, params.floor, params.scale_rad)
    mine = (m[kept] >= start) & (m[kept] < stop)
    kept = kept[mine]
    toa = np.full((stop - start, nb), np.nan)
    toa[m[kept] - start, blade[kept]] = t[kept]
    is_kept = np.zeros(t.size, bool)
    is_kept[kept] = True
    ex = np.flatnonzero(cell & ~is_kept & (m >= start) & (m < stop))
    owner = np.clip(n, 0, nr - 1)
    own = (owner >= start) & (owner < stop)
    st = np.flatnonzero(stray & own)
    return IdentifiedPulses(
        toa_s=toa, extra_revolution=m[ex], extra_blade=blade[ex].astype(np.int64), extra_toa_s=t[ex],
        stray_revolution=owner[st].astype(np.int64), stray_toa_s=t[st],
        outside=int(np.count_nonzero((before | outside) & own)), arrival_angles_rad=psi)


def identify_pulses(opr_s: np.ndarray, pulse_s: np.ndarray, arrival_angles_rad: np.ndarray, *,
                    calibrate: bool = True, tolerance: float = 0.25, outlier: float = 20.0,
                    floor: float = 0.02, encoder: EncoderRevolutions | None = None) -> IdentifiedPulses:
    """Assign one probe's unlabelled pulse times to revolutions and blades.

    :func:`identification_params` on the calibration span, then :func:`identify_window` on
    every revolution; ``bttsim ingest`` runs the same two steps over windows of revolutions,
    with the same result.

    Parameters
    ----------
    opr_s : ndarray, shape (n_rev,)
        OPR times, s, strictly increasing, ``n_rev >= 3``.
    pulse_s : ndarray, shape (n_pulses,)
        Pulse times at the probe, s, finite (any order).
    arrival_angles_rad : ndarray, shape (n_blades,)
        Rotor angle after the OPR pulse at which each blade reaches this probe, rad
        (``Geometry.nominal_arrival_angles()[:, j]``).
    calibrate : bool
        Re-centre the arrival angles on the data (the sensing point's angle on the blade
        unknown); False when they are exact (the simulator's sensing angles).
    tolerance : float
        Largest distance of a pulse from its blade's angle, in blade pitches ``2 pi / N_b``;
        further: stray.
    outlier : float
        A cell's pulse further than ``outlier`` robust scales (1.4826 MAD, per blade, of the
        kept pulses' distance from their neighbours' median) from the prediction is extra.
    floor : float
        ... but never for a distance below ``floor`` blade pitches.
    encoder : EncoderRevolutions, optional
        The shaft encoder whose pulses 0 are ``opr_s``: the rotor angle from its pulses
        (:func:`shaft_angle`).

    Returns
    -------
    IdentifiedPulses
    """
    opr = np.asarray(opr_s, dtype=float)
    t = np.sort(np.asarray(pulse_s, dtype=float).ravel())
    phase = rotor_phase_from_opr(opr)
    params = identification_params(opr, t, arrival_angles_rad, calibrate=calibrate, tolerance=tolerance,
                                   outlier=outlier, floor=floor, encoder=encoder, phase=phase)
    return identify_window(opr, t, params, 0, opr.size, encoder=encoder, phase=phase)

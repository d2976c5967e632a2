"""Steady-state results of dwells: per engine order the mean complex response over the dwell
and its 95 % intervals (``docs/processing.md``, "Steady state (dwells)").

``ctx`` is the pipeline's processing context (geometry, orders, fits, speeds, zeroing
reference, truth, options).
"""

from __future__ import annotations

import math

import numpy as np

from .detect import Crossing
from .displacement import TWO_PI
from .fit import quiet
from .intervals import MODEL_ERROR, TERM_NOTE_PCT, dwell_intervals, dwell_misfit, layout_gain
from .resonance import Detection, ResonanceEntry, ResonancePeaks, window_truth
from .travelling_wave import fit_spectra, identify_nd
from .zeroing import correction_size, zeroing_correction

__all__ = ["dwell_entries", "DWELL_BLOCK", "RowSums", "NanMean"]

#: Revolutions of a dwell read at a time: a dwell's means go over every revolution of it
#: (at constant speed a test may dwell for hours), summed block by block.
DWELL_BLOCK = 1 << 12


class RowSums:
    """``x.sum(axis=0)`` of an array given by blocks of rows (:meth:`add`, in row order): the
    same numbers. Along axis 0 numpy adds the rows one after the other, and so do the blocks,
    each onto the sums so far -- except for a single column, which numpy sums pairwise: give
    that one whole."""

    __slots__ = ("total",)

    def __init__(self) -> None:
        self.total = None

    def add(self, x: np.ndarray) -> None:
        self.total = x.sum(axis=0) if self.total is None else np.concatenate([self.total[None], x]).sum(axis=0)


class NanMean:
    """``np.nanmean(x, axis=0)`` of an array given by blocks of rows (:class:`RowSums`): the
    sum with NaN taken as 0 over the count of the others, divided as numpy divides them (the
    count cast to the sum's type): the same numbers."""

    __slots__ = ("tot", "cnt")

    def __init__(self) -> None:
        self.tot, self.cnt = RowSums(), RowSums()

    def add(self, x: np.ndarray) -> None:
        self.tot.add(_nan_zero(x))
        self.cnt.add(~np.isnan(x))

    def mean(self) -> np.ndarray:
        return np.divide(self.tot.total, self.cnt.total.astype(np.intp), out=self.tot.total, casting="unsafe")


def dwell_entries(ctx, dw) -> list[ResonanceEntry]:
    """Steady-state results of one dwell, one entry per engine order: the mean of the
    complex responses over the dwell (its first ``settle`` revolutions skipped)."""
    n = dw.stop - dw.start
    rate = float(np.mean(ctx.omega[dw.start:dw.stop])) / TWO_PI
    skip = min(max(int(math.ceil(0.5 * rate)), n // 10), n // 2)
    a, b = dw.start + skip, dw.stop  # revolutions [a, b)
    out = []
    opts = ctx.options
    n, n_eo = b - a, len(ctx.eos)
    # by blocks of revolutions (one blade: its column is summed pairwise by numpy, read at once)
    block = DWELL_BLOCK if ctx.d_flat[a:a + 1].shape[1] > 1 else max(n, 1)
    d_sum, p_sum = NanMean(), [NanMean() for _ in range(n_eo)]
    r_sum, r_cnt = [NanMean() for _ in range(n_eo)], [RowSums() for _ in range(n_eo)]
    with quiet():
        for lo in range(a, b, block):
            hi = min(lo + block, b)
            d_sum.add(ctx.d_flat[lo:hi])
            P, R = _dwell_phasors(ctx, lo, hi)
            for i in range(n_eo):
                p_sum[i].add(P[i])
                r_sum[i].add(R[i])
                r_cnt[i].add(np.isfinite(R[i]))
        d_mean = d_sum.mean()  # (blades, probes): the steady response at each probe
        r_mean = [m.mean() for m in r_sum]
        r_var = [RowSums() for _ in range(n_eo)]
        for lo in range(a, b, block):  # the scatter about the unsmoothed mean: a second pass
            R = _dwell_phasors(ctx, lo, min(lo + block, b), fits=False)[1]
            for i in range(n_eo):
                r_var[i].add(_nan_zero(np.abs(R[i] - r_mean[i]) ** 2))
    radius = ctx.geometry.tip_radius_m if opts.sampling_angles else None
    for i, eo in enumerate(ctx.eos):
        corr, source = _dwell_correction(ctx, eo, i)
        cnt = r_cnt[i].total
        with quiet():
            mean = p_sum[i].mean() + (corr if corr is not None else 0.0)
            spread = np.sqrt(r_var[i].total / np.maximum(cnt - 1, 1))
        amp = 2.0 * np.abs(mean)
        std = 2.0 * spread / np.sqrt(np.maximum(cnt, 1))
        f = eo * float(np.mean(ctx.omega[a:b])) / TWO_PI
        nb = amp.size
        with quiet():
            snr = float(np.nanmean(amp) / max(np.nanmean(std), 1e-300)) if np.isfinite(amp).any() else 0.0
        eos_fit = ctx.eos if ctx.joint else (eo,)
        k = eos_fit.index(eo)
        probes_m, dof = dwell_misfit(d_mean, ctx.geometry.probe_angles_rad, eos_fit, k, radius)
        layout_m = layout_gain(ctx.geometry.probe_angles_rad, eos_fit, k, mean) * MODEL_ERROR * amp
        peaks = dwell_intervals(ResonancePeaks(
            revolution=np.full(nb, float(a)), amp_pkpk_m=amp, freq_hz=np.full(nb, f),
            damping_ratio=np.full(nb, np.nan), method="mean", phase_rad=np.angle(mean),
            amp_std_m=std, freq_std_hz=np.full(nb, float(np.std(ctx.omega[a:b])) * eo / TWO_PI)),
            layout_m, probes_m, dof, _dwell_zeroing_bound(ctx, corr))
        nd = identify_nd(fit_spectra(mean, eo, ctx.geometry.blade_angles_rad))
        r0 = ctx.revolution0
        entry = ResonanceEntry(
            kind="dwell", eo=eo, nd=nd, cn=ctx.cns.get(eo, ctx.fit.cn), method="mean",
            rpm=float(np.mean(ctx.omega[a:b])) * 60.0 / TWO_PI, freq_hz=f, damping_ratio=math.nan,
            detection=Detection("amplitude_snr", min(snr, 1e9), opts.detect.dwell_snr_threshold, min(snr, 1e9),
                                opts.detect.dwell_snr_threshold),
            first_revolution=r0 + a, last_revolution=r0 + b - 1, peak_revolution=-1, peaks=peaks,
            notes=_dwell_notes(ctx, eo, amp, probes_m, dof, corr, source),
            zeroing_correction=correction_size(corr, mean[None, :]))
        out.append(entry.with_truth(window_truth(ctx.truth, eo, a, b - 1, mean=True)))
    return out


def _dwell_phasors(ctx, lo: int, hi: int, fits: bool = True) -> tuple:
    """Each order's complex responses of revolutions ``lo .. hi - 1``: the report's fits'
    (``fits``, else None) and the unsmoothed fits', lists by order; fitted now where the
    report does not hold the dwell's fits (``ctx.dwell_fits``: the same numbers)."""
    n_eo = len(ctx.eos)
    if ctx.dwell_fits is not None:
        P, R = ctx.dwell_fits(lo, hi, fits)
        return ([P[..., i] for i in range(n_eo)] if fits else None), [R[..., i] for i in range(n_eo)]
    P = [ctx.fit.phasor_at(i, slice(lo, hi)) for i in range(n_eo)] if fits else None
    return P, [ctx.raw.phasor[lo:hi, :, i] for i in range(n_eo)]


def _nan_zero(x: np.ndarray) -> np.ndarray:
    """``x`` with NaN as 0 (what ``np.nansum`` adds)."""
    return np.where(np.isnan(x), 0, x).astype(x.dtype, copy=False)


def _dwell_correction(ctx, eo: int, i: int) -> tuple[np.ndarray | None, Crossing | None]:
    """The response the zeroing reference held at a dwell's order, per blade (complex, m),
    and the crossing it was estimated from; ``(None, None)`` without a crossing of that order
    to estimate it from.

    The reference subtracted the response it held, ``P_ref``, from every revolution: a
    dwell's response is off by it as a crossing's is (:func:`~.zeroing.zeroing_correction`), and more
    so relative to its size off resonance. ``P_ref = K h_ref`` is estimated from the crossing
    of the same order nearest the reference, and added back. Far from the crossing the
    growth law ``h`` (one mode) is rough, so the interval spans the uncorrected value too
    (``2 |P_ref|`` pk-pk, as a crossing's when its check fails)."""
    ref = ctx.reference
    same = [c for c in ctx.crossings if c.eo == eo]
    if not same or ref is None or ref.start is None:
        return None, None
    c = min(same, key=lambda k: abs(k.peak - ref.start))
    corr = zeroing_correction(ctx, c, i)
    return (corr, c) if corr is not None else (None, None)


def _zeroing_kind(ctx) -> str:
    """How the run was zeroed: ``"exact"`` (the truth's expected times), ``"nominal"`` (the
    nominal geometry: nothing subtracted), ``"reference"`` (calibrated on the chosen
    reference window) or ``"window"`` (calibrated on a window given in the options)."""
    opts = ctx.options
    if opts.expected_times == "exact":
        return "exact"
    ref = ctx.reference
    if ref is not None and ref.start is not None:
        return "reference"
    cal = opts.calibration
    if cal is None or cal is False or isinstance(cal, str) or (isinstance(cal, (int, np.integer)) and int(cal) == 0):
        return "nominal"  # off, or "auto" that found no ramp to zero on
    return "window"


def _dwell_zeroing_bound(ctx, corr) -> np.ndarray | float:
    """A dwell's zeroing bias bound, pk-pk (m): ``2 |P_ref|`` with a correction, 0 when nothing
    was subtracted (nominal geometry or exact times), NaN when what the calibration window
    held is unknown (no crossing of the order to estimate it from, a window given in the
    options, or a baseline that took it with the slowly varying part of the dwell's own
    response): no interval then."""
    if corr is not None:
        return 2.0 * np.abs(corr)
    return 0.0 if _zeroing_kind(ctx) in ("nominal", "exact") else math.nan


def _dwell_notes(ctx, eo: int, amp: np.ndarray, probes_m: np.ndarray, dof: int, corr, source) -> tuple:
    """What limits a dwell's estimate: the zeroing reference's response (added back, or
    unknown), the probes' systematic misfit (:func:`~.intervals.dwell_misfit`) where it is
    above :data:`~.intervals.TERM_NOTE_PCT` of the amplitude, or that it cannot be seen."""
    ref = ctx.reference
    kind = _zeroing_kind(ctx)
    nominal = kind == "nominal"
    notes = []
    with quiet():
        if corr is not None:
            pct = float(np.nanmedian(100.0 * 2.0 * np.abs(corr) / amp))
            notes.append(f"zeroing: the reference held a response at EO {eo} of {pct:.2g} % of the dwell's amplitude "
                         f"(blade median), estimated from the crossing at revolution {ctx.revolution0 + source.peak} "
                         f"and added back; the "
                         f"interval spans the uncorrected value too")
        elif kind == "window":
            notes.append(f"zeroing: the response the calibration window given in the options held at EO {eo} is "
                         f"unknown: the dwell's amplitude is relative to it, and no interval is given")
        elif kind == "reference":
            r0 = ctx.revolution0
            why = "; ".join(w for w, on in (
                (f"no crossing of EO {eo} to estimate it from", not any(c.eo == eo for c in ctx.crossings)),
                ("the baseline removed with the offsets took it, with the part of the dwell's own response that "
                 "varies slowly with speed", ctx.offset_removed)) if on) or "the crossing's skirt is too short to tell"
            notes.append(f"zeroing: the response the reference (revolutions {r0 + ref.start}-{r0 + ref.stop - 1}) "
                         f"held at EO {eo} is unknown ({why}): the dwell's amplitude is relative to it, and no "
                         f"interval is given")
        why = " (a dwell alone cannot be calibrated: nominal geometry)" if nominal else ""
        if dof <= 0:
            notes.append(f"no redundant probe: the probes' position errors{why} cannot be seen in the fits; the "
                         f"interval holds the noise and the layout's share only")
        elif (pct := float(np.nanmedian(100.0 * probes_m / amp))) > TERM_NOTE_PCT:
            notes.append(f"probe positions{why}: the fits' misfit common to every blade is {pct:.2g} % of the "
                         f"amplitude (blade median, {dof} degree(s) of freedom); the interval includes it")
    return tuple(notes)

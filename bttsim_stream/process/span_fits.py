"""The report's Eq. 16 fits (:mod:`.fit`) of every order, by spans and blocks of revolutions.

The pipeline fits each revolution at the probe angles and, inside the crossings and dwells,
at the sampling angles (:func:`fit_spans`). One revolution per fit, every fit is its own
revolution's: blocks of revolutions (:func:`chunk_fits`) give the whole run's numbers, and
the report alone holds them only on the revolutions it reads (:func:`read_spans`,
:func:`held_fit`, :class:`~.spans.SpanRows`), with what it reads of the rest of the run
computed by blocks (:func:`run_amplitudes`).
"""

from __future__ import annotations

import numpy as np

from . import fit as fitting
from .displacement import TWO_PI
from .fit import SineFit, fit_revolutions
from .intervals import blade_medians
from .spans import SpanRows
from .zeroing import tail_revolutions

__all__ = ["fit_orders", "merge_spans", "fit_spans", "held_fit", "read_spans", "blade_mean", "run_amplitudes",
           "chunk_fits", "fit_rows", "order_phasors", "span_phasors", "overlap_spans"]


def fit_orders(d: np.ndarray, angles, eos: tuple, joint: bool, omega, window: int,
               radius: float | None = None) -> SineFit:
    """Eq. 16 fits of every order, jointly or one order at a time (stacked as one SineFit);
    ``radius``: at the sampling angles (:func:`~bttsim_stream.process.fit.fit_revolutions`)."""
    if joint or len(eos) == 1:
        return fit_revolutions(d, angles, eos, omega_rad_s=omega, window=window, tip_radius_m=radius)
    fits = [fit_revolutions(d, angles, (eo,), omega_rad_s=omega, window=window, tip_radius_m=radius) for eo in eos]
    coeffs = np.concatenate([fits[0].coeffs[..., :1]] + [f.coeffs[..., 1:] for f in fits], axis=-1)
    cat = lambda name: np.concatenate([getattr(f, name) for f in fits], axis=-1)  # noqa: E731
    return SineFit(engine_orders=tuple(eos), window=window, coeffs=coeffs, amp_pkpk_m=cat("amp_pkpk_m"),
                   phase_rad=cat("phase_rad"), amp_std_m=cat("amp_std_m"), dc_m=fits[0].dc_m,
                   residual_rms_m=fits[0].residual_rms_m, n_samples=fits[0].n_samples,
                   omega_rad_s=fits[0].omega_rad_s, freq_hz=None if fits[0].freq_hz is None else cat("freq_hz"),
                   cn=max(f.cn for f in fits))


def merge_spans(spans) -> list:
    """Sorted, non-overlapping ``[start, stop)`` revolution spans."""
    out: list = []
    for a, b in sorted(spans):
        if out and a <= out[-1][1]:
            out[-1] = (out[-1][0], max(out[-1][1], b))
        else:
            out.append((a, b))
    return out


def overlap_spans(a: list, b: list) -> list:
    """The revolutions in both of two lists of sorted, non-overlapping ``[start, stop)`` spans."""
    out = []
    for s0, e0 in a:
        out += [(max(s0, s1), min(e0, e1)) for s1, e1 in b if s1 < e0 and e1 > s0]
    return merge_spans(out)


def fit_spans(d: np.ndarray, angles, eos: tuple, joint: bool, omega, window: int, radius, spans) -> SineFit:
    """Fits at the probe angles everywhere and, inside ``spans`` (the crossings and dwells,
    where results are read), at the sampling angles. Outside them the response is small, and
    the two agree (the correction is proportional to the displacement)."""
    fit = fit_orders(d, angles, eos, joint, omega, window, None)
    if radius is None or not spans:
        return fit
    # written in place: the fit's arrays are this function's own (no second copy of the run's fits)
    arrays = {k: getattr(fit, k) for k in ("coeffs", "amp_pkpk_m", "phase_rad", "amp_std_m", "dc_m",
                                           "residual_rms_m", "n_samples") if getattr(fit, k) is not None}
    h = window // 2
    n = d.shape[0]
    for a, b in spans:
        if window == 1:
            for lo, hi, f in chunk_fits(d, a, b, angles, eos, joint, omega, radius):
                for k, arr in arrays.items():
                    arr[lo:hi] = getattr(f, k)
            continue
        lo, hi = max(0, a - h), min(n, b + h)
        f = fit_orders(d[lo:hi], angles, eos, joint, omega[lo:hi], window, radius)
        for k, arr in arrays.items():
            arr[a:b] = getattr(f, k)[a - lo:b - lo]
    return fit


def span_phasors(d, d_flat, angles, eos: tuple, joint: bool, omega, radius, spans: list, a: int, b: int,
                 fits: bool = True) -> tuple:
    """``(phasor, raw)``: the complex responses, shape ``(b - a, n_blades, n_eo)``, of
    revolutions ``a .. b - 1`` in the report's fits (``fits``, else None) and in its
    unsmoothed fits (of the offset-removed displacements ``d_flat``; None: the report's fits
    are the unsmoothed ones), fitted now (:func:`fit_rows`: the numbers :func:`held_fit` and
    the unsmoothed fits hold)."""
    def fitted(src) -> np.ndarray:
        ph = np.empty((b - a, d.shape[1], len(eos)), complex)
        for lo, hi, f in fit_rows(src, a, b, angles, eos, joint, omega, radius, spans):
            ph[lo - a:hi - a] = f.phasor
        return ph

    phasor = fitted(d) if fits or d_flat is None else None
    return (phasor if fits else None), (phasor if d_flat is None else fitted(d_flat))


def order_phasors(d, angles, eos: tuple, joint: bool, omega, radius, spans: list, i: int,
                  revs: np.ndarray) -> np.ndarray:
    """Order ``i``'s complex responses ``phasor[revs, :, i]`` of the report's fits (those of
    :func:`held_fit` and :func:`fit_spans`: the same numbers), fitted for the revolutions
    ``revs`` (sorted) now rather than held: by runs of consecutive revolutions, by blocks."""
    revs = np.asarray(revs, dtype=np.intp)
    out = np.empty((revs.size, d.shape[1]), complex)
    if not revs.size:
        return out
    runs = np.split(revs, np.flatnonzero(np.diff(revs) != 1) + 1)
    at = 0
    for run in runs:
        a = int(run[0])
        for lo, hi, f in fit_rows(d, a, int(run[-1]) + 1, angles, eos, joint, omega, radius, spans):
            out[at + lo - a:at + hi - a] = f.coeffs[:, :, 1 + 2 * i] + 1j * f.coeffs[:, :, 2 + 2 * i]
        at += run.size
    return out


def held_fit(d, angles, eos: tuple, joint: bool, omega, radius, spans: list, held: list) -> SineFit:
    """:func:`fit_spans` with one revolution per fit, its coefficients, amplitudes and phases
    held on the revolutions ``held`` only (:class:`~.spans.SpanRows`: the same numbers there,
    NaN elsewhere; ``spans`` inside them), the fit's other arrays None: no run-sized fit."""
    n_rev, nb = d.shape[:2]
    n_eo = len(eos)
    coeffs = SpanRows.filled(n_rev, held, (nb, 1 + 2 * n_eo))
    amp, phase = coeffs.like((nb, n_eo)), coeffs.like((nb, n_eo))
    for a, b in held:  # inside the spans at the sampling angles (radius), the rest at the probe angles
        for lo, hi, f in fit_rows(d, a, b, angles, eos, joint, omega, radius, spans):
            coeffs[lo:hi], amp[lo:hi], phase[lo:hi] = f.coeffs, f.amp_pkpk_m, f.phase_rad
    om = np.asarray(omega, dtype=float)
    return SineFit(engine_orders=tuple(eos), window=1, coeffs=coeffs, amp_pkpk_m=amp, phase_rad=phase, amp_std_m=None,
                   dc_m=coeffs[..., 0], residual_rms_m=None, n_samples=None, omega_rad_s=om,
                   freq_hz=om[:, None] * np.asarray(eos, float)[None, :] / TWO_PI,
                   cn=fit_orders(d[:1], angles, eos, joint, om[:1], 1, None).cn)


def read_spans(crossings: list, omega: np.ndarray, spans: list, reference, offset_removed: bool, n_rev: int,
               *, tails: bool = True) -> list:
    """The revolutions whose fits the report reads (merged ``[start, stop)`` spans): the
    crossings and dwells (``spans``), each crossing widened by what its peak's parabolas read
    (``W`` its half-power width: :func:`~.methods.peak_method`'s around the pick, at most
    ``max(2, W / 4)``, the SDOF peak up to one revolution past ``hi``, then
    :func:`~.intervals.crossing_intervals`' parabola and sampling, ``max(2, W // 6)``), and
    (``tails``) the skirt its zeroing correction fits (:func:`~.zeroing.tail_revolutions`)."""
    out = list(spans)
    for c in crossings:
        w = int(c.half_power_width)
        m = max(2, int(round(max(w, 1) / 4.0))) + max(2, w // 6) + 2
        out.append((max(0, c.lo - m), min(n_rev, c.hi + 1 + m)))
        tail = tail_revolutions(reference, offset_removed, crossings, omega, c) if tails else None
        if tail is not None:
            idx = tail[2]
            out += [(int(r[0]), int(r[-1]) + 1) for r in np.split(idx, np.flatnonzero(np.diff(idx) != 1) + 1)]
    return merge_spans(out)


def blade_mean(amp: np.ndarray) -> np.ndarray:
    """Each revolution's blade mean of ``amp`` (n_rev, n_blades), NaN skipped (0 without any)."""
    ok = np.isfinite(amp)
    return np.where(ok, amp, 0.0).sum(axis=1) / np.maximum(ok.sum(axis=1), 1)


def run_amplitudes(d, crossings: list, eos: tuple, joint: bool, angles, omega, radius, spans) -> dict:
    """With the fits held on some revolutions (:func:`held_fit`): what the report reads of the
    whole run's amplitudes, by blocks of revolutions (each revolution's own: the same numbers;
    :func:`fit_rows`, at the sampling angles inside ``spans``)
    -- without a crossing, the blade medians (:func:`~.intervals.no_crossing_note`); without one
    of the first order, its blade means (:func:`blade_mean`, the resonance revolutions' fallback)."""
    medians, means = not any(c.eo in eos for c in crossings), not any(c.eo == eos[0] for c in crossings)
    if not (medians or means):
        return {}
    n = d.shape[0]
    med, mean = np.empty((n, len(eos))) if medians else None, np.empty(n) if means else None
    for lo, hi, f in fit_rows(d, 0, n, angles, eos, joint, omega, radius, spans):  # the report's fits
        amp = f.amp_pkpk_m
        if medians:
            med[lo:hi] = blade_medians(amp)
        if means:
            mean[lo:hi] = blade_mean(amp[..., 0])
    return {"median_m": med, "mean_m": mean}


def chunk_fits(d, a: int, b: int, angles, eos: tuple, joint: bool, omega, radius):
    """``(lo, hi, fit)``: the one-revolution fits of revolutions ``a .. b - 1``,
    :data:`~.fit.FIT_CHUNK` at a time from ``a``, as :func:`fit_orders` of them all makes them (the
    same numbers), without a fit of the whole span at once. ``d``: an array or a
    row source (e.g. the pipeline's offset-removed displacements, computed for the rows asked
    for)."""
    for lo in range(a, b, fitting.FIT_CHUNK):
        hi = min(lo + fitting.FIT_CHUNK, b)
        yield lo, hi, fit_orders(d[lo:hi], angles, eos, joint, omega[lo:hi], 1, radius)


def fit_rows(d, a: int, b: int, angles, eos: tuple, joint: bool, omega, radius, spans):
    """``(lo, hi, fit)``: the one-revolution fits of revolutions ``a .. b - 1`` as
    :func:`fit_spans` makes them (the same numbers), in revolution order: at the sampling
    angles (``radius``) inside ``spans`` (sorted, non-overlapping ``[start, stop)``), at the
    probe angles elsewhere, :func:`chunk_fits` of each stretch."""
    inside = [(max(s, a), min(e, b)) for s, e in (spans if radius is not None else []) if s < b and e > a]
    edges = sorted({a, b}.union(*inside))
    for lo, hi in zip(edges[:-1], edges[1:]):
        r = radius if any(s <= lo and hi <= e for s, e in inside) else None
        yield from chunk_fits(d, lo, hi, angles, eos, joint, omega, r)

"""Resonance amplitude, frequency and phase of each blade through one crossing: three methods.

All three work on the Eq. 16 fits of one engine order inside a crossing's window
(revolutions ``lo .. hi`` found by :mod:`.detect`) and give, per blade, the resonant
amplitude (pk-pk, m), frequency (Hz, Eq. 17), phase (rad) and their standard uncertainties
(:class:`~bttsim_stream.process.resonance.ResonancePeaks`):

``"peak"`` -- the resonance of the per-revolution fits (Sec. 2.3). By default
    (``peak_method="fit"``) the vertex of a least-squares parabola through the *unsmoothed*
    (offset-removed, zeroing-corrected) amplitudes over ``+- h`` revolutions around the
    largest *prepared* (smoothed) amplitude (:func:`quadratic_peak`): the largest of noisy
    values is biased upwards by about the noise (and scatters with it); the fit averages
    ``2 h + 1`` revolutions instead. ``h`` (2 to ``W / 4``, :func:`fit_half_width`) balances
    the parabola's shape bias on a resonance top, ``-0.514 (h / W)^4`` of the amplitude,
    against its noise. Its frequency is interpolated at the vertex (below one revolution).
    Uncertainty: the revolution-to-revolution scatter of the unsmoothed amplitudes (robust
    second differences) times the fit's noise gain at the vertex; the vertex's for the
    frequency. On a slow crossing (half-power band over at least
    :data:`QUASI_STEADY_REVOLUTIONS` revolutions) the amplitude is instead the peak of the
    resonance's quasi-steady shape fitted to the unsmoothed complex responses over the
    half-power width either side of the vertex (:func:`resonance_fit`: ``C h(f_r) + c``,
    the SDOF frequency response and the zeroing's constant; its uncertainty from the fit's
    Jacobian): it uses the whole resonance and the phase, takes about half the bias a static
    probe position error gives the top's magnitudes, and reaches 1.4-1.8 times the Cramér-Rao
    bound where the parabola's vertex was 2.3-3.3 times; the frequency, revolution and phase
    stay the vertex's (the swept peak's: the quasi-steady fit's would carry the sweep's
    delay). ``peak_method="max"`` is the paper's literal definition, the largest
    amplitude of the prepared data (its uncertainty: the scatter times the smoother's
    noise gain ``||L||``; frequency: a uniform half-revolution, ``|Delta f| / sqrt(12)``).
``"cff"`` -- circumferential Fourier fit: Eq. 16 fitted to a centred window of ``w``
    consecutive revolutions at once (constant coefficients, ``w N_p`` samples; the multi-
    revolution form of the fit, e.g. the Bladesight tutorial's CFF) on the offset-removed,
    *unsmoothed* data, ``w`` odd, about a twelfth of the half-power width. The peak is the
    vertex of a least-squares parabola through the CFF amplitudes over ``+- h``
    (:func:`quadratic_peak`, :func:`fit_half_width`, as ``peak``), plus the window's own
    flattening of the complex response (a centred mean of ``w`` revolutions adds
    ``P'' (w^2 - 1) / 24`` to it, ``P''`` of a complex parabola through the same revolutions).
    Uncertainty: the least-squares covariance ``s^2 (B^T C B)^-1`` of one revolution times
    the parabola's noise gain. On a slow crossing the amplitude is that of the resonance's
    shape fitted to the CFF responses (:func:`resonance_fit`, as ``peak``; the window's
    flattening added back; its uncertainty times ``sqrt(w)``: the fit's residuals are those
    of a mean of ``w`` revolutions, correlated over ``w``).
``"sdof"`` -- single-degree-of-freedom fit of amplitude *and* phase through the resonance,
    with the sweep in the model. The modal coordinate ``q'' + 2 zeta w_n q' + w_n^2 q =
    exp(i phi(t))``, ``phi = EO x`` rotor angle (the OPR model of :mod:`.displacement`), is
    integrated exactly over the measured speed profile (two first-order poles, a
    linear-phase forcing between grid points ``T / 8`` apart, :mod:`.swept`);
    its envelope ``z = q exp(-i phi)`` at each revolution is fitted to the complex Eq. 16
    responses, ``P_n = C z(t_n) + c`` (``C``, ``c`` complex, solved linearly; ``f_n``,
    ``zeta`` by nonlinear least squares). Because the model is swept like the run, the
    modal parameters carry no sweep-rate bias: this *is* the sweep-rate correction (exact for
    a linear SDOF, instead of an empirical law such as Zhi et al. 2022's). Reported: the
    swept peak ``max |C z|`` (what this run's blade did, comparable with the truth's
    envelope) as ``amp_pkpk_m`` and its frequency; the sweep-corrected steady-state
    resonant amplitude ``|C| / (2 zeta sqrt(1 - zeta^2) w_n^2)`` as ``steady_amp_pkpk_m``;
    ``f_n``, ``zeta``; uncertainties from the Jacobian, ``s^2 (J^T J)^-1``. The constant
    ``c`` absorbs what the zeroing left (a reference window inside the resonance's skirt).

Amplitudes are peak-to-peak (``2 |P|``); the phase is that of ``d_j = a0 + A sin(EO theta_j
+ psi)`` (:mod:`.fit`).
"""

from __future__ import annotations

import math
import warnings

import numpy as np

from .displacement import RotorPhase
from .fit import fit_revolutions
from .resonance import ResonancePeaks
from . import swept
from .spans import as_rows
from .swept import SweptForcing, UniformGrid, sdof_envelope
from .varpro import fit_blades, inverse2, linear_part, pack_rows, projected_jacobian

__all__ = ["METHODS", "QUASI_STEADY_REVOLUTIONS", "SHAPE_MISFIT", "amplitude_noise", "quadratic_peak", "fit_half_width",
           "resonance_fit", "peak_method", "cff_method", "sdof_method", "sdof_envelope"]

TWO_PI = 2.0 * np.pi
METHODS = ("peak", "sdof", "cff")


def amplitude_noise(amp: np.ndarray) -> np.ndarray:
    """Revolution-to-revolution noise of amplitude sequences, robust to the resonance's shape.

    Parameters
    ----------
    amp : ndarray, shape (n_rev, n_blades)

    Returns
    -------
    ndarray, shape (n_blades,)
        ``1.4826 median |Delta^2 a| / sqrt(6)`` (the standard deviation of white noise).
    """
    a = np.asarray(amp, dtype=float)
    if a.shape[0] < 3:
        return np.full(a.shape[1:], np.nan)
    d2 = np.diff(a, 2, axis=0)
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return 1.4826 * np.nanmedian(np.abs(d2), axis=0) / math.sqrt(6.0)


def _freq_step_std(freq_hz: np.ndarray, idx: np.ndarray) -> np.ndarray:
    f = np.asarray(freq_hz, dtype=float)
    step = np.abs(np.gradient(f)) if f.size > 1 else np.zeros_like(f)
    return step[idx] / math.sqrt(12.0)


def fit_half_width(half_power_width: int, amp_pkpk_m=None, noise_m=None) -> int:
    """Half-width ``h`` of the peak's parabola, revolutions: the one of ``2 .. W / 4`` that
    minimises its expected squared error at the blade-median amplitude ``A`` and
    per-revolution noise ``s``: the shape bias of a parabola on a resonance's top,
    ``0.514 (h / W)^4 A`` (the quartic term of ``|H| = (1 + u^2)^(-1/2)``, ``u = 2 x / W``,
    projected on ``1, x^2`` over ``+- h``), squared, plus its noise ``2.25 s^2 / (2 h + 1)``
    (the variance of a parabola's value at the centre). Without ``A`` or ``s``: ``W / 4``."""
    W = max(int(half_power_width), 1)
    top = max(2, int(round(W / 4.0)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        A = float(np.nanmedian(amp_pkpk_m)) if amp_pkpk_m is not None else math.nan
        s = float(np.nanmedian(noise_m)) if noise_m is not None else math.nan
    if not (math.isfinite(A) and math.isfinite(s) and A > 0 and s > 0):
        return top
    h = np.arange(2, top + 1, dtype=float)
    mse = (0.514 * A * (h / W) ** 4) ** 2 + 2.25 * s * s / (2 * h + 1)
    return int(h[int(np.argmin(mse))])


def quadratic_peak(amp: np.ndarray, center: np.ndarray, half: int):
    """Vertex of a least-squares parabola through ``center +- half`` of each blade's sequence.

    Parameters
    ----------
    amp : ndarray, shape (n_rev, n_blades)
        Amplitudes (NaN skipped).
    center : ndarray of int, shape (n_blades,)
        Revolution the window is centred on.
    half : int

    Returns
    -------
    value, revolution : ndarray, shape (n_blades,)
        The vertex (NaN where the parabola is not concave or its vertex lies outside the
        window: no peak to refine).
    value_gain, revolution_gain : ndarray, shape (n_blades,)
        Standard deviations of the vertex's value and revolution per unit white noise of
        one sample (``sqrt(g^T (V^T V)^-1 g)``, ``g`` the gradient at the vertex).
    """
    amp = as_rows(amp)
    n, nb = amp.shape
    c0 = np.asarray(center, dtype=np.int64)
    j = np.arange(-half, half + 1, dtype=float)
    idx = c0[None, :] + j.astype(np.int64)[:, None]
    ok = (idx >= 0) & (idx < n)
    y = amp[np.clip(idx, 0, n - 1), np.arange(nb)[None, :]]
    ok &= np.isfinite(y)
    w = ok.astype(float)
    V = np.stack([np.ones_like(j), j, j * j], axis=1)
    G = np.einsum("jb,jp,jq->bpq", w, V, V)
    bad = np.linalg.matrix_rank(G) < 3
    G[bad] = np.eye(3)
    Gi = np.linalg.inv(G)
    c = np.einsum("bpq,bq->bp", Gi, np.einsum("jb,jp->bp", w * np.where(ok, y, 0.0), V))
    good = ~bad & (c[:, 2] < 0)
    with np.errstate(all="ignore"):
        x = -c[:, 1] / (2.0 * c[:, 2])
        good &= np.abs(x) <= half
        x = np.where(good, x, 0.0)
        val = c[:, 0] + c[:, 1] * x + c[:, 2] * x * x
        gv = np.stack([np.ones(nb), x, x * x], axis=1)  # d value / d c (the vertex is stationary)
        gx = np.stack([np.zeros(nb), -1.0 / (2.0 * c[:, 2]), c[:, 1] / (2.0 * c[:, 2] ** 2)], axis=1)
        sv = np.sqrt(np.einsum("bp,bpq,bq->b", gv, Gi, gv))
        sx = np.sqrt(np.einsum("bp,bpq,bq->b", gx, Gi, gx))
    nan = np.full(nb, np.nan)
    return (np.where(good, val, nan), np.where(good, c0 + x, nan), np.where(good, sv, nan), np.where(good, sx, nan))


#: A crossing whose half-power band takes at least this many revolutions is swept slowly
#: enough for the quasi-steady shape of :func:`resonance_fit` (as the ``fast sweep`` note's
#: threshold); faster crossings keep the parabola.
QUASI_STEADY_REVOLUTIONS = 60
#: The shape is one mode's: a blade whose responses depart from it by more than this fraction
#: of the response's amplitude beyond the noise (rms; mixed modes of a mistuned rotor: 2-6 % at
#: 2 % mistuning; the paper's default run, sweep distortion: 0.33 %) keeps the parabola (the
#: threshold of a model term worth a note, :data:`~.intervals.TERM_NOTE_PCT`).
SHAPE_MISFIT = 0.01


def _steady_model(f: np.ndarray, yn: np.ndarray, w: np.ndarray):
    """The fit's model for :func:`.varpro.fit_blades`: ``h`` at each blade's frequencies and its
    derivatives by ``f_n`` and ``zeta`` (``dh = -h^2 d(den)``)."""

    def model(q, rows):
        fn, zeta = q[:, :1], q[:, 1:]
        r = f[rows] / fn
        h = _h(f[rows], q[:, 0], q[:, 1])
        dz = -(h * h)[..., None] * np.stack([(2.0 * r * r - 2j * zeta * r) / fn, 2j * r], axis=-1)
        lp = linear_part(h, yn[rows], w[rows])
        return lp, projected_jacobian(lp, dz, w[rows]), ()

    return model


def _fit_shape(y: np.ndarray, f: np.ndarray, w: np.ndarray, f0: np.ndarray, zeta0: float):
    """Variable-projection fits of ``y = C h(f) + c``, one per row (a blade's samples ``w``):
    amplitude, peak frequency, phase, amplitude std, frequency std (NaN where a fit fails or
    its misfit beyond the noise exceeds :data:`SHAPE_MISFIT`)."""
    k = y.shape[0]
    got = np.full((5, k), np.nan)
    scale = np.max(np.where(w, np.abs(y), 0.0), axis=1, initial=0.0)
    use = np.flatnonzero((scale > 0) & (w.sum(axis=1) >= 8))
    if use.size == 0:
        return got
    y, f, w, scale, f0 = y[use], f[use], w[use], scale[use], f0[use]
    yn = np.where(w, y, 0) / scale[:, None]
    f = np.where(w, f, 1.0)
    model = _steady_model(f, yn, w)
    ones = np.ones_like(f0)
    res = fit_blades(model, np.stack([f0, zeta0 * ones], axis=1), np.stack([0.9 * f0, 1e-5 * ones], axis=1),
                     np.stack([1.1 * f0, 0.3 * ones], axis=1),
                     np.stack([np.maximum(f0 * zeta0 * 0.1, 1e-3), zeta0 * 0.1 * ones], axis=1))
    q = np.where(res.ok[:, None], res.q, [[1.0, 0.1]])  # a failed row: a finite point, dropped below
    lp = model(q, np.arange(use.size))[0]
    s2 = 2.0 * lp.cost / np.maximum(2 * lp.n - 6, 1)
    cov = s2[:, None, None] * inverse2(res.jtj)
    fn, zeta = q[:, 0], q[:, 1]

    def peak(fn_q, zeta_q):
        C = linear_part(_h(f, fn_q, zeta_q), yn, w).C
        return 2.0 * np.abs(C) * scale / (2.0 * zeta_q * np.sqrt(np.maximum(1.0 - zeta_q * zeta_q, 1e-12)))

    amp = 2.0 * np.abs(lp.C) * scale / (2.0 * zeta * np.sqrt(np.maximum(1.0 - zeta * zeta, 1e-12)))
    grad = np.stack([(peak(fn * (1 + 1e-6), zeta) - amp) / (fn * 1e-6),
                     (peak(fn, zeta * (1 + 1e-4)) - amp) / (zeta * 1e-4)], axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        # |C|'s share (1 / |z_c|^2 is (A^H A)^-1's [0, 0]), then (f_n, zeta)'s
        var = s2 / lp.nz2 * (amp / np.abs(lp.C)) ** 2 + np.einsum("kp,kpq,kq->k", grad, cov, grad)
    fpk = fn * np.sqrt(np.maximum(1.0 - 2.0 * zeta * zeta, 1e-12))
    ph = np.angle(lp.C * _h(fpk[:, None], fn, zeta)[:, 0])
    # misfit beyond the noise, per real component, over the response's amplitude (A / 2): white
    # complex noise of variance s^2 per component has E |Delta^2 e|^2 = 12 s^2, median ln 2 of it
    noise2 = np.array([float(np.median(np.abs(np.diff(yn[j, w[j]], 2)) ** 2)) / (12.0 * math.log(2.0))
                       if lp.n[j] > 2 else 0.0 for j in range(use.size)])
    with np.errstate(invalid="ignore", divide="ignore"):
        beyond = np.sqrt(np.maximum(lp.cost / lp.n - noise2, 0.0)) * scale / (0.5 * amp)
    # a damping ratio held on its bound, or a resonance a millionth of the responses, is no
    # resonance's shape: the bound's, or the noise's
    good = (res.ok & (beyond <= SHAPE_MISFIT) & np.all(np.isfinite(cov), axis=(1, 2)) & (lp.nz2 > 0)
            & np.isfinite(var) & (zeta > 1e-5) & (zeta < 0.3) & (amp > 1e-6 * scale))
    got[:, use[good]] = np.stack([amp, fpk, ph, np.sqrt(np.maximum(var, 0.0)),
                                  np.sqrt(np.maximum(cov[:, 0, 0], 0.0))])[:, good]
    return got


def _h(f: np.ndarray, fn: np.ndarray, zeta: np.ndarray) -> np.ndarray:
    """``h(f) = 1 / (1 - (f / f_n)^2 + 2 i zeta f / f_n)`` of each row's frequencies with its own
    ``(f_n, zeta)`` (:func:`resonance_fit`)."""
    r = f / fn[:, None]
    return 1.0 / (1.0 - r * r + 2j * zeta[:, None] * r)


def resonance_fit(phasor: np.ndarray, freq_hz: np.ndarray, center: np.ndarray, half: int, lo: int, hi: int,
                  zeta0: float):
    """Peak of each blade's resonance from a least-squares fit of its quasi-steady shape to the
    complex responses of ``center +- half`` revolutions (inside ``lo .. hi``).

    Near its resonance a blade's response at ``f_r = EO Omega_r / 2 pi`` (Eq. 17), swept
    slowly, is the single-degree-of-freedom steady state (the model of :mod:`.crb`)

    ``P_r = C h(f_r) + c``,  ``h(f) = 1 / (1 - (f / f_n)^2 + 2 i zeta f / f_n)``,

    ``c`` what the zeroing left (a complex constant). ``C`` and ``c`` are linear (solved
    exactly for every ``(f_n, zeta)``), ``f_n`` and ``zeta`` by nonlinear least squares. The
    peak is ``2 |C| max |h| = |C| / (zeta sqrt(1 - zeta^2))`` at ``f_pk = f_n sqrt(1 - 2
    zeta^2)``. Unlike a parabola through the amplitudes' top, the shape has no bias on the
    top, so the fit uses the whole resonance (``half`` about the half-power width), the
    phase as well as the magnitude, and takes out the zeroing's constant; a static probe
    position error, which turns the responses by a fixed real-linear map ``P -> P + m_1 P +
    m_2 conj(P)``, biases the magnitude at the top by ``|m_2| A cos(2 arg P - arg m_2)``, the
    fitted ``C`` by about half as much (``conj(h)`` turns the other way through the
    resonance: over the half-power width either side, half of it projects on ``h``).

    Parameters
    ----------
    phasor : ndarray of complex, shape (n_rev, n_blades)
    freq_hz : ndarray, shape (n_rev,)
    center : ndarray of int, shape (n_blades,)
    half, lo, hi : int
    zeta0 : float
        Starting damping ratio.

    Returns
    -------
    value, revolution, freq, phase, amp_std, freq_std : ndarray, shape (n_blades,)
        NaN where the fit fails, its peak lies outside the revolutions fitted, or its misfit
        beyond the noise exceeds :data:`SHAPE_MISFIT` of the amplitude (not one mode).
    """
    P = as_rows(phasor, complex)
    f_all = np.asarray(freq_hz, dtype=float)
    n, nb = P.shape
    out = np.full((6, nb), np.nan)
    k = np.clip(np.asarray(center, dtype=np.int64), 0, n - 1)
    a0, a1 = np.maximum(np.maximum(lo, k - int(half)), 0), np.minimum(np.minimum(hi, k + int(half)), n - 1)
    span = int(max(np.max(a1 - a0, initial=-1) + 1, 0))
    if span == 0:
        return tuple(out)
    # each blade's window, its usable samples packed to the left of a row (order kept)
    sel = a0[:, None] + np.arange(span)
    inside = sel <= a1[:, None]
    sel = np.minimum(sel, n - 1)
    y, f = P[sel, np.arange(nb)[:, None]], f_all[sel]
    w, y, f, sel = pack_rows(inside & np.isfinite(y) & np.isfinite(f), y, f, sel)
    got = _fit_shape(y, f, w, f_all[k], float(zeta0))
    for b in np.flatnonzero(np.isfinite(got[0])):
        amp, fpk, ph, s_a, s_f = got[:, b]
        fs, rows = f[b, w[b]], sel[b, w[b]]
        if not (fs.min() < fpk < fs.max()):
            continue
        by_f = np.argsort(fs)
        out[:, b] = amp, np.interp(fpk, fs[by_f], rows[by_f].astype(float)), fpk, ph, s_a, s_f
    return tuple(out)


def _shape_refine(P: np.ndarray, f: np.ndarray, center: np.ndarray, lo: int, hi: int, width: int, zeta0: float):
    """:func:`resonance_fit` over ``+- width`` revolutions of ``center`` for a slow crossing
    (``width >= QUASI_STEADY_REVOLUTIONS``; else nothing): ok, value, revolution, frequency,
    phase, amplitude std, frequency std per blade."""
    nb = P.shape[1]
    if int(width) < QUASI_STEADY_REVOLUTIONS or not math.isfinite(zeta0) or not zeta0 > 0:
        return (np.zeros(nb, bool),) + (np.full(nb, np.nan),) * 6
    val, rev, fr, ph, sv, sf = resonance_fit(P, f, center, int(width), lo, hi, zeta0)
    return (np.isfinite(val) & np.isfinite(sv), val, rev, fr, ph, sv, sf)


def _zeta_start(f: np.ndarray, lo: int, hi: int, width: int) -> float:
    """The damping ratio of a half-power band ``width`` revolutions wide: ``W |df| / (2 f)``."""
    seg = np.asarray(f, dtype=float)[lo:hi + 1]
    if seg.size < 2:
        return math.nan
    return float(width) * float(np.median(np.abs(np.diff(seg)))) / (2.0 * float(np.median(seg)))


def _refine(amp_fit: np.ndarray, k: np.ndarray, half: int, noise: np.ndarray, f: np.ndarray):
    """The parabola's vertex where it refines the pick at ``k`` (else the pick itself):
    value, revolution, amplitude std, frequency std per blade (NaN std: keep the pick's)."""
    val, rev, sv, sx = quadratic_peak(amp_fit, k, half)
    ok = np.isfinite(val)
    n = f.size
    with np.errstate(all="ignore"):
        fr = np.interp(np.where(ok, rev, 0.0), np.arange(n), f)
        step = np.abs(np.interp(np.where(ok, rev, 0.0), np.arange(n), np.gradient(f) if n > 1 else np.zeros(n)))
    return ok, val, rev, noise * sv, fr, step * noise * sx


def peak_method(amp_pkpk_m: np.ndarray, phase_rad: np.ndarray, freq_hz: np.ndarray, lo: int, hi: int, *,
                amp_raw_m: np.ndarray | None = None, gain: np.ndarray | float = 1.0,
                half_power_width: int | None = None, phasor_raw: np.ndarray | None = None) -> ResonancePeaks:
    """Resonance of each blade in revolutions ``lo .. hi`` (paper Sec. 2.3).

    Parameters
    ----------
    amp_pkpk_m, phase_rad : ndarray, shape (n_rev, n_blades)
        Per-revolution fits (of the prepared data).
    freq_hz : ndarray, shape (n_rev,)
        ``EO Omega / 2 pi`` (Eq. 17).
    lo, hi : int
    amp_raw_m : ndarray, shape (n_rev, n_blades), optional
        Unsmoothed amplitudes, for the noise and the parabola (default ``amp_pkpk_m``).
    gain : float or ndarray, shape (n_rev,)
        Noise gain of the smoothing at each revolution (1: none), for the largest value.
    half_power_width : int, optional
        The crossing's, revolutions: the peak is the vertex of a parabola through
        ``amp_raw_m`` around the largest prepared amplitude (:func:`quadratic_peak`, its
        half-width from :func:`fit_half_width`); None: the largest prepared amplitude itself
        (the paper's definition).
    phasor_raw : ndarray of complex, shape (n_rev, n_blades), optional
        Unsmoothed responses ``a1 + i a2``: with ``half_power_width`` of a slow crossing
        (at least :data:`QUASI_STEADY_REVOLUTIONS`), the peak is that of the resonance's
        shape fitted to them (:func:`resonance_fit`) instead of the parabola's vertex.

    Returns
    -------
    ResonancePeaks
    """
    amp = np.asarray(as_rows(amp_pkpk_m)[lo:hi + 1], dtype=float)
    nb = amp.shape[1]
    has = np.isfinite(amp).any(axis=0)
    k = np.argmax(np.where(np.isfinite(amp), amp, -np.inf), axis=0)
    cols = np.arange(nb)
    idx = lo + k
    raw_all = as_rows(amp_pkpk_m if amp_raw_m is None else amp_raw_m)
    raw = raw_all[lo:hi + 1]
    g = np.broadcast_to(np.asarray(gain, dtype=float), (np.asarray(freq_hz).size,))[idx]
    nan = np.full(nb, np.nan)
    f = np.asarray(freq_hz, dtype=float)
    noise = amplitude_noise(raw)
    val, rev, fr = amp[k, cols], idx.astype(float), f[idx]
    std, fstd = noise * g, _freq_step_std(f, idx)
    if half_power_width is not None:
        h = fit_half_width(half_power_width, val, noise)
        ok, v, r, sv, fv, sf = _refine(raw_all, idx, h, noise, f)
        val, rev, fr = np.where(ok, v, val), np.where(ok, r, rev), np.where(ok, fv, fr)
        std, fstd = np.where(ok, sv, std), np.where(ok, np.hypot(sf, fstd), fstd)
    ph = as_rows(phase_rad)[np.clip(np.round(rev).astype(np.int64), 0, f.size - 1), cols]
    if half_power_width is not None and phasor_raw is not None:
        # a slow crossing: the resonance's shape fitted over its half-power width each side
        ok, v, _, _, _, sv, _ = _shape_refine(as_rows(phasor_raw, None), f, np.round(rev).astype(np.int64), lo, hi,
                                                 half_power_width, _zeta_start(f, lo, hi, half_power_width))
        val, std = np.where(ok, v, val), np.where(ok, sv, std)
    return ResonancePeaks(
        revolution=np.where(has, rev, nan), amp_pkpk_m=np.where(has, val, nan),
        freq_hz=np.where(has, fr, nan), damping_ratio=nan.copy(), method="peak",
        phase_rad=np.where(has, ph, nan), amp_std_m=np.where(has, std, nan), freq_std_hz=np.where(has, fstd, nan))


def cff_window(half_power_width: int) -> int:
    """The CFF's revolutions per fit: odd, about a twelfth of the half-power width, >= 3."""
    return max(3, 2 * int(round(half_power_width / 24.0)) + 1)


def _box_flattening(P: np.ndarray, center: np.ndarray, half: int, box: int) -> np.ndarray:
    """How much a centred mean of ``box`` revolutions lowered the pk-pk amplitude of the complex
    responses ``P`` at ``center``: ``2 Re(conj(u) P'') (box^2 - 1) / 24`` (``u`` the unit
    response, ``P''`` of a complex parabola through ``center +- half``; negative at a peak)."""
    n, nb = P.shape
    j = np.arange(-half, half + 1)
    idx = center[None, :] + j[:, None]
    y = P[np.clip(idx, 0, n - 1), np.arange(nb)[None, :]]
    ok = (idx >= 0) & (idx < n) & np.isfinite(y)
    V = np.stack([np.ones(j.size), j, j * j], axis=1).astype(float)
    G = np.einsum("jb,jp,jq->bpq", ok.astype(float), V, V)
    G[np.linalg.matrix_rank(G) < 3] = np.eye(3)
    c = np.linalg.solve(G, np.einsum("jb,jp->bp", np.where(ok, y, 0.0), V)[..., None])[..., 0]
    with np.errstate(all="ignore"):
        u = c[:, 0] / np.abs(c[:, 0])
        d = 2.0 * np.real(np.conj(u) * 2.0 * c[:, 2]) * (int(box) ** 2 - 1) / 24.0
    return np.where(np.isfinite(d), d, 0.0)


def cff_method(d_m: np.ndarray, probe_angles_rad, engine_orders, index: int, omega_rad_s: np.ndarray,
               lo: int, hi: int, window: int, *, tip_radius_m: float | None = None,
               offset: np.ndarray | None = None, half_power_width: int | None = None,
               amp_noise_m: np.ndarray | None = None) -> ResonancePeaks:
    """Circumferential Fourier fit over ``window`` revolutions, peak of each blade.

    Parameters
    ----------
    d_m : ndarray, shape (n_rev, n_blades, n_probes)
        Offset-removed, unsmoothed displacements, m.
    probe_angles_rad : array_like
    engine_orders : tuple of int
        Fitted jointly (as the pipeline's fits).
    index : int
        Which of them is this crossing's.
    omega_rad_s : ndarray, shape (n_rev,)
    lo, hi : int
        The crossing's window.
    window : int
        Revolutions per fit (odd).
    tip_radius_m : float, optional
        Fit at the sampling angles (:func:`~bttsim_stream.process.fit.fit_revolutions`).
    offset : ndarray of complex, shape (n_blades,), optional
        Added to every fitted response ``a1 + i a2`` (the zeroing correction).
    half_power_width : int, optional
        The crossing's, revolutions: the peak is the vertex of a parabola through the CFF
        amplitudes around their largest value (:func:`quadratic_peak`, its half-width from
        :func:`fit_half_width`); None: their largest value.
    amp_noise_m : ndarray, shape (n_blades,), optional
        One revolution's amplitude noise (:func:`amplitude_noise` of the unsmoothed fits);
        None: the CFF's covariance times ``sqrt(window)``.

    Returns
    -------
    ResonancePeaks
    """
    half = window // 2
    a, b = max(0, lo - half), min(d_m.shape[0], hi + half + 1)
    f = fit_revolutions(d_m[a:b], probe_angles_rad, engine_orders, omega_rad_s=omega_rad_s[a:b], window=window,
                        tip_radius_m=tip_radius_m)
    i0, i1 = lo - a, hi - a
    P = f.phasor[..., index] + (0.0 if offset is None else np.asarray(offset)[None, :])
    amp_all = 2.0 * np.abs(P)
    amp = amp_all[i0:i1 + 1]
    phase = np.angle(P)
    nb = amp.shape[1]
    has = np.isfinite(amp).any(axis=0)
    k = np.argmax(np.where(np.isfinite(amp), amp, -np.inf), axis=0)
    cols = np.arange(nb)
    freq = f.freq_hz[:, index]
    nan = np.full(nb, np.nan)
    j = i0 + k
    val, rev, fr = amp[k, cols], j.astype(float), freq[j]
    std, fstd = f.amp_std_m[j, cols, index], _freq_step_std(freq, j)
    if half_power_width is not None:  # the vertex of a parabola through the CFF amplitudes
        one = std * math.sqrt(window) if amp_noise_m is None else np.asarray(amp_noise_m, dtype=float)
        h = fit_half_width(half_power_width, val, one)
        ok, v, r, sv, fv, sf = _refine(amp_all, j, h, one, freq)
        v = v - _box_flattening(P, np.where(ok, r, j).round().astype(np.int64), h, window)
        val, rev, fr = np.where(ok, v, val), np.where(ok, r, rev), np.where(ok, fv, fr)
        std, fstd = np.where(ok, sv, std), np.where(ok, np.hypot(sf, fstd), fstd)
    ph = phase[np.clip(np.round(rev).astype(np.int64), 0, freq.size - 1), cols]
    if half_power_width is not None:
        # a slow crossing: the resonance's shape fitted to the CFF responses (plus the window's
        # flattening of the complex response, as for the parabola)
        ok, v, _, _, _, sv, _ = _shape_refine(P, freq, np.round(rev).astype(np.int64), i0, i1, half_power_width,
                                                 _zeta_start(freq, i0, i1, half_power_width))
        v = v - _box_flattening(P, np.round(rev).astype(np.int64), fit_half_width(half_power_width),
                                window)
        val, std = np.where(ok, v, val), np.where(ok, sv * math.sqrt(window), std)
    return ResonancePeaks(
        revolution=np.where(has, rev + a, nan), amp_pkpk_m=np.where(has, val, nan),
        freq_hz=np.where(has, fr, nan), damping_ratio=nan.copy(), method="cff",
        phase_rad=np.where(has, ph, nan), amp_std_m=np.where(has, std, nan),
        freq_std_hz=np.where(has, fstd, nan))


def sdof_method(phasor: np.ndarray, t_sample_s: np.ndarray, opr_s: np.ndarray, phase: RotorPhase, eo: int,
                lo: int, hi: int, *, fn0_hz: np.ndarray, zeta0: float,
                uncertainty: bool = True) -> tuple[ResonancePeaks, float]:
    """Swept SDOF fit of amplitude and phase through one crossing, per blade.

    Parameters
    ----------
    phasor : ndarray of complex, shape (n_rev, n_blades)
        Eq. 16 responses ``a1 + i a2`` (offset removed, unsmoothed), m.
    t_sample_s : ndarray, shape (n_rev, n_blades)
        When each blade was sampled in each revolution (its mean TOA), s.
    opr_s : ndarray, shape (n_rev,)
    phase : RotorPhase
        The OPR model (:func:`~bttsim_stream.process.displacement.rotor_phase_from_opr`).
    eo : int
    lo, hi : int
        The crossing's window.
    fn0_hz : ndarray, shape (n_blades,)
        Starting natural frequencies (e.g. the peak pick's).
    zeta0 : float
        Starting damping ratio.
    uncertainty : bool
        Compute ``amp_std_m`` and ``freq_std_hz`` (False: NaN, and two integrations fewer per
        blade, for a caller that uses the fit's constant, misfit and peak only).

    Returns
    -------
    peaks : ResonancePeaks
        ``method == "sdof"``; see the module docstring for the fields.
    sweep_rate : float
        ``|d omega / dt| / omega_n^2`` at the resonance (blade median), dimensionless.
    """
    n_rev, nb = phasor.shape
    opr = np.asarray(opr_s, dtype=float)
    last = min(hi + 1, n_rev - 1)
    period = TWO_PI / phase.omega_mean_rad_s
    t0, t1 = float(opr[lo] - 0.25 * period[lo]), float(opr[last] + (period[last] if last == hi else 0.0))
    h = float(np.min(period[lo:hi + 1])) / 8.0
    grid = UniformGrid(t0, h, int(math.ceil((t1 - t0) / h)) + 2)  # its points where asked only

    def phi(j):  # the forcing phase at the grid points j
        n_g = np.clip(np.searchsorted(opr, grid[j], side="right") - 1, 0, n_rev - 1)
        return eo * (TWO_PI * n_g + phase.rows(n_g).angle(grid[j]))

    out = {k: np.full(nb, np.nan) for k in ("amp", "freq", "phase", "amp_std", "freq_std", "zeta", "steady",
                                            "fn", "rev", "zeta_std", "misfit")}
    out["offset"] = np.full(nb, np.nan + 0j)
    fn0 = np.asarray(fn0_hz, dtype=float)
    m = hi + 1 - lo
    per = max(1, swept.FIT_SAMPLES // m)  # the blades in groups (as SweptForcing.fit's), each fit its own
    count, scale = np.zeros(nb, dtype=np.intp), np.zeros(nb)
    for a in range(0, nb, per):
        ok, y, _ = _sdof_rows(phasor, t_sample_s, lo, hi, grid, np.arange(a, min(nb, a + per)))
        count[a:a + per], scale[a:a + per] = ok.sum(axis=1), np.max(np.where(ok, np.abs(y), 0.0), axis=1, initial=0.0)
    use = np.flatnonzero((count >= 8) & np.isfinite(fn0) & (scale > 0))
    if use.size == 0:
        return _sdof_peaks(out), math.nan
    forcing = SweptForcing(grid, lambda s, e: phi(np.arange(s, e)))
    fits = [_sdof_group(forcing, phasor, t_sample_s, lo, hi, grid, use[a:a + per], scale[use[a:a + per]],
                        fn0[use[a:a + per]], zeta0, uncertainty) for a in range(0, use.size, per)]
    f = {key: np.concatenate([g[key] for g in fits]) for key in fits[0]}
    use, scale, fn, zeta, jtj, k, z_k = f["use"], f["scale"], f["fn"], f["zeta"], f["jtj"], f["k"], f["z_k"]
    if use.size == 0:
        return _sdof_peaks(out), math.nan
    dof = np.maximum(2 * f["n"] - 6, 1)
    s2 = 2.0 * f["cost"] / dof
    cov = s2[:, None, None] * inverse2(jtj)  # NaN where J^T J is singular
    C = f["C"] * scale
    wn = TWO_PI * fn
    hmax = 1.0 / (2.0 * zeta * np.sqrt(np.maximum(1.0 - zeta * zeta, 1e-12)) * wn * wn)
    with np.errstate(invalid="ignore", divide="ignore"):
        g00 = 1.0 / f["nz2"]  # the linear part's share: |C| from (A^H A)^-1
    var_c = s2 * g00 / 2.0 * (2.0 * scale * np.abs(z_k)) ** 2
    amp = 2.0 * np.abs(C * z_k)
    grad = np.full((use.size, 2), np.nan)
    if uncertainty:
        for j, dq in enumerate((1e-4 * fn, zeta * 1e-3)):
            grad[:, j] = (f[f"swept{j}"] - amp) / dq
    finite = np.all(np.isfinite(cov), axis=(1, 2))
    var_q = np.where(finite, np.einsum("kp,kpq,kq->k", grad, np.where(finite[:, None, None], cov, 0.0), grad), np.nan)
    w_exc, w_rate = _phase_rates(phi, k, grid.size, h)
    out["amp"][use] = amp
    out["freq"][use] = w_exc / TWO_PI
    out["phase"][use] = np.angle(C * z_k)
    out["steady"][use] = 2.0 * np.abs(C) * hmax
    out["offset"][use] = f["c"] * scale
    out["misfit"][use] = np.sqrt(2.0 * f["cost"] / f["n"]) * scale
    out["zeta"][use] = zeta
    out["fn"][use] = fn
    out["rev"][use] = np.interp(grid[k], opr, np.arange(n_rev))
    out["amp_std"][use] = np.where(np.isfinite(var_q), np.sqrt(np.maximum(var_c, 0.0) + np.maximum(var_q, 0.0)), np.nan)
    out["freq_std"][use] = np.where(finite, np.sqrt(np.maximum(cov[:, 0, 0], 0.0)), np.nan)
    out["zeta_std"][use] = np.where(finite, np.sqrt(np.maximum(cov[:, 1, 1], 0.0)), np.nan)
    etas = np.abs(w_rate) / (wn * wn)
    return _sdof_peaks(out), float(np.median(etas))


def _sdof_rows(phasor, t_sample_s, lo: int, hi: int, grid, blades: np.ndarray):
    """:func:`sdof_method`'s samples of some blades in the window: ``(ok, y, ts)`` of shape
    ``(len(blades), hi + 1 - lo)``, each blade's samples (finite, on the grid) packed to the
    left of its row (:func:`.varpro.pack_rows`)."""
    y = np.asarray(phasor[lo:hi + 1, blades], dtype=complex).T
    ts = np.asarray(t_sample_s[lo:hi + 1, blades], dtype=float).T
    return pack_rows(np.isfinite(y) & np.isfinite(ts) & (ts >= grid[0]) & (ts <= grid[-1]), y, ts)


def _sdof_group(forcing: SweptForcing, phasor, t_sample_s, lo: int, hi: int, grid, use: np.ndarray,
                scale: np.ndarray, fn0: np.ndarray, zeta0: float, uncertainty: bool) -> dict:
    """:func:`sdof_method`'s fit of one group of blades ``use`` (their ``scale`` and ``fn0``):
    per fitted blade, the fit, its linear part and (with ``uncertainty``) the swept peaks
    ``swept0``, ``swept1`` a step of ``f_n`` and of ``zeta`` away."""
    ok, y, ts = _sdof_rows(phasor, t_sample_s, lo, hi, grid, use)
    ts = np.where(ok, ts, grid[0])
    yn = np.where(ok, y, 0) / scale[:, None]
    del y
    res = forcing.fit(ts, yn, ok, fn0, zeta0)
    got = res.ok
    ok, ts, yn = ok[got], ts[got], yn[got]
    g = {"use": use[got], "scale": scale[got], "fn": res.q[got, 0], "zeta": res.q[got, 1], "jtj": res.jtj[got]}
    if not got.any():
        return {**g, "k": np.zeros(0, np.intp), "z_k": np.zeros(0, complex), "C": np.zeros(0, complex),
                "c": np.zeros(0, complex), "cost": np.zeros(0), "n": np.zeros(0, np.intp), "nz2": np.zeros(0),
                "swept0": np.zeros(0), "swept1": np.zeros(0)}
    z_ts, g["k"], g["z_k"] = (a[got] for a in res.extra)  # the envelope at the fitted point
    del res
    lp = linear_part(z_ts, yn, ok)
    del z_ts
    g.update(C=lp.C, c=lp.c, cost=lp.cost, n=lp.n, nz2=lp.nz2)
    del lp
    fn, zeta = g["fn"], g["zeta"]
    steps = ((fn * (1 + 1e-4), zeta), (fn, zeta * (1 + 1e-3))) if uncertainty else ()
    for j, (q_fn, q_zeta) in enumerate(steps):
        z_q, _, _, zk_q = forcing.at(q_fn, q_zeta, ts)
        g[f"swept{j}"] = 2.0 * np.abs(linear_part(z_q, yn, ok).C) * g["scale"] * np.abs(zk_q)
        del z_q
    if not uncertainty:
        g["swept0"] = g["swept1"] = np.zeros(got.sum())
    return g


def _phase_rates(phi, k: np.ndarray, size: int, h: float):
    """``d phi / dt`` and ``d^2 phi / dt^2`` (``np.gradient`` twice on the grid of ``size``
    points, step ``h``) at the grid points ``k``, from the phase ``phi(j)`` on a window of 5
    points around each (the same differences as over the whole grid)."""
    n = min(5, size)
    start = np.clip(k - 2, 0, size - n)
    j = start[:, None] + np.arange(n)
    w = np.gradient(phi(j.ravel()).reshape(j.shape), h, axis=1)
    rate = np.gradient(w, h, axis=1)
    rows = np.arange(k.size)
    return w[rows, k - start], rate[rows, k - start]


def _sdof_peaks(out: dict) -> ResonancePeaks:
    """The swept SDOF fit's :class:`~.resonance.ResonancePeaks` from its per-blade fields."""
    return ResonancePeaks(revolution=out["rev"], amp_pkpk_m=out["amp"], freq_hz=out["freq"],
                          damping_ratio=out["zeta"], method="sdof", phase_rad=out["phase"],
                          amp_std_m=out["amp_std"], freq_std_hz=out["freq_std"],
                          steady_amp_pkpk_m=out["steady"], natural_freq_hz=out["fn"],
                          offset_m=out["offset"], misfit_m=out["misfit"])


"""Resonance amplitude, frequency and phase of each blade through one crossing: three methods.

All three work on the Eq. 16 fits of one engine order inside a crossing's window
(revolutions ``lo .. hi`` found by :mod:`.detect`) and give, per blade, the resonant
amplitude (pk-pk, m), frequency (Hz, Eq. 17), phase (rad) and their standard uncertainties
(:class:`~bttsim_stream.process.resonance.ResonancePeaks`):

``"peak"`` -- the paper's definition (Sec. 2.3): the largest amplitude of the per-revolution
    fits of the *prepared* data (offset removed, smoothed). Uncertainty: the
    revolution-to-revolution scatter of the unsmoothed amplitudes (robust second
    differences), times the noise gain ``||L||`` of the smoother at the peak; frequency: a
    uniform half-revolution, ``|Delta f| / sqrt(12)``.
``"cff"`` -- circumferential Fourier fit: Eq. 16 fitted to a centred window of ``w``
    consecutive revolutions at once (constant coefficients, ``w N_p`` samples; the multi-
    revolution form of the fit, e.g. the Bladesight tutorial's CFF) on the offset-removed,
    *unsmoothed* data, ``w`` odd, about a twelfth of the half-power width (bias of the
    window on a resonance: about ``(w / W)^2 / 3``, 0.2 %). Uncertainty: the least-squares
    covariance ``s^2 (B^T C B)^-1`` at the peak.
``"sdof"`` -- single-degree-of-freedom fit of amplitude *and* phase through the resonance,
    with the sweep in the model. The modal coordinate ``q'' + 2 zeta w_n q' + w_n^2 q =
    exp(i phi(t))``, ``phi = EO x`` rotor angle (the OPR model of :mod:`.displacement`), is
    integrated exactly over the measured speed profile (two first-order poles, a
    linear-phase forcing between grid points ``T / 8`` apart, :func:`scipy.signal.lfilter`);
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

import numpy as np

from .displacement import RotorPhase
from .fit import fit_revolutions
from .resonance import ResonancePeaks

__all__ = ["METHODS", "amplitude_noise", "peak_method", "cff_method", "sdof_method", "sdof_envelope"]

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


def peak_method(amp_pkpk_m: np.ndarray, phase_rad: np.ndarray, freq_hz: np.ndarray, lo: int, hi: int, *,
                amp_raw_m: np.ndarray | None = None, gain: np.ndarray | float = 1.0) -> ResonancePeaks:
    """Largest amplitude of each blade in revolutions ``lo .. hi`` (paper Sec. 2.3).

    Parameters
    ----------
    amp_pkpk_m, phase_rad : ndarray, shape (n_rev, n_blades)
        Per-revolution fits (of the prepared data).
    freq_hz : ndarray, shape (n_rev,)
        ``EO Omega / 2 pi`` (Eq. 17).
    lo, hi : int
    amp_raw_m : ndarray, shape (n_rev, n_blades), optional
        Unsmoothed amplitudes, for the noise (default ``amp_pkpk_m``).
    gain : float or ndarray, shape (n_rev,)
        Noise gain of the smoothing at each revolution (1: none).

    Returns
    -------
    ResonancePeaks
    """
    amp = np.asarray(amp_pkpk_m, dtype=float)[lo:hi + 1]
    nb = amp.shape[1]
    has = np.isfinite(amp).any(axis=0)
    k = np.argmax(np.where(np.isfinite(amp), amp, -np.inf), axis=0)
    cols = np.arange(nb)
    idx = lo + k
    raw = amp if amp_raw_m is None else np.asarray(amp_raw_m, dtype=float)[lo:hi + 1]
    g = np.broadcast_to(np.asarray(gain, dtype=float), (np.asarray(freq_hz).size,))[idx]
    nan = np.full(nb, np.nan)
    f = np.asarray(freq_hz, dtype=float)
    return ResonancePeaks(
        revolution=np.where(has, idx.astype(float), nan), amp_pkpk_m=np.where(has, amp[k, cols], nan),
        freq_hz=np.where(has, f[idx], nan), damping_ratio=nan.copy(), method="peak",
        phase_rad=np.where(has, np.asarray(phase_rad, float)[idx, cols], nan),
        amp_std_m=np.where(has, amplitude_noise(raw) * g, nan), freq_std_hz=np.where(has, _freq_step_std(f, idx), nan))


def cff_window(half_power_width: int) -> int:
    """The CFF's revolutions per fit: odd, about a twelfth of the half-power width, >= 3."""
    return max(3, 2 * int(round(half_power_width / 24.0)) + 1)


def cff_method(d_m: np.ndarray, probe_angles_rad, engine_orders, index: int, omega_rad_s: np.ndarray,
               lo: int, hi: int, window: int, *, tip_radius_m: float | None = None,
               offset: np.ndarray | None = None) -> ResonancePeaks:
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
    amp = 2.0 * np.abs(P[i0:i1 + 1])
    phase = np.angle(P)
    nb = amp.shape[1]
    has = np.isfinite(amp).any(axis=0)
    k = np.argmax(np.where(np.isfinite(amp), amp, -np.inf), axis=0)
    cols = np.arange(nb)
    freq = f.freq_hz[:, index]
    nan = np.full(nb, np.nan)
    return ResonancePeaks(
        revolution=np.where(has, (lo + k).astype(float), nan), amp_pkpk_m=np.where(has, amp[k, cols], nan),
        freq_hz=np.where(has, freq[i0 + k], nan), damping_ratio=nan.copy(), method="cff",
        phase_rad=np.where(has, phase[i0 + k, cols], nan),
        amp_std_m=np.where(has, f.amp_std_m[i0 + k, cols, index], nan),
        freq_std_hz=np.where(has, _freq_step_std(freq, i0 + k), nan))


def sdof_envelope(fn_hz: float, zeta: float, grid_s: np.ndarray, phi_rad: np.ndarray) -> np.ndarray:
    """Envelope ``z = q exp(-i phi)`` of the unit-forced modal coordinate on a uniform grid.

    ``q'' + 2 zeta w_n q' + w_n^2 q = exp(i phi(t))`` is split into the poles
    ``lambda_1,2 = -zeta w_n +- i w_d``, ``q = (y_1 - y_2) / (lambda_1 - lambda_2)``,
    ``y' = lambda y + exp(i phi)``; over each step the forcing phase is linear, and
    ``y_{m+1} = e^{lambda h} y_m + e^{i phi_m} (e^{i w_m h} - e^{lambda h}) / (i w_m - lambda)``
    exactly; the start is the quasi-steady state.

    Parameters
    ----------
    fn_hz, zeta : float
    grid_s : ndarray, shape (m,)
        Uniform time grid, s.
    phi_rad : ndarray, shape (m,)
        Forcing phase on the grid (``EO x`` rotor angle), rad.

    Returns
    -------
    ndarray of complex, shape (m,)
    """
    from scipy.signal import lfilter

    h = float(grid_s[1] - grid_s[0])
    wn = TWO_PI * float(fn_hz)
    zeta = float(zeta)
    wd = wn * math.sqrt(max(1.0 - zeta * zeta, 1e-12))
    lam = (-zeta * wn + 1j * wd, -zeta * wn - 1j * wd)
    w = np.diff(phi_rad) / h
    e_phi = np.exp(1j * phi_rad[:-1])
    e_wh = np.exp(1j * w * h)
    ys = []
    for lm in lam:
        a = np.exp(lm * h)
        x = e_phi * (e_wh - a) / (1j * w - lm)
        y0 = np.exp(1j * phi_rad[0]) / (1j * w[0] - lm)
        y, _ = lfilter([1.0], [1.0, -a], x, zi=np.array([a * y0]))
        ys.append(np.concatenate([[y0], y]))
    q = (ys[0] - ys[1]) / (lam[0] - lam[1])
    return q * np.exp(-1j * phi_rad)


def _interp_c(x, xp, fp):
    return np.interp(x, xp, fp.real) + 1j * np.interp(x, xp, fp.imag)


def sdof_method(phasor: np.ndarray, t_sample_s: np.ndarray, opr_s: np.ndarray, phase: RotorPhase, eo: int,
                lo: int, hi: int, *, fn0_hz: np.ndarray, zeta0: float) -> tuple[ResonancePeaks, float]:
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

    Returns
    -------
    peaks : ResonancePeaks
        ``method == "sdof"``; see the module docstring for the fields.
    sweep_rate : float
        ``|d omega / dt| / omega_n^2`` at the resonance (blade median), dimensionless.
    """
    from scipy.optimize import least_squares

    n_rev, nb = phasor.shape
    opr = np.asarray(opr_s, dtype=float)
    last = min(hi + 1, n_rev - 1)
    period = TWO_PI / phase.omega_mean_rad_s
    t0, t1 = float(opr[lo] - 0.25 * period[lo]), float(opr[last] + (period[last] if last == hi else 0.0))
    h = float(np.min(period[lo:hi + 1])) / 8.0
    grid = t0 + h * np.arange(int(math.ceil((t1 - t0) / h)) + 2)
    n_g = np.clip(np.searchsorted(opr, grid, side="right") - 1, 0, n_rev - 1)
    phi = eo * (TWO_PI * n_g + phase.rows(n_g).angle(grid))
    w_exc = np.gradient(phi, h)
    out = {k: np.full(nb, np.nan) for k in ("amp", "freq", "phase", "amp_std", "freq_std", "zeta", "steady",
                                            "fn", "rev", "zeta_std", "misfit")}
    out["offset"] = np.full(nb, np.nan + 0j)
    etas = []
    sel = slice(lo, hi + 1)
    for b in range(nb):
        y = phasor[sel, b]
        ts = t_sample_s[sel, b]
        ok = np.isfinite(y) & np.isfinite(ts) & (ts >= grid[0]) & (ts <= grid[-1])
        if ok.sum() < 8 or not np.isfinite(fn0_hz[b]):
            continue
        y, ts = y[ok], ts[ok]
        scale = float(np.max(np.abs(y)))
        if not scale > 0:
            continue
        yn = y / scale

        def solve(q, ts=ts, yn=yn):
            z = _interp_c(ts, grid, sdof_envelope(q[0], q[1], grid, phi))
            A = np.stack([z, np.ones_like(z)], axis=1)
            c, *_ = np.linalg.lstsq(A, yn, rcond=None)
            return A, c, A @ c - yn

        def resid(q):
            r = solve(q)[2]
            return np.concatenate([r.real, r.imag])

        f0 = float(fn0_hz[b])
        try:
            res = least_squares(resid, [f0, zeta0], x_scale=[max(f0 * zeta0 * 0.1, 1e-3), zeta0 * 0.1],
                                bounds=([0.8 * f0, 1e-5], [1.2 * f0, 0.3]))
        except (ValueError, np.linalg.LinAlgError):
            continue
        fn, zeta = (float(v) for v in res.x)
        A, c, r = solve(res.x)
        m = 2 * r.size
        dof = max(m - 6, 1)
        s2 = float(np.sum(np.abs(r) ** 2)) / dof
        try:
            cov = s2 * np.linalg.inv(res.jac.T @ res.jac)
        except np.linalg.LinAlgError:
            cov = np.full((2, 2), np.nan)
        z_grid = sdof_envelope(fn, zeta, grid, phi)
        k = int(np.argmax(np.abs(z_grid)))
        C = c[0] * scale
        wn = TWO_PI * fn
        hmax = 1.0 / (2.0 * zeta * math.sqrt(max(1.0 - zeta * zeta, 1e-12)) * wn * wn)
        try:  # the linear part's share: |C| from (A^H A)^-1
            g00 = float(np.real(np.linalg.inv(A.conj().T @ A)[0, 0]))
        except np.linalg.LinAlgError:
            g00 = math.nan
        var_c = s2 * g00 / 2.0 * (2.0 * scale * float(np.abs(z_grid[k]))) ** 2

        def swept(q):
            _, cq, _ = solve(q)
            return 2.0 * abs(cq[0]) * scale * float(np.abs(sdof_envelope(q[0], q[1], grid, phi)).max())

        amp = 2.0 * abs(C * z_grid[k])
        grad = np.array([(swept([fn + dq, zeta]) - amp) / dq for dq in (1e-4 * fn,)]
                        + [(swept([fn, zeta * (1 + 1e-3)]) - amp) / (zeta * 1e-3)])
        var_q = float(grad @ cov @ grad) if np.all(np.isfinite(cov)) else math.nan
        out["amp"][b] = amp
        out["freq"][b] = w_exc[k] / TWO_PI
        out["phase"][b] = float(np.angle(C * z_grid[k]))
        out["steady"][b] = 2.0 * abs(C) * hmax
        out["offset"][b] = c[1] * scale
        out["misfit"][b] = math.sqrt(float(np.mean(np.abs(r) ** 2))) * scale
        out["zeta"][b] = zeta
        out["fn"][b] = fn
        out["rev"][b] = float(np.interp(grid[k], opr, np.arange(n_rev)))
        out["amp_std"][b] = math.sqrt(max(var_c, 0.0) + max(var_q, 0.0)) if math.isfinite(var_q) else math.nan
        out["freq_std"][b] = math.sqrt(max(cov[0, 0], 0.0)) if np.all(np.isfinite(cov)) else math.nan
        out["zeta_std"][b] = math.sqrt(max(cov[1, 1], 0.0)) if np.all(np.isfinite(cov)) else math.nan
        etas.append(abs(float(np.gradient(w_exc, h)[k])) / (wn * wn))
    peaks = ResonancePeaks(revolution=out["rev"], amp_pkpk_m=out["amp"], freq_hz=out["freq"],
                           damping_ratio=out["zeta"], method="sdof", phase_rad=out["phase"],
                           amp_std_m=out["amp_std"], freq_std_hz=out["freq_std"],
                           steady_amp_pkpk_m=out["steady"], natural_freq_hz=out["fn"], **_sdof_extra(out))
    return peaks, (float(np.median(etas)) if etas else math.nan)


def _sdof_extra(out: dict) -> dict:
    """The SDOF fit's constant and misfit (:class:`~.resonance.ResonancePeaks`' ``offset_m``, ``misfit_m``)."""
    return {"offset_m": out["offset"], "misfit_m": out["misfit"]}

"""Windowed multi-frequency sine fit of BTT displacements (paper Eq. 16-17).

For a blade in a revolution the displacements at the ``N_p`` probes are modelled as

``d_j = a_0 + sum_m [a_{2m-1} sin(EO_m theta_j) + a_{2m} cos(EO_m theta_j)]``, i.e.
``d = B a`` (Eq. 16 for one EO), solved in the least-squares sense. A window of ``w``
revolutions centred on the revolution (``n - (w-1)//2 .. n + w//2``, truncated at the ends)
stacks the ``w N_p`` samples, assuming ``a`` constant over the window. Per engine order:
amplitude ``A = sqrt(a1^2 + a2^2)`` reported peak-to-peak (``2 A``), phase
``psi = atan2(a2, a1)`` so that ``d_j = a0 + A sin(EO theta_j + psi)``, and
``f_BTT = EO Omega / (2 pi)`` in Hz (Eq. 17 with Omega in rad/s).

Shapes: ``(revolution, blade, probe)`` in, ``(revolution, blade)`` or
``(revolution, blade, engine order)`` out. A missing arrival (NaN) simply drops that
sample; a fit with fewer usable probes than unknowns is NaN.

**Sampling angles.** Eq. 16 places every sample at its probe angle ``theta_j``. A vibrating
blade reaches the probe early or late: by Eq. 1 the rotor's rigid angle at the TOA is
``theta_j - d_j / R`` (``d_j = Omega R (t_exp - t_TOA)``), so the vibration was sampled at
phase ``EO (theta_j - d_j / R)``, not ``EO theta_j``. The difference, ``EO d_j / R``
(47 mrad for 1 mm at EO 9 on a 0.19 m tip), makes the samples of a pure EO response look
like that response plus a second harmonic of relative size about ``EO A / 2R`` (2.4 %
there), which a 5-probe fit aliases into the amplitude (3 % mean error at EO 9 with the
paper's probes). With ``tip_radius_m`` given, :func:`fit_revolutions` builds ``B`` per
sample at ``theta_j - d_j / R`` (one small normal-equation solve per blade and revolution);
the amplitude error of that example drops to 0.2 %.
"""

from __future__ import annotations

import warnings
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

__all__ = ["design_matrix", "SineFit", "fit_revolutions", "sine_at_probes", "quiet"]

TWO_PI = 2.0 * np.pi
_MAX_COND = 1e10  # beyond this the present probes cannot separate the unknowns
_FAST = True  # the closed-form path of the sampling-angle fit (tests compare it with the general one)


@contextmanager
def quiet():
    """Silence numpy's RuntimeWarnings of empty slices and the like (NaN is the answer)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        yield


def design_matrix(probe_angles_rad, engine_orders) -> np.ndarray:
    """The matrix ``B`` of Eq. 16, extended to several engine orders.

    Parameters
    ----------
    probe_angles_rad : array_like, shape (n_probes,)
    engine_orders : int or sequence of int

    Returns
    -------
    ndarray, shape (n_probes, 1 + 2 n_eo)
        Columns ``1, sin(EO_1 theta), cos(EO_1 theta), sin(EO_2 theta), ...``.
    """
    th = np.atleast_1d(np.asarray(probe_angles_rad, dtype=float))
    eos = np.atleast_1d(np.asarray(engine_orders, dtype=float))
    cols = [np.ones_like(th)]
    for eo in eos:
        cols += [np.sin(eo * th), np.cos(eo * th)]
    return np.stack(cols, axis=1)


def sine_at_probes(probe_angles_rad, engine_order: int, amp_pkpk_m: float, phase_rad: float,
                   dc_m: float = 0.0) -> np.ndarray:
    """The displacement a pure engine-order response gives at the probes (test fixtures).

    Returns
    -------
    ndarray, shape (n_probes,)
        ``dc + (amp_pkpk / 2) sin(EO theta_j + phase)``, m.
    """
    th = np.asarray(probe_angles_rad, dtype=float)
    return dc_m + 0.5 * amp_pkpk_m * np.sin(engine_order * th + phase_rad)


@dataclass(frozen=True, slots=True, eq=False)
class SineFit:
    """Per-revolution, per-blade sine fits.

    Attributes
    ----------
    engine_orders : tuple of int
    window : int
        Revolutions per fit.
    coeffs : ndarray, shape (n_rev, n_blades, 1 + 2 n_eo)
        ``a`` of Eq. 16, m.
    amp_pkpk_m, phase_rad, amp_std_m : ndarray, shape (n_rev, n_blades, n_eo)
        Peak-to-peak amplitude, phase and the amplitude's (pk-pk) standard deviation from the
        least-squares covariance ``s^2 (B^T B)^-1``, ``s^2 = RSS / (n - p)`` (NaN without
        redundancy).
    dc_m, residual_rms_m : ndarray, shape (n_rev, n_blades)
        ``a0`` and ``sqrt(RSS / n)``.
    n_samples : ndarray of int, shape (n_rev, n_blades)
        Samples in each fit.
    omega_rad_s : ndarray, shape (n_rev,), or None
    freq_hz : ndarray, shape (n_rev, n_eo), or None
        ``EO Omega / (2 pi)`` (Eq. 17).
    cn : float
        2-norm condition number of ``B`` for all probes.
    """

    engine_orders: tuple
    window: int
    coeffs: np.ndarray
    amp_pkpk_m: np.ndarray
    phase_rad: np.ndarray
    amp_std_m: np.ndarray
    dc_m: np.ndarray
    residual_rms_m: np.ndarray
    n_samples: np.ndarray
    omega_rad_s: np.ndarray | None
    freq_hz: np.ndarray | None
    cn: float

    @property
    def phasor(self) -> np.ndarray:
        """Complex response ``a1 + i a2`` per engine order, shape (n_rev, n_blades, n_eo), m.

        ``d(theta) = a0 + Im(phasor * exp(i EO theta))``.
        """
        return self.coeffs[..., 1::2] + 1j * self.coeffs[..., 2::2]

    def phasor_at(self, i: int, rows=slice(None), blades=slice(None)) -> np.ndarray:
        """``phasor[rows, blades, i]`` (the same numbers) without the whole run's phasors:
        order ``i``'s complex response of the revolutions (and blades) asked for."""
        return self.coeffs[rows, blades, 1 + 2 * i] + 1j * self.coeffs[rows, blades, 2 + 2 * i]


def _window_sums(x: np.ndarray, window: int) -> np.ndarray:
    """Sum of ``x`` along axis 0 over the centred window (truncated at the ends)."""
    n = x.shape[0]
    c = np.concatenate([np.zeros((1,) + x.shape[1:]), np.cumsum(x, axis=0)])
    lo = np.clip(np.arange(n) - (window - 1) // 2, 0, n)
    hi = np.clip(np.arange(n) + window // 2 + 1, 0, n)
    return c[hi] - c[lo]


def fit_revolutions(d_m: np.ndarray, probe_angles_rad, engine_orders, *,
                    omega_rad_s: np.ndarray | None = None, window: int = 1,
                    tip_radius_m: float | None = None) -> SineFit:
    """Fit Eq. 16 to every blade and revolution at once.

    Parameters
    ----------
    d_m : ndarray, shape (n_rev, n_blades, n_probes)
        Displacements, m (NaN: missing).
    probe_angles_rad : array_like, shape (n_probes,)
    engine_orders : int or sequence of int
    omega_rad_s : ndarray, shape (n_rev,), optional
        Mean speed per revolution, for ``freq_hz``.
    window : int
        Revolutions per fit (centred), >= 1.
    tip_radius_m : float, optional
        When given, each sample sits at its sampling angle ``theta_j - d_j / R`` (see the
        module docstring) instead of the probe angle.

    Returns
    -------
    SineFit

    Notes
    -----
    With the same samples in every probe (no NaN in the window) the solution is one
    precomputed pseudo-inverse applied to the window means, ``a = B^+ dbar``; windows with
    missing samples solve their own weighted normal equations ``B^T C B a = B^T C dbar``
    (``C`` the sample counts per probe), which is the stacked least-squares problem.
    """
    d = np.asarray(d_m, dtype=float)
    if d.ndim != 3:
        raise ValueError(f"d_m must be (n_rev, n_blades, n_probes), got shape {d.shape}")
    window = int(window)
    if window < 1:
        raise ValueError(f"window must be >= 1, got {window}")
    eos = tuple(int(e) for e in np.atleast_1d(engine_orders))
    if not eos:
        raise ValueError("at least one engine order is needed")
    B = design_matrix(probe_angles_rad, eos)
    n_rev, nb, npr = d.shape
    if B.shape[0] != npr:
        raise ValueError(f"{B.shape[0]} probe angles for {npr} probes")
    if window == 1 and n_rev > FIT_CHUNK:  # one revolution per fit: in blocks, bounded temporaries
        return _fit_blocks(d, probe_angles_rad, eos, omega_rad_s, tip_radius_m)
    if tip_radius_m is not None:
        return _fit_sampled(d, np.atleast_1d(np.asarray(probe_angles_rad, float)), eos, float(tip_radius_m),
                            omega_rad_s, window, float(np.linalg.cond(B)))
    p = B.shape[1]
    ok = np.isfinite(d)
    x = np.where(ok, d, 0.0)
    if window == 1:
        S, C, Q = x, ok.astype(float), x * x
    else:
        S, C, Q = (_window_sums(v, window) for v in (x, ok.astype(float), x * x))
    with np.errstate(invalid="ignore", divide="ignore"):
        dbar = S / C
    n_tot = C.sum(axis=2)
    uniform = np.all(C == C[..., :1], axis=2) & (C[..., 0] > 0)
    i1 = np.arange(1, p, 2)
    coeffs = np.full((n_rev, nb, p), np.nan)
    # (B^T C B)^-1 entries needed for the amplitude variance: [a_sin, a_cos, cross] per EO
    ginv = np.full((n_rev, nb, 3, len(eos)), np.nan)
    if npr >= p:
        coeffs = dbar @ np.linalg.pinv(B).T  # NaN where a probe is missing; redone below
        gi = np.linalg.inv(B.T @ B)
        with np.errstate(divide="ignore"):
            inv_c = np.where(uniform, 1.0 / C[..., 0], np.nan)[..., None, None]
        ginv = np.stack([gi[i1, i1], gi[i1 + 1, i1 + 1], gi[i1, i1 + 1]])[None, None] * inv_c
    coeffs[~uniform] = np.nan
    _weighted_rows(C, dbar, B, i1, uniform, coeffs, ginv)
    # residual: within-probe scatter plus the misfit of the window means
    fitted = coeffs @ B.T
    with np.errstate(invalid="ignore", divide="ignore"):
        rss = np.sum((x - fitted) ** 2 * C, axis=2) if window == 1 else _window_rss(S, C, Q, dbar, fitted)
        residual_rms, s2 = _residual_terms(rss, coeffs, n_tot, p)
    c11, c22, c12 = (ginv[..., k, :] * s2[..., None] for k in range(3))
    return _sine_fit(eos, window, coeffs, (c11, c22, c12), residual_rms, n_tot, omega_rad_s,
                     float(np.linalg.cond(B)))


class WindowFit:
    """:func:`fit_revolutions` (probe angles, ``window > 1``) of one revolution whose centred
    window is every row given, bit for bit, with the design matrix's pseudo-inverse, inverse
    and condition number computed once (the streaming processor's windowed live fits).

    Parameters
    ----------
    probe_angles_rad : array_like, shape (n_probes,)
    engine_orders : sequence of int
    window : int
        Revolutions per fit, > 1.

    Raises
    ------
    ValueError
        Fewer probes than unknowns (:func:`fit_revolutions` gives NaN fits then).

    Notes
    -----
    Revolution ``i`` of ``fit_revolutions(d[lo:hi], ..., window=w)``, when ``d[lo:hi]`` is its
    whole centred window (truncated at the ends), sums every row: ``_window_sums`` gives the
    cumulative sum's last row minus its first (zero) row, the rows added one after the other,
    which :meth:`__call__` adds in the same order. Every other step is the same operation
    on that revolution's values (element-wise, or a matrix product row by row).
    """

    def __init__(self, probe_angles_rad, engine_orders, window: int) -> None:
        self.engine_orders = tuple(int(e) for e in engine_orders)
        self.window = int(window)
        B = design_matrix(probe_angles_rad, self.engine_orders)
        self._B = B
        npr, p = B.shape
        self._p = p
        if npr < p:
            raise ValueError(f"{npr} probes cannot separate {p} unknowns")
        self._cn = float(np.linalg.cond(B))
        self._pinv = np.linalg.pinv(B)
        gi = np.linalg.inv(B.T @ B)
        i1 = np.arange(1, p, 2)
        self._i1 = i1
        self._gstack = np.stack([gi[i1, i1], gi[i1 + 1, i1 + 1], gi[i1, i1 + 1]])[None, None]

    def __call__(self, d_m: np.ndarray) -> SineFit:
        """The fit of the revolution whose window is ``d_m``.

        Parameters
        ----------
        d_m : ndarray, shape (m, n_blades, n_probes)
            The revolution's window, ``1 <= m <= window`` rows (NaN: missing).

        Returns
        -------
        SineFit
            One revolution (``n_rev = 1``), without speed.
        """
        m = d_m.shape[0]
        ok = np.isfinite(d_m)
        v = np.empty((m, 3) + d_m.shape[1:])  # x, the sample counts and x * x of every row
        x = v[:, 0]
        np.copyto(x, d_m)
        x[~ok] = 0.0  # np.where(ok, d, 0.0)
        v[:, 1] = ok
        np.multiply(x, x, out=v[:, 2])
        tot = v[0].copy()
        for j in range(1, m):  # _window_sums: the cumulative sum's order
            tot += v[j]
        S, C, Q = tot[None, 0], tot[None, 1], tot[None, 2]
        with np.errstate(invalid="ignore", divide="ignore"):  # one context for the whole fit
            return self._solve(S, C, Q)

    def _solve(self, S: np.ndarray, C: np.ndarray, Q: np.ndarray) -> SineFit:
        """The rest of :func:`fit_revolutions` from the window sums, shape (1, n_blades, n_probes)."""
        B, p, i1 = self._B, self._p, self._i1
        dbar = S / C
        n_tot = C.sum(axis=2)
        uniform = np.all(C == C[..., :1], axis=2) & (C[..., 0] > 0)
        coeffs = dbar @ self._pinv.T  # NaN where a probe is missing; redone below
        inv_c = np.where(uniform, 1.0 / C[..., 0], np.nan)[..., None, None]
        ginv = self._gstack * inv_c
        coeffs[~uniform] = np.nan
        _weighted_rows(C, dbar, B, i1, uniform, coeffs, ginv)  # fit_revolutions' own
        residual_rms, s2 = _residual_terms(_window_rss(S, C, Q, dbar, coeffs @ B.T), coeffs, n_tot, p)
        c11, c22, c12 = (ginv[..., k, :] * s2[..., None] for k in range(3))
        return _sine_fit(self.engine_orders, self.window, coeffs, (c11, c22, c12), residual_rms, n_tot, None,
                         self._cn)


#: Revolutions fitted at once by :func:`fit_revolutions` with one revolution per fit: every
#: fit is its own revolution's, so blocks give the same numbers, and the temporaries (a few
#: dozen arrays of the block's size, about 18 kB a revolution of the default wheel) stay
#: bounded however long the run.
FIT_CHUNK = 512


def _fit_blocks(d: np.ndarray, probe_angles_rad, eos: tuple, omega_rad_s, tip_radius_m) -> SineFit:
    """:func:`fit_revolutions` with ``window = 1``, :data:`FIT_CHUNK` revolutions at a time
    into preallocated outputs (the same numbers: no fit spans two revolutions)."""
    n_rev, nb = d.shape[:2]
    n_eo = len(eos)
    coeffs = np.empty((n_rev, nb, 1 + 2 * n_eo))
    amp, phase, std = (np.empty((n_rev, nb, n_eo)) for _ in range(3))
    res = np.empty((n_rev, nb))
    n_samples = np.empty((n_rev, nb), np.int64)
    cn = None
    for a in range(0, n_rev, FIT_CHUNK):
        b = min(a + FIT_CHUNK, n_rev)
        f = fit_revolutions(d[a:b], probe_angles_rad, eos, window=1, tip_radius_m=tip_radius_m)
        coeffs[a:b], amp[a:b], phase[a:b], std[a:b] = f.coeffs, f.amp_pkpk_m, f.phase_rad, f.amp_std_m
        res[a:b], n_samples[a:b], cn = f.residual_rms_m, f.n_samples, f.cn
    omega = None if omega_rad_s is None else np.asarray(omega_rad_s, dtype=float)
    freq = None if omega is None else omega[:, None] * np.asarray(eos, float)[None, :] / TWO_PI
    return SineFit(engine_orders=eos, window=1, coeffs=coeffs, amp_pkpk_m=amp, phase_rad=phase, amp_std_m=std,
                   dc_m=coeffs[..., 0], residual_rms_m=res, n_samples=n_samples, omega_rad_s=omega, freq_hz=freq,
                   cn=cn)


def _sine_fit(eos: tuple, window: int, coeffs: np.ndarray, cov: tuple, residual_rms: np.ndarray,
              n_samples: np.ndarray, omega_rad_s, cn: float) -> SineFit:
    """Amplitude, phase and the amplitude's standard deviation from the fitted coefficients.

    ``coeffs`` (..., 1 + 2 n_eo) are ``a`` of Eq. 16; ``cov`` holds the variances of the sine
    and cosine coefficients and their covariance, each (..., n_eo), m^2. The amplitude's
    variance is their projection on the amplitude's direction (the mean of the two
    variances where the amplitude is 0).
    """
    c11, c22, c12 = cov
    a1, a2 = coeffs[..., 1::2], coeffs[..., 2::2]
    amp = np.hypot(a1, a2)
    with np.errstate(all="ignore"):
        var = np.where(amp > 0, (a1 * a1 * c11 + 2 * a1 * a2 * c12 + a2 * a2 * c22) / (amp * amp),
                       0.5 * (c11 + c22))
    omega = None if omega_rad_s is None else np.asarray(omega_rad_s, dtype=float)
    freq = None if omega is None else omega[:, None] * np.asarray(eos, float)[None, :] / TWO_PI
    return SineFit(engine_orders=eos, window=window, coeffs=coeffs, amp_pkpk_m=2.0 * amp,
                   phase_rad=np.arctan2(a2, a1), amp_std_m=2.0 * np.sqrt(np.maximum(var, 0.0)),
                   dc_m=coeffs[..., 0], residual_rms_m=residual_rms, n_samples=n_samples.astype(np.int64),
                   omega_rad_s=omega, freq_hz=freq, cn=cn)


def _fit_sampled(d: np.ndarray, th: np.ndarray, eos: tuple, radius: float, omega_rad_s, window: int,
                 cn: float) -> SineFit:
    """Eq. 16 with a design row per sample at its sampling angle ``theta_j - d_j / R``."""
    n_rev, nb, npr = d.shape
    ok = np.isfinite(d)
    x = np.where(ok, d, 0.0)
    te = th[None, None, :] - x / radius
    if len(eos) == 1 and window == 1 and _FAST:
        return _fit_sampled_one(x, ok, te, eos, omega_rad_s, cn)
    cols = [np.ones_like(te)]
    for eo in eos:
        cols += [np.sin(eo * te), np.cos(eo * te)]
    Bs = np.stack(cols, axis=-1) * ok[..., None]  # (n, nb, np, p), zero rows where missing
    p = Bs.shape[-1]
    Bt = np.swapaxes(Bs, -1, -2)
    G = Bt @ Bs  # (n, nb, p, p)
    rhs = (Bt @ x[..., None])[..., 0]
    Q = np.sum(x * x, axis=2)
    C = ok.sum(axis=2).astype(float)
    if window > 1:
        G, rhs, Q, C = (_window_sums(v, window) for v in (G, rhs, Q, C))
    seen = ok if window == 1 else _window_sums(ok.astype(float), window) > 0
    n_seen = np.sum(seen, axis=2)
    good = (C >= p) & (n_seen >= p)  # enough distinct probes to separate the unknowns
    # complete rows share the nominal layout's conditioning (the sampling angles move by
    # mrad); rows with missing probes are checked one by one
    partial = good & (n_seen < npr)
    if np.any(partial):
        with np.errstate(all="ignore"):
            good[partial] = np.linalg.cond(G[partial]) < _MAX_COND
    Gg = np.where(good[..., None, None], G, np.eye(p))
    Ginv = _sym_inv(Gg)
    coeffs = (Ginv @ rhs[..., None])[..., 0]
    coeffs[~good] = np.nan
    with np.errstate(invalid="ignore", divide="ignore"):
        rss = np.maximum(Q - np.sum(coeffs * rhs, axis=-1), 0.0)  # ||d||^2 - a^T B^T d at the optimum
        rss = np.where(good, rss, np.nan)
        residual_rms = np.sqrt(rss / C)
        s2 = np.where(C > p, rss / (C - p), np.nan)
    i1 = np.arange(1, p, 2)
    cov = tuple(Ginv[..., i, j] * s2[..., None] for i, j in ((i1, i1), (i1 + 1, i1 + 1), (i1, i1 + 1)))
    return _sine_fit(eos, window, coeffs, cov, residual_rms, C, omega_rad_s, cn)


def _fit_sampled_one(x: np.ndarray, ok: np.ndarray, te: np.ndarray, eos: tuple, omega_rad_s, cn: float) -> SineFit:
    """:func:`_fit_sampled` for one engine order and one revolution per fit: the normal
    equations as nine sums over the probes and a closed-form 3 x 3 inverse."""
    npr = x.shape[2]
    arg = eos[0] * te
    sn = np.sin(arg) * ok
    cs = np.cos(arg) * ok
    m = ok.astype(float)
    C = m.sum(axis=2)
    S1, C1 = sn.sum(axis=2), cs.sum(axis=2)
    SS, SC, CC = (sn * sn).sum(axis=2), (sn * cs).sum(axis=2), (cs * cs).sum(axis=2)
    R0, R1, R2 = x.sum(axis=2), (sn * x).sum(axis=2), (cs * x).sum(axis=2)
    Q = (x * x).sum(axis=2)
    # adjugate of [[C, S1, C1], [S1, SS, SC], [C1, SC, CC]]
    A00 = SS * CC - SC * SC
    A01 = C1 * SC - S1 * CC
    A02 = S1 * SC - C1 * SS
    A11 = C * CC - C1 * C1
    A12 = S1 * C1 - C * SC
    A22 = C * SS - S1 * S1
    det = C * A00 + S1 * A01 + C1 * A02
    n_seen = ok.sum(axis=2)
    good = (n_seen >= 3) & (det > 0)
    partial = good & (n_seen < npr)
    if np.any(partial):  # rows with missing probes: their own conditioning
        G = np.stack([np.stack([C, S1, C1], -1), np.stack([S1, SS, SC], -1), np.stack([C1, SC, CC], -1)], -2)
        with np.errstate(all="ignore"):
            good[partial] = np.linalg.cond(G[partial]) < _MAX_COND
    with np.errstate(all="ignore"):
        inv = 1.0 / np.where(good, det, np.nan)
        a0 = (A00 * R0 + A01 * R1 + A02 * R2) * inv
        a1 = (A01 * R0 + A11 * R1 + A12 * R2) * inv
        a2 = (A02 * R0 + A12 * R1 + A22 * R2) * inv
        rss = np.maximum(Q - (a0 * R0 + a1 * R1 + a2 * R2), 0.0)
        residual_rms = np.sqrt(rss / C)
        s2 = np.where(C > 3, rss / (C - 3), np.nan)
        cov = (A11 * inv * s2, A22 * inv * s2, A12 * inv * s2)
    coeffs = np.stack([a0, a1, a2], axis=-1)
    return _sine_fit(eos, 1, coeffs, tuple(c[..., None] for c in cov), residual_rms, C, omega_rad_s, cn)


def _sym_inv(G: np.ndarray) -> np.ndarray:
    """Inverses of a stack of symmetric positive definite matrices (closed form for 3 x 3)."""
    if G.shape[-1] != 3:
        return np.linalg.inv(G)
    a, b, c = G[..., 0, 0], G[..., 0, 1], G[..., 0, 2]
    d, e, f = G[..., 1, 1], G[..., 1, 2], G[..., 2, 2]
    A = d * f - e * e
    B = c * e - b * f
    Cc = b * e - c * d
    D = a * f - c * c
    E = b * c - a * e
    F = a * d - b * b
    det = a * A + b * B + c * Cc
    out = np.stack([np.stack([A, B, Cc], -1), np.stack([B, D, E], -1), np.stack([Cc, E, F], -1)], -2)
    with np.errstate(all="ignore"):
        return out / det[..., None, None]


def _weighted_rows(C: np.ndarray, dbar: np.ndarray, B: np.ndarray, i1: int, uniform: np.ndarray,
                   coeffs: np.ndarray, ginv: np.ndarray) -> None:
    """The Eq. 16 fits of the blades whose probes hold unequal counts (``~uniform``, e.g. a
    missing probe) by their weighted normal equations (``C`` the counts, ``dbar`` the window
    means, ``B`` the design matrix), written into ``coeffs`` and ``ginv`` (the covariance
    terms of the first order, rows ``i1``, ``i1 + 1``); NaN where too few probes or the
    equations are ill-conditioned (:data:`_MAX_COND`)."""
    p = B.shape[1]
    rest = ~uniform & (np.sum(C > 0, axis=2) >= p)
    if not np.any(rest):
        return
    c = C[rest]
    G = np.einsum("rj,jp,jq->rpq", c, B, B)
    good = np.linalg.cond(G) < _MAX_COND
    G[~good] = np.eye(p)
    Ginv = np.linalg.inv(G)
    a = np.einsum("rpq,jq,rj->rp", Ginv, B, c * np.where(c > 0, dbar[rest], 0.0))
    a[~good] = np.nan
    Ginv[~good] = np.nan
    coeffs[rest] = a
    ginv[rest] = np.stack([Ginv[:, i1, i1], Ginv[:, i1 + 1, i1 + 1], Ginv[:, i1, i1 + 1]], axis=1)


def _window_rss(S: np.ndarray, C: np.ndarray, Q: np.ndarray, dbar: np.ndarray, fitted: np.ndarray) -> np.ndarray:
    """A windowed fit's residual sum of squares from the window sums (``S``, count ``C``,
    squares ``Q`` per probe): the scatter within each probe plus the misfit of its mean."""
    within = np.where(C > 0, Q - S * dbar, 0.0)
    misfit = np.where(C > 0, C * (dbar - fitted) ** 2, 0.0)
    return np.maximum(np.sum(within + misfit, axis=2), 0.0)


def _residual_terms(rss: np.ndarray, coeffs: np.ndarray, n_tot: np.ndarray, p: int) -> tuple:
    """``(residual_rms, s2)`` from the residual sum of squares over ``n_tot`` samples and ``p``
    unknowns (NaN where the fit is)."""
    rss = np.where(np.isfinite(coeffs[..., 0]), rss, np.nan)
    return np.sqrt(rss / n_tot), np.where(n_tot > p, rss / (n_tot - p), np.nan)

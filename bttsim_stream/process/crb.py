"""Cramér-Rao lower bounds of a blade's resonance amplitude and frequency (paper Eq. 15-17).

The limit of any unbiased estimate from the run's layout, noise level and revolutions,
reported beside the processing's own uncertainties (:mod:`.intervals`). Derivation
(``docs/processing.md``, "Cramér-Rao lower bound"):

**Samples.** In revolution ``r`` a blade's displacements at the ``N_p`` probes follow Eq. 16,
``d_r = B a_r + e_r``, with ``B`` the design matrix of the fitted engine orders
(:func:`~bttsim_stream.process.fit.design_matrix`) and white Gaussian errors of standard
deviation ``sigma_r``: TOA noise ``sigma_t`` becomes ``sigma_r = Omega_r R sigma_t``
(Eq. 15), or ``sigma_r`` is estimated from the fits' residuals.

**One revolution.** The Fisher information of ``a_r`` is ``B^T B / sigma_r^2``. The offset
``a0`` and the other engine orders' coefficients are nuisance parameters free in every
revolution, so the information on the crossing's own ``(a1, a2)`` is the inverse of the
matching 2 x 2 block ``K`` of ``(B^T B)^-1``: ``K^-1 / sigma_r^2``. The least-squares fit of
one revolution attains it (a linear Gaussian model); its pk-pk amplitude ``2 |a1 + i a2|``
has the bound ``4 u^T K u sigma_r^2`` (``u`` the unit vector along ``(a1, a2)``): the layout
enters through ``K`` (a badly conditioned ``B``, a large CN, inflates it).

**Constant response over ``n`` revolutions** (the CFF's window): the informations add,
``sum_r K^-1 / sigma_r^2``.

**Through a resonance.** The response of revolution ``r`` at frequency ``f_r = EO Omega_r /
2 pi`` (Eq. 17) is modelled as a single-degree-of-freedom resonance, quasi-steady,

``P_r = (A / 2) exp(i phi) h(f_r) / h(f_pk)``,  ``h(f) = 1 / (1 - (f / f_n)^2 + 2 i zeta f / f_n)``,

``f_n = f_pk / sqrt(1 - 2 zeta^2)``, with the four parameters ``theta = (A, f_pk, zeta, phi)``:
pk-pk amplitude and frequency of the peak, damping ratio, phase at the peak. The Fisher
information of the revolutions used is ``I = sum_r J_r^T K^-1 J_r / sigma_r^2`` with ``J_r``
the 2 x 4 Jacobian of ``(Re P_r, Im P_r)``; the bounds are ``sqrt([I^-1]_AA)`` and
``sqrt([I^-1]_ff)``, evaluated at the estimated parameters. No I/O here.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .fit import design_matrix

__all__ = ["ResonanceBound", "toa_sigma", "displacement_sigma", "phasor_covariance", "amplitude_bound",
           "window_amplitude_bound", "resonance_bound", "residual_sigma", "scatter_sigma"]

TWO_PI = 2.0 * np.pi

#: Samples (blades x revolutions) of the Jacobian :func:`resonance_bound` builds at once: its
#: temporaries are bounded by a block of blades, not by the crossing's length.
BOUND_SAMPLES = 1 << 14


@dataclass(frozen=True, slots=True, eq=False)
class ResonanceBound:
    """Cramér-Rao bounds (standard deviations) per blade.

    Attributes
    ----------
    amp_pkpk_m : ndarray, shape (n_blades,)
        Of the pk-pk resonant amplitude, m.
    freq_hz : ndarray, shape (n_blades,)
        Of the resonant frequency, Hz.
    """

    amp_pkpk_m: np.ndarray
    freq_hz: np.ndarray


def toa_sigma(trigger_jitter_s: float, clock_hz: float = 0.0) -> float:
    """Standard deviation of a TOA: the trigger jitter and, with a clock, its quantisation
    (a uniform tick, ``tick / sqrt(12)``), s."""
    tick = 1.0 / clock_hz if clock_hz > 0 else 0.0
    return float(np.sqrt(trigger_jitter_s ** 2 + tick * tick / 12.0))


def displacement_sigma(omega_rad_s, tip_radius_m: float, toa_sigma_s: float) -> np.ndarray:
    """Eq. 15: a TOA error ``sigma_t`` is a displacement error ``Omega R sigma_t``, m."""
    return np.asarray(omega_rad_s, dtype=float) * float(tip_radius_m) * float(toa_sigma_s)


def phasor_covariance(probe_angles_rad, engine_orders, index: int) -> np.ndarray:
    """``K``: the 2 x 2 block of ``(B^T B)^-1`` of engine order ``engine_orders[index]``'s
    ``(a1, a2)`` (Eq. 16; the offset and the other orders free). Times ``sigma^2`` it is the
    Cramér-Rao bound of that order's coefficients from one revolution.

    Raises
    ------
    ValueError
        Fewer probes than unknowns, or probes that cannot separate them (singular ``B^T B``).
    """
    B = design_matrix(probe_angles_rad, engine_orders)
    if B.shape[0] < B.shape[1]:
        raise ValueError(f"{B.shape[0]} probes cannot fit {B.shape[1]} unknowns (Eq. 16)")
    G = B.T @ B
    if np.linalg.cond(G) > 1e12:
        raise ValueError("the probes cannot separate the engine orders (B^T B is singular)")
    Gi = np.linalg.inv(G)
    i = 1 + 2 * int(index)
    return Gi[i:i + 2, i:i + 2]


def amplitude_bound(K: np.ndarray, phasor, sigma_m) -> np.ndarray:
    """Bound (standard deviation) of the pk-pk amplitude ``2 |P|`` from coefficients of
    covariance ``sigma^2 K``: ``2 sigma sqrt(u^T K u)``, ``u`` along ``(Re P, Im P)`` (the
    mean of the two directions where ``P = 0``). Broadcasts ``phasor`` and ``sigma_m``."""
    P = np.asarray(phasor, dtype=complex)
    mag = np.abs(P)
    with np.errstate(invalid="ignore", divide="ignore"):
        c, s = np.where(mag > 0, P.real / mag, np.nan), np.where(mag > 0, P.imag / mag, np.nan)
    q = np.where(mag > 0, c * c * K[0, 0] + 2 * c * s * K[0, 1] + s * s * K[1, 1], 0.5 * (K[0, 0] + K[1, 1]))
    return 2.0 * np.asarray(sigma_m, dtype=float) * np.sqrt(q)


def window_amplitude_bound(probe_angles_rad, engine_orders, index: int, phasor, sigma_m) -> np.ndarray:
    """Bound of the pk-pk amplitude of a response constant over the revolutions of
    ``sigma_m`` (n_rev,) m (the CFF's window): the informations of the revolutions add,
    ``sigma_eff^-2 = sum_r sigma_r^-2``. ``phasor``: the response, any shape (e.g. blades)."""
    K = phasor_covariance(probe_angles_rad, engine_orders, index)
    s = np.atleast_1d(np.asarray(sigma_m, dtype=float))
    return amplitude_bound(K, phasor, 1.0 / np.sqrt(np.sum(1.0 / (s * s))))


def _response(theta: np.ndarray, f: np.ndarray) -> np.ndarray:
    """``P_r`` of the SDOF model for parameters ``theta`` (..., 4) at frequencies ``f``
    (..., n): shape (..., n), complex."""
    A, fpk, zeta, phi = (theta[..., k, None] for k in range(4))
    fn = fpk / np.sqrt(np.maximum(1.0 - 2.0 * zeta * zeta, 1e-12))

    def h(x):
        r = x / fn
        return 1.0 / (1.0 - r * r + 2j * zeta * r)

    return 0.5 * A * np.exp(1j * phi) * h(f) / h(fpk)


def _jacobian(theta: np.ndarray, f: np.ndarray) -> np.ndarray:
    """``d P_r / d theta`` (..., n, 4) complex: A and phi exactly, f_pk and zeta by central
    differences (relative steps 1e-6 of the half-power width and of zeta)."""
    P = _response(theta, f)
    cols = [P / theta[..., 0, None], None, None, 1j * P]
    for k, scale in ((1, theta[..., 1] * theta[..., 2]), (2, theta[..., 2])):
        h = 1e-6 * np.abs(scale)
        up, dn = theta.copy(), theta.copy()
        up[..., k] += h
        dn[..., k] -= h
        cols[k] = (_response(up, f) - _response(dn, f)) / (2.0 * h[..., None])
    return np.stack(cols, axis=-1)


def resonance_bound(probe_angles_rad, engine_orders, index: int, freq_hz, sigma_m, amp_pkpk_m, peak_freq_hz,
                    damping_ratio, phase_rad) -> ResonanceBound:
    """Cramér-Rao bounds of each blade's resonant amplitude and frequency through a crossing
    (the SDOF model of the module docstring), from the revolutions given.

    Parameters
    ----------
    probe_angles_rad : array_like, shape (n_probes,)
    engine_orders : tuple of int
        The fitted orders (their coefficients are free in every revolution).
    index : int
        The crossing's order among them.
    freq_hz : ndarray, shape (n_rev,)
        ``EO Omega_r / 2 pi`` of the revolutions used (Eq. 17).
    sigma_m : float or ndarray, shape (n_rev,) or (n_rev, n_blades)
        Displacement noise per sample, m.
    amp_pkpk_m, peak_freq_hz, phase_rad : ndarray, shape (n_blades,)
        The parameters where the bound is evaluated (the estimates).
    damping_ratio : float or ndarray, shape (n_blades,)

    Returns
    -------
    ResonanceBound
        NaN for a blade whose parameters are not finite or positive, or whose information is
        singular (e.g. no revolution near its peak).
    """
    K = phasor_covariance(probe_angles_rad, engine_orders, index)
    Kinv = np.linalg.inv(K)
    f = np.asarray(freq_hz, dtype=float)
    amp = np.atleast_1d(np.asarray(amp_pkpk_m, dtype=float))
    nb = amp.size
    theta = np.stack(np.broadcast_arrays(amp, np.asarray(peak_freq_hz, float), np.asarray(damping_ratio, float),
                                         np.asarray(phase_rad, float)), axis=-1).reshape(nb, 4)
    ok = np.all(np.isfinite(theta), axis=1) & (theta[:, 0] > 0) & (theta[:, 1] > 0) & (theta[:, 2] > 0) \
        & (theta[:, 2] < 0.5)
    th = np.where(ok[:, None], theta, np.array([1.0, 1.0, 0.01, 0.0]))
    sg = np.asarray(sigma_m, dtype=float)
    sg = sg.reshape(f.size, -1) if sg.ndim else sg.reshape(1, 1)
    s = np.broadcast_to(sg, (f.size, nb)).T  # (nb, n)
    use = np.isfinite(f)[None, :] & np.isfinite(s) & (s > 0)
    w = np.where(use, 1.0 / np.where(use, s, 1.0) ** 2, 0.0)
    fr = np.where(np.isfinite(f), f, 1.0)
    info = np.empty((nb, 4, 4))
    step = max(1, BOUND_SAMPLES // max(f.size, 1))
    for a in range(0, nb, step):  # a blade's information is its own: by blocks of blades, the same numbers
        b = slice(a, a + step)
        J = _jacobian(th[b], np.broadcast_to(fr, (th[b].shape[0], f.size)))  # (blades, n, 4)
        R = np.stack([J.real, J.imag], axis=-2)  # (blades, n, 2, 4)
        del J
        info[b] = np.einsum("bn,bnip,ij,bnjq->bpq", w[b], R, Kinv, R)
    # scale to unit diagonal before inverting (A in m, f in Hz: very different sizes)
    d = np.sqrt(np.abs(np.diagonal(info, axis1=1, axis2=2)))
    good = ok & np.all(d > 0, axis=1)
    d = np.where(good[:, None], d, 1.0)
    Ns = info / (d[:, :, None] * d[:, None, :])
    good &= np.linalg.cond(np.where(good[:, None, None], Ns, np.eye(4))) < 1e12
    cov = np.linalg.inv(np.where(good[:, None, None], Ns, np.eye(4))) / (d[:, :, None] * d[:, None, :])
    nan = np.full(nb, np.nan)
    exact = ok & np.all(np.isfinite(f)[None, :] & (s == 0), axis=1)  # no noise at all: exact
    return ResonanceBound(amp_pkpk_m=np.where(exact, 0.0, np.where(good, np.sqrt(np.abs(cov[:, 0, 0])), nan)),
                          freq_hz=np.where(exact, 0.0, np.where(good, np.sqrt(np.abs(cov[:, 1, 1])), nan)))


def residual_sigma(d_m: np.ndarray, probe_angles_rad, engine_orders) -> np.ndarray:
    """Per-blade displacement noise estimated from the residuals of the per-revolution
    Eq. 16 fits: ``sqrt(sum RSS / sum (N_p - p))`` over the revolutions with every probe
    present (the unbiased pooled variance of a linear model).

    Parameters
    ----------
    d_m : ndarray, shape (n_rev, n_blades, n_probes)

    Returns
    -------
    ndarray, shape (n_blades,)
        m; NaN without redundancy (``N_p <= p``) or without a complete revolution.
    """
    d = np.asarray(d_m, dtype=float)
    B = design_matrix(probe_angles_rad, engine_orders)
    npr, p = B.shape
    nb = d.shape[1]
    if npr <= p:
        return np.full(nb, np.nan)
    resid_op = np.eye(npr) - B @ np.linalg.pinv(B)  # (I - B B^+): the residual of a fit
    full = np.all(np.isfinite(d), axis=2)  # (n_rev, nb)
    z = np.where(full[..., None], d, 0.0)
    del d, d_m  # (the whole product and sum: cut in blocks, they would round differently)
    r = z @ resid_op.T
    del z
    rss = np.sum(np.multiply(r, r, out=r), axis=(0, 2))
    dof = (npr - p) * np.sum(full, axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(dof > 0, np.sqrt(rss / np.maximum(dof, 1)), np.nan)


def scatter_sigma(phasor: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Per-blade displacement noise from the revolution-to-revolution scatter of the
    unsmoothed responses, for fits without redundancy (as many probes as unknowns): the
    second difference of white coefficients of covariance ``sigma^2 K`` has ``E |Delta^2 P|^2
    = 6 sigma^2 tr K`` (the resonance's slow change adds little); the median over the
    revolutions, over ``ln 2`` (an exponential's median), for robustness.

    Parameters
    ----------
    phasor : ndarray, shape (n_rev, n_blades), complex
    K : ndarray, shape (2, 2)
        :func:`phasor_covariance`.

    Returns
    -------
    ndarray, shape (n_blades,)
        m; NaN with fewer than 3 revolutions.
    """
    P = np.asarray(phasor, dtype=complex)
    if P.shape[0] < 3:
        return np.full(P.shape[1:], np.nan)
    d2 = np.abs(np.diff(P, 2, axis=0)) ** 2
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.sqrt(np.nanmedian(d2, axis=0) / (np.log(2.0) * 6.0 * np.trace(K)))

"""Exact modal response to chirped engine-order forcing, as slowly varying envelopes.

Conventions
-----------
Mode ``k`` obeys ``q'' + 2 zeta w q' + w^2 q = f(t)``. With ``lambda = -zeta w + i w_d`` the
complex state ``z' = lambda z + f`` carries ``q = Im(z) / w_d`` and ``q' = Im(lambda z) / w_d``.
The modal force of excitation ``m`` (paper Eq. 5-7) is ``Im(C_km exp(i EO_m phi(t)))``, so the
response splits into two carriers ``exp(+- i EO_m phi)`` with *envelopes*
``a_+- = z_+- exp(-+ i EO_m phi)`` that obey ``a' = (lambda -+ i EO_m Omega(t)) a + c_+-``
with constant ``c_+ = C / 2i``, ``c_- = -conj(C) / 2i``.

Over a grid step ``h`` in which the speed is linear (acceleration ``alpha``) the envelope
recursion is *exact*:

``a(t + h) = exp(lambda h -+ i EO (phi(t+h) - phi(t))) a(t) + c h I(u, v)``,
``I(u, v) = int_0^1 exp(u x + v x^2) dx``, ``u = (lambda -+ i EO Omega(t+h)) h``,
``v = +- i EO alpha h^2 / 2``,

with ``I`` summed as ``sum_n v^n / n! J_2n(u)``, ``J_k(u) = int_0^1 x^k exp(u x) dx`` (|v| is
below 1e-4 for grid steps of milliseconds, so five terms reach round-off).

The envelopes are smooth (the carriers hold the fast phase), so summing the modes once into
per-blade envelopes ``G_b = sum_k Psi_bk (a_+ - conj(a_-))_k / w_dk`` on a coarse grid and
interpolating them (cubic Hermite, exact derivatives) gives the displacement of any blade at
any time at a cost independent of the number of modes:
``w_b(t) = sum_m Im(G_bm(t) exp(i EO_m phi(t)))``. ``Psi_b`` is a compressed basis of blade
``b``'s tip motion (SVD; rank 6 for a rigid tip chord).
"""

from __future__ import annotations

from dataclasses import dataclass
from math import factorial

import numpy as np

from ..errors import BttsimError
from .speed import SpeedProfile

__all__ = [
    "chirp_integral",
    "modal_forcing",
    "TipBasis",
    "tip_basis",
    "EnvelopeIntegrator",
    "EnvelopeGrid",
    "build_grid",
]



def _j_series(u: np.ndarray, kmax: int, radius: float) -> np.ndarray:
    """Power series ``J_k(u) = sum_n u^n / (n! (n + k + 1))`` for ``|u| <= radius``."""
    n_terms = 4
    while radius**n_terms / factorial(n_terms) > 1e-18:
        n_terms += 1
    n = np.arange(n_terms)
    pw = np.empty(u.shape + (n_terms,), complex)
    pw[..., 0] = 1.0
    for i in range(1, n_terms):
        pw[..., i] = pw[..., i - 1] * u / i
    return pw @ (1.0 / (n[:, None] + np.arange(kmax + 1)[None, :] + 1.0))


def _j_moments(u: np.ndarray, kmax: int, vabs: np.ndarray | float = 0.0) -> np.ndarray:
    """``J_k(u) = int_0^1 x^k exp(u x) dx`` for k = 0..kmax (last axis).

    ``J_0 = expm1(u) / u`` is exact to round-off. The forward recurrence
    ``J_k = (e^u - k J_k-1) / u`` amplifies round-off by ``k! / |u|^k``; in
    :func:`chirp_integral` ``J_2n`` is weighted by ``v^n / n!``, so the recurrence is kept
    wherever ``|u| >= 1/4`` and ``|v| <= |u|^2 / 10`` (then ``(2n)! |v|^n / (n! |u|^2n) < 1``
    for n <= 3 and the weighted error stays at round-off); elsewhere the power series.
    """
    u = np.asarray(u, complex)
    out = np.empty(u.shape + (kmax + 1,), complex)
    with np.errstate(all="ignore"):
        em1 = np.expm1(u)
        eu = em1 + 1.0
        j = em1 / u
        out[..., 0] = j
        for k in range(1, kmax + 1):
            j = (eu - k * j) / u
            out[..., k] = j
    au2 = (u * u.conj()).real
    series = (au2 < 0.0625) | (np.broadcast_to(vabs, u.shape) > 0.1 * au2)
    if np.any(series):
        us = u[series]
        small = np.abs(us) < 0.25
        vals = np.empty(us.shape + (kmax + 1,), complex)
        vals[small] = _j_series(us[small], kmax, 0.25)
        if np.any(~small):
            vals[~small] = _j_series(us[~small], kmax, float(np.max(np.abs(us[~small]))))
        out[series] = vals
    return out


def chirp_integral(u, v) -> np.ndarray:
    """``I(u, v) = int_0^1 exp(u x + v x^2) dx`` for complex ``u`` and small ``|v|`` (< 1e-2)."""
    u = np.asarray(u, complex)
    v = np.asarray(v, complex)
    vmax = float(np.max(np.abs(v))) if v.size else 0.0
    n_v = 1
    while vmax ** n_v / factorial(n_v) > 1e-18 and n_v < 12:
        n_v += 1
    J = _j_moments(u, 2 * (n_v - 1), np.abs(v))
    out = J[..., 0] * np.ones(np.broadcast(u, v).shape)
    vn = np.ones_like(out)
    for n in range(1, n_v):
        vn = vn * v
        out = out + vn * J[..., 2 * n] / factorial(n)
    return out


def modal_forcing(model, excitations) -> tuple[np.ndarray, np.ndarray]:
    """Complex modal force amplitudes (paper Eq. 5-7).

    Parameters
    ----------
    model : ModalModel
    excitations : sequence of scenario ``Excitation``
        Engine order, nodal diameter (travelling-wave phase ``2 pi (b-1) N_ND / N_b``),
        amplitude (N), direction (radial, tangential, axial; normalised here), edge node.

    Returns
    -------
    C : ndarray, shape (n_modes, n_exc), complex
        Modal force of excitation m is ``Im(C[k, m] exp(i EO_m phi(t)))``, N per unit modal
        coordinate.
    eo : ndarray, shape (n_exc,)
    """
    n_b = model.n_blades
    C = np.zeros((model.n_modes, len(excitations)), complex)
    eo = np.zeros(len(excitations))
    b = np.arange(n_b)
    for m, ex in enumerate(excitations):
        if ex.node == "leading_edge":
            shapes = model.force_shapes
        else:
            if "force_shapes_trailing_edge" not in model.extra:
                raise BttsimError("excitation node 'trailing_edge' needs force_shapes_trailing_edge "
                                  "in the model file")
            shapes = model.extra["force_shapes_trailing_edge"]
        d = np.asarray(ex.direction, float)
        d = d / np.linalg.norm(d)
        phase = np.exp(2j * np.pi * b * ex.nodal_diameter / n_b)
        C[:, m] = ex.amplitude_n * (shapes @ d) @ phase
        eo[m] = ex.engine_order
    return C, eo


@dataclass(frozen=True, slots=True, eq=False)
class TipBasis:
    """Compressed basis of the tip-node motion, common to all blades.

    Attributes
    ----------
    psi : ndarray, shape (n_modes, n_blades, r)
        Modal participation in the compressed coordinates.
    nodes : ndarray, shape (r, n_tip, 3)
        Compressed coordinates -> (radial, tangential, axial) displacement of each tip node
        (in each node's own polar frame): ``tip_shapes[k, b] = sum_j psi[k, b, j] * nodes[j]``
        to round-off. For a rigid tip chord r = 6 (three translations, three rotations).
    """

    psi: np.ndarray
    nodes: np.ndarray


def tip_basis(tip_shapes: np.ndarray, rtol: float = 1e-12) -> TipBasis:
    """SVD compression of the tip shapes ``(n_modes, n_blades, n_tip, 3)`` over all blades."""
    n_modes, n_b, n_tip, _ = tip_shapes.shape
    X = tip_shapes.reshape(n_modes * n_b, n_tip * 3)
    _, S, Vt = np.linalg.svd(X, full_matrices=False)
    r = int(max(1, np.sum(S > rtol * S[0])))
    V = Vt[:r]
    psi = (X @ V.T).reshape(n_modes, n_b, r)
    return TipBasis(psi=np.ascontiguousarray(psi), nodes=np.ascontiguousarray(V.reshape(r, n_tip, 3)))


def build_grid(speed: SpeedProfile, h_max: float) -> np.ndarray:
    """Envelope grid: uniform steps <= ``h_max`` in every speed segment, knots included."""
    parts = []
    for k in range(speed.t_s.size - 1):
        t0, t1 = speed.t_s[k], speed.t_s[k + 1]
        n = max(1, int(np.ceil((t1 - t0) / h_max - 1e-9)))
        parts.append(t0 + (t1 - t0) * np.arange(n) / n)
    parts.append(speed.t_s[-1:])
    return np.concatenate(parts)


@dataclass(frozen=True, slots=True, eq=False)
class EnvelopeGrid:
    """Per-blade envelopes on a stretch of the grid.

    Attributes
    ----------
    t : ndarray, shape (n,)
        Grid times, s.
    G, dG : ndarray, shape (n, n_exc, n_blades, r), complex
        Envelope and its time derivative.
    """

    t: np.ndarray
    G: np.ndarray
    dG: np.ndarray
    a_plus: np.ndarray | None = None
    a_minus: np.ndarray | None = None


class EnvelopeIntegrator:
    """Exact, streaming integration of the modal envelopes along the grid.

    Modes with no modal force from any excitation (and so no response) are skipped.

    Parameters
    ----------
    freq_hz, damping_ratio : ndarray, shape (n_modes,)
    C : ndarray, shape (n_modes, n_exc), complex
        Modal force amplitudes (:func:`modal_forcing`).
    eo : ndarray, shape (n_exc,)
    basis : TipBasis
    speed : SpeedProfile
    initial : {"steady", "rest"}
        ``"steady"`` starts every mode in its quasi-steady forced response at the start
        speed (the rotor was running before the run-up); ``"rest"`` starts at rest.
    """

    def __init__(self, freq_hz, damping_ratio, C, eo, basis: TipBasis, speed: SpeedProfile,
                 initial: str = "steady") -> None:
        w = 2.0 * np.pi * np.asarray(freq_hz, float)
        zeta = np.asarray(damping_ratio, float)
        active = np.max(np.abs(C), axis=1) > 1e-14 * max(np.max(np.abs(C)), 1e-300)
        self.active = np.flatnonzero(active)
        w, zeta = w[active], zeta[active]
        wd = w * np.sqrt(1.0 - zeta**2)
        self.lam = (-zeta * w + 1j * wd)[:, None]  # (n_act, 1)
        self.eo = np.asarray(eo, float)[None, :]  # (1, n_exc)
        Ca = C[active]
        self.c_plus = Ca / 2j
        self.c_minus = -np.conj(Ca) / 2j
        n_b, r = basis.psi.shape[1:]
        self.n_blades, self.r = n_b, r
        self.W = (basis.psi[active] / wd[:, None, None]).reshape(len(self.active), n_b * r)
        self.speed = speed
        self.t = 0.0
        phi0, om0, al0 = (float(x) for x in speed.state(0.0))
        self.a_plus = self._initial(self.c_plus, om0, al0, +1, initial)
        self.a_minus = self._initial(self.c_minus, om0, al0, -1, initial)
        # longest sub-chunk keeping exp(-lambda t) within range
        self._max_span = 400.0 / max(float(np.max(zeta * w)) if w.size else 1.0, 1e-9)

    def _initial(self, c, omega, alpha, sign, initial):
        if initial == "rest" or c.size == 0:
            return np.zeros_like(c)
        mu = self.lam - sign * 1j * self.eo * omega
        dmu = -sign * 1j * self.eo * alpha
        ok = np.abs(dmu) < 1e-2 * np.abs(mu) ** 2
        a = -c / mu + c * dmu / mu**3 - 3.0 * c * dmu**2 / mu**5
        return np.where(ok, a, 0.0)

    def _envelopes(self, sign, a0, c, t, phi, om_end, alpha):
        """Exact envelopes at grid times ``t`` (t[0] = current time) for one carrier."""
        lam, eo = self.lam[None], self.eo[None]  # (1, n_act, 1), (1, 1, n_exc)
        h = np.diff(t)[:, None, None]
        L = lam * (t - t[0])[:, None, None] - sign * 1j * eo * (phi - phi[0])[:, None, None]
        u = (lam - sign * 1j * eo * om_end[:, None, None]) * h
        v = sign * 0.5j * eo * alpha[:, None, None] * h * h
        g = c[None] * h * chirp_integral(u, v)  # (n-1, n_act, n_exc)
        acc = np.concatenate([np.zeros_like(g[:1]), np.cumsum(g * np.exp(-L[1:]), axis=0)])
        return np.exp(L) * (a0[None] + acc)

    def advance(self, t_grid: np.ndarray, keep_modal: bool = False) -> EnvelopeGrid:
        """Integrate from the current time (``t_grid[0]``) over ``t_grid``; return envelopes.

        ``t_grid`` must come from :func:`build_grid` (no step straddles a speed knot).
        """
        t_grid = np.asarray(t_grid, float)
        if abs(t_grid[0] - self.t) > 1e-12 * max(1.0, abs(self.t)):
            raise ValueError("advance() must start at the integrator's current time")
        phi, om, _ = self.speed.state(t_grid)
        seg = self.speed.segment(0.5 * (t_grid[:-1] + t_grid[1:])) if t_grid.size > 1 else np.zeros(0, int)
        alpha_step = self.speed.alpha[seg]
        n = t_grid.size
        ap = np.empty((n, len(self.active), self.eo.shape[1]), complex)
        am = np.empty_like(ap)
        start = 0
        while start < n - 1:
            stop = start + 1
            while stop < n - 1 and t_grid[stop + 1] - t_grid[start] <= self._max_span:
                stop += 1
            sl = slice(start, stop + 1)
            ap[sl] = self._envelopes(+1, ap[start] if start else self.a_plus, self.c_plus,
                                     t_grid[sl], phi[sl], om[start + 1:stop + 1], alpha_step[start:stop])
            am[sl] = self._envelopes(-1, am[start] if start else self.a_minus, self.c_minus,
                                     t_grid[sl], phi[sl], om[start + 1:stop + 1], alpha_step[start:stop])
            start = stop
        if n == 1:
            ap[0], am[0] = self.a_plus, self.a_minus
        self.a_plus, self.a_minus, self.t = ap[-1].copy(), am[-1].copy(), float(t_grid[-1])
        mu_p = self.lam[None] - 1j * self.eo[None] * om[:, None, None]
        mu_m = self.lam[None] + 1j * self.eo[None] * om[:, None, None]
        A = ap - np.conj(am)
        dA = (mu_p * ap + self.c_plus[None]) - np.conj(mu_m * am + self.c_minus[None])
        return EnvelopeGrid(t=t_grid, G=self._to_blades(A), dG=self._to_blades(dA),
                            a_plus=ap if keep_modal else None, a_minus=am if keep_modal else None)

    def _to_blades(self, A: np.ndarray) -> np.ndarray:
        """(n, n_act, n_exc) modal envelopes -> (n, n_exc, n_blades, r) blade envelopes."""
        n, _, n_exc = A.shape
        X = A.transpose(0, 2, 1).reshape(n * n_exc, -1)
        out = (X.real @ self.W) + 1j * (X.imag @ self.W)
        return out.reshape(n, n_exc, self.n_blades, self.r)

    def modal_state(self, t: float, t_grid_point: float, a_plus, a_minus) -> np.ndarray:
        """Exact complex modal state ``z`` (n_act,) at ``t`` from envelopes at a grid point.

        Independent of the Hermite interpolation: used by tests as a reference.
        """
        ts = np.array([t_grid_point, t])
        phi, om, _ = self.speed.state(ts)
        al = self.speed.alpha[self.speed.segment(0.5 * (ts[0] + ts[1]))]
        ap = self._envelopes(+1, a_plus, self.c_plus, ts, phi, om[1:], np.array([al]))[-1]
        am = self._envelopes(-1, a_minus, self.c_minus, ts, phi, om[1:], np.array([al]))[-1]
        carrier = np.exp(1j * self.eo * phi[1])
        return np.sum(ap * carrier + am * np.conj(carrier), axis=1)

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

A free response (a start from rest, the jump of the quasi-steady envelope at a speed knot)
turns in the envelope frame at up to ``w_d + EO Omega``: there the grid is refined until it
has decayed (:meth:`EnvelopeIntegrator.transient_grid`, :class:`GridPoints`), so that the
Hermite interpolation stays within :data:`TRANSIENT_TOL_S` in TOA.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from math import factorial

import numpy as np

from .speed import SpeedProfile

__all__ = [
    "QUASI_STEADY_TOL",
    "TRANSIENT_TOL_S",
    "chirp_integral",
    "quasi_steady_envelope",
    "TipBasis",
    "tip_basis",
    "EnvelopeIntegrator",
    "FixedModes",
    "EnvelopeGrid",
    "build_grid",
    "GridPoints",
]



#: Bound on the part of a modal envelope left out by the quasi-steady series, relative to
#: the mode's smallest quasi-steady amplitude ``|c| / |mu|`` over the stretch (one unit in
#: the last place): see :meth:`EnvelopeIntegrator.quasi_steady_terms`.
QUASI_STEADY_TOL = 2.0 ** -52

#: Design bound on the TOA error (s) that the interpolation of a free response may add: the
#: envelope grid is refined where free vibration is present (:meth:`EnvelopeIntegrator.transient_grid`).
TRANSIENT_TOL_S = 1e-12

#: At most this many refined envelope grid points per speed segment (a free response that
#: never decays, e.g. zero damping, would otherwise refine the whole run): beyond it a warning.
MAX_REFINED_POINTS = 2_000_000

_log = logging.getLogger(__name__)

_UNIT_GRID = np.linspace(0.0, 1.0, 400)  # log-spaced sample of a refined stretch (transient_grid)


def quasi_steady_envelope(c, mu, m1) -> np.ndarray:
    """Quasi-steady envelope ``a = c int_0^inf exp(mu x - m1 x^2 / 2) dx`` (no free response).

    With ``mu(t) = mu + m1 (t - t0)`` linear in time (a speed segment of constant acceleration;
    ``m1 = -+ i EO alpha``), this is the solution of ``a' = mu(t) a + c`` that the same linear
    sweep, extended back to ``t = -inf``, leaves at ``t0``: the response of a mode that has been
    forced for ever, including a mode at or near resonance at ``t0`` (finite for any damping
    ``Re mu < 0``; at ``m1 = 0`` the harmonic steady state ``-c / mu``).

    Far from resonance (``q = m1 / mu^2`` small) the asymptotic series
    ``a = -(c / mu) sum_{j<K} (2j - 1)!! (-q)^j`` is summed with the fewest terms ``K <= 8``
    whose first omitted term ``(2K - 1)!! |q|^K`` is below 2^-53; elsewhere the closed form
    ``a = c sqrt(pi) / (2 s) w(-i mu / (2 s))``, ``s = sqrt(m1 / 2)`` (principal root),
    ``w`` the Faddeeva function (``scipy.special.wofz``, relative accuracy ~1e-13).

    Parameters
    ----------
    c, mu, m1 : array_like, complex
        Broadcast together; ``Re mu <= 0``, ``Re m1 = 0``.

    Returns
    -------
    ndarray, complex
        ``inf`` / ``nan`` where no steady state exists (undamped at resonance on a dwell).
    """
    c, mu, m1 = np.broadcast_arrays(*(np.asarray(x, complex) for x in (c, mu, m1)))
    out = np.empty(c.shape, complex)
    with np.errstate(all="ignore"):
        q = m1 / (mu * mu)
        aq = np.abs(q)
        K = np.zeros(c.shape, int)
        bound = np.ones(c.shape)
        for k in range(1, 9):
            bound = bound * (2 * k - 1) * aq
            K[(K == 0) & (bound <= 2.0 ** -53)] = k
        series = (K > 0) | (m1 == 0)
        S = np.ones(c.shape, complex)
        for j in range(int(K.max(initial=1)) - 1, 0, -1):  # Horner: sum_j (2j-1)!! (-q)^j
            S = np.where(j < K, 1.0 + S * ((2 * j - 1) * -q), S)
        out[series] = (-c / mu * S)[series]
        rest = ~series
        if np.any(rest):
            from scipy.special import wofz  # only near a resonance (the default run never needs it)

            s = np.sqrt(0.5 * m1[rest])
            out[rest] = c[rest] * np.sqrt(np.pi) / (2.0 * s) * wofz(-1j * mu[rest] / (2.0 * s))
    return out


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


def j_moments(u: np.ndarray, kmax: int, vabs: np.ndarray | float = 0.0) -> np.ndarray:
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
    J = j_moments(u, 2 * (n_v - 1), np.abs(v))
    out = J[..., 0] * np.ones(np.broadcast(u, v).shape)
    vn = np.ones_like(out)
    for n in range(1, n_v):
        vn = vn * v
        out = out + vn * J[..., 2 * n] / factorial(n)
    return out


def _chirp_given_exp(u: np.ndarray, eu: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``I(u, v) = int_0^1 exp(u x + v x^2) dx`` with ``exp(u)`` supplied (``eu``).

    The same sums as :func:`chirp_integral` -- ``I = sum_n v^n / n! J_2n(u)`` with the
    moments ``J_k`` by the forward recurrence ``J_k = (e^u - k J_k-1) / u`` wherever
    ``|u| >= 1/4`` and ``|v| <= |u|^2 / 10`` (round-off stays at the level of ``e^u``,
    see :func:`j_moments`) -- but ``e^u`` is given: the recursion forms it as a product of
    per-mode and per-step factors (two roundings instead of a complex exponential).
    Elsewhere (``|u| < 0.32`` there) the Taylor series of the integrand,
    ``I = sum_m c_m / (m + 1)`` with ``(m + 1) c_m+1 = u c_m + 2 v c_m-1``, is summed to
    round-off.

    Parameters
    ----------
    u, eu : ndarray, complex
        ``u`` and ``exp(u)`` (same shape).
    v : ndarray, complex
        Broadcastable to ``u``; ``|v| < 1e-2``.
    """
    vabs = np.abs(v)
    vmax = float(np.max(vabs)) if vabs.size else 0.0
    n_v = 1
    while vmax ** n_v / factorial(n_v) > 1e-18 and n_v < 12:
        n_v += 1
    with np.errstate(all="ignore"):
        inv = np.divide(1.0, u)
        j = np.subtract(eu, 1.0)
        j *= inv  # J_0
        if n_v == 1:
            out = j
        else:
            even = [j.copy()]
            tmp = np.empty_like(j)
            for k in range(1, 2 * n_v - 1):
                np.multiply(j, -float(k), out=tmp)
                tmp += eu
                np.multiply(tmp, inv, out=j)
                if k % 2 == 0:
                    even.append(j.copy())
            out = even[-1]
            for n in range(n_v - 1, 0, -1):  # Horner in v: sum_n v^n / n! J_2n
                out *= v / n
                out += even[n - 1]
    au2 = np.multiply(u.real, u.real)
    au2 += u.imag * u.imag
    series = au2 < 0.0625
    if vmax > 0.0:
        series |= np.broadcast_to(vabs, u.shape) > 0.1 * au2
    idx = np.flatnonzero(series)
    if idx.size:
        us = u.ravel()[idx]
        vs = np.broadcast_to(v, u.shape).ravel()[idx]
        # terms of e^{u x + v x^2} are below those of e^{(|u| + |v|) x} (|x| <= 1)
        radius = float(np.max(np.abs(us) + np.abs(vs)))
        n_terms = 4
        while radius ** n_terms / factorial(n_terms) > 1e-18:
            n_terms += 1
        c_prev = np.zeros_like(us)
        c = np.ones_like(us)
        acc = np.ones_like(us)
        for m in range(1, n_terms + 2):
            c_prev, c = c, (us * c + 2.0 * vs * c_prev) / m
            acc += c / (m + 1)
        out.ravel()[idx] = acc
    return out


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


class FixedModes:
    """The modal path of a model whose modes do not change with speed: the tip basis of its
    tip shapes and an :class:`EnvelopeIntegrator` of any carriers (non-synchronous ones too)."""

    nonsynchronous = True

    def __init__(self, model) -> None:
        self.model = model
        self.basis = tip_basis(model.tip_shapes)

    def integrator(self, carriers, excitations, speed: SpeedProfile, initial: str) -> EnvelopeIntegrator:
        """The integrator of the forced ``carriers`` (:class:`~bttsim_stream.sim.sources.Carriers`)."""
        m = self.model
        return EnvelopeIntegrator(m.freq_hz, m.damping_ratio, carriers.C, carriers.eo, self.basis, speed,
                                  initial=initial, omega=carriers.omega)


class GridPoints:
    """The envelope grid of :func:`build_grid`, point by point on demand (memory independent of
    the run's length): uniform steps <= ``h_max`` in every speed segment, knots included, after
    an optional refined start of the segment.

    Parameters
    ----------
    speed : SpeedProfile
    h_max : float
        Largest step, s.
    refine : dict of int -> ndarray, optional
        Per speed segment ``k``, increasing grid points from the segment's first knot
        ``t_s[k]`` (included) over the stretch where a free response needs shorter steps
        (:meth:`EnvelopeIntegrator.transient_grid`); the segment continues from the last of
        them in uniform steps <= ``h_max``. Without it, the plain uniform grid.
    """

    def __init__(self, speed: SpeedProfile, h_max: float, refine: dict | None = None) -> None:
        t = speed.t_s
        n_seg = t.size - 1
        refine = refine or {}
        pieces = [np.asarray(refine.get(k, t[k:k + 1]), float) for k in range(n_seg)]
        for k, r in enumerate(pieces):
            if r.size < 1 or r[0] != t[k] or np.any(np.diff(r) <= 0) or r[-1] >= t[k + 1]:
                raise ValueError("refined grid points must increase from their segment's first knot")
        self._nref = np.array([r.size - 1 for r in pieces], np.int64)  # refined points before u0
        self._ref = np.concatenate([r[:-1] for r in pieces] + [np.zeros(1)])
        self._roff = np.concatenate(([0], np.cumsum(self._nref)))[:-1]
        self._t0 = np.array([r[-1] for r in pieces])  # start of each segment's uniform part
        self._tk = t[:-1]
        self._t1 = t[1:]
        self._n = np.maximum(1, np.ceil((self._t1 - self._t0) / h_max - 1e-9).astype(np.int64))
        self._off = np.concatenate(([0], np.cumsum(self._n + self._nref)))  # first point of each segment
        self._end = float(t[-1])
        #: number of grid points
        self.size = int(self._off[-1]) + 1

    @property
    def refined(self) -> int:
        """Number of refined grid points (0: the plain uniform grid)."""
        return int(np.sum(self._nref))

    def points(self, start: int, stop: int) -> np.ndarray:
        """Grid points ``start .. stop - 1`` (the same numbers as ``build_grid(...)[start:stop]``)."""
        j = np.arange(max(start, 0), min(stop, self.size))
        out = np.empty(j.size)
        last = j == self.size - 1
        jj = j[~last]
        k = np.searchsorted(self._off, jj, side="right") - 1
        n = self._n[k]
        t0 = self._t0[k]
        nref = self._nref[k]
        loc = jj - self._off[k]
        out[~last] = t0 + (self._t1[k] - t0) * (loc - nref) / n
        if self._ref.size > 1:
            is_ref = loc < nref
            if np.any(is_ref):
                out[np.flatnonzero(~last)[is_ref]] = self._ref[self._roff[k[is_ref]] + loc[is_ref]]
        out[last] = self._end
        return out

    def _point(self, j: int) -> float:
        """Grid point ``j`` as a Python float (the arithmetic of :meth:`points`)."""
        if j >= self.size - 1:
            return self._end
        k = int(np.searchsorted(self._off, j, side="right")) - 1
        loc, nref = j - int(self._off[k]), int(self._nref[k])
        if loc < nref:  # a refined point
            return float(self._ref[int(self._roff[k]) + loc])
        t0 = float(self._t0[k])
        return t0 + (float(self._t1[k]) - t0) * (loc - nref) / int(self._n[k])

    def searchsorted(self, t: float) -> int:
        """``np.searchsorted(build_grid(...), t)``: the first point >= ``t``."""
        if t > self._end:
            return self.size
        k = int(np.clip(np.searchsorted(self._tk, t, side="right") - 1, 0, self._tk.size - 1))
        t0, nref, off = float(self._t0[k]), int(self._nref[k]), int(self._off[k])
        if t < t0:  # in the refined start of the segment
            roff = int(self._roff[k])
            i = off + int(np.searchsorted(self._ref[roff:roff + nref], t))
        else:
            i = off + nref + int(np.floor((t - t0) / (float(self._t1[k]) - t0) * int(self._n[k])))
        i = max(0, min(i, self.size - 1))
        while i > 0 and self._point(i - 1) >= t:  # (only if the estimate was off)
            i -= 1
        while i < self.size and self._point(i) < t:
            i += 1
        return i


def build_grid(speed: SpeedProfile, h_max: float, refine: dict | None = None) -> np.ndarray:
    """Envelope grid: uniform steps <= ``h_max`` in every speed segment, knots included (after
    the refined points ``refine`` of :class:`GridPoints`, if any)."""
    if refine:
        g = GridPoints(speed, h_max, refine)
        return g.points(0, g.size)
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


def refine_pass(k: int, t_k: float, t_end: float, zone: float, amp: float, reach_m: float, radius_m: float,
                 om_min: float, sig: np.ndarray, S0: np.ndarray, tol_s: float, h_max: float, warn: bool,
                 warnings: list) -> tuple[np.ndarray, float | None]:
    """One pass of a speed segment's refinement (:meth:`EnvelopeIntegrator.transient_grid`).

    From the free response's amplitude bound ``amp`` (m) over the refined stretch ``zone``
    (s after the knot ``t_k``), its decay rates ``sig`` and fourth-derivative weights ``S0``,
    the grid points from ``t_k`` on whose Hermite steps meet ``tol_s`` in TOA; and the new
    stretch they cover (None: no further pass would change them). ``warn``: report (in
    ``warnings``) a response that does not decay within :data:`MAX_REFINED_POINTS`.
    """
    D = (amp + reach_m) / (radius_m * om_min)
    tol_m = tol_s * radius_m * om_min

    def step(sv, D=D, tol_m=tol_m):
        """The step the bound allows at ``sv`` (s after the knot)."""
        S = np.exp(-sig[None, :] * sv[:, None]) @ S0
        with np.errstate(divide="ignore", over="ignore"):
            G = tol_m / S
            h1 = 2.0 * G**0.25
            h2 = np.sqrt(G) / D - D if D > 0 else np.full(sv.shape, np.inf)
        # steps below D cannot lower the extrapolation term (D^4 may alone exceed the
        # bound: D is overestimated, from the steady amplitudes); the interpolation
        # term is always met
        return np.maximum(np.minimum(h1, np.maximum(h2, D)), 1e-6)

    span = t_end - t_k
    h0 = float(step(np.zeros(1))[0])
    if not h0 < h_max:
        return np.array([t_k]), None
    # the step grows as the free response decays: steps h(s) by inverting
    # n(s) = int_0^s ds' / h(s') (h varies by < 1 % over a step)
    s_lo = min(h0 / 4.0, span)
    sv = np.concatenate(([0.0], s_lo * np.exp(np.log(span / s_lo) * _UNIT_GRID)))
    hv = step(sv)
    done = np.flatnonzero(hv >= h_max)
    if done.size:
        sv, hv = sv[:done[0] + 1], hv[:done[0] + 1]
    n_of_s = np.concatenate(([0.0], np.cumsum(np.diff(sv) * 0.5 * (1.0 / hv[1:] + 1.0 / hv[:-1]))))
    n_pts = int(np.floor(n_of_s[-1]))
    if warn and n_pts > MAX_REFINED_POINTS:
        msg = (f"speed segment {k}: the free response does not decay within "
               f"{MAX_REFINED_POINTS:,} refined envelope steps; later TOAs may differ from the exact "
               f"ones by more than {tol_s:g} s")
        warnings.append(msg)
        _log.warning(msg)
    n_pts = min(n_pts, MAX_REFINED_POINTS)
    s_pts = np.interp(np.arange(n_pts + 1, dtype=float), n_of_s, sv)
    pts = t_k + s_pts
    pts = pts[pts < t_end]
    if pts.size > 1:
        pts = pts[np.concatenate(([True], np.diff(pts) > 0))]
    zone_new = float(s_pts[-1]) if pts.size > 1 else 0.0
    if pts.size == 1 or zone_new >= 0.5 * zone:  # D would hardly change
        return pts, None
    return pts, zone_new


class EnvelopeIntegrator:
    """Exact, streaming integration of the modal envelopes along the grid.

    Modes with no modal force from any excitation (and so no response) are skipped.

    Parameters
    ----------
    freq_hz, damping_ratio : ndarray, shape (n_modes,)
    C : ndarray, shape (n_modes, n_exc), complex
        Modal force amplitudes (:func:`~bttsim_stream.sim.forcing.modal_forcing`).
    eo : ndarray, shape (n_exc,)
    basis : TipBasis
    speed : SpeedProfile
    initial : {"steady", "rest"}
        ``"steady"`` starts every (mode, carrier) column in its quasi-steady envelope
        (:func:`quasi_steady_envelope`: the state the first speed segment's sweep, extended
        back in time, leaves at t = 0, at or near resonance too); ``"rest"`` starts at rest.
    quasi_steady : bool
        Take the quasi-steady series where it is exact to round-off
        (:meth:`quasi_steady_terms`); False: the exact recursion everywhere (the reference
        of the tests).
    omega : ndarray, shape (n_exc,), optional
        Constant part of each carrier's frequency in the rotor frame, rad/s: excitation
        ``m`` is ``Im(C_km exp(i theta_m(t)))`` with the carrier phase
        ``theta_m(t) = EO_m phi(t) + omega_m t`` (non-synchronous forcing,
        :mod:`bttsim_stream.sim.nsv`; ``EO_m`` need not be an integer). The envelope
        equations keep their form with ``EO Omega(t)`` replaced by ``EO Omega(t) + omega``:
        ``mu = lambda -+ i (EO Omega + omega)``, the phase step ``EO dphi + omega h``; the
        chirp term ``v`` and the quasi-steady slope ``m1`` do not change, so the recursion
        and the quasi-steady series stay exact. None (default): all zero, the engine-order
        carriers of the paper (and the same arithmetic, bit for bit).
    """

    def __init__(self, freq_hz, damping_ratio, C, eo, basis: TipBasis, speed: SpeedProfile,
                 initial: str = "steady", quasi_steady: bool = True, omega=None) -> None:
        self.quasi_steady = bool(quasi_steady)
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
        # both carriers side by side (+ for every excitation, then -)
        self._lam_row = self.lam[:, 0]
        self._eo_s = np.concatenate([self.eo[0], -self.eo[0]])
        self._c_s = np.concatenate([self.c_plus, self.c_minus], axis=1)
        om_c = None if omega is None else np.asarray(omega, float).reshape(-1)
        if om_c is not None and not np.any(om_c):
            om_c = None  # engine-order carriers only: the paper's arithmetic
        #: constant carrier frequencies (n_exc,), rad/s, or None (all zero)
        self.omega = om_c
        self._om_s = None if om_c is None else np.concatenate([om_c, -om_c])
        n_b, r = basis.psi.shape[1:]
        self.n_blades, self.r = n_b, r
        self.W = np.ascontiguousarray((basis.psi[active] / wd[:, None, None]).reshape(len(self.active), n_b * r))
        self.speed = speed
        self.t = 0.0
        #: one-line warnings about the initial state and the transient step control
        self.warnings: list[str] = []
        self._zw = zeta * w
        self._wd = wd
        phi0, om0, al0 = (float(x) for x in speed.state(0.0))
        self.a_plus = self._initial(self.c_plus, om0, al0, +1, initial)
        self.a_minus = self._initial(self.c_minus, om0, al0, -1, initial)
        # columns (mode k, carrier c) flattened as k * n_car + c
        n_car = self._eo_s.size
        self._k_col = np.repeat(np.arange(len(self.active)), n_car)
        self._car_col = np.tile(np.arange(n_car), len(self.active))
        self._lam_col = self._lam_row[self._k_col]
        self._eo_col = self._eo_s[self._car_col]
        self._ieo_col = 1j * self._eo_col
        self._om_col = None if self._om_s is None else self._om_s[self._car_col]
        self._c_col = self._c_s.ravel()
        self._zw_col = (zeta * w)[self._k_col]
        self._cabs_col = np.abs(self._c_col)
        #: per advance: columns integrated by the quasi-steady series / by the exact recursion
        self.stats = {"quasi_steady": 0, "exact": 0}

    def _initial(self, c, omega, alpha, sign, initial):
        """Envelopes at t = 0: zero (``"rest"``) or the quasi-steady envelopes
        (:func:`quasi_steady_envelope` with ``mu = lambda -+ i EO Omega(0)``,
        ``m1 = -+ i EO alpha(0)``): the state the first speed segment's sweep, extended back in
        time, leaves at t = 0 -- at resonance too. A mode with no steady state (undamped, at
        resonance on a dwell) starts at rest, with a warning."""
        if initial not in ("steady", "rest"):
            raise ValueError(f"initial must be 'steady' or 'rest', got {initial!r}")
        if initial == "rest" or c.size == 0:
            return np.zeros_like(c)
        if self.omega is None:
            mu = self.lam - sign * 1j * self.eo * omega
        else:
            mu = self.lam - sign * 1j * (self.eo * omega + self.omega[None, :])
        a = quasi_steady_envelope(c, mu, -sign * 1j * self.eo * alpha)
        bad = ~np.isfinite(a)
        if np.any(bad):
            modes = sorted({int(k) for k in self.active[np.nonzero(bad)[0]]})
            msg = (f"initial = \"steady\": mode(s) {modes} have no steady state at the start speed (undamped "
                   f"at resonance on a dwell); they start at rest")
            self.warnings.append(msg)
            _log.warning(msg)
            a = np.where(bad, 0.0, a)
        return a

    def transient_grid(self, h_max: float, radius_m: float, reach_m: float = 0.0,
                       tol_s: float = TRANSIENT_TOL_S) -> dict:
        """Refined envelope grid points where a free response needs them (for :class:`GridPoints`).

        Within a speed segment (``mu = lambda -+ i EO Omega(t)`` linear in time) every column's
        envelope is its quasi-steady part (:func:`quasi_steady_envelope`, smooth on the scale of
        the sweep) plus a free response ``e(t) = e_k exp(int mu)``, which turns at
        ``|Im mu|`` -- up to ``w_d + EO Omega`` -- and decays as ``exp(-zeta w (t - t_k))``. The
        cubic Hermite interpolant of ``e`` over a step ``h`` (exact values and derivatives at
        both ends), evaluated at ``tau`` from the step's start, errs by at most
        ``|e| |mu|^4 tau^2 (tau - h)^2 / 24``; a crossing is evaluated up to ``D`` outside its
        step (the deflection and the candidate tip nodes' angular offset over the tip speed,
        ``D = (A + reach) / (R Omega)``), so the bound is
        ``sum_cols |W| |e| |mu|^4 max((h / 2)^4, D^2 (h + D)^2) / 24 <= tol_s R Omega`` (a TOA
        error of ``tol_s`` at the tip speed ``R Omega``), with ``|W|`` the column's largest
        tip-node displacement per unit envelope. The grid steps ``h(t)`` solve it from the
        segment's first knot until they reach ``h_max`` (the free response has decayed).

        ``e_k``: at t = 0 the initial envelope minus the quasi-steady one (zero for
        ``initial = "steady"``, the whole quasi-steady envelope from rest); at a speed knot the
        previous free response, decayed, plus the jump of the quasi-steady envelope between
        the two accelerations (its value and slope stay continuous).

        Parameters
        ----------
        h_max : float
            The grid's uniform step, s.
        radius_m : float
            Tip radius ``R``, m.
        reach_m : float
            Largest tangential distance of a candidate tip node from P_nom, m.
        tol_s : float
            TOA error bound, s.

        Returns
        -------
        dict of int -> ndarray
            Per segment with a transient, its refined points from its first knot.
        """
        sp = self.speed
        T, Om, al = sp.t_s, sp.omega, sp.alpha
        n_act = self.active.size
        out: dict = {}
        if n_act == 0:
            return out
        eo_s = self._eo_col
        lam = self._lam_col
        sig = self._zw_col
        c = self._c_col
        wn = np.max(np.linalg.norm(self.W.reshape(n_act, self.n_blades, self.r), axis=2), axis=1)[self._k_col]
        a0 = np.concatenate([self.a_plus, self.a_minus], axis=1).ravel()

        om_col = self._om_col

        def mu_at(om):
            return lam - 1j * eo_s * om if om_col is None else lam - 1j * (eo_s * om + om_col)

        def qs(om, alpha):
            return quasi_steady_envelope(c, mu_at(om), -1j * eo_s * alpha)

        n_seg = T.size - 1
        with np.errstate(all="ignore"):
            e = np.abs(a0 - qs(Om[0], al[0]))
            # jumps of the quasi-steady envelope at the inner knots, all at once
            om_in = Om[1:n_seg][:, None]
            jump = np.abs(qs(om_in, al[:n_seg - 1][:, None]) - qs(om_in, al[1:n_seg][:, None]))
            decay = np.exp(-sig[None, :] * np.diff(T[:n_seg])[:, None])
            for k in range(n_seg):
                if k > 0:
                    e = e * decay[k - 1] + jump[k - 1]
                e = np.where(np.isfinite(e), e, 0.0)
                if not np.any(e * wn > 0):
                    continue
                pts = self._refine_segment(k, e, wn, h_max, radius_m, reach_m, tol_s)
                if pts.size > 1:
                    out[k] = pts
        return out

    def _refine_segment(self, k, e, wn, h_max, radius_m, reach_m, tol_s) -> np.ndarray:
        """Refined points of speed segment ``k`` from its first knot (see :meth:`transient_grid`)."""
        sp = self.speed
        t_k, t_end = float(sp.t_s[k]), float(sp.t_s[k + 1])
        om_k, alpha = float(sp.omega[k]), float(sp.alpha[k])
        eo_s, sig, c = self._eo_col, self._zw_col, self._c_col
        # lambda shifted by the constant carrier frequencies: mu = lam - i EO Omega
        lam = self._lam_col if self._om_col is None else self._lam_col - 1j * self._om_col
        mu_abs = np.maximum(np.abs(lam - 1j * eo_s * om_k), np.abs(lam - 1j * eo_s * float(sp.omega[k + 1])))
        S0 = wn * e * mu_abs**4 / 24.0
        zone = t_end - t_k
        pts = np.array([t_k])
        for _ in range(2):  # the reach D from the amplitudes over the refined stretch
            om_a, om_b = om_k, om_k + alpha * zone
            im_a, im_b = (lam - 1j * eo_s * om_a).imag, (lam - 1j * eo_s * om_b).imag
            mu_min = np.where(im_a * im_b <= 0, sig, np.minimum(np.abs(lam - 1j * eo_s * om_a),
                                                                np.abs(lam - 1j * eo_s * om_b)))
            with np.errstate(divide="ignore"):
                amp = float(np.sum(wn * (np.abs(c) / mu_min + e)))
            om_min = min(om_a, om_b)
            amp = min(amp, 0.05 * radius_m)  # larger amplitudes are refused (check_tip_amplitude)
            pts, zone = refine_pass(k, t_k, t_end, zone, amp, reach_m, radius_m, om_min, sig, S0, tol_s, h_max,
                                     _ == 1, self.warnings)
            if zone is None:
                break
        return pts

    def _envelopes(self, sign, a0, c, t, phi, om_end, alpha):
        """Exact envelopes at grid times ``t`` (t[0] = current time) for one carrier."""
        lam, eo = self.lam[None], self.eo[None]  # (1, n_act, 1), (1, 1, n_exc)
        h = np.diff(t)[:, None, None]
        om_c = 0.0 if self.omega is None else self.omega[None, None, :]
        L = lam * (t - t[0])[:, None, None] - sign * 1j * (eo * (phi - phi[0])[:, None, None]
                                                           + om_c * (t - t[0])[:, None, None])
        u = (lam - sign * 1j * (eo * om_end[:, None, None] + om_c)) * h
        v = sign * 0.5j * eo * alpha[:, None, None] * h * h
        g = c[None] * h * chirp_integral(u, v)  # (n-1, n_act, n_exc)
        acc = np.concatenate([np.zeros_like(g[:1]), np.cumsum(g * np.exp(-L[1:]), axis=0)])
        return np.exp(L) * (a0[None] + acc)

    def advance(self, t_grid: np.ndarray, keep_modal: bool = False, out: np.ndarray | None = None,
                first: int = 0):
        """Integrate from the current time (``t_grid[0]``) over ``t_grid``; return envelopes.

        ``t_grid`` must come from :func:`build_grid` (no step straddles a speed knot).

        Both carriers of every excitation are advanced together, speed segment by speed
        segment (:meth:`_run`): the quasi-steady series where it is exact to round-off, the
        exact recursion elsewhere. The modal envelopes are then summed into blade envelopes
        ``G = sum_k Psi_k (a_+ - conj(a_-))_k / w_dk`` and their exact derivatives
        ``dG = sum_k Psi_k ((mu_+ a_+ + c_+) - conj(mu_- a_- + c_-))_k / w_dk``.

        Parameters
        ----------
        t_grid : ndarray, shape (n,)
        keep_modal : bool
            Keep the modal envelopes in the result (for tests).
        out : ndarray, shape (2, n_exc, 2, n - first, n_blades * r), optional
            Receives ``G`` and ``dG`` (real and imaginary parts) at ``t_grid[first:]`` (any
            strides); nothing is returned then.
        first : int
            First grid point written to ``out``.

        Returns
        -------
        EnvelopeGrid or None
        """
        t_grid = np.asarray(t_grid, float)
        if abs(t_grid[0] - self.t) > 1e-12 * max(1.0, abs(self.t)):
            raise ValueError("advance() must start at the integrator's current time")
        phi, om, _ = self.speed.state(t_grid)
        n = t_grid.size
        n_exc = self.eo.shape[1]
        A = np.empty((n, len(self.active), 2 * n_exc), complex)
        A[0, :, :n_exc] = self.a_plus
        A[0, :, n_exc:] = self.a_minus
        # columns (mode k, carrier c) flattened: the broadcasts run along whole rows
        mu2 = self._lam_col[None, :] - self._ieo_col[None, :] * om[:, None]
        if self._om_col is not None:
            mu2 -= 1j * self._om_col[None, :]
        mu = mu2.reshape(n, len(self.active), 2 * n_exc)
        if n > 1:
            seg = self.speed.segment(0.5 * (t_grid[:-1] + t_grid[1:]))
            A2 = A.reshape(n, -1)
            for start, stop in self._segments(seg):
                self._run(A2, start, stop, t_grid, phi, om, mu2, float(self.speed.alpha[seg[start]]))
        self.a_plus, self.a_minus = A[-1, :, :n_exc].copy(), A[-1, :, n_exc:].copy()
        self.t = float(t_grid[-1])
        if out is not None:
            # G = a_+ - conj(a_-) and dG = (mu a + c)_+ - conj(mu a + c)_-, formed straight
            # into contiguous real and imaginary planes for the matrix products; the products
            # write each plane of ``out`` directly when it is contiguous, else a contiguous
            # array that is then copied into it (the small-matrix kernels' strided stores
            # into memory out of cache cost several times the product; same values)
            D = mu[first:] * A[first:]
            D += self._c_s[None]
            tmp = np.empty((out.shape[3], self.W.shape[1]))
            for g, X in enumerate((A[first:], D)):
                for m in range(n_exc):
                    Xp, Xm = X[:, :, m], X[:, :, n_exc + m]
                    for c, Y in enumerate((np.subtract(Xp.real, Xm.real), np.add(Xp.imag, Xm.imag))):
                        if out[g, m, c].flags.c_contiguous:
                            np.matmul(Y, self.W, out=out[g, m, c])
                        else:
                            np.matmul(Y, self.W, out=tmp)
                            out[g, m, c] = tmp
            return None
        D = mu * A
        D += self._c_s[None]
        Ap, Am = A[..., :n_exc], A[..., n_exc:]
        XG = Ap - np.conj(Am)  # (n, n_act, n_exc)
        XD = D[..., :n_exc] - np.conj(D[..., n_exc:])
        X = np.stack([XG, XD], axis=1)  # (n, 2, n_act, n_exc)
        GD = self._to_blades(X.transpose(0, 1, 3, 2).reshape(n * 2 * n_exc, -1))  # (n * 2 * n_exc, nb * r)
        GD = GD.reshape(n, 2, n_exc, self.n_blades, self.r)
        return EnvelopeGrid(t=t_grid, G=GD[:, 0], dG=GD[:, 1],
                            a_plus=Ap.copy() if keep_modal else None,
                            a_minus=Am.copy() if keep_modal else None)

    @staticmethod
    def _segments(seg: np.ndarray):
        """Step ranges ``[start, stop)`` within one speed segment (constant acceleration)."""
        cuts = np.flatnonzero(np.diff(seg)) + 1
        bounds = np.concatenate(([0], cuts, [seg.size])).tolist()
        return list(zip(bounds[:-1], bounds[1:]))

    @staticmethod
    def _spans(t: np.ndarray, start: int, stop: int, span: float):
        """Split steps ``[start, stop)`` into ranges no longer than ``span`` seconds (one step
        at least)."""
        k = start
        while k < stop:
            end = k + 1 + int(np.searchsorted(t[k + 1:stop + 1], t[k] + span, side="right"))
            end = min(max(end - 1, k + 1), stop)
            yield k, end
            k = end

    def quasi_steady_terms(self, mu: np.ndarray, alpha: float) -> np.ndarray:
        """Terms of the quasi-steady series each column needs over a stretch (0: none suffices).

        Over a stretch of one speed segment, ``mu = lambda -+ i EO Omega(t)`` is linear in
        time with slope ``m1 = -+ i EO alpha``. The series
        ``a_p = -(c / mu) sum_{j<K} (2j - 1)!! (-q)^j``, ``q = m1 / mu^2``, satisfies
        ``a_p' = mu a_p + c + mu a_K`` with ``a_K`` its first omitted term, so the exact
        envelope is ``a = a_p + e`` with ``e' = mu e - mu a_K``: ``e`` is the homogeneous
        solution from ``a(t_start) - a_p(t_start)`` plus at most
        ``|c| (2K - 1)!! q_max^K / (zeta w)`` (``Re mu = -zeta w``). ``K`` is the smallest
        number of terms (at most 8) for which that bound is below :data:`QUASI_STEADY_TOL`
        times the column's smallest quasi-steady amplitude ``|c| / |mu|_max``.

        Parameters
        ----------
        mu : ndarray, complex, shape (n, n_cols)
            ``mu`` of every column at the stretch's grid points.
        alpha : float
            Angular acceleration of the segment, rad/s^2.
        """
        K, _ = self._quasi_steady_terms(mu, alpha)
        return K

    def _quasi_steady_terms(self, mu: np.ndarray, alpha: float):
        """:meth:`quasi_steady_terms` and ``|mu|_max`` of every column."""
        amu2 = mu.real * mu.real
        amu2 += mu.imag * mu.imag
        mn, mx = amu2.min(axis=0), np.sqrt(amu2.max(axis=0))
        q = np.abs(self._eo_col) * abs(alpha) / mn
        K = np.zeros(q.shape, int)
        with np.errstate(divide="ignore"):  # an undamped mode: no bound (inf), never quasi-steady
            bound = mx / self._zw_col
        for k in range(1, 9):
            bound *= (2 * k - 1) * q  # (2k - 1)!! q^k |mu|_max / (zeta w)
            K[(K == 0) & (bound <= QUASI_STEADY_TOL)] = k
        return K, mx

    def _run(self, A, start, stop, t, phi, om, mu, alpha):
        """The envelopes over the steps ``start .. stop`` of one speed segment (in place in
        ``A``, shape (n, n_cols)): quasi-steady series where :meth:`quasi_steady_terms`
        allows (plus the exact homogeneous part where it is not negligible), the exact
        recursion (:meth:`_run_exact`) elsewhere."""
        mu_s = mu[start:stop + 1]
        if self.quasi_steady:
            K, mu_max = self._quasi_steady_terms(mu_s, alpha)
        else:
            K = np.zeros(mu_s.shape[1], int)
        qs = K > 0
        n_qs = int(np.count_nonzero(qs))
        self.stats["quasi_steady"] += n_qs
        self.stats["exact"] += K.size - n_qs
        if n_qs:
            with np.errstate(all="ignore"):
                inv = np.divide(1.0, mu_s)
                mq = inv * inv
                mq *= 1j * self._eo_col * alpha  # -q = -m1 / mu^2, m1 = -i EO_c alpha
                # Horner: sum_j (2j-1)!! (-q)^j (the innermost factor times 1 needs no product)
                j_top = int(K.max()) - 1
                S = np.multiply(mq, float(2 * j_top - 1)) if j_top > 0 else np.ones_like(mq)
                if j_top > 0:
                    S += 1.0
                for j in range(j_top - 1, 0, -1):
                    if j > 1:
                        S *= (2 * j - 1) * mq
                    else:
                        S *= mq
                    S += 1.0
                ap = inv
                ap *= -self._c_col
                ap *= S  # (N + 1, n_cols)
            e0 = A[start] - ap[0]
            A[start + 1:stop + 1] = ap[1:]
            # the homogeneous part from a(t_start) - a_p(t_start), where it is not negligible
            keep = qs & (np.abs(e0) * mu_max > QUASI_STEADY_TOL * self._cabs_col)
            cols = np.flatnonzero(keep)
            if cols.size:
                E, Phi = self._propagators(cols, t[start:stop + 1], self._dphi(t, start, stop))
                A[start + 1:stop + 1, cols] += (E[1:] * Phi[1:]) * e0[cols]
        if n_qs < K.size:
            cols = np.flatnonzero(~qs) if n_qs else slice(None)
            # longest stretch keeping exp(-lambda (t - t_start)) of these columns in range
            span = 400.0 / max(float(np.max(self._zw_col[cols])), 1e-9)
            for a, b in self._spans(t, start, stop, span):
                self._run_exact(A, cols, a, b, t, phi, om, alpha)

    def _dphi(self, t, start, stop):
        """Rotor angle turned from ``t[start]`` at ``t[start:stop + 1]``, formed without the
        large rotor angles (:meth:`SpeedProfile.angle_change`): phase steps from rounded
        rotor angles would carry their absolute error (1e-12 rad and more) into every step."""
        return self.speed.angle_change(t[start], t[start:stop + 1])[0]

    def _propagators(self, cols, ts, dphi):
        """``exp(lambda (t - t_0))`` and ``exp(-+ i EO (phi - phi_0))`` of columns ``cols``."""
        k = self._k_col[cols]
        car = self._car_col[cols]
        modes, inv_k = np.unique(k, return_inverse=True)
        E = np.exp(self._lam_row[modes][None, :] * (ts - ts[0])[:, None])[:, inv_k]
        if self._om_s is None:
            Phi = np.exp(-1j * self._eo_s[None, :] * dphi[:, None])[:, car]
        else:
            Phi = np.exp(-1j * (self._eo_s[None, :] * dphi[:, None]
                                + self._om_s[None, :] * (ts - ts[0])[:, None]))[:, car]
        return E, Phi

    def _run_exact(self, A, cols, start, stop, t, phi, om, alpha):
        """Exact recursion over the steps ``start .. stop`` of one speed segment for the
        columns ``cols`` of ``A`` (in place).

        ``a_n = exp(lambda h_n) P_n a_n-1 + c h_n I(u_n, v_n)`` summed in closed form as
        ``a_n = E_n Phi_n (a_0 + sum_j E_j^-1 conj(Phi_j) c h_j I_j)`` with
        ``E_n = exp(lambda (t_n - t_0))`` and ``Phi_n = exp(-+ i EO (phi_n - phi_0))``; every
        step uses its own length ``h_n = t_n - t_n-1`` (grid times are rounded: the steps
        differ in their last digits), so the recursion is consistent with the grid times at
        which the envelopes are interpolated.
        """
        allc = isinstance(cols, slice)
        idx = np.arange(self._c_col.size) if allc else cols
        k = self._k_col[idx]
        car = self._car_col[idx]
        lam = self._lam_col[idx]
        eo = self._eo_col[idx]
        ts = t[start:stop + 1]
        h = np.diff(ts)  # (N,)
        h0 = float(h[0])
        modes, inv_k = np.unique(k, return_inverse=True)
        lam_m = self._lam_row[modes]
        E = np.exp(lam_m[None, :] * (ts - ts[0])[:, None])[:, inv_k]  # (N+1, Q)
        Einv = 1.0 / E[1:]
        om_end = om[start + 1:stop + 1]
        if self._om_s is None:
            Phi = np.exp(-1j * self._eo_s[None, :] * self._dphi(t, start, stop)[:, None])[:, car]
            rot = np.exp(-1j * self._eo_s[None, :] * (om_end * h)[:, None])[:, car]  # (N, Q)
        else:  # carrier phase EO phi + omega t
            Phi = np.exp(-1j * (self._eo_s[None, :] * self._dphi(t, start, stop)[:, None]
                                + self._om_s[None, :] * (ts - ts[0])[:, None]))[:, car]
            rot = np.exp(-1j * (self._eo_s[None, :] * om_end[:, None] + self._om_s[None, :]) * h[:, None])[:, car]
        if float(np.max(np.abs(h - h0))) * float(np.max(np.abs(lam_m))) <= 1e-8:
            # a uniform stretch (the steps differ in their last digits only):
            # exp(lambda h_n) = exp(lambda h_0) (1 + lambda (h_n - h_0)), |lambda (h_n - h_0)|
            # <= 1e-8, the omitted (lambda (h_n - h_0))^2 / 2 below round-off
            elh = (np.exp(lam_m * h0)[None, :] * (1.0 + lam_m[None, :] * (h - h0)[:, None]))[:, inv_k]
        else:  # refined steps of a transient (:meth:`transient_grid`)
            elh = np.exp(lam_m[None, :] * h[:, None])[:, inv_k]
        eu = elh * rot
        u = (lam[None, :] - 1j * eo[None, :] * om_end[:, None]) * h[:, None]
        if self._om_col is not None:
            u -= 1j * self._om_col[idx][None, :] * h[:, None]
        v = 0.5j * eo[None, :] * (alpha * h * h)[:, None]  # (N, Q)
        g = _chirp_given_exp(u, eu, v)
        g *= self._c_col[idx][None, :] * h[:, None]
        g *= Einv * np.conj(Phi[1:])
        acc = np.cumsum(g, axis=0)
        acc += A[start, idx][None]
        acc *= E[1:] * Phi[1:]
        if allc:
            A[start + 1:stop + 1] = acc
        else:
            A[start + 1:stop + 1, idx] = acc

    def _to_blades(self, X: np.ndarray) -> np.ndarray:
        """(m, n_act) complex modal envelopes -> (m, n_blades * r) blade envelopes."""
        out = np.empty((X.shape[0], self.W.shape[1]), complex)
        out.real = X.real @ self.W
        out.imag = X.imag @ self.W
        return out

    def modal_state(self, t: float, t_grid_point: float, a_plus, a_minus) -> np.ndarray:
        """Exact complex modal state ``z`` (n_act,) at ``t`` from envelopes at a grid point.

        Independent of the Hermite interpolation: used by tests as a reference.
        """
        ts = np.array([t_grid_point, t])
        phi, om, _ = self.speed.state(ts)
        al = self.speed.alpha[self.speed.segment(0.5 * (ts[0] + ts[1]))]
        ap = self._envelopes(+1, a_plus, self.c_plus, ts, phi, om[1:], np.array([al]))[-1]
        am = self._envelopes(-1, a_minus, self.c_minus, ts, phi, om[1:], np.array([al]))[-1]
        carrier = np.exp(1j * self.eo * phi[1]) if self.omega is None else np.exp(
            1j * (self.eo * phi[1] + self.omega[None, :] * t))
        return np.sum(ap * carrier + am * np.conj(carrier), axis=1)

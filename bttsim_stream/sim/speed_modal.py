"""Modal envelopes of a run-up whose modes follow the speed (centrifugal effects).

The reduced speed-dependent system
----------------------------------
For a model with speed-dependent modes (:mod:`bttsim_stream.model.speed_modes`: natural
cubic splines in ``s = Omega^2``), mode ``k`` obeys, with ``Omega = Omega(t)`` the run's
piecewise-linear speed (:mod:`bttsim_stream.sim.speed`),

``q_k'' + 2 zeta_k w_k(Omega) q_k' + w_k(Omega)^2 q_k = Im(sum_m C_km(Omega) exp(i EO_m phi(t)))``

with ``C_km(Omega)`` the modal force (paper Eq. 5-7) from the force shapes at ``Omega``, the
damping ratio ``zeta_k`` constant, and the tip motion ``u(t) = sum_k psi_k(Omega) q_k(t)``
from the tip shapes at ``Omega``. The modes are taken at the instantaneous speed and the
coupling that the shapes' change with speed would add (``Phi^T M dPhi/dt`` terms, of
relative size ``alpha |dPhi/dOmega| / w`` -- about 1e-6 on the paper's 2.4 rad/s^2 run-up) is
neglected: this is the reduced system that the tests' ``solve_ivp`` reference integrates.

The envelope form, with time-varying frequency
----------------------------------------------
With ``lambda(t) = -zeta w + i w_d`` (``w_d = w sqrt(1 - zeta^2)``) the complex state
``z = q' - conj(lambda) q`` carries ``q = Im(z) / w_d`` and ``q' = Re(z) - zeta w q`` at every
instant, and obeys exactly ``z' = lambda z + f - conj(lambda)' q``. Splitting
``q = (z - conj(z)) / (2 i w_d)`` gives

``z' = lambda_e z + f + kappa conj(z)``, ``lambda_e = lambda + w'/(2 w) (1 - i zeta / sqrt(1 - zeta^2))``,
``|kappa| = w' / (2 w_d)``.

The real part ``w'/(2 w)`` of the correction is the Liouville-Green (WKB) amplitude factor:
``|z|`` grows as ``sqrt(w)``, i.e. ``q`` as ``1 / sqrt(w)``, as an adiabatic oscillator's
should. The ``conj(z)`` term turns at ``-2 w_d`` relative to ``z``: it moves ``z`` by at most
``|kappa| / (2 w_d) = w' / (4 w_d^2)`` relative (2e-8 for a Southwell coefficient of 1.5 on
the paper's run-up: picometres, 1e-12 s in TOA) and is left out. The carrier envelopes
``a_+- = z_+- exp(-+ i EO phi)`` then obey ``a' = mu(t) a + c(t)`` with
``mu = lambda_e(t) -+ i EO Omega(t)``, ``c_+ = C(Omega) / 2i``, ``c_- = -conj(C(Omega)) / 2i``.

Over a grid step ``h`` (within one speed segment) ``mu`` and ``c`` are taken linear between
their values at the step's ends (``mu_0, mu_1``, ``c_0, c_1``), and the step is then exact:

``a_1 = exp(u + v) a_0 + h (c_1 I_0(u, v) - (c_1 - c_0) I_1(u, v))``, ``u = mu_1 h``,
``v = -(mu_1 - mu_0) h / 2``, ``I_j = int_0^1 x^j exp(u x + v x^2) dx``.

The carrier part of ``mu`` is linear in time on a segment (exact); the remainder is the
curvature of ``w(t)``: a phase error ``|w''| h^3 / 12`` per step, 3e-12 rad at 2 ms on the
paper's run-up (a frequency error of 1e-9 rad/s), and ``|c''| h^2 / 8`` relative in the force
(1e-12). The blade envelopes ``G_b = sum_k psi_bk(Omega) / w_dk(Omega) (a_+ - conj(a_-))_k``
and their exact derivatives (including ``d psi / dt`` and ``d w_d / dt``) are formed at the
grid points as for constant modes; everything downstream (Hermite interpolation, crossings,
:mod:`bttsim_stream.sim.toa`) is unchanged.

Start and transients
--------------------
``initial = "steady"`` is the state that the first speed segment's sweep, extended back in
time, leaves at t = 0 (as for constant modes): the envelopes are integrated exactly by the
same recursion over a lead-in of that extended sweep, long enough for the free response of
its start (the first-order adiabatic envelope ``-c/mu - c'/mu^2 + c mu'/mu^3``) to decay by
1e-9 (``21 / min(zeta w)`` seconds; 1 s for the built-in model), at or near resonance too. If
the extended sweep would leave the speeds of the model (or slow below half the start speed)
first, the lead-in is shortened and a warning says so. ``"rest"`` starts at rest; the grid is
refined where a free response is present (:meth:`SpeedDependentIntegrator.transient_grid`,
the bound of :meth:`~bttsim_stream.sim.modal.EnvelopeIntegrator.transient_grid` with the
frequencies at the segment's ends).
"""

from __future__ import annotations

import logging
from math import factorial
from types import SimpleNamespace

import numpy as np

from ..model.speed_modes import speed_modes
from .forcing import modal_forcing
from .modal import (TRANSIENT_TOL_S, EnvelopeGrid, EnvelopeIntegrator, TipBasis, j_moments, refine_pass,
                    quasi_steady_envelope, tip_basis)
from .speed import SpeedProfile

__all__ = ["SpeedDependentModes", "SpeedDependentIntegrator", "speed_tip_basis", "chirp_moments", "LEAD_IN_DECAY"]

_log = logging.getLogger(__name__)

#: The steady start's lead-in lasts until its starting error has decayed by this factor.
LEAD_IN_DECAY = 1e-9
#: Longest lead-in, s.
MAX_LEAD_IN_S = 60.0


def speed_tip_basis(model) -> tuple[TipBasis, np.ndarray]:
    """Compressed tip basis common to every sample speed, and the modal participation at each.

    Returns
    -------
    basis : TipBasis
        ``nodes`` (r, n_tip, 3) spanning the tip shapes at every speed (SVD of them all), and
        ``psi`` (n_modes, n_blades, r) at zero speed.
    psi_at_speed : ndarray, shape (S, n_modes, n_blades, r)
    """
    ts = np.asarray(model.extra["tip_shapes_at_speed"], float)
    S, n_modes = ts.shape[:2]
    b = tip_basis(ts.reshape((S * n_modes,) + ts.shape[2:]))
    psi = b.psi.reshape((S, n_modes) + b.psi.shape[1:])
    return TipBasis(psi=np.ascontiguousarray(psi[0]), nodes=b.nodes), psi


class SpeedDependentModes:
    """The modal path of a model whose modes follow the speed (centrifugal effects): the tip
    basis common to its sample speeds and a :class:`SpeedDependentIntegrator` of the
    engine-order excitations (non-synchronous forcing is not supported with it yet)."""

    nonsynchronous = False

    def __init__(self, model) -> None:
        self.model = model
        self.basis, self._psi_at_speed = speed_tip_basis(model)

    def integrator(self, carriers, excitations, speed: SpeedProfile, initial: str) -> SpeedDependentIntegrator:
        """The integrator of ``excitations`` (the modal forces follow the speed; ``carriers`` are
        their zero-speed values, not used)."""
        return SpeedDependentIntegrator(self.model, excitations, self._psi_at_speed, speed, initial=initial)


def chirp_moments(u, v) -> tuple[np.ndarray, np.ndarray]:
    """``I_j(u, v) = int_0^1 x^j exp(u x + v x^2) dx`` for j = 0, 1 (small ``|v|``, < 1e-2).

    ``I_j = sum_n v^n / n! J_(2n+j)(u)`` with the moments ``J_k`` of
    :func:`~bttsim_stream.sim.modal._j_moments` (recurrence or power series, round-off).
    """
    u = np.asarray(u, complex)
    v = np.asarray(v, complex)
    vabs = np.abs(v)
    vmax = float(np.max(vabs)) if vabs.size else 0.0
    n_v = 1
    while vmax ** n_v / factorial(n_v) > 1e-18 and n_v < 12:
        n_v += 1
    J = j_moments(u, 2 * n_v - 1, vabs)
    I0 = J[..., 2 * n_v - 2].copy()
    I1 = J[..., 2 * n_v - 1].copy()
    for n in range(n_v - 1, 0, -1):  # Horner in v
        I0 *= v / n
        I0 += J[..., 2 * n - 2]
        I1 *= v / n
        I1 += J[..., 2 * n - 1]
    return I0, I1


class SpeedDependentIntegrator:
    """Streaming envelope integration for a model whose modes follow the speed.

    The same interface as :class:`~bttsim_stream.sim.modal.EnvelopeIntegrator` as far as
    :class:`~bttsim_stream.sim.core.RunUpSimulator` uses it (``advance``,
    ``transient_grid``, ``active``, ``warnings``); see the module docstring for the
    equations. Every (mode, carrier) column takes the exact step recursion (no quasi-steady
    shortcut).

    Parameters
    ----------
    model : ModalModel
        With speed-dependent modes (``SPEED_ARRAYS``).
    excitations : sequence of scenario ``Excitation``
    psi_at_speed : ndarray, shape (S, n_modes, n_blades, r)
        Tip participation at the sample speeds (:func:`speed_tip_basis`).
    speed : SpeedProfile
    initial : {"steady", "rest"}
    """

    def __init__(self, model, excitations, psi_at_speed: np.ndarray, speed: SpeedProfile,
                 initial: str = "steady") -> None:
        if initial not in ("steady", "rest"):
            raise ValueError(f"initial must be 'steady' or 'rest', got {initial!r}")
        sm = speed_modes(model)
        S = sm.speed_rad_s.size
        te = model.extra.get("force_shapes_trailing_edge_at_speed")
        C_s = []
        for i in range(S):
            view = SimpleNamespace(n_blades=model.n_blades, n_modes=model.n_modes,
                                   force_shapes=model.extra["force_shapes_at_speed"][i],
                                   extra={} if te is None else {"force_shapes_trailing_edge": te[i]})
            C, eo = modal_forcing(view, excitations)
            C_s.append(C)
        C_s = np.stack(C_s)  # (S, n_modes, n_exc)
        mx = np.max(np.abs(C_s), axis=(0, 2))
        self.active = np.flatnonzero(mx > 1e-14 * max(float(np.max(mx, initial=0.0)), 1e-300))
        act = self.active
        self.eo = np.asarray(eo, float)[None, :]
        n_exc = self.eo.shape[1]
        self.speed = speed
        self.t = 0.0
        self.warnings: list[str] = []
        self.stats = {"quasi_steady": 0, "exact": 0}
        self._zeta = np.asarray(model.damping_ratio, float)[act]
        self._sq = np.sqrt(1.0 - self._zeta**2)
        w2 = sm.omega2
        self._w2 = type(w2).construct_fast(w2.c[:, :, act], w2.x)  # PPoly in s of w_k^2 (active)
        Cs = C_s[:, act]
        self._C_re, self._C_im = sm.spline(Cs.real), sm.spline(Cs.imag)
        self._psi = sm.spline(psi_at_speed[:, act].reshape(S, act.size, -1))  # (n_act, nb * r)
        self._psi_deg = _degree(self._psi)
        self.n_blades, self.r = psi_at_speed.shape[2:]
        n_car = 2 * n_exc
        self._k_col = np.repeat(np.arange(act.size), n_car)
        self._eo_col = np.tile(np.concatenate([self.eo[0], -self.eo[0]]), act.size)
        self._n_exc = n_exc
        self.max_speed_rad_s = sm.max_speed_rad_s
        _, om0, al0 = (float(x) for x in speed.state(0.0))
        shape = (act.size, n_exc)
        if initial == "rest" or act.size == 0:
            self.a_plus, self.a_minus = np.zeros(shape, complex), np.zeros(shape, complex)
        else:
            a = self._lead_in(om0, al0)
            self.a_plus, self.a_minus = a[:, :n_exc].copy(), a[:, n_exc:].copy()
        w0 = self._w_at(om0)[0][0]
        self.lam = (-self._zeta * w0 + 1j * self._sq * w0)[:, None]  # at t = 0 (for reference)

    # -- coefficients at speeds -------------------------------------------------------------
    def _w_at(self, om):
        """``w_k`` and ``beta_k = dw_k/dOmega`` (so ``w' = beta alpha``) at speeds ``om`` (n,): (n, n_act)."""
        om = np.atleast_1d(np.asarray(om, float))
        s = om * om
        w2 = self._w2(s)
        w = np.sqrt(w2)
        beta = self._w2(s, 1) * om[:, None] / w  # dw/dOmega = (dw^2/ds) Omega / w
        return w, beta

    def _coeffs(self, om):
        """Per speed ``om`` (n,): ``(om, w, beta, lambda_0, rho, c)`` with ``lambda_e = lambda_0 +
        alpha rho`` (n, n_act) and ``c`` of every column (n, n_cols)."""
        om = np.atleast_1d(np.asarray(om, float))
        w, beta = self._w_at(om)
        lam0 = -self._zeta * w + 1j * (self._sq * w)
        rho = (beta / (2.0 * w)) * (1.0 - 1j * self._zeta / self._sq)
        C = self._C(om)  # (n, n_act, n_exc)
        c = np.concatenate([C / 2j, -np.conj(C) / 2j], axis=2).reshape(om.size, -1)
        return om, w, beta, lam0, rho, c

    def _mu(self, co, alpha, sl=slice(None)):
        """``mu`` of every column (m, n_cols) at the points ``sl`` of :meth:`_coeffs` ``co``,
        accelerations ``alpha`` (m,)."""
        om, _, _, lam0, rho, _ = co
        lam = lam0[sl] + np.asarray(alpha, float).reshape(-1, 1) * rho[sl]
        return lam[:, self._k_col] - 1j * self._eo_col[None, :] * om[sl, None]

    def _mu_c(self, om, alpha):
        """``mu`` and ``c`` of every column (n, n_cols) at speeds ``om`` with accelerations ``alpha`` (n,)."""
        co = self._coeffs(om)
        return self._mu(co, np.broadcast_to(np.asarray(alpha, float), co[0].shape)), co[5]

    def _C(self, om, nu: int = 0):
        s = np.square(np.atleast_1d(np.asarray(om, float)))
        return self._C_re(s, nu) + 1j * self._C_im(s, nu)

    # -- the recursion ----------------------------------------------------------------------
    def _propagate(self, a0, t, co, alpha_steps):
        """Envelopes (n, n_cols) at grid times ``t`` (n,) from ``a0`` (n_cols,) at ``t[0]``.

        ``co`` holds the coefficients at the speeds of ``t`` (:meth:`_coeffs`);
        ``alpha_steps`` (n - 1,) the acceleration of each step (no step straddles a speed
        knot)."""
        n = t.size
        A = np.empty((n, a0.size), complex)
        A[0] = a0
        if n == 1 or a0.size == 0:
            return A
        h = np.diff(t)
        mu0 = self._mu(co, alpha_steps, slice(0, n - 1))
        mu1 = self._mu(co, alpha_steps, slice(1, n))
        c0, c1 = co[5][:-1], co[5][1:]
        om = co[0]
        self.stats["exact"] += a0.size
        zw_max = float(np.max(self._zeta * self._w_at(np.array([om.min(), om.max()]))[0]))
        span = 300.0 / max(zw_max, 1e-9)  # keeps exp(-+ int mu) of a stretch in range
        for a, b in EnvelopeIntegrator._spans(t, 0, n - 1, span):
            hh = h[a:b, None]
            u = mu1[a:b] * hh
            v = -0.5 * (mu1[a:b] - mu0[a:b]) * hh
            I0, I1 = chirp_moments(u, v)
            g = hh * (c1[a:b] * I0 - (c1[a:b] - c0[a:b]) * I1)
            L = np.cumsum(u + v, axis=0)
            acc = np.cumsum(g * np.exp(-L), axis=0)
            acc += A[a]
            A[a + 1:b + 1] = np.exp(L) * acc
        return A

    def _lead_in(self, om0: float, al0: float) -> np.ndarray:
        """The steady start: the envelopes (n_act, n_car) at t = 0 after an exact lead-in along
        the first segment's sweep extended back in time (see the module docstring)."""
        w, _ = self._w_at(np.array([om0]))
        zw_min = float(np.min(self._zeta * w[0]))
        want = -np.log(LEAD_IN_DECAY) / zw_min if zw_min > 0 else np.inf
        lead = min(want, MAX_LEAD_IN_S)
        if al0 > 0:
            lead = min(lead, 0.5 * om0 / al0)
        elif al0 < 0:
            lead = min(lead, (self.max_speed_rad_s - om0) / -al0)
        if lead < want:
            msg = (f"initial = \"steady\" with speed-dependent modes: the lead-in along the extended first sweep "
                   f"is {lead:.3g} s, shorter than the {want:.3g} s its start needs to decay by "
                   f"{LEAD_IN_DECAY:g} (slowest decay {zw_min:.3g} 1/s); the first revolutions may carry a small "
                   "free response")
            self.warnings.append(msg)
            _log.warning(msg)
        n = max(1, int(np.ceil(lead / 2e-3)))
        tau = np.linspace(-lead, 0.0, n + 1)
        om = om0 + al0 * tau
        # first-order adiabatic envelope at the lead-in's start: -c/mu - c'/mu^2 + c mu'/mu^3
        mu, c = self._mu_c(om[:1], al0)
        mu_d = (self._mu_c(om[:1] + 1e-3 * max(om0, 1.0), al0)[0] - self._mu_c(om[:1] - 1e-3 * max(om0, 1.0),
                                                                               al0)[0]) / (2e-3 * max(om0, 1.0)) * al0
        Cd = self._C(om[:1], 1) * (2.0 * om[0] * al0)
        c_d = np.concatenate([Cd / 2j, -np.conj(Cd) / 2j], axis=2).reshape(1, -1)
        with np.errstate(all="ignore"):
            a0 = (-c / mu - c_d / mu**2 + c * mu_d / mu**3)[0]
        a0 = np.where(np.isfinite(a0), a0, 0.0)
        A = self._propagate(a0, tau, self._coeffs(om), np.full(n, al0))
        return A[-1].reshape(self.active.size, -1)

    def advance(self, t_grid: np.ndarray, keep_modal: bool = False, out: np.ndarray | None = None,
                first: int = 0):
        """Integrate from the current time (``t_grid[0]``) over ``t_grid``; return envelopes.

        As :meth:`EnvelopeIntegrator.advance` (same ``out`` layout), with the modes at the
        speed of each grid point: ``G = sum_k psi_k(Omega) / w_dk(Omega) (a_+ - conj(a_-))_k``
        and ``dG`` its exact time derivative.
        """
        t_grid = np.asarray(t_grid, float)
        if abs(t_grid[0] - self.t) > 1e-12 * max(1.0, abs(self.t)):
            raise ValueError("advance() must start at the integrator's current time")
        _, om, al_pts = self.speed.state(t_grid)
        n, n_exc, n_act = t_grid.size, self._n_exc, self.active.size
        a0 = np.concatenate([self.a_plus, self.a_minus], axis=1).ravel()
        co = self._coeffs(om)
        if n > 1:
            al_steps = self.speed.alpha[self.speed.segment(0.5 * (t_grid[:-1] + t_grid[1:]))]
            A = self._propagate(a0, t_grid, co, al_steps)
        else:
            A = a0[None].copy()
        A3 = A.reshape(n, n_act, 2 * n_exc)
        self.a_plus, self.a_minus = A3[-1, :, :n_exc].copy(), A3[-1, :, n_exc:].copy()
        self.t = float(t_grid[-1])
        sl = slice(first, None)
        D3 = (self._mu(co, al_pts[sl], sl) * A[sl] + co[5][sl]).reshape(-1, n_act, 2 * n_exc)
        Ap, Am = A3[sl, :, :n_exc], A3[sl, :, n_exc:]
        Y = Ap - np.conj(Am)  # (m, n_act, n_exc)
        dY = D3[..., :n_exc] - np.conj(D3[..., n_exc:])
        om_s, al_s = om[sl], al_pts[sl]
        wd = self._sq * co[1][sl]
        dwd = self._sq * co[2][sl] * al_s[:, None]
        X = Y / wd[..., None]
        dX = dY / wd[..., None] - Y * (dwd / wd**2)[..., None]
        ds = 2.0 * om_s * al_s  # ds/dt
        GD = self._blade_sum(X, dX, om_s * om_s, ds)  # (2, n_exc, 2, m, nb * r): G / dG, re / im
        if out is not None:
            out[...] = GD
            return None
        GD = (GD[:, :, 0] + 1j * GD[:, :, 1]).reshape(2, n_exc, -1, self.n_blades, self.r).transpose(0, 2, 1, 3, 4)
        return EnvelopeGrid(t=t_grid[sl], G=GD[0], dG=GD[1],
                            a_plus=Ap.copy() if keep_modal else None, a_minus=Am.copy() if keep_modal else None)

    def _blade_sum(self, X, dX, s, ds):
        """``G = sum_k psi_k(s) X_k`` and ``dG = sum_k (psi_k(s) dX_k + dpsi_k/ds ds/dt X_k)`` as
        real planes (2 [G, dG], n_exc, 2 [re, im], m, n_blades * r).

        ``psi`` is a polynomial in ``d = s - s_i`` on each spline interval ``i`` (only the
        powers the spline uses): per interval present, one real matrix product of the
        stacked ``(X d^p, dX d^p + p d^(p-1) ds/dt X)`` rows by the stacked coefficients."""
        spl = self._psi
        m, n_act, n_exc = X.shape
        nbr = spl.c.shape[-1]
        out = np.empty((2, n_exc, 2, m, nbr))
        ival = np.clip(np.searchsorted(spl.x, s, side="right") - 1, 0, spl.x.size - 2)
        deg = self._psi_deg
        Xt = X.transpose(2, 0, 1)  # (n_exc, m, n_act)
        dXt = dX.transpose(2, 0, 1)
        for i in np.unique(ival):
            rows = np.flatnonzero(ival == i)
            whole = rows.size == m
            xg, xd = (Xt, dXt) if whole else (Xt[:, rows], dXt[:, rows])
            d = (s if whole else s[rows]) - spl.x[i]
            dsr = ds if whole else ds[rows]
            mi = d.size
            M = np.empty((2, n_exc, mi, deg + 1, n_act), complex)  # G / dG rows, powers side by side
            dp_prev = None
            dp = np.ones(mi)
            for p in range(deg + 1):
                M[0, :, :, p] = xg * dp[:, None]
                M[1, :, :, p] = xd * dp[:, None]
                if p > 0:
                    M[1, :, :, p] += xg * (p * dp_prev * dsr)[:, None]
                dp_prev, dp = dp, dp * d
            P = spl.c[3 - np.arange(deg + 1), i].reshape((deg + 1) * n_act, nbr)
            M = M.reshape(2, n_exc, mi, -1)
            R = np.stack([M.real, M.imag], axis=2)  # (2, n_exc, 2, mi, (deg + 1) n_act)
            Z = (R.reshape(-1, R.shape[-1]) @ P).reshape(2, n_exc, 2, mi, nbr)
            if whole:
                out[...] = Z
            else:
                out[:, :, :, rows] = Z
        return out

    # -- refined grid where a free response is present --------------------------------------
    def transient_grid(self, h_max: float, radius_m: float, reach_m: float = 0.0,
                       tol_s: float = TRANSIENT_TOL_S) -> dict:
        """Refined envelope grid points where a free response needs them.

        The bound of :meth:`EnvelopeIntegrator.transient_grid`, per speed segment, with the
        frequencies, modal forces and decay rates of the speed-dependent modes: the largest
        ``|mu|`` and ``|c|`` and the smallest ``zeta w`` of the segment's two end speeds, and a
        resonance inside the segment where ``Im mu`` changes sign between them. The free
        response at a knot: the previous one, decayed, plus the jump of the quasi-steady
        envelope (:func:`quasi_steady_envelope` with ``mu' = dmu/dt``) between the two
        accelerations; at t = 0 the whole quasi-steady envelope for a start from rest (none
        for the steady start: its lead-in leaves it decayed).
        """
        sp = self.speed
        T, Om, al = sp.t_s, sp.omega, sp.alpha
        out: dict = {}
        n_act = self.active.size
        if n_act == 0:
            return out
        psi = self._psi(np.square(Om)).reshape(Om.size, n_act, self.n_blades, self.r)
        wn = np.max(np.linalg.norm(psi, axis=3), axis=(0, 2))
        w_min = np.min(self._w_at(Om)[0], axis=0) * self._sq
        wn = (wn / w_min)[self._k_col]

        def qs(om, alpha):
            """Quasi-steady envelopes (n, n_cols) at speeds ``om`` (n,), accelerations ``alpha`` (n,)."""
            mu, c = self._mu_c(om, alpha)
            d = 1e-4 * np.maximum(om, 1.0)
            mu_d = (self._mu_c(om + d, alpha)[0] - self._mu_c(om - d, alpha)[0]) / (2 * d)[:, None]
            return quasi_steady_envelope(c, mu, mu_d * alpha[:, None])  # m1 = dmu/dt

        a0 = np.concatenate([self.a_plus, self.a_minus], axis=1).ravel()
        n_seg = T.size - 1
        # per segment: mu and c at both end speeds (the segment's acceleration), slowest decay
        mu_lo, c_lo = self._mu_c(Om[:-1], al[:-1])
        mu_hi, c_hi = self._mu_c(Om[1:], al[:-1])
        zw_k = self._zeta * self._w_at(Om)[0]
        sig = np.minimum(zw_k[:-1], zw_k[1:])[:, self._k_col]  # (n_seg, n_cols)
        with np.errstate(all="ignore"):
            e = np.abs(a0 - qs(Om[:1], al[:1])[0]) if np.all(a0 == 0) else np.zeros(a0.size)
            # jumps of the quasi-steady envelope at the inner knots, all at once
            jump = (np.abs(qs(Om[1:n_seg], al[:n_seg - 1]) - qs(Om[1:n_seg], al[1:n_seg])) if n_seg > 1
                    else np.zeros((0, a0.size)))
            for k in range(n_seg):
                if k > 0:
                    e = e * np.exp(-sig[k - 1] * (T[k] - T[k - 1])) + jump[k - 1]
                e = np.where(np.isfinite(e), e, 0.0)
                if not np.any(e * wn > 0):
                    continue
                pts = self._refine_segment(k, e, wn, h_max, radius_m, reach_m, tol_s,
                                           (mu_lo[k], mu_hi[k]), np.maximum(np.abs(c_lo[k]), np.abs(c_hi[k])),
                                           sig[k])
                if pts.size > 1:
                    out[k] = pts
        return out

    def _refine_segment(self, k, e, wn, h_max, radius_m, reach_m, tol_s, mu_ends, c, sig) -> np.ndarray:
        """As :meth:`EnvelopeIntegrator._refine_segment`, with the segment's end speeds' modes
        (``mu_ends``: ``mu`` at both ends; ``c``: the larger ``|c|``; ``sig``: the slower decay)."""
        sp = self.speed
        t_k, t_end = float(sp.t_s[k]), float(sp.t_s[k + 1])
        om_k, alpha = float(sp.omega[k]), float(sp.alpha[k])
        S0 = wn * e * np.maximum(np.abs(mu_ends[0]), np.abs(mu_ends[1])) ** 4 / 24.0
        zone = t_end - t_k
        pts = np.array([t_k])
        for _ in range(2):
            om_b = om_k + alpha * zone
            mu_b = mu_ends[1] if zone == t_end - t_k else self._mu_c(np.array([om_b]), alpha)[0][0]
            mu_ab = np.stack([mu_ends[0], mu_b])
            im_a, im_b = mu_ab[0].imag, mu_ab[1].imag
            mu_min = np.where(im_a * im_b <= 0, sig, np.min(np.abs(mu_ab), axis=0))
            with np.errstate(divide="ignore"):
                amp = float(np.sum(wn * (c / mu_min + e)))
            om_min = min(om_k, om_b)
            amp = min(amp, 0.05 * radius_m)
            pts, zone = refine_pass(k, t_k, t_end, zone, amp, reach_m, radius_m, om_min, sig, S0, tol_s, h_max,
                                     _ == 1, self.warnings)
            if zone is None:
                break
        return pts


def _degree(spl) -> int:
    """Highest power of ``s - s_i`` with a nonzero coefficient in a cubic spline (0..3)."""
    for p in (3, 2, 1):
        if np.any(spl.c[3 - p] != 0):
            return p
    return 0


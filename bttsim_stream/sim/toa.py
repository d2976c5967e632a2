"""Blade times of arrival: stage A crossing times (Eq. 8, 12-14) and stage B axial interpolation (Eq. 9-11).

Conventions
-----------
A *crossing* is one (revolution, blade, probe) event. For each crossing the rigid nominal
sensing point P_nom reaches the probe when the rotor angle is ``phi_c``; tip node ``n`` of
blade ``b`` reaches it when ``phi(t) + delta_n(t) = phi_c + theta_Pnom - theta_n`` with
``delta_n = atan2(u_tang, r_n + u_rad)`` its angular deflection (paper Eq. 8 with the
rotor-frame angle of the deformed node). Times in s, angles in rad.

Stage A, per tip node:

* ``HP``: Newton's method on the exact response from a first-order start (the rigid node
  time corrected by the deflection and its rate): one Newton step, then one simplified
  Newton step whose size, the reported residual, is at most 1e-13 s (else full Newton steps
  for those crossings) -- :func:`hp_crossings`.
* ``AD`` (Eq. 12): linear interpolation of the angular difference between the two
  integrator grid points ``t_{i-1}, t_i = i * dt`` that bracket the crossing (Eq. 14).
* ``PAD`` (Eq. 13): linear interpolation of the *product* of angular differences
  ``Delta_i * Delta_{i-1}`` between the same grid points; with a locally linear
  ``Delta`` this lands at ``t_{i-1} + dt (1 + x) / 2`` for a true crossing at
  ``t_{i-1} + x dt``, an error in ``[0, dt/2]`` that depends on where the crossing falls in the
  step: speed-dependent, noise-like errors in the BTT displacement (paper Sec. 3.3.1).

States at grid points are exact (the grid is the integrator's; no ODE tolerance enters).
The bracketing grid step is found from the HP crossing, which is where a sequential scan of
``Pi Delta <= 0`` (Eq. 14) stops for a single crossing.

Stage B (Eq. 9-11): of the nodes' axial positions at their own crossing times, the two
nearest the probe on opposite sides are interpolated linearly in z; ``axial_interpolation =
false`` takes the nearest node (reproduces the paper's Fig. 7).

Layout: every array has the crossings on its last axis (long, contiguous inner loops); the
tip motion near a crossing is a :class:`LocalMotion`, the blade's compressed cubic Hermite
envelope projected once per batch onto the node components needed (:func:`project_planes`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .speed import SpeedProfile

__all__ = ["stage_b", "hermite_in_place", "LocalMotion", "crossing_frame", "project_planes", "eval_planes",
           "eval_local", "node_angle_residual", "hp_crossings", "grid_crossings"]


def stage_b(t_det: np.ndarray, dz: np.ndarray, axial_interpolation: bool = True):
    """TOA from the candidate nodes' crossing times and axial offsets (Eq. 9-11).

    Parameters
    ----------
    t_det, dz : ndarray, shape (n_c, q)
        Crossing time (s) and ``z_node(t_det) - z_probe`` (m) of each candidate node.

    Returns
    -------
    toa : ndarray, shape (n_c,)
    pair : ndarray, shape (n_c, 2)
        Column indices (into q) of the two nodes used (the same twice for nearest-node).
    bracketed : ndarray of bool, shape (n_c,)
        False where no node pair straddled the probe (two nearest nodes extrapolated).
    """
    big = np.inf
    pos = np.where(dz >= 0, dz, big)
    neg = np.where(dz < 0, -dz, big)
    k1 = np.argmin(pos, axis=1)
    k2 = np.argmin(neg, axis=1)
    rows = np.arange(t_det.shape[0])
    bracketed = np.isfinite(pos[rows, k1]) & np.isfinite(neg[rows, k2])
    order = np.argsort(np.abs(dz), axis=1)
    k1 = np.where(bracketed, k1, order[:, 0])
    k2 = np.where(bracketed, k2, order[:, 1])
    if not axial_interpolation:
        kn = order[:, 0]
        return t_det[rows, kn], np.stack([kn, kn], axis=1), bracketed
    t1, t2 = t_det[rows, k1], t_det[rows, k2]
    z1, z2 = dz[rows, k1], dz[rows, k2]
    toa = t1 - z1 * (t2 - t1) / (z2 - z1)
    return toa, np.stack([k1, k2], axis=1), bracketed


# ------------------------------------------------------------------------------------------
# Crossing engine: crossings on the last axis, node components projected once per batch
# ------------------------------------------------------------------------------------------


def hermite_in_place(P: np.ndarray, h) -> np.ndarray:
    """Cubic Hermite coefficients ``(P0, P1, P2, P3)`` in ``tau = t - t0``, in place.

    ``P = [G0, D0, G1, D1]`` along the first axis: values and derivatives of an envelope at
    ``t0`` and ``t0 + h`` (``h`` broadcasts against the last axis). With
    ``s = (G1 - G0) / h`` and ``e = D0 + D1 - 2 s``: ``P2 = (s - D0 - e) / h``
    (``= (3 s - 2 D0 - D1) / h``) and ``P3 = e / h^2``; ``P0 = G0``, ``P1 = D0``."""
    inv = 1.0 / h
    s = P[2] - P[0]
    s *= inv
    e = P[1] + P[3]
    e -= s
    e -= s
    np.subtract(s, P[1], out=P[2])
    P[2] -= e
    P[2] *= inv
    e *= inv
    np.multiply(e, inv, out=P[3])
    return P


@dataclass(frozen=True, slots=True, eq=False)
class LocalMotion:
    """Motion of selected tip-node components near each crossing (crossings last).

    The displacement of component ``j`` at time ``t`` is
    ``sum_m Im(X_mj(t - t0) exp(i EO_m phi(t_ref)) exp(i EO_m (phi(t) - phi(t_ref))))`` with
    ``X_mj`` the cubic Hermite interpolant of the blade envelope projected onto the component
    (the modal sum of Eq. 5-7 forcing, in envelope form): the large rotor angle enters once
    per crossing (``rot``), an evaluation only needs the small angle turned since ``t_ref``.

    Attributes
    ----------
    P : ndarray, shape (4, n_exc, q, c, 2, n)
        Hermite coefficients in ``tau = t - t0`` (q nodes, c components, real and imaginary
        parts, n crossings).
    t0, t_ref : ndarray, shape (n,)
        Start of the envelope interval and reference time of each crossing.
    om_ref, alpha : ndarray, shape (n,)
        Speed (rad/s) at ``t_ref`` and acceleration (rad/s^2) of its speed segment.
    seg_lo, seg_hi : ndarray, shape (n,)
        Bounds of the speed segment of ``t_ref`` (-inf / +inf at the profile's ends).
    phi_ref : ndarray, shape (n,)
        Rotor angle at ``t_ref`` (as :meth:`SpeedProfile.state`), rad.
    margin : float
        Smallest distance from a ``t_ref`` to its segment's bounds, s.
    rot : ndarray, shape (n_exc, 2, n)
        ``cos`` and ``sin`` of the carrier phase ``theta_m(t_ref) = EO_m phi(t_ref) + omega_m t_ref``.
    eo : ndarray, shape (n_exc,)
    omega : ndarray, shape (n_exc,), or None
        Constant carrier frequencies ``omega_m``, rad/s (non-synchronous carriers,
        :class:`~bttsim_stream.sim.modal.EnvelopeIntegrator`); None: all zero.
    """

    P: np.ndarray
    t0: np.ndarray
    t_ref: np.ndarray
    om_ref: np.ndarray
    alpha: np.ndarray
    seg_lo: np.ndarray
    seg_hi: np.ndarray
    phi_ref: np.ndarray
    margin: float
    rot: np.ndarray
    eo: np.ndarray
    omega: np.ndarray | None = None

    def take(self, idx) -> "LocalMotion":
        """The crossings ``idx``."""
        return LocalMotion(P=self.P[..., idx], t0=self.t0[idx], t_ref=self.t_ref[idx], om_ref=self.om_ref[idx],
                           alpha=self.alpha[idx], seg_lo=self.seg_lo[idx], seg_hi=self.seg_hi[idx],
                           phi_ref=self.phi_ref[idx], margin=self.margin, rot=self.rot[..., idx], eo=self.eo,
                           omega=self.omega)

    def with_P(self, P: np.ndarray) -> "LocalMotion":
        """The same crossings with other components."""
        return LocalMotion(P=P, t0=self.t0, t_ref=self.t_ref, om_ref=self.om_ref, alpha=self.alpha,
                           seg_lo=self.seg_lo, seg_hi=self.seg_hi, phi_ref=self.phi_ref, margin=self.margin,
                           rot=self.rot, eo=self.eo, omega=self.omega)

    def angle_change(self, speed: SpeedProfile, t: np.ndarray):
        """Rotor angle turned since ``t_ref`` (rad) and speed (rad/s) at times ``t`` (q, n).

        ``(t - t_ref) (Omega_ref + alpha (t - t_ref) / 2)`` in the segment of ``t_ref``
        (Eq. 6, without the large rotor angle); across a speed knot
        :meth:`SpeedProfile.angle_change`.
        """
        dt = t - self.t_ref
        om = self.alpha * dt
        d = 0.5 * om
        d += self.om_ref
        d *= dt
        om += self.om_ref
        if dt.size == 0 or max(float(dt.max()), -float(dt.min())) < self.margin:
            return d, om
        out = (t < self.seg_lo) | (t >= self.seg_hi)
        if np.any(out):
            tr = np.broadcast_to(self.t_ref, t.shape)[out]
            d[out], om[out] = speed.angle_change(tr, t[out])
        return d, om


def crossing_frame(speed: SpeedProfile, t0: np.ndarray, t_ref: np.ndarray, eo, omega=None) -> LocalMotion:
    """A :class:`LocalMotion` without components: the crossings' reference times, speeds and
    carriers ``exp(i theta_m(t_ref))``, ``theta_m = EO_m phi + omega_m t`` (``omega`` None:
    all zero)."""
    k = speed.segment(t_ref)
    s = t_ref - speed.t_s[k]
    lo = np.where(k == 0, -np.inf, speed.t_s[k])
    hi = np.where(k == speed.t_s.size - 2, np.inf, speed.t_s[k + 1])
    a = speed.alpha[k]
    w = speed.omega[k]
    om = w + a * s
    phi = speed.phi_knots[k] + s * (w + 0.5 * a * s)  # as SpeedProfile.state
    eo = np.asarray(eo, float)
    th = eo[:, None] * phi[None, :]
    if omega is not None:
        omega = np.asarray(omega, float)
        th = th + omega[:, None] * t_ref[None, :]
    rot = np.stack([np.cos(th), np.sin(th)], axis=1)  # (n_exc, 2, n)
    margin = float(np.min(np.minimum(t_ref - lo, hi - t_ref), initial=np.inf))
    return LocalMotion(P=np.zeros((4, eo.size, 0, 0, 2, t_ref.size)), t0=t0, t_ref=t_ref, om_ref=om, alpha=a,
                       seg_lo=lo, seg_hi=hi, phi_ref=phi, margin=margin, rot=rot, eo=eo, omega=omega)


def project_planes(CPr: np.ndarray, V: np.ndarray) -> np.ndarray:
    """Project rotated compressed Hermite coefficients onto node components (one BLAS call).

    Parameters
    ----------
    CPr : ndarray, shape (4, n_exc, r, 2, n)
        Hermite coefficients of the compressed blade envelopes, real and imaginary parts,
        crossings last.
    V : ndarray, shape (r, q, c)
        Compressed coordinates -> the selected components of the selected nodes.

    Returns
    -------
    ndarray, shape (4, n_exc, q, c, 2, n)
    """
    r, q, c = V.shape
    s = CPr.shape
    out = V.reshape(r, q * c).T @ CPr.reshape(s[0], s[1], r, s[3] * s[4])
    return out.reshape(s[0], s[1], q, c, s[3], s[4])


def eval_planes(P: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """Horner evaluation of cubic coefficients ``P`` (4, ..., n) at ``tau`` (n,)."""
    X = P[3] * tau
    X += P[2]
    X *= tau
    X += P[1]
    X *= tau
    X += P[0]
    return X


def eval_local(lm: LocalMotion, speed: SpeedProfile, t: np.ndarray, derivative: bool = True):
    """Components (and their time derivatives) at times ``t`` of shape (q, n).

    Returns
    -------
    val, der : ndarray, shape (q, c, n)
        Displacement components (m) and velocities (m/s); ``der`` None unless ``derivative``.
    dphi, om : ndarray, shape (q, n)
        Rotor angle turned since ``t_ref`` (rad) and speed (rad/s) at ``t``.
    """
    dphi, om = lm.angle_change(speed, t)
    tau = (t - lm.t0)[:, None, None, :]  # (q, 1, 1, n)
    val = der = None
    for m in range(lm.eo.size):
        P0, P1, P2, P3 = lm.P[:, m]  # (q, c, 2, n)
        th = lm.eo[m] * dphi
        if lm.omega is not None:
            th = th + lm.omega[m] * (t - lm.t_ref)
        cd, sd = np.cos(th), np.sin(th)
        c0, s0 = lm.rot[m]
        cr = cd * c0
        cr -= np.multiply(sd, s0, out=th)  # th no longer needed
        ci = np.multiply(sd, c0, out=sd)
        ci += np.multiply(cd, s0, out=cd)  # exp(i EO phi(t)) = exp(i EO phi(t_ref)) exp(i EO dphi)
        cr, ci = cr[:, None, :], ci[:, None, :]
        X = P3 * tau
        X += P2
        X *= tau
        X += P1
        X *= tau
        X += P0
        Xr, Xi = X[:, :, 0], X[:, :, 1]
        v = Xi * cr
        tmp = Xr * ci
        v += tmp  # Im(X e^{i th})
        val = v if val is None else val + v
        if derivative:
            Xd = (3.0 * tau) * P3
            Xd += 2.0 * P2
            Xd *= tau
            Xd += P1
            # d/dt Im(X e^{i th}) = Im((X' + i EO Omega X) e^{i th}), in place, the same
            # operations in the same order
            d = Xd[:, :, 1] * cr
            d += np.multiply(Xd[:, :, 0], ci, out=tmp)
            rate = lm.eo[m] * om if lm.omega is None else lm.eo[m] * om + lm.omega[m]
            w = np.multiply(Xr, cr, out=Xd[:, :, 0])
            w -= np.multiply(Xi, ci, out=tmp)
            w *= rate[:, None, :]
            d += w
            der = d if der is None else der + d
    return val, der, dphi, om


def node_angle_residual(lm: LocalMotion, speed: SpeedProfile, t: np.ndarray, target_rel: np.ndarray,
                        radius: np.ndarray, derivative: bool = True):
    """Paper Eq. 8 for tip nodes: ``g = phi(t) - phi(t_ref) + atan2(u_tang, r + u_rad) - target_rel``.

    ``lm`` holds the (radial, tangential[, axial]) components of the nodes; ``target_rel`` is
    the rotor angle at which the rigid node would reach the probe, minus ``phi(t_ref)``.
    Returns ``g``, its time derivative (None unless ``derivative``) and the components.
    """
    val, der, dphi, om = eval_local(lm, speed, t, derivative)
    x = radius + val[:, 0]
    y = val[:, 1]
    g = dphi + np.arctan2(y, x) - target_rel
    if not derivative:
        return g, None, val
    dg = om + (x * der[:, 1] - y * der[:, 0]) / (x * x + y * y)
    return g, dg, val


def hp_crossings(lm: LocalMotion, speed: SpeedProfile, target_rel: np.ndarray, radius: np.ndarray,
                 t_start: np.ndarray, tol_s: float = 1e-13, max_iter: int = 12):
    """HP crossing times of tip nodes (paper Sec. 2.2, stage A, converged root of Eq. 8).

    One Newton step from the first-order start ``t_start``, then a simplified Newton step
    (the same derivative) that also yields the nodes' components; crossings whose last step
    still exceeds ``tol_s`` continue with full Newton steps (vectorised over them).

    Parameters
    ----------
    lm : LocalMotion
        (radial, tangential, axial) components of q nodes per crossing.
    target_rel, radius, t_start : ndarray, shape (q, n)

    Returns
    -------
    t : ndarray, shape (q, n)
        Crossing times, s.
    u : ndarray, shape (q, 3, n)
        Node displacement at the crossing, taken before the last step (<= ``tol_s``: its
        change is below 1e-12 m).
    residual_s : float
        Largest final Newton step, s.
    """
    lm_rt = lm.with_P(lm.P[:, :, :, :2])
    g, dg, _ = node_angle_residual(lm_rt, speed, t_start, target_rel, radius)
    t = t_start - g / dg
    g, _, u = node_angle_residual(lm, speed, t, target_rel, radius, derivative=False)
    step = g / dg
    t = t - step
    big = np.abs(step) > tol_s
    residual = float(np.max(np.abs(step))) if step.size else 0.0
    if np.any(big):  # not yet converged: full Newton on those crossings
        cols = np.flatnonzero(big.any(axis=0))
        sub = lm.take(cols)
        ts, tr, rr = t[:, cols], target_rel[:, cols], radius[:, cols]
        for _ in range(max_iter):
            g, dg, us = node_angle_residual(sub, speed, ts, tr, rr)
            step_s = g / dg
            ts = ts - step_s
            if np.max(np.abs(step_s)) <= tol_s:
                break
        t[:, cols] = ts
        u[:, :, cols] = us
        residual = max(float(np.max(np.abs(np.delete(step, cols, axis=1)), initial=0.0)),
                       float(np.max(np.abs(step_s))))
    return t, u, residual


def grid_crossings(lm: LocalMotion, speed: SpeedProfile, target_rel: np.ndarray, radius: np.ndarray,
                   t_hp: np.ndarray, dt: float, method: str) -> np.ndarray:
    """AD (Eq. 12) or PAD (Eq. 13-14) crossing times on the integrator grid ``i * dt``,
    from the exact states at the grid points bracketing the HP crossing ``t_hp`` (q, n)."""
    i = np.ceil(t_hp / dt)
    i = np.where(i * dt == t_hp, i + 1, i)  # t_hp in [t_{i-1}, t_i)
    g = [node_angle_residual(lm, speed, (i - k) * dt, target_rel, radius, derivative=False)[0]
         for k in (2, 1, 0)]
    t_prev = (i - 1) * dt
    if method == "AD":
        return t_prev - g[1] * dt / (g[2] - g[1])
    p_prev = g[1] * g[0]
    p_now = g[2] * g[1]
    return t_prev + dt * p_prev / (p_prev - p_now)

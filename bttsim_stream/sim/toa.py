"""Blade times of arrival: stage A crossing times (Eq. 8, 12-14) and stage B axial interpolation (Eq. 9-11).

Conventions
-----------
A *crossing* is one (revolution, blade, probe) event. For each crossing the rigid nominal
sensing point P_nom reaches the probe when the rotor angle is ``phi_c``; tip node ``n`` of
blade ``b`` reaches it when ``phi(t) + delta_n(t) = phi_c + theta_Pnom - theta_n`` with
``delta_n = atan2(u_tang, r_n + u_rad)`` its angular deflection (paper Eq. 8 with the
rotor-frame angle of the deformed node). Times in s, angles in rad.

Stage A, per tip node:

* ``HP``: Newton's method from the rigid crossing time on the exact response, to a
  residual of 1e-13 s (quadratic convergence: 2-4 iterations).
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
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .modal import EnvelopeGrid
from .speed import SpeedProfile

__all__ = ["CrossingSet", "prepare_crossings", "eval_compressed", "node_displacement", "eval_nodes", "stage_a_hp", "stage_a_grid", "stage_b"]


@dataclass(frozen=True, slots=True, eq=False)
class CrossingSet:
    """Per-crossing data for evaluating one blade's tip motion near one arrival.

    Attributes
    ----------
    blade : ndarray, shape (n_c,)
    t0 : ndarray, shape (n_c,)
        Start of the envelope grid interval used for this crossing, s.
    P : ndarray, shape (4, n_c, n_exc, r), complex
        Cubic Hermite coefficients of the blade envelope in ``tau = t - t0``.
    nodes : ndarray, shape (r, n_tip, 3)
        Compressed coordinates -> node displacements (common to all blades).
    """

    blade: np.ndarray
    t0: np.ndarray
    P: np.ndarray
    nodes: np.ndarray


def prepare_crossings(env: EnvelopeGrid, blade: np.ndarray, t_guess: np.ndarray,
                      nodes_basis: np.ndarray) -> CrossingSet:
    """Gather the Hermite coefficients of each crossing's blade envelope around ``t_guess``."""
    i = np.clip(np.searchsorted(env.t, t_guess, side="right") - 1, 0, env.t.size - 2)
    t0, t1 = env.t[i], env.t[i + 1]
    h = (t1 - t0)[:, None, None]
    G0, G1 = env.G[i, :, blade], env.G[i + 1, :, blade]
    D0, D1 = env.dG[i, :, blade], env.dG[i + 1, :, blade]
    dG = (G1 - G0) / h
    P2 = (3.0 * dG - 2.0 * D0 - D1) / h
    P3 = (D0 + D1 - 2.0 * dG) / (h * h)
    return CrossingSet(blade=blade, t0=t0, P=np.stack([G0, D0, P2, P3]), nodes=nodes_basis)


def eval_compressed(cs: CrossingSet, speed: SpeedProfile, eo: np.ndarray, t: np.ndarray,
                    derivative: bool = True):
    """Compressed tip coordinates ``w`` (and ``dw/dt``) at times ``t`` of shape (n_c, q)."""
    tau = (t - cs.t0[:, None])[..., None, None]  # (n_c, q, 1, 1)
    P0, P1, P2, P3 = (p[:, None] for p in cs.P)  # (n_c, 1, n_exc, r)
    G = P0 + tau * (P1 + tau * (P2 + tau * P3))
    phi, om, _ = speed.state(t)
    arg = eo[None, None, :] * phi[..., None]
    cr, ci = np.cos(arg)[..., None], np.sin(arg)[..., None]  # carrier exp(i EO phi)
    w = np.sum(G.imag * cr + G.real * ci, axis=2)  # Im(G carrier), (n_c, q, r)
    if not derivative:
        return w, None
    H = P1 + tau * (2.0 * P2 + 3.0 * tau * P3) + 1j * (eo[None, None, :] * om[..., None])[..., None] * G
    return w, np.sum(H.imag * cr + H.real * ci, axis=2)


def node_displacement(w: np.ndarray, nodes_basis: np.ndarray, node: np.ndarray) -> np.ndarray:
    """(n_c, q, r) compressed coordinates -> (n_c, q, 3) displacement of tip node ``node``."""
    V = nodes_basis[:, node, :]  # (r, n_c, q, 3)
    return np.einsum("cqr,rcqd->cqd", w, V)


def eval_nodes(cs: CrossingSet, speed: SpeedProfile, eo: np.ndarray, t: np.ndarray,
               node: np.ndarray, derivative: bool = True):
    """Displacement (and velocity) of tip nodes at times ``t``.

    Parameters
    ----------
    t, node : ndarray, shape (n_c, q)
        Query times and tip-node indices for each crossing.

    Returns
    -------
    u, du : ndarray, shape (n_c, q, 3)
        (radial, tangential, axial) displacement (m) and velocity (m/s); ``du`` is None
        when ``derivative`` is false.
    """
    w, dw = eval_compressed(cs, speed, eo, t, derivative)
    u = node_displacement(w, cs.nodes, node)
    return u, (None if dw is None else node_displacement(dw, cs.nodes, node))


def _angle_residual(cs, speed, eo, t, node, target, radius, derivative=True):
    u, du = eval_nodes(cs, speed, eo, t, node, derivative)
    x = radius + u[..., 0]
    y = u[..., 1]
    phi, om, _ = speed.state(t)
    g = phi + np.arctan2(y, x) - target
    if not derivative:
        return g, u, None
    dg = om + (x * du[..., 1] - y * du[..., 0]) / (x * x + y * y)
    return g, u, dg


def stage_a_hp(cs: CrossingSet, speed: SpeedProfile, eo: np.ndarray, node: np.ndarray,
               target: np.ndarray, radius: np.ndarray, t_start: np.ndarray,
               tol_s: float = 1e-13, max_iter: int = 12):
    """HP crossing times by Newton's method (vectorised over all crossings and nodes).

    Parameters
    ----------
    node, target, radius, t_start : ndarray, shape (n_c, q)
        Tip node index, rotor-angle target ``phi_c + theta_Pnom - theta_n`` (rad), the node's
        reference radius (m) and the starting time (s).

    Returns
    -------
    t : ndarray, shape (n_c, q)
        Crossing times, s.
    u : ndarray, shape (n_c, q, 3)
        Node displacement at the crossing.
    residual_s : float
        Largest final Newton step, s.
    """
    t = t_start.copy()
    for _ in range(max_iter):
        g, u, dg = _angle_residual(cs, speed, eo, t, node, target, radius)
        step = g / dg
        t = t - step
        if np.max(np.abs(step)) <= tol_s:
            break
    # u is taken before the last step (<= tol_s): its change is below 1e-12 m
    return t, u, float(np.max(np.abs(step)))


def stage_a_grid(cs: CrossingSet, speed: SpeedProfile, eo: np.ndarray, node: np.ndarray,
                 target: np.ndarray, radius: np.ndarray, t_hp: np.ndarray, dt: float, method: str):
    """AD (Eq. 12) or PAD (Eq. 13-14) crossing times on the integrator grid ``i * dt``."""
    i = np.ceil(t_hp / dt)
    i = np.where(i * dt == t_hp, i + 1, i)  # t_hp in [t_{i-1}, t_i)
    tg = np.stack([(i - 2) * dt, (i - 1) * dt, i * dt], axis=-1)  # (n_c, q, 3)
    n_c, q = node.shape
    g, _, _ = _angle_residual(cs, speed, eo, tg.reshape(n_c, q * 3), np.repeat(node, 3, axis=1),
                              np.repeat(target, 3, axis=1), np.repeat(radius, 3, axis=1),
                              derivative=False)
    g = g.reshape(n_c, q, 3)
    if method == "AD":
        return tg[..., 1] - g[..., 1] * dt / (g[..., 2] - g[..., 1])
    p_prev = g[..., 1] * g[..., 0]
    p_now = g[..., 2] * g[..., 1]
    return tg[..., 1] + dt * p_prev / (p_prev - p_now)


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

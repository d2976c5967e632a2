"""The brute-force TOA reference shared by the simulator's tests.

A test integrates the responding modes with ``solve_ivp`` (its own right-hand side: fixed
modes, non-synchronous carriers, speed-dependent modes); :func:`newton_toas` then solves paper
Eq. 8 for every tip node by Newton's method on that solution and applies Eq. 9-11
(:func:`~bttsim_stream.sim.toa.stage_b`).
"""

import numpy as np

from bttsim_stream.sim.toa import stage_b


def initial_state(sim):
    """The simulator's modal displacements and velocities at t = 0 (before it runs)."""
    integ = sim.integrator
    lam = integ.lam[:, 0]
    z0 = integ.modal_state(0.0, 0.0, integ.a_plus, integ.a_minus)
    return np.concatenate([np.imag(z0) / lam.imag, np.imag(lam * z0) / lam.imag])


def fixed_mode_motion(sol, shapes, n, extra=None):
    """Tip motion ``motion(t, bi, b, node) -> (u, du)`` of fixed mode shapes ``shapes`` (n, ..., 3)
    (already gathered at the tip nodes of the reference) from the dense ``solve_ivp`` solution
    ``sol`` of ``n`` modes (displacements then velocities), plus ``extra(t, b, node)`` -- a
    displacement and velocity added in closed form -- if given."""

    def motion(t, bi, b, node):
        y = sol.sol(t.ravel()).reshape(2 * n, *t.shape)
        u = np.einsum("k...,k...c->...c", y[:n], shapes)
        du = np.einsum("k...,k...c->...c", y[n:], shapes)
        if extra is not None:
            e, de = extra(t, b, node)
            u, du = u + e, du + de
        return u, du

    return motion


def tip_grid(sim, run, blades):
    """Index arrays of the reference: (bi, b, node), each of shape (n_rev, blades, probes, n_tip)."""
    t_exp = run.truth.t_exp_s[:, blades]
    shape = t_exp.shape + (sim.model.n_tip,)
    bi = np.broadcast_to(np.arange(len(blades))[None, :, None, None], shape)
    b = np.asarray(blades)[bi]
    node = np.broadcast_to(np.arange(sim.model.n_tip)[None, None, None, :], shape)
    return bi, b, node


def newton_toas(sim, run, blades, motion, *, iterations, tol):
    """TOAs (n_rev, blades, probes): Newton on Eq. 8 for every tip node from the expected
    arrival times, with the tip motion ``motion(t, bi, b, node) -> (u, du)`` ((..., 3) each, in
    (radial, tangential, axial)), then Eq. 9-11. Asserts the angle residual is below ``tol`` rad."""
    m, speed = sim.model, sim.speed
    t_exp = run.truth.t_exp_s[:, blades]
    nr, nbs, npr = t_exp.shape
    nt = m.n_tip
    bi, b, node = tip_grid(sim, run, blades)
    theta_j = np.broadcast_to(sim.probe_actual[None, None, :, None], b.shape)
    r_ref, th_ref, z_ref = (m.tip_ref[b, node, i] for i in range(3))
    turn = np.round((m.tip_ref[b, m.nominal_node, 1] + speed.angle(t_exp[..., None]) - theta_j) / (2 * np.pi))
    t = np.broadcast_to(t_exp[..., None], b.shape).copy()
    for _ in range(iterations):
        u, du = motion(t, bi, b, node)
        x, yt = r_ref + u[..., 0], u[..., 1]
        g = th_ref + speed.angle(t) + np.arctan2(yt, x) - theta_j - 2 * np.pi * turn
        t = t - g / (speed.speed(t) + (x * du[..., 1] - yt * du[..., 0]) / (x * x + yt * yt))
    assert np.max(np.abs(g)) < tol
    u, _ = motion(t, bi, b, node)
    dz = z_ref + u[..., 2] - sim.z_probe
    return stage_b(t.reshape(-1, nt), dz.reshape(-1, nt))[0].reshape(nr, nbs, npr)

"""Exactness of the modal integration and of the HP crossing times against independent references."""

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.optimize import brentq

from bttsim_stream.scenario import scenario_from_dict
from bttsim_stream.sim.core import RunUpSimulator, collect
from bttsim_stream.sim.modal import (
    EnvelopeIntegrator,
    TipBasis,
    build_grid,
    chirp_integral,
    modal_forcing,
    tip_basis,
)
from bttsim_stream.sim.speed import RPM, SpeedProfile
from bttsim_stream.sim.toa import stage_b

ONE = TipBasis(psi=np.ones((1, 1, 1)), nodes=np.ones((1, 1, 3)))


def _sdof(speed, f_hz, zeta, eo, force, initial, h=1e-3):
    integ = EnvelopeIntegrator([f_hz], [zeta], np.array([[force]], complex), [eo], ONE, speed, initial)
    t = build_grid(speed, h)
    env = integ.advance(t)
    phi, om, _ = speed.state(t)
    carrier = np.exp(1j * eo * phi)
    q = np.imag(env.G[:, 0, 0, 0] * carrier)
    dq = np.imag((env.dG[:, 0, 0, 0] + 1j * eo * om * env.G[:, 0, 0, 0]) * carrier)
    return t, q, dq


def _analytic_sdof(t, w, zeta, wf, F, psi):
    """q'' + 2 zeta w q' + w^2 q = F sin(wf t + psi) from rest: steady part + transient."""
    wd = w * np.sqrt(1 - zeta**2)
    D = (w**2 - wf**2) ** 2 + (2 * zeta * w * wf) ** 2
    a = F * (w**2 - wf**2) / D
    b = -F * 2 * zeta * w * wf / D
    qp = a * np.sin(wf * t + psi) + b * np.cos(wf * t + psi)
    dqp = wf * (a * np.cos(wf * t + psi) - b * np.sin(wf * t + psi))
    A = -(a * np.sin(psi) + b * np.cos(psi))
    B = (-wf * (a * np.cos(psi) - b * np.sin(psi)) + zeta * w * A) / wd
    e = np.exp(-zeta * w * t)
    qh = e * (A * np.cos(wd * t) + B * np.sin(wd * t))
    dqh = e * (-zeta * w * (A * np.cos(wd * t) + B * np.sin(wd * t)) + wd * (-A * np.sin(wd * t) + B * np.cos(wd * t)))
    return qp, dqp, qp + qh, dqp + dqh


@pytest.mark.parametrize("f_hz,zeta,eo,rps", [(100.0, 0.02, 4, 23.0), (344.0, 0.0097, 8, 43.0),
                                              (3500.0, 0.1, 8, 40.0)], ids=["off", "resonant", "stiff"])
def test_constant_speed_matches_analytic_sdof(f_hz, zeta, eo, rps):
    om = 2 * np.pi * rps
    speed = SpeedProfile(np.array([0.0, 1.5]), np.array([om, om]))
    F = 2.25
    t, q, dq = _sdof(speed, f_hz, zeta, eo, F, "rest")
    _, _, q_ref, dq_ref = _analytic_sdof(t, 2 * np.pi * f_hz, zeta, eo * om, F, 0.0)
    assert np.max(np.abs(q - q_ref)) <= 1e-8 * np.max(np.abs(q_ref))
    assert np.max(np.abs(dq - dq_ref)) <= 1e-8 * np.max(np.abs(dq_ref))
    # the "steady" start is the analytic steady-state response, with no transient at all
    t, q, dq = _sdof(speed, f_hz, zeta, eo, F, "steady")
    qp, dqp, _, _ = _analytic_sdof(t, 2 * np.pi * f_hz, zeta, eo * om, F, 0.0)
    assert np.max(np.abs(q - qp)) <= 1e-10 * np.max(np.abs(qp))


@pytest.mark.parametrize("h", [5e-4, 2e-3, 1e-2], ids=["h0.5ms", "h2ms", "h10ms"])
def test_chirp_window_matches_tight_solve_ivp(h):
    speed = SpeedProfile(np.array([0.0, 0.3, 0.6]), np.array([38.0, 45.0, 41.0]) * 2 * np.pi)
    f_hz, zeta, eo, F = 344.0, 0.0097, 8, 2.25
    t, q, _ = _sdof(speed, f_hz, zeta, eo, F, "rest", h=h)
    w = 2 * np.pi * f_hz

    def rhs(tt, y):
        return [y[1], F * np.sin(eo * speed.angle(tt)) - 2 * zeta * w * y[1] - w * w * y[0]]

    sol = solve_ivp(rhs, (0.0, t[-1]), [0.0, 0.0], method="DOP853", rtol=1e-13, atol=1e-18,
                    t_eval=t, max_step=2e-4)
    assert np.max(np.abs(q - sol.y[0])) <= 1e-8 * np.max(np.abs(sol.y[0]))


def test_chirp_integral_against_quadrature():
    rng = np.random.default_rng(0)
    u = np.concatenate([rng.normal(size=20) * 0.1 + 1j * rng.normal(size=20) * 0.1,
                        -rng.uniform(0, 5, 20) + 1j * rng.normal(size=20) * 30])
    v = 1j * rng.uniform(-1e-4, 1e-4, u.size)
    x = np.linspace(0, 1, 200001)
    f = np.exp(u[:, None] * x[None] + v[:, None] * x[None] ** 2)
    from scipy.integrate import simpson
    ref = simpson(f, x=x, axis=1)
    np.testing.assert_allclose(chirp_integral(u, v), ref, rtol=1e-10)


def test_speed_profile_is_eq6_and_invertible():
    speed = SpeedProfile(np.array([0.0, 130.0]), np.array([1000.0, 4000.0]) * RPM)
    t = np.linspace(0, 130, 1001)
    wi, wf = 1000 * RPM, 4000 * RPM
    np.testing.assert_allclose(speed.angle(t), wi * t + (wf - wi) / (2 * 130) * t**2, rtol=1e-14)
    np.testing.assert_allclose(speed.time_at_angle(speed.angle(t)), t, atol=1e-12)
    seg = SpeedProfile(np.array([0.0, 1.0, 3.0, 4.0]), np.array([100.0, 200.0, 200.0, 50.0]))
    tt = np.linspace(0, 4, 4001)
    phi = seg.angle(tt)
    np.testing.assert_allclose(np.gradient(phi, tt)[1:-1], seg.speed(tt)[1:-1], rtol=1e-3)
    np.testing.assert_allclose(seg.time_at_angle(phi), tt, atol=1e-12)


# --- HP TOAs against brute-force root finding on the direct modal sum ---------------------

DWELL = {"speed": {"start_rpm": 2570.0, "segments": [{"duration_s": 0.25, "end_rpm": 2590.0}]}}


@pytest.fixture(scope="module")
def dwell_run():
    scn = scenario_from_dict(DWELL)
    sim = RunUpSimulator(scn, chunk_revolutions=3)
    return scn, sim, collect(sim)


def _reference_node_angle(sim, integ, env, blade, node):
    """Exact rotor-frame angle of a tip node from the modal states (no envelope interpolation,
    no compression): direct sum over the modes."""
    m = sim.model
    act = integ.active
    wd = 2 * np.pi * m.freq_hz[act] * np.sqrt(1 - m.damping_ratio[act] ** 2)
    shapes = m.tip_shapes[act][:, blade, node, :]
    r_ref, th_ref, z_ref = m.tip_ref[blade, node]

    def state(t):
        i = int(np.clip(np.searchsorted(env.t, t, side="right") - 1, 0, env.t.size - 2))
        z = integ.modal_state(t, env.t[i], env.a_plus[i], env.a_minus[i])
        u = (np.imag(z) / wd) @ shapes
        return th_ref + sim.speed.angle(t) + np.arctan2(u[1], r_ref + u[0]), z_ref + u[2]

    return state


def test_hp_toas_match_brute_force_root_finding(dwell_run):
    scn, sim, res = dwell_run
    m = sim.model
    C, eo = modal_forcing(m, scn.excitation)
    integ = EnvelopeIntegrator(m.freq_hz, m.damping_ratio, C, eo, tip_basis(m.tip_shapes), sim.speed)
    env = integ.advance(build_grid(sim.speed, 2e-3), keep_modal=True)
    rng = np.random.default_rng(1)
    picks = [(n, b, j) for n in (1, 5) for b in rng.choice(29, 6, replace=False) for j in (0, 3)]
    worst = 0.0
    for n, b, j in picks:
        t_exp = res.truth.t_exp_s[n, b, j]
        theta_j = sim.probe_actual[j]
        k_turn = np.round((m.tip_ref[b, 4, 1] + sim.speed.angle(t_exp) - theta_j) / (2 * np.pi))
        t_det, dz = np.zeros(9), np.zeros(9)
        for node in range(9):
            state = _reference_node_angle(sim, integ, env, b, node)
            g = lambda t: state(t)[0] - theta_j - 2 * np.pi * k_turn
            t_det[node] = brentq(g, t_exp - 1e-3, t_exp + 1e-3, xtol=1e-15, rtol=1e-15, maxiter=200)
            dz[node] = state(t_det[node])[1] - scn.probes.axial_position_m
        toa_ref, _, _ = stage_b(t_det[None], dz[None])
        worst = max(worst, abs(toa_ref[0] - res.toa_s[n, b, j]))
    assert worst <= 1e-11, worst
    assert res.residual_s <= 1e-12


def test_travelling_wave_phase_eq7(dwell_run):
    """Tuned wheel, ND 1 forcing (Eq. 7): only the ND 1 modes respond, and every blade's
    response is blade 0's shifted by the travelling-wave phase 2 pi b N_ND / N_b."""
    scn, sim, _ = dwell_run
    m = sim.model
    assert set(m.nodal_diameter[sim.integrator.active].tolist()) == {1}
    C, eo = modal_forcing(m, scn.excitation)
    basis = tip_basis(m.tip_shapes)
    integ = EnvelopeIntegrator(m.freq_hz, m.damping_ratio, C, eo, basis, sim.speed)
    env = integ.advance(build_grid(sim.speed, 2e-3))
    G = np.einsum("tmbr,rnd->tmbnd", env.G, basis.nodes)[:, 0, :, 4, 1]  # P_nom tangential
    shift = np.exp(2j * np.pi * np.arange(29) / 29)
    np.testing.assert_allclose(G, G[:, :1] * shift[None, :], rtol=0, atol=1e-9 * np.abs(G).max())

"""Exactness of the modal integration and of the HP crossing times against independent references."""

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.optimize import brentq

from bttsim_stream.scenario import scenario_from_dict
from bttsim_stream.sim.core import RunUpSimulator, collect
from bttsim_stream.sim.forcing import modal_forcing
from bttsim_stream.sim.modal import (
    EnvelopeIntegrator,
    GridPoints,
    TipBasis,
    build_grid,
    chirp_integral,
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

            def g(t):
                return state(t)[0] - theta_j - 2 * np.pi * k_turn

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


# --- the fast paths of the envelope integration and of the crossings ------------------------


def test_chirp_given_exp_against_quadrature():
    """The recursion's chirp integral (exp(u) supplied as a product) against quadrature and
    against chirp_integral, in both of its regions (recurrence; series near u = 0)."""
    from scipy.integrate import simpson

    from bttsim_stream.sim.modal import _chirp_given_exp

    rng = np.random.default_rng(4)
    u = np.concatenate([rng.normal(size=30) * 0.1 + 1j * rng.normal(size=30) * 0.1,  # series
                        -rng.uniform(0, 5, 30) + 1j * rng.normal(size=30) * 30,  # recurrence
                        0.02 + 0.01j * rng.normal(size=10)])  # |v| > |u|^2 / 10: series
    v = 1j * rng.uniform(-3e-3, 3e-3, u.size)
    x = np.linspace(0, 1, 200001)
    ref = simpson(np.exp(u[:, None] * x[None] + v[:, None] * x[None] ** 2), x=x, axis=1)
    got = _chirp_given_exp(u, np.exp(u), v)
    np.testing.assert_allclose(got, ref, rtol=1e-10)
    np.testing.assert_allclose(got, chirp_integral(u, v), rtol=1e-13)


def _modal_run(quasi_steady, speed, initial, h=2e-3, block=64):
    """Envelopes of a few modes (the far-off families and one resonant mode) along ``speed``."""
    f_hz = np.array([344.0, 900.0, 1700.0, 3500.0])
    zeta = 0.5 * 9e-6 * 2 * np.pi * f_hz
    C = np.array([[2.25], [1.0 - 0.5j], [0.3j], [0.2]])
    basis = TipBasis(psi=np.ones((4, 1, 1)), nodes=np.ones((1, 1, 3)))
    integ = EnvelopeIntegrator(f_hz, zeta, C, [8], basis, speed, initial, quasi_steady=quasi_steady)
    t = build_grid(speed, h)
    ap, am = [], []
    i = 0
    while i < t.size - 1:
        stop = min(i + block, t.size - 1)
        env = integ.advance(t[i:stop + 1], keep_modal=True)
        ap.append(env.a_plus[1 if i else 0:])
        am.append(env.a_minus[1 if i else 0:])
        i = stop
    return integ, t, np.concatenate(ap)[..., 0], np.concatenate(am)[..., 0]


@pytest.mark.slow
def test_quasi_steady_envelopes_against_full_recursion_and_solve_ivp():
    """The quasi-steady series (with its bound, QUASI_STEADY_TOL) against the exact recursion
    everywhere, and the physical response against solve_ivp; a run-up with a speed knot, from
    rest (the homogeneous part matters), through the resonance of the first mode."""
    speed = SpeedProfile(np.array([0.0, 0.8, 1.2]), np.array([42.0, 43.5, 42.5]) * 2 * np.pi)
    qs, t, ap_q, am_q = _modal_run(True, speed, "rest")
    ex, _, ap_x, am_x = _modal_run(False, speed, "rest")
    assert qs.stats["quasi_steady"] > 2 * qs.stats["exact"] > 0  # both paths taken
    for a, b in ((ap_q, ap_x), (am_q, am_x)):
        scale = np.abs(b).max(axis=0)
        assert np.all(np.abs(a - b).max(axis=0) <= 1e-12 * scale)
    # the physical response q_k = Im(a+ e^{i EO phi} + a- e^{-i EO phi}) / w_dk of the
    # resonant mode and of a far one, against one tight solve_ivp of both
    phi = speed.angle(t)
    carrier = np.exp(8j * phi)[:, None]
    q = np.imag(ap_q * carrier + am_q * np.conj(carrier)) / qs.lam[:, 0].imag
    k = np.array([0, 2])
    w = 2 * np.pi * np.array([344.0, 900.0, 1700.0, 3500.0])[k]
    zeta = 0.5 * 9e-6 * w
    F = np.array([2.25, 1.0 - 0.5j, 0.3j, 0.2])[k]

    def rhs(tt, y):
        return np.concatenate([y[2:], np.imag(F * np.exp(8j * speed.angle(tt))) - 2 * zeta * w * y[2:] - w * w * y[:2]])

    sol = solve_ivp(rhs, (0.0, t[-1]), np.zeros(4), method="DOP853", rtol=1e-13, atol=1e-18, t_eval=t, max_step=2e-4)
    for col, ref in zip(k, sol.y[:2]):
        assert np.max(np.abs(q[:, col] - ref)) <= 1e-8 * np.max(np.abs(ref)), col


def test_envelopes_keep_their_precision_at_large_rotor_angles():
    """A minute of run-up (rotor angles ~1e4 rad, 30,000 steps): the exact recursion forms its
    phase steps without the large angles and agrees with the quasi-steady series (no
    recursion at all) to its accumulated round-off (seen: 2.4e-13); phase steps taken from
    the rounded rotor angles drifted by ~2e-11."""
    speed = SpeedProfile(np.array([0.0, 60.0]), np.array([1000.0, 2400.0]) * RPM)
    _, _, ap_q, am_q = _modal_run(True, speed, "steady", block=1024)
    _, _, ap_x, am_x = _modal_run(False, speed, "steady", block=1024)
    for a, b in ((ap_q, ap_x), (am_q, am_x)):
        far = slice(1, None)  # the modes that stay far from resonance: quasi-steady throughout
        assert np.max(np.abs(a[:, far] - b[:, far]) / np.abs(b[:, far])) <= 1e-12


def test_angle_change_is_the_difference_of_angles():
    seg = SpeedProfile(np.array([0.0, 1.0, 3.0, 4.0]), np.array([100.0, 200.0, 200.0, 50.0]))
    t_ref = np.array([0.5, 0.9999, 2.0, 3.99, 3.5])
    t = t_ref[:, None] + np.array([-2e-3, -1e-4, 0.0, 1e-4, 2e-3])[None, :]  # some cross a knot
    d, om = seg.angle_change(t_ref[:, None], t)
    np.testing.assert_allclose(d, seg.angle(t) - seg.angle(t_ref)[:, None], rtol=0, atol=1e-12)
    np.testing.assert_allclose(om, seg.speed(t), rtol=1e-15)
    t1 = 2.0 + 1e-9
    small = seg.angle_change(np.array([2.0]), np.array([t1]))[0]  # a dwell at 200 rad/s
    assert abs(small[0] - 200.0 * (t1 - 2.0)) <= 4e-16 * small[0]  # relative precision of a small angle


def test_chunking_is_bit_for_bit():
    """Every number of a batch is computed per crossing, and the envelopes per global grid
    block: the chunk size changes nothing (the paced simulator node uses 1 revolution)."""
    d = {"speed": {"start_rpm": 2500.0, "end_rpm": 2600.0, "duration_s": 1.5}, "run": {"seed": 9},
         "acquisition": {"trigger_jitter_s": 1e-7, "clock_hz": 1e8}, "model": {"stiffness_std": 0.01}}
    scn = scenario_from_dict(d)
    runs = [collect(RunUpSimulator(scn, chunk_revolutions=c)) for c in (1, 7, 32)]
    for other in runs[1:]:
        np.testing.assert_array_equal(other.toa_ticks, runs[0].toa_ticks)
        np.testing.assert_array_equal(other.opr_s, runs[0].opr_s)
        for f in ("toa_s", "t_exp_s", "d_eqv_m", "d_tang_m", "d_z_m", "d_eq1_m", "d_eqv_pkpk_m"):
            np.testing.assert_array_equal(getattr(other.truth, f), getattr(runs[0].truth, f), err_msg=f)


def test_grid_points_on_demand_are_build_grid():
    speed = SpeedProfile(np.array([0.0, 1.0, 3.0, 3.01, 4.0]), np.array([100.0, 200.0, 200.0, 190.0, 50.0]))
    for h in (2e-3, 7e-3, 1.0):
        g = build_grid(speed, h)
        pts = GridPoints(speed, h)
        assert pts.size == g.size
        np.testing.assert_array_equal(pts.points(0, g.size), g)
        np.testing.assert_array_equal(pts.points(5, 17), g[5:17])
        for t in np.concatenate([g[::7], np.linspace(-1.0, 5.0, 101)]):
            assert pts.searchsorted(t) == np.searchsorted(g, t)

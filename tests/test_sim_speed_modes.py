"""Speed-dependent modes (issue 13): interpolation, the run-up against a solve_ivp reference on
the reduced speed-dependent system, and the resonance where the Campbell diagram puts it.

The models are synthetic Southwell models (:func:`~bttsim_stream.model.speed_modes.southwell_model`)
built from the built-in zero-speed model: ``w_k^2 = w_k0^2 + kappa Omega^2`` and shapes that
scale and twist smoothly with ``Omega^2``.

The reference integrates, independently of the envelope machinery, the reduced system of
:mod:`bttsim_stream.sim.speed_modal`:
``q_k'' + 2 zeta_k w_k(Omega) q_k' + w_k(Omega)^2 q_k = Im(sum_m C_km(Omega) exp(i EO_m phi(t)))``,
tip motion ``sum_k psi_k(Omega) q_k`` with the full (uncompressed) tip shapes, every quantity
interpolated as the model file says (natural cubic splines in ``Omega^2``, built here with
scipy directly), by ``solve_ivp`` (DOP853, rtol 1e-11, dense output), then Newton on paper
Eq. 8 for every tip node and Eq. 9-11, as ``tests/test_sim_transient.py`` does.
"""

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.interpolate import CubicSpline

from _reference import newton_toas

from bttsim_stream import cli
from bttsim_stream.errors import BttsimError
from bttsim_stream.model import build_model, save_model
from bttsim_stream.model.speed_modes import SpeedModes, check_speed_range, southwell_model, speed_modes
from bttsim_stream.scenario import scenario_from_dict
from bttsim_stream.sim.core import RunUpSimulator, collect
from bttsim_stream.sim.forcing import modal_forcing
from bttsim_stream.sim.speed import RPM
from bttsim_stream.sim.speed_modal import chirp_moments

KAPPA = 1.5
TOP = 4200.0 * RPM
RATE = 3000.0 / 130.0  # the paper's run-up, rpm/s


@pytest.fixture(scope="module")
def one_family():
    """The built-in model with one family (the ND 1 pair responds) and its Southwell version."""
    scn = scenario_from_dict({"model": {"n_families": 1}})
    m0 = build_model(scn)
    return m0, southwell_model(m0, np.linspace(0.0, TOP, 5), KAPPA, shape_change=0.05)


def _resonance_rpm(f0_hz, eo=8, kappa=KAPPA):
    """EO Omega = w(Omega) with w^2 = w0^2 + kappa Omega^2."""
    return 2 * np.pi * f0_hz / np.sqrt(eo * eo - kappa) / RPM


# --- interpolation -----------------------------------------------------------------------


def test_two_samples_give_the_southwell_line_and_splines_hit_their_samples(one_family):
    m0, m = one_family
    w0 = 2 * np.pi * m0.freq_hz
    om = np.linspace(0.0, TOP, 37)
    lin = southwell_model(m0, [0.0, TOP], KAPPA)
    f_lin = speed_modes(lin).freq_hz(om)
    np.testing.assert_allclose(f_lin, np.sqrt(w0**2 + KAPPA * om[:, None] ** 2) / (2 * np.pi), rtol=1e-13)
    sm = speed_modes(m)
    np.testing.assert_allclose(sm.freq_hz(sm.speed_rad_s), m.extra["freq_hz_at_speed"], rtol=1e-14)
    # a smooth curve that is not linear in Omega^2: the natural spline converges on it
    s_top = TOP**2
    err = []
    for n in (5, 9, 17, 33):
        sp = np.sqrt(np.linspace(0.0, 1.0, n)) * TOP  # evenly spaced in Omega^2
        y = np.sin(2.0 * sp**2 / s_top)
        spl = SpeedModes(speed_rad_s=sp, omega2=None).spline(y)
        np.testing.assert_allclose(spl(sp**2), y, atol=1e-14)
        err.append(np.max(np.abs(spl(om**2) - np.sin(2.0 * om**2 / s_top))))
        assert abs(spl(0.0, 2)) < 1e-20 and abs(spl(s_top, 2)) < 1e-20  # natural ends
    assert err[0] < 0.02 and np.all(np.diff(np.log2(err)) < -1.5), err  # converging (2nd order at the ends)


def test_chirp_moments_against_quadrature():
    from scipy.integrate import simpson

    rng = np.random.default_rng(5)
    u = np.concatenate([rng.normal(size=20) * 0.1 + 1j * rng.normal(size=20) * 0.1,
                        -rng.uniform(0, 5, 20) + 1j * rng.normal(size=20) * 30])
    v = rng.uniform(-1e-4, 1e-4, u.size) + 1j * rng.uniform(-3e-3, 3e-3, u.size)
    x = np.linspace(0, 1, 200001)
    f = np.exp(u[:, None] * x[None] + v[:, None] * x[None] ** 2)
    I0, I1 = chirp_moments(u, v)
    np.testing.assert_allclose(I0, simpson(f, x=x, axis=1), rtol=1e-10)
    np.testing.assert_allclose(I1, simpson(x[None] * f, x=x, axis=1), rtol=1e-10)


def test_speed_above_the_last_sample_is_refused(one_family, tmp_path, capsys):
    _, m = one_family
    check_speed_range(m, TOP)
    with pytest.raises(BttsimError, match="stop at 4200 rpm"):
        check_speed_range(m, 4300.0 * RPM)
    path = tmp_path / "sd.npz"
    save_model(m, path)
    scn = tmp_path / "s.toml"
    scn.write_text(f'[model]\nsource = "{path}"\n[speed]\nstart_rpm = 4000.0\n'
                   '[[speed.segments]]\nduration_s = 1.0\nend_rpm = 4400.0\n')
    assert cli.main(["simulate", str(scn), "--out", str(tmp_path / "o.mcap"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("bttsim: error:") and err.count("\n") == 1 and "4400 rpm" in err, err


# --- the run-up against solve_ivp on the reduced system -----------------------------------


def _reference_toas(sim, run, blades, t_start, y0):
    """solve_ivp of the reduced speed-dependent system from ``y0`` at ``t_start`` (the first
    segment's sweep extended back when ``t_start < 0``), then Eq. 8 and Eq. 9-11."""
    m, speed = sim.model, sim.speed
    act = sim.integrator.active
    n = act.size
    sp = m.extra["speed_rad_s"]
    s_k = sp**2

    def spl(a):
        return CubicSpline(s_k, a, axis=0, bc_type="natural")

    Cs = _forcing_at_speeds(m, sim.scn.excitation)[:, act]  # (S, n, n_exc)
    n_exc = Cs.shape[2]
    # w_k^2 and the modal forces in one spline (one evaluation per right-hand side)
    coef = spl(np.concatenate([(2 * np.pi * m.extra["freq_hz_at_speed"][:, act]) ** 2,
                               Cs.real.reshape(sp.size, -1), Cs.imag.reshape(sp.size, -1)], axis=1))
    eo = sim.eo
    zeta = m.damping_ratio[act]

    def rhs(t, y):
        phi, om, _ = speed.state(t)
        v = coef(om * om)
        wk2 = v[:n]
        C = (v[n:n + n * n_exc] + 1j * v[n + n * n_exc:]).reshape(n, n_exc)
        f = np.imag(C @ np.exp(1j * eo * phi))
        return np.concatenate([y[n:], f - 2 * zeta * np.sqrt(wk2) * y[n:] - wk2 * y[:n]])

    sol = solve_ivp(rhs, (t_start, speed.duration_s), y0, method="DOP853", rtol=1e-11, atol=1e-17,
                    dense_output=True)
    assert sol.status == 0
    tips = spl(m.extra["tip_shapes_at_speed"][:, act][:, :, blades])  # (n, blades, nt, 3) at s

    def motion(t, bi, b, node):
        S = tips(speed.speed(t).ravel() ** 2)[np.arange(t.size), :, bi.ravel(), node.ravel()]  # (N, n, 3)
        y = sol.sol(t.ravel())
        u = np.einsum("kN,Nkc->Nc", y[:n], S).reshape(*t.shape, 3)
        du = np.einsum("kN,Nkc->Nc", y[n:], S).reshape(*t.shape, 3)
        return u, du

    # rad: round-off of the rotor angle (hundreds of rad)
    return newton_toas(sim, run, blades, motion, iterations=10, tol=1e-12)


def _forcing_at_speeds(m, excitations):
    """Modal forces (S, n_modes, n_exc) from the force shapes at each sample speed (Eq. 5-7)."""
    out = []
    te = m.extra["force_shapes_trailing_edge_at_speed"]
    for i in range(m.extra["speed_rad_s"].size):
        view = type("V", (), {"n_blades": m.n_blades, "n_modes": m.n_modes,
                              "force_shapes": m.extra["force_shapes_at_speed"][i],
                              "extra": {"force_shapes_trailing_edge": te[i]}})
        out.append(modal_forcing(view, excitations)[0])
    return np.stack(out)


def _quasi_steady_pkpk(m, excitations, active, om):
    """Harmonic pk-pk d_eqv (Eq. 3-4) of every blade at speeds ``om`` (n,) with the
    interpolated modes, one excitation: ``2 |sum_k C_k H_k eqv_k|``, shape (n, n_blades)."""
    sm = speed_modes(m)
    s = om**2
    wk = 2 * np.pi * sm.freq_hz(om)[:, active]
    Cs = _forcing_at_speeds(m, excitations)[:, active, 0]
    C = sm.spline(Cs.real)(s) + 1j * sm.spline(Cs.imag)(s)
    tip = sm.spline(m.extra["tip_shapes_at_speed"][:, active][:, :, :, m.nominal_node])(s)  # (n, k, b, 3)
    eqv = tip[..., 1] + tip[..., 2] / np.tan(np.deg2rad(m.meta["stagger_deg"]))
    wf = excitations[0].engine_order * om[:, None]
    zeta = m.damping_ratio[active]
    H = 1.0 / (wk**2 - wf**2 + 2j * zeta * wk * wf)
    return 2 * np.abs(np.einsum("nk,nkb->nb", C * H, eqv))


def _quasi_steady_u(m, excitations, om):
    """Harmonic complex amplitude of P_nom's (radial, tangential, axial) motion at speeds
    ``om`` (n,) with the interpolated modes, one excitation: shape (n, n_blades, 3)."""
    sm = speed_modes(m)
    s = om**2
    wk = 2 * np.pi * sm.freq_hz(om)
    Cs = _forcing_at_speeds(m, excitations)[:, :, 0]
    C = sm.spline(Cs.real)(s) + 1j * sm.spline(Cs.imag)(s)
    tip = sm.spline(m.extra["tip_shapes_at_speed"][:, :, :, m.nominal_node])(s)  # (n, k, b, 3)
    wf = excitations[0].engine_order * om[:, None]
    H = 1.0 / (wk**2 - wf**2 + 2j * m.damping_ratio * wk * wf)
    return np.abs(np.einsum("nk,nkbc->nbc", C * H, tip))


def _window(start_rpm, duration_s, initial, rate=RATE):
    return {"model": {"n_families": 1},
            "speed": {"start_rpm": start_rpm, "initial": initial,
                      "segments": [{"duration_s": duration_s, "end_rpm": start_rpm + rate * duration_s}]}}


TWO = {"excitation": [{"engine_order": 8, "nodal_diameter": 1, "amplitude_n": 2.25},
                      {"engine_order": 10, "nodal_diameter": 10, "amplitude_n": 1.5, "node": "trailing_edge"}]}


@pytest.mark.slow
@pytest.mark.parametrize("case,lead_s,refined", [
    (_window(2598.0, 1.2, "steady"), 1.2, False),  # steady start 12 rpm below the shifted resonance, across it
    (_window(2610.0, 0.25, "steady"), 1.2, False),  # steady start at the shifted resonance
    (_window(2605.0, 0.1, "rest"), 0.0, True),  # from rest just below it: the refined grid follows the transient
    ({"model": {"n_families": 1},  # a knot onto a dwell at the resonance: the quasi-steady envelope jumps
      "speed": {"start_rpm": 2606.0, "segments": [{"duration_s": 0.1, "end_rpm": 2610.0},
                                                  {"duration_s": 0.1, "end_rpm": 2610.0}]}}, 1.2, True),
    (dict(_window(2598.0, 0.3, "steady"), **TWO), 1.2, False),  # two excitations, one at the trailing edge
], ids=["steady-crossing", "steady-at-resonance", "rest-near-resonance", "knot-to-dwell", "two-excitations"])
def test_speed_dependent_run_matches_solve_ivp(one_family, case, lead_s, refined):
    _, m = one_family
    scn = scenario_from_dict(case)
    sim = RunUpSimulator(scn, m, chunk_revolutions=4)
    assert sim.integrator.warnings == []
    assert (sim.grid.refined > 0) == refined
    run = collect(sim)
    n = sim.integrator.active.size
    blades = [0, 11, 23]
    ref = _reference_toas(sim, run, blades, -lead_s, np.zeros(2 * n))  # from rest, lead_s before t = 0
    err = np.abs(run.toa_s[:, blades] - ref).max(axis=(1, 2))
    print("max TOA error per revolution, s:", err.max(), err[:3])
    assert err.size >= 4
    assert np.all(err <= 1e-10), err
    # the modes did move: the constant-mode simulator is far off in TOA here
    if lead_s and len(scn.excitation) == 1:
        const = collect(RunUpSimulator(scn, build_model(scn), chunk_revolutions=4))
        assert np.max(np.abs(const.toa_s[:, blades] - ref)) > 1e-7


def test_resonance_falls_where_the_campbell_diagram_says(one_family):
    """A slow run-up (1/10 of the paper's rate) through the EO 8 crossing of the stiffened ND 1
    family: the Campbell crossing ``8 Omega / 2 pi = f(Omega)`` on the interpolated family line
    is 30 rpm above the zero-speed one, and the simulated peak of pk-pk d_eqv falls there.

    Tolerances: the quasi-steady peak (the largest harmonic response ``|sum_k C_k H_k eqv_k|``
    of the interpolated modes) lies below the crossing by the damped-peak shift, about
    ``zeta^2`` of the speed (0.25 rpm); the swept peak lags the quasi-steady one by the sweep
    over two decay times, ``2 alpha / (zeta w)`` (0.22 rpm here: with ``a' = mu a + c``,
    ``mu = -sigma + i delta(t)``, the quasi-steady series ``a = -(c / mu)(1 - delta' i / mu^2)``
    has ``|a|^2`` peaking at ``delta = 2 delta' / sigma``, first order in the sweep rate),
    which is checked to 20 % plus half a revolution's speed change (0.03 rpm)."""
    m0, m = one_family
    sm = speed_modes(m)
    nd1 = np.flatnonzero(m.nodal_diameter == 1)[0]
    om = np.linspace(2560, 2660, 100001) * RPM
    f = sm.freq_hz(om)[:, nd1]
    i = np.flatnonzero(np.diff(np.sign(8 * om / (2 * np.pi) - f)))[0]
    campbell_rpm = om[i] / RPM
    assert abs(campbell_rpm - _resonance_rpm(m0.freq_hz[nd1])) < 0.01  # the Southwell line
    assert campbell_rpm - m0.freq_hz[nd1] * 60 / 8 > 25.0  # well away from the zero-speed crossing
    rate = RATE / 10
    scn = scenario_from_dict(_window(campbell_rpm - 6.0, 12.0 / rate, "steady", rate=rate))
    sim = RunUpSimulator(scn, m)
    run = collect(sim)
    pk = run.truth.d_eqv_pkpk_m.mean(axis=1)
    j = int(np.argmax(pk))
    peak_rpm = run.truth.omega_mean[j] / RPM
    # quasi-steady response of the interpolated modes
    oq = np.linspace(campbell_rpm - 2, campbell_rpm + 2, 4001) * RPM
    qs_pk = _quasi_steady_pkpk(m, scn.excitation, sim.integrator.active, oq).mean(axis=1)
    qs_rpm = oq[np.argmax(qs_pk)] / RPM
    zeta1 = m.damping_ratio[nd1]
    lag_rpm = 2 * rate * RPM / (zeta1 * 2 * np.pi * f[i]) / RPM
    half_rev_rpm = 0.5 * rate * 60.0 / campbell_rpm
    print("Campbell", campbell_rpm, "quasi-steady peak", qs_rpm, "simulated peak", peak_rpm, "lag", lag_rpm)
    assert 0.0 <= campbell_rpm - qs_rpm <= 1.2 * zeta1**2 * campbell_rpm
    assert abs(peak_rpm - qs_rpm - lag_rpm) <= 0.2 * lag_rpm + half_rev_rpm
    np.testing.assert_allclose(pk[j], qs_pk.max(), rtol=0.05)  # the slow sweep nearly reaches steady state


def test_steady_start_at_resonance_has_the_quasi_steady_amplitude_at_revolution_0(one_family):
    """At the shifted resonance (2610 rpm), revolution 0 carries the harmonic steady pk-pk of
    the interpolated modes within 1 % (the sweep lowers it by ~0.5 %), not the zero-speed
    model's response there (its resonance is 30 rpm lower: a fraction of it)."""
    _, m = one_family
    scn = scenario_from_dict(_window(2610.0, 0.1, "steady"))
    sim = RunUpSimulator(scn, m, n_revolutions=1)
    run = collect(sim)
    pkpk = _quasi_steady_pkpk(m, scn.excitation, sim.integrator.active, np.array([2610.0 * RPM]))[0]
    np.testing.assert_allclose(run.truth.d_eqv_pkpk_m[0], pkpk, rtol=0.01)
    assert pkpk.mean() > 2e-3


def test_a_lead_in_cut_short_by_the_model_speeds_warns(one_family):
    """A steady start decelerating from just below the model's top speed: the extended sweep
    would leave the model's speeds within the lead-in, which is cut short, with a warning."""
    _, m = one_family
    scn = scenario_from_dict({"model": {"n_families": 1},
                              "speed": {"start_rpm": 4199.0, "segments": [{"duration_s": 0.1, "end_rpm": 4150.0}]}})
    sim = RunUpSimulator(scn, m)
    assert len(sim.integrator.warnings) == 1 and "lead-in" in sim.integrator.warnings[0]


def test_scenario_check_refuses_a_run_beyond_the_model_speeds(one_family, tmp_path, capsys):
    _, m = one_family
    path = tmp_path / "sd.npz"
    save_model(m, path)
    scn = tmp_path / "s.toml"
    scn.write_text(f'[model]\nsource = "{path}"\n[speed]\nstart_rpm = 4000.0\n'
                   '[[speed.segments]]\nduration_s = 1.0\nend_rpm = 4300.0\n')
    assert cli.main(["scenario", "--check", str(scn)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "4300 rpm" in err and "stop at 4200 rpm" in err, err


def test_tip_amplitude_check_sees_the_shifted_resonance(one_family):
    """A strongly stiffened family (kappa = 6: the ND 1 crossing moves from 2579 to 2709 rpm)
    and a run-up across the shifted crossing only: the amplitude estimate with the modes
    frozen at the Campbell crossings finds the resonant amplitude of P_nom, which the
    zero-speed modes (130 rpm = 4 half-power bandwidths away) would miss; a force that makes
    it too large is refused."""
    from bttsim_stream.sim.core import check_tip_amplitude

    m0, _ = one_family
    m = southwell_model(m0, np.linspace(0.0, TOP, 3), 6.0)
    case = _window(2690.0, 1.0, "steady", rate=40.0)
    scn = scenario_from_dict(case)
    amp = float(np.max(check_tip_amplitude(scn, m).tip_0pk_m))
    om = np.array([_resonance_rpm(m0.freq_hz[np.flatnonzero(m0.nodal_diameter == 1)[0]], kappa=6.0) * RPM])
    peak = np.max(np.linalg.norm(_quasi_steady_u(m, scn.excitation, om), axis=-1))
    amp0 = float(np.max(check_tip_amplitude(scn, m0).tip_0pk_m))
    print(amp, peak, amp0)
    assert peak * 0.99 <= amp <= peak * 1.6  # any tip node, the ND 1 pair's modes summed in absolute value
    assert amp > 3 * amp0
    loud = scenario_from_dict(dict(case, excitation=[{"engine_order": 8, "nodal_diameter": 1, "amplitude_n": 40.0}]))
    with pytest.raises(BttsimError, match="lower the force"):
        check_tip_amplitude(loud, m)


def test_speed_dependent_output_does_not_depend_on_the_chunking(one_family):
    _, m = one_family
    scn = scenario_from_dict(_window(2605.0, 0.6, "steady"))
    a = collect(RunUpSimulator(scn, m, chunk_revolutions=3))
    b = collect(RunUpSimulator(scn, m, chunk_revolutions=7))
    np.testing.assert_array_equal(a.toa_s, b.toa_s)
    np.testing.assert_array_equal(a.truth.d_eqv_m, b.truth.d_eqv_m)

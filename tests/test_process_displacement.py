"""Displacements from OPR and TOAs (Eq. 1), the OPR phase model, calibration, blade identification."""

import warnings

import numpy as np
import pytest

from bttsim_stream.process import (Geometry, btt_displacement, calibrate_arrival_angles, compute_displacements,
                                   expected_times, identify_blades, mean_speed_from_opr, rotor_phase_from_opr)
from bttsim_stream.paper.validate_processing import simulate

TWO_PI = 2 * np.pi
PROBES = np.deg2rad([5.0, 15.15, 23.82, 220.0, 301.5])


def _ramp(n_rev=40, w0=100.0, alpha=2.4):
    """OPR times of a constant acceleration ``phi = w0 t + alpha t^2 / 2`` (phi = 2 pi n)."""
    n = np.arange(n_rev + 1)
    t = 2 * TWO_PI * n / (w0 + np.sqrt(w0 * w0 + 2 * alpha * TWO_PI * n))
    return t, w0, alpha


def _rigid_toas(opr, w0, alpha, psi, delta_rad=0.0):
    """Exact TOAs of blades reaching the probe at rotor angle ``psi - delta`` after each OPR."""
    n = np.arange(opr.size)[:, None, None]
    target = TWO_PI * n + psi[None] - delta_rad
    return 2 * target / (w0 + np.sqrt(w0 * w0 + 2 * alpha * target))


def test_mean_speed_exact_and_extrapolated():
    opr = np.array([0.0, 0.1, 0.19, 0.27])
    om = mean_speed_from_opr(opr)
    np.testing.assert_allclose(om[:3], TWO_PI / np.diff(opr), rtol=1e-15)
    assert om[3] == pytest.approx(2 * om[2] - om[1], rel=1e-15)


def test_quadratic_phase_is_exact_under_constant_acceleration():
    t, w0, alpha = _ramp()
    phase = rotor_phase_from_opr(t)
    np.testing.assert_allclose(phase.alpha_rad_s2[:-1], alpha, rtol=1e-6)
    psi = np.linspace(0.01, TWO_PI - 0.01, 7)
    t_exp = phase.time_at_angle(np.broadcast_to(psi, (t.size, psi.size)))
    truth = _rigid_toas(t, w0, alpha, psi[None, :])[:, 0, :]
    np.testing.assert_allclose(t_exp[:-1], truth[:-1], rtol=0, atol=1e-13)
    # the textbook linear model is off by alpha T^2 / 8 rad mid-revolution
    linear = t[:, None] + psi[None, :] / mean_speed_from_opr(t)[:, None]
    assert np.max(np.abs(linear - truth)[:-1]) > 1e-6


def test_eq1_recovers_a_known_tangential_displacement():
    t, w0, _ = _ramp(alpha=0.0)
    g = Geometry(n_blades=29, probe_angles_rad=PROBES, tip_radius_m=0.19)
    psi = g.nominal_arrival_angles()
    delta = np.random.default_rng(0).uniform(-5e-3, 5e-3, (t.size, 29, 5))  # m, ahead of the rigid blade
    toa = _rigid_toas(t, w0, 0.0, psi, delta / 0.19)
    disp = compute_displacements(t, toa, g, calibration=None)
    assert disp.method == "nominal"
    np.testing.assert_allclose(disp.d_m[:-1], delta[:-1], rtol=0, atol=1e-12)


def test_calibration_absorbs_blade_and_probe_angle_offsets():
    t, w0, alpha = _ramp(n_rev=80)
    g = Geometry(n_blades=29, probe_angles_rad=PROBES, tip_radius_m=0.19)
    rng = np.random.default_rng(1)
    offset = rng.uniform(-0.01, 0.01, (29, 5))  # unknown sensing point and probe positions, rad
    vib = np.zeros((t.size, 29, 5))
    vib[40:] = 1e-3 * np.sin(np.arange(40, t.size) / 3.0)[:, None, None]
    toa = _rigid_toas(t, w0, alpha, g.nominal_arrival_angles() + offset, vib / 0.19)
    cal = compute_displacements(t, toa, g, calibration=20)
    nominal = compute_displacements(t, toa, g, calibration=None)
    assert cal.method == "calibrated"
    # Eq. 1 with the exact expected times (its mean speed differs from the instantaneous one)
    t_exp = _rigid_toas(t, w0, alpha, g.nominal_arrival_angles() + offset)
    eq1 = btt_displacement(mean_speed_from_opr(t), 0.19, t_exp, toa)
    np.testing.assert_allclose(cal.d_m[:-1], eq1[:-1], rtol=0, atol=1e-11)
    np.testing.assert_allclose(cal.d_m[:-1], vib[:-1], rtol=0, atol=2e-3 * 1e-3)
    assert np.max(np.abs(nominal.d_m - vib)) > 1e-3
    psi = calibrate_arrival_angles(rotor_phase_from_opr(t), toa, (0, 20))
    np.testing.assert_allclose(psi, g.nominal_arrival_angles() + offset, atol=1e-12)


def test_arrival_near_the_opr_pulse_keeps_its_revolution():
    # blade 0 reaches the probe 0.2 deg after the OPR pulse; the nominal geometry believes
    # it arrives 0.3 deg *before* the pulse (in the previous revolution): 0.5 deg late, not 359.5
    t, w0, _ = _ramp(n_rev=10, alpha=0.0)
    true_psi = np.full((1, 1), np.deg2rad(0.2))
    toa = _rigid_toas(t, w0, 0.0, true_psi)
    g = Geometry(n_blades=1, probe_angles_rad=[0.0], tip_radius_m=0.2, blade_angles_rad=[np.deg2rad(0.3)])
    d = compute_displacements(t, toa, g, calibration=None).d_m
    np.testing.assert_allclose(d[:-1], 0.2 * np.deg2rad(-0.5), rtol=1e-9)  # 0.5 deg late


def test_missing_toas_give_nan_without_warnings():
    t, w0, alpha = _ramp()
    g = Geometry(n_blades=29, probe_angles_rad=PROBES, tip_radius_m=0.19)
    toa = _rigid_toas(t, w0, alpha, g.nominal_arrival_angles())
    toa[3, 4, 2] = np.nan
    toa[:, 7, 1] = np.nan  # never seen: calibration falls back to the nominal angle
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        d = compute_displacements(t, toa, g, calibration=10).d_m
    assert np.isnan(d[3, 4, 2]) and np.all(np.isnan(d[:, 7, 1]))
    assert np.sum(np.isnan(d)) == 1 + t.size
    np.testing.assert_allclose(np.nan_to_num(d[:-1]), 0.0, atol=1e-11)


def test_btt_displacement_is_eq1():
    d = btt_displacement(np.array([300.0]), 0.19, np.array([[[1.0 + 1e-6]]]), np.array([[[1.0]]]))
    assert d[0, 0, 0] == pytest.approx(300.0 * 0.19 * 1e-6, rel=1e-9)


def test_geometry_from_info_and_model():
    run = simulate()
    from bttsim_stream.model import build_model

    model = build_model()
    g = Geometry.from_info(run.info)
    np.testing.assert_allclose(g.blade_angles_rad, TWO_PI * np.arange(29) / 29)
    gm = Geometry.from_info(run.info, model)
    np.testing.assert_allclose(gm.blade_angles_rad, model.tip_ref[:, model.nominal_node, 1])
    assert g.tip_radius_m == run.info.tip_radius_m and g.n_probes == 5
    with pytest.raises(ValueError, match="blade_angles_rad"):
        Geometry(n_blades=3, probe_angles_rad=[0.0], tip_radius_m=0.2, blade_angles_rad=[0.0, 1.0])


def test_simulated_run_exact_and_opr_expected_times():
    run = simulate()
    g_exact = Geometry.from_info(run.info)
    exact = compute_displacements(run.opr_s, run.toa_s, g_exact, t_exp_s=run.truth.t_exp_s)
    np.testing.assert_allclose(exact.d_m[:-1], run.truth.d_eq1_m[:-1], rtol=0, atol=1e-15)
    from bttsim_stream.model import build_model

    # with the model's sensing-point angles the OPR-only expected times are the truth's
    g = Geometry.from_info(run.info, build_model())
    phase = rotor_phase_from_opr(run.opr_s)
    t_exp = expected_times(phase, g.nominal_arrival_angles(), run.toa_s)
    assert np.max(np.abs(t_exp - run.truth.t_exp_s)[1:-1]) < 1e-9


# -- blade identification ----------------------------------------------------------------

def _pulses(n_rev=6, nb=29, period=0.02, probe=PROBES[0], opr_angle=0.0):
    g = Geometry(n_blades=nb, probe_angles_rad=PROBES, tip_radius_m=0.19, opr_angle_rad=opr_angle)
    opr = np.arange(n_rev) * period
    psi = np.mod(probe - g.blade_angles_rad - opr_angle, TWO_PI)
    return g, opr, opr[:, None] + psi[None, :] / TWO_PI * period


@pytest.mark.parametrize("opr_angle", [0.0, 1.0], ids=["opr0", "opr1rad"])
def test_identify_blades_exact(opr_angle):
    g, opr, truth = _pulses(opr_angle=opr_angle)
    got = identify_blades(opr, np.random.default_rng(0).permutation(truth.ravel()), PROBES[0], g)
    np.testing.assert_array_equal(got, truth)


def test_missing_pulse_does_not_shift_numbering():
    g, opr, truth = _pulses()
    pulses = np.delete(truth.ravel(), [2 * 29 + 10, 4 * 29 + 0])
    got = identify_blades(opr, pulses, PROBES[0], g)
    expect = truth.copy()
    expect[2, 10] = np.nan
    expect[4, 0] = np.nan
    np.testing.assert_array_equal(got, expect)


def test_spurious_pulses_are_dropped():
    g, opr, truth = _pulses()
    pitch_t = 0.02 / 29
    spurious = [truth[1, 5] + 0.4 * pitch_t,  # between two blades: too far from both
                truth[3, 8] + 0.05 * pitch_t,  # close to blade 8 but the true pulse is closer
                opr[-1] + 0.5 * 0.02 + 2.0]  # long after the last revolution
    got = identify_blades(opr, np.concatenate([truth.ravel(), spurious]), PROBES[0], g)
    np.testing.assert_array_equal(got, truth)


def test_identify_blades_tolerates_vibration_across_the_opr_pulse():
    # blade 0 arrives just after the OPR pulse; vibration makes it arrive just before
    g = Geometry(n_blades=29, probe_angles_rad=[np.deg2rad(0.5)], tip_radius_m=0.19)
    opr = np.arange(5) * 0.02
    psi = np.mod(np.deg2rad(0.5) - g.blade_angles_rad, TWO_PI)
    truth = opr[:, None] + psi[None, :] / TWO_PI * 0.02
    shaken = truth.copy()
    shaken[2, 0] -= np.deg2rad(1.0) / TWO_PI * 0.02  # now 0.5 deg *before* OPR 2
    got = identify_blades(opr, shaken.ravel(), np.deg2rad(0.5), g)
    np.testing.assert_array_equal(got, shaken)


def test_identify_blades_relabels_the_simulator_stream():
    from bttsim_stream.model import build_model

    run = simulate()
    g = Geometry.from_info(run.info, build_model())
    rng = np.random.default_rng(7)
    for j in (0, 2, 4):
        labelled = run.toa_s[:400, :, j].copy()
        labelled[rng.random(labelled.shape) < 0.02] = np.nan
        pulses = labelled[np.isfinite(labelled)]
        # noise pulses between blades (0.2 to 0.8 of the blade pitch after a real one)
        pitch_s = 2 * np.pi / 29 / run.truth.omega_mean[:400].mean()
        spurious = rng.choice(pulses, 50) + rng.uniform(0.2, 0.8, 50) * pitch_s
        got = identify_blades(run.opr_s[:400], rng.permutation(np.concatenate([pulses, spurious])),
                              g.probe_angles_rad[j], g, tolerance=0.05)
        np.testing.assert_array_equal(got, labelled)


def test_extra_edges_go_to_the_blade_whose_window_holds_them():
    from bttsim_stream.process.displacement import DoublePulses, assign_extra_edges

    toa = np.array([1.0, 2.0, np.nan, 4.0, 3.0])  # blade spacing 1 s (median gap), window +-0.5 s
    edges = np.array([1.1, 3.9, 0.3, 2.45, 3.2, np.inf])
    np.testing.assert_array_equal(assign_extra_edges(toa, edges), [0, 3, -1, 1, 4, -1])
    np.testing.assert_array_equal(assign_extra_edges(np.array([1.0, np.nan]), np.array([1.01])), [-1])
    count = DoublePulses()
    count.add(toa, edges)
    count.add(toa, np.zeros(0))
    assert count.to_summary() == {"double_pulses": 4, "extra_edges": 4, "stray_edges": 2}

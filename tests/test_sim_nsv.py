"""Non-synchronous vibration against independent references.

* Rotating stall (non-integer engine order, and a fixed stationary-frame frequency): TOAs
  against ``solve_ivp`` of the modal equations forced by ``Im(C exp(i (EO phi + omega t)))``,
  Newton on Eq. 8 and Eq. 9-11, as ``tests/test_sim_transient.py`` does for engine orders.
* Flutter: TOAs against the same reference plus the closed-form travelling wave evaluated
  directly (no envelope grid); the logistic amplitude law against ``solve_ivp`` of the
  Van der Pol-type equation of the travelling modal coordinate.
* Broadband: bit-identical per seed; the truth rms against the steady-state frequency
  response of the modes to each line.
"""

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from bttsim_stream.errors import BttsimError
from bttsim_stream.scenario import scenario_from_dict
from bttsim_stream.sim.core import RunUpSimulator, collect

from _reference import fixed_mode_motion, initial_state, newton_toas, tip_grid


def _reference_toas(sim, run, blades, y0, extra=None):
    """TOAs (n_rev, blades, probes) from solve_ivp of the forced modes (every carrier
    ``EO phi + omega t``) from the initial state ``y0`` (:func:`_reference.initial_state`), plus ``extra(t, b)`` -- a
    displacement of the tip nodes (..., n_tip, 3) added in closed form -- by Newton on Eq. 8
    and Eq. 9-11."""
    m, integ, speed = sim.model, sim.integrator, sim.speed
    act = integ.active
    Ca = integ.c_plus * 2j  # (n_act, n_forced)
    eo = integ.eo[0]
    om_c = np.zeros(eo.size) if integ.omega is None else integ.omega
    w = 2 * np.pi * m.freq_hz[act]
    zeta = m.damping_ratio[act]
    n = act.size

    def rhs(t, y):
        f = np.imag(Ca @ np.exp(1j * (eo * speed.angle(t) + om_c * t)))
        return np.concatenate([y[n:], f - 2 * zeta * w * y[n:] - w * w * y[:n]])

    sol = solve_ivp(rhs, (0.0, speed.duration_s), y0, method="DOP853", rtol=1e-10, atol=1e-16,
                    dense_output=True)
    assert sol.status == 0
    _, b, node = tip_grid(sim, run, blades)
    motion = fixed_mode_motion(sol, m.tip_shapes[act][:, b, node, :], n, extra)
    return newton_toas(sim, run, blades, motion, iterations=8, tol=1e-13)


# 8 cells at 0.14 of the shaft speed: EO 6.88, the 344 Hz first family (ND 8) crossed near 3000 rpm
STALL_RAMP = {"speed": {"start_rpm": 2990.0, "initial": "rest", "segments": [{"duration_s": 0.08, "end_rpm": 3010.0}]},
              "rotating_stall": [{"cells": 8, "speed_fraction": 0.14, "amplitude_n": 1.0}]}
# a 4-lobe pattern at 250 Hz in the stationary frame: rotor-frame 4 x 50 Hz - 250 Hz = -50 Hz ...
# the first family is reached by the engine-order part only; a steady start with a speed knot
STALL_FIXED = {"speed": {"start_rpm": 2999.0, "initial": "steady",
                         "segments": [{"duration_s": 0.04, "end_rpm": 3001.0},
                                      {"duration_s": 0.04, "end_rpm": 3001.0}]},
               "rotating_stall": [{"cells": 4, "frequency_hz": 545.0, "amplitude_n": 2.0, "direction": [0, 1, 0]}]}


@pytest.mark.slow
@pytest.mark.parametrize("case", [STALL_RAMP, STALL_FIXED], ids=["stall-fraction-rest-ramp", "stall-fixed-freq-knot"])
def test_rotating_stall_toas_match_solve_ivp_in_every_revolution(case):
    sim = RunUpSimulator(scenario_from_dict(case), chunk_revolutions=2)
    assert sim.omega is not None and sim.nsv.components[0].kind == "rotating_stall"
    y0 = initial_state(sim)
    run = collect(sim)
    blades = [0, 11, 23]
    err = np.abs(run.toa_s[:, blades] - _reference_toas(sim, run, blades, y0)).max(axis=(1, 2))
    print("max TOA error per revolution, s:", err)
    assert err.size >= 3
    assert np.all(err <= 1e-10), err
    # the stall really moves the blades: compare with the same run without it
    plain = collect(RunUpSimulator(scenario_from_dict({"speed": case["speed"]}), chunk_revolutions=2))
    assert np.max(np.abs(run.toa_s - plain.toa_s)) > 1e-8


def test_rotating_stall_truth_frequency_and_nd():
    sim = RunUpSimulator(scenario_from_dict(STALL_RAMP))
    tr = collect(sim).truth
    assert tr.nsv_kind.shape == (tr.opr_s.size, 1) and set(tr.nsv_kind.ravel()) == {"rotating_stall"}
    np.testing.assert_allclose(tr.nsv_freq_hz[:, 0], 8 * 0.86 * tr.omega_mean / (2 * np.pi), rtol=1e-12)
    assert np.all(tr.nsv_nd == 8)  # 8 cells, 29 blades: forward ND 8
    assert np.all(tr.nsv_amp_pkpk_m > 0)
    # fixed stationary frequency: rotor-frame 4 Omega - 2 pi 545 Hz < 0 at 50 Hz: ND flips to backward
    tr = collect(RunUpSimulator(scenario_from_dict(STALL_FIXED))).truth
    np.testing.assert_allclose(tr.nsv_freq_hz[:, 0], np.abs(4 * tr.omega_mean / (2 * np.pi) - 545.0), rtol=1e-12)
    assert np.all(tr.nsv_nd == -4)


# zeta_aero 0.03 over zeta_s 0.0098: sigma = 44 /s, from 1 nm to near the limit in 0.35 s
FLUTTER = {"speed": {"start_rpm": 3000.0, "segments": [{"duration_s": 0.4, "end_rpm": 3010.0}]},
           "flutter": {"enabled": True, "family": 1, "nodal_diameter": -3, "start_s": 0.05, "aero_damping_ratio": 0.03,
                       "limit_amplitude_m": 3e-4, "seed_amplitude_m": 1e-9, "phase_deg": 30.0}}


@pytest.mark.slow
def test_flutter_toas_match_closed_form_and_solve_ivp():
    sim = RunUpSimulator(scenario_from_dict(FLUTTER), chunk_revolutions=3)
    fw = sim.nsv.flutter
    y0 = initial_state(sim)
    run = collect(sim)
    m = sim.model
    nodes = sim.basis.nodes  # (r, nt, 3)

    def extra(t, b, node):
        """The travelling wave at the tip nodes, straight from the closed form."""
        R, dR = fw.amplitude(t)
        T = np.einsum("...j,j...c->...c", fw.shape[b], nodes[:, node, :])  # (..., 3) complex
        e = np.exp(1j * fw.omega * t)[..., None]
        return (np.imag(R[..., None] * T * e),
                np.imag((dR[..., None] + 1j * fw.omega * R[..., None]) * T * e))

    blades = [0, 7, 19]
    err = np.abs(run.toa_s[:, blades] - _reference_toas(sim, run, blades, y0, extra)).max(axis=(1, 2))
    print("max TOA error per revolution, s:", err)
    assert np.all(err <= 1e-10), err
    tr = run.truth
    on = tr.opr_s > fw.t_on + 0.002
    assert np.all(tr.nsv_amp_pkpk_m[tr.opr_s + 0.021 < fw.t_on] == 0.0)  # absent before onset
    R_end = fw.amplitude(tr.toa_s[-1].max())[0]
    assert tr.nsv_amp_pkpk_m[-1, 0] == pytest.approx(R_end, rel=1e-3)  # R is the largest blade's pk-pk
    assert np.all(np.diff(tr.nsv_amp_pkpk_m[on, 0]) > 0) and tr.nsv_amp_pkpk_m[-1, 0] > 0.3 * 3e-4
    assert np.all(tr.nsv_nd == -3)
    zs = m.damping_ratio[list(fw.modes)].mean()
    np.testing.assert_allclose(tr.nsv_freq_hz, m.freq_hz[list(fw.modes)].mean() * np.sqrt(1 - zs**2), rtol=1e-12)
    # the wave travels backward at ND 3: blade-to-blade phase of d_eqv's flutter part is -2 pi 3 / 29
    y = fw.shape @ sim._v_eqv
    adv = np.angle(y[1:] / y[:-1])
    np.testing.assert_allclose(adv, -2 * np.pi * 3 / m.n_blades, atol=0.05)


def test_flutter_amplitude_is_the_averaged_van_der_pol_law():
    """solve_ivp of the Van der Pol modal equation ``q'' + 2 zs w q' - 2 za w (1 - beta q^2) q'
    + w^2 q = 0``, ``beta = 4 (za - zs) / (za R_lim^2)``: its amplitude ``sqrt(q^2 + (q'/w)^2)``
    follows the logistic closed form within the averaging error O(sigma / w)."""
    from bttsim_stream.sim.nsv import FlutterWave

    w, zs, za, R0, Rl = 2 * np.pi * 344.0, 0.0098, 0.03, 1e-3, 1.0
    beta = 4 * (za - zs) / (za * Rl**2)
    fw = FlutterWave(omega=w, sigma=(za - zs) * w, t_on=0.0, seed_m=R0, limit_m=Rl, shape=np.ones((1, 1)),
                     nodal_diameter=0, modes=())

    def rhs(t, y):
        return [y[1], -2 * zs * w * y[1] + 2 * za * w * (1 - beta * y[0] ** 2) * y[1] - w * w * y[0]]

    T = 12.0 / fw.sigma
    t = np.linspace(0.0, T, 400)
    sol = solve_ivp(rhs, (0.0, T), [R0, fw.sigma * R0], method="DOP853", rtol=1e-10, atol=1e-14, t_eval=t)
    R = np.hypot(sol.y[0], sol.y[1] / w)
    ref, _ = fw.amplitude(t)
    print("largest |R - logistic| / R_lim:", np.max(np.abs(R - ref)) / Rl, "sigma / w:", fw.sigma / w)
    np.testing.assert_allclose(R, ref, atol=2 * fw.sigma / w * Rl, rtol=0.02)
    assert np.max(np.abs(R[-40:] - Rl)) < 2 * fw.sigma / w * Rl


BROADBAND = {"speed": {"start_rpm": 3000.0, "segments": [{"duration_s": 0.1, "end_rpm": 3000.0}]},
             "excitation": [{"amplitude_n": 0.0}],
             "broadband": {"enabled": True, "band_hz": [330.0, 360.0], "psd_n2_per_hz": 1e-3, "n_lines": 6}}


def test_broadband_is_seeded_and_its_rms_is_the_frequency_response():
    scn = scenario_from_dict(BROADBAND)
    a = collect(RunUpSimulator(scn))
    b = collect(RunUpSimulator(scn))
    assert a.toa_s.tobytes() == b.toa_s.tobytes()
    other = collect(RunUpSimulator(scenario_from_dict({**BROADBAND, "run": {"seed": 7}})))
    assert np.max(np.abs(other.toa_s - a.toa_s)) > 1e-9
    sim = RunUpSimulator(scn)
    m, nsv = sim.model, sim.nsv
    # steady state of every mode to every line: d_eqv at P_nom of each blade
    w = 2 * np.pi * m.freq_hz
    zeta = m.damping_ratio
    tip = m.tip_shapes[:, :, m.nominal_node, :]
    v = tip[..., 1] + tip[..., 2] / np.tan(np.deg2rad(float(m.meta["stagger_deg"])))  # (n_modes, n_blades)
    wl = nsv.omega
    H = 1.0 / (w[:, None] ** 2 - wl[None, :] ** 2 + 2j * zeta[:, None] * w[:, None] * wl[None, :])
    A = np.einsum("kb,kj->bj", v, nsv.C * H)  # (n_blades, n_lines) complex amplitude of d_eqv
    ms_blade = 0.5 * np.sum(np.abs(A) ** 2, axis=1)
    tr = a.truth
    np.testing.assert_allclose(tr.nsv_rms_m[:, 0], np.sqrt(np.mean(ms_blade)), rtol=1e-6)
    assert np.all(tr.nsv_band_hz[:, 0] == [330.0, 360.0]) and np.all(tr.nsv_kind == "broadband")
    # the truth's d_eqv (only broadband forcing here) has that rms
    assert np.sqrt(np.mean(tr.d_eqv_m**2)) == pytest.approx(np.sqrt(np.mean(ms_blade)), rel=0.15)


def test_flutter_needs_more_aero_damping_than_the_structure():
    scn = scenario_from_dict({**FLUTTER, "flutter": {**FLUTTER["flutter"], "aero_damping_ratio": 0.001}})
    with pytest.raises(BttsimError, match="aero_damping_ratio"):
        RunUpSimulator(scn)


def test_stall_truth_amplitude_is_the_steady_frequency_response_on_a_dwell():
    """On a dwell the stall's pk-pk d_eqv truth is ``2 max_b |sum_k v_kb C_k H_k(EO Omega + omega)|``."""
    scn = scenario_from_dict({"speed": {"start_rpm": 3000.0, "segments": [{"duration_s": 0.1, "end_rpm": 3000.0}]},
                              "excitation": [{"amplitude_n": 0.0}],
                              "rotating_stall": [{"cells": 4, "frequency_hz": 545.0, "amplitude_n": 2.0}]})
    sim = RunUpSimulator(scn)
    tr = collect(sim).truth
    m, nsv = sim.model, sim.nsv
    w, zeta = 2 * np.pi * m.freq_hz, m.damping_ratio
    tip = m.tip_shapes[:, :, m.nominal_node, :]
    v = tip[..., 1] + tip[..., 2] / np.tan(np.deg2rad(float(m.meta["stagger_deg"])))
    rate = nsv.eo[0] * 3000.0 * np.pi / 30.0 + nsv.omega[0]  # rad/s, negative here
    H = 1.0 / (w**2 - rate**2 + 2j * zeta * w * rate)
    A = v.T @ (nsv.C[:, 0] * H)  # (n_blades,)
    # truth pk-pk is the largest over the revolution's arrivals (blades and probes): all blades alike here
    np.testing.assert_allclose(tr.nsv_amp_pkpk_m[:, 0], 2 * np.max(np.abs(A)), rtol=1e-3)


def test_flutter_onset_at_a_speed():
    from bttsim_stream.sim.nsv import flutter_onset_s

    scn = scenario_from_dict({"speed": {"start_rpm": 2970.0, "end_rpm": 3030.0, "duration_s": 0.8},
                              "flutter": {"enabled": True, "start_rpm": 2980.0}})
    sim = RunUpSimulator(scn)
    t_on = flutter_onset_s(scn.flutter, sim.speed)
    assert t_on == pytest.approx(0.8 * 10.0 / 60.0, rel=1e-12)
    tr = collect(sim).truth
    before = tr.opr_s + 2 * np.pi / tr.omega_mean < t_on  # whole revolutions before onset
    assert before.sum() > 3 and np.all(tr.nsv_amp_pkpk_m[before] == 0.0)
    assert np.all(tr.nsv_amp_pkpk_m[tr.opr_s > t_on] > 0.0)

"""Validation of the simulator against the paper's Sec. 3.2-3.3.1 (numbers for the docs).

``bttsim validate`` runs the default scenario (HP) and a 10 s window through the resonance
(2450 -> 2700 rpm) with nearest-node TOAs and with AD / PAD interpolation, and reports:

* resonance speed, blade-mean resonant ``d_eqv`` (pk-pk) and frequency (paper 2580 rpm,
  2.37 mm, 344.16 Hz);
* ``max |d_j(Eq. 1) - d_eqv(t_TOA)|`` over the whole run, relative to the resonant amplitude
  (Fig. 6);
* the largest revolution-to-revolution jump of ``d_j`` both ways, with and without axial
  interpolation (Fig. 7);
* AD and PAD against HP: largest difference and noise-to-signal ratio in the resonance
  window (Fig. 8; paper: AD close to HP, PAD about 10 %).
"""

from __future__ import annotations

import time

import numpy as np

from ..model import build_model
from ..scenario import Scenario, scenario_from_dict
from ..sim.core import RunUpSimulator, collect

__all__ = ["validate"]

WINDOW = {"speed": {"start_rpm": 2450.0, "segments": [{"duration_s": 10.0, "end_rpm": 2700.0}]}}


def validate() -> dict:
    """Run the validation and return its numbers (SI units unless the key says otherwise)."""
    model = build_model()
    t0 = time.perf_counter()
    sim = RunUpSimulator(Scenario(), model)
    run = collect(sim)
    wall = time.perf_counter() - t0
    tr = run.truth
    pk = tr.d_eqv_pkpk_m
    i_res = np.argmax(pk, axis=0)
    eo = sim.info.engine_orders[0]
    out = {
        "default_run": {
            "revolutions": int(run.revolution.size), "toas": int(run.toa_s.size),
            "wall_s": round(wall, 2), "real_time_factor": round(sim.info.duration_s / wall, 1),
            "resonance_rpm_mean": float(np.mean(tr.omega_mean[i_res]) * 60 / (2 * np.pi)),
            "resonant_d_eqv_pkpk_mm_mean": float(1e3 * np.mean(pk.max(axis=0))),
            "resonant_d_eqv_pkpk_mm_range": [float(1e3 * pk.max(axis=0).min()), float(1e3 * pk.max(axis=0).max())],
            "resonant_freq_hz_mean": float(np.mean(eo * tr.omega_mean[i_res] / (2 * np.pi))),
            "eq1_vs_d_eqv_max_pct_of_pkpk": float(100 * np.max(np.abs(tr.d_eq1_m - tr.d_eqv_m)) / pk.max()),
            "d_tang_vs_d_eqv_max_pct_of_pkpk": float(100 * np.max(np.abs(tr.d_tang_m - tr.d_eqv_m)) / pk.max()),
            "hp_newton_residual_s": run.residual_s,
        }
    }

    def window(**toa):
        d = dict(WINDOW, toa=toa) if toa else WINDOW
        return collect(RunUpSimulator(scenario_from_dict(d), model))

    hp = window()
    near = window(axial_interpolation=False)
    d_hp = hp.truth.d_eq1_m
    wpk = hp.truth.d_eqv_pkpk_m
    win = wpk.max(axis=1) > 0.5 * wpk.max()
    jumps = {}
    for name, res in (("axial_interpolation", hp), ("nearest_node", near)):
        dd = np.diff(res.truth.d_eq1_m, axis=0)
        jumps[name] = {"max_up_mm": float(1e3 * dd.max()), "max_down_mm": float(1e3 * dd.min())}
    out["fig7_rev_to_rev_jump"] = jumps
    grid = {}
    for method in ("AD", "PAD"):
        res = window(method=method)
        e = res.truth.d_eq1_m - d_hp
        ew = e[win]
        grid[method] = {
            "grid_step_s": Scenario().toa.grid_step_s,
            "max_abs_diff_mm": float(1e3 * np.max(np.abs(e))),
            "max_toa_diff_s": float(np.max(np.abs(res.toa_s - hp.toa_s))),
            "nsr_pct": float(100 * np.std(ew - ew.mean(axis=0)) / np.std(d_hp[win])),
        }
    out["fig8_interpolated_vs_hp"] = grid
    return out

"""Benchmark: run-up simulation speed, scaling and memory (prints JSON).

Usage::

    python bench/bench_sim.py            # full default scenario + scaling table
    python bench/bench_sim.py --quick    # shorter scaling runs

Each configuration runs in its own process (``--one``) so that its peak memory (max RSS)
is its own. Target: the default 130 s run-up (29 blades, 5 probes, 145 modes, 9 tip nodes,
HP) at >= 20x real time on one core; goal 100x.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time


def _one(cfg: dict) -> dict:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import numpy as np

    from bttsim_stream.model import build_model
    from bttsim_stream.model.bladed_disk import BladedDiskDesign
    from bttsim_stream.scenario import scenario_from_dict
    from bttsim_stream.sim.core import RunUpSimulator

    scn = scenario_from_dict(cfg["scenario"])
    t0 = time.perf_counter()
    model = build_model(scn)
    build_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    sim = RunUpSimulator(scn, model)
    n_toa = 0
    peak_pk = 0.0
    for batch in sim:
        n_toa += batch.toa_s.size
        peak_pk = max(peak_pk, float(batch.truth.d_eqv_pkpk_m.max()))
    wall = time.perf_counter() - t0
    return {
        "name": cfg["name"], "duration_s": scn.speed.duration_s, "n_blades": model.n_blades,
        "n_probes": len(scn.probes.angles_deg), "n_modes": model.n_modes,
        "n_active_modes": int(sim.integrator.active.size), "n_tip_nodes": model.n_tip,
        "method": scn.toa.method, "n_toas": n_toa, "model_build_s": round(build_s, 3),
        "wall_s": round(wall, 3), "real_time_factor": round(scn.speed.duration_s / wall, 1),
        "us_per_toa": round(1e6 * wall / max(n_toa, 1), 3),
        "crossing_us_per_toa": round(1e6 * sim.timing["crossings_s"] / max(n_toa, 1), 3),
        "envelope_s_per_sim_s": round(sim.timing["envelopes_s"] / scn.speed.duration_s, 5),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "max_pkpk_mm": round(1e3 * peak_pk, 4),
    }


def _configs(quick: bool) -> list[dict]:
    dur = 10.0 if quick else 30.0
    ramp = {"start_rpm": 2400.0, "end_rpm": 2800.0, "duration_s": dur}
    mist = {"stiffness_std": 0.01}
    cfgs = [{"name": "default (paper Table 1, HP)", "scenario": {}}]
    for d in (dur / 3, dur, 3 * dur):
        cfgs.append({"name": f"duration {d:g} s", "scenario": {"speed": {**ramp, "duration_s": d}}})
    for fam in (1, 3, 5):
        cfgs.append({"name": f"mistuned, {fam * 29} modes (all active)",
                     "scenario": {"speed": ramp, "model": {**mist, "n_families": fam}}})
    for n_tip, spacing in ((5, 0.000875), (9, 0.0004375), (17, 0.00021875)):
        nominal = (n_tip + 1) // 2
        cfgs.append({"name": f"{n_tip} tip nodes", "scenario": {
            "speed": ramp, "rotor": {"n_tip_nodes": n_tip, "tip_node_spacing_m": spacing,
                                     "nominal_node": nominal}}})
    for probes in ([5.0, 15.15, 23.82], [5.0, 15.15, 23.82, 220.0, 301.5],
                   [5.0, 10.6, 15.15, 23.82, 148.5, 190.35, 202.11, 220.0, 255.6, 301.5]):
        cfgs.append({"name": f"{len(probes)} probes", "scenario": {"speed": ramp, "probes": {"angles_deg": probes}}})
    for method in ("AD", "PAD"):
        cfgs.append({"name": f"{method}", "scenario": {"speed": ramp, "toa": {"method": method}}})
    return cfgs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--one", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        print(json.dumps(_one(json.loads(args.one))))
        return
    rows = []
    for cfg in _configs(args.quick):
        out = subprocess.run([sys.executable, __file__, "--one", json.dumps(cfg)], capture_output=True,
                             text=True, env=dict(os.environ, OMP_NUM_THREADS="1"), check=True)
        rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
        print(json.dumps(rows[-1]), file=sys.stderr)
    print(json.dumps({"benchmark": "simulation", "target_rtf": 20, "goal_rtf": 100, "runs": rows}, indent=2))


if __name__ == "__main__":
    main()

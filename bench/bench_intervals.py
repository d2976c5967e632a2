"""Benchmark: calibration of the per-blade 95 % intervals against the exact truth (prints JSON).

Usage::

    python bench/bench_intervals.py                  # the matrix below, 3 seeds, every method
    python bench/bench_intervals.py --seeds 2 --out intervals.json

Simulates a small matrix of short run-ups through the default rotor's EO 8 ND 1 resonance
(~2580 rpm), several seeds per class, processes each with ``peak``, ``sdof`` and ``cff``
(truth off inside the estimate: the truth only scores the result), and reports per class
and method: blades scored, the coverage of the 95 % amplitude and frequency intervals
(``amp_ci95_m``, ``freq_ci95_hz``; ``amp +- 1.96 amp_std_m`` on a build without them), the
median amplitude half-width (% of the amplitude) and the mean E_A. Every blade row of every
crossing found counts once; a run without a crossing counts as ``missing``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

#: Short run-ups: 2300 -> 2900 rpm over 20 s is 30 rpm/s, the paper's 23 rpm/s (1000 -> 4000 in 130 s).
_UP = {"speed": {"start_rpm": 2300.0, "end_rpm": 2900.0, "duration_s": 20.0}}


def _merge(*parts: dict) -> dict:
    out: dict = {}
    for p in parts:
        for k, v in p.items():
            out[k] = _merge(out.get(k, {}), v) if isinstance(v, dict) else v
    return out


#: class -> scenario overrides (``scenario_from_dict`` form); the seed is added per run.
CLASSES = {
    "paper_rate": _merge(_UP, {"model": {"stiffness_std": 0.002}}),
    "jitter_probe_errors": _merge(_UP, {"acquisition": {"trigger_jitter_s": 2e-7, "probe_angle_error_deg": 0.05}}),
    "fast_sweep": {"speed": {"start_rpm": 2000.0, "end_rpm": 3200.0, "duration_s": 5.0},
                   "model": {"stiffness_std": 0.002}},
    "mistuned_5pct": _merge(_UP, {"model": {"stiffness_std": 0.05}}),
    "bad_layout_cn": {"speed": {"start_rpm": 2000.0, "end_rpm": 3200.0, "duration_s": 40.0},
                      "probes": {"angles_deg": [5.0, 51.0, 97.0]}, "acquisition": {"trigger_jitter_s": 1e-7}},
    "short_window": {"speed": {"start_rpm": 2480.0, "end_rpm": 2680.0, "duration_s": 7.0},
                     "model": {"stiffness_std": 0.002}},
}
METHODS = ("peak", "sdof", "cff")



def score_summary(summary: dict) -> list[dict]:
    """Per blade of every crossing: amplitude/frequency covered, half-width %, E_A %."""
    out = []
    for e in summary.get("resonances", []):
        for r in e["blades"]:
            if "truth_amp_pkpk_m" not in r or r.get("amp_pkpk_m") is None:
                continue
            a = r.get("amp_ci95_m") or [r["amp_pkpk_m"] - 1.96 * r.get("amp_std_m", 0.0),
                                        r["amp_pkpk_m"] + 1.96 * r.get("amp_std_m", 0.0)]
            f = r.get("freq_ci95_hz") or [r["freq_hz"] - 1.96 * r.get("freq_std_hz", 0.0),
                                          r["freq_hz"] + 1.96 * r.get("freq_std_hz", 0.0)]
            ta, tf = r["truth_amp_pkpk_m"], r["truth_freq_hz"]
            out.append({"amp_covered": bool(a[0] <= ta <= a[1]), "freq_covered": bool(f[0] <= tf <= f[1]),
                        "half_width_pct": 50.0 * (a[1] - a[0]) / r["amp_pkpk_m"], "E_A_pct": r["E_A_pct"],
                        "notes": list(e.get("notes", []))})
    return out


def _stats(rows: list[dict], missing: int) -> dict:
    import numpy as np

    if not rows:
        return {"blades": 0, "missing_runs": missing}
    return {"blades": len(rows), "missing_runs": missing,
            "amp_coverage_pct": round(100.0 * float(np.mean([r["amp_covered"] for r in rows])), 1),
            "freq_coverage_pct": round(100.0 * float(np.mean([r["freq_covered"] for r in rows])), 1),
            "median_half_width_pct": round(float(np.median([r["half_width_pct"] for r in rows])), 3),
            "mean_E_A_pct": round(float(np.mean([r["E_A_pct"] for r in rows])), 3),
            "max_E_A_pct": round(float(np.max([r["E_A_pct"] for r in rows])), 3)}


def run_matrix(classes: dict, seeds: int, methods=METHODS) -> dict:
    """Simulate and score every (class, seed, method); returns the per-class, per-method table."""
    from threadpoolctl import threadpool_limits

    from bttsim_stream.paper.validate_processing import simulate
    from bttsim_stream.process import ProcessOptions, process_arrays

    rows: dict = {(c, m): [] for c in classes for m in methods}
    missing: dict = {(c, m): 0 for c in classes for m in methods}
    with threadpool_limits(1):
        for c, over in classes.items():
            for seed in range(seeds):
                run = simulate(_merge(over, {"run": {"seed": seed}}))
                for m in methods:
                    s = process_arrays(run.opr_s, run.toa_s, run.info, ProcessOptions(method=m),
                                       truth=run.truth).summary
                    got = score_summary(s)
                    rows[c, m] += got
                    missing[c, m] += not got
    table = {c: {m: _stats(rows[c, m], missing[c, m]) for m in methods} for c in classes}
    pooled = {m: _stats([r for c in classes for r in rows[c, m]], sum(missing[c, m] for c in classes))
              for m in methods}
    return {"classes": table, "pooled": pooled}


def main(seeds: int = 3, out: str | None = None) -> dict:
    sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
    t0 = time.perf_counter()
    res = run_matrix(CLASSES, seeds)
    res["seeds"] = seeds
    res["wall_s"] = round(time.perf_counter() - t0, 1)
    text = json.dumps(res, indent=1)
    if out:
        with open(out, "w") as fh:
            fh.write(text + "\n")
    print(text)
    return res


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--out")
    a = p.parse_args()
    main(a.seeds, a.out)

"""Benchmark: amplitude and frequency errors against the Cramér-Rao bound on noise-limited runs
(prints JSON).

Usage::

    python bench/bench_crb.py                    # seeds 1000-1003 of each case
    python bench/bench_crb.py --seeds 16 --seed0 20 --cases jitter_1us,jitter_1us_probe_0.1deg

Cases: the default rotor's EO 8 crossing at the paper's sweep rate (2000 -> 3200 rpm in 52 s)
with 1 us TOA jitter alone, and with 0.1 deg probe position errors added; a faster sweep
(2200 -> 3000 rpm in 20 s) with 2 us jitter and 0.05 deg probe errors. Each seed is
simulated in this process and processed with ``peak``, ``cff`` and ``sdof``; per method:

* ``rms_amp_err_m``: the RMS over blades and seeds of (estimate - truth) of the pk-pk
  amplitude (the truth of the crossing's own engine order, :func:`window_truth`);
* ``crb_amp_m``: the RMS of the summary's ``crb_amp_m`` (noise from the fits' residuals);
* ``crb_amp_scenario_m``: ``bttsim crb``'s bound from the scenario's jitter (Eq. 15);
* ``ratio``: ``rms_amp_err_m / crb_amp_m`` (an efficient, unbiased estimate: 1); the same for
  the frequency.
"""

from __future__ import annotations

import argparse
import json
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from bttsim_stream.crb_report import scenario_bounds  # noqa: E402
from bttsim_stream.model import build_model  # noqa: E402
from bttsim_stream.process.options import ProcessOptions  # noqa: E402
from bttsim_stream.process.pipeline import process_arrays  # noqa: E402
from bttsim_stream.scenario import scenario_from_dict  # noqa: E402
from bttsim_stream.sim.core import RunUpSimulator, collect  # noqa: E402

SPEED = {"start_rpm": 2000.0, "end_rpm": 3200.0, "duration_s": 52.0}
FAST = {"start_rpm": 2200.0, "end_rpm": 3000.0, "duration_s": 20.0}
CASES = {
    "jitter_1us": (SPEED, {"trigger_jitter_s": 1e-6}),
    "jitter_1us_probe_0.1deg": (SPEED, {"trigger_jitter_s": 1e-6, "probe_angle_error_deg": 0.1}),
    "fast_jitter_2us_probe_0.05deg": (FAST, {"trigger_jitter_s": 2e-6, "probe_angle_error_deg": 0.05}),
}
METHODS = ("peak", "cff", "sdof")


def _rms(x) -> float:
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x * x))) if x.size else float("nan")


def run_case(speed: dict, acq: dict, seeds, model) -> dict:
    errs = {m: {"amp": [], "freq": [], "crb_amp": [], "crb_freq": []} for m in METHODS}
    scenario_crb = None
    for seed in seeds:
        scn = scenario_from_dict({"speed": speed, "acquisition": acq, "run": {"seed": int(seed)}})
        if scenario_crb is None:
            b = scenario_bounds(scn, model=model)[0]
            scenario_crb = {"amp_m": _rms(b.crb_amp_m), "freq_hz": _rms(b.crb_freq_hz)}
        sim = RunUpSimulator(scn, model)
        res = collect(sim)
        for m in METHODS:
            s = process_arrays(res.opr_s, res.toa_s, sim.info, ProcessOptions(method=m), truth=res.truth).summary
            e = next((e for e in s["resonances"] if e["eo"] == 8), None)
            if e is None:
                continue
            for r in e["blades"]:
                errs[m]["amp"].append(r["amp_pkpk_m"] - r["truth_amp_pkpk_m"])
                errs[m]["freq"].append(r["freq_hz"] - r["truth_freq_hz"])
                errs[m]["crb_amp"].append(r.get("crb_amp_m", np.nan))
                errs[m]["crb_freq"].append(r.get("crb_freq_hz", np.nan))
    out = {"crb_amp_scenario_m": scenario_crb["amp_m"], "crb_freq_scenario_hz": scenario_crb["freq_hz"]}
    for m, d in errs.items():
        ra, ca, rf, cf = _rms(d["amp"]), _rms(d["crb_amp"]), _rms(d["freq"]), _rms(d["crb_freq"])
        out[m] = {"n": len(d["amp"]), "rms_amp_err_m": ra, "crb_amp_m": ca, "amp_ratio": ra / ca,
                  "mean_amp_err_m": float(np.mean(d["amp"])) if d["amp"] else None,
                  "rms_freq_err_hz": rf, "crb_freq_hz": cf, "freq_ratio": rf / cf}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=4, help="seeds per case")
    ap.add_argument("--seed0", type=int, default=1000, help="first seed")
    ap.add_argument("--cases", help="comma-separated case names (default: all)")
    args = ap.parse_args()
    model = build_model()
    t0 = time.process_time()
    seeds = list(range(args.seed0, args.seed0 + args.seeds))
    out = {"seeds": seeds, "cases": {}}
    for name, (speed, acq) in CASES.items():
        if args.cases and name not in args.cases.split(","):
            continue
        out["cases"][name] = {"speed": speed, **run_case(speed, acq, seeds, model)}
    out["cpu_s"] = round(time.process_time() - t0, 1)
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()

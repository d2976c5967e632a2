"""Benchmark: ``bttsim campaign`` throughput on Dask against plain simulate + process (prints JSON).

Usage::

    python bench/bench_campaign.py                 # 8 runs, 1 and 2 workers
    python bench/bench_campaign.py --runs 16 --workers 1,2

One spec: the short run-up through the EO 8 resonance (2400 -> 2700 rpm in 6 s, 255
revolutions) with 1 us trigger jitter, ``--runs`` seeds, the ``peak`` method. Times

* ``plain``: the same runs one after another in this process, exactly what each task does
  (:func:`~bttsim_stream.campaign.run.execute_run`), no Dask: seconds per run;
* ``campaign_Nw``: :func:`~bttsim_stream.campaign.run_campaign` on a loopback
  ``LocalCluster`` of N single-threaded workers: runs per second counted from the first
  submission to the last result (cluster start-up apart, reported as ``startup_s``).

``overhead_pct`` compares one worker's seconds per run with ``plain`` (what Dask, Parquet and
the report cost per run); ``scaling_efficiency`` is the 2-worker rate over twice the 1-worker
rate. The machine is shared and has 2 cores: numbers move with the neighbours' load.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

SPEC = """
[campaign]
name = "bench"
seeds = {runs}
processors = ["peak"]

[scenario.speed]
start_rpm = 2400.0
end_rpm = 2700.0
duration_s = 6.0

[scenario.acquisition]
trigger_jitter_s = 1e-6
"""


def main(runs: int, workers: list[int]) -> dict:
    from bttsim_stream.campaign import expand, load_spec, run_campaign
    from bttsim_stream.campaign.run import execute_run

    out: dict = {"runs": runs, "scenario": "2400 -> 2700 rpm in 6 s, 255 revolutions, jitter 1 us, method peak",
                 "cpu_count": os.cpu_count()}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        (tmp / "spec.toml").write_text(SPEC.format(runs=runs))
        spec = load_spec(tmp / "spec.toml")
        plan = expand(spec)
        execute_run(plan[0])  # imports and first-call costs, as a worker's first task pays them too
        t0 = time.perf_counter()
        for r in plan:
            execute_run(r)
        plain = (time.perf_counter() - t0) / runs
        out["plain_s_per_run"] = round(plain, 3)
        for n in workers:
            t0 = time.perf_counter()
            res = run_campaign(spec, tmp / f"out{n}", n_workers=n)
            out[f"campaign_{n}w"] = {"runs_per_s": round(res.runs_per_s, 3), "compute_s": round(res.compute_s, 2),
                                      "startup_s": round(res.wall_s - res.compute_s, 2),
                                      "total_s": round(time.perf_counter() - t0, 2), "failed": res.failed}
    if 1 in workers:
        out["overhead_pct"] = round(100.0 * (1.0 / out["campaign_1w"]["runs_per_s"] / plain - 1.0), 1)
    if 1 in workers and 2 in workers:
        out["scaling_efficiency"] = round(out["campaign_2w"]["runs_per_s"] / (2 * out["campaign_1w"]["runs_per_s"]), 3)
    return out


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=8)
    parser.add_argument("--workers", default="1,2", help="comma-separated worker counts (1,2)")
    args = parser.parse_args()
    print(json.dumps(main(args.runs, [int(w) for w in args.workers.split(",")]), indent=2))

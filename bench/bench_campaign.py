"""Benchmark: ``bttsim campaign`` on Dask against plain simulate + process (prints JSON).

Usage::

    python bench/bench_campaign.py                          # all three parts (about 3 CPU-minutes)
    python bench/bench_campaign.py --parts overhead,scaling --runs 16
    python bench/bench_campaign.py --parts overhead --length short   # the worst case
    python bench/bench_campaign.py --parts memory --memory-runs 200

The runs: a run-up through the EO 8 x ND 1 resonance with 1 us trigger jitter and a
different seed per run, scored with ``peak``: for ``overhead`` and ``scaling`` the paper's
1000 -> 4000 rpm in 130 s (``--length paper``, 6800 revolutions, about 3 s of CPU), or
2400 -> 2700 rpm in 6 s (``--length short``, 255 revolutions, 0.1 s: the worst case for a
per-run overhead); ``memory`` always uses the short one (what grows with the number of runs
shows in 200 short runs; a long run's own memory is ``bench_memory.py``'s).

Three measurements, all in **CPU time** (``time.process_time`` here; for a
cluster, ``psutil``'s user + system time of this process, which hosts the scheduler and the
client, and of every nanny and worker process):

* ``overhead``: CPU per run of a plain simulate + process in this process (the same calls as
  ``bttsim simulate`` + ``bttsim process``, in memory, no Dask, no scoring, no files) against
  CPU per run of the whole ``run_campaign`` call on a warm one-worker ``LocalCluster``
  (submission, scheduler, worker, scoring, one Parquet part per run, ``results.parquet``,
  ``report.md``). ``overhead_pct`` = campaign / plain - 1; ``overhead_pct_per_run`` leaves
  out the per-campaign part (``fixed_cpu_s``: ``results.parquet``, ``report.md`` and its
  figures, timed again by resuming the finished campaign). Acceptance: <= 10 %. Part of it
  grows with wall time, not with work (the event loops of scheduler, nanny and worker:
  ``idle_cpu_pct_of_core``, measured on the idle cluster), so a loaded machine, stretching
  each run's wall time, inflates it.
* ``scaling``: runs per wall second of the same campaign on 1 and on 2 workers;
  ``scaling_efficiency`` = rate(2) / (2 rate(1)). Acceptance: >= 0.85 on 2 cores. Wall time
  depends on the cores being free: ``cpu_share`` (cluster CPU / wall / workers) says how much
  of a core each worker got, and the load averages are reported; on a shared machine read the
  efficiency together with them. ``cpu_scaling_efficiency`` (CPU per run on 1 worker over CPU
  per run on 2) is what the efficiency would be with both cores free (wall time = CPU time):
  it shows what two workers cost each other (memory bandwidth, caches) and Dask's per-worker
  share, independently of the neighbours' load.
* ``memory``: a ``--memory-runs`` campaign on 2 workers; each worker's resident set size
  (``psutil``) sampled after every finished run: first, last, max, and the least-squares slope
  over the second half, MB per 100 runs. Acceptance: flat (no growth with the run count).

Every cluster is warmed up first (imports, first-call caches) with a few runs of other seeds,
as a worker of a long campaign is.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
import tomllib
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

SHORT = "start_rpm = 2400.0\nend_rpm = 2700.0\nduration_s = 6.0\n"
PAPER = "start_rpm = 1000.0\nend_rpm = 4000.0\nduration_s = 130.0\n"
SPEC = """
[campaign]
name = "bench"
seed = {seed}
seeds = {runs}
processors = ["peak"]

[scenario.speed]
{speed}
[scenario.acquisition]
trigger_jitter_s = 1e-6
"""


def _spec(folder: Path, name: str, runs: int, seed: int, paper: bool):
    """A campaign of ``runs`` seeds of the short or the paper-length run-up."""
    from bttsim_stream.campaign import load_spec

    path = folder / f"{name}.toml"
    path.write_text(SPEC.format(runs=runs, seed=seed, speed=PAPER if paper else SHORT))
    return load_spec(path)


def plain_run(run) -> None:
    """What ``bttsim simulate`` + ``bttsim process`` compute for one run, in memory."""
    from bttsim_stream.acquisition import AcquisitionStream
    from bttsim_stream.process.pipeline import ProcessOptions, process_arrays
    from bttsim_stream.scenario import scenario_from_dict
    from bttsim_stream.sim.core import collect

    scn = scenario_from_dict(tomllib.loads(run.scenario_toml))
    stream = AcquisitionStream(scn, include_truth=True, chunk_revolutions=None)
    b = collect(list(stream.sim))
    for p in run.processors:
        process_arrays(b.opr_s, b.toa_s, stream.info, ProcessOptions(method=p.method, prep=p.prep, window=p.window),
                       truth=b.truth, revolution0=int(b.revolution[0]))


def _cluster_cpu(pids) -> float:
    """User + system CPU seconds of the processes ``pids`` (this one and the cluster's)."""
    import psutil

    total = 0.0
    for pid in pids:
        t = psutil.Process(pid).cpu_times()
        total += t.user + t.system
    return total


class _Sampler:
    """A ``progress`` for :func:`run_campaign`: the workers' RSS after every finished run."""

    def __init__(self, worker_pids: dict) -> None:
        import psutil

        self.procs = {name: psutil.Process(pid) for name, pid in worker_pids.items()}
        self.rss = {name: [] for name in worker_pids}

    def update(self, text: str, **_) -> None:
        for name, p in self.procs.items():
            self.rss[name].append(p.memory_info().rss / 2**20)

    def note(self, text: str) -> None:
        pass

    def close(self) -> None:
        pass


class _Cluster:
    """The embedded loopback ``LocalCluster`` of ``n`` single-threaded workers, warmed up."""

    def __init__(self, n: int, folder: Path, paper: bool) -> None:
        import psutil

        from bttsim_stream.campaign import connect

        client, self.cluster = connect(None, n)  # the embedded cluster of `bttsim campaign --workers n`
        self.address = self.cluster.scheduler_address
        self.worker_pids = {str(client.scheduler_info()["workers"][a]["name"]): pid
                            for a, pid in client.run(os.getpid).items()}
        client.close()
        me = psutil.Process()
        self.pids = [me.pid] + [c.pid for c in me.children(recursive=True)]
        from bttsim_stream.campaign import run_campaign

        # imports and first-call caches on every worker, with seeds the measured runs do not use
        run_campaign(_spec(folder, f"warm{n}{paper}", 2 * n, 99, paper), folder / f"warm{n}{paper}",
                     scheduler=self.address)

    def idle_cpu_pct(self, seconds: float = 5.0) -> float:
        """CPU of the idle cluster (scheduler and client loop, nannies, workers), % of a core."""
        c0, t0 = _cluster_cpu(self.pids), time.perf_counter()
        time.sleep(seconds)
        return 100.0 * (_cluster_cpu(self.pids) - c0) / (time.perf_counter() - t0)

    def close(self) -> None:
        self.cluster.close()


def _timed_campaign(cluster: _Cluster, spec, out: Path, progress=None) -> dict:
    from bttsim_stream.campaign import run_campaign

    load0 = os.getloadavg()[0]
    cpu0, t0 = _cluster_cpu(cluster.pids), time.perf_counter()
    res = run_campaign(spec, out, scheduler=cluster.address, progress=progress)
    wall, cpu = time.perf_counter() - t0, _cluster_cpu(cluster.pids) - cpu0
    n = len(cluster.worker_pids)
    # the per-campaign part: results.parquet, report.md and its figures from the part files
    # (what resuming a finished campaign does: no run, no cluster)
    c0 = time.process_time()
    run_campaign(spec, out, resume=True)
    fixed = time.process_time() - c0
    return {"runs": res.executed, "failed": res.failed, "wall_s": round(wall, 2), "cpu_s": round(cpu, 2),
            "cpu_s_per_run": round(cpu / res.executed, 4), "fixed_cpu_s": round(fixed, 3),
            "cpu_s_per_run_without_fixed": round((cpu - fixed) / res.executed, 4),
            "runs_per_s": round(res.executed / wall, 3),
            "cpu_share": round(cpu / wall / n, 3), "load_avg_1min": [round(load0, 2), round(os.getloadavg()[0], 2)]}


def _slope_per_100(values: list[float]) -> float:
    import numpy as np

    y = np.asarray(values[len(values) // 2:], float)
    if y.size < 3:
        return float("nan")
    return float(np.polyfit(np.arange(y.size), y, 1)[0] * 100)


def main(parts: set, runs: int, memory_runs: int, paper: bool) -> dict:
    import numpy as np

    from bttsim_stream.campaign import expand

    out: dict = {"scenario": ("1000 -> 4000 rpm in 130 s" if paper else "2400 -> 2700 rpm in 6 s, 255 revolutions")
                 + ", trigger jitter 1 us, method peak", "memory_scenario": "2400 -> 2700 rpm in 6 s",
                 "cpu_count": os.cpu_count(),
                 "load_avg_at_start": [round(x, 2) for x in os.getloadavg()]}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        spec = _spec(tmp, "bench", runs, 1, paper)
        if "overhead" in parts:
            plan = expand(spec)
            plain_run(expand(_spec(tmp, "warm", 1, 99, paper))[0])  # imports and first-call costs
            c0, t0 = time.process_time(), time.perf_counter()
            for r in plan:
                plain_run(r)
            cpu, wall = time.process_time() - c0, time.perf_counter() - t0
            out["plain"] = {"runs": runs, "cpu_s": round(cpu, 2), "cpu_s_per_run": round(cpu / runs, 4),
                            "wall_s": round(wall, 2)}
        for n in (1, 2):
            if not ({"overhead", "scaling"} & parts) or (n == 2 and "scaling" not in parts):
                continue
            cl = _Cluster(n, tmp, paper)
            try:
                out[f"campaign_{n}w"] = _timed_campaign(cl, spec, tmp / f"out{n}")
                out[f"campaign_{n}w"]["idle_cpu_pct_of_core"] = round(cl.idle_cpu_pct(), 2)
            finally:
                cl.close()
        if "overhead" in parts:
            c1, plain = out["campaign_1w"], out["plain"]["cpu_s_per_run"]
            out["overhead_pct"] = round(100.0 * (c1["cpu_s_per_run"] / plain - 1.0), 1)
            out["overhead_pct_per_run"] = round(100.0 * (c1["cpu_s_per_run_without_fixed"] / plain - 1.0), 1)
        if "scaling" in parts:
            r1, r2 = out["campaign_1w"]["runs_per_s"], out["campaign_2w"]["runs_per_s"]
            out["scaling_efficiency"] = round(r2 / (2 * r1), 3)
            # what the efficiency would be with both cores free (wall = CPU): CPU per run on
            # one worker over CPU per run on two
            out["cpu_scaling_efficiency"] = round(out["campaign_1w"]["cpu_s_per_run_without_fixed"]
                                                  / out["campaign_2w"]["cpu_s_per_run_without_fixed"], 3)
        if "memory" in parts:
            cl = _Cluster(2, tmp, False)
            try:
                sampler = _Sampler(cl.worker_pids)
                res = _timed_campaign(cl, _spec(tmp, "memory", memory_runs, 3, False), tmp / "memory", sampler)
            finally:
                cl.close()
            out["memory"] = {"runs": res["runs"], "failed": res["failed"], "wall_s": res["wall_s"],
                             "samples": len(next(iter(sampler.rss.values()))),
                             "worker_rss_mb": {name: {"first": round(v[0], 1), "last": round(v[-1], 1),
                                                      "max": round(max(v), 1),
                                                      "mean_by_quarter": [round(float(np.mean(q)), 1)
                                                                          for q in np.array_split(v, 4)],
                                                      "slope_mb_per_100_runs_2nd_half": round(_slope_per_100(v), 2)}
                                               for name, v in sampler.rss.items()}}
    out["load_avg_at_end"] = [round(x, 2) for x in os.getloadavg()]
    return out


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parts", default="overhead,scaling,memory", help="overhead, scaling, memory (all)")
    parser.add_argument("--runs", type=int, default=8, help="runs of the overhead and scaling campaigns (8)")
    parser.add_argument("--memory-runs", type=int, default=200, help="runs of the memory campaign (200)")
    parser.add_argument("--length", choices=("paper", "short"), default="paper",
                        help="run-up of the overhead and scaling runs: paper (130 s, default) or short (6 s)")
    args = parser.parse_args()
    parts = {p.strip() for p in args.parts.split(",") if p.strip()}
    print(json.dumps(main(parts, args.runs, args.memory_runs, args.length == "paper"), indent=2))

"""Benchmark: CPU of the live chain against the simulator alone (prints JSON).

Usage::

    python bench/bench_live_cpu.py                 # the default scenario
    python bench/bench_live_cpu.py SCENARIO.toml --repeat 2

In one run, side by side, on the same scenario:

* ``bttsim simulate`` (a child process; its CPU from ``os.wait4``);
* ``bttsim run`` (run in this process, :func:`bttsim_stream.orchestrate.run_all`): each node
  (recorder, processor, viewer, simulator) is a child process, and its CPU comes from
  ``os.wait4`` when it is reaped -- exact, nothing sampled. The run's own process (the
  progress line, the status board) is reported apart (``orchestrator_cpu_s``).

CPU is user + system seconds (the machine is shared: wall time would measure the
neighbours). ``ratio`` = all nodes / simulate; the target is <= 3. With ``--repeat`` each
measurement is repeated and the smallest CPU of each process kept.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

BTTSIM = [sys.executable, "-m", "bttsim_stream.cli"]


class _RusagePopen(subprocess.Popen):
    """A :class:`subprocess.Popen` that reaps its child with ``os.wait4`` and keeps the
    child's resource usage (``self.rusage``)."""

    rusage = None

    def _wait4(self, pid, flags):
        pid_, sts, ru = os.wait4(pid, flags)
        if pid_ == pid:
            self.rusage = ru
        return pid_, sts

    def _try_wait(self, wait_flags):  # the blocking and the timed waits
        try:
            return self._wait4(self.pid, wait_flags)
        except ChildProcessError:
            return self.pid, 0

    def _internal_poll(self, _deadstate=None, _waitpid=None, **kw):  # poll()
        return super()._internal_poll(_deadstate, _waitpid=self._wait4, **kw)


def _cpu(ru) -> float:
    return float(ru.ru_utime + ru.ru_stime) if ru is not None else float("nan")


def simulate_cpu(scenario: str | None, work: Path) -> float:
    """CPU seconds of ``bttsim simulate`` of the scenario."""
    cmd = [*BTTSIM, "simulate", "-q", "--out", str(work / "sim.mcap")] + ([scenario] if scenario else [])
    p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, ru = os.wait4(p.pid, 0)
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"bttsim simulate failed: {p.stderr.read().decode(errors='replace')[-400:]}")
    return _cpu(ru)


def run_cpu(scenario: str | None, work: Path) -> dict:
    """Each node's CPU seconds in ``bttsim run`` of the scenario, and the run's own."""
    from bttsim_stream import orchestrate

    procs: list = []

    class Popen(_RusagePopen):
        def __init__(self, args, *a, **kw):
            super().__init__(args, *a, **kw)
            procs.append((args[3], self))  # [python, -m, bttsim_stream.nodes, NODE, ...]

    before = resource.getrusage(resource.RUSAGE_SELF)
    real = orchestrate.subprocess.Popen
    orchestrate.subprocess.Popen = Popen
    try:
        result = orchestrate.run_all(scenario, str(work / "run"), quiet=True)
    finally:
        orchestrate.subprocess.Popen = real
    after = resource.getrusage(resource.RUSAGE_SELF)
    if result["failed"] or not (result["summary"] or {}).get("complete"):
        raise SystemExit(f"bttsim run failed: {result['failed']} {result['recording']}")
    nodes = {name: _cpu(p.rusage) for name, p in procs}
    return {"nodes": nodes, "orchestrator": _cpu(after) - _cpu(before), "wall_s": result["wall_s"],
            "revolutions": result["summary"].get("revolutions_processed")}


def main(scenario: str | None = None, repeat: int = 1) -> dict:
    sims, runs = [], []
    with tempfile.TemporaryDirectory(prefix="bench-live-cpu-") as tmp:
        for _ in range(repeat):
            sims.append(simulate_cpu(scenario, Path(tmp)))
            runs.append(run_cpu(scenario, Path(tmp)))
    nodes = {n: min(r["nodes"][n] for r in runs) for n in runs[0]["nodes"]}
    total = sum(nodes.values())
    sim = min(sims)
    return {"scenario": scenario or "default", "repeat": repeat,
            "simulate_cpu_s": round(sim, 3),
            "run_node_cpu_s": {n: round(v, 3) for n, v in nodes.items()},
            "run_all_nodes_cpu_s": round(total, 3),
            "node_share": {n: round(v / total, 3) for n, v in nodes.items()},
            "orchestrator_cpu_s": round(min(r["orchestrator"] for r in runs), 3),
            "run_wall_s": round(min(r["wall_s"] for r in runs), 2),
            "revolutions": runs[0]["revolutions"],
            "ratio": round(total / sim, 2), "target_ratio": 3.0, "ok": total <= 3.0 * sim}


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scenario", nargs="?", help="scenario TOML (default: the paper's Table 1)")
    ap.add_argument("--repeat", type=int, default=1)
    a = ap.parse_args()
    print(json.dumps(main(a.scenario, a.repeat), indent=2))

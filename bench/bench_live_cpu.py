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

``--floor`` also measures what the live chain costs before any work per message, with the
bus as it is (one message per key and revolution): each node's start-up (``bttsim run`` of
a 0.3 s run), the CPU of Zenoh's own threads in each node (``rx-*``, ``tx-*``, ... read
from ``/proc/PID/task`` while the run goes: receiving and sending the messages), and
``bttsim process`` of the run's recording (the work the processor's final report repeats).
``floor_ratio`` = (the simulation itself, ``bttsim simulate``'s CPU + the other nodes'
start-ups + every node's Zenoh threads + the report) / simulate: a lower bound of
``ratio`` that no change inside the nodes' code per message can go below.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import threading
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


#: Zenoh's runtime threads (by name prefix): what they spend is the bus's, not the node's code.
ZENOH_THREADS = ("rx-", "tx-", "acc-", "net-", "app-")


def _zenoh_cpu(procs: list, stop: threading.Event, out: dict) -> None:
    """Until ``stop``: each node's Zenoh threads' CPU seconds, the latest read of each thread
    (``/proc/PID/task/TID/stat``, every 50 ms) summed into ``out[node]``."""
    tick = os.sysconf("SC_CLK_TCK")
    last: dict = {}
    while not stop.wait(0.05):
        for name, p in list(procs):
            try:
                tids = os.listdir(f"/proc/{p.pid}/task")
            except OSError:
                continue
            for tid in tids:
                try:
                    with open(f"/proc/{p.pid}/task/{tid}/stat") as f:
                        stat = f.read()
                except OSError:
                    continue
                comm, rest = stat[stat.index("(") + 1:stat.rindex(")")], stat[stat.rindex(")") + 2:].split()
                if comm.startswith(ZENOH_THREADS):
                    last[(name, p.pid, tid)] = (int(rest[11]) + int(rest[12])) / tick
        for name, _ in procs:
            out[name] = sum(v for (n, _, _), v in last.items() if n == name)


def run_cpu(scenario: str | None, work: Path, zenoh: bool = False) -> dict:
    """Each node's CPU seconds in ``bttsim run`` of the scenario, and the run's own
    (``zenoh``: also each node's Zenoh threads')."""
    from bttsim_stream import orchestrate

    procs: list = []
    threads: dict = {}
    stop = threading.Event()
    watch = threading.Thread(target=_zenoh_cpu, args=(procs, stop, threads), daemon=True)
    if zenoh:
        watch.start()

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
        stop.set()
        if zenoh:
            watch.join()
    after = resource.getrusage(resource.RUSAGE_SELF)
    if result["failed"] or not (result["summary"] or {}).get("complete"):
        raise SystemExit(f"bttsim run failed: {result['failed']} {result['recording']}")
    nodes = {name: _cpu(p.rusage) for name, p in procs}
    return {"nodes": nodes, "orchestrator": _cpu(after) - _cpu(before), "wall_s": result["wall_s"],
            "revolutions": result["summary"].get("revolutions_processed"), "zenoh": threads,
            "recording": str(work / "run" / "run.mcap")}


#: A 0.3 s run of the default wheel: the nodes' start-up and end, almost no revolutions.
SHORT_RUN = "[speed]\nstart_rpm = 2970.0\nend_rpm = 3030.0\nduration_s = 0.3\n"


def process_cpu(recording: str) -> float:
    """CPU seconds of ``bttsim process`` of a recording."""
    p = subprocess.Popen([*BTTSIM, "process", recording], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, ru = os.wait4(p.pid, 0)
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"bttsim process failed: {p.stderr.read().decode(errors='replace')[-400:]}")
    return _cpu(ru)


def floor(scenario: str | None, work: Path, sim: float, run: dict) -> dict:
    """What the live chain costs before any work per message (see the module's docstring)."""
    short = work / "short.toml"
    short.write_text(SHORT_RUN)
    start = run_cpu(str(short), work / "short")["nodes"]
    report = process_cpu(run["recording"])
    consumers = [n for n in run["nodes"] if n != "sim"]
    total = sim + sum(start[n] for n in consumers) + sum(run["zenoh"].values()) + report
    return {"startup_cpu_s": {n: round(v, 3) for n, v in start.items()},
            "zenoh_threads_cpu_s": {n: round(v, 3) for n, v in run["zenoh"].items()},
            "process_cpu_s": round(report, 3),
            "floor_cpu_s": round(total, 3), "floor_ratio": round(total / sim, 2)}


def main(scenario: str | None = None, repeat: int = 1, with_floor: bool = False) -> dict:
    sims, runs = [], []
    with tempfile.TemporaryDirectory(prefix="bench-live-cpu-") as tmp:
        for k in range(repeat):
            sims.append(simulate_cpu(scenario, Path(tmp)))
            runs.append(run_cpu(scenario, Path(tmp) / f"run{k}", zenoh=with_floor))
        nodes = {n: min(r["nodes"][n] for r in runs) for n in runs[0]["nodes"]}
        total = sum(nodes.values())
        sim = min(sims)
        extra = floor(scenario, Path(tmp), sim, runs[0]) if with_floor else {}
    return extra | {"scenario": scenario or "default", "repeat": repeat,
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
    ap.add_argument("--floor", action="store_true",
                    help="also the cost before any work per message: start-ups, Zenoh's threads, the report")
    a = ap.parse_args()
    print(json.dumps(main(a.scenario, a.repeat, a.floor), indent=2))

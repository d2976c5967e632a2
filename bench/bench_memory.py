"""Benchmark: peak memory against run length (prints JSON).

Usage::

    python bench/bench_memory.py                  # 130 s (default) vs 1000 s run-up
    python bench/bench_memory.py --long-s 520     # a shorter long run

For the default 130 s run-up and a longer one (same speeds, 1000 -> 4000 rpm), measures the
peak resident set size (MB) of

* ``bttsim simulate``, ``bttsim process``, ``bttsim export`` (CSV), ``bttsim view``
  (``--rrd``) and ``bttsim replay`` (``--rate max`` to a loopback listen endpoint that nobody
  connects to: what reading and publishing the file costs) of the simulated recording (exact:
  ``os.wait4``'s ``ru_maxrss``);
* every node of ``bttsim run`` -- processor, recorder, viewer, simulator (``VmHWM`` of each
  node process, read from ``/proc`` every 0.1 s while it runs: a peak in its last 0.1 s can
  be missed);

and the ratio long / default of each. The target: every ratio within 1.25 (memory that does
not grow with the run's length). ``--only process,export`` measures some commands only
(``run`` for the nodes). Linux only (``/proc``).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _proc import children, memory_mb, node_name  # noqa: E402
from bttsim_stream.testing import free_port  # noqa: E402

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

BTTSIM = [sys.executable, "-m", "bttsim_stream.cli"]


def _peak_mb(cmd: list, cwd: Path) -> float:
    """Peak RSS (MB) of one command (not of its children)."""
    p = subprocess.Popen(cmd, cwd=cwd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    _, status, usage = os.wait4(p.pid, 0)
    p.returncode = os.waitstatus_to_exitcode(status)
    if p.returncode not in (0, 3):
        raise RuntimeError(f"{' '.join(map(str, cmd))}: exit {p.returncode}")
    return usage.ru_maxrss / 1024.0


def _run_nodes_mb(scenario: Path, out: Path) -> dict:
    """Peak RSS (MB) of every node of ``bttsim run``, sampled."""
    p = subprocess.Popen([*BTTSIM, "run", str(scenario), "--out", str(out), "-q"], stdout=subprocess.DEVNULL,
                         stderr=subprocess.DEVNULL)
    peaks: dict[str, float] = {}
    names: dict[int, str] = {}
    while p.poll() is None:
        todo = children(p.pid)
        seen = set()
        while todo:  # the whole process tree below the run
            pid = todo.pop()
            if pid in seen:
                continue
            seen.add(pid)
            todo += children(pid)
            if pid not in names:
                name = node_name(pid)
                if name is None:
                    continue
                names[pid] = name
            mb = memory_mb(pid, "VmHWM")
            if mb is not None:
                peaks[names[pid]] = max(peaks.get(names[pid], 0.0), mb)
        time.sleep(0.1)
    return dict(sorted(peaks.items()))


COMMANDS = ("simulate", "process", "export", "view", "replay", "run")


def measure(duration_s: float | None, work: Path, only: tuple) -> dict:
    """Peak RSS of the commands in ``only`` (``run``: the run nodes) for one run-up length."""
    tag = "default" if duration_s is None else f"{duration_s:g}s"
    scenario = work / f"{tag}.toml"
    scenario.write_text("" if duration_s is None else
                        f"[speed]\nstart_rpm = 1000.0\nend_rpm = 4000.0\nduration_s = {duration_s!r}\n")
    mcap = work / f"{tag}.mcap"
    res = {"simulate": _peak_mb([*BTTSIM, "simulate", str(scenario), "--out", str(mcap), "-q"], work)}
    cmds = {"process": ["process", str(mcap), "--summary", str(work / f"{tag}.json")],
            "export": ["export", str(mcap), "--format", "csv", "--out", str(work / f"{tag}.export")],
            "view": ["view", str(mcap), "--rrd", str(work / f"{tag}.rrd")],
            "replay": ["replay", str(mcap), "--wait", "0", "-l", f"tcp/127.0.0.1:{free_port()}"]}
    for name, argv in cmds.items():
        if name in only:
            res[name] = _peak_mb([*BTTSIM, *argv], work)
    shutil.rmtree(work / f"{tag}.export", ignore_errors=True)
    for f in (mcap, work / f"{tag}.rrd"):
        f.unlink(missing_ok=True)
    if "run" in only:
        res["run_nodes"] = _run_nodes_mb(scenario, work / f"{tag}.run")
        shutil.rmtree(work / f"{tag}.run", ignore_errors=True)
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--long-s", type=float, default=1000.0, help="the long run-up's duration, s (1000)")
    ap.add_argument("--only", default=",".join(COMMANDS), metavar="CMDS",
                    help=f"comma-separated commands to measure ({','.join(COMMANDS)}; simulate always)")
    ap.add_argument("--no-run", action="store_true", help="leave out bttsim run (its nodes)")
    args = ap.parse_args()
    only = tuple(c for c in args.only.split(",") if c in COMMANDS and not (args.no_run and c == "run"))
    with tempfile.TemporaryDirectory(prefix="bttsim-bench-memory-") as tmp:
        work = Path(tmp)
        short = measure(None, work, only)
        long = measure(args.long_s, work, only)
    ratio = {k: round(long[k] / short[k], 3) for k in COMMANDS if k in short and k != "run"}
    if "run_nodes" in short:
        ratio["run_nodes"] = {n: round(long["run_nodes"][n] / mb, 3) for n, mb in short["run_nodes"].items()
                              if n in long["run_nodes"]}
    print(json.dumps({"unit": "MB peak RSS", "default_130s": short, f"runup_{args.long_s:g}s": long,
                      "ratio": ratio, "target_ratio": 1.25}, indent=2))


if __name__ == "__main__":
    main()

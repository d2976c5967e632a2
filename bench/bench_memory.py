"""Benchmark: peak memory against run length (prints JSON).

Usage::

    python bench/bench_memory.py                  # 130 s (default) vs 1000 s run-up
    python bench/bench_memory.py --long-s 520     # a shorter long run

For the default 130 s run-up and a longer one (same speeds, 1000 -> 4000 rpm), measures the
peak resident set size (MB) of

* ``bttsim simulate`` and ``bttsim process`` (exact: ``os.wait4``'s ``ru_maxrss``);
* every node of ``bttsim run`` (``VmHWM`` of each node process, read from ``/proc`` every
  0.1 s while it runs: a peak in its last 0.1 s can be missed);

and the ratio long / default of each. Issue 25's acceptance: every ratio of ``process`` and
of the run nodes within 1.25. Linux only (``/proc``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

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


def _children(pid: int) -> list[int]:
    out = []
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat") as f:
                    ppid = int(f.read().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            if ppid == pid:
                out.append(int(d))
    return out


def _node_name(pid: int) -> str | None:
    try:
        argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    except OSError:
        return None
    argv = [a.decode(errors="replace") for a in argv]
    if "bttsim_stream.nodes" in argv:
        i = argv.index("bttsim_stream.nodes")
        return argv[i + 1] if i + 1 < len(argv) else None
    return None


def _hwm_mb(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def _run_nodes_mb(scenario: Path, out: Path) -> dict:
    """Peak RSS (MB) of every node of ``bttsim run``, sampled."""
    p = subprocess.Popen([*BTTSIM, "run", str(scenario), "--out", str(out), "-q"], stdout=subprocess.DEVNULL,
                         stderr=subprocess.DEVNULL)
    peaks: dict[str, float] = {}
    names: dict[int, str] = {}
    while p.poll() is None:
        todo = _children(p.pid)
        seen = set()
        while todo:  # the whole process tree below the run
            pid = todo.pop()
            if pid in seen:
                continue
            seen.add(pid)
            todo += _children(pid)
            if pid not in names:
                name = _node_name(pid)
                if name is None:
                    continue
                names[pid] = name
            mb = _hwm_mb(pid)
            if mb is not None:
                peaks[names[pid]] = max(peaks.get(names[pid], 0.0), mb)
        time.sleep(0.1)
    return dict(sorted(peaks.items()))


def measure(duration_s: float | None, work: Path, run: bool) -> dict:
    """Peak RSS of simulate, process and (``run``) the run nodes for one run-up length."""
    tag = "default" if duration_s is None else f"{duration_s:g}s"
    scenario = work / f"{tag}.toml"
    scenario.write_text("" if duration_s is None else
                        f"[speed]\nstart_rpm = 1000.0\nend_rpm = 4000.0\nduration_s = {duration_s!r}\n")
    mcap = work / f"{tag}.mcap"
    res = {"simulate": _peak_mb([*BTTSIM, "simulate", str(scenario), "--out", str(mcap), "-q"], work),
           "process": _peak_mb([*BTTSIM, "process", str(mcap), "--summary", str(work / f"{tag}.json")], work)}
    mcap.unlink()
    if run:
        res["run_nodes"] = _run_nodes_mb(scenario, work / f"{tag}.run")
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--long-s", type=float, default=1000.0, help="the long run-up's duration, s (1000)")
    ap.add_argument("--no-run", action="store_true", help="simulate and process only (no bttsim run)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="bttsim-bench-memory-") as tmp:
        work = Path(tmp)
        short = measure(None, work, not args.no_run)
        long = measure(args.long_s, work, not args.no_run)
    ratio = {k: round(long[k] / short[k], 3) for k in ("simulate", "process")}
    if "run_nodes" in short:
        ratio["run_nodes"] = {n: round(long["run_nodes"][n] / mb, 3) for n, mb in short["run_nodes"].items()
                              if n in long["run_nodes"]}
    print(json.dumps({"unit": "MB peak RSS", "default_130s": short, f"runup_{args.long_s:g}s": long,
                      "ratio": ratio, "target_ratio": 1.25}, indent=2))


if __name__ == "__main__":
    main()

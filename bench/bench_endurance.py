"""Benchmark: endurance of ``bttsim run`` at maximum rate, RSS of every node over time
(prints JSON, plots a PNG).

Usage::

    python bench/bench_endurance.py                          # 3600 s profile (~150k revolutions, ~22M TOAs)
    python bench/bench_endurance.py --duration-s 600 --png docs/img/endurance_rss.png

The scenario is the default wheel (29 blades x 5 probes) on a slow sweep with dwells,
``--duration-s`` of simulated time in all: a ramp 1000 -> 2581.5 rpm (30 %), a dwell on
the EO 8 resonance (10 %), a ramp to 4000 rpm (30 %), a dwell there (10 %) and a run-down
to 1000 rpm (20 %). ``bttsim run`` publishes it as fast as the nodes take it (the
simulator's ``--rate max``, lossless back-pressure), so an hour of acquisition takes a few
minutes of wall time per core.

Every ``--every`` seconds the resident set size (``VmRSS``) of each node process
(recorder, processor, viewer, simulator) is read from ``/proc`` (the time axis is the wall
time of the run; the revolution and TOA counts are the run's). The JSON has each node's series, its peak, and the
*growth*: the mean RSS over the last quarter of the run divided by the mean over the second
quarter (after the start-up); a flat curve is near 1. ``growth_streaming`` and
``peak_streaming_mb`` are the same over the samples taken while the simulator node ran (the
stream, without the processor's final report after it). Linux only (``/proc``).
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

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _proc import children, memory_mb, node_name  # noqa: E402

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

BTTSIM = [sys.executable, "-m", "bttsim_stream.cli"]
NODES = ("recorder", "processor", "viewer", "sim")
RESONANCE_RPM = 2581.5  # EO 8 of the default wheel


def scenario_toml(duration_s: float) -> str:
    """The sweep-and-dwell profile of ``duration_s`` simulated seconds (default wheel)."""
    d = float(duration_s)
    segs = [(0.3 * d, RESONANCE_RPM), (0.1 * d, RESONANCE_RPM), (0.3 * d, 4000.0), (0.1 * d, 4000.0),
            (0.2 * d, 1000.0)]
    rows = ",\n  ".join(f"{{duration_s = {t!r}, end_rpm = {r!r}}}" for t, r in segs)
    return f"[speed]\nstart_rpm = 1000.0\nsegments = [\n  {rows},\n]\n"








def run(duration_s: float, every_s: float, work: Path) -> dict:
    """``bttsim run`` of the profile; RSS series of every node."""
    scn = work / "endurance.toml"
    scn.write_text(scenario_toml(duration_s))
    out = work / "run"
    t0 = time.monotonic()
    p = subprocess.Popen([*BTTSIM, "run", str(scn), "--out", str(out), "-q"], stdout=subprocess.DEVNULL,
                         stderr=subprocess.PIPE)
    series: dict[str, list] = {n: [] for n in NODES}
    names: dict[int, str] = {}
    while p.poll() is None:
        now = round(time.monotonic() - t0, 2)
        for pid in children(p.pid):
            name = names.get(pid) or node_name(pid)
            if name is None:
                continue
            names[pid] = name
            mb = memory_mb(pid)
            if mb is not None and name in series:
                series[name].append((now, round(mb, 1)))
        time.sleep(every_s)
    err = p.stderr.read().decode(errors="replace")
    if p.returncode not in (0, 3):
        raise SystemExit(f"bttsim run failed (exit {p.returncode}): {err[-400:]}")
    from bttsim_stream.scenario import load_scenario

    summary = json.loads((out / "summary.json").read_text())
    info = load_scenario(str(scn))
    return {"wall_s": round(time.monotonic() - t0, 1), "series": series, "summary": summary,
            "toas_per_revolution": info.rotor.n_blades * len(info.probes.angles_deg)}


def _quarters(v: list) -> tuple[float, float] | None:
    """Mean of the second and of the last quarter of ``v`` (None: too few samples)."""
    if len(v) < 8:
        return None
    q = len(v) // 4
    second, last = v[q:2 * q], v[3 * q:]
    return sum(second) / len(second), sum(last) / len(last)


def _growth(points: list, streaming_until: float | None) -> dict:
    """Peak, and the growth over the whole series and over the samples taken while the
    simulator ran (the stream itself, without what a node does after it: the processor's
    final report)."""
    v = [mb for _, mb in points]
    out: dict = {"peak_mb": max(v, default=None), "growth": None}
    whole = _quarters(v)
    if whole:
        out.update(second_quarter_mean_mb=round(whole[0], 1), last_quarter_mean_mb=round(whole[1], 1),
                   growth=round(whole[1] / whole[0], 3))
    live = [mb for t, mb in points if streaming_until is None or t <= streaming_until]
    out["peak_streaming_mb"] = max(live, default=None)
    q = _quarters(live)
    out["growth_streaming"] = round(q[1] / q[0], 3) if q else None
    return out


def plot(result: dict, png: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4.2), dpi=110)
    for name, pts in result["series"].items():
        if pts:
            ax.plot([t for t, _ in pts], [mb for _, mb in pts], label=name)
    ax.set_xlabel("wall time of the run, s")
    ax.set_ylabel("RSS, MB")
    ax.set_ylim(bottom=0)
    ax.set_title(f"bttsim run, {result['revolutions']:,} revolutions, {result['toas'] / 1e6:.1f} M TOAs "
                 f"({result['duration_s']:g} s of sweep and dwells) at maximum rate", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(png)


def main(duration_s: float = 3600.0, every_s: float = 1.0, png: str | None = None) -> dict:
    with tempfile.TemporaryDirectory(prefix="bench-endurance-") as tmp:
        r = run(duration_s, every_s, Path(tmp))
    s = r["summary"]
    revs = int(s.get("revolutions_processed") or 0)
    result = {"duration_s": duration_s, "revolutions": revs, "toas": revs * r["toas_per_revolution"],
              "wall_s": r["wall_s"],
              "complete": s.get("complete"), "lost": s.get("lost"),
              "nodes": {n: _growth(p, max((t for t, _ in r["series"]["sim"]), default=None))
                        for n, p in r["series"].items()}, "every_s": every_s,
              "series": r["series"]}
    if png:
        plot(result, png)
        result["png"] = png
    return result


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration-s", type=float, default=3600.0, help="simulated seconds of the profile (3600)")
    ap.add_argument("--every", type=float, default=1.0, metavar="S", help="RSS sampling period, s (1)")
    ap.add_argument("--png", help="plot the RSS curves into this PNG (matplotlib)")
    a = ap.parse_args()
    print(json.dumps(main(a.duration_s, a.every, a.png), indent=2))

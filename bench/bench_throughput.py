"""Benchmark: sustained real-time throughput of the processor node (prints JSON).

Usage::

    python bench/bench_throughput.py                       # 10 min per level (the acceptance run)
    python bench/bench_throughput.py --minutes 0.5         # a short run
    python bench/bench_throughput.py --factors 1,2,4 --stages 2

One stage of an engine's shape -- 60 blades x 16 probes at a constant 10,000 rpm (960 TOAs
per revolution, 160,000 TOA/s in real time) -- is published by a simulator node paced at
``F`` times real time (``--rate F``; F = 1 is ``--realtime``), blind (no truth), to a
processor node (``--no-score``) over a real Zenoh link on loopback. For each factor of
``--factors`` in turn (until one fails) the bench runs ``--minutes`` of wall time and
watches the bus from a third session: the newest OPR pulse and the newest fit, every
0.5 s. The processor *keeps up* at a factor when

* the backlog (newest OPR revolution minus newest fitted revolution) does not grow: its
  least-squares slope over the second half of the run is below 1 % of the revolution rate
  (a backlog growing that fast would reach a second's worth of revolutions in 100 s), and its
  largest value there is under one second's worth of revolutions,
* and the processor's final status counts 0 lost (and processed every revolution).

The rate is the one seen on the bus (OPR pulses per second x 960). A source that cannot hold
the pace (below 95 % of the target: ``source_held_pace`` false; the simulator computes each
revolution as it publishes it, and shares the cores) ends the search: a higher factor would
not load the processor more. ``--source replay`` publishes a recording of the stage instead
(made first with ``bttsim simulate``, not timed), which costs far less per revolution.

``TOA/s per processor core`` = the TOA rate / the processor's CPU share of one core (user +
system from ``/proc``, over the second half of the run, the steady state), measured at the
highest factor that kept up. The engine's need follows: ~2.4e6 TOA/s (10 stages x 16
probes x 60 blades at 15,000 rpm) / that figure.

Then the same with ``--stages`` stages on one bus through ``bttsim router`` (every node a
client of the router; each stage its own rig key, ``stage1``, ``stage2``..., its own
simulator and processor) at the highest factor that kept up alone (or 1): whether every
processor keeps up, and each one's CPU.

The machine is shared: the results depend on the load (printed, ``loadavg``).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

NODE = [sys.executable, "-m", "bttsim_stream.nodes"]
PROBES_DEG = [5.0, 10.6, 15.15, 23.82, 40.0, 70.0, 100.0, 148.5, 190.35, 202.11, 220.0, 245.0, 255.6, 280.0,
              301.5, 330.0]
RPM = 10_000.0
N_BLADES = 60
TOA_PER_REV = N_BLADES * len(PROBES_DEG)
ENGINE_TOA_S = 2.4e6
TICK = os.sysconf("SC_CLK_TCK")


def stage_scenario(rig: str, duration_s: float) -> str:
    """The TOML of one engine stage at a constant ``RPM`` for ``duration_s`` (simulated time)."""
    from bttsim_stream.scenario import dumps_toml, scenario_from_dict

    return dumps_toml(scenario_from_dict({
        "rotor": {"n_blades": N_BLADES}, "probes": {"angles_deg": PROBES_DEG},
        "speed": {"start_rpm": RPM, "end_rpm": RPM, "duration_s": float(duration_s)}, "run": {"rig": rig}}))


def _cpu_s(pid: int) -> float | None:
    try:
        f = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None
    return (int(f[11]) + int(f[12])) / TICK


class _Watch:
    """Newest OPR and fitted revolution of each rig, from the bus (decoded headers only)."""

    def __init__(self, session, rigs) -> None:
        from bttsim_stream.bus import codec, keys

        self.opr = dict.fromkeys(rigs, -1)
        self.fit = dict.fromkeys(rigs, -1)
        self._subs = []
        for rig in rigs:
            def on_opr(s, rig=rig):
                self.opr[rig] = max(self.opr[rig], codec.decode_opr(s.payload.to_bytes()).header.revolution)

            def on_fit(s, rig=rig):
                self.fit[rig] = max(self.fit[rig], codec.decode_fit(s.payload.to_bytes()).header.revolution)

            self._subs += [session.declare_subscriber(keys.opr_key(rig), on_opr),
                           session.declare_subscriber(keys.fits_key(rig), on_fit)]

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()


def _slope(t, y) -> float:
    n = len(t)
    if n < 2:
        return 0.0
    mt, my = sum(t) / n, sum(y) / n
    den = sum((a - mt) ** 2 for a in t)
    return sum((a - mt) * (b - my) for a, b in zip(t, y)) / den if den else 0.0


def _stop(p: subprocess.Popen, timeout_s: float) -> int:
    try:
        return p.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, signal.SIGTERM)
        try:
            return p.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            return p.wait()


def run_level(factor: float, minutes: float, n_stages: int, work: Path, source: str = "sim") -> dict:
    """One run: ``n_stages`` stages at ``factor`` x real time for ``minutes`` of wall time."""
    from bttsim_stream.bus.session import free_port, make_config, open_session
    from bttsim_stream.bus.status import read_status_file

    wall_s = minutes * 60.0
    rigs = [f"stage{i + 1}" for i in range(n_stages)]
    procs: list[subprocess.Popen] = []
    logs = []

    def start(name: str, args: list) -> subprocess.Popen:
        log = open(work / f"{name}.log", "w")
        logs.append(log)
        p = subprocess.Popen([*NODE, *map(str, args)], stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        procs.append(p)
        return p

    router = None
    if n_stages > 1:  # one bus through a router: every node a client of it
        rport = free_port()
        router = start("router", ["router", "-l", f"tcp/127.0.0.1:{rport}"])
        client = ["-m", "client", "-e", f"tcp/127.0.0.1:{rport}"]
    sources, processors, status, ports = {}, {}, {}, {}
    obs_port = free_port()
    try:
        for rig in rigs:
            scn = work / f"{rig}.toml"
            scn.write_text(stage_scenario(rig, wall_s * factor))
            if source == "replay":  # the same stage, recorded first (not timed)
                subprocess.run([sys.executable, "-m", "bttsim_stream.cli", "simulate", "-q", "--no-truth",
                                "--out", str(work / f"{rig}.mcap"), str(scn)], check=True, stdout=subprocess.DEVNULL)
            status[rig] = work / f"{rig}-processor.json"
            ports[rig] = free_port()
        if router is None:  # the watching session listens: the processors and sources reach it
            conf = make_config("peer", listen=[f"tcp/127.0.0.1:{obs_port}"])
        else:
            conf = make_config("client", connect=[f"tcp/127.0.0.1:{rport}"])
        samples = []
        with open_session(conf) as session:
            watch = _Watch(session, rigs)
            for rig in rigs:
                src_flags = client if router is not None else ["-l", f"tcp/127.0.0.1:{ports[rig]}", "-e",
                                                               f"tcp/127.0.0.1:{obs_port}"]
                flags = client if router is not None else ["-e", f"tcp/127.0.0.1:{ports[rig]}", "-e",
                                                           f"tcp/127.0.0.1:{obs_port}"]
                processors[rig] = start(f"{rig}-processor", ["processor", "--rig", rig, "--no-score",
                                                             "--status-file", status[rig], *flags])
                if source == "replay":
                    sources[rig] = start(f"{rig}-replay", ["replay", work / f"{rig}.mcap", "--rate", f"{factor:g}",
                                                           "--wait", "30", *src_flags])
                else:  # each waits for its processor's tokens
                    sources[rig] = start(f"{rig}-sim", ["sim", work / f"{rig}.toml", "--rate", f"{factor:g}",
                                                        "--no-truth", "--wait-for", "1", *src_flags])
            t0 = None
            while any(p.poll() is None for p in sources.values()):
                time.sleep(0.5)
                now = time.monotonic()
                if t0 is None and all(v >= 0 for v in watch.opr.values()):
                    t0 = now
                if t0 is not None:
                    samples.append((now - t0, dict(watch.opr), dict(watch.fit),
                                    {r: _cpu_s(p.pid) for r, p in processors.items()}))
            time.sleep(1.0)
            watch.close()
        codes = {f"{r}-{source}": sources[r].returncode for r in rigs}
        for r in rigs:
            codes[f"{r}-processor"] = _stop(processors[r], 300)
    finally:
        for p in procs:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGTERM)
                try:
                    p.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    os.killpg(p.pid, signal.SIGKILL)
                    p.wait()
        for log in logs:
            log.close()
    return _verdict(factor, minutes, rigs, samples, status, codes, read_status_file)


def _verdict(factor, minutes, rigs, samples, status, codes, read_status_file) -> dict:
    target_rev_s = RPM / 60.0 * factor
    half = [s for s in samples if s[0] >= samples[-1][0] / 2] if samples else []
    stages = {}
    for rig in rigs:
        st = read_status_file(status[rig], "processor")
        stats = dict(st.stats) if st is not None else {}
        if len(half) >= 2:
            dt = half[-1][0] - half[0][0]
            rev_s = (half[-1][1][rig] - half[0][1][rig]) / dt if dt > 0 else 0.0
            cpu = [s[3][rig] for s in half if s[3][rig] is not None]
            cpu_share = (cpu[-1] - cpu[0]) / dt if len(cpu) >= 2 and dt > 0 else float("nan")
            backlog = [s[1][rig] - s[2][rig] for s in half]
            slope = _slope([s[0] for s in half], backlog)
        else:
            rev_s, cpu_share, backlog, slope = 0.0, float("nan"), [0], 0.0
        paced = rev_s >= 0.95 * target_rev_s
        flat = slope < 0.01 * max(rev_s, 1.0) and max(backlog) < max(rev_s, 1.0)
        lost = stats.get("lost")
        complete = stats.get("revolutions_processed") == stats.get("revolutions_expected") and stats.get("report")
        stages[rig] = {
            "toa_per_s": round(rev_s * TOA_PER_REV), "revolutions_per_s": round(rev_s, 1),
            "source_held_pace": paced, "backlog_revolutions_max": int(max(backlog)),
            "backlog_slope_rev_per_s": round(slope, 3), "backlog_flat": flat,
            "processor_cpu_share": round(cpu_share, 3),
            "toa_per_s_per_core": round(rev_s * TOA_PER_REV / cpu_share) if cpu_share > 0 else None,
            "lost": lost, "revolutions_processed": stats.get("revolutions_processed"),
            "revolutions_expected": stats.get("revolutions_expected"),
            "kept_up": bool(flat and lost == 0 and complete and not any(codes.values()))}
    return {"factor": factor, "target_toa_per_s": round(target_rev_s * TOA_PER_REV), "minutes": minutes,
            "exit_codes": codes, "stages": stages, "kept_up": all(s["kept_up"] for s in stages.values()),
            "loadavg": [round(x, 2) for x in os.getloadavg()]}


def main(minutes: float = 10.0, factors=(1, 2, 4, 8), n_stages: int = 2, source: str = "sim") -> dict:
    levels, best = [], None
    with tempfile.TemporaryDirectory(prefix="bench-throughput-") as tmp:
        for i, f in enumerate(factors):
            work = Path(tmp) / f"single-{i}"
            work.mkdir()
            r = run_level(float(f), minutes, 1, work, source)
            levels.append(r)
            print(json.dumps(r), file=sys.stderr, flush=True)
            if not r["kept_up"]:
                break
            best = r
            if not all(st["source_held_pace"] for st in r["stages"].values()):
                break  # the source is the limit here: a higher factor would not load the processor more
        multi = None
        if n_stages > 1:
            work = Path(tmp) / "multi"
            work.mkdir()
            multi = run_level(best["factor"] if best else 1.0, minutes, n_stages, work, source)
            print(json.dumps(multi), file=sys.stderr, flush=True)
    per_core = best["stages"]["stage1"]["toa_per_s_per_core"] if best else None
    return {"stage": {"n_blades": N_BLADES, "n_probes": len(PROBES_DEG), "rpm": RPM,
                      "toa_per_s_realtime": round(RPM / 60.0 * TOA_PER_REV)},
            "source": source, "minutes_per_level": minutes, "single_stage": levels,
            "max_kept_up_toa_per_s": best["stages"]["stage1"]["toa_per_s"] if best else None,
            "toa_per_s_per_processor_core": per_core,
            "engine_toa_per_s": ENGINE_TOA_S,
            "engine_processor_cores": round(ENGINE_TOA_S / per_core, 2) if per_core else None,
            "multi_stage": multi}


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--minutes", type=float, default=10.0, help="wall time of each level (10)")
    ap.add_argument("--factors", default="1,2,4,8", help="pacing factors tried in turn (1,2,4,8)")
    ap.add_argument("--stages", type=int, default=2, help="stages on one bus through a router (2; 1: none)")
    ap.add_argument("--source", choices=("sim", "replay"), default="sim",
                    help="what publishes the stage: the simulator node (sim), or a replay of the stage "
                         "simulated beforehand (replay: cheaper to publish, for rates the simulator cannot hold)")
    a = ap.parse_args()
    print(json.dumps(main(a.minutes, [float(x) for x in a.factors.split(",")], a.stages, a.source), indent=2))

"""``bttsim run``: the whole virtual acquisition on an embedded Zenoh peer network.

Starts four node processes on loopback -- recorder, processor, viewer, simulator -- each
listening on its own free port and connecting to the ones started before it (a full mesh,
no router needed; ``-e/--connect`` joins an existing Zenoh network instead). The simulator
waits for the other three nodes' liveliness tokens, publishes the run, and the others end
when it (and the processor's final report) is done. Progress (revolution, rpm, elapsed and
remaining time) comes from the OPR stream. Ctrl-C stops the simulator first; every other
node then finalises its file, so ``run.mcap``, ``views.rrd`` and ``summary.json`` stay valid.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from .errors import BttsimError

__all__ = ["run_all"]

NODES = ("recorder", "processor", "viewer", "sim")


def _session_flags(listen: str | None, connect: list[str], config: str | None) -> list[str]:
    out: list[str] = []
    if listen:
        out += ["-l", listen]
    for e in connect:
        out += ["-e", e]
    if config:
        out += ["-c", config]
    return out


def run_all(scenario_path: str | None, out_dir: str, *, web: bool = False, web_port: int = 9090,
            realtime: bool = False, connect: list[str] | None = None, config: str | None = None,
            quiet: bool = False) -> dict:
    """Run the main job; returns the summary dict (also written to ``OUT/summary.json``)."""
    from .io import codec, keys
    from .scenario import Scenario, dumps_toml, load_scenario
    from .sim.speed import speed_profile_from_scenario
    from .testing import free_port
    from .transport import make_config, open_session

    scn = load_scenario(scenario_path) if scenario_path else Scenario()  # bad input: exit 2 now
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise BttsimError(f"{out}: cannot create the output folder ({exc.strerror or exc})") from None
    scn_file = out / "scenario.toml"
    scn_file.write_text(dumps_toml(scn))
    rig = scn.run.rig
    files = {"mcap": out / "run.mcap", "rrd": out / "views.rrd", "summary": out / "summary.json"}
    for f in files.values():
        f.unlink(missing_ok=True)

    embedded = not connect and not config
    ports = {n: free_port() for n in NODES} if embedded else {}
    endpoints = {n: f"tcp/127.0.0.1:{p}" for n, p in ports.items()}
    args = {
        "recorder": ["bttsim_stream.nodes.recorder_node", "--rig", rig, "--out", files["mcap"],
                     "--until", "sim,processor"],
        "processor": ["bttsim_stream.nodes.processor_node", "--rig", rig, "--summary", files["summary"]],
        "viewer": ["bttsim_stream.nodes.viewer_node", "--rig", rig, "--rrd", files["rrd"]]
        + (["--web", "--web-port", str(web_port)] if web else []),
        "sim": ["bttsim_stream.nodes.sim_node", scn_file, "--wait-for", "3",
                "--rate", "realtime" if realtime else "max"],
    }
    procs: dict[str, subprocess.Popen] = {}
    logs = {n: open(out / f"{n}.log", "w") for n in NODES}
    interrupted = False

    def on_sigint(signum, frame):
        nonlocal interrupted
        interrupted = True
        sim = procs.get("sim")
        if sim is not None and sim.poll() is None:
            sim.send_signal(signal.SIGTERM)

    old = {s: signal.signal(s, on_sigint) for s in (signal.SIGINT, signal.SIGTERM)}
    t0 = time.monotonic()
    summary = None
    try:
        started: list[str] = []
        for n in NODES:
            flags = _session_flags(endpoints.get(n), [endpoints[m] for m in started] if embedded else
                                   list(connect or []), config)
            procs[n] = subprocess.Popen([sys.executable, "-m", *map(str, args[n]), *flags],
                                        stdout=logs[n], stderr=subprocess.STDOUT,
                                        start_new_session=True)  # Ctrl-C reaches only us
            started.append(n)
        conf = make_config(connect=list(endpoints.values()) if embedded else list(connect or []),
                           config_file=config)
        speed = speed_profile_from_scenario(scn)
        n_rev = int(np.floor((speed.angle(speed.duration_s) - np.deg2rad(scn.probes.opr_angle_deg)) / (2 * np.pi)))
        with open_session(conf) as session:
            state = {"rev": 0, "rpm": 0.0, "last": None}

            def on_opr(sample):
                m = codec.decode_opr(sample.payload.to_bytes())
                if state["last"] is not None and m.opr_s > state["last"]:
                    state["rpm"] = 60.0 / (m.opr_s - state["last"])
                state["last"] = m.opr_s
                state["rev"] = m.header.revolution + 1

            def show():
                el = time.monotonic() - t0
                rev = state["rev"]
                rem = f"{el * (n_rev - rev) / rev:5.1f} s" if rev else "  ?  "
                print(f"\rrevolution {rev:5d}/{n_rev}  {state['rpm']:6.0f} rpm  elapsed {el:5.1f} s  "
                      f"remaining {rem}", end="", file=sys.stderr, flush=True)

            sub = session.declare_subscriber(keys.opr_key(rig), on_opr)
            while procs["sim"].poll() is None:
                time.sleep(0.25)
                if not quiet:
                    show()
            time.sleep(0.1)
            if not quiet:
                show()
            sub.undeclare()
        if not quiet:
            print(file=sys.stderr)
        for n in ("processor", "recorder", "viewer"):
            try:
                procs[n].wait(timeout=120)
            except subprocess.TimeoutExpired:
                procs[n].send_signal(signal.SIGTERM)
                procs[n].wait(timeout=30)
        bad = {n: p.returncode for n, p in procs.items() if p.returncode not in (0, None)}
        if bad and not interrupted:
            raise BttsimError(f"node(s) failed: {bad}; see the logs in {out}")
        if files["summary"].exists():
            summary = json.loads(files["summary"].read_text())
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
                try:
                    p.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()
        for f in logs.values():
            f.close()
        for s, h in old.items():
            signal.signal(s, h)
    return {"summary": summary, "files": {k: str(v) for k, v in files.items()},
            "interrupted": interrupted, "wall_s": time.monotonic() - t0}

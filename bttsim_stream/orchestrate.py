"""``bttsim run``: the whole virtual acquisition on an embedded Zenoh peer network.

Starts four node processes on loopback -- recorder, processor, viewer, simulator -- each
listening on its own free port and connecting to the ones started before it (a full mesh,
no router needed; ``-e/--connect`` joins an existing Zenoh network instead). The simulator
waits for the other three nodes' liveliness tokens, publishes the run, and the others end
when it (and the processor's final report) is done. Progress (revolution, rpm, elapsed and
remaining time) comes from the OPR stream. Ctrl-C (or SIGTERM, SIGHUP) stops the simulator
first; every other node then finalises its file, so ``run.mcap``, ``views.rrd`` and
``summary.json`` stay valid; a second signal, or one after the simulator has ended, stops
every node at once.

With ``--web`` the viewer serves the Rerun web viewer on ``--bind`` (127.0.0.1) at
``--web-port`` and ``--grpc-port``, both checked free before anything starts. After the run
the result is reported and the viewer keeps serving until Ctrl-C. The nodes get SIGTERM
when the orchestrator dies, however it dies (:mod:`bttsim_stream.children`): no node
outlives it.

With ``tls_dir`` (``bttsim run --tls-dir DIR``, certificates from ``bttsim certs DIR``) every
node, and the run's own session (identity ``run``), speaks mutual TLS on ``tls/127.0.0.1``
endpoints under the access-control policy of :mod:`bttsim_stream.bus.security`.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

from .bus import codec, keys
from .bus.ports import check_port_free, parse_bind
from .bus.security import TlsFiles
from .bus.session import CONNECT_TIMEOUT_S, free_port, make_config, open_session
from .children import die_with_parent
from .defaults import DEFAULT_BIND, DEFAULT_GRPC_PORT, DEFAULT_WEB_PORT
from .errors import BttsimError
from .runtime import Progress
from .scenario import Scenario, dumps_toml, load_scenario

__all__ = ["run_all", "NODES"]

#: The node programs of a run, in start order (the simulator last: it waits for the others).
NODES = ("recorder", "processor", "viewer", "sim")
#: The viewer node's log line once its views are complete and it only serves the web viewer.
SERVING_LINE = "serving the web viewer until stopped"


def _session_flags(listen: str | None, connect: list[str], config: str | None, mode: str,
                   security: list[str]) -> list[str]:
    out: list[str] = ["-m", mode, *security]
    if listen:
        out += ["-l", listen]
    for e in connect:
        out += ["-e", e]
    if config:
        out += ["-c", config]
    return out


def run_all(scenario_path: str | None, out_dir: str, *, web: bool = False, web_port: int = DEFAULT_WEB_PORT,
            grpc_port: int = DEFAULT_GRPC_PORT, bind: str = DEFAULT_BIND, realtime: bool = False,
            connect: list[str] | None = None, config: str | None = None, quiet: bool = False,
            mode: str = "peer", on_serving=None, tls_dir: str | None = None, access_control: bool = True,
            connect_timeout_s: float = CONNECT_TIMEOUT_S) -> dict:
    """Run the main job; returns the summary dict (also written to ``OUT/summary.json``).

    With ``web``, once the run's result is known and the viewer only serves, ``on_serving``
    (if given) is called with the result (the dict this function returns) and the web viewer
    is served until a signal (Ctrl-C, SIGTERM, SIGHUP) stops it. ``tls_dir``: mutual TLS (and,
    with ``access_control``, the access-control policy) with the certificates of that folder;
    ``connect_timeout_s``: how long every node tries to reach its endpoints before it gives up
    with an error.
    """
    if mode == "client" and not connect:
        raise BttsimError("client mode needs a Zenoh router: -e tcp/HOST:PORT (bttsim router)")
    tls = None
    security: list[str] = ["--connect-timeout", f"{connect_timeout_s:g}"]
    if tls_dir:
        d = Path(tls_dir).resolve()
        tls = TlsFiles(d / "ca.pem", d / "run.pem", d / "run-key.pem", access_control)
        for n in NODES:  # every identity there before anything starts
            TlsFiles(d / "ca.pem", d / f"{n}.pem", d / f"{n}-key.pem")
        security += ["--tls-dir", str(d)] + ([] if access_control else ["--no-access-control"])
    scn = load_scenario(scenario_path) if scenario_path else Scenario()  # bad input: exit 2 now
    if web:  # a busy port is an error now, not after the run (Rerun would only log it)
        bind = parse_bind(bind)
        if int(web_port) == int(grpc_port):
            raise BttsimError(f"--web-port and --grpc-port are both {int(web_port)}: give two ports")
        check_port_free(bind, int(grpc_port), "web viewer's data server (--grpc-port)")
        check_port_free(bind, int(web_port), "web viewer (--web-port)")
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

    embedded = not connect  # a -c file is merged with each node's own loopback endpoint
    ports = {n: free_port() for n in NODES} if embedded else {}
    endpoints = {n: f"{'tls' if tls else 'tcp'}/127.0.0.1:{p}" for n, p in ports.items()}
    args = {
        "recorder": ["recorder", "--rig", rig, "--out", files["mcap"], "--until", "sim,processor"],
        "processor": ["processor", "--rig", rig, "--summary", files["summary"]],
        "viewer": ["viewer", "--rig", rig, "--rrd", files["rrd"], "--until", "sim,processor"]
        + (["--web", "--web-port", str(web_port), "--grpc-port", str(grpc_port), "--bind", bind] if web else []),
        "sim": ["sim", scn_file, "--wait-for", "3", "--rate", "realtime" if realtime else "max"],
    }
    # our own session's configuration first: bad endpoints, files or certificates end the run
    # before any node starts
    conf = make_config(mode, connect=list(endpoints.values()) if embedded else list(connect or []),
                       config_file=config, tls=tls,
                       # our own nodes may be done before we reach the last of them (a short
                       # run): follow them from the background; a router must answer
                       connect_timeout_s=None if embedded else connect_timeout_s)
    procs: dict[str, subprocess.Popen] = {}
    logs = {n: open(out / f"{n}.log", "w") for n in NODES}
    interrupted = finished = False
    n_signals = 0

    def on_signal(signum, frame):
        nonlocal interrupted, n_signals
        n_signals += 1
        interrupted = interrupted or not finished
        sim = procs.get("sim")
        if n_signals == 1 and sim is not None and sim.poll() is None:
            sim.send_signal(signal.SIGTERM)  # the others end after it, finalising their files
            return
        for p in procs.values():  # the run is over (or a second signal): stop every node now
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    t0 = time.monotonic()
    progress = Progress(not quiet, period_s=5.0)
    summary = None
    recorder: dict = {}
    viewer: dict = {}
    result_complete = False
    failed: dict = {}
    n_rev = 0
    try:
        started: list[str] = []
        for n in NODES:
            flags = _session_flags(endpoints.get(n), [endpoints[m] for m in started] if embedded else
                                   list(connect or []), config, mode, security)
            procs[n] = subprocess.Popen([sys.executable, "-m", "bttsim_stream.nodes", *map(str, args[n]), *flags],
                                        stdout=logs[n], stderr=subprocess.STDOUT,
                                        start_new_session=True,  # Ctrl-C reaches only us
                                        preexec_fn=die_with_parent())  # and they end when we do
            started.append(n)
        with open_session(conf) as session:
            n_rev = _revolutions(procs, session, rig)
            if web:  # printed by the viewer before it joined: the simulator waited for it
                url = _log_line(out / "viewer.log", "web viewer: ")
                if url:
                    progress.note(url)
            state = {"rev": 0, "rpm": 0.0, "last": None}

            def on_opr(sample):
                m = codec.decode_opr(sample.payload.to_bytes())
                if state["last"] is not None and m.body.opr_s > state["last"]:
                    state["rpm"] = 60.0 / (m.body.opr_s - state["last"])
                state["last"] = m.body.opr_s
                state["rev"] = m.header.revolution + 1

            def line() -> str:
                el = time.monotonic() - t0
                rev = state["rev"]
                rem = f"{el * (n_rev - rev) / rev:5.1f} s" if rev and n_rev else "  ?  "
                return (f"revolution {rev:5d}/{n_rev}  {state['rpm']:6.0f} rpm  elapsed {el:5.1f} s  "
                        f"remaining {rem}")

            sub = session.declare_subscriber(keys.opr_key(rig), on_opr)
            while procs["sim"].poll() is None:
                time.sleep(0.25)
                progress.update(line())
            time.sleep(0.1)
            progress.update(line(), force=True)
            sub.undeclare()
        progress.close()
        # a simulator that failed (it may never have published) leaves the others nothing to
        # wait for: they get a short grace to notice, then SIGTERM (they finalise their files)
        grace = 120 if procs["sim"].returncode == 0 else 15
        for n in ("processor", "recorder"):
            _wait_or_stop(procs[n], grace)
        serving = web and _wait_serving(procs["viewer"], out / "viewer.log", 120)
        if serving and interrupted:  # its .rrd is complete: no serving after Ctrl-C
            procs["viewer"].send_signal(signal.SIGTERM)
            serving = False
        if not serving:
            _wait_or_stop(procs["viewer"], grace)
        failed = {n: p.returncode for n, p in procs.items() if p.returncode not in (0, None)}
        if files["summary"].exists():
            summary = json.loads(files["summary"].read_text())
        elif "processor" in failed:  # no report: say so in the file a reader looks at
            summary = _no_report_summary(n_rev, failed["processor"])
            files["summary"].write_text(json.dumps(summary, indent=2) + "\n")
        recorder = _last_json_line(out / "recorder.log")
        viewer = _last_json_line(out / "viewer.log")  # its own counts: what the views lost
        if summary is not None:  # the result is complete only with a complete recording of it
            result_complete = bool(summary.get("complete", False))
            summary["recording"] = _recording(recorder)
            summary["complete"] = result_complete and summary["recording"]["complete"]
            files["summary"].write_text(json.dumps(summary, indent=2) + "\n")
        finished = True
        if serving:
            if on_serving is not None:
                on_serving(_result(summary, files, recorder, viewer, interrupted, failed, t0, result_complete))
            procs["viewer"].wait()  # until a signal: the handler stops it
    finally:
        progress.close()
        for p in procs.values():
            if p.poll() is None:
                _wait_or_stop(p, 0)
        for f in logs.values():
            f.close()
        for s, h in old.items():
            signal.signal(s, h)
    return _result(summary, files, recorder, viewer, interrupted, failed, t0, result_complete)


def _result(summary, files: dict, recorder: dict, viewer: dict, interrupted: bool, failed: dict, t0: float,
            result_complete: bool) -> dict:
    """The run's outcome; ``result_complete``: the processor's own verdict (``summary["complete"]``
    also needs a complete recording)."""
    return {"summary": summary, "files": {k: str(v) for k, v in files.items()}, "recorder": recorder, "viewer": viewer,
            "interrupted": interrupted, "failed": failed, "wall_s": time.monotonic() - t0,
            "result_complete": result_complete, "recording": _recording(recorder)}


def _recording(stats: dict) -> dict:
    """The summary's ``recording`` block from the recorder's statistics (its JSON line):
    ``complete``, ``missing`` (messages), ``missing_by_key`` (``{key: {"head", "gaps", "tail"}}``),
    ``messages``, ``duplicates``, ``rejected`` and ``incomplete`` (why, "" if complete)."""
    if "complete" not in stats:
        return {"complete": False, "missing": None, "missing_by_key": {}, "messages": stats.get("messages"),
                "duplicates": None, "rejected": None,
                "incomplete": "the recorder gave no completeness statistics (see recorder.log)"}
    return {"complete": bool(stats["complete"]), "missing": stats.get("missing"),
            "missing_by_key": stats.get("missing_by_key", {}), "messages": stats.get("messages"),
            "duplicates": stats.get("duplicates_skipped"), "rejected": stats.get("rejected"),
            "incomplete": stats.get("incomplete", "")}


def describe_exit(returncode: int) -> str:
    """``"exit 1"`` or ``"killed by SIGKILL"``."""
    if returncode < 0:
        try:
            return f"killed by {signal.Signals(-returncode).name}"
        except ValueError:
            return f"killed by signal {-returncode}"
    return f"exit {returncode}"


def _no_report_summary(n_revolutions: int, returncode: int) -> dict:
    """The summary of a run whose processor ended without its report: nothing claimed."""
    return {"status": "none", "complete": False, "revolutions_expected": int(n_revolutions),
            "revolutions_processed": 0, "lost": None, "duplicates": None, "rejected": None,
            "resonances": [], "steady": [], "blades": [],
            "error": f"the processor ended ({describe_exit(returncode)}) before its report; "
                     "the recording may still hold the run: bttsim process run.mcap"}


def _wait_or_stop(proc: subprocess.Popen, timeout_s: float) -> None:
    """Wait for ``proc`` to end; SIGTERM it after ``timeout_s`` (SIGKILL 30 s later)."""
    try:
        proc.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _wait_serving(viewer: subprocess.Popen, log_path: Path, timeout_s: float) -> bool:
    """Wait until the viewer has finished its views and only serves (True: its log says so)
    or has ended (False); False after ``timeout_s`` too."""
    deadline = time.monotonic() + timeout_s
    while viewer.poll() is None and time.monotonic() < deadline:
        if _log_line(log_path, SERVING_LINE):
            return True
        time.sleep(0.1)
    return False


def _log_line(path: Path, text: str) -> str | None:
    """The first line of the log ``path`` that contains ``text`` (None if none yet)."""
    try:
        content = path.read_text(errors="replace")
    except OSError:
        return None
    return next((line.strip() for line in content.splitlines() if text in line), None)


def _last_json_line(path: Path) -> dict:
    """The recorder's statistics: the last JSON line of its log ({} if none)."""
    for line in reversed(path.read_text(errors="replace").splitlines()):
        if line.startswith("{"):
            try:
                return json.loads(line)
            except ValueError:
                break
    return {}


def _revolutions(procs: dict, session, rig: str) -> int:
    """The run's revolution count, from the simulator's metadata queryable (0 if it does not
    answer before the simulator ends)."""
    while procs["sim"].poll() is None:
        for reply in session.get(keys.meta_key(rig), timeout=1.0):
            if reply.ok is not None:
                return codec.decode_run_metadata(reply.ok.payload.to_bytes()).body.n_revolutions
        time.sleep(0.05)
    return 0

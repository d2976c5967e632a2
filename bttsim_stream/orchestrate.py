"""``bttsim run``: the whole virtual acquisition on an embedded Zenoh peer network.

Starts four node processes on loopback -- recorder, processor, viewer, simulator -- each
listening on its own free port and connecting to the ones started before it (a full mesh,
no router needed; ``-e/--connect`` joins an existing Zenoh network instead). The simulator
waits for the other three nodes' liveliness tokens, publishes the run, and the others end
when it (and the processor's final report) is done. Progress (revolution of the run's count,
rpm, elapsed time, and the remaining time once the rate seen is a second old) comes from the
bus; after the last revolution each phase is named (the report, the recording, the views).
Ctrl-C (or SIGTERM, SIGHUP) prints "stopping ..." at once and stops the simulator and the
processor (which reports on what it has); the recorder and the viewer then finalise their
files, so ``run.mcap``, ``views.rrd`` and ``summary.json`` stay valid. A node still running
``STOP_GRACE_S`` later gets SIGTERM, then SIGKILL; a second signal, or one after the
simulator has ended, stops every node at once. Nodes are signalled by process group.

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

import contextlib
import json
import os
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

from .bus import codec, keys
from .bus.ports import check_web_ports
from .bus.security import TlsFiles
from .bus.session import CONNECT_TIMEOUT_S, declare_subscriber, free_port, make_config, open_session
from .children import die_with_parent
from .defaults import DEFAULT_BIND, DEFAULT_GRPC_PORT, DEFAULT_WEB_PORT
from .errors import BttsimError
from .runtime import Progress
from .scenario import Scenario, dumps_toml, load_scenario

__all__ = ["run_all", "NODES"]

#: The node programs of a run, in start order (the simulator last: it waits for the others).
NODES = ("recorder", "processor", "viewer", "sim")
#: After Ctrl-C (or SIGTERM, SIGHUP): seconds the nodes have to end on their own (the
#: simulator and the processor get SIGTERM at once, the recorder and the viewer end after
#: them), then every node left gets SIGTERM, and SIGKILL ``STOP_KILL_S`` later; the recorder,
#: writing what it holds to the file, gets ``RECORDER_KILL_S``.
STOP_GRACE_S = 3.0
STOP_KILL_S = 1.5
RECORDER_KILL_S = 10.0
#: The progress line shows no remaining time before this long and this many revolutions
#: since the first OPR seen (the start-up is no rate).
ESTIMATE_AFTER_S = 1.0
ESTIMATE_AFTER_REVS = 5
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
        bind = check_web_ports(bind, web_port, grpc_port)
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
    # the run's own session listens too, and every node connects to it as it starts: it has
    # the run metadata and every OPR from the first (the progress line), however slow a start
    ports = {n: free_port() for n in (*NODES, "run")} if embedded else {}
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
    conf = make_config(mode, connect=[] if embedded else list(connect or []),
                       listen=[endpoints["run"]] if embedded else [], config_file=config, tls=tls,
                       connect_timeout_s=None if embedded else connect_timeout_s)  # a router must answer
    procs: dict[str, subprocess.Popen] = {}
    logs = {n: open(out / f"{n}.log", "w") for n in NODES}
    interrupted = finished = False
    stop_at: float | None = None  # when the first signal came (monotonic)
    n_signals = 0
    t0 = time.monotonic()
    progress = Progress(not quiet, period_s=5.0)

    def on_signal(signum, frame):
        nonlocal interrupted, n_signals, stop_at
        n_signals += 1
        interrupted = interrupted or not finished
        if stop_at is None:
            stop_at = time.monotonic()
            progress.signal_note("stopping ...")
        sim = procs.get("sim")
        if n_signals == 1 and sim is not None and sim.poll() is None:
            # the simulator, and the processor: it reports on what it has without waiting
            # for the rest; the recorder and the viewer take that report, then finalise
            _signal(sim, signal.SIGTERM)
            _signal(procs.get("processor"), signal.SIGTERM)
            return
        for p in procs.values():  # the run is over (or a second signal): stop every node now
            _signal(p, signal.SIGTERM)

    def wait(name: str, timeout_s: float) -> None:
        """Wait for a node; SIGTERM it after ``timeout_s``. After a signal, every node still
        running gets SIGTERM ``STOP_GRACE_S`` after it, and SIGKILL ``STOP_KILL_S`` later
        (the recorder, writing what it has, ``RECORDER_KILL_S``)."""
        p = procs.get(name)
        if p is None:
            return
        end = time.monotonic() + timeout_s
        while p.poll() is None:
            limit = end if stop_at is None else min(end, stop_at + STOP_GRACE_S)
            left = limit - time.monotonic()
            if left <= 0:
                break
            with contextlib.suppress(subprocess.TimeoutExpired):
                p.wait(timeout=min(left, 0.1))
        if p.poll() is not None:
            return
        if stop_at is None:
            _wait_or_stop(p, 0)
            return
        for q in procs.values():
            _signal(q, signal.SIGTERM)
        kill_s = RECORDER_KILL_S if name == "recorder" else STOP_KILL_S
        try:
            p.wait(timeout=max(0.0, stop_at + STOP_GRACE_S + kill_s - time.monotonic()))
        except subprocess.TimeoutExpired:
            _signal(p, signal.SIGKILL)
            p.wait()

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    summary = None
    recorder: dict = {}
    viewer: dict = {}
    result_complete = False
    failed: dict = {}
    n_rev = 0
    try:
        started: list[str] = []
        progress.phase(f"starting the {len(NODES)} nodes ...")
        with open_session(conf) as session:
            follow = _Follower(session, rig)
            for n in NODES:
                if stop_at is not None:
                    break
                flags = _session_flags(endpoints.get(n), [endpoints[m] for m in ("run", *started)] if embedded
                                       else list(connect or []), config, mode, security)
                procs[n] = subprocess.Popen([sys.executable, "-m", "bttsim_stream.nodes", *map(str, args[n]),
                                             *flags], stdout=logs[n], stderr=subprocess.STDOUT,
                                            start_new_session=True,  # Ctrl-C reaches only us
                                            preexec_fn=die_with_parent())  # and they end when we do
                started.append(n)
            url, shown = None, -1
            while "sim" in procs and procs["sim"].poll() is None:
                if stop_at is not None and time.monotonic() > stop_at + STOP_GRACE_S:
                    break  # a simulator slow to stop: wait() below stops it
                time.sleep(0.25)
                follow.ask()
                if web and url is None:  # printed by the viewer before it joined
                    url = _log_line(out / "viewer.log", "web viewer: ")
                    if url:
                        progress.note(url)
                if follow.started and progress.update(follow.line(time.monotonic() - t0)):
                    shown = follow.rev
            time.sleep(0.1)
            if follow.started and follow.rev != shown:  # the last state, once
                progress.update(follow.line(time.monotonic() - t0, final=True), force=True)
            n_rev = follow.n_rev
            follow.close()
        wait("sim", 0 if stop_at is None else STOP_GRACE_S)
        # a simulator that failed (it may never have published) leaves the others nothing to
        # wait for: they get a short grace to notice, then SIGTERM (they finalise their files)
        grace = 120 if procs.get("sim") is not None and procs["sim"].returncode == 0 else 15
        progress.phase("making the report ...")
        wait("processor", grace)
        progress.phase("finishing the recording ...")
        wait("recorder", grace)
        progress.phase("finishing the views ...")
        serving = web and "viewer" in procs and _wait_serving(procs["viewer"], out / "viewer.log", 120,
                                                              lambda: stop_at is not None)
        if serving and interrupted:  # its .rrd is complete: no serving after Ctrl-C
            _signal(procs["viewer"], signal.SIGTERM)
            serving = False
        if not serving:
            wait("viewer", grace)
        failed = {n: p.returncode for n, p in procs.items() if p.returncode not in (0, None)}
        if files["summary"].exists():
            summary = json.loads(files["summary"].read_text())
        elif "processor" in failed:  # no report: say so in the file a reader looks at
            summary = _no_report_summary(n_rev, failed["processor"], files["mcap"])
            files["summary"].write_text(json.dumps(summary, indent=2) + "\n")
        recorder = _last_json_line(out / "recorder.log")
        viewer = _last_json_line(out / "viewer.log")  # its own counts: what the views lost
        if summary is not None:  # the result is complete only with a complete recording of it
            result_complete = bool(summary.get("complete", False))
            summary["recording"] = _recording(recorder)
            summary["complete"] = result_complete and summary["recording"]["complete"]
            files["summary"].write_text(json.dumps(summary, indent=2) + "\n")
        finished = True
        progress.close()
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


def _no_report_summary(n_revolutions: int, returncode: int, mcap: Path | str) -> dict:
    """The summary of a run whose processor ended without its report: nothing claimed; the
    error names the command that processes the recording ``mcap`` (the path as given)."""
    return {"status": "none", "complete": False, "revolutions_expected": int(n_revolutions),
            "revolutions_processed": 0, "lost": None, "duplicates": None, "rejected": None,
            "resonances": [], "steady": [], "blades": [],
            "error": f"the processor ended ({describe_exit(returncode)}) before its report; "
                     f"the recording may still hold the run: bttsim process {shlex.quote(str(mcap))}"}


def _signal(proc: subprocess.Popen | None, sig: int) -> None:
    """Send ``sig`` to a running node's process group (each node leads its own)."""
    if proc is None or proc.poll() is not None:
        return
    try:
        os.killpg(proc.pid, sig)
    except ProcessLookupError:
        pass
    except PermissionError:  # not a group leader after all: the node itself
        proc.send_signal(sig)


def _wait_or_stop(proc: subprocess.Popen, timeout_s: float) -> None:
    """Wait for ``proc`` to end; SIGTERM it after ``timeout_s`` (SIGKILL 30 s later)."""
    try:
        proc.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        _signal(proc, signal.SIGTERM)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            _signal(proc, signal.SIGKILL)
            proc.wait()


def _wait_serving(viewer: subprocess.Popen, log_path: Path, timeout_s: float, stopped=lambda: False) -> bool:
    """Wait until the viewer has finished its views and only serves (True: its log says so)
    or has ended, or ``stopped()`` (False); False after ``timeout_s`` too."""
    deadline = time.monotonic() + timeout_s
    while viewer.poll() is None and time.monotonic() < deadline and not stopped():
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


class _Follower:
    """The run as the bus shows it, for the progress line: the revolution count (the run
    metadata, as a sample or from the simulator's queryable), the last revolution and speed
    (the OPR stream), and the rate since the first OPR seen. Every sample is untrusted: a
    bad one is ignored."""

    def __init__(self, session, rig: str) -> None:
        self.n_rev = 0
        self.rev = 0
        self.rpm = 0.0
        self.started = False  # an OPR has been seen
        self._session, self._rig = session, rig
        self._last_opr_s: float | None = None
        self._first: tuple[float, int] | None = None  # (monotonic time, revolution) of the first OPR seen
        self._asked = -float("inf")
        self._subs = [declare_subscriber(session, keys.opr_key(rig), self._on_opr, history=False),
                      declare_subscriber(session, keys.meta_key(rig), self._on_meta, history=True)]

    def _on_meta(self, sample) -> None:
        with contextlib.suppress(BttsimError, ValueError):
            self.n_rev = int(codec.decode_run_metadata(sample.payload.to_bytes()).body.n_revolutions)

    def _on_reply(self, reply) -> None:
        if reply.ok is not None:
            self._on_meta(reply.ok)

    def _on_opr(self, sample) -> None:
        try:
            m = codec.decode_opr(sample.payload.to_bytes())
        except (BttsimError, ValueError):
            return
        if self._last_opr_s is not None and m.body.opr_s > self._last_opr_s:
            self.rpm = 60.0 / (m.body.opr_s - self._last_opr_s)
        self._last_opr_s = m.body.opr_s
        self.rev = int(m.header.revolution) + 1
        if self._first is None:
            self._first = (time.monotonic(), self.rev)
        self.started = True

    def ask(self) -> None:
        """Ask the simulator's queryable for the count (in the background, once a second)
        while it is not known."""
        if not self.n_rev and time.monotonic() - self._asked > 1.0:
            self._asked = time.monotonic()
            with contextlib.suppress(Exception):  # a session closing under us: the count stays unknown
                self._session.get(keys.meta_key(self._rig), self._on_reply, timeout=1.0)

    def remaining_s(self) -> float | None:
        """Time left at the rate seen so far; None until that rate means something
        (``ESTIMATE_AFTER_S`` and ``ESTIMATE_AFTER_REVS`` since the first OPR seen)."""
        if not self.n_rev or self._first is None or self.rev >= self.n_rev:
            return None
        dt, drev = time.monotonic() - self._first[0], self.rev - self._first[1]
        if dt < ESTIMATE_AFTER_S or drev < ESTIMATE_AFTER_REVS:
            return None
        return max(0.0, dt * (self.n_rev - self.rev) / drev)

    def line(self, elapsed_s: float, final: bool = False) -> str:
        text = f"revolution {self.rev:5d}" + (f"/{self.n_rev}" if self.n_rev else "")
        text += f"  {self.rpm:6.0f} rpm  elapsed {elapsed_s:5.1f} s"
        rem = None if final else self.remaining_s()
        return text + (f"  remaining {rem:5.1f} s" if rem is not None else "")

    def close(self) -> None:
        for sub in self._subs:
            with contextlib.suppress(Exception):
                sub.undeclare()

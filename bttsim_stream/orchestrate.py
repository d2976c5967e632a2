"""``bttsim run``: the whole virtual acquisition on an embedded Zenoh peer network.

Starts four node processes on loopback -- recorder, processor, viewer, simulator -- each
listening on its own free port and connecting to the ones started before it (a full mesh,
no router needed; ``-e/--connect`` joins an existing Zenoh network instead). The simulator
waits for the other three nodes' liveliness tokens, publishes the run, and the others end
when it (and the processor's final report) is done. Progress (revolution of the run's count,
rpm, elapsed time, and the remaining time once the rate seen is a second old) comes from the
bus; after the last revolution each phase is named (the report, the recording, the views).

The run is a :class:`Run` object in steps -- ``start`` (the nodes), ``watch`` (the bus until
the simulator ends), ``collect`` (each node's end, then the result), ``serve`` (``--web``) --
planned first by :func:`plan_run`, which checks every input before anything starts. The
nodes say how far they are on their status keys, ``bttsim/<rig>/status/<node>``
(:mod:`bttsim_stream.bus.status`; their status files where the bus did not deliver): the web
viewer's address, that the viewer only serves, and the recorder's and the viewer's final
statistics. Their logs, ``OUT/<node>.log``, are for people: the run reads none of them.

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
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .bus import codec, keys
from .bus.ports import check_web_ports
from .bus.security import TlsFiles
from .bus.session import CONNECT_TIMEOUT_S, GONE_SIGNAL, declare_subscriber, free_port, make_config, opened
from .bus.status import StatusBoard
from .children import die_with_parent
from .diskspace import check_free_space, estimate_output_bytes
from .defaults import DEFAULT_BIND, DEFAULT_GRPC_PORT, DEFAULT_WEB_PORT
from .errors import BttsimError
from .runtime import DRAIN_TIMEOUT_S, Progress
from .scenario import Scenario, dumps_toml, load_scenario
from .summary import describe_exit, no_report_summary, recording_block, with_recording

__all__ = ["run_all", "plan_run", "Run", "RunPlan", "NODES", "describe_exit"]

#: The node programs of a run, in start order (the simulator last: it waits for the others).
NODES = ("recorder", "processor", "viewer", "sim")
#: The nodes each consumer of a run follows (the processor: the simulator, its own; the
#: recorder and the viewer: ``--until``): once all of a consumer's are reaped, it is told
#: they are gone for good (:data:`~bttsim_stream.bus.session.GONE_SIGNAL`).
FOLLOWS = {"processor": ("sim",), "recorder": ("sim", "processor"), "viewer": ("sim", "processor")}
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
#: A consumer node's exit status (recorder, processor, viewer) when what it received or wrote
#: is incomplete (its final statistics say what is missing): not a failure of the node.
NODE_INCOMPLETE = 3
#: How long, after a node ended normally, its final status may still be on its way on the bus
#: before its status file is read instead (s).
FINAL_STATUS_WAIT_S = 2.0
#: After the simulator failed (it may never have published), seconds the consumers have, all
#: together, to notice and end on their own before they get SIGTERM; then as long again each
#: to finalise their files.
FAILED_SIM_GRACE_S = 15.0
#: After the processor failed in a run whose simulator ended well (the simulator waited for the
#: recorder's and viewer's whole acquisition), seconds the recorder and viewer have, together,
#: for what the processor sent before it died (at most in flight): its report never comes.
FAILED_PROCESSOR_GRACE_S = 2.0

_no_report_summary = no_report_summary  # the name this module gave it before summary.py


@dataclass(frozen=True)
class RunPlan:
    """What a run starts, decided (and checked) before anything starts.

    Attributes
    ----------
    out : Path
        The output folder.
    files : dict of {str: Path}
        ``mcap``, ``rrd``, ``summary``: the run's outputs.
    rig : str
    commands : dict of {str: list of str}
        Each node's arguments to ``python -m bttsim_stream.nodes``, in start order.
    status_dir : Path
        A temporary folder for the status files (removed by :meth:`Run.close`).
    status_files : dict of {str: Path}
        Where each node also writes its status (``--status-file``).
    conf : zenoh.Config
        The run's own session (identity ``run``; with the embedded network it listens, and
        every node connects to it).
    web : bool
        The viewer serves the web viewer.
    """

    out: Path
    files: dict
    rig: str
    commands: dict
    status_dir: Path
    status_files: dict
    conf: object
    web: bool


def plan_run(scenario_path: str | None, out_dir: str, *, web: bool = False, web_port: int = DEFAULT_WEB_PORT,
             grpc_port: int = DEFAULT_GRPC_PORT, bind: str = DEFAULT_BIND, realtime: bool = False,
             connect: list[str] | None = None, config: str | None = None, mode: str = "peer",
             tls_dir: str | None = None, access_control: bool = True,
             connect_timeout_s: float = CONNECT_TIMEOUT_S, force: bool = False,
             drain_timeout_s: float = DRAIN_TIMEOUT_S) -> RunPlan:
    """Check the inputs and prepare the output folder (``scenario.toml`` written, old outputs
    removed); bad input is a :class:`BttsimError` before any node starts."""
    if mode == "client" and not connect:
        raise BttsimError("client mode needs a Zenoh router: -e tcp/HOST:PORT (bttsim router)")
    tls, security = _security(tls_dir, access_control, connect_timeout_s)
    scn = load_scenario(scenario_path) if scenario_path else Scenario()  # bad input: exit 2 now
    if not force:  # an output that cannot fit, or an absurd force (the simulator refuses it), is refused now
        with np.errstate(over="ignore", invalid="ignore"):
            need = estimate_output_bytes(scn, run=True)
        check_free_space(out_dir, need, what="bttsim run")
    if web:  # a busy port is an error now, not after the run (Rerun would only log it)
        bind = check_web_ports(bind, web_port, grpc_port)
    out, files = _prepare_folder(Path(out_dir), scn)
    embedded = not connect  # a -c file is merged with each node's own loopback endpoint
    # the run's own session listens too, and every node connects to it as it starts: it has
    # the run metadata and every OPR from the first (the progress line), however slow a start
    ports = {n: free_port() for n in (*NODES, "run")} if embedded else {}
    endpoints = {n: f"{'tls' if tls else 'tcp'}/127.0.0.1:{p}" for n, p in ports.items()}
    # our own session's configuration first: bad endpoints, files or certificates end the run
    # before any node starts
    conf = make_config(mode, connect=[] if embedded else list(connect or []),
                       listen=[endpoints["run"]] if embedded else [], config_file=config, tls=tls,
                       connect_timeout_s=None if embedded else connect_timeout_s)  # a router must answer
    node_args = _node_args(scn.run.rig, files, out / "scenario.toml", realtime,
                           ["--web", "--web-port", str(web_port), "--grpc-port", str(grpc_port), "--bind", bind]
                           if web else [], drain_timeout_s)
    status_dir = Path(tempfile.mkdtemp(prefix="bttsim-run-status-"))
    status_files = {n: status_dir / f"{n}.json" for n in NODES}
    commands = {}
    for i, n in enumerate(NODES):  # each node connects to the run and to the nodes before it
        connects = [endpoints[m] for m in ("run", *NODES[:i])] if embedded else list(connect or [])
        commands[n] = [*map(str, node_args[n]), "--status-file", str(status_files[n]),
                       *_session_flags(endpoints.get(n), connects, config, mode, security)]
    return RunPlan(out=out, files=files, rig=scn.run.rig, commands=commands, status_dir=status_dir,
                   status_files=status_files, conf=conf, web=web)


def _security(tls_dir: str | None, access_control: bool, connect_timeout_s: float) -> tuple:
    """The run's own :class:`TlsFiles` (None: security off) and the nodes' security flags."""
    flags: list[str] = ["--connect-timeout", f"{connect_timeout_s:g}"]
    if not tls_dir:
        return None, flags
    d = Path(tls_dir).resolve()
    tls = TlsFiles(d / "ca.pem", d / "run.pem", d / "run-key.pem", access_control)
    for n in NODES:  # every identity there before anything starts
        TlsFiles(d / "ca.pem", d / f"{n}.pem", d / f"{n}-key.pem")
    return tls, flags + ["--tls-dir", str(d)] + ([] if access_control else ["--no-access-control"])


def _prepare_folder(out: Path, scn: Scenario) -> tuple[Path, dict]:
    """Create the output folder, write the scenario there and remove a previous run's outputs."""
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise BttsimError(f"{out}: cannot create the output folder ({exc.strerror or exc})") from None
    (out / "scenario.toml").write_text(dumps_toml(scn))
    files = {"mcap": out / "run.mcap", "rrd": out / "views.rrd", "summary": out / "summary.json"}
    for f in files.values():
        f.unlink(missing_ok=True)
    return out, files


def _node_args(rig: str, files: dict, scn_file: Path, realtime: bool, web_flags: list[str],
               drain_timeout_s: float = DRAIN_TIMEOUT_S) -> dict:
    """Each node's own arguments (session and status flags aside)."""
    drain = ["--drain-timeout", f"{drain_timeout_s:g}"]
    return {
        "recorder": ["recorder", "--rig", rig, "--out", files["mcap"], "--until", ",".join(FOLLOWS["recorder"]),
                     *drain],
        "processor": ["processor", "--rig", rig, "--summary", files["summary"], *drain],
        "viewer": ["viewer", "--rig", rig, "--rrd", files["rrd"], "--until", ",".join(FOLLOWS["viewer"]), *drain,
                   *web_flags],
        "sim": ["sim", scn_file, "--wait-for", "3", "--rate", "realtime" if realtime else "max"],
    }


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
            connect_timeout_s: float = CONNECT_TIMEOUT_S, force: bool = False,
            drain_timeout_s: float = DRAIN_TIMEOUT_S) -> dict:
    """Run the main job; returns the result (:meth:`Run.result`; its summary is also written to
    ``OUT/summary.json``).

    With ``web``, once the run's result is known and the viewer only serves, ``on_serving``
    (if given) is called with the result (the dict this function returns) and the web viewer
    is served until a signal (Ctrl-C, SIGTERM, SIGHUP) stops it. ``tls_dir``: mutual TLS (and,
    with ``access_control``, the access-control policy) with the certificates of that folder;
    ``connect_timeout_s``: how long every node tries to reach its endpoints before it gives up
    with an error; ``drain_timeout_s``: how long a consumer waits in silence for the rest of a
    run whose publishers are gone before all of it came (``--drain-timeout``).
    """
    plan = plan_run(scenario_path, out_dir, web=web, web_port=web_port, grpc_port=grpc_port, bind=bind,
                    realtime=realtime, connect=connect, config=config, mode=mode, tls_dir=tls_dir,
                    access_control=access_control, connect_timeout_s=connect_timeout_s, force=force,
                    drain_timeout_s=drain_timeout_s)
    run = Run(plan, Progress(not quiet, period_s=5.0))
    with run.handling_signals():
        try:
            with opened(plan.conf) as session:
                run.start(session)
                run.watch(session)
                run.collect()
                run.serve(on_serving)
        finally:
            run.close()
    return run.result()


class Run:
    """One ``bttsim run``: :meth:`start` the nodes, :meth:`watch` the run on the bus,
    :meth:`collect` the result, and with ``--web`` :meth:`serve`; :meth:`close` in any case.

    The nodes say how far they are on the bus (:class:`~bttsim_stream.bus.status.StatusBoard`:
    ``bttsim/<rig>/status/<node>``, or their status files where the bus did not deliver): the
    web viewer's address, that the viewer only serves, and the recorder's and the viewer's
    final statistics. Their logs (``OUT/<node>.log``) are for people; the run reads none.

    Signals (installed by :meth:`handling_signals`): the first stops the simulator and the
    processor, which reports on what it has; the recorder and the viewer take that report,
    then finalise their files. A second signal, or one after the simulator ended, stops every
    node at once. Nodes are signalled by process group.
    """

    def __init__(self, plan: RunPlan, progress: Progress) -> None:
        self.plan = plan
        self.progress = progress
        self.procs: dict[str, subprocess.Popen] = {}
        self.board: StatusBoard | None = None
        self.t0 = time.monotonic()
        self.interrupted = self.finished = self.serving = False
        self.stop_at: float | None = None  # when the first signal came (monotonic)
        self.n_signals = 0
        self.n_rev = 0
        self.summary: dict | None = None
        self.recorder: dict = {}
        self.viewer: dict = {}
        self.failed: dict = {}
        self._told: set = set()  # the consumers told their followed nodes are gone for good
        self.result_complete = False  # the processor's own verdict, before the recording's
        self.write_error = ""  # the summary could not be written (a full disk)
        self._logs: dict = {}
        self._url_shown = not plan.web

    # -- signals -------------------------------------------------------------------------
    @contextlib.contextmanager
    def handling_signals(self):
        """Ctrl-C, SIGTERM and SIGHUP go to :meth:`_on_signal` while in this block."""
        old = {s: signal.signal(s, self._on_signal) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
        try:
            yield self
        finally:
            for s, h in old.items():
                signal.signal(s, h)

    def _on_signal(self, signum, frame) -> None:
        self.n_signals += 1
        self.interrupted = self.interrupted or not self.finished
        if self.stop_at is None:
            self.stop_at = time.monotonic()
            self.progress.signal_note("stopping ...")
        sim = self.procs.get("sim")
        if self.n_signals == 1 and sim is not None and sim.poll() is None:
            # the simulator, and the processor: it reports on what it has without waiting
            # for the rest; the recorder and the viewer take that report, then finalise
            _signal(sim, signal.SIGTERM)
            _signal(self.procs.get("processor"), signal.SIGTERM)
            return
        for p in self.procs.values():  # the run is over (or a second signal): stop every node now
            _signal(p, signal.SIGTERM)

    # -- the steps -----------------------------------------------------------------------
    def start(self, session) -> None:
        """Follow the nodes' status on ``session``, then start the nodes in order, each
        logging to ``OUT/<node>.log`` (none after a signal)."""
        self.progress.phase(f"starting the {len(NODES)} nodes ...")
        self.board = StatusBoard(session, self.plan.rig, NODES, files=self.plan.status_files)
        self._logs = {n: open(self.plan.out / f"{n}.log", "w") for n in NODES}
        for n in NODES:
            if self.stop_at is not None:
                break
            self.procs[n] = subprocess.Popen([sys.executable, "-m", "bttsim_stream.nodes", *self.plan.commands[n]],
                                             stdout=self._logs[n], stderr=subprocess.STDOUT,
                                             start_new_session=True,  # Ctrl-C reaches only us
                                             # they end when we do; the gone signal before they
                                             # handle it is ignored, not their end
                                             preexec_fn=die_with_parent(ignore=(GONE_SIGNAL,)))

    def watch(self, session) -> None:
        """Until the simulator ends: the progress line from the bus (the run's revolution count,
        the OPR stream) and the web viewer's address once the viewer's status gives it."""
        follow = _Follower(session, self.plan.rig)
        shown = -1
        try:
            while "sim" in self.procs and self.procs["sim"].poll() is None:
                if self.stop_at is not None and time.monotonic() > self.stop_at + STOP_GRACE_S:
                    break  # a simulator slow to stop: collect() stops it
                time.sleep(0.25)
                follow.ask()
                self._show_url()
                if follow.started and self.progress.update(follow.line(time.monotonic() - self.t0)):
                    shown = follow.rev
            time.sleep(0.1)
            if follow.started and follow.rev != shown:  # the last state, once
                self.progress.update(follow.line(time.monotonic() - self.t0, final=True), force=True)
            self.n_rev = follow.n_rev
        finally:
            follow.close()

    def collect(self) -> None:
        """Wait for the nodes in turn, each phase named, then gather the result: the summary
        the processor wrote, completed with the recorder's final statistics."""
        self._wait("sim", 0 if self.stop_at is None else STOP_GRACE_S)
        # a simulator that failed (it may never have published) leaves the others nothing to
        # wait for: they get a short grace to notice, then SIGTERM (they finalise their files)
        sim = self.procs.get("sim")
        sim_ok = sim is not None and sim.returncode == 0
        grace = 120 if sim_ok else FAILED_SIM_GRACE_S
        self._tell_gone()
        if not sim_ok:  # one deadline for all: each had the same time to notice, none waits on another
            self._stop_consumers_after(FAILED_SIM_GRACE_S)
        self.progress.phase("making the report ...")
        self._wait("processor", grace)
        processor = self.procs.get("processor")
        self._tell_gone()
        if sim_ok and processor is not None and processor.returncode not in (0, None, NODE_INCOMPLETE):
            self._stop_consumers_after(FAILED_PROCESSOR_GRACE_S)  # not 30 s of silence for its report
        self.progress.phase("finishing the recording ...")
        self._wait("recorder", grace)
        self.progress.phase("finishing the views ...")
        self.serving = self.plan.web and "viewer" in self.procs and self._wait_serving(120)
        if self.serving and self.interrupted:  # its .rrd is complete: no serving after Ctrl-C
            _signal(self.procs["viewer"], signal.SIGTERM)
            self.serving = False
        if not self.serving:
            self._wait("viewer", grace)
        self.recorder = self._final_stats("recorder")
        self.viewer = self._final_stats("viewer")  # its own counts: what the views lost
        stats = {"recorder": self.recorder, "viewer": self.viewer, "processor": self._final_stats("processor")}
        # an incomplete node that said what it misses has not failed: the run reports what is missing
        self.failed = {n: p.returncode for n, p in self.procs.items() if p.returncode not in (0, None)
                       and not (p.returncode == NODE_INCOMPLETE and stats.get(n))}
        self.summary, self.result_complete = self._summary()
        self.finished = True
        self.progress.close()

    def serve(self, on_serving=None) -> None:
        """With the viewer serving the web viewer: ``on_serving(result)``, then serve until a
        signal stops the viewer."""
        if not self.serving:
            return
        if on_serving is not None:
            on_serving(self.result())
        self.procs["viewer"].wait()  # until a signal: the handler stops it

    def close(self) -> None:
        """Stop what still runs; close the logs, the status board and the status files."""
        self.progress.close()
        for p in self.procs.values():
            if p.poll() is None:
                _wait_or_stop(p, 0)
        for f in self._logs.values():
            f.close()
        if self.board is not None:
            self.board.close()
        shutil.rmtree(self.plan.status_dir, ignore_errors=True)

    def result(self) -> dict:
        """The run's outcome: ``summary`` (None: no report), ``files``, ``recorder`` and
        ``viewer`` (their final statistics, ``{}`` if none came), ``recording`` (the summary's
        block), ``interrupted``, ``failed`` (``{node: returncode}``), ``wall_s`` and
        ``result_complete`` (the processor's own verdict: ``summary["complete"]`` also needs
        a complete recording)."""
        return {"summary": self.summary, "files": {k: str(v) for k, v in self.plan.files.items()},
                "recorder": self.recorder, "viewer": self.viewer, "interrupted": self.interrupted,
                "failed": self.failed, "wall_s": time.monotonic() - self.t0,
                "result_complete": self.result_complete, "recording": recording_block(self.recorder),
                "write_error": self.write_error}

    # -- helpers -------------------------------------------------------------------------
    def _show_url(self) -> None:
        """Print the web viewer's address once its status gives it."""
        if self._url_shown or self.board is None:
            return
        status = self.board.get("viewer")
        if status is not None and status.url:
            self.progress.note(f"web viewer: {status.url}")
            self._url_shown = True

    def _wait(self, name: str, timeout_s: float) -> None:
        """Wait for a node; SIGTERM it after ``timeout_s``. After a signal, every node still
        running gets SIGTERM ``STOP_GRACE_S`` after it, and SIGKILL ``STOP_KILL_S`` later
        (the recorder, writing what it has, ``RECORDER_KILL_S``)."""
        p = self.procs.get(name)
        if p is None:
            return
        end = time.monotonic() + timeout_s
        while p.poll() is None:
            limit = end if self.stop_at is None else min(end, self.stop_at + STOP_GRACE_S)
            left = limit - time.monotonic()
            if left <= 0:
                break
            with contextlib.suppress(subprocess.TimeoutExpired):
                p.wait(timeout=min(left, 0.1))
        if p.poll() is not None:
            return
        if self.stop_at is None:
            _wait_or_stop(p, 0)
            return
        for q in self.procs.values():
            _signal(q, signal.SIGTERM)
        kill_s = RECORDER_KILL_S if name == "recorder" else STOP_KILL_S
        try:
            p.wait(timeout=max(0.0, self.stop_at + STOP_GRACE_S + kill_s - time.monotonic()))
        except subprocess.TimeoutExpired:
            _signal(p, signal.SIGKILL)
            p.wait()

    def _tell_gone(self) -> None:
        """Tell each consumer whose followed nodes (:data:`FOLLOWS`) have all been reaped (or
        never started) that they are gone for good (:data:`GONE_SIGNAL`, once): nothing more
        can come from them, so it ends once it has handed out what it received and its inbox
        stays quiet, instead of waiting its ``--drain-timeout`` of silence for data that can no
        longer come (a failed simulator's, a report a failed processor never sent, what a
        consumer stalled past the lease lost). A consumer that has the whole run ends at once
        either way."""
        over = {n for n in NODES if self.procs.get(n) is None or self.procs[n].poll() is not None}
        for n, follows in FOLLOWS.items():
            p = self.procs.get(n)
            if n not in self._told and set(follows) <= over and p is not None and p.poll() is None:
                self._told.add(n)
                p.send_signal(GONE_SIGNAL)  # the node alone, not its process group

    def _stop_consumers_after(self, timeout_s: float) -> None:
        """Wait up to ``timeout_s`` for the consumers (all at once) to end on their own, then
        SIGTERM those still running (they hand out what they received and finalise their files);
        a viewer that may serve the web viewer is left to :meth:`_wait_serving`."""
        names = [n for n in ("processor", "recorder", "viewer") if n in self.procs
                 and not (n == "viewer" and self.plan.web)]
        end = time.monotonic() + timeout_s
        while self.stop_at is None and time.monotonic() < end:
            self._tell_gone()  # the processor ended: the recorder and the viewer follow it
            running = [self.procs[n] for n in names if self.procs[n].poll() is None]
            if not running:
                return
            with contextlib.suppress(subprocess.TimeoutExpired):
                running[0].wait(timeout=min(0.1, max(0.0, end - time.monotonic())))
        if self.stop_at is None:  # after a signal, _wait's own sequence stops them
            for n in names:
                _signal(self.procs[n], signal.SIGTERM)

    def _wait_serving(self, timeout_s: float) -> bool:
        """Wait until the viewer's status says it only serves (True), or it has ended, or a
        signal came (False); False after ``timeout_s`` too."""
        viewer = self.procs["viewer"]
        deadline = time.monotonic() + timeout_s
        while viewer.poll() is None and time.monotonic() < deadline and self.stop_at is None:
            status = self.board.get("viewer")
            if status is not None and status.state == "serving":
                self._show_url()
                return True
            time.sleep(0.1)
        return False

    def _final_stats(self, name: str) -> dict:
        """A node's final statistics from its status (``{}``: it gave none, e.g. killed)."""
        p = self.procs.get(name)
        if p is None or self.board is None:
            return {}
        ended_well = p.returncode in (0, None, NODE_INCOMPLETE)
        status = self.board.final(name, wait_s=FINAL_STATUS_WAIT_S if ended_well else 0.0)
        return dict(status.stats) if status is not None else {}

    def _summary(self) -> tuple[dict | None, bool]:
        """The processor's summary (or, if it failed, one that says so) with the recording
        block, written back to ``summary.json``; and the processor's own verdict."""
        path = self.plan.files["summary"]
        summary = None
        if path.exists():
            try:
                summary = json.loads(path.read_text())
            except (OSError, ValueError):  # cut short (a full disk): the processor failed too, or says so below
                self.failed.setdefault("processor", 2)
        if summary is None and "processor" in self.failed:  # no report: say so in the file a reader looks at
            summary = no_report_summary(self.n_rev, self.failed["processor"], self.plan.files["mcap"])
        elif summary is None:
            return None, False
        result_complete = bool(summary.get("complete", False))
        summary = with_recording(summary, self.recorder)  # complete only with a complete recording
        try:
            _write_atomically(path, json.dumps(summary, indent=2) + "\n")
        except OSError as exc:
            self.write_error = f"{path}: cannot write ({exc.strerror or exc})"
        return summary, result_complete


def _write_atomically(path: Path, text: str) -> None:
    """Write ``path`` through a temporary file and a rename: a full disk leaves the old file
    (or none), never a cut one."""
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    except OSError:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


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

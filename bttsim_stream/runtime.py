"""The node runtime: every node program in ``nodes/`` is a thin program on it.

* :class:`NodeProgram` -- a node's name, what it does, its arguments and its ``main``,
  declared once: :func:`run_node` (the node's own script / console script) and ``bttsim node
  NAME`` (:func:`add_node_parser`) build the same parser from it, so both show the same
  flags and help. The Zenoh session flags (``-m``, ``-e/--connect``, ``-l/--listen``,
  ``-c/--config``, ``--multicast-scouting``) come from :func:`~bttsim_stream.bus.session.add_session_args`.
* :class:`NodeContext` (:func:`node_session`) -- the loop every subscribing node runs: one
  session, its subscriptions into one bounded inbox (back-pressure instead of unbounded
  memory), publishers, the liveliness token ``bttsim/<rig>/alive/<name>``, the node's status
  (``bttsim/<rig>/status/<name>``, :mod:`bttsim_stream.bus.status`; also written to
  ``--status-file``), the watch on the nodes whose end ends this one, a drain, and everything
  undeclared on the way out.
* :class:`Progress` -- the progress line: redrawn in place on a terminal, plain periodic
  lines otherwise (a log file gets no carriage returns).
"""

from __future__ import annotations

import argparse
import math
import contextlib
import logging
import os
import re
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import zenoh

from .bus import keys
from .bus.session import NodeWatch, Received, StopFlag, add_session_args, config_from_args, declare_publisher, \
    declare_subscriber, opened, pack_attachment
from .bus.status import STATES as STATUS_STATES
from .bus.status import NodeStatus, encode_status, write_status_file
from .defaults import DEFAULT_BIND, DEFAULT_GRPC_PORT, DEFAULT_WEB_PORT
from .errors import BttsimError, exit_status
from .threads import single_threaded_blas

__all__ = ["Parser", "NodeProgram", "node_parser", "add_node_parser", "run_node", "NodeContext", "node_session",
           "Progress", "parse_rate", "RATE_HELP", "plain_text", "add_status_argument", "add_web_arguments",
           "add_drain_argument", "add_wait_arguments", "add_name_argument", "DRAIN_TIMEOUT_S", "EXIT_INCOMPLETE"]

#: How long a consumer waits, in silence, for the rest of a run whose nodes have gone (s).
DRAIN_TIMEOUT_S = 30.0
#: Exit status of a consumer node (processor, recorder, viewer) whose received or written
#: stream is not complete (as ``bttsim run``'s).
EXIT_INCOMPLETE = 3

#: Help text of every ``--rate`` option.
RATE_HELP = "pacing: 'max' (default: as fast as possible), 'realtime', or a speed-up factor"


@dataclass(frozen=True)
class NodeProgram:
    """A node program, declared once.

    Attributes
    ----------
    name : str
        ``bttsim node NAME``; also the liveliness token name.
    description : str
        What the node does, its keys and how it stops (the ``--help`` text).
    add_arguments : callable
        ``add_arguments(parser)``: the node's own options (every one with help text).
    main : callable
        ``main(conf, args)``: runs the node with a ``zenoh.Config`` and the parsed options.
    """

    name: str
    description: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    main: Callable[..., object]

    @property
    def help_text(self) -> str:
        """The description as plain text (``--help`` prints no reST markup)."""
        return plain_text(self.description)

    @property
    def summary(self) -> str:
        return self.help_text.strip().splitlines()[0]


_ROLE = re.compile(r":[a-z:]+:`(~?)([^`<]*?)(?:\s*<[^>]*>)?`")
_LITERAL = re.compile(r"``(.+?)``", re.DOTALL)


def plain_text(rst: str) -> str:
    """A docstring's text without its reST inline markup: double-backquoted literals lose
    their quotes, a cross-reference role becomes its target (the last component with ``~``,
    the title of an explicit ``title <target>``)."""
    def role(m: re.Match) -> str:
        target = m.group(2).strip()
        return target.rsplit(".", 1)[-1] if m.group(1) else target

    return _LITERAL.sub(r"\1", _ROLE.sub(role, rst))


class Parser(argparse.ArgumentParser):
    """argparse with the project's one-line error format (argparse already exits 2)."""

    def error(self, message: str) -> None:
        self.exit(2, f"bttsim: error: {message}\n")


def _configure(parser: argparse.ArgumentParser, program: NodeProgram) -> argparse.ArgumentParser:
    program.add_arguments(parser)
    add_session_args(parser)
    parser.set_defaults(node_program=program)
    return parser


def node_parser(program: NodeProgram) -> argparse.ArgumentParser:
    """The parser of a node's own script (``python -m bttsim_stream.nodes.X``)."""
    parser = Parser(prog=f"bttsim-{program.name}", description=program.help_text,
                     formatter_class=argparse.RawDescriptionHelpFormatter)
    return _configure(parser, program)


def add_node_parser(subparsers, program: NodeProgram, name: str | None = None) -> argparse.ArgumentParser:
    """Add ``program`` to a ``bttsim`` subcommand table (``bttsim node NAME``, ``bttsim replay``...)."""
    parser = subparsers.add_parser(name or program.name, help=program.summary, description=program.help_text,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
    return _configure(parser, program)


def run_parsed(args: argparse.Namespace):
    """Run the node program of parsed arguments (from :func:`node_parser` or :func:`add_node_parser`),
    logging to stderr."""
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
    zenoh.try_init_log_from_env()  # RUST_LOG=warn (or zenoh=debug...): Zenoh's own log too
    return args.node_program.main(config_from_args(args), args)


#: Options naming a file or folder a command writes, and those naming what it reads.
_OUTPUTS = ("out", "dir", "summary", "rrd", "status_file")
_INPUTS = ("mcap", "scenario", "opr", "results", "options", "deck", "model", "from_export", "spec")


def check_paths(args: argparse.Namespace) -> None:
    """An empty output path (it would write into the working folder under no name), or an
    output that is one of the command's inputs (it would be overwritten before it is read),
    is one line before anything runs."""
    inputs: dict[str, str] = {}
    for name in _INPUTS:
        value = getattr(args, name, None)
        for v in (value if isinstance(value, list) else [value]):
            if isinstance(v, (str, os.PathLike)) and str(v):
                inputs[os.path.realpath(v)] = str(v)
    for name in _OUTPUTS:
        value = getattr(args, name, None)
        if value is None:
            continue
        flag = "--" + name.replace("_", "-") if name != "dir" else "DIR"
        if not str(value).strip():
            raise BttsimError(f"{flag}: an empty path")
        same = inputs.get(os.path.realpath(value))
        if same is not None:
            raise BttsimError(f"{flag} {value}: that is the input {same}; it would be overwritten")
        if name in ("summary", "status_file"):  # written at the end (or replaced, atomically): its folder must be there
            folder = os.path.dirname(os.path.abspath(value))
            if not os.path.isdir(folder) or os.path.isdir(value):
                raise BttsimError(f"{flag}: cannot write {value}: " + ("it is a folder" if os.path.isdir(value) else
                                                                       f"no folder {folder}"))


def checked(fn, args: argparse.Namespace):
    """``fn(args)`` once :func:`check_paths` passed (for :func:`~bttsim_stream.errors.exit_status`)."""
    check_paths(args)
    return fn(args)


def run_node(program: NodeProgram, argv=None) -> int:
    """Run a node program: parse flags, log to stderr, and turn a :class:`BttsimError` into one
    line ``bttsim: error: ...`` with exit status 2."""
    single_threaded_blas()
    return exit_status(checked, run_parsed, node_parser(program).parse_args(argv))


def parse_rate(text: str) -> float | None:
    """``--rate``: None for ``max``, 1.0 for ``realtime``, else a positive speed-up factor."""
    if text == "max":
        return None
    if text == "realtime":
        return 1.0
    try:
        value = float(text)
    except ValueError:
        raise BttsimError(f"--rate must be 'max', 'realtime' or a positive factor, got {text!r}") from None
    if not value > 0:
        raise BttsimError(f"--rate must be positive, got {text!r}")
    return value



def add_status_argument(p: argparse.ArgumentParser) -> None:
    """``--status-file``: where a node also writes its status (for a reader no bus reaches)."""
    p.add_argument("--status-file", metavar="FILE.json",
                   help="also write the node's status (state, final statistics: the JSON of its "
                        "bttsim/<rig>/status/<node> messages) to FILE.json, replaced atomically")


def seconds(text: str, zero: bool = True) -> float:
    """A duration argument: a finite number of seconds, 0 or more (``zero=False``: above 0)."""
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not (math.isfinite(value) and (value >= 0 if zero else value > 0)):
        raise argparse.ArgumentTypeError(f"{text!r} is not a duration in seconds (a finite number "
                                         f"{'>=' if zero else '>'} 0)")
    return value


def positive_seconds(text: str) -> float:
    """A duration argument that must pass: a finite number of seconds above 0."""
    return seconds(text, zero=False)


def count(text: str, least: int = 0) -> int:
    """A count argument: a whole number, ``least`` or more."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value < least:
        raise argparse.ArgumentTypeError(f"{text!r} is below {least}")
    return value


def positive_count(text: str) -> int:
    """A count argument of 1 or more."""
    return count(text, 1)


def port(text: str) -> int:
    """A TCP port argument: 1 to 65535."""
    value = count(text, 1)
    if value > 65535:
        raise argparse.ArgumentTypeError(f"{text!r} is not a port (1 to 65535)")
    return value


def rig_name(text: str) -> str:
    """A rig name argument (letters, digits, ``_`` and ``-``)."""
    try:
        return keys.validate_rig(text)
    except BttsimError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_duration_argument(p: argparse.ArgumentParser) -> None:
    """``--duration``: a node stops after that many seconds (a finite number above 0)."""
    p.add_argument("--duration", type=positive_seconds, metavar="S", help="stop after S seconds")


def add_drain_argument(p: argparse.ArgumentParser) -> None:
    """``--drain-timeout``: how long a consumer waits for the rest of a run whose nodes have gone."""
    p.add_argument("--drain-timeout", type=seconds, default=DRAIN_TIMEOUT_S, metavar="S",
                   help="when the nodes it follows are gone (or have sent all) before the whole run came in (a "
                        f"router restart, a lease expiry), wait up to S seconds of silence for the rest "
                        f"({DRAIN_TIMEOUT_S:g})")


#: Names a consumer node cannot take: the publishers (which ``--wait-for`` does not count, and
#: whose status key they would share) and the processor (whose report its followers await).
RESERVED_NAMES = ("sim", "router", "processor")


def _node_name(text: str) -> str:
    try:
        name = keys.validate_node(text)
    except BttsimError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    if name in RESERVED_NAMES:
        raise argparse.ArgumentTypeError(f"{name!r} is another node's name ({', '.join(RESERVED_NAMES)} are taken)")
    return name


def add_name_argument(p: argparse.ArgumentParser, default: str) -> None:
    """``--name``: the node's name on the bus (its ``alive``, ``ready``, ``done``, ``awaiting``,
    ``reported`` and ``status`` keys), ``default`` unless given: two consumers of one rig under
    one name count once for a publisher's ``--wait-for`` and the first one done would let it go."""
    p.add_argument("--name", type=_node_name, default=default, metavar="NAME",
                   help=f"the node's name on the bus, in its bttsim/<rig>/alive|ready|done|status/NAME keys "
                        f"({default}); give a second {default} of one rig another name, so that a simulator's or "
                        "a replay's --wait-for counts it and waits for its whole run")


def add_wait_arguments(p: argparse.ArgumentParser) -> None:
    """``--wait-for N`` and ``--wait-timeout S``: a publisher (simulator, replay) starts the run
    once N consumers have it (:func:`~bttsim_stream.bus.session.wait_for_consumers`)."""
    p.add_argument("--wait-for", type=count, default=0, metavar="N",
                   help="wait for N other nodes' liveliness tokens on the rig before publishing")
    p.add_argument("--wait-timeout", type=seconds, default=30.0, metavar="S",
                   help="give up waiting for --wait-for nodes after S seconds (30)")


def add_web_arguments(p: argparse.ArgumentParser) -> None:
    """``--web-port``, ``--grpc-port``, ``--bind``: where the Rerun web viewer is served (the
    viewer node, ``bttsim run`` and ``bttsim view`` alike)."""
    p.add_argument("--web-port", type=port, default=DEFAULT_WEB_PORT, metavar="PORT",
                   help=f"web viewer HTTP port ({DEFAULT_WEB_PORT})")
    p.add_argument("--grpc-port", type=port, default=DEFAULT_GRPC_PORT, metavar="PORT",
                   help=f"port of the web viewer's data server ({DEFAULT_GRPC_PORT})")
    p.add_argument("--bind", default=DEFAULT_BIND, metavar="ADDR",
                   help=f"IP address the web viewer listens on ({DEFAULT_BIND}: this machine only)")

#: Samples taken from one subscription's FIFO at a time; how long an idle node sleeps between
#: two looks at the FIFOs (s): the longest a sample waits when nothing else is coming.
_BATCH = 4096
_IDLE_POLL_S = 0.01
#: A node whose samples wait for their run's metadata asks the metadata queryable at most
#: this often (s), and for at most :data:`_META_ASK_RIGS` rigs at a time.
META_ASK_EVERY_S = 1.0
_META_ASK_RIGS = 8
#: Samples waiting in the inbox that wake its sleeping consumer before its sleep ends.
WAKE_AT = 64
#: Live samples a subscription's FIFO holds before Zenoh's delivery blocks (back-pressure):
#: about 40 MB of 10 kB TOA batches, whatever the run's length.
FIFO_SIZE = 1 << 12

#: The live FIFO of the nodes that only take the stream in (the recorder's ``--queue``, the
#: viewer): samples waiting there, and the network buffers they came in, are memory of
#: Zenoh's threads, which swung by up to 160 MB with 4096 in a recorder or viewer lagging
#: behind a fast run, its peak the higher the longer the run (``bttsim run``, 130 s / 1000 s
#: run-ups: recorder 193 / 250 MB, viewer 303 / 393 MB; with 256: 79 / 86 and 213 / 246).
#: 256 keep the run as fast; past them Zenoh's delivery blocks and the publishers slow down.
SINK_FIFO_SIZE = 1 << 8


class Inbox:
    """A bounded FIFO from Zenoh's receiving threads to the node's main thread.

    Cheaper per sample than :class:`queue.Queue`: :meth:`put` wakes a sleeping consumer only
    once :data:`WAKE_AT` samples wait (else its sleep, at most :data:`_IDLE_POLL_S`, ends on its
    own: a sample waits at most that long, and a busy stream wakes it once per batch rather
    than once per sample), and :meth:`take` hands out everything waiting at once (one lock
    round per batch, not per sample). A full inbox blocks :meth:`put` (back-pressure).
    """

    def __init__(self, maxsize: int) -> None:
        self._items: deque = deque()
        self._max = max(1, int(maxsize))
        self._lock = threading.Lock()
        self._nonempty = threading.Condition(self._lock)
        self._nonfull = threading.Condition(self._lock)
        self._sleeping = False  # the consumer waits for a sample
        self._full = 0  # producers waiting for room

    def put(self, item) -> None:
        with self._lock:
            while len(self._items) >= self._max:
                self._full += 1
                self._nonfull.wait()
                self._full -= 1
            self._items.append(item)
            if self._sleeping and len(self._items) >= WAKE_AT:
                self._nonempty.notify()

    def qsize(self) -> int:
        return len(self._items)

    def wait(self, timeout: float) -> None:
        """Sleep up to ``timeout`` s, or until :data:`WAKE_AT` samples wait."""
        with self._lock:
            if not self._items:
                self._sleeping = True
                self._nonempty.wait(timeout)
                self._sleeping = False

    def take(self, timeout: float) -> list:
        """Everything waiting, in order; if nothing waits, sleeps up to ``timeout`` s (or until
        :data:`WAKE_AT` samples wait) first (``[]``: nothing came)."""
        with self._lock:
            if not self._items and timeout > 0:
                self._sleeping = True
                self._nonempty.wait(timeout)
                self._sleeping = False
            items = list(self._items)
            self._items.clear()
            if self._full:
                self._nonfull.notify_all()
        return items


class NodeContext:
    """A node's presence on the bus (see :func:`node_session`).

    Samples of every subscription go into one bounded inbox, in arrival order; a full inbox
    blocks Zenoh's delivery (back-pressure) rather than growing without bound. A
    subscription's live FIFO holds at most ``fifo_size`` samples (default
    :data:`FIFO_SIZE`): a node slower than its publishers slows them down instead of holding
    the rest of the run in memory.
    """

    def __init__(self, session, rig: str, name: str, *, inbox_size: int = 1 << 16,
                 fifo_size: int | None = None, status_file: str | None = None) -> None:
        self.session = session
        self.rig = rig
        self.name = name
        self._inbox = Inbox(inbox_size)
        self._inbox_max = max(1, int(inbox_size))
        self._fifo_size = max(1, int(FIFO_SIZE if fifo_size is None else fifo_size))
        self._live: list = []  # subscribers whose samples wait in Zenoh's FIFOs
        self._subs: list = []
        self._history: list[str] = []  # key expressions subscribed with history
        self._pubs: dict[str, object] = {}
        self._others: list = []
        self.watch: NodeWatch | None = None
        self._ready = False
        self._confirmed: set[str] = set()  # the confirmation tokens declared (done, awaiting, reported)
        self._asked_meta = -META_ASK_EVERY_S  # when the metadata queryables were last asked
        self.status_file = status_file
        #: The web viewer's address, sent with every status ("" when none).
        self.url = ""
        self._status_seq = 0

    # -- declarations --------------------------------------------------------------------
    def subscribe(self, key_expr: str, *, history: bool = False, fifo: bool = True) -> None:
        """Receive ``key_expr`` (``history``: also late-joiner history, into the inbox).

        With ``fifo`` the live samples wait in a bounded FIFO inside Zenoh that
        :meth:`samples` drains in batches: Zenoh's receiving thread runs no Python (nor waits
        for the interpreter lock) per sample. A subscription's samples keep their arrival
        order, but those of two such subscriptions come a batch of one, then a batch of the
        other: a node that needs the arrival order across its subscriptions (OPR pulses
        between TOA batches) says ``fifo=False`` and gets every sample through the inbox, in
        arrival order."""
        put = self._inbox.put
        sub = declare_subscriber(self.session, key_expr, lambda s: put(Received.of(s)), history=history,
                                 channel=self._fifo_size if fifo else None)
        self._subs.append(sub)
        if fifo:
            self._live.append(sub)
        if history:
            self._history.append(key_expr)

    def catch_up(self, timeout_s: float = 2.0) -> int:
        """Ask the publishers' caches (zenoh-ext advanced publishers) again for what they hold on
        the keys subscribed with ``history``; the replies join the inbox (a receiver tells them
        from samples already in by their numbers). Returns how many came; a query that fails
        (no route now) is 0. While it waits, the live FIFOs are moved into the inbox: a full
        FIFO blocks Zenoh's receiving thread, and the replies come through that thread."""
        n = 0
        for expr in self._history:
            replies = zenoh.handlers.FifoChannel(1 << 16)
            try:
                pending = self.session.get(f"{expr}/@adv/**", replies, consolidation=zenoh.ConsolidationMode.NONE,
                                           accept_replies=zenoh.ReplyKeyExpr.ANY, timeout=timeout_s)
            except zenoh.ZError:
                continue
            while True:
                try:
                    reply = pending.try_recv()
                except zenoh.ZError:  # empty and closed: every reply is in
                    break
                if reply is None:
                    self._relieve()
                    time.sleep(_IDLE_POLL_S)
                    continue
                sample = reply.ok
                if sample is not None and keys.key_matches(expr, str(sample.key_expr)):
                    self._inbox.put(Received.of(sample))
                    n += 1
        return n

    def _relieve(self) -> None:
        """Move what waits in the live FIFOs into the inbox (in each one's order)."""
        for sub in self._live:
            while self._inbox.qsize() < self._inbox_max:
                s = sub.try_recv()
                if s is None:
                    break
                self._inbox.put(Received.of(s))

    def publisher(self, key: str, *, cache_samples: int = 64, lossy: bool = False):
        """The publisher of ``key`` (declared on first use)."""
        pub = self._pubs.get(key)
        if pub is None:
            pub = self._pubs[key] = declare_publisher(self.session, key, cache_samples=cache_samples, lossy=lossy)
        return pub

    def declare(self, entity):
        """Keep ``entity`` (a queryable, a token...) to undeclare it on close; returns it."""
        self._others.append(entity)
        return entity

    def query(self, key_expr: str, timeout_s: float = 1.0) -> int:
        """Ask a queryable; its replies join the inbox like samples. Returns how many came."""
        n = 0
        for reply in self.session.get(key_expr, timeout=timeout_s):
            if reply.ok is not None:
                self._inbox.put(Received.of(reply.ok))
                n += 1
        return n

    def ask_metadata(self, rigs) -> None:
        """Samples of ``rigs`` came before their run's metadata (the node joined late, or the
        metadata sample went by before its subscription reached the publisher): ask the rigs'
        ``bttsim/<rig>/meta`` queryables, at most every :data:`META_ASK_EVERY_S`; the replies
        join the inbox like samples."""
        now = time.monotonic()
        if not rigs or now - self._asked_meta < META_ASK_EVERY_S:
            return
        self._asked_meta = now
        for rig in sorted(rigs)[:_META_ASK_RIGS]:
            with contextlib.suppress(BttsimError, zenoh.ZError):  # a rig name no run can have: nothing to ask
                self.query(keys.meta_key(rig))

    def announce(self) -> None:
        """Declare the liveliness token ``bttsim/<rig>/alive/<name>`` (after the subscriptions:
        a simulator waiting for the token then finds them)."""
        self.declare(self.session.liveliness().declare_token(keys.alive_key(self.rig, self.name)))
        self.status("starting")

    def status(self, state: str, stats: dict | None = None) -> None:
        """Publish the node's status (``starting``, ``ready``, ``done`` with its final
        statistics, ``serving``) on ``bttsim/<rig>/status/<name>`` and write it to the status
        file, if any. A status that cannot go out is logged, never fatal."""
        status = NodeStatus(self.name, state, self._status_seq, self.url, dict(stats or {}))
        self._status_seq += 1
        try:
            payload = encode_status(status)
            if self.status_file:
                write_status_file(self.status_file, status)
        except (BttsimError, OSError) as exc:
            logging.getLogger(f"bttsim.{self.name}").warning("status %s not sent: %s", state, exc)
            return
        with contextlib.suppress(zenoh.ZError):
            # an attachment like every sample of the bus (its number, wall-clock time); dropped,
            # never waited for, under congestion: a node blocked in its status put does not drain
            # its own subscriptions, and two consumers blocked so (each subscribed to the other's
            # status) wait for each other for ever. The file and the cache keep the status.
            self.publisher(keys.status_key(self.rig, self.name), cache_samples=len(STATUS_STATES),
                           lossy=True).put(payload, attachment=pack_attachment(status.seq, time.time_ns()))

    def ready(self) -> None:
        """Declare (once) the token ``bttsim/<rig>/ready/<name>``: this node has received the run
        metadata on the bus, so its subscriptions reach the simulator, which waits for it."""
        if not self._ready:
            self._ready = True
            self.declare(self.session.liveliness().declare_token(keys.ready_key(self.rig, self.name)))
            self.status("ready")

    def done(self, rig: str | None = None) -> None:
        """Declare (once per rig) the token ``bttsim/<rig>/done/<name>``: this node has the
        whole acquisition stream (:class:`~bttsim_stream.bus.stream.StreamEnd`); the
        simulator waits for it before it closes its session."""
        self.confirm(keys.done_key, rig)

    def sent(self, rig: str | None = None) -> None:
        """Declare (once per rig) the token ``bttsim/<rig>/sent/<name>``: this node has published
        all it will and only waits for confirmations now (:func:`~bttsim_stream.bus.keys.sent_key`);
        a consumer that follows it and lacks part of the run then stops waiting for it to leave."""
        self.confirm(keys.sent_key, rig)

    def confirm(self, token_key, rig: str | None = None) -> None:
        """Declare (once per rig) the liveliness token ``token_key(rig, name)``
        (:func:`~bttsim_stream.bus.keys.done_key`, ``awaiting_key``, ``reported_key``)."""
        key = token_key(rig or self.rig, self.name)
        if key not in self._confirmed:
            self._confirmed.add(key)
            self.declare(self.session.liveliness().declare_token(key))

    def watch_nodes(self, names, grace_s: float = 5.0) -> NodeWatch:
        """Follow the named nodes' liveliness: :meth:`samples` ends once they are gone."""
        self.watch = NodeWatch(self.session, self.rig, names, grace_s=grace_s)
        return self.watch

    # -- the loop ------------------------------------------------------------------------
    def samples(self, stop: StopFlag, *, idle_s: float = 0.5, poll_s: float = 0.05, done=None,
                patience_s: float = 10.0) -> Iterator:
        """Yield received samples; ``None`` about every ``poll_s`` while idle (time to flush).

        Ends on ``stop`` once what was already received has been handed out, or once the
        watched nodes have ended and the inbox has been empty for ``idle_s`` (drained). A
        node's liveliness token travels ahead of its last data (declarations go first), so a
        node that can tell whether it has everything (``done()``: e.g. every revolution of the
        run) waits up to ``patience_s`` of silence for the rest before it gives up -- unless
        the watched nodes are known to be gone for good (:attr:`NodeWatch.final`: their
        process was reaped), when ``idle_s`` of silence is enough. A consumer that lacks part
        of the run also counts a watched node that declared it has sent all (its ``sent``
        token) as ended: that node waits for this one's confirmation before it leaves.
        """
        idle_since = None
        left = None  # samples still to hand out once stopped
        batch: list = []  # taken from the inbox, not yet handed out
        i = 0
        while True:
            if left is None and stop:
                batch, i = batch[i:] + self._take(0.0), 0
                left = len(batch)
            if left is not None:
                if left <= 0:
                    return
                left -= 1
            if i == len(batch):
                batch, i = self._take(poll_s if left is None else 0.0), 0
            if i < len(batch):
                sample = batch[i]
                i += 1
                idle_since = None
                yield sample
                continue
            if left is not None:
                return
            have = self.watch is not None and (done is None or done())
            # a followed node that sent all and waits for confirmations ends the wait only of a
            # consumer that lacks part of the run (it would wait for that node, which waits for it)
            if self.watch is not None and self.watch.ended(sent=not have):
                idle_since = idle_since or time.monotonic()
                wait = idle_s if have or self.watch.final else patience_s
                if time.monotonic() - idle_since > wait:
                    return
            yield None

    def _take(self, timeout_s: float) -> list:
        """Everything received (the inbox first: history and query replies, then each
        subscription's FIFO), waiting up to ``timeout_s`` for something to come."""
        deadline = None
        while True:
            out = self._inbox.take(0.0)
            for sub in self._live:
                recv = sub.try_recv
                while len(out) < _BATCH:
                    s = recv()
                    if s is None:
                        break
                    out.append(Received.of(s))
            if out or timeout_s <= 0:
                return out
            now = time.monotonic()
            deadline = deadline or now + timeout_s
            if now >= deadline:
                return out
            self._inbox.wait(min(_IDLE_POLL_S, deadline - now))

    def close(self, linger_s: float = 0.0) -> None:
        """Undeclare everything (after ``linger_s``, so that the last samples leave first)."""
        if linger_s and self._pubs:
            time.sleep(linger_s)
        for entity in [*self._pubs.values(), *self._subs, *reversed(self._others)]:
            with contextlib.suppress(Exception):
                entity.undeclare()
        if self.watch is not None:
            with contextlib.suppress(Exception):
                self.watch.undeclare()
        self._pubs.clear()
        self._subs.clear()
        self._others.clear()


@contextlib.contextmanager
def node_session(conf, rig: str, name: str, *, inbox_size: int = 1 << 16, fifo_size: int | None = None,
                 linger_s: float = 0.2, status_file: str | None = None):
    """Open a session and a :class:`NodeContext` for node ``name`` on ``rig``; on exit,
    wait ``linger_s`` if anything was published, undeclare everything and close.
    ``status_file``: where the node's status is also written (``--status-file``)."""
    with opened(conf) as session:
        ctx = NodeContext(session, rig, name, inbox_size=inbox_size, fifo_size=fifo_size, status_file=status_file)
        try:
            yield ctx
        finally:
            ctx.close(linger_s)


class Progress:
    """A progress line on stderr.

    On a terminal it is redrawn in place (at most every ``redraw_s``); otherwise (a log file,
    a pipe) it prints a plain line at most every ``period_s`` and a last one on :meth:`close`.

    Parameters
    ----------
    enabled : bool
    stream : file, optional
        Default ``sys.stderr``.
    period_s, redraw_s : float
    """

    def __init__(self, enabled: bool = True, stream=None, *, period_s: float = 10.0, redraw_s: float = 0.1) -> None:
        self.enabled = bool(enabled)
        self.stream = stream if stream is not None else sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self._every = redraw_s if self.tty else period_s
        self._last = -float("inf")
        self._text = ""
        self._shown = ""

    def update(self, text: str, *, force: bool = False) -> bool:
        """Show ``text`` (throttled unless ``force``); True if it was written now."""
        self._text = text
        now = time.monotonic()
        if not self.enabled or (not force and now - self._last < self._every):
            return False
        self._last = now
        self._write(text)
        return True

    def _write(self, text: str) -> None:
        if self.tty:
            self.stream.write("\r" + text + " " * max(0, len(self._shown) - len(text)))
        else:
            self.stream.write(text + "\n")
        self.stream.flush()
        self._shown = text

    def note(self, text: str) -> None:
        """Print ``text`` on a line of its own (above the progress line on a terminal), also
        when the progress line is off."""
        redraw = self.tty and self._shown
        if redraw:
            self.stream.write("\r" + " " * len(self._shown) + "\r")
        self.stream.write(text + "\n")
        if redraw and self.enabled:
            self.stream.write(self._shown)
        self.stream.flush()

    def phase(self, text: str) -> None:
        """End the progress line and say, on a line of its own, what is being done now that
        has no count (``"making the report ..."``); nothing when the progress line is off."""
        if not self.enabled:
            return
        self._end_line()
        self.stream.write(text + "\n")
        self.stream.flush()

    def signal_note(self, text: str) -> None:
        """Print ``text`` on a line of its own from a signal handler, also when the progress
        line is off: one unbuffered write to the stream's file descriptor, as the interrupted
        code may be inside a write to the stream (whose buffer lock it holds)."""
        prefix = "\n" if self.tty and self._shown else ""
        try:
            os.write(self.stream.fileno(), (prefix + text + "\n").encode(errors="replace"))
        except (AttributeError, OSError, ValueError):  # no file descriptor (a test's StringIO)
            return
        if prefix:
            self._shown = ""

    def _end_line(self) -> None:
        if self._text and self._text != self._shown:
            self._write(self._text)
        if self.tty and self._shown:
            self.stream.write("\n")
            self.stream.flush()
        self._text = self._shown = ""

    def close(self) -> None:
        """Show the last state and end the line."""
        if not self.enabled:
            return
        self._end_line()
        self.enabled = False

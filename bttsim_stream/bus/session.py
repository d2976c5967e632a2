"""Zenoh sessions for the nodes: flags, configuration, attachments, liveliness, stopping.

Defaults keep everything on this machine: peer mode, multicast scouting off, and only the
endpoints given with ``-l/--listen`` and ``-e/--connect`` (use loopback addresses such as
``tcp/127.0.0.1:7447``). ``-c/--config`` loads a Zenoh JSON5 configuration file to join a real
Zenoh network with a router. A node that cannot reach every ``-e`` endpoint within
``--connect-timeout`` seconds (nobody there, a TLS handshake refused) stops with a one-line
error instead of running alone. Security (mutual TLS, access control) is off unless a
certificate is given: :mod:`bttsim_stream.bus.security`. Every sample carries a 16-byte
attachment (sequence number and log time in ns, little-endian) so recorders need not decode
payloads.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import random
import select
import signal
import socket
import struct
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import zenoh
import zenoh.ext as zx

from ..errors import BttsimError
from . import keys
from .security import TlsFiles, add_security_args, apply_security, tls_from_args

__all__ = ["NodeWatch", "add_session_args", "config_from_args", "make_config", "pack_attachment",
           "unpack_attachment", "Received", "StopFlag", "wait_for_liveliness", "wait_for_subscribers", "wait_for_done",
           "wait_for_consumers", "READY_TIMEOUT_S", "open_session", "opened", "close_session", "free_port",
           "declare_publisher", "declare_subscriber"]

log = logging.getLogger("bttsim.session")
_ATT = struct.Struct("<Qq")


def add_session_args(parser: argparse.ArgumentParser) -> None:
    """The zenoh example flags: ``-m/--mode``, ``-e/--connect``, ``-l/--listen``, ``-c/--config``."""
    g = parser.add_argument_group("zenoh session")
    g.add_argument("-m", "--mode", choices=("peer", "client"), default="peer", help="session mode (peer)")
    g.add_argument("-e", "--connect", action="append", default=[], metavar="ENDPOINT",
                   help="endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable)")
    g.add_argument("-l", "--listen", action="append", default=[], metavar="ENDPOINT",
                   help="endpoint to listen on, e.g. tcp/127.0.0.1:7447 (repeatable)")
    g.add_argument("-c", "--config", metavar="FILE", help="Zenoh JSON5 configuration file")
    g.add_argument("--multicast-scouting", action="store_true",
                   help="enable multicast scouting (off by default: loopback-only runs)")
    g.add_argument("--connect-timeout", type=float, default=CONNECT_TIMEOUT_S, metavar="S",
                   help=f"give up (error) when the -e endpoints are not all reached after S seconds "
                        f"({CONNECT_TIMEOUT_S:g})")
    add_security_args(parser)


#: How long a node tries to reach its ``-e`` endpoints before it gives up with an error (s).
CONNECT_TIMEOUT_S = 30.0


#: Zenoh's defaults close a link whose receiver has not drained a blocking (lossless) message
#: within 5 s, or that was silent for 10 s: on a loaded machine (or a consumer stopped for a
#: while) that loses messages mid-run. We would rather stall the publisher than lose data.
_PATIENCE = {
    "transport/link/tx/queue/congestion_control/block/wait_before_close": "60000000",  # us
    "transport/link/tx/lease": "30000",  # ms
    # Zenoh (1.5 and later) passes a payload of 3 kB or more between two sessions of one host
    # through a shared-memory pool of the publishing process, and takes a buffer back for
    # reuse once the receiving process has not confirmed holding it for about 100 ms (a
    # thread of that process confirms every 50 ms). A receiver that does not run for that
    # long (stopped, or starved on a loaded machine) while its FIFO holds such samples then
    # reads them overwritten by later messages: valid samples that no longer parse. Every
    # payload is copied over the link instead.
    "transport/shared_memory/enabled": "false",
}


def make_config(mode: str = "peer", connect=(), listen=(), config_file: str | None = None,
                multicast_scouting: bool = False, *, tls: TlsFiles | None = None,
                connect_timeout_s: float | None = CONNECT_TIMEOUT_S) -> "zenoh.Config":
    """A Zenoh configuration; a bad file or endpoint is a one-line :class:`BttsimError`.

    Without a file: ``mode``, only the given listen and connect endpoints, multicast
    scouting off (unless ``multicast_scouting``). A file (``-c``) is merged with these
    defaults rather than replacing them: what it sets wins (TLS, access control, a router's
    endpoints...), but where it says nothing about listen endpoints the node listens only
    where ``listen`` says (not on every interface, zenoh's own default), multicast scouting
    stays off unless the file or ``multicast_scouting`` turns it on, and ``-e``/``-l`` given
    on the command line are added. Links are patient (:data:`_PATIENCE`): a slow consumer
    slows the publisher down (lossless) instead of being cut off after 5 s; and payloads are
    copied, never lent from a shared-memory pool that a stalled receiver loses.

    ``connect_timeout_s``: opening the session waits until every ``connect`` endpoint is
    reached, and fails after that long (None: zenoh's default, retry in the background
    forever; a router node always retries). ``tls``: mutual TLS and access control
    (:func:`~bttsim_stream.bus.security.apply_security`); every endpoint given must then be
    ``tls/...``.
    """
    if tls is not None:
        plain = [e for e in [*connect, *listen] if not str(e).startswith("tls/")]
        if plain:
            raise BttsimError(f"with TLS on, endpoints must be tls/HOST:PORT, got {plain[0]!r}")
    if connect_timeout_s is not None and not connect_timeout_s > 0:
        raise BttsimError(f"--connect-timeout must be positive, got {connect_timeout_s:g}")
    try:
        if config_file:
            if not Path(config_file).is_file():
                raise BttsimError(f"{config_file}: no such Zenoh configuration file")
            conf = zenoh.Config.from_file(config_file)
            defaults = zenoh.Config()
            if conf.get_json("listen/endpoints") == defaults.get_json("listen/endpoints"):
                conf.insert_json5("listen/endpoints", _json_list(listen))
            elif listen:
                conf.insert_json5("listen/endpoints", _json_list(listen))
            if multicast_scouting:
                conf.insert_json5("scouting/multicast/enabled", "true")
            elif conf.get_json("scouting/multicast/enabled") in (None, "null"):
                conf.insert_json5("scouting/multicast/enabled", "false")
            if conf.get_json("mode") in (None, "null"):
                conf.insert_json5("mode", f'"{mode}"')
        else:
            conf = zenoh.Config()
            conf.insert_json5("mode", f'"{mode}"')
            conf.insert_json5("scouting/multicast/enabled", "true" if multicast_scouting else "false")
            conf.insert_json5("listen/endpoints", _json_list(listen))
            if mode == "client" and not connect:  # a router listens; a peer may do neither
                raise BttsimError("client mode needs -e/--connect ENDPOINT")
        if connect:
            conf.insert_json5("connect/endpoints", _json_list(connect))
        defaults = zenoh.Config()
        for key, value in _PATIENCE.items():  # unless the file chose otherwise
            if conf.get_json(key) == defaults.get_json(key):
                conf.insert_json5(key, value)
        if connect and connect_timeout_s is not None and mode != "router" and \
                conf.get_json("connect/timeout_ms") in (None, "null"):
            ms = int(connect_timeout_s * 1000)
            conf.insert_json5("connect/timeout_ms", f'{{"router": -1, "peer": {ms}, "client": {ms}}}')
            conf.insert_json5("connect/exit_on_failure", '{"router": false, "peer": true, "client": true}')
            if conf.get_json("connect/retry") in (None, "null"):  # zenoh's first retry comes after 1 s
                conf.insert_json5("connect/retry", '{"period_init_ms": 100, "period_max_ms": 1000, '
                                                   '"period_increase_factor": 2}')
        if tls is not None:
            apply_security(conf, tls)
        conf.insert_json5("timestamping/enabled", "true")  # needed by the advanced publishers
        return conf
    except BttsimError:
        raise
    except Exception as exc:  # zenoh raises ZError for a malformed file or value
        raise BttsimError(f"zenoh configuration: {str(exc).splitlines()[0]}") from None


def _json_list(items) -> str:
    for e in items:
        if "/" not in e or any(c in e for c in "\"'\\[]"):
            raise BttsimError(f"bad zenoh endpoint {e!r} (expected e.g. tcp/127.0.0.1:7447)")
    return "[" + ",".join(f'"{e}"' for e in items) + "]"


def config_from_args(args: argparse.Namespace, name: str | None = None, mode: str | None = None,
                     listen=None) -> "zenoh.Config":
    """The configuration the session flags ask for; ``name`` is the node's identity for
    ``--tls-dir`` (default: the node program's name), ``mode``/``listen`` override the flags."""
    if name is None:
        name = args.node_program.name if hasattr(args, "node_program") else "run"
        name = {"replay": "sim"}.get(name, name)  # a replay publishes what a simulator does
    return make_config(mode or args.mode, args.connect, args.listen if listen is None else listen, args.config,
                       args.multicast_scouting, tls=tls_from_args(args, name),
                       connect_timeout_s=getattr(args, "connect_timeout", CONNECT_TIMEOUT_S))


def open_session(conf: "zenoh.Config") -> "zenoh.Session":
    """Open a session; an endpoint already in use or unreachable (nobody listening, a TLS
    handshake refused) is a one-line error."""
    try:
        return zenoh.open(conf)
    except Exception as exc:
        text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        if "Unable to connect" in text:
            ends = ", ".join(_json_loads(conf.get_json("connect/endpoints")))
            raise BttsimError(f"cannot reach {ends} (nobody listening there, or the TLS handshake was "
                              "refused: check the endpoints and certificates)") from None
        text = text.split(" at /")[0]  # zenoh appends its source location
        raise BttsimError(f"cannot open the zenoh session: {text}") from None


@contextlib.contextmanager
def opened(conf: "zenoh.Config"):
    """``with opened(conf) as session``: :func:`open_session`, closed on the way out; a close
    that fails (zenoh: "close operation timed out", after a peer vanished or a link stalled
    past the lease) is one logged line, never an exception: what the node did stands."""
    session = open_session(conf)
    try:
        yield session
    finally:
        close_session(session)


def close_session(session) -> None:
    """Close ``session``; a failure is logged in one line."""
    try:
        session.close()
    except Exception as exc:  # zenoh.ZError (a timeout), or a session already torn down
        text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        log.warning("zenoh session close: %s", text.split(" at /")[0])


def _json_loads(text) -> list:
    import json

    try:
        value = json.loads(text)
    except (TypeError, ValueError):
        return []
    if isinstance(value, dict):  # per-mode lists
        return sorted({e for v in value.values() for e in (v or [])})
    return list(value or [])


_ISSUED: set[int] = set()
_ISSUE_LOCK = threading.Lock()


def _ephemeral_range() -> tuple[int, int]:
    """The kernel's range for outgoing connections' local ports (Linux; 32768-60999 else)."""
    try:
        lo, hi = map(int, Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split())
        return lo, hi
    except (OSError, ValueError):
        return 32768, 60999


def free_port() -> int:
    """A free TCP port on 127.0.0.1, outside the kernel's ephemeral range.

    A port the kernel hands out for ``bind(0)`` comes from the same range as the local ports
    of outgoing connections: between picking it and a node listening on it, another node's
    connection may take it ("Address already in use"). Ports below (or above) that range are
    never given to connections; each is checked free here and never issued twice by one
    process.
    """
    lo, hi = _ephemeral_range()
    ranges = [r for r in ((10000, lo - 1), (hi + 1, 65535)) if r[1] - r[0] >= 1000]
    rng = random.SystemRandom()
    with _ISSUE_LOCK:
        for _ in range(200 if ranges else 0):
            a, b = rng.choice(ranges)
            port = rng.randint(a, b)
            if port in _ISSUED:
                continue
            with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
                try:
                    s.bind(("127.0.0.1", port))
                except OSError:
                    continue
            _ISSUED.add(port)
            return port
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:  # no room outside the range
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
            _ISSUED.add(port)
            return port


def pack_attachment(seq: int, log_time_ns: int) -> bytes:
    """The 16-byte attachment of a sample: sequence number and log time (ns)."""
    return _ATT.pack(int(seq), int(log_time_ns))


def unpack_attachment(att) -> tuple[int, int] | None:
    """``(seq, log_time_ns)`` from a sample's attachment (or its bytes), or None."""
    if att is None:
        return None
    raw = att if isinstance(att, bytes) else att.to_bytes()
    if len(raw) != _ATT.size:
        return None
    return _ATT.unpack(raw)


@dataclass(frozen=True, slots=True)
class Received:
    """A sample (or query reply) as received, copied out of Zenoh's buffers.

    Attributes
    ----------
    key : str
    payload : bytes
    att : tuple of (int, int) or None
        ``(seq, log_time_ns)`` from the attachment (None if missing or malformed).
    source : str or None
        The id of the Zenoh session that published it (from its timestamp: sessions stamp
        what they publish), None if it has no timestamp.
    """

    key: str
    payload: bytes
    att: tuple[int, int] | None
    source: str | None = None

    @classmethod
    def of(cls, sample) -> "Received":
        """Copy ``sample`` while Zenoh still owns it (inside its callback: a sample kept past
        the callback that delivered it on Zenoh's own thread can see its buffer reused)."""
        ts = sample.timestamp
        return cls(str(sample.key_expr), sample.payload.to_bytes(), unpack_attachment(sample.attachment),
                   None if ts is None else str(ts.get_id()))


class StopFlag:
    """Set by SIGINT / SIGTERM / SIGHUP (installed in the main thread) or by a deadline.

    SIGHUP (the terminal closed) stops like SIGTERM, so files are finalised and servers
    released instead of the default abrupt end. The signal handler takes no lock: it runs in
    the main thread, which may hold one (a ``threading.Event``'s, while waiting on it), and
    it may run nested when signals come in quick succession (Ctrl-C twice, a parent-death
    SIGTERM and the orchestrator's own). Waiters sleep on a pipe that :meth:`set` writes to.
    """

    def __init__(self, duration_s: float | None = None, install: bool = True) -> None:
        self._stopped = False
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_w, False)
        self._deadline = None if duration_s is None else time.monotonic() + duration_s
        self.signal: int | None = None
        if install and threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
                signal.signal(sig, self._handler)

    def _handler(self, signum, _frame) -> None:
        self.signal = signum
        self.set()

    def set(self) -> None:
        if not self._stopped:
            self._stopped = True
            try:
                os.write(self._wake_w, b"\0")  # the pipe stays readable: every waiter wakes
            except OSError:
                pass

    def __bool__(self) -> bool:
        if self._deadline is not None and time.monotonic() >= self._deadline:
            self._stopped = True
        return self._stopped

    def wait(self, timeout: float) -> bool:
        """Sleep up to ``timeout`` s; True if stopped."""
        if self._deadline is not None:
            timeout = min(timeout, max(0.0, self._deadline - time.monotonic()))
        if not self._stopped:
            poller = select.poll()  # one per call: threads may wait at once
            poller.register(self._wake_r, select.POLLIN)
            poller.poll(max(0, int(timeout * 1000.0 + 0.999)))
        return bool(self)

    def __del__(self) -> None:
        for fd in (getattr(self, "_wake_r", None), getattr(self, "_wake_w", None)):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass


def declare_publisher(session, key: str, *, cache_samples: int = 64, lossy: bool = False):
    """A reliable publisher that keeps its last ``cache_samples`` samples for late joiners
    (zenoh-ext advanced publisher) and blocks under congestion (``lossy``: drops instead).

    Its samples go to the other sessions only: a node never takes its own samples, and a
    sample delivered to its own session's full FIFO subscription would wait, whatever the
    congestion control, for the very thread that drains that FIFO (a recorder or viewer,
    which subscribe to every key of their rig, blocked so for ever in their status put)."""
    return zx.declare_advanced_publisher(
        session, key, cache=zx.CacheConfig(max_samples=int(cache_samples), replies_config=None),
        publisher_detection=True, sample_miss_detection=None,
        congestion_control=zenoh.CongestionControl.DROP if lossy else zenoh.CongestionControl.BLOCK,
        reliability=zenoh.Reliability.RELIABLE, encoding=None, priority=None, express=None,
        allowed_destination=zenoh.Locality.REMOTE)


#: How long a subscriber's one-time history query waits for the publishers' caches (s).
HISTORY_TIMEOUT_S = 10.0


def declare_subscriber(session, key_expr: str, handler, *, history: bool = True, channel: int | None = None):
    """A subscriber calling ``handler(sample)``; with ``history`` it also receives, once, the
    samples the publishers already there hold in their caches (a late joiner's history). With
    ``channel``, the live samples go instead into a bounded FIFO of that many samples inside
    Zenoh, which the caller drains with the subscriber's ``try_recv`` (no Python, and no
    interpreter lock, on Zenoh's receiving thread; a full FIFO blocks it: back-pressure, not
    loss); the history still reaches ``handler``.

    ``handler`` runs in Zenoh's own receiving thread (``indirect=False``), in the order the
    samples arrive on the link. Zenoh-python's default runs each subscriber's callback in a
    thread of its own, and then the samples of different keys (a revolution's OPR pulse and its
    TOA batches) overtake each other by hundreds of revolutions on a loaded machine. A
    handler that blocks (a full inbox) slows the link down: back-pressure, not loss.

    The live subscription is a plain Zenoh subscriber. The history is one query of the
    advanced publishers' caches (``<key_expr>/@adv/**``, every cached sample, no
    consolidation) whose replies reach ``handler`` too, interleaved with live samples: a
    receiver tells them apart by sequence number
    (:class:`~bttsim_stream.bus.stream.SequenceTracker`). zenoh-ext's advanced subscriber is
    not used: it holds back and re-orders every sample of a session by timestamp while it
    queries a publisher declared mid-run, and in a few runs in a hundred it dropped live
    samples for good (a recorder missed 81 messages that a plain subscriber beside it got).
    """
    live = zenoh.handlers.Callback(handler, indirect=False) if channel is None else \
        zenoh.handlers.FifoChannel(int(channel))
    sub = session.declare_subscriber(key_expr, live)
    if history:
        def on_reply(reply) -> None:
            sample = reply.ok
            if sample is not None and keys.key_matches(key_expr, str(sample.key_expr)):
                handler(sample)

        session.get(f"{key_expr}/@adv/**", zenoh.handlers.Callback(on_reply, indirect=False),
                    consolidation=zenoh.ConsolidationMode.NONE, accept_replies=zenoh.ReplyKeyExpr.ANY,
                    timeout=HISTORY_TIMEOUT_S)
    return sub


def wait_for_liveliness(session, key_expr: str, count: int, timeout_s: float, stop: StopFlag,
                        exclude=()) -> int:
    """Wait until ``count`` liveliness tokens match ``key_expr`` (those whose last chunk is in
    ``exclude`` aside); returns how many were seen."""
    deadline = time.monotonic() + timeout_s
    seen = 0
    while not stop and time.monotonic() < deadline:
        seen = sum(1 for r in session.liveliness().get(key_expr, timeout=1.0)
                   if r.ok is not None and str(r.ok.key_expr).rsplit("/", 1)[-1] not in exclude)
        if seen >= count:
            break
        stop.wait(0.1)
    return seen


def wait_for_done(session, rig: str, timeout_s: float, stop: StopFlag, *, asked: str = "ready",
                  given: str = "done") -> set[str]:
    """Wait until every node that declared an ``asked`` token on the rig (``ready``: it
    confirmed the run) has declared its ``given`` token too (``done``: the whole stream), or
    time runs out; returns the nodes still missing. A node that dies drops its tokens and is
    no longer waited for. The processor waits so for its report: ``awaiting`` and
    ``reported``."""
    def names(what: str) -> set[str]:
        return {str(r.ok.key_expr).rsplit("/", 1)[-1]
                for r in session.liveliness().get(f"{keys.PREFIX}/{rig}/{what}/*", timeout=1.0) if r.ok is not None}

    deadline = time.monotonic() + timeout_s
    while True:
        waiting = names(asked) - names(given)
        if not waiting or stop or time.monotonic() >= deadline:
            return waiting
        stop.wait(0.05)


def wait_for_subscribers(session, key_exprs, timeout_s: float, stop: StopFlag, *, every: bool = True) -> bool:
    """Wait until every key expression (``every=False``: any one) has a matching subscriber,
    or time runs out; returns whether it happened."""
    probes = [session.declare_publisher(k) for k in key_exprs]
    done = all if every else any
    try:
        deadline = time.monotonic() + timeout_s
        while not stop and time.monotonic() < deadline:
            if done(p.matching_status.matching for p in probes):
                return True
            stop.wait(0.05)
        return done(p.matching_status.matching for p in probes)
    finally:
        for p in probes:
            p.undeclare()


#: How long a publisher waiting for its consumers (:func:`wait_for_consumers`) waits, after the
#: run metadata, for them to confirm it (``bttsim/<rig>/ready/<node>``; the project's nodes do;
#: a foreign subscriber may not) (s).
READY_TIMEOUT_S = 5.0


def wait_for_consumers(session, rig: str, count: int, timeout_s: float, stop: StopFlag, *, data_keys,
                       publish_metadata) -> None:
    """Publish a run's metadata once ``count`` consumers are there to hear it, and return once
    they have it: the start of a run for a simulator or a replay given ``--wait-for N``.

    1. Wait for ``count`` liveliness tokens of other nodes on the rig
       (``bttsim/<rig>/alive/*``; the publisher's own ``sim`` and a router, which consumes
       nothing, aside).
    2. Wait for a subscriber on every key of ``data_keys`` (the OPR and TOA keys): their
       subscriptions reach the publishers a moment after their tokens (through a router,
       later still).
    3. ``publish_metadata()``.
    4. Wait up to :data:`READY_TIMEOUT_S` (at most ``timeout_s``) for ``count`` ``ready``
       tokens (``bttsim/<rig>/ready/*``): each consumer has the metadata, so its
       subscriptions reach the publisher; a warning if they do not all come.

    With ``count`` 0, only ``publish_metadata()``; once ``stop`` is set, nothing more (a
    signal while waiting is a clean stop, not an error). After the run, :func:`wait_for_done` waits
    for the same consumers to have the whole stream.

    Raises
    ------
    BttsimError
        Fewer than ``count`` nodes (unless ``stop`` is set), or a key of ``data_keys`` with no
        subscriber, after ``timeout_s`` seconds.
    """
    if count > 0:
        log.info("waiting for %d node(s) on %s (up to %g s)", count, rig, timeout_s)
        seen = wait_for_liveliness(session, keys.alive_all_key(rig), count, timeout_s, stop, exclude=("sim", "router"))
        log.info("%d other node(s) alive on %s", seen, rig)
        if seen < count and not stop:
            raise BttsimError(f"found {seen} of the {count} node(s) to wait for on {rig} after {timeout_s:g} s: "
                              "check the endpoints (behind a Zenoh router, use client mode: -m client); nodes "
                              "count by name (a second recorder or viewer of the rig: --name)")
        if not wait_for_subscribers(session, data_keys, timeout_s, stop) and not stop:
            raise BttsimError(f"no subscriber on {rig}'s OPR and TOA keys after {timeout_s:g} s")
    if stop:  # stopped while waiting (a signal, --duration): a clean stop, nothing published
        return
    publish_metadata()
    if count > 0:
        ready = wait_for_liveliness(session, keys.ready_all_key(rig), count, min(timeout_s, READY_TIMEOUT_S),
                                    stop)
        if ready < count and not stop:
            log.warning("%d of %d node(s) confirmed the run metadata of %s; publishing anyway", ready, count, rig)


#: The signal that tells a consumer the nodes it follows and saw go are gone for good
#: (:attr:`NodeWatch.final`). ``bttsim run`` starts its nodes with it ignored
#: (:func:`~bttsim_stream.children.die_with_parent`), so one sent before a node has installed
#: its handler is lost, not fatal.
GONE_SIGNAL = signal.SIGUSR1


class NodeWatch:
    """Follows the liveliness tokens ``bttsim/<rig>/alive/<name>`` of the named nodes.

    :meth:`ended` is true once every named node has been seen and is over -- gone, or has
    declared that it published all it will (``bttsim/<rig>/sent/<name>``,
    :func:`~bttsim_stream.bus.keys.sent_key`: a simulator that then waits for its consumers'
    confirmations; :meth:`~bttsim_stream.runtime.NodeContext.samples` counts that only for a
    consumer lacking part of the run) -- or once the first of them is over and ``grace_s``
    passed without the others ever appearing (a node that was never started). Tokens also go
    on SIGKILL, so a crashed node ends a run too.

    :attr:`final` tells whether the nodes that went are gone for good: set by
    :data:`GONE_SIGNAL` (installed here when built in the main thread), which ``bttsim run``
    sends to its consumers once it has reaped a failed simulator or processor. A token gone
    may otherwise be a link that comes back (a router restart), worth the consumer's
    ``--drain-timeout`` of patience; a process reaped is not.
    """

    def __init__(self, session, rig: str, names=("sim",), grace_s: float = 5.0) -> None:
        self.names = tuple(names)
        self.seen: set[str] = set()
        self.gone: set[str] = set()
        self.sent: set[str] = set()
        self.final = False
        self._first: dict[str, float] = {}  # when the first node went ("gone") or sent all ("sent")
        self._grace = grace_s
        self._lock = threading.Lock()
        self._subs = [session.liveliness().declare_subscriber(f"bttsim/{rig}/{kind}/*", on, history=True)
                      for kind, on in (("alive", self._on_sample), ("sent", self._on_sent))]
        self._handles = threading.current_thread() is threading.main_thread()
        if self._handles:
            signal.signal(GONE_SIGNAL, self._on_gone)

    def _on_gone(self, _signum, _frame) -> None:  # a signal handler: no lock (see StopFlag)
        self.final = True

    def _on_sample(self, sample) -> None:
        name = str(sample.key_expr).rsplit("/", 1)[-1]
        if name not in self.names:
            return
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self.seen.add(name)
                self.gone.discard(name)
            elif name in self.seen:
                self.gone.add(name)
                self._first.setdefault("gone", time.monotonic())

    def _on_sent(self, sample) -> None:
        name = str(sample.key_expr).rsplit("/", 1)[-1]
        if name not in self.names:
            return
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self.seen.add(name)
                self.sent.add(name)
                self._first.setdefault("sent", time.monotonic())
            else:  # that instance left (its alive token goes too); one that comes back declares anew
                self.sent.discard(name)

    def ended(self, sent: bool = True) -> bool:
        """True once the named nodes are over (above); ``sent=False``: only once they are gone
        (a node that sent all but still waits for confirmations is not over)."""
        with self._lock:
            over = self.gone | self.sent if sent else set(self.gone)
            if not over:
                return False
            if over >= set(self.names):
                return True
            first = min(t for k, t in self._first.items() if sent or k == "gone")
            return over >= self.seen and time.monotonic() - first > self._grace

    def undeclare(self) -> None:
        """Stop following; :data:`GONE_SIGNAL` is ignored again from here on. Python resets
        its own signal handlers to the default action (terminate) when the interpreter exits,
        and ``bttsim run`` may send the signal just then, once the last node this one follows
        is reaped: a node that did its work would die of it."""
        try:
            for sub in self._subs:
                sub.undeclare()
        finally:
            if self._handles and signal.getsignal(GONE_SIGNAL) == self._on_gone:  # still ours
                signal.signal(GONE_SIGNAL, signal.SIG_IGN)

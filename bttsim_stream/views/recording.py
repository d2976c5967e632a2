"""Views of an MCAP recording, logged in one pass (:func:`log_recording`)."""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import rerun as rr

from ..bus import keys
from ..bus.recording import RecordingScan
from ..defaults import DEFAULT_BIND, DEFAULT_GRPC_PORT, DEFAULT_WEB_PORT
from ..errors import BttsimError
from ..process.options import ProcessOptions, engine_orders_of
from .blueprint import build_blueprint
from .live import LiveViews, MessageDecoder
from .rotor import DEFAULT_EXAGGERATION
from .signal import signal_stride
from .sinks import ViewSinks, finish_files, open_recording

__all__ = ["FLUSH_EVERY", "ViewSession", "log_recording"]

log = logging.getLogger("bttsim.views")

#: Messages read between two flushes of the views to the stream (memory: this many decoded
#: messages and their Rerun columns, whatever the recording's length).
FLUSH_EVERY = 4096


@dataclass(frozen=True, slots=True, eq=False)
class _Survey:
    """What a first pass over a recording says (before any output is opened)."""

    meta: object
    engine_orders: list
    max_probe: int
    has_signal: bool
    stride: int
    signal_key: str | None


def _decoded(messages, decoder: MessageDecoder, stride: int, signal_key: str | None):
    """The decoded messages that the views show (raw signals: one probe, every stride-th
    revolution; a signal key's sequence number is its revolution count)."""
    for m in messages:
        if "/signal/" in m.key and (m.key != signal_key or m.seq % stride):
            continue
        if (msg := decoder.decode(m.key, m.payload)) is not None:
            yield msg


def _survey(recording_path, signal_probe: int, rig: str | None) -> _Survey:
    """First pass over a recording, as a stream: the run metadata, the fitted engine orders
    (in order of appearance), and every message decoded once, so that one that does not
    decode is refused before anything is written.

    Raises
    ------
    BttsimError
        Unreadable recording, or a message in it that does not decode.
    """
    meta = None
    decoder = MessageDecoder()
    for m in _scan(recording_path, rig):  # the metadata comes first: the scan stops there
        if m.key.endswith("/meta") and (d := decoder.decode(m.key, m.payload)) is not None:
            meta = d.decoded.body
            break
    stride = signal_stride(meta.n_revolutions) if meta is not None else 1
    signal_key = keys.signal_key(meta.rig, signal_probe) if meta is not None else None
    decoder = MessageDecoder(log_bad=False)  # a bad message is refused below, in one line
    eos: dict[int, None] = {}
    max_probe, has_signal = 0, False
    scan = RecordingScan(recording_path)
    for m in _scan(scan, rig):
        has_signal = has_signal or "/signal/" in m.key
        for msg in _decoded((m,), decoder, stride, signal_key):
            if msg.kind == "fit":
                eos.setdefault(int(msg.decoded.body.engine_order), None)
            elif msg.kind in ("toa", "tw"):
                max_probe = max(max_probe, int(msg.decoded.body.probe))
    if decoder.bad:  # a file is not a live bus: a message that does not decode makes it corrupt
        more = f" ({decoder.bad - 1} more refused)" if decoder.bad > 1 else ""
        raise BttsimError(f"{scan.path}: {decoder.first_bad}{more}")
    return _Survey(meta=meta, engine_orders=list(eos), max_probe=max_probe, has_signal=has_signal, stride=stride,
                   signal_key=signal_key)


def _scan(recording, rig: str | None):
    """The messages of a recording (a path or a :class:`RecordingScan`), of one rig's keys if
    ``rig`` is given."""
    scan = recording if isinstance(recording, RecordingScan) else RecordingScan(recording)
    return scan if rig is None else keys.of_rig(scan, rig)


@dataclass(eq=False)
class ViewSession:
    """The result of :func:`log_recording`: the stream (keep it alive while serving), its
    sinks and counts.

    Attributes
    ----------
    recording : rerun.RecordingStream
    sinks : ViewSinks
    stats : dict
        Message counts (``messages``, ``revolutions``, ``fits``, ``tw``, ``truth``, ...;
        ``truncated`` when the file was cut).
    elapsed_s : float
        Wall time of reading, decoding and logging.
    """

    recording: rr.RecordingStream
    sinks: ViewSinks
    stats: dict = field(default_factory=dict)
    elapsed_s: float = 0.0

    def close(self) -> None:
        """Flush and disconnect every sink (finalises the ``.rrd``, stops the hosted servers)."""
        self.recording.flush()
        self.recording.disconnect()
        self.sinks.close()


def log_recording(recording_path, rrd_path=None, *, serve_web: bool = False, web_port: int = DEFAULT_WEB_PORT,
                  grpc_port: int = DEFAULT_GRPC_PORT, bind: str = DEFAULT_BIND, grpc_url: str | None = None,
                  blades: Sequence[int] | None = None, exaggeration: float = DEFAULT_EXAGGERATION,
                  signal_probe: int = 0, rig: str | None = None) -> ViewSession:
    """Log every view of an MCAP recording to Rerun in one pass.

    Parameters
    ----------
    recording_path : path
        An MCAP recording of the bus (``bttsim simulate``, the recorder node, ``bttsim run``).
    rrd_path : path, optional
        Write an ``.rrd`` file (finalised before returning, also while serving).
    serve_web : bool
        Host the web viewer on ``bind:web_port`` (gRPC server on ``bind:grpc_port``); the
        URL is in ``session.sinks.web_url``. Keep the process (and the returned session)
        alive while it is viewed, then ``session.close()``.
    bind : str
        IP address of both servers (default 127.0.0.1: this machine only).
    grpc_url : str, optional
        Also stream to a running viewer.
    blades : sequence of int, optional
        Blades of the raw-displacement views (default 0 and ``n_blades // 2``).
    exaggeration : float
        Tip deflection gain of the rotor view.
    signal_probe : int
        Probe of the raw signal view (when the recording holds raw signals).
    rig : str, optional
        Show only this rig's messages (a recording of several rigs); default every message.

    Returns
    -------
    ViewSession

    Raises
    ------
    BttsimError
        Unreadable recording, a message in it that does not decode (corrupt, or a value out
        of range: nothing is written), or no output requested.
    """
    t_start = time.perf_counter()
    survey = _survey(recording_path, signal_probe, rig)
    meta, decoder = survey.meta, MessageDecoder(log_bad=False)
    eos = survey.engine_orders or (list(engine_orders_of(meta, ProcessOptions())) if meta else [8])
    n_probes = meta.n_probes if meta is not None else 1 + survey.max_probe
    blueprint = build_blueprint(n_probes, n_blades=meta.n_blades if meta else None, engine_orders=eos, live=False,
                                signal_probe=signal_probe if survey.has_signal else None)
    rec, sinks = open_recording(rrd_path=rrd_path, grpc_url=grpc_url, serve_web=serve_web, web_port=web_port,
                                grpc_port=grpc_port, bind=bind, blueprint=blueprint,
                                recording_id=meta.run_id if meta is not None else None)
    views = LiveViews(rec, live=False, blades=blades, exaggeration=exaggeration, send_blueprint=False,
                      engine_orders=eos, decoder=decoder, signal_probe=signal_probe)
    scan = RecordingScan(recording_path)
    for i, msg in enumerate(_decoded(_scan(scan, rig), decoder, survey.stride, survey.signal_key)):
        views.feed_decoded(msg)
        if i % FLUSH_EVERY == FLUSH_EVERY - 1:  # bounded: what is read is logged and dropped
            views.flush()
            rec.flush()
    views.close()
    session = ViewSession(recording=rec, sinks=sinks, stats=views.stats, elapsed_s=time.perf_counter() - t_start)
    if scan.truncated:
        session.stats["truncated"] = True
    if serve_web:
        finish_files(rec)  # the .rrd is complete while the page is served
    else:
        session.close()
    log.info("logged %d messages (%d revolutions) in %.1f s", session.stats["messages"],
             session.stats["revolutions"], session.elapsed_s)
    return session

"""Node status: each node's state and final statistics, on the bus or in a status file.

Key ``bttsim/<rig>/status/<node>`` (:func:`~bttsim_stream.bus.keys.status_key`), one JSON
message type, ``bttsim.status.v1`` (UTF-8, at most :data:`MAX_STATUS_BYTES`)::

    {"schema": "bttsim.status.v1", "node": "recorder", "state": "done", "seq": 2,
     "url": "", "stats": {"messages": 12345, "gaps": 0, "complete": true, ...}}

``state`` is one of :data:`STATES`: ``starting`` (the node's subscriptions are declared and
its ``alive`` token is out), ``ready`` (it has the run metadata), ``done`` (its work is over:
``stats`` holds its final statistics) and ``serving`` (the viewer's views are complete and it
only serves the web viewer at ``url``). A node numbers its messages from 0 (``seq``); a reader
keeps the highest. ``url`` is the web viewer's address ("" when none); ``stats`` a JSON object
(``{}`` until ``done``). Like every sample of the bus, a status sample carries the 16-byte
attachment (``seq`` and the wall-clock time in ns).

The same message can be written to a status file (:func:`write_status_file`: a temporary file
renamed over the target, so a reader never sees half of one) for a reader that no bus reaches.
Status is untrusted input like every message on the bus: :func:`decode_status` checks the
size, the fields and their types, and that the node named in the message is the one in the
key (and one the reader expects). Status keys are never recorded (the recorder and the viewer
skip them), so a live recording stays byte-identical with ``bttsim simulate``.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import BttsimError
from . import keys

__all__ = ["SCHEMA", "STATES", "FINAL_STATES", "MAX_STATUS_BYTES", "NodeStatus", "encode_status", "decode_status",
           "write_status_file", "read_status_file", "StatusBoard"]

#: The ``schema`` field of every status message.
SCHEMA = "bttsim.status.v1"
#: A node's states, in the order it goes through them (``serving``: the viewer with ``--web`` only).
STATES = ("starting", "ready", "done", "serving")
#: States whose message carries the node's final statistics.
FINAL_STATES = ("done", "serving")
#: Largest status message accepted (bytes): the recorder's statistics of a run with a few
#: dozen keys take a few kB.
MAX_STATUS_BYTES = 256 * 1024
_MAX_URL = 2048
_MAX_SEQ = 1 << 62
_FIELDS = {"schema", "node", "state", "seq", "url", "stats"}
_NAME_RE = re.compile(r"[A-Za-z0-9_-]+")


@dataclass(frozen=True, slots=True)
class NodeStatus:
    """One status message.

    Attributes
    ----------
    node : str
        The node's name (``[A-Za-z0-9_-]+``), the last chunk of its status key.
    state : str
        One of :data:`STATES`.
    seq : int
        The message's number, from 0 per node.
    url : str
        The web viewer's address, "" when none.
    stats : dict
        The node's final statistics (a JSON object), ``{}`` before ``done``.
    """

    node: str
    state: str
    seq: int
    url: str = ""
    stats: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.node, str) or not _NAME_RE.fullmatch(self.node):
            raise BttsimError(f"status: invalid node name {str(self.node)[:40]!r}")
        if self.state not in STATES:
            raise BttsimError(f"status of {self.node}: state {str(self.state)[:40]!r} "
                              f"is not one of {', '.join(STATES)}")
        if isinstance(self.seq, bool) or not isinstance(self.seq, int) or not 0 <= self.seq < _MAX_SEQ:
            raise BttsimError(f"status of {self.node}: seq {str(self.seq)[:40]!r} is not a non-negative integer")
        if not isinstance(self.url, str) or len(self.url) > _MAX_URL:
            raise BttsimError(f"status of {self.node}: url is not a string of at most {_MAX_URL} characters")
        if not isinstance(self.stats, dict):
            raise BttsimError(f"status of {self.node}: stats is not a JSON object")

    @property
    def final(self) -> bool:
        """Does this message carry the node's final statistics?"""
        return self.state in FINAL_STATES


def encode_status(status: NodeStatus) -> bytes:
    """The JSON bytes of ``status``.

    Raises
    ------
    BttsimError
        If the message would exceed :data:`MAX_STATUS_BYTES`.
    """
    data = json.dumps({"schema": SCHEMA, "node": status.node, "state": status.state, "seq": status.seq,
                       "url": status.url, "stats": status.stats}, separators=(",", ":")).encode()
    if len(data) > MAX_STATUS_BYTES:
        raise BttsimError(f"status of {status.node}: {len(data)} bytes (at most {MAX_STATUS_BYTES})")
    return data


def decode_status(payload: bytes, key: str | None = None, *, nodes=None) -> NodeStatus:
    """Decode an untrusted status message.

    Parameters
    ----------
    payload : bytes
    key : str, optional
        The key it came on: the node it names must be the message's.
    nodes : iterable of str, optional
        The node names accepted (None: any).

    Raises
    ------
    BttsimError
        Too large, not UTF-8 JSON, another schema, a missing, extra or mistyped field, a node
        other than the key's or not among ``nodes``.
    """
    if len(payload) > MAX_STATUS_BYTES:
        raise BttsimError(f"status: {len(payload)} bytes (at most {MAX_STATUS_BYTES})")
    try:
        msg = json.loads(bytes(payload).decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise BttsimError(f"status: not UTF-8 JSON ({type(exc).__name__})") from None
    if not isinstance(msg, dict) or set(msg) != _FIELDS or msg["schema"] != SCHEMA:
        raise BttsimError(f"status: not a {SCHEMA} message")
    status = NodeStatus(node=msg["node"], state=msg["state"], seq=msg["seq"], url=msg["url"], stats=msg["stats"])
    if key is not None:
        info = keys.parse_key(key)
        if info.kind != "status" or info.node != status.node:
            raise BttsimError(f"status of {status.node} on {key}")
    if nodes is not None and status.node not in nodes:
        raise BttsimError(f"status of an unexpected node {status.node!r}")
    return status


def write_status_file(path, status: NodeStatus) -> None:
    """Write ``status`` to ``path`` atomically (a temporary file beside it, then renamed)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_bytes(encode_status(status))
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def read_status_file(path, node: str) -> NodeStatus | None:
    """The status in the file ``path`` if it holds one of ``node`` (None: no file, or not a
    valid status of that node)."""
    try:
        with open(path, "rb") as f:
            data = f.read(MAX_STATUS_BYTES + 1)
        return decode_status(data, nodes=(node,))
    except (OSError, BttsimError):
        return None


class StatusBoard:
    """The latest status of each expected node, from the bus (and status files).

    Subscribes to ``bttsim/<rig>/status/*`` (with the publishers' cached history, so a status
    sent before the board was declared still arrives) and keeps, per node named in ``nodes``,
    the message with the highest ``seq``; anything else (another name, a malformed message) is
    counted in :attr:`rejected` and dropped.

    Parameters
    ----------
    session : zenoh.Session
    rig : str
    nodes : iterable of str
        The node names whose status is accepted.
    files : dict of {str: path}, optional
        Each node's status file, read when the bus has not delivered its final status.
    """

    def __init__(self, session, rig: str, nodes, files: dict | None = None) -> None:
        from .session import declare_subscriber  # session imports zenoh: not for the codec users

        self.nodes = tuple(nodes)
        self.files = dict(files or {})
        self.rejected = 0
        self._latest: dict[str, NodeStatus] = {}
        self._lock = threading.Lock()
        self._sub = declare_subscriber(session, keys.status_all_key(rig), self._on_sample, history=True)

    def _on_sample(self, sample) -> None:
        try:
            status = decode_status(sample.payload.to_bytes(), str(sample.key_expr), nodes=self.nodes)
        except BttsimError:
            with self._lock:
                self.rejected += 1
            return
        self.offer(status)

    def offer(self, status: NodeStatus) -> None:
        """Keep ``status`` if it is newer than what is known of its node."""
        with self._lock:
            known = self._latest.get(status.node)
            if known is None or status.seq > known.seq:
                self._latest[status.node] = status

    def get(self, node: str) -> NodeStatus | None:
        """The latest status of ``node`` seen on the bus (None: none yet)."""
        with self._lock:
            return self._latest.get(node)

    def final(self, node: str, wait_s: float = 0.0) -> NodeStatus | None:
        """The status with ``node``'s final statistics: from the bus, else from its status file
        (the node writes it before it publishes), else from the bus after up to ``wait_s``; None
        if none has it (the node died first)."""
        deadline = time.monotonic() + wait_s
        path = self.files.get(node)
        while True:
            status = self.get(node)
            if status is not None and status.final:
                return status
            status = read_status_file(path, node) if path is not None else None
            if status is not None and status.final:
                self.offer(status)
                return status
            if time.monotonic() >= deadline:
                return None
            time.sleep(0.05)

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self._sub.undeclare()

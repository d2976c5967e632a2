"""What the codec modules share: the header and decoded-message types, the decoders' limits,
the wire helpers and the schema helpers (:mod:`.codec` and :mod:`.codec_results` build on it).

Together these three modules are the only users of the generated protobuf code.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from google.protobuf import descriptor_pb2
from google.protobuf.message import DecodeError

from ..defaults import MAX_REVOLUTIONS
from ..errors import BttsimError
from . import keys as _keys
from ._gen.bttsim.v1 import bttsim_pb2 as _pb


__all__ = ["MAX_PAYLOAD_BYTES", "PROTO_FILE", "Header", "Decoded", "log_time_ns", "schema_name_for",
           "file_descriptor_set",
           # the codec modules' shared helpers
           "MAX_NS", "as_array", "as_vector", "check_len", "check_probe_key", "corrupt_error", "fill_header",
           "header_of", "packed_doubles", "parse_payload", "serialize"]

#: Largest payload a decoder accepts, bytes.
MAX_PAYLOAD_BYTES = 64 * 1024 * 1024
#: Name of the schema file inside the descriptor (and path under ``schemas/``).
PROTO_FILE = "bttsim/v1/bttsim.proto"
_PACKAGE = "bttsim.v1"
MAX_NS = (1 << 63) - 1


@dataclass(frozen=True, slots=True)
class Header:
    """The header every message carries.

    Attributes
    ----------
    run_id : str
    seq : int
        Per-publisher, per-key sequence number (0, 1, 2, ...).
    revolution : int
        Revolution index, -1 where it does not apply.
    t_s : float
        Simulated time the message refers to, s.
    """

    run_id: str
    seq: int
    revolution: int = -1
    t_s: float = 0.0


@dataclass(frozen=True, slots=True)
class Decoded:
    """A decoded message: its header and its body (the library dataclass of its type)."""

    header: Header
    body: Any


# --------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------


def log_time_ns(t_s: float) -> int:
    """MCAP log time of a message: ``round(t_s * 1e9)`` clamped to ``[0, 2**63 - 1]``."""
    t = float(t_s)
    if not math.isfinite(t):
        return 0 if t != math.inf else MAX_NS
    return min(max(int(round(t * 1e9)), 0), MAX_NS)


def fill_header(h, run_id: str, seq: int, revolution: int, t_s: float) -> None:
    h.run_id = run_id
    h.seq = seq
    h.revolution = revolution
    h.t_s = t_s


def serialize(msg) -> bytes:
    return msg.SerializeToString(deterministic=True)


def as_vector(values, name: str, n: int | None = None, dtype=float) -> np.ndarray:
    arr = np.asarray(values, dtype=dtype)
    if arr.ndim != 1 or (n is not None and arr.size != n):
        want = f"({n},)" if n is not None else "1-D"
        raise ValueError(f"{name}: expected shape {want}, got {arr.shape}")
    return arr


def parse_payload(cls, payload, where: str | None):
    name = cls.DESCRIPTOR.name
    where = where or cls.DESCRIPTOR.full_name
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        raise BttsimError(f"{where}: {name} payload must be bytes, got {type(payload).__name__}")
    size = len(payload)
    if size > MAX_PAYLOAD_BYTES:
        raise BttsimError(f"{where}: {name} payload of {size} bytes exceeds the "
                          f"{MAX_PAYLOAD_BYTES} byte limit")
    msg = cls()
    try:
        msg.ParseFromString(bytes(payload))
    except (DecodeError, ValueError, RuntimeError) as exc:
        text = " ".join(str(exc).split()) or type(exc).__name__
        raise BttsimError(f"{where}: corrupt {name} ({text})") from None
    size = msg.ByteSize()
    msg.DiscardUnknownFields()
    if msg.ByteSize() != size:  # another message type's payload on this key parses, with fields it lacks
        raise BttsimError(f"{where}: corrupt {name} (fields that are not in its schema)")
    if not msg.HasField("header"):
        raise BttsimError(f"{where}: corrupt {name} (no header)")
    if not math.isfinite(msg.header.t_s):
        raise BttsimError(f"{where}: corrupt {name} (header time {msg.header.t_s!r} is not finite)")
    if not -1 <= msg.header.revolution <= MAX_REVOLUTIONS:
        raise BttsimError(f"{where}: corrupt {name} (header revolution {msg.header.revolution} "
                          f"out of [-1, {MAX_REVOLUTIONS}])")
    return msg, where


def corrupt_error(where: str, msg, problem: str) -> BttsimError:
    return BttsimError(f"{where}: corrupt {msg.DESCRIPTOR.name} ({problem})")


def header_of(h) -> Header:
    return Header(h.run_id, int(h.seq), int(h.revolution), float(h.t_s))  # positional: a hot path


def as_array(values, dtype=np.float64) -> np.ndarray:
    """A 1-D array of a repeated protobuf field (or a list): ``np.fromiter`` with the length
    known, about 4x faster than ``np.array`` on protobuf's containers (same values)."""
    n = len(values)
    return np.fromiter(values, dtype=dtype, count=n) if n else np.empty(0, dtype)


def packed_doubles(payload: bytes, numbers: frozenset) -> dict | None:
    """The top-level repeated double fields ``numbers`` of a message that parsed, read
    straight from its bytes (``{number: array}``, absent fields left out): ``np.frombuffer``
    instead of protobuf's containers, element by element. None when a field of ``numbers``
    is not one packed run (unpacked or split: valid protobuf, read the slow way then)."""
    out: dict = {}
    i, n = 0, len(payload)
    while i < n:
        key, i = _varint_at(payload, i)
        num, wire = key >> 3, key & 7
        if wire == 2:
            size, i = _varint_at(payload, i)
            if num in numbers:
                if num in out or size % 8:
                    return None
                out[num] = np.frombuffer(payload, "<f8", size // 8, i).astype(np.float64)
            i += size
        elif num in numbers:
            return None
        elif wire == 0:
            _, i = _varint_at(payload, i)
        elif wire in (1, 5):
            i += 8 if wire == 1 else 4
        else:
            return None
    return out


def _varint_at(data: bytes, i: int) -> tuple[int, int]:
    """The varint at ``data[i]`` and the index after it."""
    b = data[i]
    if b < 0x80:
        return b, i + 1
    value, shift = 0, 0
    while True:
        b = data[i]
        i += 1
        value |= (b & 0x7F) << shift
        shift += 7
        if b < 0x80:
            return value, i


def check_len(where: str, msg, field: str, n: int, shape: str) -> None:
    got = len(getattr(msg, field))
    if got != n:
        raise corrupt_error(where, msg, f"{field} has {got} values, expected {n} for shape {shape}")


def check_probe_key(where: str, msg, key: str | None, kind: str) -> None:
    if key is None:
        return
    try:
        info = _keys.parse_key(key)
    except BttsimError:
        return
    if info.kind == kind and info.probe != msg.probe:
        raise corrupt_error(where, msg, f"probe {msg.probe} on the key of probe {info.probe}")


# --------------------------------------------------------------------------------------
# Schema helpers
# --------------------------------------------------------------------------------------


def schema_name_for(message_type: str) -> str:
    """The MCAP schema name (full protobuf name) of a message type.

    Parameters
    ----------
    message_type : str
        ``"ToaBatch"`` or ``"bttsim.v1.ToaBatch"``.

    Raises
    ------
    BttsimError
        If the schema has no such message.
    """
    short = message_type.removeprefix(_PACKAGE + ".")
    desc = _pb.DESCRIPTOR.message_types_by_name.get(short)
    if desc is None:
        raise BttsimError(f"unknown message type {message_type!r}")
    return desc.full_name


@functools.lru_cache(maxsize=1)
def file_descriptor_set() -> bytes:
    """The serialized ``FileDescriptorSet`` of ``bttsim/v1/bttsim.proto`` and its dependencies.

    This is the MCAP schema data of every channel (schema encoding ``"protobuf"``).
    """
    fds = descriptor_pb2.FileDescriptorSet()
    seen: set[str] = set()

    def add(fd) -> None:
        if fd.name in seen:
            return
        seen.add(fd.name)
        for dep in fd.dependencies:
            add(dep)
        fd.CopyToProto(fds.file.add())

    add(_pb.DESCRIPTOR)
    return fds.SerializeToString(deterministic=True)

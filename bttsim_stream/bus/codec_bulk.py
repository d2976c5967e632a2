"""The acquisition stream's messages many at once: the protobuf wire format written with
numpy, vectorised over the messages of a batch (the same bytes as the one-message encoders of
:mod:`.codec`, which re-exports what is public here)."""

from __future__ import annotations

import functools
import struct

import numpy as np
from google.protobuf import descriptor_pb2

from ._gen.bttsim.v1 import bttsim_pb2 as _pb
from .codec_base import MAX_NS

__all__ = ["is_repeated", "log_times_ns", "encode_opr_batch", "encode_toa_batches", "encode_fits", "encode_probe_waves",
           "assemble",
           "field_tag", "header_bytes", "header_parts", "le_doubles", "packed_field", "packed_varints", "scalar_field",
           "varint_bytes"]

# --------------------------------------------------------------------------------------
# Acquisition stream, many messages at once (the same bytes as the encoders above)
# --------------------------------------------------------------------------------------
#
# The protobuf wire format is written directly with numpy, vectorised over the messages of a
# batch: a message is a sequence of parts (tag, varint, fixed 8-byte value, packed array),
# each part a (n_messages, width) byte matrix with a length per message (0 for a proto3
# field at its default value, which protobuf leaves out). Field numbers come from the
# generated descriptors; tests compare every byte with ``SerializeToString``.


@functools.lru_cache(maxsize=None)
def _repeated_fields() -> frozenset[tuple[str, str]]:
    """(message, field) names of every repeated field in the schema.

    Read from the schema's own ``FileDescriptorProto`` (public in every protobuf release we
    support): the runtime descriptors changed between releases (protobuf 7 removed
    ``FieldDescriptor.label``; ``is_repeated`` appeared only in 6.x).
    """
    fdp = descriptor_pb2.FileDescriptorProto.FromString(_pb.DESCRIPTOR.serialized_pb)
    repeated = descriptor_pb2.FieldDescriptorProto.LABEL_REPEATED
    return frozenset((m.name, f.name) for m in fdp.message_type for f in m.field if f.label == repeated)


def is_repeated(field) -> bool:
    """True if the schema's field descriptor ``field`` is a repeated field (any protobuf release)."""
    return (field.containing_type.name, field.name) in _repeated_fields()


@functools.lru_cache(maxsize=None)
def _tag_of(message_name: str, field: str) -> int:
    f = getattr(_pb, message_name).DESCRIPTOR.fields_by_name[field]
    wire = 2 if (f.type in (f.TYPE_MESSAGE, f.TYPE_STRING, f.TYPE_BYTES) or is_repeated(f)) else (
        1 if f.type == f.TYPE_DOUBLE else 0)
    return (f.number << 3) | wire


def field_tag(message, field: str) -> int:
    """The key byte (field number and wire type) of a field (fields 1..15: one byte)."""
    return _tag_of(message.DESCRIPTOR.name, field)


@functools.lru_cache(maxsize=256)
def _const_rows(data: bytes, n: int) -> tuple[np.ndarray, np.ndarray]:
    b = np.broadcast_to(np.frombuffer(data, np.uint8), (n, len(data)))
    lens = np.full(n, len(data), np.int64)
    lens.flags.writeable = False
    return b, lens


def _const(n: int, data: bytes, present=None):
    """A part holding the same bytes in every message (or only where ``present``)."""
    b, lens = _const_rows(data, n)
    return (b, lens) if present is None else (b, np.where(present, len(data), 0))


def _varints(values, present=None):
    """Varints of integers (two's complement for negatives, as protobuf's int64): a part."""
    u = np.ascontiguousarray(np.asarray(values).astype(np.int64)).view(np.uint64)
    top = int(u.max()) if u.size else 0
    n_bytes = max(1, (top.bit_length() + 6) // 7)
    out = np.empty(u.shape + (n_bytes,), np.uint8)
    lens = np.ones(u.shape, np.int64)
    for k in range(n_bytes):
        out[..., k] = (u & np.uint64(0x7F)).astype(np.uint8)
        u = u >> np.uint64(7)
        if k + 1 < n_bytes:
            more = u != 0
            out[..., k] |= np.uint8(0x80) * more.astype(np.uint8)
            lens += more
    if present is not None:
        lens = np.where(present, lens, 0)
    return out, lens


def scalar_field(tag: int, values, kind: str):
    """A proto3 scalar field, left out at its default (zero bits): two parts (tag, value)."""
    if kind == "double":
        v = np.ascontiguousarray(np.asarray(values, dtype="<f8"))
        present = v.view(np.uint64) != 0
        value = (v.view(np.uint8).reshape(-1, 8), np.where(present, 8, 0))
    else:
        v = np.asarray(values, dtype=np.int64)
        present = v != 0
        value = _varints(v, present)
    return [_const(v.shape[0], bytes([tag]), present), value]


def packed_field(tag: int, data: np.ndarray, lens=None):
    """A packed repeated field: tag, byte length, data (n, w) (``lens`` per message, or w)."""
    n, w = data.shape
    lens = np.full(n, w, np.int64) if lens is None else lens
    present = lens > 0
    return [_const(n, bytes([tag]), present), _varints(lens, present), (data, lens)]


def packed_varints(tag: int, values: np.ndarray):
    """A packed repeated int64 field of the rows of ``values`` (n, k)."""
    b, l = _varints(values)  # (n, k, w), (n, k)
    n, k = l.shape
    w = b.shape[-1]
    start = np.cumsum(l, axis=1) - l
    out = np.zeros((n, w * k), np.uint8)
    j = np.arange(w)
    mask = j[None, None, :] < l[..., None]
    rows = np.broadcast_to(np.arange(n)[:, None, None], mask.shape)
    out[rows[mask], (start[..., None] + j)[mask]] = b[mask]
    return packed_field(tag, out, l.sum(axis=1))


def header_parts(run_id: str, seq, revolution, t_s):
    n = len(seq)
    rid = run_id.encode()
    parts = []
    if rid:
        parts += [_const(n, bytes([field_tag(_pb.Header, "run_id")])), _varints(np.full(n, len(rid))), _const(n, rid)]
    parts += scalar_field(field_tag(_pb.Header, "seq"), seq, "int")
    parts += scalar_field(field_tag(_pb.Header, "revolution"), revolution, "int")
    parts += scalar_field(field_tag(_pb.Header, "t_s"), t_s, "double")
    hlen = np.sum([l for _, l in parts], axis=0)
    return [_const(n, bytes([0x0A])), _varints(hlen)] + parts  # field 1: the header


def assemble(parts) -> list[bytes]:
    """Concatenate each message's parts; one ``bytes`` per message.

    Messages whose parts all have the same lengths (nearly always all of them: only a
    varint crossing a power of 128 or a field at its default changes a length) are laid out
    together as the rows of one byte matrix, a column range per part."""
    lens = np.stack([l for _, l in parts], axis=1)  # (n, P)
    n = lens.shape[0]
    same = (lens == lens[0]).all(axis=1) if n else np.zeros(0, bool)
    if same.all():
        groups = [(None, lens[0])] if n else []
    else:  # a few layouts (e.g. probe 0, whose index protobuf leaves out)
        groups = []
        rest = np.arange(n)
        while rest.size:
            eq = (lens[rest] == lens[rest[0]]).all(axis=1)
            groups.append((rest[eq], lens[rest[0]]))
            rest = rest[~eq]
    out: list = [None] * n
    for rows, L in groups:
        m = n if rows is None else rows.size
        width = int(L.sum())
        mat = np.empty((m, width), np.uint8)
        col = 0
        for (b, _), w in zip(parts, L.tolist()):
            if w:
                mat[:, col:col + w] = b[:, :w] if rows is None else b[rows, :w]
                col += w
        data = mat.tobytes()
        if rows is None:
            return [data[k * width:(k + 1) * width] for k in range(m)]
        for k, i in enumerate(rows.tolist()):
            out[i] = data[k * width:(k + 1) * width]
    return out


def le_doubles(a: np.ndarray) -> np.ndarray:
    """Rows of float64 values as little-endian bytes, (n, 8 k)."""
    a = np.ascontiguousarray(a, dtype="<f8")
    return a.view(np.uint8).reshape(a.shape[0], -1)


def log_times_ns(t_s: np.ndarray) -> np.ndarray:
    """:func:`log_time_ns` of many times (int64)."""
    t = np.asarray(t_s, dtype=np.float64)
    with np.errstate(invalid="ignore", over="ignore"):
        ns = np.rint(t * 1e9)  # round half to even, as round()
    out = np.zeros(t.shape, np.int64)
    ok = (ns > 0) & (ns < 2.0 ** 63)
    out[ok] = ns[ok].astype(np.int64)
    out[ns >= 2.0 ** 63] = MAX_NS  # also +inf; NaN and -inf stay 0
    return out


def encode_opr_batch(run_id: str, seq, revolution, t_s, opr_s, opr_ticks=None) -> list[bytes]:
    """:func:`encode_opr` of many pulses at once (the same bytes).

    Parameters
    ----------
    run_id : str
    seq, revolution : array_like of int, shape (n,)
    t_s, opr_s : array_like of float, shape (n,)
        Header times and OPR times.
    opr_ticks : array_like of int, shape (n,), optional
    """
    seq = np.asarray(seq)
    n = seq.size
    parts = header_parts(run_id, seq, revolution, t_s)
    parts += scalar_field(field_tag(_pb.Opr, "opr_s"), opr_s, "double")
    if opr_ticks is not None:
        parts += scalar_field(field_tag(_pb.Opr, "opr_ticks"), opr_ticks, "int")
        parts.append(_const(n, bytes([field_tag(_pb.Opr, "has_ticks"), 1])))
    return assemble(parts)


def encode_toa_batches(run_id: str, seq, revolution, t_s, probe, toa_s, toa_ticks=None,
                       extra=None) -> list[bytes]:
    """:func:`encode_toa_batch` of many (revolution, probe) batches at once (the same bytes).

    Parameters
    ----------
    seq, revolution, probe : array_like of int, shape (n,)
    t_s : array_like of float, shape (n,)
        Header times.
    toa_s : ndarray, shape (n, n_blades)
    toa_ticks : ndarray of int, shape (n, n_blades), optional
    extra : (message, extra_toa_s, extra_toa_ticks or None), optional
        Later edges of double pulses: the message index (0..n-1, non-decreasing) of each,
        its time and its ticks. Fields 6 and 7 are the last of ``ToaBatch``: appended to the
        messages that have any, they give the bytes of a deterministic serialization.
    """
    seq = np.asarray(seq)
    n = seq.size
    parts = header_parts(run_id, seq, revolution, t_s)
    parts += scalar_field(field_tag(_pb.ToaBatch, "probe"), probe, "int")
    parts += packed_field(field_tag(_pb.ToaBatch, "toa_s"), le_doubles(np.asarray(toa_s).reshape(n, -1)))
    if toa_ticks is not None:
        parts += packed_varints(field_tag(_pb.ToaBatch, "toa_ticks"), np.asarray(toa_ticks).reshape(n, -1))
        parts.append(_const(n, bytes([field_tag(_pb.ToaBatch, "has_ticks"), 1])))
    out = assemble(parts)
    if extra is not None and len(extra[0]):
        msg, times, ticks = (np.asarray(extra[0], np.int64), np.asarray(extra[1], np.float64),
                             None if extra[2] is None or toa_ticks is None else np.asarray(extra[2], np.int64))
        bounds = np.searchsorted(msg, np.arange(n + 1))
        tag_s, tag_k = field_tag(_pb.ToaBatch, "extra_toa_s"), field_tag(_pb.ToaBatch, "extra_toa_ticks")
        for i in np.flatnonzero(np.diff(bounds)).tolist():
            lo, hi = bounds[i], bounds[i + 1]
            body = times[lo:hi].astype("<f8").tobytes()
            tail = varint_bytes(tag_s) + varint_bytes(len(body)) + body
            if ticks is not None:
                v, lens = _varints(ticks[lo:hi])
                body = v[np.arange(v.shape[1]) < lens[:, None]].tobytes()  # each varint's own bytes, in order
                tail += varint_bytes(tag_k) + varint_bytes(len(body)) + body
            out[i] = out[i] + tail
    return out


def varint_bytes(value: int) -> bytes:
    """One protobuf varint (``value`` >= 0)."""
    if 0 <= value < 128:  # one byte (tags, lengths, small numbers): from a table
        return _ONE_BYTE[value]
    out = bytearray()
    while True:
        b, value = value & 0x7F, value >> 7
        out.append(b | (0x80 if value else 0))
        if not value:
            return bytes(out)


_ONE_BYTE = tuple(bytes((v,)) for v in range(128))
_MASK64 = (1 << 64) - 1
_F8 = struct.Struct("<d")
_ZERO8 = bytes(8)


def _varint_field(tag: int, value: int) -> bytes:
    """An integer field (``int32``/``int64``: a negative one as its 64-bit two's complement, ten
    bytes; as protobuf), left out at 0."""
    return varint_bytes(tag) + varint_bytes(int(value) & _MASK64) if value else b""


def header_bytes(run_id: str, seq: int, revolution: int, t_s: float) -> bytes:
    """The ``header`` field (field 1) of one message, as protobuf writes it (the header is set,
    so present even when every field is at its default; those are left out)."""
    rid, tag_seq, tag_rev, tag_t = _header_parts(run_id)
    t = _F8.pack(float(t_s))
    body = b"".join((
        rid,
        _varint_field(tag_seq, seq),
        _varint_field(tag_rev, revolution),
        varint_bytes(tag_t) + t if t != _ZERO8 else b""))
    return b"\x0a" + varint_bytes(len(body)) + body


@functools.lru_cache(maxsize=16)
def _header_parts(run_id: str) -> tuple[bytes, int, int, int]:
    """What every header of a run shares: its ``run_id`` field's bytes (left out when empty) and
    the tags of ``seq``, ``revolution`` and ``t_s`` (the run's messages ask for them each)."""
    rid = run_id.encode()
    return (varint_bytes(field_tag(_pb.Header, "run_id")) + varint_bytes(len(rid)) + rid if rid else b"",
            field_tag(_pb.Header, "seq"), field_tag(_pb.Header, "revolution"), field_tag(_pb.Header, "t_s"))


def encode_probe_waves(run_id: str, seq, revolution: int, t_s: float, forward_m: np.ndarray,
                       backward_m: np.ndarray, nd: int) -> list[bytes]:
    """:func:`~.codec.encode_probe_wave` of every probe of one revolution at once (the same
    bytes): probe ``p``'s ``TravellingWave`` numbered ``seq[p]``, its spectrum row ``p``.

    Parameters
    ----------
    run_id : str
    seq : sequence of int, length n_probes
    revolution : int
    t_s : float
        Header time.
    forward_m, backward_m : ndarray, shape (n_probes, n_nd)
    nd : int
        The revolution's dominant nodal diameter (every probe's message carries it).
    """
    fwd = np.ascontiguousarray(forward_m, dtype="<f8")
    bwd = np.ascontiguousarray(backward_m, dtype="<f8")
    if fwd.ndim != 2 or bwd.shape != fwd.shape:
        raise ValueError(f"forward_m and backward_m: expected one shape (n_probes, n_nd), got {fwd.shape}, {bwd.shape}")
    n_probes, n_nd = fwd.shape
    if n_nd == 0:
        raise ValueError("forward_m: at least one nodal diameter is needed")
    w = 8 * n_nd
    packed = varint_bytes(w)
    tags = _tags("TravellingWave")
    tag_p, tag_f, tag_b = (varint_bytes(tags[f]) for f in ("probe", "forward_m", "backward_m"))
    mid = _varint_field(tags["n_nd"], n_nd)
    tail = _varint_field(tags["dominant_nd"], nd)
    fb, bb = fwd.tobytes(), bwd.tobytes()
    return [b"".join((header_bytes(run_id, seq[p], revolution, t_s), tag_p + varint_bytes(p) if p else b"", mid,
                      tag_f, packed, fb[p * w:(p + 1) * w], tag_b, packed, bb[p * w:(p + 1) * w], tail))
            for p in range(n_probes)]


@functools.lru_cache(maxsize=None)
def _tags(message_name: str) -> dict[str, int]:
    """:func:`field_tag` of every field of a message of the schema, by field name."""
    message = getattr(_pb, message_name)
    return {f: field_tag(message, f) for f in message.DESCRIPTOR.fields_by_name}


def _double_field(tag: int, value: float) -> bytes:
    """A proto3 double field, left out when its bits are zero (as protobuf)."""
    v = _F8.pack(float(value))
    return varint_bytes(tag) + v if v != _ZERO8 else b""


def _packed_doubles(tag: int, values: np.ndarray) -> bytes:
    """A packed repeated double field of a 1-D array, left out when empty."""
    data = np.ascontiguousarray(values, dtype="<f8").tobytes()
    return varint_bytes(tag) + varint_bytes(len(data)) + data if data else b""


def encode_fits(run_id: str, seq, revolution: int, t_s: float, engine_orders, omega_rad_s: float, freq_hz,
                cn: float, amp_pkpk_m: np.ndarray, phase_rad: np.ndarray, amp_std_m: np.ndarray, dc_m: np.ndarray,
                residual_rms_m: np.ndarray) -> list[bytes]:
    """:func:`~.codec.encode_fit` of every engine order of one revolution at once (the same
    bytes): order ``k``'s ``BladeFits`` numbered ``seq[k]`` (Eq. 16-17).

    Parameters
    ----------
    run_id, seq, revolution, t_s
        The headers, as :func:`encode_probe_waves` (``seq``: one number per engine order).
    engine_orders : sequence of int, length n_eo
    omega_rad_s : float
    freq_hz : array_like, shape (n_eo,)
    cn : float
    amp_pkpk_m, phase_rad, amp_std_m : ndarray, shape (n_blades, n_eo)
    dc_m, residual_rms_m : ndarray, shape (n_blades,)
    """
    amp, phase, std = (np.asarray(a, dtype=float) for a in (amp_pkpk_m, phase_rad, amp_std_m))
    dc, res = np.asarray(dc_m, dtype=float), np.asarray(residual_rms_m, dtype=float)
    n_eo = len(engine_orders)
    if amp.ndim != 2 or amp.shape[1] != n_eo or phase.shape != amp.shape or std.shape != amp.shape \
            or dc.shape != amp.shape[:1] or res.shape != amp.shape[:1]:
        raise ValueError(f"fit arrays: expected shapes (n_blades, {n_eo}) and (n_blades,), got {amp.shape}, "
                         f"{phase.shape}, {std.shape}, {dc.shape}, {res.shape}")
    tag = _tags("BladeFits").__getitem__
    common = (_double_field(tag("omega_mean_rad_s"), omega_rad_s),)
    rest = (_packed_doubles(tag("dc_m"), dc), _packed_doubles(tag("residual_m"), res))
    head = _varint_field(tag("n_blades"), amp.shape[0])
    return [b"".join((header_bytes(run_id, seq[k], revolution, t_s), head,
                      _varint_field(tag("engine_order"), int(engine_orders[k])), *common,
                      _double_field(tag("freq_hz"), freq_hz[k]), _double_field(tag("cn"), cn),
                      _packed_doubles(tag("amp_pkpk_m"), amp[:, k]), _packed_doubles(tag("phase_rad"), phase[:, k]),
                      *rest, _packed_doubles(tag("amp_std_m"), std[:, k])))
            for k in range(n_eo)]

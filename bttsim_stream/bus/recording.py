"""MCAP recordings of the bus: write raw payloads, read them back (also from a cut file).

File layout (see ``schemas/bus.md``):

* one channel per key expression (topic = key, message encoding ``"protobuf"``);
* one schema per message type (encoding ``"protobuf"``, name = full message name such as
  ``"bttsim.v1.ToaBatch"``, data = the ``FileDescriptorSet`` of ``bttsim/v1/bttsim.proto``),
  so any MCAP reader with protobuf support decodes the file without project code;
* message ``log_time`` = simulated time in ns (``publish_time`` likewise unless given);
* a metadata record ``bttsim.run`` (``run_id``, ``rig``, ``scenario_toml``,
  ``software_version``, ...) written right after the file header, before any chunk;
* zstd-compressed chunks of about ``chunk_size`` bytes, written straight to the file with
  no user-space buffering: a process killed mid-run leaves a file whose complete chunks are
  all readable (:func:`read_recording` reports ``truncated=True`` for it).
"""

from __future__ import annotations

import io
import logging
import os
import struct
import zlib
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field

from mcap.data_stream import ReadDataStream
from mcap.exceptions import EndOfFile
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Footer, Header, Metadata, Schema
from mcap.records import Message as McapMessage
from mcap.records import MessageIndex as McapMessageIndex
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import CompressionType, Writer
import numpy as np

try:  # what the mcap library decompresses zstd chunks with (without it: the library's way)
    import zstandard as _zstd
except ImportError:  # pragma: no cover
    _zstd = None

from ..errors import BttsimError
from . import codec
from . import keys as _keys
from .stream import Message

__all__ = [
    "MCAP_MAGIC",
    "RUN_METADATA_NAME",
    "DEFAULT_CHUNK_SIZE",
    "Recording",
    "McapRecorder",
    "read_messages",
    "read_recording",
    "RecordingScan",
    "run_metadata_from_mcap",
]

log = logging.getLogger(__name__)

MCAP_MAGIC = b"\x89MCAP0\r\n"
#: Name of the MCAP metadata record that describes the run.
RUN_METADATA_NAME = "bttsim.run"
#: MCAP message sequence numbers are unsigned 32-bit.
MAX_SEQ = 1 << 32
#: Channels of messages a recorder refused (``rejected/<key>``): never read as data.
REJECTED_PREFIX = "rejected/"
#: Target uncompressed chunk size, bytes: a killed recorder loses at most about this much.
DEFAULT_CHUNK_SIZE = 1024 * 1024
_ENCODING = "protobuf"
_MESSAGE_OPCODE = int(Opcode.MESSAGE)
_CHUNK_OPCODE = int(Opcode.CHUNK)
_MESSAGE_INDEX_OPCODE = int(Opcode.MESSAGE_INDEX)
_CHANNEL_OPCODE = int(Opcode.CHANNEL)
_SCHEMA_OPCODE = int(Opcode.SCHEMA)
#: The mcap stream reader's default record size limit (a longer record is its error).
_RECORD_SIZE_LIMIT = 4 * 2**30
_OPCODE_LENGTH = struct.Struct("<BQ")
#: A chunk record's fixed fields: start and end times, uncompressed size and CRC, the
#: compression string's length.
_CHUNK_FIELDS = struct.Struct("<QQQII")
#: A message record's opcode, length, channel id, sequence, log and publish times.
_MESSAGE_HEAD = struct.Struct("<BQHIQQ")
_U64 = struct.Struct("<Q")
_U32 = struct.Struct("<I")


class _PackedMessageIndex(McapMessageIndex):
    """An MCAP message index written with one ``bytes`` for all its entries: the same
    record as :meth:`mcap.records.MessageIndex.write` (opcode, channel id, byte length, then
    (log time, offset) as little-endian uint64 pairs), without a Python call per entry."""

    def write(self, stream) -> None:
        stream.start_record(Opcode.MESSAGE_INDEX)
        stream.write2(self.channel_id)
        stream.write4(len(self.records) * 16)
        if self.records:
            stream.write(np.array(self.records, dtype="<u8").tobytes())
        stream.finish_record()


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


@dataclass(frozen=True, slots=True, eq=False)
class Recording:
    """Everything readable from an MCAP recording.

    Attributes
    ----------
    path : str
    messages : list of Message
        In file order.
    metadata : dict
        Metadata records, ``name -> {key: value}`` (a later record of the same name wins).
    truncated : bool
        True when the file ends before its footer (a killed recorder): ``messages`` holds
        everything up to the last complete chunk.
    schemas : dict
        ``topic (key) -> schema name`` (full protobuf message name) of every channel seen.
    """

    path: str
    messages: list
    metadata: dict
    truncated: bool
    schemas: dict = field(default_factory=dict)

    @property
    def run_metadata(self) -> dict | None:
        """The ``bttsim.run`` metadata record, or None."""
        return self.metadata.get(RUN_METADATA_NAME)

    def keys(self) -> list[str]:
        """Keys (channel topics) in order of first appearance."""
        return list(self.schemas)


class _DirectFile:
    """Write-through file for :class:`mcap.writer.Writer`: no user-space buffer, so every
    chunk the writer finishes is in the OS before the next one starts."""

    def __init__(self, raw: io.FileIO) -> None:
        self._raw = raw
        self._pos = 0

    def write(self, data) -> int:
        view = memoryview(data)
        done = 0
        while done < len(view):
            done += self._raw.write(view[done:])
        self._pos += done
        return done

    def tell(self) -> int:
        return self._pos

    def flush(self) -> None:
        pass

    def close(self) -> None:
        self._raw.close()


class McapRecorder:
    """Record raw bus payloads to an MCAP file (context manager).

    Parameters
    ----------
    path : str or Path
        Output file, written directly (created or truncated).
    chunk_size : int
        Target uncompressed chunk size, bytes.
    run_metadata : mapping, optional
        Written at once as the ``bttsim.run`` metadata record (see
        :meth:`write_run_metadata`).

    Examples
    --------
    >>> with McapRecorder("run.mcap") as rec:                      # doctest: +SKIP
    ...     rec.write_run_metadata(run_id, rig, scenario_toml, version)
    ...     rec.write_all(stream.acquisition(batch))
    """

    def __init__(self, path, *, chunk_size: int = DEFAULT_CHUNK_SIZE,
                 run_metadata: Mapping[str, str] | None = None) -> None:
        self.path = str(path)
        try:
            raw = io.FileIO(self.path, "w")
        except OSError as exc:
            raise BttsimError(f"{self.path}: cannot write ({exc.strerror or exc})") from None
        self._file = _DirectFile(raw)
        self._writer = Writer(self._file, chunk_size=int(chunk_size),
                              compression=CompressionType.ZSTD)
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._closed = False
        self.n_messages = 0
        from .. import __version__  # read here: a reader of recordings never needs it

        self._guard(self._writer.start, profile="", library=f"bttsim_stream {__version__}")
        if run_metadata is not None:
            self.write_metadata(RUN_METADATA_NAME, run_metadata)

    # -- context manager -------------------------------------------------------------------
    def __enter__(self) -> "McapRecorder":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _guard(self, fn, *args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except OSError as exc:
            raise BttsimError(f"{self.path}: cannot write ({exc.strerror or exc})") from None

    # -- writing ---------------------------------------------------------------------------
    def write_metadata(self, name: str, data: Mapping[str, str]) -> None:
        """Write an MCAP metadata record (string to string map) now."""
        self._check_open()
        self._guard(self._writer.add_metadata, name, {str(k): str(v) for k, v in data.items()})

    def write_run_metadata(self, run_id: str, rig: str, scenario_toml: str,
                           software_version: str | None = None, **extra: str) -> None:
        """Write the ``bttsim.run`` metadata record (call it first, right after opening).

        Parameters
        ----------
        run_id, rig, scenario_toml : str
        software_version : str, optional
            Default: this package's version.
        **extra : str
            More string entries (e.g. ``has_truth="true"``).
        """
        if software_version is None:
            from .. import __version__

            software_version = __version__
        data = {"run_id": run_id, "rig": _keys.validate_rig(rig), "scenario_toml": scenario_toml,
                "software_version": software_version}
        data.update(extra)
        self.write_metadata(RUN_METADATA_NAME, data)

    def _channel(self, key: str, message_type: str | None) -> int:
        channel_id = self._channels.get(key)
        if channel_id is None:
            name = codec.schema_name_for(message_type or _keys.message_type_for_key(key))
            schema_id = self._schemas.get(name)
            if schema_id is None:
                schema_id = self._writer.register_schema(name=name, encoding=_ENCODING,
                                                         data=codec.file_descriptor_set())
                self._schemas[name] = schema_id
            channel_id = self._writer.register_channel(topic=key, message_encoding=_ENCODING,
                                                       schema_id=schema_id)
            self._channels[key] = channel_id
        return channel_id

    def write(self, key: str, payload: bytes, log_time_ns: int, publish_time_ns: int | None = None,
              *, seq: int = 0, message_type: str | None = None) -> None:
        """Append one raw payload (not decoded) on the channel of ``key``.

        Parameters
        ----------
        key : str
            Concrete bus key; its message type comes from
            :func:`~bttsim_stream.bus.keys.message_type_for_key` unless ``message_type`` is given.
        payload : bytes
        log_time_ns : int
            Simulated time of the message, ns (>= 0).
        publish_time_ns : int, optional
            Defaults to ``log_time_ns``.
        seq : int
            The publisher's sequence number (the MCAP message ``sequence`` field).
        message_type : str, optional
            Full protobuf message name, for keys outside the standard table.
        """
        self._check_open()
        log_time = int(log_time_ns)
        publish = log_time if publish_time_ns is None else int(publish_time_ns)
        if log_time < 0 or publish < 0:
            raise ValueError(f"{key}: MCAP times must be >= 0, got {log_time}, {publish}")
        if not 0 <= int(seq) < MAX_SEQ:
            raise ValueError(f"{key}: MCAP sequence numbers are 32-bit, got {seq}")
        channel_id = self._channel(key, message_type)
        self._guard(self._writer.add_message, channel_id=channel_id, log_time=log_time,
                    data=bytes(payload), publish_time=publish, sequence=int(seq))
        self.n_messages += 1

    def write_rejected(self, key: str, payload: bytes, log_time_ns: int, *, seq: int = 0) -> None:
        """Keep a refused message on the channel ``rejected/<key>`` (no schema: the payload
        may not decode). Readers of the data never read these channels unless asked for them
        by name (:func:`read_messages`)."""
        self._check_open()
        topic = REJECTED_PREFIX + key
        channel_id = self._channels.get(topic)
        if channel_id is None:
            channel_id = self._channels[topic] = self._guard(
                self._writer.register_channel, topic=topic, message_encoding="application/octet-stream", schema_id=0)
        t = min(max(int(log_time_ns), 0), (1 << 63) - 1)
        self._guard(self._writer.add_message, channel_id=channel_id, log_time=t, data=bytes(payload),
                    publish_time=t, sequence=int(seq) if 0 <= int(seq) < MAX_SEQ else 0)

    def write_message(self, message: Message) -> None:
        """Append one :class:`~bttsim_stream.bus.stream.Message` (its key, payload, log time and
        sequence number)."""
        self.write(message.key, message.payload, message.log_time_ns, seq=message.seq)

    def write_all(self, messages: Iterable[Message]) -> None:
        """Append :class:`~bttsim_stream.bus.stream.Message` records in order.

        The same file as :meth:`write_message` one message at a time, byte for byte; once a
        batch's keys all have their channel, its message records are laid out together
        (:meth:`_append_records`) instead of one ``mcap`` call per message.
        """
        msgs = messages if isinstance(messages, list) else list(messages)
        first_fast = 0
        for i, m in enumerate(msgs):  # new keys: their channel records go in at their place
            if m.key not in self._channels:
                first_fast = i + 1
        for m in msgs[:first_fast]:
            self.write_message(m)
        if first_fast < len(msgs):
            if not self._append_records(msgs[first_fast:]):
                for m in msgs[first_fast:]:
                    self.write_message(m)

    def _append_records(self, msgs: list) -> bool:
        """Append messages on known channels as :meth:`mcap.writer.Writer.add_message` would,
        in bulk: the same records, message indexes, statistics and chunk boundaries.

        Uses the writer's internal state (mcap 1.6's chunk builder and statistics); returns
        False, having written nothing, when that state is not there (another mcap version),
        chunking is off, or a value does not fit its field (the caller then writes the
        messages one by one, which reports the problem).
        """
        w = self._writer
        cb = getattr(w, "_Writer__chunk_builder", None)
        st = getattr(w, "_Writer__statistics", None)
        chunk_size = getattr(w, "_Writer__chunk_size", None)
        finalize = getattr(w, "_Writer__finalize_chunk", None)
        rb = getattr(cb, "record_writer", None)
        if cb is None or st is None or chunk_size is None or finalize is None or rb is None:
            return False
        self._check_open()
        n = len(msgs)
        channel = np.fromiter((self._channels[m.key] for m in msgs), np.int64, n)
        log = np.fromiter((m.log_time_ns for m in msgs), np.int64, n)
        seq = np.fromiter((m.seq for m in msgs), np.int64, n)
        data = [bytes(m.payload) for m in msgs]
        size = np.fromiter((len(d) for d in data), np.int64, n)
        if (log.min() < 0 or seq.min() < 0 or seq.max() > 0xFFFFFFFF or channel.max() > 0xFFFF):
            return False
        head = np.zeros(n, np.dtype([("op", "u1"), ("len", "<u8"), ("ch", "<u2"), ("seq", "<u4"), ("log", "<u8"),
                                     ("pub", "<u8")]))
        head["op"] = _MESSAGE_OPCODE
        head["len"] = 22 + size
        head["ch"] = channel
        head["seq"] = seq
        head["log"] = log
        head["pub"] = log
        hb = head.tobytes()
        rec = 31 + size
        log_l, ch_l = log.tolist(), channel.tolist()
        i = 0
        while i < n:
            start = rb.count
            ends = start + np.cumsum(rec[i:])
            over = np.flatnonzero(ends > chunk_size)
            j = i + (int(over[0]) + 1 if over.size else n - i)  # messages [i, j) go in this chunk
            offsets = (ends - rec[i:])[: j - i].tolist()
            t = log_l[i:j]
            t_min, t_max = min(t), max(t)
            cb.message_start_time = t_min if cb.num_messages == 0 else min(cb.message_start_time, t_min)
            cb.message_end_time = max(cb.message_end_time, t_max)
            for k in range(i, j):
                c = ch_l[k]
                index = cb.message_indices.get(c)
                if not index:
                    index = cb.message_indices[c] = _PackedMessageIndex(channel_id=c, records=[])
                index.records.append((log_l[k], offsets[k - i]))
                st.channel_message_counts[c] += 1
            cb.num_messages += j - i
            st.message_start_time = t_min if st.message_count == 0 else min(st.message_start_time, t_min)
            st.message_end_time = max(st.message_end_time, t_max)
            st.message_count += j - i
            rb.write(b"".join([x for k in range(i, j) for x in (hb[31 * k:31 * k + 31], data[k])]))
            if rb.count > chunk_size:
                self._guard(finalize)
            i = j
        self.n_messages += n
        return True

    def flush(self) -> None:
        """Finish the chunk in progress (if it holds messages) and hand it to the OS."""
        self._check_open()
        flush = getattr(self._writer, "flush", None)  # mcap >= 1.6
        if flush is not None:
            self._guard(flush)

    def close(self) -> None:
        """Write the last chunk, the summary and the footer, and close the file (idempotent)."""
        if self._closed:
            return
        self._closed = True
        try:
            self._guard(self._writer.finish)
        finally:
            self._file.close()

    @property
    def closed(self) -> bool:
        return self._closed

    def _check_open(self) -> None:
        if self._closed:
            raise ValueError(f"{self.path}: recorder is closed")


# ------------------------------------------------------------------------------------------
# Reading
# ------------------------------------------------------------------------------------------


class _StrictFile:
    """Reads that never come back short: a read past the end raises ``EndOfFile`` at once
    (the stock stream reader would return short data and fail later, obscurely)."""

    def __init__(self, f, size: int, pos: int) -> None:
        self._f = f
        self._size = size
        self.pos = pos

    def read(self, n: int) -> bytes:
        if n > self._size - self.pos:
            raise EndOfFile()
        data = self._f.read(n)
        if len(data) < n:
            raise EndOfFile()
        self.pos += n
        return data


class _Scan:
    """State of one pass over a file."""

    def __init__(self, path: str) -> None:
        self.path = path
        self.truncated = False
        self.metadata: dict[str, dict[str, str]] = {}

    def corrupt(self, what: str) -> BttsimError:
        return BttsimError(f"{self.path}: corrupt MCAP ({what})")


def _records(scan: _Scan, decode_chunks: bool = True) -> Iterator:
    """Records of the file in order (chunks broken up); sets ``scan.truncated`` at a cut.

    The records are those of the mcap library's :class:`~mcap.stream_reader.StreamReader`
    and :func:`~mcap.stream_reader.breakup_chunk` (with ``validate_crc``), with two
    exceptions: a message of a chunk read by :func:`_chunk_records` comes as a tuple
    ``(channel_id, log_time, data, sequence)``, and message index records are not yielded
    (no reader of a recording uses them). Chunks and message indexes, the bulk of a file,
    are read here (:func:`_fast_record`) when their fields fit their record exactly as the
    library would read them; every other record, and any of those that does not fit, is
    the library's to read from the same place: the same records, the same errors and the
    same cut.
    """
    path = scan.path
    try:
        f = open(path, "rb")
    except OSError as exc:
        raise BttsimError(f"{path}: cannot read ({exc.strerror or exc})") from None
    with f:
        size = os.fstat(f.fileno()).st_size
        magic = f.read(len(MCAP_MAGIC))
        if magic != MCAP_MAGIC:
            if magic and MCAP_MAGIC.startswith(magic):
                scan.truncated = True
                return
            raise BttsimError(f"{path}: not an MCAP file")
        strict = _StrictFile(f, size, len(MCAP_MAGIC))
        # the library's reader, used where this one does not read: between records it holds
        # nothing but the file's position, which both share
        it = iter(StreamReader(strict, skip_magic=True, emit_chunks=True).records)
        first = True
        footer = False  # after the footer, the library reads its closing magic
        while True:
            start = strict.pos
            rec = None if footer else _fast_record(f, strict, size, decode_chunks)
            if rec is None:
                try:
                    rec = next(it)
                except StopIteration:
                    return
                except EndOfFile:
                    scan.truncated = True
                    return
                except Exception as exc:  # any parse failure of a complete record
                    raise scan.corrupt(f"record at byte {start}: {_one_line(exc)}") from None
            if first and not isinstance(rec, Header):
                raise scan.corrupt("the first record is not a header")
            first = False
            if isinstance(rec, Chunk):
                if not decode_chunks:
                    continue
                inner = _chunk_records(rec)
                if inner is None:  # not a plain chunk: the library's reading, or its error
                    try:
                        inner = breakup_chunk(rec, validate_crc=True)
                    except Exception as exc:
                        raise scan.corrupt(f"chunk at byte {start}: {_one_line(exc)}") from None
                yield from inner
            elif rec is not _SKIPPED:
                if isinstance(rec, Metadata):
                    scan.metadata[rec.name] = dict(rec.metadata)
                elif isinstance(rec, Footer):
                    footer = True
                    _check_summary_crc(scan, f, rec, start)
                yield rec


#: What :func:`_fast_record` gives for a record read and not yielded (a message index).
_SKIPPED = object()


def _fast_record(f, strict: _StrictFile, size: int, decode_chunks: bool):
    """The chunk (a :class:`~mcap.records.Chunk`, its data not decompressed) or message index
    (:data:`_SKIPPED`) at ``strict.pos``, read with the file positioned after it, when it lies
    whole in the file and its fields fit its length -- what the library's
    :meth:`~mcap.records.Chunk.read` or :meth:`~mcap.records.MessageIndex.read` would read
    there, padding included. Else None, the file where it was (the library reads it then, and
    says what is wrong with it)."""
    pos = strict.pos
    if size - pos < 9:
        return None
    head = f.read(9)
    if len(head) == 9:
        opcode, length = _OPCODE_LENGTH.unpack(head)
        if opcode in (_CHUNK_OPCODE, _MESSAGE_INDEX_OPCODE) and length <= min(_RECORD_SIZE_LIMIT, size - pos - 9):
            body = f.read(length)
            if len(body) == length:
                rec = _chunk_of(body, decode_chunks) if opcode == _CHUNK_OPCODE else _message_index_fits(body)
                if rec is not None:
                    strict.pos = pos + 9 + length
                    return rec
    f.seek(pos)
    return None


def _message_index_fits(body: bytes):
    """:data:`_SKIPPED` when a message index record's entries (16 bytes each, read while
    fewer than ``records_length`` bytes were) end within its ``body``; else None."""
    if len(body) < 6:
        return None
    (records_length,) = _U32.unpack_from(body, 2)
    return _SKIPPED if 6 + -(-records_length // 16) * 16 <= len(body) else None


def _chunk_of(body: bytes, with_data: bool):
    """The :class:`~mcap.records.Chunk` of a chunk record's ``body`` (None: its fields do not
    fit it, or its compression is not UTF-8)."""
    n = len(body)
    if n < _CHUNK_FIELDS.size:
        return None
    t_start, t_end, uncompressed_size, crc, compression_length = _CHUNK_FIELDS.unpack_from(body, 0)
    p = _CHUNK_FIELDS.size + compression_length
    if p + 8 > n:
        return None
    (data_length,) = _U64.unpack_from(body, p)
    if p + 8 + data_length > n:
        return None
    try:
        compression = str(body[_CHUNK_FIELDS.size:p], "utf-8")
    except UnicodeDecodeError:
        return None
    data = body[p + 8:p + 8 + data_length] if with_data else b""
    return Chunk(compression=compression, data=data, message_end_time=t_end, message_start_time=t_start,
                 uncompressed_crc=crc, uncompressed_size=uncompressed_size)


def _chunk_records(chunk: Chunk) -> list | None:
    """The records of a chunk as :func:`~mcap.stream_reader.breakup_chunk` (with
    ``validate_crc``) reads them, messages as ``(channel_id, log_time, data, sequence)``
    tuples; None for a chunk that is not plain (lz4, no zstd module, a decompression or CRC
    failure, a record that does not end within the chunk, a schema or channel whose fields do
    not fill its record exactly): :func:`~mcap.stream_reader.breakup_chunk` reads it then, or
    says what is wrong with it."""
    if chunk.compression == "zstd":
        if _zstd is None:
            return None
        try:
            data = _zstd.decompress(chunk.data, chunk.uncompressed_size)
        except Exception:
            return None
    elif chunk.compression == "lz4":
        return None
    else:  # the library reads any other compression as none
        data = chunk.data
    if chunk.uncompressed_crc != 0 and zlib.crc32(data) != chunk.uncompressed_crc:
        return None
    out: list = []
    append = out.append
    head = _MESSAGE_HEAD.unpack_from
    op_len = _OPCODE_LENGTH.unpack_from
    n, pos = len(data), 0
    while pos < n:
        if n - pos < 9:
            return None
        opcode, length = op_len(data, pos)
        end = pos + 9 + length
        if end > n:
            return None
        if opcode == _MESSAGE_OPCODE:
            if length < 22:
                return None
            _, _, channel_id, sequence, log_time, _ = head(data, pos)
            append((channel_id, log_time, data[pos + 31:end], sequence))
        elif opcode == _CHANNEL_OPCODE or opcode == _SCHEMA_OPCODE:
            stream = ReadDataStream(io.BytesIO(data[pos + 9:]))  # the rest of the chunk, as the library reads it
            try:
                rec = (Channel if opcode == _CHANNEL_OPCODE else Schema).read(stream)
            except Exception:
                return None
            if stream.count != length:  # the library would go on from where its fields ended
                return None
            append(rec)
        pos = end  # another record: skipped, as the library does
    return out


#: Bytes of a footer record that its summary CRC covers: opcode, length, summary_start and
#: summary_offset_start.
_FOOTER_CRC_BYTES = 1 + 8 + 8 + 8


def _check_summary_crc(scan: _Scan, f, footer: Footer, footer_start: int) -> None:
    """The footer's ``summary_crc`` (when not 0) against the bytes it covers: the summary
    section and the footer up to ``summary_offset_start`` (the MCAP specification). The index
    other readers rely on is held to it, though this reader does not use it."""
    if not footer.summary_crc or not footer.summary_start:
        return
    start, stop = footer.summary_start, footer_start + _FOOTER_CRC_BYTES
    if not len(MCAP_MAGIC) <= start <= footer_start:
        raise scan.corrupt(f"footer summary_start {start} outside the file's records")
    crc, pos = 0, start
    while pos < stop:
        block = os.pread(f.fileno(), min(1 << 20, stop - pos), pos)
        if not block:
            raise scan.corrupt("footer beyond the end of the file")
        crc = zlib.crc32(block, crc)
        pos += len(block)
    if crc != footer.summary_crc:
        raise scan.corrupt(f"summary CRC {crc:#010x} does not match the footer's {footer.summary_crc:#010x}")


def _messages(scan: _Scan, keys, schemas_out: dict) -> Iterator[Message]:
    exprs = None if keys is None else [keys] if isinstance(keys, str) else list(keys)
    schema_names: dict[int, str] = {}
    channels: dict[int, tuple[str, bool]] = {}  # id -> (topic, wanted)
    for rec in _records(scan):
        if type(rec) is tuple:  # (channel_id, log_time, data, sequence): a message of a chunk
            ch = channels.get(rec[0])
            if ch is None:
                raise scan.corrupt(f"message on unknown channel {rec[0]}")
            if ch[1]:
                yield Message(ch[0], rec[2], rec[1], rec[3])
        elif isinstance(rec, McapMessage):
            ch = channels.get(rec.channel_id)
            if ch is None:
                raise scan.corrupt(f"message on unknown channel {rec.channel_id}")
            if ch[1]:
                yield Message(ch[0], rec.data, rec.log_time, rec.sequence)
        elif isinstance(rec, Schema):
            schema_names[rec.id] = rec.name
        elif isinstance(rec, Channel):
            if rec.schema_id != 0 and rec.schema_id not in schema_names:
                raise scan.corrupt(f"channel {rec.topic!r} refers to unknown schema "
                                   f"{rec.schema_id}")
            if exprs is None:  # every channel of data: refused messages are not data
                wanted = not rec.topic.startswith(REJECTED_PREFIX)
            else:
                wanted = any(_keys.key_matches(e, rec.topic) for e in exprs)
            channels[rec.id] = (rec.topic, wanted)
            if not rec.topic.startswith(REJECTED_PREFIX):
                schemas_out.setdefault(rec.topic, schema_names.get(rec.schema_id, ""))


def read_messages(path, keys=None) -> Iterator[Message]:
    """Iterate over the messages of a recording in file order.

    Parameters
    ----------
    path : str or Path
    keys : str or iterable of str, optional
        Key expressions to keep (``*`` one chunk, ``**`` any number); default all.

    Yields
    ------
    Message
        ``(key, payload, log_time_ns, seq)``.

    Raises
    ------
    BttsimError
        ``"FILE: not an MCAP file"``, ``"FILE: corrupt MCAP (...)"`` or unreadable file. A
        truncated file is not an error: iteration stops after its last complete chunk and a
        warning is logged.
    """
    scan = _Scan(str(path))
    yield from _messages(scan, keys, {})
    if scan.truncated:
        log.warning("%s: truncated MCAP file (read up to its last complete chunk)", scan.path)


class RecordingScan:
    """One pass over a recording as a stream: iterate for the messages in file order (none is
    kept); afterwards ``truncated``, ``metadata`` and ``schemas`` say what :func:`read_recording`
    would have said. Memory does not grow with the file.

    Parameters
    ----------
    path : str or Path
    keys : str or iterable of str, optional
        Key expressions of the messages to yield.

    Raises
    ------
    BttsimError
        As :func:`read_messages` (while iterating).
    """

    def __init__(self, path, keys=None) -> None:
        self._scan = _Scan(str(path))
        self._keys = keys
        self.schemas: dict[str, str] = {}

    @property
    def path(self) -> str:
        return self._scan.path

    @property
    def truncated(self) -> bool:
        return self._scan.truncated

    @property
    def metadata(self) -> dict:
        return dict(self._scan.metadata)

    def __iter__(self) -> Iterator[Message]:
        return _messages(self._scan, self._keys, self.schemas)


def read_recording(path, keys=None) -> Recording:
    """Read a whole recording: messages, metadata, channel schemas and whether it was cut.

    Parameters
    ----------
    path : str or Path
    keys : str or iterable of str, optional
        Key expressions of the messages to keep (all channels are still listed).

    Raises
    ------
    BttsimError
        As :func:`read_messages`.
    """
    scan = _Scan(str(path))
    schemas: dict[str, str] = {}
    messages = list(_messages(scan, keys, schemas))
    return Recording(path=scan.path, messages=messages, metadata=dict(scan.metadata),
                     truncated=scan.truncated, schemas=schemas)


def run_metadata_from_mcap(path) -> dict | None:
    """The ``bttsim.run`` metadata record of a recording (None if absent).

    Chunks are skipped without decompression. A truncated file is read up to its cut.

    Raises
    ------
    BttsimError
        Not an MCAP file, corrupt, or unreadable.
    """
    scan = _Scan(str(path))
    for _ in _records(scan, decode_chunks=False):
        pass
    return scan.metadata.get(RUN_METADATA_NAME)

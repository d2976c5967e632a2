"""MCAP recordings: exact round trip, decoding with no project code, cut and corrupt files."""

import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from mcap.data_stream import ReadDataStream
from mcap.reader import make_reader
from mcap.records import Chunk, Message
from mcap.stream_reader import breakup_chunk

from bttsim_stream.errors import BttsimError
from bttsim_stream.bus import codec, recording as mcap_io
from bttsim_stream.bus.recording import McapRecorder, read_messages, read_recording, run_metadata_from_mcap

from _io_helpers import NB, NP, RUN_META, make_batch, recorded_messages

REPO = Path(__file__).resolve().parents[1]


def _record(path, messages, chunk_size=mcap_io.DEFAULT_CHUNK_SIZE):
    with McapRecorder(path, chunk_size=chunk_size) as rec:
        rec.write_run_metadata(**RUN_META)
        rec.write_all(messages)
    return path


@pytest.fixture(scope="module")
def messages():
    return recorded_messages()


@pytest.fixture(scope="module")
def recording(messages, tmp_path_factory):
    return _record(tmp_path_factory.mktemp("rec") / "run.mcap", messages)


@pytest.fixture(scope="module")
def chunked(messages, tmp_path_factory):
    """A recording with many small chunks, and the number of messages at the end of each."""
    path = _record(tmp_path_factory.mktemp("rec") / "chunked.mcap", messages, chunk_size=4000)
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    chunks = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    assert len(chunks) >= 5
    return path, chunks


def test_round_trip_is_exact(recording, messages):
    rec = read_recording(recording)
    assert not rec.truncated
    assert list(rec.messages) == messages
    assert rec.run_metadata == RUN_META
    assert rec.schemas["bttsim/rig1/toa/4"] == "bttsim.v1.ToaBatch"
    assert rec.schemas["bttsim/rig1/meta"] == "bttsim.v1.RunMetadata"
    assert rec.keys()[0] == "bttsim/rig1/meta"
    assert list(read_messages(recording)) == messages
    assert run_metadata_from_mcap(recording) == RUN_META


def test_key_filter(recording, messages):
    got = list(read_messages(recording, keys=["bttsim/rig1/opr", "bttsim/rig1/toa/*"]))
    assert list(got) == [m for m in messages if "/opr" in m.key or "/toa/" in m.key]


def test_decoded_recording_matches_the_batch(recording):
    batch = make_batch(seed=0)
    toa = [codec.decode_toa_batch(m.payload, m.key).body for m in read_messages(recording, "bttsim/rig1/toa/2")]
    np.testing.assert_array_equal(np.stack([t.toa_s for t in toa[:3]]), batch.toa_s[:, :, 2])
    meta = [codec.decode_run_metadata(m.payload, m.key).body for m in read_messages(recording, "bttsim/*/meta")]
    assert len(meta) == 1 and meta[0].n_blades == NB


def test_file_layout(recording):
    with open(recording, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        records = list(reader.iter_metadata())
    assert {c.topic for c in summary.channels.values()} >= {"bttsim/rig1/opr", "bttsim/rig1/truth"}
    assert all(c.message_encoding == "protobuf" for c in summary.channels.values())
    assert all(s.encoding == "protobuf" and s.data == codec.file_descriptor_set()
               for s in summary.schemas.values())
    assert len(summary.schemas) == 4  # RunMetadata, Opr, ToaBatch, TruthBatch: one per type
    assert all(c.compression == "zstd" for c in summary.chunk_indexes)
    assert [m.name for m in records] == ["bttsim.run"]
    # the run metadata record comes before the first chunk
    assert records and min(c.chunk_start_offset for c in summary.chunk_indexes) > \
        summary.metadata_indexes[0].offset


DECODE_WITHOUT_PROJECT = textwrap.dedent("""
    import json, sys
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    out = []
    with open(sys.argv[1], "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message, proto in reader.iter_decoded_messages():
            out.append({"topic": channel.topic, "type": schema.name, "log_time": message.log_time,
                        "seq": proto.header.seq, "revolution": proto.header.revolution,
                        "toa_s": list(proto.toa_s) if schema.name == "bttsim.v1.ToaBatch" else None,
                        "opr_s": proto.opr_s if schema.name == "bttsim.v1.Opr" else None,
                        "n_probes": proto.n_probes if schema.name == "bttsim.v1.RunMetadata" else None})
    assert not any(m.startswith("bttsim_stream") for m in sys.modules), "project code imported"
    print(json.dumps(out))
""")


def test_recording_decodes_without_project_code(recording, tmp_path):
    script = tmp_path / "decode.py"
    script.write_text(DECODE_WITHOUT_PROJECT)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    proc = subprocess.run([sys.executable, "-I", str(script), str(recording)], capture_output=True,
                          text=True, cwd=tmp_path, env=env, timeout=60)
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    batch = make_batch(seed=0)
    assert out[0]["type"] == "bttsim.v1.RunMetadata" and out[0]["n_probes"] == NP
    assert out[1]["topic"] == "bttsim/rig1/opr" and out[1]["opr_s"] == batch.opr_s[0]
    toa2 = [m for m in out if m["topic"] == "bttsim/rig1/toa/2"]
    assert [m["seq"] for m in toa2] == list(range(12))
    assert toa2[1]["toa_s"] == batch.toa_s[1, :, 2].tolist()
    assert toa2[1]["log_time"] == int(round(batch.toa_s[1, :, 2].max() * 1e9))


def _cut(src: Path, dst: Path, n: int) -> Path:
    dst.write_bytes(src.read_bytes()[:n])
    return dst


def _messages_per_chunk(path, chunks):
    """Message count of each chunk, read with the mcap library alone."""
    counts = []
    with open(path, "rb") as f:
        for c in chunks:
            f.seek(c.chunk_start_offset + 9)  # opcode (1) + record length (8)
            chunk = Chunk.read(ReadDataStream(f))
            counts.append(sum(isinstance(r, Message) for r in breakup_chunk(chunk)))
    return counts


def test_truncated_files_yield_their_complete_chunks(chunked, messages, tmp_path):
    path, chunks = chunked
    counts = _messages_per_chunk(path, chunks)
    assert sum(counts) == len(messages)
    for k, c in enumerate(chunks[:4]):
        end = c.chunk_start_offset + c.chunk_length
        before = sum(counts[:k])
        cases = {"mid-chunk": (c.chunk_start_offset + c.chunk_length // 2, before),
                 "after-chunk": (end, before + counts[k]),
                 "in-message-index": (end + 3, before + counts[k])}
        for name, (n, expected) in cases.items():
            rec = read_recording(_cut(path, tmp_path / "cut.mcap", n))
            assert rec.truncated, (k, name)
            assert len(rec.messages) == expected, (k, name)
            assert list(rec.messages) == messages[:expected]
            assert rec.run_metadata == RUN_META
            assert run_metadata_from_mcap(tmp_path / "cut.mcap") == RUN_META


@pytest.mark.parametrize("fraction", [0.5, 0.9, 0.999])
def test_file_cut_anywhere_reads_a_prefix(chunked, messages, tmp_path, fraction):
    path, _ = chunked
    n = int(path.stat().st_size * fraction)
    rec = read_recording(_cut(path, tmp_path / "cut.mcap", n))
    assert rec.truncated and 0 < len(rec.messages) <= len(messages)
    assert list(rec.messages) == messages[:len(rec.messages)]
    assert list(read_messages(tmp_path / "cut.mcap")) == \
        list(rec.messages)


def test_file_cut_in_its_summary_keeps_every_message(chunked, messages, tmp_path):
    path, _ = chunked
    rec = read_recording(_cut(path, tmp_path / "cut.mcap", path.stat().st_size - 4))
    assert rec.truncated and list(rec.messages) == messages


def test_file_cut_before_any_chunk(chunked, tmp_path):
    path, chunks = chunked
    rec = read_recording(_cut(path, tmp_path / "cut.mcap", chunks[0].chunk_start_offset))
    assert rec.truncated and rec.messages == [] and rec.run_metadata == RUN_META
    rec = read_recording(_cut(path, tmp_path / "cut.mcap", 5))
    assert rec.truncated and rec.messages == [] and rec.run_metadata is None
    assert run_metadata_from_mcap(tmp_path / "cut.mcap") is None


def _error(excinfo) -> str:
    text = str(excinfo.value)
    assert "\n" not in text
    return text


@pytest.mark.parametrize("content", [b"", b"hello world, not an mcap file\n" * 10,
                                     bytes(range(256))], ids=["empty", "text", "binary"])
def test_garbage_is_not_an_mcap_file(tmp_path, content):
    path = tmp_path / "bad.mcap"
    path.write_bytes(content)
    with pytest.raises(BttsimError) as excinfo:
        read_recording(path)
    assert _error(excinfo) == f"{path}: not an MCAP file"
    with pytest.raises(BttsimError):
        list(read_messages(path))
    with pytest.raises(BttsimError):
        run_metadata_from_mcap(path)


def test_garbage_after_the_magic_is_corrupt(tmp_path):
    path = tmp_path / "bad.mcap"
    path.write_bytes(mcap_io.MCAP_MAGIC + b"\x07" + bytes(200))
    with pytest.raises(BttsimError, match=r"corrupt MCAP \(the first record is not a header\)"):
        read_recording(path)


def test_damaged_chunk_is_corrupt(chunked, tmp_path):
    path, chunks = chunked
    data = bytearray(path.read_bytes())
    data[chunks[1].chunk_start_offset + chunks[1].chunk_length - 10] ^= 0xFF
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    with pytest.raises(BttsimError) as excinfo:
        read_recording(bad)
    assert _error(excinfo).startswith(f"{bad}: corrupt MCAP (chunk at byte ")


def test_a_damaged_summary_is_corrupt(chunked, tmp_path):
    """The summary section (the index third-party readers use) is held to the footer's CRC:
    one flipped bit in its statistics, which mcap's own reader takes as a message count, is
    a one-line error, though every message would still read."""
    from mcap.reader import make_reader

    path, _ = chunked
    data = bytearray(path.read_bytes())
    with open(path, "rb") as f:
        stats_at = make_reader(f).get_summary().statistics
    footer = len(data) - len(mcap_io.MCAP_MAGIC) - (1 + 8 + 8 + 8 + 4)
    summary_start = int.from_bytes(data[footer + 9:footer + 17], "little")
    pos = summary_start
    while data[pos] != 0x0B:  # the Statistics record
        pos += 9 + int.from_bytes(data[pos + 1:pos + 9], "little")
    data[pos + 9] ^= 0x01  # its message_count's lowest bit
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    with open(bad, "rb") as f:  # mcap's reader takes the damaged index as it is
        assert make_reader(f).get_summary().statistics.message_count == stats_at.message_count ^ 1
    with pytest.raises(BttsimError) as excinfo:
        read_recording(bad)
    assert _error(excinfo).startswith(f"{bad}: corrupt MCAP (summary CRC ")
    assert len(read_recording(path).messages) == stats_at.message_count


def test_missing_file(tmp_path):
    with pytest.raises(BttsimError, match="cannot read"):
        read_recording(tmp_path / "nope.mcap")
    with pytest.raises(BttsimError, match="cannot write"):
        McapRecorder(tmp_path / "no" / "dir" / "x.mcap")


def test_flush_puts_messages_on_disk_while_recording(messages, tmp_path):
    path = tmp_path / "live.mcap"
    with McapRecorder(path, run_metadata=RUN_META) as rec:
        rec.write_all(messages[:10])
        assert read_recording(path).messages == []  # still in the open chunk
        rec.flush()
        live = read_recording(path)
        assert live.truncated and list(live.messages) == messages[:10]
        rec.write_all(messages[10:])
    done = read_recording(path)
    assert not done.truncated and list(done.messages) == messages


def test_recorder_refuses_unknown_keys_and_negative_times(tmp_path):
    with McapRecorder(tmp_path / "x.mcap") as rec:
        with pytest.raises(BttsimError, match="not a bttsim key"):
            rec.write("other/topic", b"", 0)
        with pytest.raises(ValueError):
            rec.write("bttsim/rig1/opr", b"", -1)
        with pytest.raises(ValueError, match="32-bit"):  # refused before anything is written
            rec.write("bttsim/rig1/opr", b"", 0, seq=1 << 62)
        rec.write("other/topic", b"", 0, message_type="bttsim.v1.Opr")
    back = read_recording(tmp_path / "x.mcap")
    assert back.schemas == {"other/topic": "bttsim.v1.Opr"} and not back.truncated and len(back.messages) == 1


KILLED_WRITER = textwrap.dedent("""
    import os, signal, sys
    sys.path.insert(0, sys.argv[2])
    sys.path.insert(0, os.path.join(sys.argv[2], "tests"))
    from bttsim_stream.bus.recording import McapRecorder
    from _io_helpers import RUN_META, recorded_messages
    msgs = recorded_messages(8)
    rec = McapRecorder(sys.argv[1], chunk_size=8000, run_metadata=RUN_META)
    rec.write_all(msgs)
    print(len(msgs), flush=True)
    os.kill(os.getpid(), signal.SIGKILL)
""")


def test_sigkill_loses_at_most_the_open_chunk(tmp_path):
    path = tmp_path / "killed.mcap"
    script = tmp_path / "kill.py"
    script.write_text(KILLED_WRITER)
    proc = subprocess.run([sys.executable, str(script), str(path), str(REPO)], capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    n_written = int(proc.stdout)
    rec = read_recording(path)
    assert rec.truncated and rec.run_metadata == RUN_META
    expected = recorded_messages(8)
    assert list(rec.messages) == expected[:len(rec.messages)]
    open_chunk = 8000 // min(len(m.payload) for m in expected) + 1
    assert n_written - open_chunk <= len(rec.messages) <= n_written


@pytest.mark.parametrize("chunk_size", [mcap_io.DEFAULT_CHUNK_SIZE, 4000, 300, 1])
def test_write_all_is_message_by_message_byte_for_byte(messages, tmp_path, chunk_size):
    """write_all lays out a batch's records in bulk: the same file as one message at a time
    (chunk boundaries, message indexes, statistics), channels appearing mid-batch included."""
    one = tmp_path / "one.mcap"
    with McapRecorder(one, chunk_size=chunk_size) as rec:
        rec.write_run_metadata(**RUN_META)
        for m in messages:
            rec.write_message(m)
    bulk = tmp_path / "bulk.mcap"
    with McapRecorder(bulk, chunk_size=chunk_size) as rec:
        rec.write_run_metadata(**RUN_META)
        rec.write_all(messages[:4])  # new channels inside a batch
        for k in range(4, len(messages), 9):
            rec.write_all(messages[k:k + 9])
        assert rec.n_messages == len(messages)
    assert bulk.read_bytes() == one.read_bytes()


@pytest.mark.parametrize("chunk_size", [4096, mcap_io.DEFAULT_CHUNK_SIZE], ids=["small-chunks", "default"])
def test_bulk_writer_is_byte_identical_to_the_public_api(messages, tmp_path, chunk_size):
    """``write_all`` fills mcap's writer state in bulk; ``write_message`` goes through mcap's public
    ``add_message``. Both must give the same file, byte for byte (chunks, indexes, statistics),
    and ``write_all`` must take the public path where the writer's internals are missing."""
    bulk = _record(tmp_path / "bulk.mcap", messages, chunk_size)
    with McapRecorder(tmp_path / "public.mcap", chunk_size=chunk_size) as rec:
        rec.write_run_metadata(**RUN_META)
        for m in messages:
            rec.write_message(m)
    assert bulk.read_bytes() == (tmp_path / "public.mcap").read_bytes()

    class Private(McapRecorder):  # a writer without mcap 1.6's internals: the public path
        def _append_records(self, msgs):
            return False

    with Private(tmp_path / "fallback.mcap", chunk_size=chunk_size) as rec:
        rec.write_run_metadata(**RUN_META)
        rec.write_all(messages)
    assert bulk.read_bytes() == (tmp_path / "fallback.mcap").read_bytes()


def test_the_bulk_writer_uses_mcap_internals_of_the_tested_release(messages, tmp_path):
    """pyproject.toml bounds mcap to the release whose private writer state the bulk writer fills:
    on it, the fast path must be taken. Fails loudly, naming the release, when mcap moves them."""
    from importlib.metadata import version

    msgs = list(messages)
    with McapRecorder(tmp_path / "x.mcap") as rec:
        seen = set()
        for m in msgs:  # a first message on each key declares its channel (public API)
            if m.key not in seen:
                rec.write_message(m)
                seen.add(m.key)
        assert rec._append_records(msgs[-50:]), (
            f"mcap {version('mcap')}: the Writer's private chunk builder/statistics moved; the recorder "
            "falls back to add_message (correct, slower): update _append_records or the mcap bound")


# -- what the recorder writes: RecordGate ---------------------------------------------------

@pytest.fixture(scope="module")
def run_messages():
    """A short run's metadata and acquisition messages (5 probes, truth)."""
    from bttsim_stream.acquisition import AcquisitionStream
    from bttsim_stream.scenario import scenario_from_dict

    scn = scenario_from_dict({"speed": {"start_rpm": 2400.0, "end_rpm": 2500.0, "duration_s": 0.5}})
    acq = AcquisitionStream(scn, include_truth=True, n_revolutions=12)
    return acq.meta, [m for _, ms in acq.batches() for m in ms]


def _admit(gate, m, source="sim", seq=None, t=None):
    return gate.admit(m.key, m.payload, (m.seq if seq is None else seq, m.log_time_ns if t is None else t), source)


def test_the_gate_writes_a_clean_run_whole_and_in_order(run_messages):
    from bttsim_stream.bus.admission import RecordGate

    meta, msgs = run_messages
    gate = RecordGate("rig1")
    assert [v.action for m in msgs[:5] for v in _admit(gate, m)] == []  # before the metadata: they wait
    out = _admit(gate, meta)
    assert out[0].action == "write" and out[0].meta is not None and [v.action for v in out[1:]] == ["write"] * 5
    for m in msgs[5:]:
        assert [v.action for v in _admit(gate, m)] == ["write"]
    assert gate.missing() == {} and gate.rejected == 0 and gate.conflicts == 0
    assert gate.summary()["messages"] == len(msgs) + 1


def test_the_gate_refuses_forgeries_and_counts_them(run_messages):
    from bttsim_stream.bus import codec
    from bttsim_stream.bus.admission import KEEP_REJECTED, RecordGate

    meta, msgs = run_messages
    gate = RecordGate("rig1")
    _admit(gate, meta)
    toa0 = [m for m in msgs if m.key == "bttsim/rig1/toa/0"]
    first = toa0[0]
    cases = {  # (key, payload, att, source) -> the reason counted
        "not from the session that published the run": (first.key, first.payload, (0, first.log_time_ns), "forger"),
        "does not decode": (first.key, b"\x08\x96\x01garbage", (1, 0), "sim"),
        "header and attachment numbers differ": (first.key, toa0[5].payload, (1, toa0[5].log_time_ns), "sim"),
        "header and attachment times differ": (first.key, first.payload, (0, 12345), "sim"),
        "a probe the run does not have": ("bttsim/rig1/toa/7", codec.encode_toa_batch(
            codec.Header(meta_run_id(meta), 0, 0, 0.0), 7, [0.0] * 29), (0, 0), "sim"),
        "another rig": ("bttsim/rig2/opr", first.payload, (0, 0), "sim"),
        "no sequence-number attachment": (first.key, first.payload, None, "sim"),
    }
    for reason, (key, payload, att, source) in cases.items():
        (v,) = gate.admit(key, payload, att, source)
        assert v.action == "reject" and v.reason == reason, (reason, v)
    # the real messages are all still written
    for m in msgs:
        assert [v.action for v in _admit(gate, m)] == ["write"], m.key
    # a second, different, well-formed payload for a written number: a conflict, the first stays
    forged = codec.encode_toa_batch(codec.Header(meta_run_id(meta), 3, 3, codec.decode_message(
        first.key, toa0[3].payload).header.t_s), 0, [1.0] * 29)
    (v,) = gate.admit(first.key, forged, (3, toa0[3].log_time_ns), "sim")
    assert v.action == "reject" and gate.conflicts_by_key == {first.key: 1}
    assert [v.action for v in _admit(gate, toa0[3])] == ["duplicate"]
    # a flood: counted whole, kept bounded
    kept = sum(v.keep for i in range(KEEP_REJECTED + 500) for v in gate.admit("bttsim/rig1/fit", b"zz", (i, 0), "x"))
    assert kept == KEEP_REJECTED and gate.rejected_by_key["bttsim/rig1/fit"] == KEEP_REJECTED + 500
    assert gate.missing() == {}


def meta_run_id(meta) -> str:
    from bttsim_stream.bus import codec

    return codec.decode_run_metadata(meta.payload, meta.key).body.run_id


def test_a_gate_that_follows_the_processor_needs_its_report(run_messages):
    """Following the processor, a run whose acquisition is whole but whose resonance report
    never came is incomplete, and says so; the report (number 0) makes it complete. Not
    following it, the report is not asked for."""
    from bttsim_stream.bus.admission import RecordGate
    from bttsim_stream.process.resonance import ResonancePeaks, resonance_report

    meta, msgs = run_messages
    nb = codec.decode_run_metadata(meta.payload, meta.key).body.n_blades
    peaks = ResonancePeaks(revolution=np.arange(nb, dtype=float), amp_pkpk_m=np.full(nb, 1e-3),
                           freq_hz=np.full(nb, 300.0), damping_ratio=np.full(nb, np.nan), method="max")
    report = codec.encode_resonance_report(codec.Header(meta_run_id(meta), 0, 11, msgs[-1].log_time_ns * 1e-9),
                                           resonance_report(peaks, nd=1, eo=8, cn=1.4))
    gates = {follows: RecordGate("rig1", report=follows) for follows in (False, True)}
    for gate in gates.values():
        for m in [meta, *msgs]:
            _admit(gate, m)
    assert gates[False].completeness("rig1")["complete"] is True
    assert gates[True].missing(report=False) == {}  # before it came, the report is no gap
    c = gates[True].completeness("rig1")
    assert c["complete"] is False and c["missing"] == 1
    assert c["missing_by_key"] == {"bttsim/rig1/resonance": {"head": 1, "gaps": 0, "tail": 0}}
    assert "no resonance report from the processor (rig1)" in c["incomplete"]
    (v,) = gates[True].admit("bttsim/rig1/resonance", report, (0, msgs[-1].log_time_ns), "processor")
    assert v.action == "write", v
    c = gates[True].completeness("rig1")
    assert c["complete"] is True and c["missing"] == 0 and c["incomplete"] == ""


def test_the_gate_counts_head_gaps_and_tail_and_a_late_number_closes_its_gap(run_messages):
    from bttsim_stream.bus.admission import RecordGate

    meta, msgs = run_messages
    gate = RecordGate("rig1")
    _admit(gate, meta)
    opr = [m for m in msgs if m.key == "bttsim/rig1/opr"]
    n = len(opr)
    for m in msgs:
        if not (m.key == "bttsim/rig1/opr" and m.seq in (0, 4, 5, n - 1)):
            _admit(gate, m)
    assert gate.missing()["bttsim/rig1/opr"].to_dict() == {"head": 1, "gaps": 2, "tail": 1}
    assert gate.jumps == 2  # the first number came after 0, then 3 -> 6
    for m in opr:  # a publisher's cache, replayed: the missing ones are written, the rest duplicates
        _admit(gate, m)
    assert gate.missing() == {} and gate.duplicates == n - 4
    # a key whose metadata never came: refused at the end, not written
    other = RecordGate("rig1")
    _admit(other, opr[0])
    assert [(v.action, v.reason) for v in other.finish()] == [("reject", "no run metadata received for its rig")]


def _library_read(path) -> tuple:
    """What the mcap library's own reader makes of a file, as :func:`read_recording` read it
    before it parsed chunks and message indexes itself: ``(messages, truncated, metadata)``
    or the one-line error."""
    from mcap.exceptions import EndOfFile
    from mcap.records import Channel, Footer, Header, Metadata
    from mcap.stream_reader import StreamReader

    scan = mcap_io._Scan(str(path))
    out, channels, truncated = [], {}, False
    with open(path, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        magic = f.read(8)
        if magic != mcap_io.MCAP_MAGIC:
            if magic and mcap_io.MCAP_MAGIC.startswith(magic):
                return [], True, {}
            return f"{path}: not an MCAP file"
        strict = mcap_io._StrictFile(f, size, 8)
        it = iter(StreamReader(strict, skip_magic=True, emit_chunks=True).records)
        first = True
        try:
            while True:
                start = strict.pos
                try:
                    rec = next(it)
                except StopIteration:
                    break
                except EndOfFile:
                    truncated = True
                    break
                except Exception as exc:
                    raise scan.corrupt(f"record at byte {start}: {mcap_io._one_line(exc)}") from None
                if first and not isinstance(rec, Header):
                    raise scan.corrupt("the first record is not a header")
                first = False
                if isinstance(rec, Chunk):
                    try:
                        inner = breakup_chunk(rec, validate_crc=True)
                    except Exception as exc:
                        raise scan.corrupt(f"chunk at byte {start}: {mcap_io._one_line(exc)}") from None
                else:
                    if isinstance(rec, Metadata):
                        scan.metadata[rec.name] = dict(rec.metadata)
                    elif isinstance(rec, Footer):
                        mcap_io._check_summary_crc(scan, f, rec, start)
                    inner = [rec]
                for r in inner:
                    if isinstance(r, Message):
                        if r.channel_id not in channels:
                            raise scan.corrupt(f"message on unknown channel {r.channel_id}")
                        out.append((channels[r.channel_id], r.data, r.log_time, r.sequence))
                    elif isinstance(r, Channel):
                        channels[r.id] = r.topic
        except BttsimError as exc:
            return str(exc)
    return out, truncated, scan.metadata


def _our_read(path):
    try:
        rec = read_recording(path)
    except BttsimError as exc:
        return str(exc)
    return [(m.key, m.payload, m.log_time_ns, m.seq) for m in rec.messages], rec.truncated, rec.metadata


def test_the_reader_reads_as_the_mcap_library_does(chunked, tmp_path):
    """Chunks and message indexes are parsed here, not by the library: on the file and on
    hundreds of damaged copies of it (bytes changed in record heads, lengths and chunk
    fields, cuts), the messages, the cut and every error are the library's."""
    path, chunks = chunked
    data = path.read_bytes()
    assert _our_read(path) == _library_read(path)
    rng = np.random.default_rng(7)
    heads = [c.chunk_start_offset for c in chunks] + [c.chunk_start_offset + c.chunk_length for c in chunks]
    bad = tmp_path / "bad.mcap"
    kinds = set()
    for trial in range(400):
        copy = bytearray(data)
        at = int(rng.choice(heads)) + int(rng.integers(0, 60))
        if trial % 5 == 4:
            copy = copy[:at]
        else:
            copy[at] = int(rng.integers(0, 256)) if trial % 2 else copy[at] ^ (1 << int(rng.integers(0, 8)))
        bad.write_bytes(bytes(copy))
        ours, theirs = _our_read(bad), _library_read(bad)
        assert ours == theirs, (trial, at)
        kinds.add(ours if isinstance(ours, str) and "record at" not in ours else type(ours).__name__)
    assert len(kinds) > 5  # the damage took many forms


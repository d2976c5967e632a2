"""Protobuf codec: exact round trips, sequence numbers, determinism, refusal of bad payloads,
and the committed generated code being current."""

import importlib.metadata
import importlib.util
import math
import sys
from pathlib import Path

import numpy as np
import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

from bttsim_stream.errors import BttsimError
from bttsim_stream.io import codec
from bttsim_stream.sim.core import RevolutionBatch, RunInfo

from _io_helpers import NB, NP, NR, TRUTH_2D, make_batch, make_info

REPO = Path(__file__).resolve().parents[1]
GENERATED = REPO / "bttsim_stream" / "io" / "_gen" / "bttsim" / "v1" / "bttsim_pb2.py"


@pytest.mark.parametrize("ticks", [False, True], ids=["float-clock", "ticks"])
def test_revolutions_round_trip_exactly(ticks):
    batch = make_batch(seed=1, ticks=ticks)
    encoded = codec.encode_revolutions(batch, "run-a", "rig1", {})
    assert len(encoded) == NR * (NP + 2)
    expected_keys = (["bttsim/rig1/opr"] + [f"bttsim/rig1/toa/{j}" for j in range(NP)]
                     + ["bttsim/rig1/truth"]) * NR
    assert [e.key for e in encoded] == expected_keys
    it = iter(encoded)
    for i in range(NR):
        key, payload, t_ns = next(it)
        opr = codec.decode_opr(payload, key)
        assert opr.header.run_id == "run-a" and opr.header.revolution == i
        assert opr.opr_s == batch.opr_s[i] and opr.header.t_s == batch.opr_s[i]
        assert t_ns == int(round(batch.opr_s[i] * 1e9))
        assert opr.opr_ticks == (int(batch.opr_ticks[i]) if ticks else None)
        for j in range(NP):
            key, payload, t_ns = next(it)
            toa = codec.decode_toa_batch(payload, key, n_blades=NB)
            assert toa.probe == j and toa.header.revolution == i
            np.testing.assert_array_equal(toa.toa_s, batch.toa_s[i, :, j])
            assert toa.toa_s.dtype == np.float64
            if ticks:
                np.testing.assert_array_equal(toa.toa_ticks, batch.toa_ticks[i, :, j])
                assert toa.toa_ticks.dtype == np.int64
            else:
                assert toa.toa_ticks is None
            assert toa.header.t_s == batch.toa_s[i, :, j].max()
            assert t_ns == int(round(batch.toa_s[i, :, j].max() * 1e9))
        key, payload, t_ns = next(it)
        tr = codec.decode_truth_batch(payload, key)
        assert (tr.n_blades, tr.n_probes) == (NB, NP)
        assert tr.opr_s == batch.truth.opr_s[i] and tr.omega_mean_rad_s == batch.truth.omega_mean[i]
        assert tr.header.t_s == batch.opr_s[i] and t_ns == int(round(batch.opr_s[i] * 1e9))
        for name in TRUTH_2D:
            np.testing.assert_array_equal(getattr(tr, name), getattr(batch.truth, name)[i])
        np.testing.assert_array_equal(tr.d_eqv_pkpk_m, batch.truth.d_eqv_pkpk_m[i])


def test_sequence_numbers_count_per_key_across_batches():
    seqs = {}
    first = codec.encode_revolutions(make_batch(seed=1), "r", "rig1", seqs)
    second = codec.encode_revolutions(make_batch(seed=2, rev0=NR), "r", "rig1", seqs)
    assert seqs == {"bttsim/rig1/opr": 2 * NR, "bttsim/rig1/truth": 2 * NR,
                    **{f"bttsim/rig1/toa/{j}": 2 * NR for j in range(NP)}}
    by_key = {}
    for key, payload, _ in first + second:
        by_key.setdefault(key, []).append(codec.decode_message(key, payload).header)
    for key, headers in by_key.items():
        assert [h.seq for h in headers] == list(range(2 * NR)), key
        assert [h.revolution for h in headers] == list(range(2 * NR)), key


def test_truth_can_be_left_out():
    encoded = codec.encode_revolutions(make_batch(), "r", "rig1", {}, include_truth=False)
    assert len(encoded) == NR * (NP + 1)
    assert not any(e.key.endswith("/truth") for e in encoded)


def test_encoding_is_deterministic():
    a = codec.encode_revolutions(make_batch(seed=3, ticks=True), "r", "rig1", {})
    b = codec.encode_revolutions(make_batch(seed=3, ticks=True), "r", "rig1", {})
    assert a == b


def test_log_time_of_a_toa_batch_ignores_missing_arrivals():
    batch = make_batch(seed=4)
    toa = batch.toa_s.copy()
    toa[0, 3, 2] = np.nan
    toa[1, :, 4] = np.nan
    batch = RevolutionBatch(revolution=batch.revolution, opr_s=batch.opr_s, toa_s=toa,
                            opr_ticks=None, toa_ticks=None, truth=batch.truth, residual_s=0.0,
                            bracketed=batch.bracketed)
    enc = {(e.key, codec.decode_message(e.key, e.payload).header.revolution): e
           for e in codec.encode_revolutions(batch, "r", "rig1", {})}
    assert enc["bttsim/rig1/toa/2", 0].log_time_ns == int(round(np.nanmax(toa[0, :, 2]) * 1e9))
    assert enc["bttsim/rig1/toa/4", 1].log_time_ns == int(round(batch.opr_s[1] * 1e9))
    back = codec.decode_toa_batch(enc["bttsim/rig1/toa/2", 0].payload)
    np.testing.assert_array_equal(back.toa_s, toa[0, :, 2])  # NaN survives


def test_log_time_ns():
    assert codec.log_time_ns(1.5) == 1_500_000_000
    assert codec.log_time_ns(-1e-6) == 0
    assert codec.log_time_ns(math.nan) == 0


def test_run_metadata_round_trip():
    info = make_info()
    payload = codec.encode_run_metadata(info, "run-a", "[run]\nseed = 1\n", "0.1.0", True)
    meta = codec.decode_run_metadata(payload, "bttsim/rig1/meta")
    assert (meta.run_id, meta.rig, meta.header.run_id, meta.header.revolution) == \
        ("run-a", "rig1", "run-a", -1)
    assert meta.scenario_toml == "[run]\nseed = 1\n" and meta.software_version == "0.1.0"
    assert meta.has_truth is True and meta.tick_s == 1 / 80e6
    back = meta.to_run_info()
    for name in RunInfo.__dataclass_fields__:
        got, want = getattr(back, name), getattr(info, name)
        if isinstance(want, np.ndarray):
            np.testing.assert_array_equal(got, want)
        else:
            assert got == want, name
    unclocked = codec.decode_run_metadata(codec.encode_run_metadata(
        make_info(clock_hz=0.0), "r", "", "0.1.0", False))
    assert unclocked.tick_s == 0.0 and unclocked.has_truth is False


def test_blade_fits_round_trip():
    rng = np.random.default_rng(5)
    arrays = {name: rng.standard_normal(NB) for name in
              ("amp_pkpk_m", "phase_rad", "dc_m", "residual_m", "amp_std_m")}
    seqs = {}
    key, payload, t_ns = codec.encode_blade_fits(run_id="r", rig="rig1", seqs=seqs, revolution=7,
                                                 t_s=2.5, engine_order=8, omega_mean_rad_s=270.0,
                                                 cn=1.4, **arrays)
    assert key == "bttsim/rig1/fit" and t_ns == 2_500_000_000 and seqs == {key: 1}
    fits = codec.decode_blade_fits(payload, key)
    assert (fits.n_blades, fits.engine_order, fits.cn, fits.header.revolution) == (NB, 8, 1.4, 7)
    assert fits.freq_hz == 8 * 270.0 / (2 * math.pi)  # Eq. 17
    for name, values in arrays.items():
        np.testing.assert_array_equal(getattr(fits, name), values)


def test_travelling_wave_round_trip_and_dominant_nd():
    fwd = np.array([0.1, 0.2, 0.9, 0.0])
    bwd = np.array([0.1, 0.0, 0.3, 1.5])
    key, payload, _ = codec.encode_travelling_wave(run_id="r", rig="rig1", seqs={}, revolution=2,
                                                   t_s=0.1, probe=3, forward_m=fwd, backward_m=bwd)
    tw = codec.decode_travelling_wave(payload, key)
    assert key == "bttsim/rig1/tw/3" and tw.probe == 3 and tw.n_nd == 4
    assert tw.dominant_nd == -3
    np.testing.assert_array_equal(tw.forward_m, fwd)
    np.testing.assert_array_equal(tw.backward_m, bwd)
    _, payload, _ = codec.encode_travelling_wave(run_id="r", rig="rig1", seqs={}, revolution=2,
                                                 t_s=0.1, probe=3, forward_m=fwd, backward_m=bwd / 10)
    assert codec.decode_travelling_wave(payload).dominant_nd == 2


def _summary(truth: bool) -> dict:
    blades = []
    for b in range(3):
        row = {"blade": b, "amp_pkpk_m": 2.3e-3 + b * 1e-5, "freq_hz": 344.1 + b * 0.01}
        if truth:
            row.update(truth_amp_pkpk_m=2.37e-3, truth_freq_hz=344.16, E_A_pct=1.0 + b,
                       E_f_pct=0.01 * b)
        blades.append(row)
    out = {"nd": 1, "eo": 8, "cn": 1.4, "blades": blades}
    if truth:
        out.update(mean_E_A_pct=2.0, max_E_A_pct=3.0, mean_E_f_pct=0.01, max_E_f_pct=0.02)
    return out


@pytest.mark.parametrize("truth", [True, False], ids=["with-truth", "blind"])
def test_resonance_report_round_trip(truth):
    summary = _summary(truth)
    key, payload, _ = codec.encode_resonance_report(summary, run_id="r", rig="rig1", seqs={})
    report = codec.decode_resonance_report(payload, key)
    assert key == "bttsim/rig1/resonance" and report.has_truth is truth
    assert report.to_summary() == summary


def _one_line_error(excinfo) -> str:
    text = str(excinfo.value)
    assert "\n" not in text
    return text


def test_random_bytes_are_refused():
    payload = np.random.default_rng(6).bytes(200)
    for decode in (codec.decode_opr, codec.decode_toa_batch, codec.decode_truth_batch,
                   codec.decode_run_metadata, codec.decode_blade_fits,
                   codec.decode_travelling_wave, codec.decode_resonance_report):
        with pytest.raises(BttsimError) as excinfo:
            decode(payload, "bttsim/rig1/x")
        assert _one_line_error(excinfo).startswith("bttsim/rig1/x: corrupt ")


def test_empty_payload_has_no_header():
    with pytest.raises(BttsimError, match=r"^bttsim.v1.Opr: corrupt Opr \(no header\)$"):
        codec.decode_opr(b"")


def test_oversized_payload_is_refused(monkeypatch):
    payload = codec.encode_revolutions(make_batch(), "r", "rig1", {})[1].payload
    monkeypatch.setattr(codec, "MAX_PAYLOAD_BYTES", len(payload) - 1)
    with pytest.raises(BttsimError, match="exceeds the .* byte limit") as excinfo:
        codec.decode_toa_batch(payload, "bttsim/rig1/toa/0")
    _one_line_error(excinfo)


def _varint(n: int) -> bytes:
    out = bytearray()
    while True:
        b, n = n & 0x7F, n >> 7
        out.append(b | (0x80 if n else 0))
        if not n:
            return bytes(out)


def _field(number: int, wire: int, body: bytes) -> bytes:
    """Raw protobuf field bytes; appended to a message they merge into it (no generated code)."""
    return _varint(number << 3 | wire) + body


def test_inconsistent_toa_batch_is_refused():
    encoded = codec.encode_revolutions(make_batch(ticks=True), "r", "rig1", {})
    key, payload, _ = encoded[1]
    # one more packed toa_ticks value (field 4) than toa_s
    bad = payload + _field(4, 2, _varint(1) + _varint(5))
    with pytest.raises(BttsimError, match=r"toa_ticks has 30 values, expected 29") as excinfo:
        codec.decode_toa_batch(bad, key)
    assert _one_line_error(excinfo).startswith("bttsim/rig1/toa/0: corrupt ToaBatch")
    with pytest.raises(BttsimError, match="expected n_blades = 28"):
        codec.decode_toa_batch(payload, key, n_blades=28)
    with pytest.raises(BttsimError, match="probe 0 on the key of probe 3"):
        codec.decode_toa_batch(payload, "bttsim/rig1/toa/3")


def test_inconsistent_truth_batch_is_refused():
    encoded = codec.encode_revolutions(make_batch(), "r", "rig1", {})
    key, payload, _ = encoded[NP + 1]
    bad = payload + _field(5, 0, _varint(4))  # n_probes = 4
    with pytest.raises(BttsimError, match=r"toa_s has 145 values, expected 116 for shape \(29, 4\)"):
        codec.decode_truth_batch(bad, key)


def test_decode_message_refuses_unknown_keys():
    with pytest.raises(BttsimError, match="not a bttsim key"):
        codec.decode_message("bttsim/rig1/bogus", b"")


def test_schema_names():
    assert codec.schema_name_for("ToaBatch") == "bttsim.v1.ToaBatch"
    assert codec.schema_name_for("bttsim.v1.Opr") == "bttsim.v1.Opr"
    with pytest.raises(BttsimError):
        codec.schema_name_for("Nope")


def test_file_descriptor_set_decodes_payloads_without_generated_code():
    fds = descriptor_pb2.FileDescriptorSet.FromString(codec.file_descriptor_set())
    assert [f.name for f in fds.file] == ["bttsim/v1/bttsim.proto"]
    pool = descriptor_pool.DescriptorPool()
    for f in fds.file:
        pool.Add(f)
    cls = message_factory.GetMessageClass(pool.FindMessageTypeByName("bttsim.v1.ToaBatch"))
    batch = make_batch(seed=7)
    msg = cls.FromString(codec.encode_revolutions(batch, "r", "rig1", {})[2].payload)
    assert msg.probe == 1 and msg.header.run_id == "r"
    assert list(msg.toa_s) == batch.toa_s[0, :, 1].tolist()


def _grpc_tools_or_skip():
    if importlib.util.find_spec("grpc_tools") is None:
        pytest.skip("grpcio-tools is not installed (pip install 'grpcio-tools==1.71.*'); "
                    "cannot check that the generated code is current")
    sys.path.insert(0, str(REPO / "scripts"))
    try:
        import gen_proto
    finally:
        sys.path.pop(0)
    return gen_proto


def test_generated_descriptor_matches_the_proto(tmp_path):
    """Any protoc: the committed code describes the current .proto."""
    _grpc_tools_or_skip()
    from grpc_tools import protoc

    out = tmp_path / "fds.pb"
    assert protoc.main(["protoc", f"-I{REPO / 'schemas'}", f"--descriptor_set_out={out}",
                        str(REPO / "schemas" / "bttsim" / "v1" / "bttsim.proto")]) == 0
    fresh = descriptor_pb2.FileDescriptorSet.FromString(out.read_bytes())
    for f in fresh.file:  # not kept in the generated module's descriptor
        for m in f.message_type:
            for fld in m.field:
                fld.ClearField("json_name")
    committed = descriptor_pb2.FileDescriptorSet.FromString(codec.file_descriptor_set())
    assert fresh == committed, "regenerate: python scripts/gen_proto.py"


def test_generated_code_is_byte_identical(tmp_path):
    """With the pinned protoc, regenerating gives the committed file byte for byte."""
    gen_proto = _grpc_tools_or_skip()
    version = importlib.metadata.version("grpcio-tools")
    if not version.startswith(gen_proto.PINNED_GRPC_TOOLS):
        pytest.skip(f"grpcio-tools {version} is not the pinned {gen_proto.PINNED_GRPC_TOOLS}x")
    path = gen_proto.generate(tmp_path)
    assert path.read_bytes() == GENERATED.read_bytes(), "regenerate: python scripts/gen_proto.py"

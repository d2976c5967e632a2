"""Protobuf codec: exact round trips to the library's dataclasses, determinism, refusal of bad
payloads, and the committed generated code being current."""

import importlib.metadata
import importlib.util
import math
import sys
from pathlib import Path

import numpy as np
import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

from bttsim_stream.bus import codec, codec_base
from bttsim_stream.bus.stream import MessageStream
from bttsim_stream.errors import BttsimError
from bttsim_stream.process.results import RevolutionFit
from bttsim_stream.process.resonance import ResonancePeaks, ResonanceReport, TruthPeaks, resonance_report
from bttsim_stream.process.travelling_wave import ProbeWave
from bttsim_stream.sim.core import RevolutionBatch, RunInfo, Truth

from _io_helpers import NB, NP, NR, TRUTH_2D, make_batch, make_info

REPO = Path(__file__).resolve().parents[1]
GENERATED = REPO / "bttsim_stream" / "bus" / "_gen" / "bttsim" / "v1" / "bttsim_pb2.py"


pytestmark = pytest.mark.unit


def _header(seq=0, revolution=-1, t_s=0.0) -> codec.Header:
    return codec.Header("run-a", seq, revolution, t_s)


@pytest.mark.parametrize("ticks", [False, True], ids=["float-clock", "ticks"])
def test_acquisition_messages_round_trip_exactly(ticks):
    batch = make_batch(seed=1, ticks=ticks)
    msgs = MessageStream("run-a", "rig1").acquisition(batch)
    assert len(msgs) == NR * (NP + 2)
    expected_keys = (["bttsim/rig1/opr"] + [f"bttsim/rig1/toa/{j}" for j in range(NP)]
                     + ["bttsim/rig1/truth"]) * NR
    assert [m.key for m in msgs] == expected_keys
    it = iter(msgs)
    for i in range(NR):
        m = next(it)
        opr = codec.decode_opr(m.payload, m.key)
        assert opr.header.run_id == "run-a" and opr.header.revolution == i and opr.header.seq == m.seq == i
        assert opr.body.opr_s == batch.opr_s[i] and opr.header.t_s == batch.opr_s[i]
        assert m.log_time_ns == int(round(batch.opr_s[i] * 1e9))
        assert opr.body.opr_ticks == (int(batch.opr_ticks[i]) if ticks else None)
        for j in range(NP):
            m = next(it)
            toa = codec.decode_toa_batch(m.payload, m.key, n_blades=NB)
            assert toa.body.probe == j and toa.header.revolution == i
            np.testing.assert_array_equal(toa.body.toa_s, batch.toa_s[i, :, j])
            assert toa.body.toa_s.dtype == np.float64
            if ticks:
                np.testing.assert_array_equal(toa.body.toa_ticks, batch.toa_ticks[i, :, j])
                assert toa.body.toa_ticks.dtype == np.int64
            else:
                assert toa.body.toa_ticks is None
            assert toa.header.t_s == batch.toa_s[i, :, j].max()
            assert m.log_time_ns == int(round(batch.toa_s[i, :, j].max() * 1e9))
        m = next(it)
        tr = codec.decode_truth(m.payload, m.key)
        assert isinstance(tr.body, Truth) and tr.body.toa_s.shape == (1, NB, NP)
        assert tr.body.opr_s[0] == batch.truth.opr_s[i] and tr.body.omega_mean[0] == batch.truth.omega_mean[i]
        assert tr.header.t_s == batch.opr_s[i] and m.log_time_ns == int(round(batch.opr_s[i] * 1e9))
        for name in TRUTH_2D:
            np.testing.assert_array_equal(getattr(tr.body, name)[0], getattr(batch.truth, name)[i])
        np.testing.assert_array_equal(tr.body.d_eqv_pkpk_m[0], batch.truth.d_eqv_pkpk_m[i])


def test_truth_can_be_left_out():
    msgs = MessageStream("r", "rig1").acquisition(make_batch(), include_truth=False)
    assert len(msgs) == NR * (NP + 1)
    assert not any(m.key.endswith("/truth") for m in msgs)


def test_encoding_is_deterministic():
    a = MessageStream("r", "rig1").acquisition(make_batch(seed=3, ticks=True))
    b = MessageStream("r", "rig1").acquisition(make_batch(seed=3, ticks=True))
    assert a == b


def test_log_time_of_a_toa_batch_ignores_missing_arrivals():
    batch = make_batch(seed=4)
    toa = batch.toa_s.copy()
    toa[0, 3, 2] = np.nan
    toa[1, :, 4] = np.nan
    batch = RevolutionBatch(revolution=batch.revolution, opr_s=batch.opr_s, toa_s=toa,
                            opr_ticks=None, toa_ticks=None, truth=batch.truth, residual_s=0.0,
                            bracketed=batch.bracketed)
    enc = {(m.key, codec.decode_message(m.key, m.payload).header.revolution): m
           for m in MessageStream("r", "rig1").acquisition(batch)}
    assert enc["bttsim/rig1/toa/2", 0].log_time_ns == int(round(np.nanmax(toa[0, :, 2]) * 1e9))
    assert enc["bttsim/rig1/toa/4", 1].log_time_ns == int(round(batch.opr_s[1] * 1e9))
    back = codec.decode_toa_batch(enc["bttsim/rig1/toa/2", 0].payload)
    np.testing.assert_array_equal(back.body.toa_s, toa[0, :, 2])  # NaN survives


def test_log_time_ns():
    assert codec.log_time_ns(1.5) == 1_500_000_000
    assert codec.log_time_ns(-1e-6) == 0
    assert codec.log_time_ns(math.nan) == 0


def _assert_same_info(got: RunInfo, want: RunInfo, skip=()) -> None:
    for name in RunInfo.__dataclass_fields__:
        if name in skip:
            continue
        a, b = getattr(got, name), getattr(want, name)
        if isinstance(b, np.ndarray) or isinstance(a, np.ndarray):
            np.testing.assert_array_equal(a, b, err_msg=name)
        else:
            assert a == b, name


def test_run_metadata_round_trip_is_the_run_info():
    fam = np.linspace(300.0, 2000.0, 3 * (NB // 2 + 1)).reshape(3, NB // 2 + 1)
    info = make_info(run_id="run-a", sensing_angles_rad=np.linspace(0, 6, NB), family_freq_hz=fam,
                     speed_range_rpm=(1000.0, 4000.0))
    d = codec.decode_run_metadata(codec.encode_run_metadata(_header(), info), "bttsim/rig1/meta")
    assert (d.header.run_id, d.header.revolution) == ("run-a", -1)
    assert isinstance(d.body, RunInfo) and d.body.tick_s == 1 / 80e6
    _assert_same_info(d.body, info)
    # the optional model data may be absent; the run id then comes from the header
    bare = make_info(clock_hz=0.0, has_truth=False)
    back = codec.decode_run_metadata(codec.encode_run_metadata(_header(), bare)).body
    assert back.tick_s == 0.0 and back.has_truth is False and back.run_id == "run-a"
    assert back.sensing_angles_rad is None and back.family_freq_hz is None
    assert back.family_speed_rad_s is None and back.family_freq_hz_at_speed is None
    _assert_same_info(back, bare, skip=("run_id",))


def _curves(n_speeds=5, n_families=3):
    """A speed-dependent Campbell table: (speeds (S,), zero-speed table, table at speeds)."""
    speeds = np.linspace(0.0, 500.0, n_speeds)
    fam = np.linspace(300.0, 2000.0, n_families * (NB // 2 + 1)).reshape(n_families, NB // 2 + 1)
    at_speed = np.sqrt(fam[None] ** 2 + 1.3 * (speeds[:, None, None] / (2 * np.pi)) ** 2)
    return speeds, fam, at_speed


def test_run_metadata_round_trip_with_family_curves():
    speeds, fam, at_speed = _curves()
    info = make_info(run_id="run-a", family_freq_hz=fam, family_speed_rad_s=speeds, family_freq_hz_at_speed=at_speed)
    back = codec.decode_run_metadata(codec.encode_run_metadata(_header(), info), "bttsim/rig1/meta").body
    assert back.family_freq_hz_at_speed.shape == (5, 3, NB // 2 + 1)
    _assert_same_info(back, info)
    # without the curves (a zero-speed model, or a message from before they existed): None
    flat = codec.decode_run_metadata(codec.encode_run_metadata(_header(), make_info(family_freq_hz=fam))).body
    np.testing.assert_array_equal(flat.family_freq_hz, fam)
    assert flat.family_speed_rad_s is None and flat.family_freq_hz_at_speed is None


def test_older_recording_metadata_decodes_without_family_curves():
    from bttsim_stream.bus import keys
    from bttsim_stream.bus.recording import read_recording

    meta = next(m for m in read_recording(REPO / "recordings" / "resonance_window.mcap").messages
                if keys.parse_key(m.key).kind == "meta")
    info = codec.decode_run_metadata(meta.payload, meta.key).body
    assert info.family_speed_rad_s is None and info.family_freq_hz_at_speed is None


@pytest.mark.parametrize("changes,words", [
    (dict(family_freq_hz_at_speed=None), "go together"),
    (dict(family_freq_hz=None), "needs family_freq_hz"),
    (dict(family_freq_hz_at_speed=np.ones((4, 3, NB // 2 + 1))), "family_freq_hz_at_speed: expected shape"),
    (dict(family_speed_rad_s=np.zeros((5, 1))), "family_speed_rad_s: expected shape"),
], ids=["no-table", "no-families", "wrong-speeds", "2-d-speeds"])
def test_run_metadata_refuses_to_encode_inconsistent_family_curves(changes, words):
    speeds, fam, at_speed = _curves()
    base = dict(family_freq_hz=fam, family_speed_rad_s=speeds, family_freq_hz_at_speed=at_speed)
    with pytest.raises(ValueError, match=words):
        codec.encode_run_metadata(_header(), make_info(**{**base, **changes}))


def _forged_curves(n_speeds=5, **changes) -> bytes:
    """A RunMetadata payload with family curves, then ``changes`` applied to the protobuf."""
    speeds, fam, at_speed = _curves(n_speeds)
    info = make_info(family_freq_hz=fam, family_speed_rad_s=speeds, family_freq_hz_at_speed=at_speed)
    m = codec._pb.RunMetadata()
    m.ParseFromString(codec.encode_run_metadata(_header(), info))
    for name, value in changes.items():
        if isinstance(value, list):
            del getattr(m, name)[:]
            getattr(m, name).extend(value)
        else:
            setattr(m, name, value)
    return m.SerializeToString()


_S5 = [0.0, 100.0, 200.0, 300.0, 400.0]


@pytest.mark.parametrize("n_speeds,changes,words", [
    (5, dict(family_speed_rad_s=[0.0, 100.0, 100.0, 300.0, 400.0]), "ascending from 0"),
    (5, dict(family_speed_rad_s=[0.0, 300.0, 200.0, 350.0, 400.0]), "ascending from 0"),
    (5, dict(family_speed_rad_s=[10.0, 100.0, 200.0, 300.0, 400.0]), "ascending from 0"),
    (5, dict(family_speed_rad_s=[0.0, 100.0, math.nan, 300.0, 400.0]), "family_speed_rad_s"),
    (5, dict(family_speed_rad_s=[0.0, 100.0, 200.0, 300.0, math.inf]), "family_speed_rad_s"),
    (5, dict(family_speed_rad_s=[0.0, 100.0, 200.0, 300.0, 1e300]), "at most"),
    (2, dict(family_speed_rad_s=[0.0, 1e-300]), "at least 0.001 rad/s apart"),
    (2, dict(family_speed_rad_s=[0.0]), "2..64"),
    (64, dict(family_speed_rad_s=list(np.arange(65.0))), "2..64"),
    (5, dict(family_speed_rad_s=_S5[:4]), "family_freq_hz_at_speed has"),
    (5, dict(family_speed_rad_s=[]), "family_freq_hz_at_speed has"),
    (5, dict(family_freq_hz_at_speed=[350.0] * (5 * 3 * (NB // 2 + 1) - 1)), "family_freq_hz_at_speed has"),
    (5, dict(family_freq_hz_at_speed=[350.0] * 7 + [math.nan] + [350.0] * (5 * 3 * (NB // 2 + 1) - 8)),
     "family_freq_hz_at_speed must be finite"),
    (5, dict(family_freq_hz_at_speed=[-1.0] * (5 * 3 * (NB // 2 + 1))), "family_freq_hz_at_speed must be finite"),
    (5, dict(family_freq_hz_at_speed=[1e300] * (5 * 3 * (NB // 2 + 1))), "family_freq_hz_at_speed must be finite"),
    (5, dict(n_families=0, family_freq_hz=[]), "without family_freq_hz"),
], ids=["repeated", "descending", "not-from-0", "nan", "inf", "too-fast", "tiny-step", "one-speed", "65-speeds",
        "short-speeds", "no-speeds", "short-table", "nan-table", "negative-table", "huge-table", "no-families"])
def test_run_metadata_refuses_forged_family_curves(n_speeds, changes, words):
    with pytest.raises(BttsimError, match="corrupt RunMetadata") as info:
        codec.decode_run_metadata(_forged_curves(n_speeds, **changes), "bttsim/rig1/meta")
    assert words in str(info.value) and "\n" not in str(info.value)


def test_run_metadata_refuses_a_wrong_family_table():
    with pytest.raises(ValueError, match="family_freq_hz"):
        codec.encode_run_metadata(_header(), make_info(family_freq_hz=np.ones((2, 3))))


@pytest.mark.parametrize("changes,words", [
    (dict(tip_radius_m=0.0), "tip_radius_m"),
    (dict(tip_radius_m=math.nan), "tip_radius_m"),
    (dict(probe_angles_rad=np.array([1e10, 0.26, 0.41, 3.8, 5.2])), "probe_angles_rad"),
    (dict(probe_angles_rad=np.array([0.1, 0.1, 0.41, 3.8, 5.2])), "distinct"),
    (dict(stagger_deg=90.0), "stagger_deg"),
    (dict(clock_hz=-5.0), "clock_hz"),
    (dict(engine_orders=(0,)), "engine order 0"),
    (dict(engine_orders=(2**31,)), "engine order"),
    (dict(nodal_diameters=(NB,)), "nodal diameter"),
    (dict(n_revolutions=2**62), "n_revolutions"),
    (dict(n_revolutions=0), "n_revolutions = 0"),
    (dict(speed_range_rpm=(3000.0, 1000.0)), "the lowest above the highest"),
    (dict(n_blades=1000, sensing_angles_rad=None), "n_blades = 1000"),
    (dict(speed_range_rpm=(math.nan, 1.0)), "speed_min_rpm"),
    (dict(family_freq_hz=-np.ones((2, NB // 2 + 1))), "family_freq_hz"),
], ids=lambda v: next(iter(v)) if isinstance(v, dict) else None)
def test_run_metadata_refuses_an_impossible_run(changes, words):
    payload = codec.encode_run_metadata(_header(), make_info(**changes))
    with pytest.raises(BttsimError, match="corrupt RunMetadata") as info:
        codec.decode_run_metadata(payload, "bttsim/rig1/meta")
    assert words in str(info.value) and "\n" not in str(info.value)


@pytest.mark.parametrize("t_s", [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize("key", ["bttsim/rig1/meta", "bttsim/rig1/opr", "bttsim/rig1/fit"])
def test_a_header_time_that_is_not_finite_is_refused(key, t_s):
    """Every message's header time is a time: NaN or infinite is corrupt, on every key."""
    good = {"bttsim/rig1/meta": lambda h: codec.encode_run_metadata(h, make_info()),
            "bttsim/rig1/opr": lambda h: codec.encode_opr(h, codec.OprPulse(opr_s=1.0)),
            "bttsim/rig1/fit": lambda h: codec.encode_fit(h, RevolutionFit(
                engine_order=8, omega_rad_s=270.0, freq_hz=8 * 270.0 / (2 * math.pi), cn=1.4,
                **{n: np.zeros(NB) for n in ("amp_pkpk_m", "phase_rad", "dc_m", "residual_rms_m", "amp_std_m")}))}
    codec.decode_message(key, good[key](_header(0, 0, 1.0)))
    with pytest.raises(BttsimError, match="header time .* is not finite"):
        codec.decode_message(key, good[key](_header(0, 0, t_s)))
    with pytest.raises(BttsimError, match="header time .* is not finite"):
        codec.check_message(key, good[key](_header(0, 0, t_s)))


def test_fit_round_trip():
    rng = np.random.default_rng(5)
    arrays = {name: rng.standard_normal(NB) for name in
              ("amp_pkpk_m", "phase_rad", "dc_m", "residual_rms_m", "amp_std_m")}
    fit = RevolutionFit(engine_order=8, omega_rad_s=270.0, freq_hz=8 * 270.0 / (2 * math.pi), cn=1.4, **arrays)
    d = codec.decode_fit(codec.encode_fit(_header(3, 7, 2.5), fit), "bttsim/rig1/fit")
    assert (d.header.seq, d.header.revolution, d.header.t_s) == (3, 7, 2.5)
    got = d.body
    assert (got.n_blades, got.engine_order, got.cn, got.omega_rad_s) == (NB, 8, 1.4, 270.0)
    assert got.freq_hz == fit.freq_hz
    for name, values in arrays.items():
        np.testing.assert_array_equal(getattr(got, name), values)


def test_probe_wave_round_trip():
    fwd = np.array([0.1, 0.2, 0.9, 0.0])
    bwd = np.array([0.1, 0.0, 0.3, 1.5])
    wave = ProbeWave(probe=3, forward_m=fwd, backward_m=bwd, nd=-3)
    d = codec.decode_probe_wave(codec.encode_probe_wave(_header(0, 2, 0.1), wave), "bttsim/rig1/tw/3")
    assert d.body.probe == 3 and d.body.n_nd == 4 and d.body.nd == -3
    np.testing.assert_array_equal(d.body.forward_m, fwd)
    np.testing.assert_array_equal(d.body.backward_m, bwd)
    np.testing.assert_array_equal(d.body.signed_spectrum(), [0.0, 0.9, 0.2, 0.1, 0.0, 0.3, 1.5])
    with pytest.raises(BttsimError, match="probe 3 on the key of probe 1"):
        codec.decode_probe_wave(codec.encode_probe_wave(_header(), wave), "bttsim/rig1/tw/1")


_EDGE_VALUES = (0.0, -0.0, 1.5, 1e308, 5e-324, -5e-324, -1.0, math.nan, math.inf, -math.inf)


@pytest.mark.parametrize("where", ["forward_m", "backward_m"])
def test_probe_wave_magnitudes_are_refused_as_numpy_would_judge_them(where):
    """A magnitude is >= 0 or NaN: each value at the edges, in one field or the other, among
    others, refused exactly when numpy's NaN-skipping min is negative or its max infinite (the
    rule the decoder applies without making an array)."""
    for value in _EDGE_VALUES:
        for others in ([], [0.3, math.nan], [2.0, 0.0, 7.0]):
            values = np.array(others[:1] + [value] + others[1:])
            rest = np.full(values.size, 0.25)
            fwd, bwd = (values, rest) if where == "forward_m" else (rest, values)
            payload = codec.encode_probe_wave(_header(), ProbeWave(probe=0, forward_m=fwd, backward_m=bwd, nd=0))
            with np.errstate(invalid="ignore"):
                bad = bool(np.fmin.reduce(values) < 0 or np.fmax.reduce(values) == np.inf)
            for decode in (codec.decode_message, codec.check_message):
                if bad:
                    with pytest.raises(BttsimError, match=f"{where} must be >= 0"):
                        decode("bttsim/rig1/tw/0", payload)
                else:
                    decode("bttsim/rig1/tw/0", payload)
            if not bad:
                np.testing.assert_array_equal(codec.decode_probe_wave(payload).body.forward_m, fwd)


def _report(truth: bool) -> ResonanceReport:
    nb = 3
    peaks = ResonancePeaks(revolution=np.array([10.0, 11.0, 12.0]), amp_pkpk_m=2.3e-3 + 1e-5 * np.arange(nb),
                           freq_hz=344.1 + 0.01 * np.arange(nb), damping_ratio=np.full(nb, np.nan), method="max")
    if not truth:
        return resonance_report(peaks, nd=-1, eo=8, cn=1.4)
    tp = TruthPeaks(revolution=np.array([10, 11, 12]), amp_pkpk_m=np.full(nb, 2.37e-3), freq_hz=np.full(nb, 344.16))
    return resonance_report(peaks, nd=1, eo=8, cn=1.4, truth=tp)


@pytest.mark.parametrize("truth", [True, False], ids=["with-truth", "blind"])
def test_resonance_report_round_trip(truth):
    report = _report(truth)
    d = codec.decode_resonance_report(codec.encode_resonance_report(_header(), report), "bttsim/rig1/resonance")
    assert isinstance(d.body, ResonanceReport) and (d.body.truth is not None) is truth
    assert d.body.to_summary() == report.to_summary()
    assert d.body.peaks.method == "reported"


def _entry(kind, eo, truth, method="sdof"):
    from bttsim_stream.process.resonance import Detection, ResonanceEntry

    nb = 3
    peaks = ResonancePeaks(revolution=np.array([100.0, 101.5, np.nan]),
                           amp_pkpk_m=np.array([2.3e-3, 2.4e-3, np.nan]), freq_hz=np.array([344.1, 344.2, np.nan]),
                           damping_ratio=np.array([0.0096, 0.0097, np.nan]), method=method,
                           phase_rad=np.array([0.1, -2.0, np.nan]), amp_std_m=np.array([1e-6, 2e-6, np.nan]),
                           freq_std_hz=np.array([0.01, 0.02, np.nan]),
                           steady_amp_pkpk_m=np.array([2.31e-3, 2.41e-3, np.nan]),
                           natural_freq_hz=np.array([343.9, 344.0, np.nan]))
    det = (Detection("prominence_ratio", 23.7, 2.0, 1e9, 8.0) if kind == "crossing"
           else Detection("amplitude_snr", 55.0, 5.0, 55.0, 5.0))
    e = ResonanceEntry(kind=kind, eo=eo, nd=-3, cn=1.43, method=method if kind == "crossing" else "mean", rpm=2580.5,
                       freq_hz=344.15, damping_ratio=0.00965 if method == "sdof" else math.nan, detection=det,
                       first_revolution=1479, last_revolution=2607, peak_revolution=2043 if kind == "crossing" else -1,
                       peaks=peaks, sweep_rate=4.1e-6 if method == "sdof" else math.nan, zeroing_correction=0.25)
    if truth:
        e = e.with_truth(TruthPeaks(revolution=np.array([99, 101, 102]), amp_pkpk_m=np.full(nb, 2.37e-3),
                                    freq_hz=np.full(nb, 344.16)))
    return e


@pytest.mark.parametrize("truth", [True, False], ids=["with-truth", "blind"])
@pytest.mark.parametrize("status", ["resonance", "steady", "none"])
def test_resonance_report_with_entries_round_trip(truth, status):
    """Issue 12: status, every resonance and dwell (blade tables with phase, uncertainty, SDOF
    fields, NaN kept), detection statistics, revolutions, the zeroing reference and notes."""
    res = (_entry("crossing", 8, truth), _entry("crossing", 9, truth, method="peak")) if status == "resonance" else ()
    steady = (_entry("dwell", 8, truth),) if status != "none" else ()
    ref = {"method": "calibrated", "first": 0, "last": 63, "contamination_pct": 2.35,
           "reason": "the slowest quiet window"}
    report = ResonanceReport.from_entries(res, steady, eo=8, cn=1.43, reference=ref,
                                          notes=("a note", "another") if status == "none" else ())
    assert report.status == status
    s = report.to_summary()
    d = codec.decode_resonance_report(codec.encode_resonance_report(_header(), report), "bttsim/rig1/resonance")
    back = d.body.to_summary()
    assert back.keys() == s.keys() and back["status"] == status and back["notes"] == s["notes"]
    assert back["reference"] == s["reference"]
    _assert_close(back, s)
    if status == "none":
        assert back["blades"] == [] and "mean_E_A_pct" not in back


def _assert_close(a, b, path="summary"):
    """Equal structure, equal strings and ints, floats equal to 1e-12 relative (NaN == NaN)."""
    assert type(a) is type(b) or {type(a), type(b)} <= {int, float}, path
    if isinstance(a, dict):
        assert a.keys() == b.keys(), path
        for k in a:
            _assert_close(a[k], b[k], f"{path}.{k}")
    elif isinstance(a, list):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            _assert_close(x, y, f"{path}[{i}]")
    elif isinstance(a, float):
        assert a == pytest.approx(b, rel=1e-12, nan_ok=True), path
    else:
        assert a == b, path


def test_resonance_report_from_an_older_writer_decodes():
    """A payload without the issue-12 fields (status "") still decodes to the legacy report."""
    report = _report(True)
    payload = codec.encode_resonance_report(_header(), report)
    d = codec.decode_resonance_report(payload)
    assert d.body.status == "" and d.body.resonances == () and d.body.to_summary()["status"] == "resonance"


def _one_line_error(excinfo) -> str:
    text = str(excinfo.value)
    assert "\n" not in text
    return text


def test_random_bytes_are_refused():
    payload = np.random.default_rng(6).bytes(200)
    for decode in (codec.decode_opr, codec.decode_toa_batch, codec.decode_truth, codec.decode_signal_batch,
                   codec.decode_run_metadata, codec.decode_fit,
                   codec.decode_probe_wave, codec.decode_resonance_report):
        with pytest.raises(BttsimError) as excinfo:
            decode(payload, "bttsim/rig1/x")
        assert _one_line_error(excinfo).startswith("bttsim/rig1/x: corrupt ")


def test_empty_payload_has_no_header():
    with pytest.raises(BttsimError, match=r"^bttsim.v1.Opr: corrupt Opr \(no header\)$"):
        codec.decode_opr(b"")


def test_oversized_payload_is_refused(monkeypatch):
    payload = MessageStream("r", "rig1").acquisition(make_batch())[1].payload
    monkeypatch.setattr(codec_base, "MAX_PAYLOAD_BYTES", len(payload) - 1)  # the limit of every decoder
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
    m = MessageStream("r", "rig1").acquisition(make_batch(ticks=True))[1]
    key, payload = m.key, m.payload
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
    m = MessageStream("r", "rig1").acquisition(make_batch())[NP + 1]
    key, payload = m.key, m.payload
    bad = payload + _field(5, 0, _varint(4))  # n_probes = 4
    with pytest.raises(BttsimError, match=r"toa_s has 145 values, expected 116 for shape \(29, 4\)"):
        codec.decode_truth(bad, key)


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
    msg = cls.FromString(MessageStream("r", "rig1").acquisition(batch)[2].payload)
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


# --- batch encoders: the same bytes as one message at a time ------------------------------

_EDGE_T = [0.0, -0.0, 1.5, -2.25, float("nan"), float("inf"), -float("inf"), 5e-324, 1e300, 130.0 + 1e-14]
_EDGE_I = [0, 1, 127, 128, 16383, 16384, 2 ** 35, 2 ** 62, -1, -(2 ** 40)]


def _edge_rows(rng, n):
    """n values mixing the edge cases and random ones."""
    t = np.array([_EDGE_T[i % len(_EDGE_T)] if i < 2 * len(_EDGE_T) else rng.normal() * 100 for i in range(n)])
    k = np.array([_EDGE_I[i % len(_EDGE_I)] if i < 2 * len(_EDGE_I) else int(rng.integers(-5, 10 ** 9))
                  for i in range(n)], dtype=np.int64)
    return t, k


@pytest.mark.parametrize("run_id", ["", "run-a", "r" * 200])
def test_batch_encoders_are_byte_identical_to_the_message_encoders(run_id):
    rng = np.random.default_rng(7)
    n, nb, npr = 40, 3, 2
    t, k = _edge_rows(rng, n)
    seq = np.abs(k[::-1])
    rev = k
    opr, ticks = t[::-1].copy(), k[::-1].copy()
    for tk in (None, ticks):
        got = codec.encode_opr_batch(run_id, seq, rev, t, opr, tk)
        for i in range(n):
            ref = codec.encode_opr(codec.Header(run_id, int(seq[i]), int(rev[i]), float(t[i])),
                                   codec.OprPulse(float(opr[i]), None if tk is None else int(tk[i])))
            assert got[i] == ref, i
    toa = np.concatenate([t, t[::-1], rng.normal(size=n) * 1e3])[: n * nb].reshape(n, nb)
    toa_ticks = np.concatenate([k, k[::-1], rng.integers(-3, 2 ** 40, n)])[: n * nb].reshape(n, nb)
    probe = np.abs(k) % 7
    for tk in (None, toa_ticks):
        got = codec.encode_toa_batches(run_id, seq, rev, t, probe, toa, tk)
        for i in range(n):
            ref = codec.encode_toa_batch(codec.Header(run_id, int(seq[i]), int(rev[i]), float(t[i])), int(probe[i]),
                                         toa[i].tolist(), None if tk is None else tk[i].tolist())
            assert got[i] == ref, i
    arrays = {name: rng.normal(size=(n, nb, npr)) for name in TRUTH_2D}
    arrays["toa_s"].flat[: len(_EDGE_T)] = _EDGE_T
    truth = Truth(opr_s=opr, omega_mean=t, d_eqv_pkpk_m=rng.normal(size=(n, nb)), **arrays)
    got = codec.encode_truth_batch(run_id, seq, rev, t, truth)
    for i in range(n):
        ref = codec.encode_truth(codec.Header(run_id, int(seq[i]), int(rev[i]), float(t[i])), truth, i)
        assert got[i] == ref, i


def test_log_times_ns_is_log_time_ns():
    t, _ = _edge_rows(np.random.default_rng(2), 60)
    t = np.concatenate([t, [0.5e-9, 1.5e-9, 2.5e-9, -0.4e-9, 9.3e9, 9.2e9, 1e-10]])
    t = t[~(np.abs(t) > 1e299)]  # log_time_ns overflows there (OverflowError); log_times_ns clamps
    assert codec.log_times_ns(t).tolist() == [codec.log_time_ns(x) for x in t]


# -- raw probe signals ---------------------------------------------------------------------


def _signal_batch(**changes) -> codec.SignalBatch:
    rng = np.random.default_rng(11)
    n_samp = rng.integers(2, 40, NB)
    fields = dict(probe=3, sample_rate_hz=2e6, range_lo_v=-0.5, lsb_v=2.0 / 4095, bits=12, trigger="constant_fraction",
                  level_v=0.3155, hysteresis_v=0.05, edge="rising", first_sample=rng.integers(0, 1 << 40, NB),
                  n_samples=n_samp, codes=rng.integers(0, 4096, int(n_samp.sum())),
                  toa_s=np.where(np.arange(NB) == 4, np.nan, rng.uniform(1, 2, NB)),
                  n_edges=np.where(np.arange(NB) == 4, 0, 1 + (np.arange(NB) == 7)), fraction=0.4)
    fields.update(changes)
    return codec.SignalBatch(**fields)


def test_signal_batch_round_trip_and_windows():
    b = _signal_batch()
    d = codec.decode_message("bttsim/rig1/signal/3", codec.encode_signal_batch(_header(5, 12, 1.5), b))
    assert d.header == _header(5, 12, 1.5)
    for f in codec.SignalBatch.__slots__:
        np.testing.assert_array_equal(getattr(d.body, f), getattr(b, f), err_msg=f)
    t, v = d.body.window(2)
    start = int(b.n_samples[:2].sum())
    np.testing.assert_array_equal(t, (b.first_sample[2] + np.arange(b.n_samples[2])) / 2e6)
    np.testing.assert_array_equal(v, -0.5 + b.codes[start:start + b.n_samples[2]] * (2.0 / 4095))


@pytest.mark.parametrize("changes, words", [
    (dict(codes=np.full(int(_signal_batch().n_samples.sum()), 4096)), "an ADC code above 2^12 - 1"),
    (dict(codes=np.zeros(3, int)), "codes has 3 values, expected"),
    (dict(n_samples=np.full(NB, codec.MAX_WINDOW_SAMPLES + 1),
          codes=np.zeros(NB * (codec.MAX_WINDOW_SAMPLES + 1), int)),
     "n_samples must be in [1, 65536]"),
    (dict(toa_s=np.zeros(NB - 1)), f"toa_s has {NB - 1} values, expected {NB}"),
    (dict(sample_rate_hz=math.nan), "sample_rate_hz = nan (finite, >= 1)"),
    (dict(lsb_v=0.0), "lsb_v = 0.0 (finite, > 0)"),
    (dict(level_v=math.inf), "level_v = inf (finite)"),
    (dict(trigger="cfd"), "trigger 'cfd'"),
    (dict(bits=0), "bits = 0"),
    (dict(fraction=1.5), "fraction = 1.5"),
    # finite fields whose plot does not fit a float (the viewer's axes overflowed and it died)
    (dict(range_lo_v=-1e308, lsb_v=1e305), "ADC range"),
    (dict(sample_rate_hz=1e-301, first_sample=np.zeros(NB, int)), "sample_rate_hz = 1e-301 (finite, >= 1)"),
    # a window index near the int64 limit wrapped silently into garbage times
    (dict(first_sample=np.full(NB, (1 << 63) - 10)), "first_sample beyond +-2^52"),
], ids=["code", "count", "window", "toa", "rate", "lsb", "level", "trigger", "bits", "fraction", "range-top",
        "rate-tiny", "first-sample"])
def test_inconsistent_signal_batch_is_refused(changes, words):
    payload = codec.encode_signal_batch(_header(), _signal_batch(**changes))
    with pytest.raises(BttsimError) as excinfo:
        codec.decode_signal_batch(payload, "bttsim/rig1/signal/3")
    assert words in _one_line_error(excinfo)
    assert str(excinfo.value).startswith("bttsim/rig1/signal/3: corrupt SignalBatch")


def test_signal_batch_on_another_probe_key_or_blade_count_is_refused():
    payload = codec.encode_signal_batch(_header(), _signal_batch())
    with pytest.raises(BttsimError, match="probe 3 on the key of probe 0"):
        codec.decode_signal_batch(payload, "bttsim/rig1/signal/0")
    with pytest.raises(BttsimError, match="expected n_blades = 28"):
        codec.decode_signal_batch(payload, "bttsim/rig1/signal/3", n_blades=28)


def test_ticked_toa_batch_with_extra_edges_needs_their_ticks():
    """The encoder refuses what its own decoder would: ticked TOAs whose extra edges have none."""
    with pytest.raises(ValueError, match="extra_toa_ticks"):
        codec.encode_toa_batch(_header(), 0, [1.0, 2.0], [10, 20], extra_toa_s=[1.5])
    payload = codec.encode_toa_batch(_header(), 0, [1.0, 2.0], [10, 20], extra_toa_s=[1.5], extra_toa_ticks=[15])
    assert codec.decode_toa_batch(payload, "bttsim/rig1/toa/0").body.extra_toa_ticks.tolist() == [15]


def test_toa_batch_extra_edges_round_trip_and_batch_bytes():
    rng = np.random.default_rng(3)
    toa = rng.uniform(1, 2, (4, NB))
    ticks = np.floor(toa * 1e8).astype(np.int64)
    extra = (np.array([0, 0, 2]), np.array([1.5, 1.6, 1.7]), np.array([150000000, 160000000, 170000000]))
    batch = codec.encode_toa_batches("r", np.arange(4), np.arange(4), np.full(4, 2.0), np.zeros(4, int), toa, ticks,
                                     extra)
    for i in range(4):
        sel = extra[0] == i
        one = codec.encode_toa_batch(codec.Header("r", i, i, 2.0), 0, toa[i].tolist(), ticks[i].tolist(),
                                     extra[1][sel], extra[2][sel])
        assert batch[i] == one
        d = codec.decode_toa_batch(one, "bttsim/rig1/toa/0").body
        np.testing.assert_array_equal(d.extra_toa_s, extra[1][sel])
        np.testing.assert_array_equal(d.extra_toa_ticks, extra[2][sel])
    plain = codec.encode_toa_batch(codec.Header("r", 0, 0, 2.0), 0, toa[0].tolist(), ticks[0].tolist())
    assert plain == codec.encode_toa_batches("r", [0], [0], [2.0], [0], toa[:1], ticks[:1])[0]  # none: no bytes
    assert codec.decode_toa_batch(plain).body.extra_toa_s.size == 0


@pytest.mark.parametrize("extra_s, extra_ticks, words", [
    (np.full(8 * NB + 1, 1.5), np.full(8 * NB + 1, 1), f"{8 * NB + 1} extra edges for {NB} blades"),
    (np.array([np.nan]), np.array([1]), "an extra edge time is not finite"),
    (np.array([1.5, 1.6]), np.array([1]), "extra_toa_ticks has 1 values, expected 2"),
], ids=["too-many", "nan", "ticks"])
def test_toa_batch_with_bad_extra_edges_is_refused(extra_s, extra_ticks, words):
    toa = np.full(NB, 1.0)
    payload = codec.encode_toa_batch(_header(), 0, toa.tolist(), np.ones(NB, int).tolist(), extra_s, extra_ticks)
    with pytest.raises(BttsimError) as excinfo:
        codec.decode_toa_batch(payload, "bttsim/rig1/toa/0")
    assert words in _one_line_error(excinfo)


def _truth_message(rng, nb=7, npr=3, nsv=2):
    from bttsim_stream.bus._gen.bttsim.v1 import bttsim_pb2 as pb

    m = pb.TruthBatch()
    m.header.run_id, m.header.seq, m.header.revolution, m.header.t_s = "r", 4, 4, 0.1
    m.opr_s, m.omega_mean_rad_s, m.n_blades, m.n_probes = 0.1, 200.0, nb, npr
    for name in TRUTH_2D:
        getattr(m, name).extend(rng.normal(size=nb * npr).tolist())
    m.d_eqv_pkpk_m.extend(rng.random(nb).tolist())
    for j in range(nsv):
        c = m.nsv.add()
        c.kind, c.freq_hz, c.nodal_diameter, c.amp_pkpk_m, c.rms_m = "flutter", 300.0 + j, 2, 1e-4, 3e-5
        c.band_lo_hz, c.band_hi_hz = 290.0, 310.0
    return m


def test_truth_arrays_read_from_the_bytes_equal_the_parsed_fields():
    """decode_truth reads its packed arrays straight from the payload; valid encodings it
    does not take that way (an array unpacked, or split in two runs) are read from the
    parsed message: every value the same."""
    rng = np.random.default_rng(3)
    m = _truth_message(rng)
    payload = m.SerializeToString(deterministic=True)
    assert codec_base.packed_doubles(payload, codec._TRUTH_NUMBERS) is not None  # the fast path
    want = {name: np.array(getattr(m, name)) for name in (*TRUTH_2D, "d_eqv_pkpk_m")}

    def check(data):
        t = codec.decode_truth(data).body
        for name, v in want.items():
            np.testing.assert_array_equal(getattr(t, name).ravel(), v)
        assert t.nsv_freq_hz.tolist() == [[300.0, 301.0]]

    check(payload)
    num = m.DESCRIPTOR.fields_by_name["d_z_m"].number
    rest = type(m)()
    rest.CopyFrom(m)
    rest.ClearField("d_z_m")
    unpacked = b"".join(bytes([num << 3 | 1]) + np.float64(v).tobytes() for v in want["d_z_m"])
    assert codec_base.packed_doubles(rest.SerializeToString() + unpacked, codec._TRUTH_NUMBERS) is None
    check(rest.SerializeToString() + unpacked)
    half = len(want["d_z_m"]) // 2
    split = b"".join(bytes([num << 3 | 2, 8 * len(p)]) + p.astype("<f8").tobytes()
                     for p in (want["d_z_m"][:half], want["d_z_m"][half:]))
    assert codec_base.packed_doubles(rest.SerializeToString() + split, codec._TRUTH_NUMBERS) is None
    check(rest.SerializeToString() + split)


def test_another_message_types_payload_on_a_key_is_refused():
    """Protobuf parses a TOA batch or a truth payload as an Opr (the header is the same field,
    the rest unknown fields): the codec refuses a payload with fields its type lacks, so a
    message sent on the wrong key cannot pass for that key's own."""
    msgs = MessageStream("run-a", "rig1").acquisition(make_batch(seed=1, ticks=False))
    opr = next(m for m in msgs if m.key.endswith("/opr"))
    assert codec.decode_opr(opr.payload, opr.key).header.run_id == "run-a"
    for m in (m for m in msgs if not m.key.endswith("/opr")):
        with pytest.raises(BttsimError, match=r"corrupt Opr \(fields that are not in its schema\)$"):
            codec.decode_opr(m.payload, "bttsim/rig1/opr")


def test_truth_without_its_per_probe_fields_is_the_same_truth_and_checked_the_same():
    """``decode_truth(..., fields=...)`` builds only the per-probe fields asked for (the others
    None); every other field is the full decode's, and a payload the full decode refuses is
    refused with the same message."""
    rng = np.random.default_rng(5)
    payload = _truth_message(rng).SerializeToString(deterministic=True)
    full = codec.decode_truth(payload, "bttsim/rig1/truth")
    for fields in ((), ("t_exp_s",), ("toa_s", "d_z_m")):
        part = codec.decode_truth(payload, "bttsim/rig1/truth", fields=fields)
        assert part.header == full.header
        for name in TRUTH_2D:
            got = getattr(part.body, name)
            if name in fields:
                np.testing.assert_array_equal(got, getattr(full.body, name))
            else:
                assert got is None
        for name in ("opr_s", "omega_mean", "d_eqv_pkpk_m", "eo_engine_order", "eo_pkpk_m", "nsv_kind",
                     "nsv_freq_hz", "nsv_nd", "nsv_amp_pkpk_m", "nsv_rms_m", "nsv_band_hz"):
            a, b = getattr(part.body, name), getattr(full.body, name)
            assert (a is None) == (b is None)
            if a is not None:
                assert a.dtype == b.dtype and a.shape == b.shape
                np.testing.assert_array_equal(a, b)
    m = MessageStream("r", "rig1").acquisition(make_batch())[NP + 1]
    bad = m.payload + _field(5, 0, _varint(4))  # n_probes = 4: the per-probe lengths do not fit
    for fields in (None, ()):
        with pytest.raises(BttsimError, match=r"toa_s has 145 values, expected 116 for shape \(29, 4\)"):
            codec.decode_truth(bad, m.key, fields=fields)


def test_probe_waves_at_once_are_the_bytes_of_one_at_a_time():
    """``encode_probe_waves`` writes the wire format itself: every byte equals protobuf's
    (``encode_probe_wave``) over run ids, sequence numbers, revolutions (-1, large), header
    times (0, -0, NaN, inf), NaN and zero magnitudes, probe 0 (left out) and negative NDs."""
    rng = np.random.default_rng(21)
    n = 0
    for _ in range(400):
        npr, nnd = int(rng.integers(1, 9)), int(rng.integers(1, 20))
        f = rng.random((npr, nnd)) * 10.0 ** float(rng.integers(-9, 3))
        b = rng.random((npr, nnd))
        f[rng.random(f.shape) < 0.1] = np.nan
        b[rng.random(b.shape) < 0.1] = rng.choice([0.0, -0.0])
        run_id = str(rng.choice(["", "r", "run-2026-12-03T17:00:00-abcdef", "x" * 200, "é-ü"]))
        seq = [int(rng.choice([0, 1, 127, 128, 2 ** 32 + 5, 2 ** 63 + 7])) for _ in range(npr)]
        rev = int(rng.choice([-1, 0, 1, 300, 2 ** 40]))
        t = float(rng.choice([0.0, -0.0, 1.5, 1e-300, np.nan, np.inf, rng.random() * 100]))
        nd = int(rng.integers(-nnd + 1, nnd))
        got = codec.encode_probe_waves(run_id, seq, rev, t, f, b, nd)
        assert len(got) == npr
        for p in range(npr):
            assert got[p] == codec.encode_probe_wave(codec.Header(run_id, seq[p], rev, t), ProbeWave(p, f[p], b[p], nd))
            n += 1
    assert n > 1000
    with pytest.raises(ValueError, match="at least one nodal diameter"):
        codec.encode_probe_waves("r", [0], 0, 0.0, np.zeros((1, 0)), np.zeros((1, 0)), 0)


def test_fits_at_once_are_the_bytes_of_one_at_a_time():
    """``encode_fits`` writes the wire format itself: every byte equals protobuf's
    (``encode_fit`` of each order's ``RevolutionFit``), with zero, -0 and NaN values, several
    engine orders and no blade at all."""
    rng = np.random.default_rng(22)
    n = 0
    for _ in range(300):
        nb, n_eo = int(rng.integers(0, 40)), int(rng.integers(1, 4))
        eos = sorted(rng.choice(np.arange(1, 30), n_eo, replace=False).tolist())
        arrays = [rng.normal(size=(nb, n_eo)) for _ in range(3)] + [rng.normal(size=nb) for _ in range(2)]
        for a in arrays:
            a[rng.random(a.shape) < 0.1] = rng.choice([np.nan, 0.0, -0.0])
        omega, cn = (float(rng.choice([0.0, -0.0, 250.0 * rng.random()])) for _ in range(2))
        freq = rng.choice([0.0, np.nan, 300.0], n_eo)
        seq = [int(rng.choice([0, 5, 2 ** 40])) for _ in range(n_eo)]
        rev, t = int(rng.choice([-1, 0, 7])), float(rng.choice([0.0, 2.5]))
        amp, phase, std, dc, res = arrays
        got = codec.encode_fits("run", seq, rev, t, eos, omega, freq, cn, amp, phase, std, dc, res)
        for k, eo in enumerate(eos):
            fit = RevolutionFit(engine_order=eo, omega_rad_s=omega, freq_hz=float(freq[k]), cn=cn,
                                amp_pkpk_m=amp[:, k], phase_rad=phase[:, k], dc_m=dc, residual_rms_m=res,
                                amp_std_m=std[:, k])
            assert got[k] == codec.encode_fit(codec.Header("run", seq[k], rev, t), fit)
            n += 1
    assert n > 300
    with pytest.raises(ValueError, match="fit arrays"):
        codec.encode_fits("r", [0], 0, 0.0, (8,), 1.0, [1.0], 1.0, np.zeros((3, 1)), np.zeros((3, 1)),
                          np.zeros((3, 1)), np.zeros(2), np.zeros(3))


def test_the_row_decoders_match_the_decoders():
    """``opr_row``, ``toa_row`` and ``truth_row`` (what ``load_run`` reads with) give the
    decoders' values."""
    from _io_helpers import recorded_messages

    for m in recorded_messages():
        kind = m.key.split("/")[2]
        if kind == "opr":
            d = codec.decode_opr(m.payload, m.key)
            assert codec.opr_row(m.payload, m.key) == (d.header.run_id, d.header.revolution, d.body.opr_s)
        elif kind == "toa":
            d = codec.decode_toa_batch(m.payload, m.key)
            run_id, rev, probe, toa, extra = codec.toa_row(m.payload, m.key)
            assert (run_id, rev, probe) == (d.header.run_id, d.header.revolution, d.body.probe)
            assert toa.dtype == d.body.toa_s.dtype and np.array_equal(toa, d.body.toa_s, equal_nan=True)
            assert extra.dtype == d.body.extra_toa_s.dtype and np.array_equal(extra, d.body.extra_toa_s)
        elif kind == "truth":
            d = codec.decode_truth(m.payload, m.key)
            for fields in (None, ("opr_s", "d_eqv_pkpk_m", "nsv_kind", "eo_pkpk_m"), ("t_exp_s", "omega_mean")):
                run_id, rev, tail, arrays = codec.truth_row(m.payload, m.key, fields=fields)
                assert (run_id, rev, tail) == (d.header.run_id, d.header.revolution, d.body.toa_s.shape[1:])
                assert set(arrays) == set(fields or arrays)
                for name, a in arrays.items():
                    b = getattr(d.body, name)
                    assert a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b), name

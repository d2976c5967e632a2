"""Truth per engine order: each engine order's own response beside the sum, checked against
runs of each excitation alone (the model is linear), carried by the codec, and used to score
a crossing against its own order."""

import numpy as np
import pytest

from bttsim_stream.bus import codec
from bttsim_stream.errors import BttsimError
from bttsim_stream.model import build_model
from bttsim_stream.process.options import ProcessOptions
from bttsim_stream.process.pipeline import process_arrays
from bttsim_stream.process.resonance import TruthPeakTracker, TruthRows, window_truth
from bttsim_stream.scenario import scenario_from_dict
from bttsim_stream.sim.core import RunUpSimulator, Truth, collect

from _io_helpers import TRUTH_2D

pytestmark = pytest.mark.unit

EO7 = {"engine_order": 7, "nodal_diameter": 7}
EO8 = {"engine_order": 8, "nodal_diameter": 1}
SHORT = {"start_rpm": 2550.0, "end_rpm": 2620.0, "duration_s": 1.0}


@pytest.fixture(scope="module")
def model():
    return build_model()


def _truth(model, excitations, speed=SHORT):
    return collect(RunUpSimulator(scenario_from_dict({"speed": speed, "excitation": excitations}), model)).truth


def test_each_order_equals_its_excitation_alone(model):
    """The two-EO run's per-order envelopes are the envelopes of the runs excited by each
    order alone (superposition; 1e-4: the envelopes are read at the TOAs, which the other
    order's deflection moves by a few microseconds), and their sum bounds the summed
    envelope."""
    both = _truth(model, [EO7, EO8])
    assert both.eo_engine_order.shape == (both.opr_s.size, 2)
    assert both.eo_engine_order[0].tolist() == [7, 8]
    for j, ex in enumerate((EO7, EO8)):
        alone = _truth(model, [ex])
        ref = alone.d_eqv_pkpk_m
        np.testing.assert_allclose(both.eo_pkpk_m[..., j], ref, rtol=1e-4)
    # the summed envelope is the largest over the arrivals of the sum: between the larger
    # order and the sum of the orders' largest values
    assert np.all(both.d_eqv_pkpk_m <= both.eo_pkpk_m.sum(axis=2) * (1 + 1e-12))
    assert np.all(both.d_eqv_pkpk_m >= both.eo_pkpk_m.max(axis=2) * (1 - 1e-12))


def test_one_order_equals_the_total_exactly(model):
    t = _truth(model, [EO8])
    assert t.eo_engine_order[0].tolist() == [8]
    assert np.array_equal(t.eo_pkpk_m[..., 0], t.d_eqv_pkpk_m)


def test_excitations_of_one_order_superpose_as_complex_envelopes(model):
    """Two excitations at EO 8 (ND 1 and ND 1 with half the force): one column, the response
    of the summed force (1.5 times the first), not the sum of the magnitudes."""
    half = dict(EO8, amplitude_n=1.125)
    t = _truth(model, [EO8, half])
    ref = _truth(model, [dict(EO8, amplitude_n=3.375)])
    assert t.eo_engine_order[0].tolist() == [8]
    np.testing.assert_allclose(t.eo_pkpk_m[..., 0], ref.d_eqv_pkpk_m, rtol=1e-4)


def _random_truth(n, nb, npr, orders, rng):
    arrays = {name: rng.normal(size=(n, nb, npr)) for name in TRUTH_2D}
    k = len(orders)
    return Truth(opr_s=rng.random(n), omega_mean=100 + rng.random(n), d_eqv_pkpk_m=rng.random((n, nb)),
                 eo_engine_order=np.broadcast_to(np.array(orders, np.int64), (n, k)).copy(),
                 eo_pkpk_m=rng.random((n, nb, k)), **arrays)


@pytest.mark.parametrize("orders", [(), (8,), (7, 8, 200)])
def test_codec_round_trip_and_batch_encoder(orders):
    rng = np.random.default_rng(3)
    n, nb, npr = 6, 4, 3
    truth = _random_truth(n, nb, npr, orders, rng)
    got = codec.encode_truth_batch("r", np.arange(n), np.arange(n), truth.opr_s, truth)
    for i in range(n):
        ref = codec.encode_truth(codec.Header("r", i, i, float(truth.opr_s[i])), truth, i)
        assert got[i] == ref, i
        d = codec.decode_truth(ref).body
        assert d.eo_engine_order.shape == (1, len(orders)) and d.eo_pkpk_m.shape == (1, nb, len(orders))
        np.testing.assert_array_equal(d.eo_engine_order[0], truth.eo_engine_order[i])
        np.testing.assert_array_equal(d.eo_pkpk_m[0], truth.eo_pkpk_m[i])


def test_a_truth_without_the_fields_decodes_to_no_orders():
    rng = np.random.default_rng(4)
    t = _random_truth(2, 3, 2, (8,), rng)
    old = Truth(**{f: getattr(t, f) for f in Truth.__dataclass_fields__ if not f.startswith("eo_")})
    d = codec.decode_truth(codec.encode_truth(codec.Header("r", 0, 0, 0.0), old, 0)).body
    assert d.eo_engine_order.shape == (1, 0) and d.eo_pkpk_m.shape == (1, 3, 0)


@pytest.mark.parametrize("orders, amp, msg", [
    ((8, 7), None, "ascend strictly"),
    ((0,), None, "ascend strictly"),
    ((8,), -1.0, "finite and >= 0"),
    ((8,), np.nan, "finite and >= 0"),
])
def test_bad_per_order_truth_is_refused(orders, amp, msg):
    rng = np.random.default_rng(5)
    t = _random_truth(1, 3, 2, orders, rng)
    if amp is not None:
        t.eo_pkpk_m[0, 1, 0] = amp
    payload = codec.encode_truth(codec.Header("r", 0, 0, 0.0), t, 0)
    with pytest.raises(BttsimError, match=msg):
        codec.decode_truth(payload, "bttsim/rig1/truth")
    short = _random_truth(1, 3, 2, (7, 8), rng)
    payload = codec.encode_truth(codec.Header("r", 0, 0, 0.0), short, 0) + bytes([0x79]) + b"\0" * 8  # one more
    with pytest.raises(BttsimError, match=r"eo_pkpk_m has 7 values, expected 6"):
        codec.decode_truth(payload, "bttsim/rig1/truth")


def test_window_truth_takes_the_crossing_order_and_falls_back_to_the_sum():
    total = np.array([[1.0, 2.0], [3.0, 4.0], [2.0, 1.0]])
    own = np.stack([total * 0.25, total * 0.5], axis=2)  # EO 7, EO 8
    om = np.full(3, 300.0)
    rows = TruthRows(d_eqv_pkpk_m=total, omega_mean=om, eo_engine_order=np.array([7, 8]), eo_pkpk_m=own)
    assert window_truth(rows, 8, 0, 2).amp_pkpk_m.tolist() == [1.5, 2.0]
    assert window_truth(rows, 7, 0, 2).amp_pkpk_m.tolist() == [0.75, 1.0]
    assert window_truth(rows, 9, 0, 2).amp_pkpk_m.tolist() == [3.0, 4.0]  # not carried: the sum
    tr = TruthPeakTracker(8)
    for i in range(3):
        tr.update(10 + i, total[i], 300.0, eo=(np.array([7, 8]), own[i]))
    np.testing.assert_array_equal(tr.rows(10, 3).eo_pkpk_m, own)
    assert window_truth(tr.rows(10, 3), 8, 0, 2).amp_pkpk_m.tolist() == [1.5, 2.0]


@pytest.mark.slow
def test_two_order_run_scores_each_crossing_against_its_own_truth(model):
    """EO 7 ND 7 + EO 8 ND 1 over both crossings at the paper's sweep rate: every method's
    mean E_A against each order's own truth is within 2 % (against the summed envelope it was
    5-11 %), and no note says the truth is summed."""
    speed = {"start_rpm": 2000.0, "end_rpm": 3100.0, "duration_s": 1100.0 / 3000.0 * 130.0}
    sim = RunUpSimulator(scenario_from_dict({"speed": speed, "excitation": [EO7, EO8]}), model)
    res = collect(sim)
    for method in ("peak", "sdof", "cff"):
        out = process_arrays(res.opr_s, res.toa_s, sim.info, ProcessOptions(method=method), truth=res.truth)
        s = out.summary
        eos = sorted(e["eo"] for e in s["resonances"])
        assert eos == [7, 8], (method, eos)
        for e in s["resonances"]:
            assert e["mean_E_A_pct"] <= 2.0, (method, e["eo"], e["mean_E_A_pct"])
        assert not any("sums every excitation" in n for n in s.get("notes", []))


@pytest.mark.slow
def test_recorded_two_order_run_through_the_processor_session(tmp_path, model):
    """The same two-EO run recorded to MCAP (truth with the per-order fields) and processed
    as the processor node does (its session, truth from the messages): each order's E_A is
    the in-process one, within 2 %, with the per-order truth read back from the file."""
    from bttsim_stream.acquisition import simulate_to_mcap
    from bttsim_stream.offline import load_run, processing_messages

    speed = {"start_rpm": 2000.0, "end_rpm": 3100.0, "duration_s": 1100.0 / 3000.0 * 130.0}
    scn = scenario_from_dict({"speed": speed, "excitation": [EO7, EO8]})
    path = tmp_path / "two.mcap"
    simulate_to_mcap(scn, path, model=model)
    run = load_run(path, keep_messages=True)
    assert run.truth.eo_engine_order[0].tolist() == [7, 8]
    _, s = processing_messages(run)
    live = {e["eo"]: e["mean_E_A_pct"] for e in s["resonances"]}
    offline = process_arrays(run.opr_s, run.toa_s, run.meta, truth=run.truth).summary
    assert live == {e["eo"]: e["mean_E_A_pct"] for e in offline["resonances"]}
    assert sorted(live) == [7, 8] and max(live.values()) <= 2.0, live

"""A flutter whose order passes a whole number is one non-synchronous vibration: its blocks
next to the whole order (alias in the synchronous band) are bridged, not split into two
detections, and its level is scored against the truth at the revolutions it was measured."""

import numpy as np
import pytest

from bttsim_stream.model import build_model
from bttsim_stream.process import ProcessOptions, process_arrays
from bttsim_stream.process.nsv import LAST_REVOLUTIONS
from bttsim_stream.scenario import scenario_from_dict
from bttsim_stream.sim.core import RunUpSimulator, collect

pytestmark = pytest.mark.unit


def _flutter(nd: int, speed: dict, start_rpm: float, seed: int = 1):
    """Like examples/flutter.toml (family 1, 0.3 mm limit cycle), on a run-up."""
    scn = scenario_from_dict({"run": {"seed": seed}, "speed": speed,
                              "flutter": {"enabled": True, "family": 1, "nodal_diameter": nd, "start_rpm": start_rpm,
                                          "aero_damping_ratio": 0.03, "limit_amplitude_m": 3e-4,
                                          "seed_amplitude_m": 1e-9}})
    sim = RunUpSimulator(scn, build_model())
    res = collect(sim)
    return res, process_arrays(res.opr_s, res.toa_s, sim.info, ProcessOptions(), truth=res.truth)


@pytest.mark.parametrize("nd, speed, start", [
    (5, {"start_rpm": 2850.0, "end_rpm": 3100.0, "duration_s": 11.0}, 2860.0),  # order 7.3 -> 6.7 (passes 7)
    (-3, {"start_rpm": 3100.0, "end_rpm": 2850.0, "duration_s": 11.0}, 3090.0),  # run-down, 6.7 -> 7.3
    # through the EO 8 crossing at the paper's sweep rate: the order passes 8, 7.5 and 7
    (5, {"start_rpm": 2000.0, "end_rpm": 3100.0, "duration_s": 47.7}, 2450.0),
], ids=["runup-fwd5", "rundown-bwd3", "through-eo8"])
def test_flutter_through_a_whole_order_is_one_detection(nd, speed, start):
    res, out = _flutter(nd, speed, start)
    t = res.truth
    order = t.nsv_freq_hz[:, 0] * 2 * np.pi / t.omega_mean
    on = t.nsv_amp_pkpk_m[:, 0] > 1e-5
    assert order[on].min() < 7.0 < order[on].max()  # the flutter's order does pass 7
    dets = out.summary["non_synchronous"]
    assert len(dets) == 1, [(d["order"], d["revolutions"]) for d in dets]
    d = dets[0]
    assert d["nd"] == nd and d["truth"]["nd_correct"]
    # the detection spans the whole order's passage
    rev7 = int(np.flatnonzero(np.diff(np.sign(order - 7.0)))[0])
    assert d["revolutions"]["first"] < rev7 - 64 and d["revolutions"]["last"] > rev7 + 64
    assert abs(d["truth"]["freq_error_hz"]) < 0.1
    assert abs(d["truth"]["amp_last_error_pct"]) < 3.0
    assert d["amp_pkpk_m"] == pytest.approx(3e-4, rel=0.05)


def test_level_is_scored_at_the_measured_revolutions():
    """The truth's level is taken at the revolutions of the detection's last per-revolution
    amplitudes: recomputed here from the truth rows, it is the reported one exactly."""
    res, out = _flutter(5, {"start_rpm": 2850.0, "end_rpm": 3100.0, "duration_s": 11.0}, 2860.0)
    (det,) = out.nsv
    revs = det.revolutions[np.isfinite(det.rev_amp_pkpk_m)][-LAST_REVOLUTIONS:]
    assert det.truth["amp_last_pkpk_m"] == float(np.median(res.truth.nsv_amp_pkpk_m[revs, 0]))
    assert det.amp_last_pkpk_m == float(np.median(det.rev_amp_pkpk_m[np.isfinite(det.rev_amp_pkpk_m)][-8:]))

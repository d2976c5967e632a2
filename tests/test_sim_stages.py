"""Acquisition stages (sim/stages.py) and excitation sources (sim/sources.py) as parts."""

import numpy as np
import pytest

from bttsim_stream.scenario import scenario_from_dict
from bttsim_stream.sim.stages import (Acquired, Clock, OprJitter, Passages, SignalChain, TriggerJitter,
                                      acquisition_stages)

pytestmark = pytest.mark.unit


def _passages(toa):
    return Passages(toa.ravel(), np.zeros(toa.size, np.int64), lambda: np.zeros(toa.size))


def test_default_scenario_has_no_acquisition_stage():
    assert acquisition_stages(scenario_from_dict({}), None, np.full(29, 0.19)) == []


@pytest.mark.parametrize("acq, kinds", [
    ({"clock_hz": 1e6, "trigger_jitter_s": 1e-8, "opr_jitter_s": 1e-8}, [TriggerJitter, OprJitter, Clock]),
    ({"clock_hz": 1e6, "opr_jitter_s": 1e-8, "signal": {"enabled": True}}, [SignalChain, OprJitter, Clock]),
], ids=["jitter-clock", "signal-chain"])
def test_stages_come_in_their_order(acq, kinds):
    scn = scenario_from_dict({"acquisition": acq})
    assert [type(s) for s in acquisition_stages(scn, None, np.full(29, 0.19))] == kinds


def test_clock_latches_the_tick_before():
    toa = np.array([[[0.1234567, 2.0000004]]])
    acq = Acquired(toa_s=toa.copy(), opr_s=np.array([0.05000009]))
    Clock(1e6).apply(acq, _passages(toa))
    np.testing.assert_array_equal(acq.toa_ticks, [[[123456, 2000000]]])
    np.testing.assert_array_equal(acq.opr_ticks, [50000])
    np.testing.assert_allclose(acq.toa_s, [[[0.123456, 2.0]]], rtol=0, atol=1e-15)


def test_clock_marks_a_missing_pulse_of_the_signal_chain():
    toa = np.array([[[0.5, np.nan]]])
    acq = Acquired(toa_s=toa.copy(), opr_s=np.array([0.0]), extra_toa_s=np.array([0.7500001]), from_signal=True)
    Clock(1e3).apply(acq, _passages(toa))
    np.testing.assert_array_equal(acq.toa_ticks, [[[500, -1]]])
    assert np.isnan(acq.toa_s[0, 0, 1])
    np.testing.assert_array_equal(acq.extra_toa_ticks, [750])


def test_jitter_draws_its_own_stream():
    """Trigger jitter draws SeedSequence([seed, 1]) whatever else is switched on."""
    toa = np.zeros((2, 3, 4))
    acq = Acquired(toa_s=toa.copy(), opr_s=np.zeros(2))
    TriggerJitter(1e-6, seed=7).apply(acq, _passages(toa))
    want = 1e-6 * np.random.default_rng(np.random.SeedSequence([7, 1])).standard_normal(toa.shape)
    np.testing.assert_array_equal(acq.toa_s, want)

"""Live latency: a revolution's fit goes out as soon as the OPR pulse that ends it is in,
before the next revolution's TOAs, and equals the fit the full revolution would have given."""
import numpy as np

from bttsim_stream.acquisition import AcquisitionStream
from bttsim_stream.bus import codec, keys
from bttsim_stream.process import ProcessOptions, StreamingProcessor
from bttsim_stream.process.streaming import LIVE_CALIBRATION
from bttsim_stream.processor import ProcessorSession
from bttsim_stream.scenario import scenario_from_dict
from bttsim_stream.paper.validate_processing import simulate

SHORT = {"speed": {"start_rpm": 2400.0, "end_rpm": 2700.0, "duration_s": 6.0}}


def _fields(o):
    return (o.revolution, o.opr_s, o.omega_rad_s, o.d_m, o.amp_pkpk_m, o.phase_rad, o.amp_std_m, o.dc_m,
            o.residual_rms_m, o.probe_tw.forward_m, o.probe_tw.backward_m, o.fit_tw.forward_m, o.calibrated)


def test_advance_gives_each_revolution_on_the_next_pulse_and_the_same_outputs():
    run = simulate(SHORT)
    n = run.opr_s.size
    plain = StreamingProcessor(run.info)
    ref = [o for k in range(n) for o in plain.push(k, run.opr_s[k], run.toa_s[k])] + plain.flush()
    proc = StreamingProcessor(run.info)
    outs, early = [], 0
    for k in range(n):
        ahead = proc.advance(k, run.opr_s[k])  # the pulse first, the TOAs later
        if k >= 3 and k != LIVE_CALIBRATION:  # after the start and the calibration step
            assert [o.revolution for o in ahead] == [k - 1]
            early += 1
        outs += ahead
        pushed = proc.push(k, run.opr_s[k], run.toa_s[k])
        assert all(o.revolution < k for o in pushed)
        outs += pushed
    outs += proc.flush()
    assert early > n - 10
    assert [o.revolution for o in outs] == [o.revolution for o in ref] == list(range(n))
    for a, b in zip(outs, ref):  # bit for bit
        for x, y in zip(_fields(a), _fields(b)):
            np.testing.assert_array_equal(x, y)
    # the final report rests on the same history
    assert proc.finish() == plain.finish()


def test_processor_session_publishes_a_fit_when_the_ending_pulse_arrives():
    scn = scenario_from_dict({**SHORT, "run": {"rig": "lat"}})
    stream = AcquisitionStream(scn, include_truth=False)
    session = ProcessorSession(codec.decode_run_metadata(stream.meta.payload).body, ProcessOptions(), score=False)
    fit_key = keys.fits_key("lat")
    checked = 0
    for _, msgs in stream.batches():
        for m in msgs:
            kind = keys.parse_key(m.key).kind
            out = session.add(kind, m.key, codec.decode_message(m.key, m.payload), m.seq)
            fits = [codec.decode_fit(o.payload).header.revolution for o in out if o.key == fit_key]
            if kind == "opr":
                rev = codec.decode_opr(m.payload).header.revolution
                if rev >= 3 and rev != LIVE_CALIBRATION:
                    assert fits == [rev - 1]  # before any TOA of revolution rev
                    checked += 1
            elif kind == "toa":
                assert not fits or codec.decode_toa_batch(m.payload).header.revolution == LIVE_CALIBRATION
    assert checked > 100
    msgs, summary = session.finish()
    assert summary["lost"] == 0 and summary["revolutions_processed"] == session.meta.n_revolutions

"""Non-synchronous vibration: detection, order alias, signed ND and amplitude against an
analytic blade response turned into TOAs by root finding (tests/_nsv_truth.py); the
synchronous default run gives no detection; an NSV is never reported as a resonance."""

import json

import numpy as np
import pytest

from bttsim_stream.process import Geometry, ProcessOptions, process_arrays
from bttsim_stream.process.nsv import NsvOptions, detect_nsv, scan_blocks, screen_block
from bttsim_stream.process.resonance import summary_table

from _nsv_truth import logistic, synthesize

#: Order tolerance: the alias is refined between FFT bins of 1 / (pad x block) = 1/64 per rev.
ORDER_TOL = 0.01


def _geometry(run):
    return Geometry(run.n_blades, run.probe_angles_rad, run.tip_radius_m)


def _live_nsv(proc, run) -> list:
    """Every revolution of ``run`` pushed into the streaming processor ``proc``: the NSV
    detections it published live (flushed at the end, not finished)."""
    live = []
    for n in range(run.opr_s.size):
        proc.push(n, run.opr_s[n], run.toa_s[n])
        live += proc.nsv_ready()
    proc.flush()
    return live + proc.nsv_ready()


def _process(run, **opts):
    return process_arrays(run.opr_s, run.toa_s, _geometry(run), ProcessOptions(**opts))


@pytest.mark.parametrize("n_cells,fraction,nd", [(5, 0.55, -5), (3, 0.3, 3), (7, 0.62, 7), (4, 0.4, -11)],
                         ids=["5cells-bwd5", "3cells-fwd3", "7cells-fwd7", "4cells-bwd11"])
def test_rotating_stall_order_nd_and_amplitude(n_cells, fraction, nd):
    order = n_cells * (1.0 - fraction)  # a non-integer engine order, constant with speed
    run = synthesize(n_rev=256, rpm0=3000.0, order=order, nd=nd, amp_pk_m=0.15e-3, noise_s=5e-8, seed=3)
    res = _process(run)
    s = res.summary
    assert len(s["non_synchronous"]) == 1
    det = s["non_synchronous"][0]
    assert det["order"] == pytest.approx(order, abs=ORDER_TOL)
    assert det["alias_per_rev"] == pytest.approx(abs(order - round(order)), abs=ORDER_TOL)
    assert det["nd"] == nd
    assert det["freq_hz"] == pytest.approx(order * 3000 / 60, abs=ORDER_TOL * 50)
    assert det["amp_pkpk_m"] == pytest.approx(0.3e-3, rel=0.03)
    assert det["detection"]["value"] >= det["detection"]["threshold"]
    # no engine-order resonance is claimed where none was crossed
    assert s["status"] == "none" and s["resonances"] == [] and s["blades"] == []
    assert any("non-synchronous vibration (not an engine-order resonance)" in n for n in s["notes"])
    text = summary_table(s)
    assert "NON-SYNCHRONOUS VIBRATION" in text and f"ND {nd:+d}" in text
    json.loads(json.dumps(s))


def test_flutter_growth_during_a_run_up():
    """Flutter at a fixed rotor-frame frequency, growing logistically to its limit while the
    speed rises: the detection gives the frequency, ND and the amplitude growth."""
    f, nd, limit = 344.5, 3, 1.0e-3
    run = synthesize(n_rev=640, rpm0=2300.0, rpm1=2500.0, freq_hz=f, nd=nd,
                     amp_pk_m=logistic(0.5e-6, 0.5 * limit, 1.5), noise_s=5e-8, seed=4)
    res = _process(run)
    dets = res.nsv
    assert len(dets) == 1
    d = dets[0]
    assert d.nd == nd
    assert f == pytest.approx(d.freq_hz, abs=0.5)
    assert d.freq_min_hz > f - 1.0 and d.freq_max_hz < f + 1.0
    # the speed moved the order: each block's order is f / f_shaft of that block
    sc = res.nsv_scan
    ok = sc.detected
    np.testing.assert_allclose(sc.order[ok], f * 2 * np.pi / sc.omega_rad_s[ok], atol=0.03)
    # growth: small at the start, the limit amplitude at the end
    assert d.amp_first_pkpk_m < 0.2 * limit
    assert d.amp_pkpk_m == pytest.approx(limit, rel=0.05)
    late = d.rev_amp_pkpk_m[-64:]
    assert np.nanmedian(late) == pytest.approx(limit, rel=0.06)
    assert np.nanmedian(d.rev_amp_pkpk_m[:32]) < 0.5 * np.nanmedian(late)
    assert d.amp_last_pkpk_m == pytest.approx(limit, rel=0.05)
    assert res.summary["status"] == "none"


def test_alias_and_order_alternatives_are_consistent():
    """Whatever the probes can or cannot resolve, every reported order has the alias that one
    sample per revolution shows."""
    run = synthesize(n_rev=128, rpm0=2800.0, order=6.3, nd=-2, amp_pk_m=0.1e-3)
    g = _geometry(run)
    res = _process(run)
    d = res.nsv[0]
    for nu in (d.order, *d.order_alternatives):
        assert abs(nu - round(nu)) == pytest.approx(d.alias, abs=1e-9)
    assert d.order == pytest.approx(6.3, abs=ORDER_TOL) and d.nd == -2
    # four equally spaced probes cannot tell nu from nu + 4: both are listed
    probes = (10.0, 100.0, 190.0, 280.0)
    run4 = synthesize(n_rev=128, rpm0=2800.0, order=6.3, nd=-2, amp_pk_m=0.1e-3, probes_deg=probes)
    g4 = _geometry(run4)
    from bttsim_stream.process.displacement import compute_displacements
    disp = compute_displacements(run4.opr_s, run4.toa_s, g4, calibration=None)
    _, dets = detect_nsv(disp.d_m, disp.omega_rad_s, g4.nominal_arrival_angles())
    orders = {round(x, 2) for x in (dets[0].order, *dets[0].order_alternatives)}
    assert {6.3, 2.3, 10.3} <= {round(x, 1) for x in orders}
    assert g is not None


@pytest.mark.parametrize("case", ["synchronous", "noise"])
def test_no_detection_without_nsv(case):
    """A synchronous response (EO 8, casing-fixed, with noise) or noise alone: no detection;
    the statistic of white noise stays near its expected 1.5."""
    sync = (8, 0.8e-3, 0.2) if case == "synchronous" else None
    run = synthesize(n_rev=512, rpm0=2000.0, rpm1=2600.0, order=3.3, nd=0, amp_pk_m=0.0, sync=sync,
                     noise_s=2e-7, seed=5)
    g = _geometry(run)
    from bttsim_stream.process.displacement import compute_displacements
    disp = compute_displacements(run.opr_s, run.toa_s, g, calibration=None)
    scan = scan_blocks(disp.d_m, disp.omega_rad_s, g.nominal_arrival_angles())
    assert not scan.detected.any()
    assert np.max(scan.ratio) < 3.0
    assert "non_synchronous" not in _process(run).summary


def test_weak_nsv_in_noise_is_detected_by_the_statistic():
    """The documented sensitivity: a pk-pk amplitude of four times the per-sample noise rms
    gives a ratio of about 1 + 0.043 L a^2 / sigma^2 (23 with L = 32), above the threshold."""
    sigma_s, rpm, R = 2e-7, 3000.0, 0.19
    sigma_m = sigma_s * rpm / 60 * 2 * np.pi * R
    run = synthesize(n_rev=256, rpm0=rpm, order=4.37, nd=6, amp_pk_m=2 * sigma_m, noise_s=sigma_s, seed=6)
    g = _geometry(run)
    from bttsim_stream.process.displacement import compute_displacements
    disp = compute_displacements(run.opr_s, run.toa_s, g, calibration=None)
    scan, dets = detect_nsv(disp.d_m, disp.omega_rad_s, g.nominal_arrival_angles(), NsvOptions(min_amp_m=1e-6))
    assert scan.detected.all()
    assert np.median(scan.ratio) == pytest.approx(1 + 0.043 * 32 * 16, rel=0.3)
    assert dets and dets[0].nd == 6 and dets[0].order == pytest.approx(4.37, abs=ORDER_TOL)


def test_nsv_beside_a_synchronous_response_keeps_both():
    """A steady EO 8 response at constant speed and a stall NSV: the NSV is detected at its
    order and ND while the synchronous response stays (a dwell), not taken for the NSV."""
    run = synthesize(n_rev=320, rpm0=2500.0, order=2.6, nd=-4, amp_pk_m=0.1e-3, sync=(8, 0.5e-3, 0.4),
                     noise_s=2e-8, seed=7)
    res = _process(run)
    s = res.summary
    assert len(res.nsv) == 1 and res.nsv[0].nd == -4 and res.nsv[0].order == pytest.approx(2.6, abs=ORDER_TOL)
    assert res.nsv[0].amp_pkpk_m == pytest.approx(0.2e-3, rel=0.05)
    assert s["status"] == "steady" and s["steady"][0]["eo"] == 8 and s["steady"][0]["nd"] == 8
    assert np.mean([b["amp_pkpk_m"] for b in s["steady"][0]["blades"]]) == pytest.approx(1.0e-3, rel=0.05)


def test_live_blocks_agree_with_the_report_and_travel_on_the_bus():
    """The streaming processor's per-block detections (the live ``nsv`` messages) give the
    final report's order and ND; the message and the report round-trip through the codec,
    and a malformed message is refused with a one-line error."""
    from bttsim_stream.bus import codec, keys
    from bttsim_stream.errors import BttsimError
    from bttsim_stream.process import StreamingProcessor
    from bttsim_stream.bus._gen.bttsim.v1 import bttsim_pb2 as pb

    run = synthesize(n_rev=256, rpm0=3000.0, order=3.45, nd=-7, amp_pk_m=0.1e-3, noise_s=2e-8, seed=8)
    g = _geometry(run)
    proc = StreamingProcessor(g)
    live = _live_nsv(proc, run)
    proc.finish()
    assert len(live) >= 4  # blocks 64.. (block 32-63 holds the calibration switch; the first detected one waits)
    assert all(d.nd == -7 and d.order == pytest.approx(3.45, abs=ORDER_TOL) for d in live)
    report = proc.result.report
    assert report.non_synchronous[0].nd == -7 and report.status == "none"
    # the bus
    payload = codec.encode_nsv(codec.Header("r", 3, live[0].last_revolution, 1.0), live[0])
    back = codec.decode_message(keys.nsv_key("rig"), payload).body
    assert back.to_summary() == live[0].to_summary()
    np.testing.assert_array_equal(back.rev_amp_pkpk_m, live[0].rev_amp_pkpk_m)
    np.testing.assert_array_equal(back.revolutions, live[0].revolutions)
    rp = codec.encode_resonance_report(codec.Header("r", 0), report)
    assert codec.decode_resonance_report(rp).body.to_summary() == report.to_summary()
    m = pb.NonSynchronous()
    m.ParseFromString(payload)
    m.forward_m.extend([0.0] * 500)
    with pytest.raises(BttsimError, match="spectrum"):
        codec.decode_nsv(m.SerializeToString())
    m = pb.NonSynchronous()
    m.ParseFromString(payload)
    m.alias_per_rev = 0.9
    with pytest.raises(BttsimError, match="alias"):
        codec.decode_nsv(m.SerializeToString())
    m = pb.NonSynchronous()
    m.ParseFromString(payload)
    m.rev_amp_pkpk_m.append(1.0)
    with pytest.raises(BttsimError, match="per-revolution amplitudes"):
        codec.decode_nsv(m.SerializeToString())


@pytest.mark.integration
def test_recording_through_process_and_view(tmp_path):
    """A flutter recording: ``bttsim process`` prints and writes the NSV (status none, no
    resonance), and ``bttsim view`` shows it (the Non-synchronous tab's entities)."""
    import subprocess
    import sys
    import warnings

    from rerun.chunk import RrdReader

    from _nsv_truth import write_recording
    from bttsim_stream.views import paths

    run = synthesize(n_rev=320, rpm0=2500.0, rpm1=2550.0, freq_hz=344.0, nd=-2,
                     amp_pk_m=logistic(1e-6, 0.3e-3, 2.0), noise_s=3e-8, seed=9)
    rec = tmp_path / "flutter.mcap"
    write_recording(rec, run)
    summary = tmp_path / "s.json"
    res = subprocess.run([sys.executable, "-m", "bttsim_stream.cli", "process", str(rec), "--summary", str(summary)],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    assert "NON-SYNCHRONOUS VIBRATION" in res.stdout and "ND -2 (backward)" in res.stdout
    s = json.loads(summary.read_text())
    assert s["status"] == "none" and s["resonances"] == []
    assert s["non_synchronous"][0]["nd"] == -2
    assert s["non_synchronous"][0]["freq_hz"] == pytest.approx(344.0, abs=0.5)
    out = tmp_path / "v.rrd"
    res = subprocess.run([sys.executable, "-m", "bttsim_stream.cli", "view", str(rec), "--rrd", str(out)],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    ents: dict = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for chunk in RrdReader(out).stream():
            e = ents.setdefault(chunk.entity_path, {"rows": 0, "static": False})
            e["static"] |= chunk.is_static
            e["rows"] += 0 if chunk.is_static else chunk.num_rows
    for p in (paths.NSV_AMP, paths.NSV_ND, paths.NSV_ORDER):
        assert ents["/" + p]["rows"] >= 5, p
    assert ents["/" + paths.NSV_REV_AMP]["rows"] >= 5 * 32  # the growth, every revolution of the live blocks
    assert ents["/" + paths.NSV_TABLE]["static"] and ents["/" + paths.NSV_TW]["static"]


def _bump(t0_s, width_s, amp_pk_m):
    return lambda t: amp_pk_m * np.exp(-0.5 * ((t - t0_s) / width_s) ** 2)


def test_an_nsv_that_comes_and_goes_is_not_an_engine_order_resonance(monkeypatch):
    """Rotating stall that appears and disappears during a run-up makes the EO 8 fits peak;
    without the NSV guard the pipeline reports an EO 8 resonance there (checked), with it the
    run reports no resonance, the NSV, and a note on the dropped peak."""
    import bttsim_stream.process.pipeline as pipeline

    run = synthesize(n_rev=640, rpm0=2200.0, rpm1=2800.0, order=2.45, nd=4, amp_pk_m=_bump(6.0, 1.2, 0.4e-3),
                     noise_s=3e-8, seed=2)
    s = _process(run).summary
    assert s["status"] == "none" and s["resonances"] == []
    assert any("not reported as a resonance: it is the non-synchronous vibration" in n for n in s["notes"])
    det = s["non_synchronous"][0]
    assert det["nd"] == 4 and det["order"] == pytest.approx(2.45, abs=ORDER_TOL)
    assert det["amp_pkpk_m"] == pytest.approx(0.8e-3, rel=0.05)  # the bump's top, block-averaged
    monkeypatch.setattr(pipeline, "NSV_DOMINANCE", np.inf)  # the guard off: the confident wrong answer
    assert _process(run).summary["status"] == "resonance"


def test_a_real_crossing_beside_an_nsv_stays_a_resonance():
    """An EO 8 response peaking during the run-up (a crossing, 1.6 mm pk-pk) and a weaker
    rotating stall over the whole run: the crossing is reported, the NSV beside it."""
    run = synthesize(n_rev=640, rpm0=2200.0, rpm1=2800.0, order=3.3, nd=-6, amp_pk_m=0.1e-3,
                     sync=(8, _bump(7.0, 0.6, 0.8e-3), 0.3), noise_s=3e-8, seed=11)
    res = _process(run)
    s = res.summary
    assert s["status"] == "resonance" and [e["eo"] for e in s["resonances"]] == [8]
    assert s["resonances"][0]["nd"] == 8
    assert np.mean([b["amp_pkpk_m"] for b in s["blades"]]) == pytest.approx(1.6e-3, rel=0.05)
    assert len(res.nsv) == 1 and res.nsv[0].nd == -6 and res.nsv[0].order == pytest.approx(3.3, abs=ORDER_TOL)
    assert res.nsv[0].amp_pkpk_m == pytest.approx(0.2e-3, rel=0.1)


def test_a_short_run_is_one_block():
    """A run shorter than two blocks (39 revolutions, like examples/flutter.toml) is analysed as
    one block: a flutter at a fixed 346.9 Hz, whose order falls from 7.0 to 6.87 while the speed
    rises, growing to its limit, gives its frequency (amplitude-weighted speed), ND and the
    level reached."""
    f, limit = 346.9, 0.3e-3
    run = synthesize(n_rev=39, rpm0=2971.0, rpm1=3028.0, freq_hz=f, nd=-3,
                     amp_pk_m=logistic(1e-9, 0.5 * limit, 60.0), noise_s=1e-8, seed=12)
    res = _process(run)
    assert res.nsv_scan.whole_run and res.nsv_scan.block == 39
    (d,) = res.nsv
    assert d.nd == -3 and d.freq_hz == pytest.approx(f, abs=1.0)
    # the trend removal models the growth as linear over the block: 8 % here (0.6 % at 640 revs)
    assert d.amp_last_pkpk_m == pytest.approx(limit, rel=0.08)
    assert res.summary["status"] == "none"


@pytest.mark.integration
def test_view_of_a_short_run_shows_the_reports_growth(tmp_path):
    """A run shorter than two blocks has no live NSV message: ``bttsim view`` shows the final
    report's detection (growth per revolution, travelling wave by ND, table)."""
    import subprocess
    import sys
    import warnings

    from rerun.chunk import RrdReader

    from _nsv_truth import write_recording
    from bttsim_stream.views import paths

    run = synthesize(n_rev=39, rpm0=2971.0, rpm1=3028.0, freq_hz=346.9, nd=-3,
                     amp_pk_m=logistic(1e-9, 0.15e-3, 60.0), noise_s=1e-8, seed=12)
    rec = tmp_path / "short.mcap"
    write_recording(rec, run)
    out = tmp_path / "v.rrd"
    res = subprocess.run([sys.executable, "-m", "bttsim_stream.cli", "view", str(rec), "--rrd", str(out)],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    ents: dict = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for chunk in RrdReader(out).stream():
            e = ents.setdefault(chunk.entity_path, {"rows": 0, "static": False})
            e["static"] |= chunk.is_static
            e["rows"] += 0 if chunk.is_static else chunk.num_rows
    assert ents["/" + paths.NSV_REV_AMP]["rows"] == 39
    assert "/" + paths.NSV_AMP not in ents
    assert ents["/" + paths.NSV_TABLE]["static"] and ents["/" + paths.NSV_TW]["static"]


def test_detections_are_scored_against_the_truth_offline_and_live():
    """With the truth's NSV components (the simulator's ``Truth.nsv_*``), each detection is
    scored (ND correct, frequency error, level error); the streaming processor's final report,
    fed per revolution through a truth tracker, scores the same; the truth is only scored."""
    from bttsim_stream.process import StreamingProcessor, TruthPeakTracker
    from bttsim_stream.bus import codec

    f, nd, limit = 344.5, -4, 0.6e-3
    run = synthesize(n_rev=320, rpm0=2450.0, rpm1=2500.0, freq_hz=f, nd=nd,
                     amp_pk_m=logistic(1e-6, 0.5 * limit, 3.0), noise_s=3e-8, seed=13)
    res = process_arrays(run.opr_s, run.toa_s, _geometry(run), ProcessOptions(), truth=run.truth)
    det = res.summary["non_synchronous"][0]
    t = det["truth"]
    assert t["present"] and t["kind"] == "flutter" and t["nd"] == nd and t["nd_correct"]
    assert abs(t["freq_error_hz"]) < 0.5 and abs(t["amp_last_error_pct"]) < 5.0
    assert t["amp_last_pkpk_m"] == pytest.approx(limit, rel=0.01)
    blind = _process(run).summary
    assert "truth" not in blind["non_synchronous"][0]
    blind["non_synchronous"][0]["truth"] = t
    assert blind == res.summary  # scoring changes nothing else
    assert "truth: flutter" in summary_table(res.summary)
    # live: the same through the tracker
    proc = StreamingProcessor(_geometry(run))
    tracker = TruthPeakTracker(8)
    tr = run.truth
    for n in range(run.opr_s.size):
        proc.push(n, run.opr_s[n], run.toa_s[n])
        tracker.update(n, np.zeros(run.n_blades), run.omega_rad_s[n],
                       nsv=(tr.nsv_kind[n], tr.nsv_freq_hz[n], tr.nsv_nd[n], tr.nsv_amp_pkpk_m[n]))
    live = proc.finish(tracker)
    assert live["non_synchronous"][0]["truth"] == t
    rp = codec.encode_resonance_report(codec.Header("r", 0), proc.result.report)
    assert codec.decode_resonance_report(rp).body.to_summary()["non_synchronous"] == live["non_synchronous"]


def test_a_false_detection_is_scored_as_one():
    """Truth without any NSV component in the detection's revolutions: ``present`` false."""
    import dataclasses

    run = synthesize(n_rev=128, rpm0=2800.0, order=2.3, nd=5, amp_pk_m=0.1e-3)
    silent = dataclasses.replace(run.truth, nsv_amp_pkpk_m=np.zeros_like(run.truth.nsv_amp_pkpk_m))
    s = process_arrays(run.opr_s, run.toa_s, _geometry(run), ProcessOptions(), truth=silent).summary
    assert s["non_synchronous"][0]["truth"] == {"kind": None, "present": False}
    assert "a false detection" in summary_table(s)


def test_the_live_screen_is_the_scans_first_step():
    # screen_block (the finite-data shortcut, and the general code with missing samples) passes
    # a block exactly when scan_blocks's statistic and rough amplitude would analyse it
    from bttsim_stream.process.nsv import _band_power, _spectrum

    rng = np.random.default_rng(7)
    L, nb, npr = 32, 12, 5
    n = np.arange(L)[:, None, None]
    seen = set()
    for trial in range(200):
        amp = 10.0 ** rng.uniform(-7.5, -4.5)
        d = 1e-4 * rng.normal(size=(1, nb, npr)) + 1e-7 * n + rng.normal(0, 2e-7, (L, nb, npr))
        d = d + amp * np.sin(2 * np.pi * rng.uniform(0.15, 0.45) * n + rng.uniform(0, 6, (1, nb, npr)))
        if trial % 4 == 3:
            d[rng.random(d.shape) < 0.02] = np.nan
        for opts in (NsvOptions(), NsvOptions(ratio_threshold=3.0, min_amp_m=1e-7)):
            sp = _spectrum(L, opts.pad, opts.guard)
            _, ratio, _, peak = _band_power(d.reshape(1, L, -1), sp)
            rough = 4.0 * np.sqrt(peak[0] / (nb * npr)) / sp[4]
            want = bool(ratio[0] >= opts.ratio_threshold and rough >= 0.5 * opts.min_amp_m)
            finite = bool(np.isfinite(d).all())
            assert screen_block(d, opts) == screen_block(d, opts, finite=finite) == want
            seen.add(want)
    assert seen == {True, False}


@pytest.mark.parametrize("order,nd,rigid", [(0.13, 0, True), (0.13, 3, False), (6.13, 0, False)],
                         ids=["order0.13-nd0", "order0.13-nd3", "order6.13-nd0"])
def test_the_rotors_own_motion_is_named_not_reported_as_vibration(order, nd, rigid):
    """ND 0 below the shaft frequency (every blade's arrival moved alike, slower than the
    shaft: a speed fluctuation, shaft torsion, OPR timing) is not a blade's non-synchronous
    vibration: no detection is reported, offline or live, and a note names it. The same
    content at ND 3, or ND 0 above the shaft frequency (a blade mode), stays a detection."""
    from bttsim_stream.process import StreamingProcessor

    run = synthesize(n_rev=256, rpm0=3000.0, order=order, nd=nd, amp_pk_m=0.1e-3, noise_s=2e-8, seed=4)
    res = _process(run)
    notes = [n for n in res.summary["notes"] if n.startswith("rigid-body motion, not blade vibration: ND 0")]
    if rigid:
        assert res.nsv == () and not res.summary.get("non_synchronous") and len(notes) == 1, res.summary["notes"]
        assert f"(order {order:.3f}, slower than the shaft)" in notes[0]
    else:
        assert len(res.nsv) == 1 and res.nsv[0].nd == nd and res.nsv[0].order == pytest.approx(order, abs=ORDER_TOL)
        assert notes == []
    found = _live_nsv(StreamingProcessor(_geometry(run)), run)
    assert (found == []) == rigid, found

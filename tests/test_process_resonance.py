"""Resonance peaks, E_A / E_f (Eq. 18-19) and the summary JSON of the brief."""

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest

from bttsim_stream.process import (TruthPeaks, TruthPeakTracker, find_peaks, resonance_errors, resonance_report,
                                   summary_table, truth_peaks)

BLADE_KEYS = {"blade", "amp_pkpk_m", "freq_hz", "truth_amp_pkpk_m", "truth_freq_hz", "E_A_pct", "E_f_pct"}
TOP_KEYS = {"nd", "eo", "cn", "blades", "mean_E_A_pct", "max_E_A_pct", "mean_E_f_pct", "max_E_f_pct"}
#: Added by issue 12 beside the legacy keys (a legacy report built by resonance_report has no entries).
NEW_KEYS = {"status", "resonances", "steady", "notes"}


def _sdof_curve(f, fn, zeta, a0):
    r = f / fn
    return a0 / np.sqrt((1 - r * r) ** 2 + (2 * zeta * r) ** 2)


def test_peak_pick_and_parabolic_vertex():
    n = np.arange(100.0)
    f = 300 + 0.1 * n
    amp = np.stack([2e-3 - 1e-7 * (n - 40.3) ** 2, 1e-3 - 1e-7 * (n - 70) ** 2], axis=1)
    amp[3, 0] = np.nan
    pk = find_peaks(amp, f)
    np.testing.assert_array_equal(pk.revolution, [40, 70])
    np.testing.assert_allclose(pk.freq_hz, [304.0, 307.0])
    par = find_peaks(amp, f, method="parabolic")
    np.testing.assert_allclose(par.revolution, [40.3, 70.0], atol=1e-9)
    np.testing.assert_allclose(par.amp_pkpk_m, [2e-3, 1e-3], rtol=1e-12)
    np.testing.assert_allclose(par.freq_hz, [304.03, 307.0], atol=1e-9)
    with pytest.raises(ValueError):
        find_peaks(amp, f, method="nope")


def test_sdof_fit_recovers_the_curve():
    f = np.linspace(330, 360, 3001)
    fn, zeta = 344.0, 0.01
    amp = np.stack([_sdof_curve(f, fn, zeta, 1e-5), _sdof_curve(f, fn + 2, 2 * zeta, 2e-5)], axis=1)
    pk = find_peaks(amp, f, method="sdof")
    f_peak = np.array([fn, fn + 2]) * np.sqrt(1 - 2 * np.array([zeta, 2 * zeta]) ** 2)
    a_peak = np.array([1e-5, 2e-5]) / (2 * np.array([zeta, 2 * zeta]) * np.sqrt(1 - np.array([zeta, 2 * zeta]) ** 2))
    np.testing.assert_allclose(pk.freq_hz, f_peak, rtol=1e-7)
    np.testing.assert_allclose(pk.amp_pkpk_m, a_peak, rtol=1e-6)
    np.testing.assert_allclose(pk.damping_ratio, [zeta, 2 * zeta], rtol=1e-5)


def test_all_nan_blade():
    amp = np.ones((5, 2))
    amp[:, 1] = np.nan
    pk = find_peaks(amp, np.arange(5.0))
    assert np.isnan(pk.amp_pkpk_m[1]) and pk.amp_pkpk_m[0] == 1.0


def test_truth_peaks_and_tracker_agree():
    rng = np.random.default_rng(0)
    truth = SimpleNamespace(d_eqv_pkpk_m=rng.random((50, 4)), omega_mean=np.linspace(200, 300, 50))
    tp = truth_peaks(truth, 8)
    tr = TruthPeakTracker(8)
    for n in range(50):
        tr.update(n, truth.d_eqv_pkpk_m[n], truth.omega_mean[n])
    got = tr.peaks()
    np.testing.assert_array_equal(got.revolution, tp.revolution)
    np.testing.assert_array_equal(got.amp_pkpk_m, tp.amp_pkpk_m)
    np.testing.assert_allclose(got.freq_hz, 8 * truth.omega_mean[tp.revolution] / (2 * np.pi), rtol=1e-15)
    assert TruthPeakTracker(8).peaks() is None


def test_errors_are_eq18_19():
    pk = find_peaks(np.array([[2.0e-3], [2.2e-3]]), np.array([340.0, 345.0]))
    truth = TruthPeaks(revolution=np.array([1]), amp_pkpk_m=np.array([2.0e-3]), freq_hz=np.array([344.0]))
    e_a, e_f = resonance_errors(pk, truth)
    assert e_a[0] == pytest.approx(10.0) and e_f[0] == pytest.approx(100 / 344.0)


def _report(with_truth):
    rng = np.random.default_rng(1)
    amp = rng.random((30, 3)) * 1e-3
    pk = find_peaks(amp, np.linspace(340, 348, 30))
    truth = TruthPeaks(revolution=np.zeros(3, int), amp_pkpk_m=np.full(3, 1e-3), freq_hz=np.full(3, 344.0))
    return resonance_report(pk, nd=1, eo=8, cn=1.4328, truth=truth if with_truth else None)


def test_summary_json_exact_form():
    s = _report(True).to_summary()
    assert set(s) == TOP_KEYS | NEW_KEYS
    assert s["status"] == "resonance" and s["resonances"] == [] and s["steady"] == []
    assert [b["blade"] for b in s["blades"]] == [0, 1, 2]
    assert all(set(b) == BLADE_KEYS for b in s["blades"])
    assert isinstance(s["nd"], int) and isinstance(s["eo"], int) and isinstance(s["cn"], float)
    assert all(isinstance(v, float) for b in s["blades"] for k, v in b.items() if k != "blade")
    assert s["mean_E_A_pct"] == pytest.approx(np.mean([b["E_A_pct"] for b in s["blades"]]))
    assert s["max_E_f_pct"] == pytest.approx(max(b["E_f_pct"] for b in s["blades"]))
    json.loads(json.dumps(s))
    blind = _report(False).to_summary()
    assert set(blind) == {"nd", "eo", "cn", "blades"} | NEW_KEYS
    assert all(set(b) == {"blade", "amp_pkpk_m", "freq_hz"} for b in blind["blades"])


@pytest.mark.parametrize("with_truth", [True, False], ids=["truth", "blind"])
def test_summary_round_trips_through_the_codec(with_truth):
    from bttsim_stream.bus import codec

    report = _report(with_truth)
    s = report.to_summary()
    payload = codec.encode_resonance_report(codec.Header("r", 0), report)
    back = codec.decode_resonance_report(payload).body.to_summary()
    assert back.keys() == s.keys()
    for a, b in zip(back["blades"], s["blades"]):
        assert a == pytest.approx(b)


def test_table_text():
    text = _report(True).table()
    assert "E_A mean" in text and len(text.splitlines()) == 2 + 3 + 1
    assert "E_A" not in summary_table(_report(False).to_summary())
    assert not math.isnan(float(text.splitlines()[2].split()[1]))

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


def _one_entry_summary(amp_m, amp_std_m, phase_rad):
    """A summary holding one crossing of two blades (amplitudes pk-pk, m)."""
    blades = [{"blade": b, "amp_pkpk_m": a, "freq_hz": 344.2, "phase_rad": p, "amp_std_m": s}
              for b, (a, s, p) in enumerate(zip(amp_m, amp_std_m, phase_rad))]
    entry = {"kind": "crossing", "eo": 8, "nd": 1, "rpm": 2581.0, "freq_hz": 344.2, "method": "peak", "cn": 1.4,
             "detection": {"value": 3.0, "threshold": 2.0, "snr": 100.0, "snr_threshold": 8.0},
             "revolutions": {"first": 0, "last": 10, "peak": 5}, "blades": blades}
    return {"status": "resonance", "resonances": [entry], "steady": [], "blades": blades, "nd": 1, "eo": 8,
            "cn": 1.4}


def _columns(text: str) -> tuple[list[str], list[list[float]]]:
    """The per-blade table of ``text``: its header cells (split on two spaces) and its rows."""
    lines = text.splitlines()
    i = next(k for k, line in enumerate(lines) if line.lstrip().startswith("blade"))
    head = [c.strip() for c in lines[i].split("  ") if c.strip()]
    rows = []
    for line in lines[i + 1:]:
        cells = line.split()
        if not cells or not cells[0].isdigit():
            break
        rows.append([float(c) for c in cells])
    return head, rows


def test_table_prints_the_uncertainty_in_micrometres_and_the_phase_in_degrees():
    """An uncertainty of 19 nm is not 0.0000 mm: it is printed in um, beside the phase (deg)."""
    text = summary_table(_one_entry_summary([2.3732e-3, 2.3717e-3], [1.88e-8, 2.5e-7], [-1.3475, math.pi / 2]))
    head, rows = _columns(text)
    assert head == ["blade", "amp mm pk-pk", "+- \u00b5m", "freq Hz", "phase deg"]
    np.testing.assert_allclose([r[1] for r in rows], [2.3732, 2.3717], atol=1e-4)
    np.testing.assert_allclose([r[2] for r in rows], [0.019, 0.25], atol=1e-3)
    np.testing.assert_allclose([r[4] for r in rows], [math.degrees(-1.3475), 90.0], atol=0.05)


def test_table_prints_small_amplitudes_in_micrometres():
    head, rows = _columns(summary_table(_one_entry_summary([12e-6, 8.5e-6], [1e-7, 1e-7], [0.0, 3 * math.pi])))
    assert head[1] == "amp \u00b5m pk-pk"
    np.testing.assert_allclose([r[1] for r in rows], [12.0, 8.5], atol=1e-4)
    np.testing.assert_allclose([r[4] for r in rows], [0.0, -180.0], atol=1e-9)  # wrapped to [-180, 180)

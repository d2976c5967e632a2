"""95 % intervals (process/intervals.py): each term against an analytic case, and a coverage floor."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bttsim_stream.process.fit import fit_revolutions, sine_at_probes
from bttsim_stream.process.intervals import (CN_NOTE_THRESHOLD, MODEL_ERROR, Z95, ZEROING_SHARE, IntervalTerms,
                                             crossing_intervals, crossing_notes, layout_gain)
from bttsim_stream.process.resonance import ResonancePeaks

PAPER_PROBES = np.deg2rad([5.0, 15.15, 23.82, 220.0, 301.5])


def test_noise_term_covers_95_percent_of_a_known_sine():
    """Term (a): amp +- 1.96 amp_std of the least-squares fit, 200 seeds of white noise."""
    amp, phase, sigma, window = 2e-3, 0.7, 2e-5, 10
    hits = []
    for seed in range(200):
        rng = np.random.default_rng(seed)
        clean = sine_at_probes(PAPER_PROBES, 8, amp, phase, 1e-4)
        d = clean[None, None, :] + sigma * rng.standard_normal((window, 1, PAPER_PROBES.size))
        f = fit_revolutions(d, PAPER_PROBES, 8, window=window)
        k = window // 2
        a, s = f.amp_pkpk_m[k, 0, 0], f.amp_std_m[k, 0, 0]
        hits.append(abs(a - amp) <= Z95 * s)
    assert 0.90 <= np.mean(hits) <= 0.99


def test_layout_gain_of_a_uniform_layout_and_a_poor_one():
    n = 6
    th = 2 * np.pi * np.arange(n) / n + 0.1
    P = np.exp(1j * np.linspace(0, 3, 4))
    np.testing.assert_allclose(layout_gain(th, (1,), 0, P), math.sqrt(2.0 / n), rtol=1e-12)
    poor = layout_gain(np.deg2rad([5.0, 51.0, 97.0]), (8,), 0, P)
    assert np.all(poor > 30 * math.sqrt(2.0 / 3))  # direction-dependent: 38-121 here


def _peaks(A, rev, f, psi=0.0, std=0.0):
    nb = len(A)
    return ResonancePeaks(revolution=np.asarray(rev, float), amp_pkpk_m=np.asarray(A, float),
                          freq_hz=np.asarray(f, float), damping_ratio=np.full(nb, np.nan), method="peak",
                          phase_rad=np.full(nb, psi), amp_std_m=np.full(nb, std), freq_std_hz=np.zeros(nb))


def test_crossing_terms_on_an_exact_parabola():
    """No noise, an exact parabola: the model term is 0; the zeroing and layout terms are as
    documented; the frequency interval spans the plateau within h_A, +- half a step."""
    n = 41
    r = np.arange(n)
    f = 300.0 + 0.05 * r
    amp = (1e-3 - 1e-7 * (r - 20.0) ** 2)[:, None]
    pk = _peaks([1e-3], [20], [f[20]])
    gain = np.array([0.6])
    out, t = crossing_intervals(pk, amp, np.zeros((n, 1)), amp, f, 0, n - 1, gain=gain, half_power_width=30,
                                zeroing_correction=0.04, contamination=0.02)
    assert t.model_m[0] == pytest.approx(0.0, abs=1e-12)
    assert t.zeroing_m[0] == pytest.approx(ZEROING_SHARE * 0.04 * 1e-3)
    assert t.layout_m[0] == pytest.approx(0.6 * MODEL_ERROR * 1e-3)
    h = Z95 * t.layout_m[0] + t.zeroing_m[0]
    np.testing.assert_allclose(out.amp_ci95_m[0], [1e-3 - h, 1e-3 + h])
    k = int(math.floor(math.sqrt(h / 1e-7)))  # revolutions within h of the peak each side
    np.testing.assert_allclose(out.freq_ci95_hz[0], [f[20 - k] - 0.025, f[20 + k] + 0.025])
    assert out.phase_ci95_rad[0, 0] < 0 < out.phase_ci95_rad[0, 1]


def test_frequency_interval_is_at_least_half_a_revolution_step():
    n = 21
    f = 300.0 + 0.2 * np.arange(n)
    amp = np.where(np.arange(n) == 10, 1e-3, 5e-4)[:, None]
    out, _ = crossing_intervals(_peaks([1e-3], [10], [f[10]]), amp, np.zeros((n, 1)), amp, f, 0, n - 1,
                                gain=np.array([0.5]), half_power_width=6)
    np.testing.assert_allclose(out.freq_ci95_hz[0], [f[10] - 0.1, f[10] + 0.1])


def test_notes_name_a_poor_layout_and_overlaps():
    z = np.zeros(2)
    t = IntervalTerms(noise_m=z, layout_m=np.full(2, 1e-4), model_m=z, zeroing_m=z, half_width_m=z)
    notes = crossing_notes(eo=8, method="peak", cn=433.0, terms=t, amp_pkpk_m=np.full(2, 1e-3),
                           contamination=0.0, contamination_limit=0.05, zeroing_correction=math.nan,
                           nsv_overlap=["order 7.5"], other_crossings=[7])
    assert any("poor layout" in n and f"{CN_NOTE_THRESHOLD:g}" in n for n in notes)
    assert any("non-synchronous" in n for n in notes) and any("EO 7" in n for n in notes)
    quiet = crossing_notes(eo=8, method="peak", cn=1.4, terms=t, amp_pkpk_m=np.full(2, 1e-3), contamination=0.0,
                           contamination_limit=0.05, zeroing_correction=math.nan, nsv_overlap=[], other_crossings=[])
    assert quiet == ()


@pytest.mark.slow
def test_coverage_floor_on_a_small_seeded_matrix():
    """The paper's default run: every method's 95 % amplitude and frequency intervals hold the
    truth on >= 80 % of the blades, median half-width <= 1 % of the amplitude; a fast sweep
    (peak, not corrected) likewise >= 80 %."""
    from bench.bench_intervals import score_summary
    from bttsim_stream.paper.validate_processing import simulate
    from bttsim_stream.process import ProcessOptions, process_arrays

    run = simulate(None)
    for method in ("peak", "sdof", "cff"):
        rows = score_summary(process_arrays(run.opr_s, run.toa_s, run.info, ProcessOptions(method=method),
                                            truth=run.truth).summary)
        assert len(rows) == 29
        assert np.mean([r["amp_covered"] for r in rows]) >= 0.8, method
        assert np.mean([r["freq_covered"] for r in rows]) >= 0.8, method
        assert np.median([r["half_width_pct"] for r in rows]) <= 1.0, method
    fast = simulate({"speed": {"start_rpm": 2000.0, "end_rpm": 3200.0, "duration_s": 5.0},
                     "model": {"stiffness_std": 0.002}, "run": {"seed": 1}})
    s = process_arrays(fast.opr_s, fast.toa_s, fast.info, ProcessOptions(method="peak"), truth=fast.truth).summary
    rows = score_summary(s)
    assert rows and np.mean([r["amp_covered"] for r in rows]) >= 0.8

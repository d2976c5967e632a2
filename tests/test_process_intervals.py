"""95 % intervals (process/intervals.py): each term against an analytic case, coverage against the exact
truth, the notes, and one code path offline and live."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bttsim_stream.process.fit import fit_revolutions, sine_at_probes
from bttsim_stream.process.intervals import (CN_NOTE_THRESHOLD, MODEL_ERROR, Z95, IntervalTerms, crossing_intervals,
                                             crossing_notes, dwell_intervals, dwell_misfit, layout_gain)
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


def test_dwell_misfit_covers_common_probe_errors_95_percent():
    """A dwell's probe term: every blade's steady response (a travelling wave) plus one error
    per probe common to all blades (isotropic, 300 seeds). The amplitude's interval from the
    misfit, ``t_dof std``, holds the true amplitude for about 95 % of the blades; with no error
    the term vanishes, and with 3 probes (no redundancy) it cannot be seen."""
    from scipy.stats import t as student_t

    nb, amp, sigma = 29, 2e-3, 3e-4
    phases = 2 * np.pi * np.arange(nb) / nb
    clean = np.stack([sine_at_probes(PAPER_PROBES, 8, amp, ph) for ph in phases])
    std0, dof0 = dwell_misfit(clean, PAPER_PROBES, (8,), 0)
    assert dof0 == 2 and np.all(std0 < 1e-12 * amp)
    hits = []
    for seed in range(300):
        d = clean + sigma * np.random.default_rng(seed).standard_normal(PAPER_PROBES.size)[None, :]
        std, dof = dwell_misfit(d, PAPER_PROBES, (8,), 0)
        est = fit_revolutions(d[None], PAPER_PROBES, 8).amp_pkpk_m[0, :, 0]
        hits += list(np.abs(est - amp) <= student_t.ppf(0.975, dof) * std)
    assert 0.92 <= np.mean(hits) <= 0.98, np.mean(hits)
    three = PAPER_PROBES[:3]
    std3, dof3 = dwell_misfit(np.stack([sine_at_probes(three, 8, amp, ph) for ph in phases]), three, (8,), 0)
    assert dof3 == 0 and np.all(np.isnan(std3))


def test_dwell_intervals_add_their_terms_and_none_when_the_zeroing_is_unknown():
    """``1.96 sqrt(noise^2 + layout^2) + t_dof probes + zeroing``, not below zero; a NaN
    zeroing bound (the reference's response unknown) gives no amplitude or phase interval."""
    from scipy.stats import t as student_t

    pk = _peaks([1e-3, 2e-3], [0, 0], [300.0, 300.0], psi=0.5, std=1e-6)
    out = dwell_intervals(pk, layout_m=np.array([2e-6, 0.0]), probes_m=np.array([1e-5, 1e-3]), dof=2,
                          zeroing_m=np.array([3e-6, 0.0]))
    t = student_t.ppf(0.975, 2)
    h = np.array([Z95 * math.hypot(1e-6, 2e-6) + t * 1e-5 + 3e-6, Z95 * 1e-6 + t * 1e-3])
    np.testing.assert_allclose(out.amp_ci95_m[:, 1] - [1e-3, 2e-3], h, rtol=1e-12)
    assert out.amp_ci95_m[0, 0] == pytest.approx(1e-3 - h[0], rel=1e-12) and out.amp_ci95_m[1, 0] == 0.0
    assert out.phase_ci95_rad[0, 1] - 0.5 == pytest.approx(math.asin(h[0] / 1e-3), rel=1e-12)
    assert out.phase_ci95_rad[1, 1] - 0.5 == pytest.approx(math.pi)  # h above the amplitude: any phase
    unknown = dwell_intervals(pk, zeroing_m=math.nan)
    assert np.all(np.isnan(unknown.amp_ci95_m)) and np.all(np.isnan(unknown.phase_ci95_rad))
    assert np.all(np.isfinite(unknown.freq_ci95_hz))


def _peaks(A, rev, f, psi=0.0, std=0.0):
    nb = len(A)
    return ResonancePeaks(revolution=np.asarray(rev, float), amp_pkpk_m=np.asarray(A, float),
                          freq_hz=np.asarray(f, float), damping_ratio=np.full(nb, np.nan), method="peak",
                          phase_rad=np.full(nb, psi), amp_std_m=np.full(nb, std), freq_std_hz=np.zeros(nb))


def test_crossing_terms_on_an_exact_parabola():
    """No noise, an exact parabola: the model term is the revolution sampling's only
    (``2 |P''| / 8``); the layout term as documented; the frequency interval spans the plateau
    within 2 h_A, +- half a step; the phase interval is ``asin(h_A / A)`` wide."""
    n = 41
    r = np.arange(n)
    f = 300.0 + 0.05 * r
    amp = (1e-3 - 1e-7 * (r - 20.0) ** 2)[:, None]
    pk = _peaks([1e-3], [20], [f[20]])
    gain = np.array([0.6])
    out, t = crossing_intervals(pk, amp, np.zeros((n, 1)), amp, f, 0, n - 1, gain=gain, half_power_width=30)
    assert t.model_m[0] == pytest.approx(2.0 * 1e-7 / 8.0, rel=1e-9)  # |P''| = (2e-7) / 2
    assert t.zeroing_m[0] == 0.0
    assert t.layout_m[0] == pytest.approx(0.6 * MODEL_ERROR * 1e-3)
    h = Z95 * t.layout_m[0] + t.model_m[0]
    np.testing.assert_allclose(out.amp_ci95_m[0], [1e-3 - h, 1e-3 + h])
    k = int(math.floor(math.sqrt(2 * h / 1e-7)))  # revolutions within 2h of the peak each side
    np.testing.assert_allclose(out.freq_ci95_hz[0], [f[20 - k] - 0.025, f[20 + k] + 0.025])
    np.testing.assert_allclose(out.phase_ci95_rad[0], [-math.asin(h / 1e-3), math.asin(h / 1e-3)])


def test_frequency_interval_is_at_least_half_a_revolution_step():
    n = 21
    f = 300.0 + 0.2 * np.arange(n)
    amp = np.where(np.arange(n) == 10, 1e-3, 5e-4)[:, None]
    flat = np.full((n, 1), 1e-3)  # unsmoothed amplitudes: no noise, no model term
    out, _ = crossing_intervals(_peaks([1e-3], [10], [f[10]]), amp, np.zeros((n, 1)), flat, f, 0, n - 1,
                                gain=np.array([0.5]), half_power_width=6)
    np.testing.assert_allclose(out.freq_ci95_hz[0], [f[10] - 0.1, f[10] + 0.1])


def _swept_resonance(n=161, width=20.0, peak=80.3):
    """A resonance's complex response per revolution (pk-pk 2 mm at ``peak``), its frequencies."""
    x = (np.arange(n) - peak) / (width / 2)
    P = 1e-3 / (1.0 - 1j * x)  # |P| = 1 mm at the peak, the phase turns by pi
    return P, 340.0 + 0.02 * np.arange(n)


def test_zeroing_error_taken_out_widens_towards_the_truth():
    """The zeroing left a known complex error ``e`` in the responses: the intervals span the
    peak with ``e`` taken out, so the truth's amplitude, frequency and phase are covered; an
    interval that ignores ``e`` misses all three."""
    P, f = _swept_resonance()
    e = np.array([0.3e-3 * np.exp(2.0j)])
    meas = P[:, None] + e[None, :]
    amp, ph = 2.0 * np.abs(meas), np.angle(meas)
    k = int(np.argmax(amp[:, 0]))
    pk = _peaks([amp[k, 0]], [k], [f[k]], psi=ph[k, 0])
    kt = int(np.argmax(np.abs(P)))
    truth = (2.0 * abs(P[kt]), f[kt], np.angle(P[kt]))

    def covered(out):
        a, fr, p = out.amp_ci95_m[0], out.freq_ci95_hz[0], out.phase_ci95_rad[0]
        return (a[0] <= truth[0] <= a[1], fr[0] <= truth[1] <= fr[1], p[0] <= truth[2] <= p[1])

    args = (pk, amp, ph, amp, f, 0, P.size - 1)
    blind, _ = crossing_intervals(*args, gain=np.array([0.6]), half_power_width=20)
    assert not any(covered(blind))
    known, t = crossing_intervals(*args, gain=np.array([0.6]), half_power_width=20, zeroing_error=e)
    assert all(covered(known))
    assert t.zeroing_m[0] > 0.0


def test_notes_name_a_poor_layout_a_fast_sweep_and_overlaps():
    z = np.zeros(2)
    t = IntervalTerms(noise_m=z, layout_m=np.full(2, 1e-4), model_m=np.full(2, 2e-5), zeroing_m=z,
                      half_width_m=z, orders_m=np.full(2, 3e-5))
    notes = crossing_notes(eo=8, method="peak", cn=433.0, terms=t, amp_pkpk_m=np.full(2, 1e-3),
                           contamination=0.0, contamination_limit=0.05, zeroing_correction=math.nan,
                           nsv_overlap=["order 7.5"], other_crossings=[7], half_power_width=14.0,
                           fast_sweep_revolutions=60.0)
    assert any("poor layout" in n and f"{CN_NOTE_THRESHOLD:g}" in n for n in notes)
    assert any(n.startswith("fast sweep") and "14 revolutions" in n for n in notes)
    assert any("non-synchronous" in n for n in notes) and any("EO 7" in n for n in notes)
    assert any("other engine orders fitted jointly" in n for n in notes)
    t0 = IntervalTerms(noise_m=z, layout_m=np.full(2, 1e-4), model_m=z, zeroing_m=z, half_width_m=z)
    quiet = crossing_notes(eo=8, method="peak", cn=1.4, terms=t0, amp_pkpk_m=np.full(2, 1e-3), contamination=0.0,
                           contamination_limit=0.05, zeroing_correction=math.nan, nsv_overlap=[], other_crossings=[],
                           half_power_width=150.0, fast_sweep_revolutions=60.0)
    assert quiet == ()


#: A fast sweep through the default rotor's EO 8 resonance (the half-power band in ~14
#: revolutions, a reference window that is not quiet) and a poorly conditioned layout.
FAST = {"speed": {"start_rpm": 2000.0, "end_rpm": 3200.0, "duration_s": 5.0}, "model": {"stiffness_std": 0.002},
        "acquisition": {"trigger_jitter_s": 1e-7}, "run": {"seed": 3}}
POOR = {"speed": {"start_rpm": 2200.0, "end_rpm": 3000.0, "duration_s": 12.0},
        "probes": {"angles_deg": [5.0, 51.0, 97.0]}, "run": {"seed": 3}}


@pytest.fixture(scope="module")
def fast_run():
    from bench.bench_intervals import _Truths, simulate

    run, actual = simulate(FAST)
    return run, _Truths(FAST, run, actual)


@pytest.mark.slow
@pytest.mark.parametrize("method", ["peak", "sdof", "cff"])
def test_coverage_on_a_fast_sweep_against_the_exact_truth(fast_run, method):
    """Every method's amplitude, frequency and phase intervals hold the exact truth (its own
    response; the phase of Eq. 16 on the exact deflections) on >= 80 % of the blades, and the
    crossing says the sweep is fast."""
    from bench.bench_intervals import score_summary
    from bttsim_stream.process import ProcessOptions, process_arrays

    run, truths = fast_run
    s = process_arrays(run.opr_s, run.toa_s, run.info, ProcessOptions(method=method), truth=run.truth).summary
    rows = score_summary(s, truths)
    assert len(rows) == 29
    for key in ("amp_covered", "freq_covered", "phase_covered"):
        assert np.mean([r[key] for r in rows]) >= 0.8, key
    assert all(any(n.startswith("fast sweep") for n in r["notes"]) for r in rows)


@pytest.mark.slow
def test_a_poor_layout_is_noted_in_process():
    """Probes at 5, 51, 97 deg (CN 433 at EO 8): the crossing names the layout, and its
    intervals hold the truth though its errors are large."""
    from bench.bench_intervals import _Truths, score_summary, simulate
    from bttsim_stream.process import ProcessOptions, process_arrays

    run, actual = simulate(POOR)
    s = process_arrays(run.opr_s, run.toa_s, run.info, ProcessOptions(), truth=run.truth).summary
    rows = score_summary(s, _Truths(POOR, run, actual))
    assert rows and all(any(n.startswith("poor layout: CN") for n in r["notes"]) for r in rows)
    assert np.mean([r["amp_covered"] for r in rows]) >= 0.8
    assert all(r["notes"] for r in rows if r["E_A_pct"] > 3.0)


@pytest.mark.slow
def test_live_processor_uses_the_same_interval_code(fast_run, monkeypatch):
    """The streaming processor's final report (the live node's) goes through the offline
    pipeline's interval code: the same calls, bit-identical intervals and notes."""
    import bttsim_stream.process.pipeline as pipeline
    from bttsim_stream.process import ProcessOptions, StreamingProcessor, process_arrays

    run, _ = fast_run
    calls = []
    real = pipeline.crossing_intervals

    def spy(*a, **k):
        calls.append(k["half_power_width"])
        return real(*a, **k)

    monkeypatch.setattr(pipeline, "crossing_intervals", spy)
    opts = ProcessOptions(method="peak")
    offline = process_arrays(run.opr_s, run.toa_s, run.info, opts).summary
    n_offline = len(calls)
    proc = StreamingProcessor(run.info, opts)
    for n in range(run.opr_s.size):
        proc.push(n, run.opr_s[n], run.toa_s[n])
    live = proc.finish()
    assert n_offline >= 1 and len(calls) == 2 * n_offline
    keys = ("amp_ci95_m", "freq_ci95_hz", "phase_ci95_rad")
    for a, b in zip(offline["resonances"], live["resonances"], strict=True):
        assert a["notes"] == b["notes"] and a["notes"]
        assert [[r[k] for k in keys] for r in a["blades"]] == [[r[k] for k in keys] for r in b["blades"]]


@pytest.mark.slow
def test_paper_default_run_covers_with_narrow_intervals():
    """The paper's default run: every method's amplitude, frequency and phase intervals hold
    the exact truth on >= 80 % of the blades, median amplitude half-width <= 1 %."""
    from bench.bench_intervals import _Truths, score_summary, simulate
    from bttsim_stream.process import ProcessOptions, process_arrays

    run, actual = simulate({})
    truths = _Truths({}, run, actual)
    for method in ("peak", "sdof", "cff"):
        rows = score_summary(process_arrays(run.opr_s, run.toa_s, run.info, ProcessOptions(method=method),
                                            truth=run.truth).summary, truths)
        assert len(rows) == 29
        for key in ("amp_covered", "freq_covered", "phase_covered"):
            assert np.mean([r[key] for r in rows]) >= (0.95 if key == "amp_covered" else 0.8), (method, key)
        assert np.median([r["half_width_pct"] for r in rows]) <= 1.0, method


@pytest.mark.slow
def test_a_quiet_reference_still_gets_the_zeroing_term(monkeypatch):
    """A slow run-up with a quiet reference (no correction, no note): the prepared baseline can
    still leave a constant in the responses, so the swept SDOF fit's constant is measured on
    every blade and enters the amplitude interval, which then holds the exact truth."""
    from bench.bench_intervals import CLASSES, _merge, _Truths, score_summary, simulate
    from bttsim_stream.process import ProcessOptions, pipeline, process_arrays

    seen = []
    real = pipeline.crossing_intervals

    def spy(*args, **kw):
        seen.append(kw)
        return real(*args, **kw)

    monkeypatch.setattr(pipeline, "crossing_intervals", spy)
    cfg = _merge(CLASSES["paper_rate"], {"speed": {"start_rpm": 1600.0, "end_rpm": 3600.0, "duration_s": 66.0}})
    run, actual = simulate(cfg)
    s = process_arrays(run.opr_s, run.toa_s, run.info, ProcessOptions(), truth=run.truth).summary
    assert len(seen) == 1 and not s["resonances"][0]["notes"]
    e = np.asarray(seen[0]["zeroing_error"])
    assert e.shape == (29,) and np.all(np.isfinite(e)) and np.all(np.abs(e) > 0.0)
    rows = score_summary(s, _Truths(cfg, run, actual))
    assert np.mean([r["amp_covered"] for r in rows]) >= 0.9  # the pooled acceptance of the intervals


def test_no_crossing_note_names_a_strongly_changing_response():
    """A run inside a resonance's skirt (amplitude rising 4x to the run's end) gets the note with
    the range and the speed of the largest; a flat response (within the ratio) gets none."""
    from bttsim_stream.process.intervals import no_crossing_note

    n, nb = 200, 29
    omega = np.linspace(2540.0, 2620.0, n) * 2 * np.pi / 60
    rising = np.linspace(0.13e-3, 0.54e-3, n)[:, None, None] * np.ones((1, nb, 1))
    note = no_crossing_note(rising, omega, (8,), 2.0)
    assert note is not None and "EO 8" in note and "largest at 2620 rpm" in note
    lo, hi = np.percentile(np.linspace(0.13e-3, 0.54e-3, n), [5, 95])
    assert f"({hi / lo:.1f} x)" in note
    flat = 1e-4 * (1.0 + 0.3 * np.sin(np.linspace(0, 6, n)))[:, None, None] * np.ones((1, nb, 1))
    assert no_crossing_note(flat, omega, (8,), 2.0) is None


def test_zeroing_gain_by_blocks_recovers_k_and_equals_the_whole_sum():
    """``P = K g`` over the skirt gives back ``K`` per blade (0 for a blade with no data), and
    reading the skirt's responses by blocks (any size, array or reader) gives the very same
    numbers as the sums over the whole array -- one column (summed pairwise by numpy) too."""
    from bttsim_stream.process.zeroing import tail_gain

    rng = np.random.default_rng(7)
    n, nb = 9000, 5
    g = rng.normal(size=n) + 1j * rng.normal(size=n)
    K = (rng.normal(size=nb) + 1j * rng.normal(size=nb)) * 1e-5
    P = g[:, None] * K[None, :] + 1e-9 * (rng.normal(size=(n, nb)) + 1j * rng.normal(size=(n, nb)))
    P[rng.random((n, nb)) < 0.1] = np.nan
    P[:, 3] = np.nan
    whole = tail_gain(g, P, block=n)
    assert np.allclose(whole[[0, 1, 2, 4]], K[[0, 1, 2, 4]], rtol=1e-5) and whole[3] == 0.0
    ok = np.isfinite(P)  # the sums written out, row after row, as numpy adds along axis 0
    w = np.where(ok, np.abs(g)[:, None] ** 2, 0.0).sum(axis=0)
    with np.errstate(all="ignore"):
        ref = np.where(ok, np.conj(g)[:, None] * np.where(ok, P, 0.0), 0.0).sum(axis=0) / w
    assert np.array_equal(whole, np.where(w > 0, ref, 0.0))
    for block in (1, 13, 1024, 4096):
        assert np.array_equal(tail_gain(g, P, block), whole)
        assert np.array_equal(tail_gain(g, lambda rows: P[rows], block), whole)
    one = P[:, :1]
    assert np.array_equal(tail_gain(g, one, block=64), tail_gain(g, one, block=n))


def test_dwell_means_by_blocks_are_numpys():
    """A dwell's sums and means given by blocks of revolutions (:class:`RowSums`,
    :class:`NanMean`) are ``np.nanmean`` / ``np.nansum`` / the counts of the dwell's rows,
    number for number: (revolution, blade, probe) displacements, complex responses, all-NaN
    columns; a single column (summed pairwise by numpy) given whole."""
    import warnings

    from bttsim_stream.process.steady import NanMean, RowSums

    rng = np.random.default_rng(3)
    run = rng.normal(size=(9000, 6, 4)) * 1e-5
    run[rng.random(run.shape) < 0.05] = np.nan
    run[:, 2, 1] = np.nan
    cplx = run[..., 0] + 1j * run[..., 1]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for x in (run, cplx, cplx[:, :1]):
            want = np.nanmean(x, axis=0)
            for block in ((1, 999, 4096) if x.shape[1] > 1 else (len(x),)):
                mean, fin, sq = NanMean(), RowSums(), RowSums()
                for lo in range(0, len(x), block):
                    mean.add(x[lo:lo + block])
                    fin.add(np.isfinite(x[lo:lo + block]))
                got = mean.mean()
                assert got.dtype == want.dtype and np.array_equal(got, want, equal_nan=True)
                assert np.array_equal(fin.total, np.sum(np.isfinite(x), axis=0))
                for lo in range(0, len(x), block):
                    sq.add(np.nan_to_num(np.abs(x[lo:lo + block] - got) ** 2, nan=0.0))
                assert np.array_equal(sq.total, np.nansum(np.abs(x - want) ** 2, axis=0))

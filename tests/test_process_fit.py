"""Windowed sine fits (Eq. 16-17): exact recovery, missing probes, windows, uncertainty."""

import numpy as np
import pytest

from bttsim_stream.process import design_matrix, fit_revolutions, sine_at_probes

PROBES = np.deg2rad([5.0, 15.15, 23.82, 220.0, 301.5])


def _sines(rng, n_rev, nb, eo, probes=PROBES):
    amp = rng.uniform(1e-4, 3e-3, (n_rev, nb))
    phase = rng.uniform(-np.pi, np.pi, (n_rev, nb))
    dc = rng.uniform(-1e-3, 1e-3, (n_rev, nb))
    d = dc[..., None] + 0.5 * amp[..., None] * np.sin(eo * probes + phase[..., None])
    return d, amp, phase, dc


@pytest.mark.parametrize("eo", [1, 3, 8, 11], ids=lambda e: f"EO{e}")
def test_known_sine_is_recovered(eo):
    d, amp, phase, dc = _sines(np.random.default_rng(eo), 7, 29, eo)
    f = fit_revolutions(d, PROBES, eo, omega_rad_s=np.full(7, 270.0))
    np.testing.assert_allclose(f.amp_pkpk_m[..., 0], amp, rtol=0, atol=1e-9)
    np.testing.assert_allclose(f.dc_m, dc, rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.angle(np.exp(1j * (f.phase_rad[..., 0] - phase))), 0.0, atol=1e-9)
    np.testing.assert_allclose(f.residual_rms_m, 0.0, atol=1e-12)
    np.testing.assert_allclose(f.freq_hz, eo * 270.0 / (2 * np.pi), rtol=1e-15)
    assert f.n_samples.min() == 5


def test_sine_at_probes_matches_the_fit_convention():
    d = sine_at_probes(PROBES, 8, 2.4e-3, 0.7, 1e-4)
    f = fit_revolutions(d[None, None], PROBES, 8)
    assert f.amp_pkpk_m[0, 0, 0] == pytest.approx(2.4e-3, abs=1e-15)
    assert f.phase_rad[0, 0, 0] == pytest.approx(0.7, abs=1e-12)
    a = f.coeffs[0, 0]
    assert a[1] == pytest.approx(1.2e-3 * np.cos(0.7)) and a[2] == pytest.approx(1.2e-3 * np.sin(0.7))


def test_two_engine_orders_with_five_probes():
    rng = np.random.default_rng(2)
    d8, a8, p8, dc = _sines(rng, 3, 4, 8)
    d3, a3, p3, _ = _sines(rng, 3, 4, 3)
    f = fit_revolutions(d8 + d3, PROBES, (8, 3))
    np.testing.assert_allclose(f.amp_pkpk_m[..., 0], a8, atol=1e-9)
    np.testing.assert_allclose(f.amp_pkpk_m[..., 1], a3, atol=1e-9)
    assert np.all(np.isnan(f.amp_std_m))  # 5 equations, 5 unknowns: no redundancy
    assert f.coeffs.shape == (3, 4, 5)


def test_missing_probes():
    d, amp, _, _ = _sines(np.random.default_rng(3), 4, 6, 8)
    d[0, 1, 2] = np.nan  # four probes left: still determined
    d[1, 2, [0, 1, 2]] = np.nan  # two left: undetermined
    f = fit_revolutions(d, PROBES, 8)
    assert f.amp_pkpk_m[0, 1, 0] == pytest.approx(amp[0, 1], abs=1e-12)
    assert f.n_samples[0, 1] == 4
    assert np.isnan(f.amp_pkpk_m[1, 2, 0]) and np.isnan(f.dc_m[1, 2])
    mask = np.ones(d.shape[:2], bool)
    mask[1, 2] = False
    np.testing.assert_allclose(f.amp_pkpk_m[..., 0][mask], amp[mask], atol=1e-12)


@pytest.mark.parametrize("window", [1, 2, 3, 5], ids=lambda w: f"w{w}")
def test_window_of_a_constant_response(window):
    d, amp, _, _ = _sines(np.random.default_rng(4), 1, 3, 8)
    d = np.repeat(d, 9, axis=0)
    d[4, 0, 3] = np.nan
    f = fit_revolutions(d, PROBES, 8, window=window)
    np.testing.assert_allclose(f.amp_pkpk_m[..., 0], np.repeat(amp, 9, axis=0), atol=1e-12)
    assert f.n_samples[4, 0] == 5 * window - 1  # the missing sample is in every window
    assert f.n_samples[0, 1] == 5 * (window // 2 + 1)  # truncated at the start


def test_window_stacks_samples():
    rng = np.random.default_rng(5)
    d = rng.standard_normal((5, 2, 5))
    f = fit_revolutions(d, PROBES, 8, window=3)
    B = np.tile(design_matrix(PROBES, 8), (3, 1))
    a, *_ = np.linalg.lstsq(B, d[1:4, 0].reshape(-1), rcond=None)
    np.testing.assert_allclose(f.coeffs[2, 0], a, atol=1e-12)
    rss = np.sum((d[1:4, 0].reshape(-1) - B @ a) ** 2)
    assert f.residual_rms_m[2, 0] == pytest.approx(np.sqrt(rss / 15), rel=1e-10)


def test_amplitude_uncertainty_matches_monte_carlo():
    rng = np.random.default_rng(6)
    n, sigma = 20000, 50e-6
    clean = sine_at_probes(PROBES, 8, 2e-3, 0.3)
    d = clean[None, None, :] + sigma * rng.standard_normal((n, 1, 5))
    f = fit_revolutions(d, PROBES, 8)
    B = design_matrix(PROBES, 8)
    cov = sigma ** 2 * np.linalg.inv(B.T @ B)
    a1, a2 = 1e-3 * np.cos(0.3), 1e-3 * np.sin(0.3)
    predicted = 2 * np.sqrt((a1 * a1 * cov[1, 1] + 2 * a1 * a2 * cov[1, 2] + a2 * a2 * cov[2, 2]) / 1e-6)
    assert np.std(f.amp_pkpk_m) == pytest.approx(predicted, rel=0.03)
    # the per-fit estimate (2 degrees of freedom) is right on average in variance
    assert np.mean(f.amp_std_m ** 2) == pytest.approx(predicted ** 2, rel=0.05)


def test_condition_number_in_the_fit():
    f = fit_revolutions(np.zeros((1, 1, 5)), PROBES, 8)
    assert f.cn == pytest.approx(1.4328125, abs=1e-6)
    with pytest.raises(ValueError):
        fit_revolutions(np.zeros((1, 1, 4)), PROBES, 8)


@pytest.mark.parametrize("window", [2, 3, 5])
@pytest.mark.parametrize("eos", [(8,), (8, 3)], ids=["EO8", "EO8+3"])
def test_window_fit_is_fit_revolutions_bit_for_bit(window, eos):
    """WindowFit (the streaming processor's windowed fits) gives revolution i of
    fit_revolutions over its centred window, every byte: full, truncated windows, missing,
    infinite and scarce samples."""
    from bttsim_stream.process.fit import WindowFit

    rng = np.random.default_rng(window * 10 + len(eos))
    d, _, _, _ = _sines(rng, 12, 29, eos[0])
    d[rng.random(d.shape) < 0.08] = np.nan
    d[3, 4, :3] = np.nan  # too few probes in the revolution
    d[5, 7] = np.nan  # a blade without samples
    d[6, :, 2] = np.nan  # a probe lost for a revolution
    d[8, 1, 0] = np.inf
    d[9] = np.nan
    wf = WindowFit(PROBES, eos, window)
    fields = ("coeffs", "amp_pkpk_m", "phase_rad", "amp_std_m", "dc_m", "residual_rms_m", "n_samples")
    for k in range(d.shape[0]):
        lo, hi = max(0, k - (window - 1) // 2), min(d.shape[0], k + window // 2 + 1)
        ref = fit_revolutions(d[lo:hi], PROBES, eos, window=window)
        got = wf(d[lo:hi])
        for name in fields:
            a, b = getattr(ref, name)[k - lo], getattr(got, name)[0]
            assert a.tobytes() == b.tobytes() and a.dtype == b.dtype, (k, name)
        assert got.cn == ref.cn

"""Data preparation (Sec. 2.3): smoother, offset removal, resonance location, switches."""

import warnings

import numpy as np
import pytest

import bttsim_stream.process.prep as prep
from bttsim_stream.process import (PrepOptions, fit_baseline, locate_resonance, prepare, remove_offset,
                                   smooth_revolutions, speed_adaptive_half_width)

PROBES = np.deg2rad([5.0, 15.15, 23.82, 220.0, 301.5])


def _brute_smooth(x, h, w):
    n = x.shape[0]
    H = int(np.ceil(np.max(h)))
    out = np.full_like(x, np.nan)
    for i in range(n):
        for c in range(x.shape[1]):
            if np.isnan(x[i, c]):
                continue
            js = np.arange(-H, H + 1)
            ii = i + js
            ok = (ii >= 0) & (ii < n)
            js, ii = js[ok], ii[ok]
            y = x[ii, c]
            v = ~np.isnan(y)
            u = np.abs(js) / (h[i] + 1)
            k = np.where(u < 1, (1 - u ** 3) ** 3, 0) * w[ii] * v
            A = np.stack([np.ones_like(js), js, js ** 2], 1).astype(float) * np.sqrt(k)[:, None]
            out[i, c] = np.linalg.lstsq(A, np.where(v, y, 0) * np.sqrt(k), rcond=None)[0][0]
    return out


@pytest.mark.parametrize("nan_fraction", [0.0, 0.05], ids=["complete", "missing"])
def test_smoother_is_a_local_quadratic_regression(nan_fraction):
    rng = np.random.default_rng(0)
    x = np.cumsum(rng.standard_normal((300, 6)), axis=0)
    x[rng.random(x.shape) < nan_fraction] = np.nan
    h = np.linspace(2, 7.5, 300)
    w = 1 / np.linspace(1, 2, 300) ** 2
    got = smooth_revolutions(x, h, w)
    np.testing.assert_allclose(got, _brute_smooth(x, h, w), rtol=0, atol=1e-10)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(x))


def test_smoother_keeps_quadratics_and_reduces_noise():
    n = np.arange(500.0)
    q = 1e-3 + 2e-6 * n - 3e-9 * n ** 2
    x = np.stack([q, q + 1e-4 * np.random.default_rng(1).standard_normal(500)], axis=1)
    x[100, 0] = np.nan
    s = smooth_revolutions(x, 10.0)
    np.testing.assert_allclose(np.delete(s[:, 0], 100), np.delete(q, 100), rtol=0, atol=1e-15)
    assert np.std(s[50:-50, 1] - q[50:-50]) < 0.5 * 1e-4


def test_speed_adaptive_half_width():
    om = np.array([100.0, 200.0, 400.0])
    np.testing.assert_allclose(speed_adaptive_half_width(om, 8.0, 200.0), [2.0, 8.0, 32.0])
    np.testing.assert_allclose(speed_adaptive_half_width(om, 8.0, 200.0, adaptive=False), 8.0)
    np.testing.assert_allclose(speed_adaptive_half_width(om, 8.0, 200.0, hi=20.0), [2.0, 8.0, 20.0])


def _resonance_run(n_rev=2000, peak=1200, width=60.0, seed=0, noise=0.0):
    """Displacements of an EO-8 SDOF-like resonance plus a per-probe quadratic baseline in speed."""
    rng = np.random.default_rng(seed)
    n = np.arange(n_rev)
    omega = np.linspace(100, 400, n_rev)
    x = (n - peak) / (width / 2)
    resp = 1.2e-3 / (1 + 1j * x)  # complex amplitude through the resonance (half-power full width)
    phase = np.angle(resp)[:, None, None] + 0.3 * np.arange(3)[None, :, None]
    d = np.abs(resp)[:, None, None] * np.sin(8 * PROBES[None, None, :] + phase)
    xs = (omega - 250) / 150
    base = (1e-4 + 5e-5 * xs + 8e-5 * xs ** 2)[:, None, None] * np.linspace(-1, 1, 5)[None, None, :]
    return d + base + noise * rng.standard_normal(d.shape), d, base, omega


def test_locate_resonance():
    d, _, _, omega = _resonance_run()
    region = locate_resonance(d, PROBES, 8)
    assert np.all(np.abs(region.peak_revolution - 1200) <= 2)
    np.testing.assert_allclose(region.half_power_width, 60, atol=4)
    assert np.all(region.significant)
    assert np.all(region.mask[1200]) and not np.any(region.mask[:500]) and not np.any(region.mask[-300:])


def test_offset_removal_keeps_the_resonance():
    d, clean, base, omega = _resonance_run()
    region = locate_resonance(d, PROBES, 8)
    out, offset = remove_offset(d, omega, region.mask, degree=2, robust=True)
    # the baseline is recovered, give or take the off-resonance forced response that a
    # polynomial in speed partly follows (a few % of the peak amplitude)
    assert np.max(np.abs(offset - base)) < 0.1 * 1.2e-3
    # the resonant amplitude is kept to 1 %: the bridged baseline's error is in
    # quadrature with the resonant response at the peak
    from bttsim_stream.process import fit_revolutions

    amp = fit_revolutions(out, PROBES, 8).amp_pkpk_m[..., 0]
    np.testing.assert_allclose(amp.max(axis=0), 2.4e-3, rtol=0.01)


def test_offset_fit_is_robust_to_outliers():
    d, clean, base, omega = _resonance_run(n_rev=1000, peak=10_000)
    d = np.broadcast_to(base, clean.shape).copy()
    d[::37, 1, 2] += 5e-3
    out, offset = remove_offset(d, omega, None, degree=2, robust=True)
    good = np.ones(1000, bool)
    good[::37] = False
    np.testing.assert_allclose(offset[good, 1, 2], base[good, 0, 2], atol=1e-9)


@pytest.mark.parametrize("clip", [False, True])
def test_baseline_rows_are_the_whole_offsets_rows(monkeypatch, clip):
    """A :class:`Baseline` gives, for any revolutions, the rows of the whole offset array (in
    small windows and column blocks too), and ``prepare(keep_offset=False)`` the same numbers."""
    d, clean, base, omega = _resonance_run()
    d = d.copy()
    d[1::53, 2, 1] = np.nan
    d[:, 2, 0] = np.nan  # a column without data
    region = locate_resonance(d, PROBES, 8)
    exclude = region.mask.copy()
    if clip:
        exclude[:300, ::2] = True  # fitted on part of the speeds: clipped, not extrapolated
    out, offset = remove_offset(d, omega, exclude)
    n = d.shape[0]
    rows_asked = (slice(0, 1), slice(17, 400), slice(n - 5, None), np.array([n - 1, 0, 700]), 5)
    b = fit_baseline(d, omega, exclude)
    assert (b.lo is not None) == clip
    assert np.array_equal(b.to_array(), offset, equal_nan=True)
    for rows in rows_asked:
        assert np.array_equal(b[rows], offset[rows], equal_nan=True)
    assert np.all(offset[:, 2, 0] == 0)
    # cut in small column blocks and row windows: a row's numbers do not depend on the rows asked
    # for (the fit itself may move in the last digit: the small products are not the whole's)
    monkeypatch.setattr(prep, "PREP_BLOCK", 4096)
    monkeypatch.setattr(prep, "GEMM_SMALL", 0)
    b = fit_baseline(d, omega, exclude)
    assert len(prep._row_windows(n, 15, 3)) > 1
    whole = b.to_array()
    np.testing.assert_allclose(whole, offset, rtol=1e-9, atol=1e-15)
    for rows in rows_asked:
        assert np.array_equal(b[rows], whole[rows], equal_nan=True)
    monkeypatch.undo()
    opts = PrepOptions()
    whole = prepare(d, omega, PROBES, 8, opts)
    lean = prepare(d, omega, PROBES, 8, opts, keep_offset=False)
    assert np.array_equal(whole.d_m, lean.d_m, equal_nan=True)
    assert np.array_equal(lean.offset_m[100:200], whole.offset_m[100:200], equal_nan=True)


def test_prepare_reduces_noise_and_keeps_the_peak():
    noisy, clean, _, omega = _resonance_run(noise=1e-4)
    prep = prepare(noisy, omega, PROBES, 8)
    err = prep.d_m - clean
    assert np.std(err[1000:1400]) < 0.6 * 1e-4
    from bttsim_stream.process import fit_revolutions

    amp = fit_revolutions(prep.d_m, PROBES, 8).amp_pkpk_m[..., 0]
    e_a = np.abs(amp.max(axis=0) / 2.4e-3 - 1)
    assert np.mean(e_a) < 0.02 and np.max(e_a) < 0.04
    assert np.all(np.isfinite(prep.half_width))


def test_prepare_switches_and_missing_data():
    d, _, _, omega = _resonance_run()
    d[5, 1, 2] = np.nan
    d[:, 2, 4] = np.nan
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        off = prepare(d, omega, PROBES, 8, PrepOptions(remove_offset=False, smooth=False))
        only_offset = prepare(d, omega, PROBES, 8, PrepOptions(smooth=False))
        both = prepare(d, omega, PROBES, 8)
    np.testing.assert_array_equal(off.d_m, d)
    assert np.all(off.offset_m == 0) and np.all(np.isnan(off.half_width))
    assert np.any(only_offset.offset_m != 0) and np.all(np.isnan(only_offset.half_width))
    np.testing.assert_array_equal(np.isnan(both.d_m), np.isnan(d))
    with pytest.raises(ValueError):
        PrepOptions(min_half_width=0)


@pytest.mark.parametrize("seed", range(4))
def test_median_then_mean_is_scipy_ndimage_bit_for_bit(seed):
    """The numpy smoother equals scipy.ndimage's running median then running mean, bit for bit:
    odd and even windows, ties, one and several columns, a window as long as the curve."""
    from scipy.ndimage import median_filter, uniform_filter1d

    from bttsim_stream.process.prep import median_then_mean

    rng = np.random.default_rng(seed)
    for _ in range(200):
        n = int(rng.integers(1, 400))
        size = int(rng.integers(1, min(n, 70) + 1))
        shape = (n,) if rng.random() < 0.5 else (n, int(rng.integers(1, 7)))
        x = rng.normal(size=shape) * 10 ** rng.uniform(-7, 3)
        if rng.random() < 0.3:
            x = np.round(x, 1)
        ref = uniform_filter1d(median_filter(x, size=(size,) + (1,) * (x.ndim - 1), mode="nearest"), size,
                               axis=0, mode="nearest")
        assert np.array_equal(median_then_mean(x, size), ref), (n, size, shape)

"""The peak of a resonance's quasi-steady shape fitted to the complex responses
(:func:`bttsim_stream.process.methods.resonance_fit`), against analytic truth."""

import numpy as np

from bttsim_stream.process.methods import resonance_fit

FN, ZETA, AMP = 344.0, 0.004, 2.3e-3  # Hz, -, pk-pk m (the default rotor's EO 8 crossing)


def _crossing(n_rev=400, phase=0.7):
    """A run-up's frequencies and the exact quasi-steady responses ``C h(f)`` (``2 |C| max |h| = AMP``)."""
    f = np.linspace(FN * 0.97, FN * 1.03, n_rev)
    r = f / FN
    h = 1.0 / (1.0 - r * r + 2j * ZETA * r)
    C = 0.5 * AMP * 2.0 * ZETA * np.sqrt(1.0 - ZETA ** 2) * np.exp(1j * phase)
    return f, C * h


def _fit(P, f):
    k = np.argmax(np.abs(P), axis=0)
    W = int(np.sum(np.abs(P[:, 0]) >= np.abs(P[:, 0]).max() / np.sqrt(2)))
    return resonance_fit(P, f, k, W, 0, P.shape[0] - 1, ZETA * 1.5)


def test_exact_response_and_constant_recovered():
    f, P = _crossing()
    P = P[:, None] + np.array([0.0, 3e-5 - 2e-5j])[None, :]  # the second blade: a zeroing leftover
    val, rev, fpk, ph, s_a, _ = _fit(P, f)
    assert np.allclose(val, AMP, rtol=1e-6)
    assert np.allclose(fpk, FN * np.sqrt(1 - 2 * ZETA ** 2), rtol=1e-7)
    assert np.all(np.abs(rev - np.argmin(np.abs(f - fpk[0]))) <= 1.0)


def test_uncertainty_calibrated_by_monte_carlo():
    f, P0 = _crossing()
    rng = np.random.default_rng(5)
    sigma = 15e-6  # per real component, m (amplitude, not pk-pk)
    n = 120
    noise = sigma * (rng.standard_normal((P0.size, n)) + 1j * rng.standard_normal((P0.size, n)))
    val, _, _, _, s_a, _ = _fit(P0[:, None] + noise, f)
    ok = np.isfinite(val)
    assert ok.mean() > 0.95
    err = val[ok] - AMP
    assert abs(err.mean()) < 3.0 * err.std() / np.sqrt(ok.sum())  # unbiased
    assert 0.8 < err.std() / np.median(s_a[ok]) < 1.25  # the reported std is the scatter


def test_static_probe_error_distortion_leaves_the_amplitude():
    """A fixed real-linear map ``P -> P + m2 conj(P)`` (a static probe position error) moves the
    largest magnitude by up to ``|m2| A``; the fitted shape's peak about half as much (``conj(h)``
    turns against ``h`` through the resonance)."""
    f, P = _crossing()
    m2 = 0.01 * np.exp(1j * np.linspace(0, 2 * np.pi, 8, endpoint=False))
    Pd = P[:, None] + m2[None, :] * np.conj(P)[:, None]
    top = 2.0 * np.abs(Pd).max(axis=0)
    val, *_ = _fit(Pd, f)
    assert np.max(np.abs(top - AMP)) > 0.5 * 0.01 * AMP
    assert np.max(np.abs(val - AMP)) < 0.6 * np.max(np.abs(top - AMP))

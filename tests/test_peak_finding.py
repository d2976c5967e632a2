"""``interior_peaks`` against ``scipy.signal.find_peaks(x, prominence=0.0)``: the same four
arrays, bit for bit and of the same dtype, on random curves of every kind the detector can meet
and on the awkward ones it should not (flat tops, NaN, inf, signed zeros, very short curves)."""

import warnings

import numpy as np
import pytest
from scipy.signal import find_peaks

from bttsim_stream.process.peak_finding import interior_peaks

pytestmark = pytest.mark.unit


def _assert_as_scipy(x: np.ndarray) -> None:
    with warnings.catch_warnings():  # scipy warns of a 0 prominence (none is ever found)
        warnings.simplefilter("ignore")
        peaks, props = find_peaks(x, prominence=0.0)
    got = interior_peaks(x)
    for name, want, have in (("peaks", peaks, got.index), ("prominences", props["prominences"], got.prominence),
                             ("left_bases", props["left_bases"], got.left_base),
                             ("right_bases", props["right_bases"], got.right_base)):
        assert have.dtype == want.dtype and have.shape == want.shape, (name, x)
        assert have.tobytes() == want.tobytes(), (name, x, want, have)  # bit for bit


def _noise(rng, n):
    return rng.normal(size=n)


def _moving_sum(v, width):
    return np.convolve(v, np.ones(width))[width // 2:width // 2 + v.size] if v.size else v


def _smoothed(rng, n):
    return _moving_sum(rng.normal(size=n), 7) / 7


def _rounded(rng, n):  # flat tops and flat valleys of every width, ties between peaks and bases
    return np.round(_moving_sum(rng.normal(size=n), 4))


def _steps(rng, n):  # a random walk of integers: long plateaus
    return np.cumsum(rng.integers(-1, 2, n)).astype(float)


def _with_nan(rng, n):
    x = np.round(rng.normal(size=n) * 2)
    x[rng.random(n) < 0.15] = np.nan
    return x


def _with_inf(rng, n):
    x = np.round(rng.normal(size=n))
    u = rng.random(n)
    x[u < 0.1] = np.inf
    x[(u >= 0.1) & (u < 0.2)] = -np.inf
    x[u > 0.95] = np.nan
    return x


def _signed_zeros(rng, n):
    x = rng.integers(0, 3, n).astype(float) - 1.0
    x[x == 0] = np.where(rng.random(int(np.count_nonzero(x == 0))) < 0.5, 0.0, -0.0)
    return x


def _resonance(rng, n):  # the detector's own case: a smoothed response over noise
    r = np.linspace(0.8, 1.2, n)
    return 1.0 / np.abs(1 - r * r + 0.02j * r) + 0.5 * _smoothed(rng, n)


KINDS = [_noise, _smoothed, _rounded, _steps, _with_nan, _with_inf, _signed_zeros, _resonance]


@pytest.mark.parametrize("kind", KINDS, ids=[k.__name__.strip("_") for k in KINDS])
def test_random_curves_give_what_scipy_gives(kind):
    rng = np.random.default_rng(20261206)
    for _ in range(400):
        _assert_as_scipy(kind(rng, int(rng.integers(0, 60))))
    for n in (257, 1024, 5000):  # several levels of the block table, long walks
        _assert_as_scipy(kind(rng, n))


@pytest.mark.parametrize("x", [[], [1.0], [1.0, 2.0], [0.0, 1.0, 0.0], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0],
                               [np.nan, 1.0, 0.0], [0.0, np.inf, 0.0], [0.0, np.nan, 0.0], [-np.inf, 0.0, -np.inf],
                               [5.0] * 7, [0.0, 1.0, 1.0, 0.0], [0.0, 1.0, 1.0, 1.0, 0.0], [0.0, 1.0, 1.0, 2.0]],
                         ids=lambda x: str(x))
def test_short_and_constant_curves(x):
    _assert_as_scipy(np.array(x, dtype=float))


def test_structured_curves():
    n = 4001
    i = np.arange(n, dtype=float)
    rising = i.copy()
    rising[::2] -= 1.5  # an increasing sawtooth: every walk reaches the start
    for x in (rising, rising[::-1].copy(), np.sin(i / 30.0), np.round(3 * np.sin(i / 30.0)), np.abs(np.sin(i / 7))):
        _assert_as_scipy(x)


def test_a_flat_top_gives_its_middle_rounded_down_and_the_nearest_lowest_bases():
    x = np.array([3.0, 0.0, 1.0, 0.0, 2.0, 2.0, 2.0, 2.0, 0.0, 1.0, 0.0, 3.0])
    pk = interior_peaks(x)
    np.testing.assert_array_equal(pk.index, [2, 5, 9])
    np.testing.assert_array_equal(pk.left_base, [1, 3, 8])  # 0.0 at 1 and 3: the nearer one
    np.testing.assert_array_equal(pk.right_base, [3, 8, 10])
    np.testing.assert_array_equal(pk.prominence, [1.0, 2.0, 1.0])


def test_two_dimensional_input_is_refused():
    with pytest.raises(ValueError, match="one-dimensional"):
        interior_peaks(np.zeros((3, 3)))

"""Per-revolution arrays held on spans of revolutions (``process.spans``): the whole array's
numbers on the held revolutions, NaN elsewhere, and refusals where the whole run's array
would be made."""

import numpy as np
import pytest

from bttsim_stream.process.intervals import blade_medians, no_crossing_note
from bttsim_stream.process.spans import SpanRows, angle, as_rows

pytestmark = pytest.mark.unit

SPANS = [(3, 9), (15, 16), (30, 41)]


def _pair(dtype=float):
    rng = np.random.default_rng(4)
    whole = rng.normal(size=(50, 6, 3))
    if dtype is complex:
        whole = whole + 1j * rng.normal(size=whole.shape)
    x = SpanRows.filled(50, SPANS, (6, 3), dtype)
    for a, b in SPANS:
        x[a:b] = whole[a:b]
    held = np.zeros(50, bool)
    for a, b in SPANS:
        held[a:b] = True
    masked = whole.copy()
    masked[~held] = np.nan
    return x, whole, masked, held


def _same(a, b) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and np.array_equal(a, b, equal_nan=True)


def test_indexing_gives_the_whole_arrays_numbers_on_the_held_revolutions_and_nan_elsewhere():
    x, whole, masked, held = _pair()
    assert x.shape == whole.shape and x.ndim == 3 and _same(x.held(), held)
    cols = np.arange(6)
    idx = np.array([[3, 4, 20, 40, 49, 0], [8, 15, 16, 30, 2, 5]])
    for key in (5, -10, 20, slice(None, 12), slice(28, 45), slice(2, 40, 3), (slice(4, 33), 2),
                (slice(0, 50), slice(1, 4), 1), (7, 3), (np.array([3, 20, 35]),),
                (np.array([3, 20, 35]), slice(None), 2),
                (idx, cols[None, :], 0), (np.clip(idx - 1, 0, 49), cols[None, :]), (held,), (36, 5, 2)):
        assert _same(x[key], masked[key]), key
    col = x[..., 1]  # every revolution: still held on the spans, a view
    assert isinstance(col, SpanRows) and col.shape == (50, 6) and _same(col[0:50], masked[..., 1])
    assert isinstance(x[:, 2], SpanRows) and _same(x[:, 2][31:33, 1], masked[31:33, 2, 1])
    assert float(col[:, 4][34]) == whole[34, 4, 1] and np.isnan(col[:, 4][12])


def test_arithmetic_acts_on_the_held_rows():
    x, whole, masked, _ = _pair()
    z = x[..., 0] + 1j * x[..., 1]
    assert _same(z[0:50], masked[..., 0] + 1j * masked[..., 1])
    for got, want in ((2.0 * np.abs(z), 2.0 * np.abs(masked[..., 0] + 1j * masked[..., 1])),
                      (angle(z), np.angle(masked[..., 0] + 1j * masked[..., 1])),
                      (x[..., 2] - np.ones((1, 6)), masked[..., 2] - 1.0), (-x / 2.0, -masked / 2.0)):
        assert _same(got[0:50], want)
    c = x.copy()
    c[4:6] += 1.0
    assert _same(c[4:6], whole[4:6] + 1.0) and _same(x[4:6], whole[4:6])  # the copy's own rows


def test_refusals():
    x, _, _, _ = _pair()
    with pytest.raises(TypeError):
        np.asarray(x)
    with pytest.raises(IndexError):
        x[8:11] = 0.0  # revolutions 9 and 10 are not held
    with pytest.raises(IndexError):
        x[50]
    assert as_rows(x) is x and isinstance(as_rows([1, 2]), np.ndarray)


def test_blade_medians_of_blocks_are_the_whole_runs():
    rng = np.random.default_rng(2)
    amp = rng.gamma(2.0, size=(1000, 7, 2))
    amp[rng.random(amp.shape) < 0.1] = np.nan
    amp[17] = np.nan
    whole = blade_medians(amp)
    blocks = np.concatenate([blade_medians(amp[a:a + 128]) for a in range(0, 1000, 128)])
    assert _same(whole, blocks)
    omega = np.linspace(200.0, 300.0, 1000)
    amp[400:600] *= np.linspace(1, 30, 200)[:, None, None]
    note = no_crossing_note(amp, omega, (3, 5), 4.0)
    assert note is not None and note == no_crossing_note(None, omega, (3, 5), 4.0, medians=blade_medians(amp))

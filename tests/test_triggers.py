"""The trigger levels shared by the signal chain and the views (:mod:`bttsim_stream.triggers`)."""

import numpy as np
import pytest

from bttsim_stream.triggers import BASELINE_SAMPLES, constant_fraction_level

pytestmark = pytest.mark.unit


def test_constant_fraction_level_of_a_known_pulse():
    """Baseline 0.1 V (the first four samples), top 2.1 V: half way is 1.1 V."""
    y = np.array([0.1, 0.1, 0.1, 0.1, 1.0, 2.1, 1.0, 0.1])
    assert BASELINE_SAMPLES == 4
    assert constant_fraction_level(y, 0.5) == pytest.approx(1.1, abs=1e-15)
    cols = np.stack([y, 2 * y], axis=1)  # one level per window (column)
    np.testing.assert_allclose(constant_fraction_level(cols, 0.5), [1.1, 2.2], rtol=0, atol=1e-15)


def test_the_signal_chain_uses_the_one_rule():
    from bttsim_stream.sim import signal

    assert signal.constant_fraction_level is constant_fraction_level

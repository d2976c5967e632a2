"""Trigger levels of the raw-signal TOA detection, shared by the signal chain and the views.

A leaf module (numpy only): the simulator's signal chain (:mod:`bttsim_stream.sim.signal`)
latches its constant-fraction TOAs at this level, and the raw signal view
(:mod:`bttsim_stream.views.signal`) draws it, without the views importing the simulator.
Volts in V; window arrays are ``(n_samples, ...)``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["BASELINE_SAMPLES", "constant_fraction_level"]

#: Samples averaged for the constant-fraction baseline.
BASELINE_SAMPLES = 4


def constant_fraction_level(y: np.ndarray, fraction: float) -> np.ndarray:
    """The constant-fraction trigger's level of each window, V.

    Parameters
    ----------
    y : ndarray, shape (n_samples, ...)
        Window samples, V.
    fraction : float
        The trigger's fraction ``f`` of the pulse height.

    Returns
    -------
    ndarray, shape (...)
        ``b + f (max - b)`` with ``b`` the mean of the window's first
        :data:`BASELINE_SAMPLES` samples (its baseline), V.
    """
    base = y[:BASELINE_SAMPLES].mean(axis=0)
    return base + fraction * (y.max(axis=0) - base)

"""The interpolation of speed-dependent modal quantities between tabulated speeds.

One owner for the contract of :mod:`bttsim_stream.model.speed_modes` (and of the model file's
``*_at_speed`` arrays, ``schemas/modal_model.md``): every quantity is a natural cubic spline
in ``s = Omega^2`` through the S samples, frequencies through ``omega^2 = (2 pi f)^2``. It is
a leaf module (numpy; scipy imported on first use) so that the views, which must not import
the model package, draw the Campbell curves exactly as the simulator integrates them.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from scipy.interpolate import CubicSpline

__all__ = ["speed_spline", "interpolate_freq_hz"]


def speed_spline(speed_rad_s: np.ndarray, values: np.ndarray) -> CubicSpline:
    """Natural cubic spline of ``values`` (S, ...) in ``Omega^2`` over ``speed_rad_s`` (S,)."""
    from scipy.interpolate import CubicSpline  # only for speed-dependent models

    s = np.square(np.asarray(speed_rad_s, float))
    return CubicSpline(s, np.asarray(values, float), axis=0, bc_type="natural", extrapolate=True)


def interpolate_freq_hz(speed_rad_s, freq_hz_at_speed, omega) -> np.ndarray:
    """Frequencies tabulated at speeds, interpolated as the modes are (see the module notes).

    Parameters
    ----------
    speed_rad_s : array_like, shape (S,)
        Sample speeds, rad/s, strictly ascending (S >= 2).
    freq_hz_at_speed : array_like, shape (S, ...)
        Frequencies at those speeds, Hz (e.g. a Campbell table (S, n_families, n_nd)).
    omega : array_like
        Speeds, rad/s, within ``[speed_rad_s[0], speed_rad_s[-1]]`` (not checked: outside,
        the spline's end polynomials extrapolate).

    Returns
    -------
    ndarray, shape ``omega.shape + freq_hz_at_speed.shape[1:]``
        Hz: ``sqrt`` of the natural cubic spline of ``(2 pi f)^2`` in ``Omega^2``.
    """
    w2 = (2.0 * np.pi * np.asarray(freq_hz_at_speed, float)) ** 2
    out = speed_spline(speed_rad_s, w2)(np.square(np.asarray(omega, float)))
    return np.sqrt(np.maximum(out, 0.0)) / (2.0 * np.pi)

"""Speed-dependent modes: interpolation of a model's modes between the speeds it stores.

A speed-dependent :class:`~bttsim_stream.model.modal_model.ModalModel` carries its modes at
speeds ``speed_rad_s`` (S,), ascending from 0 (``SPEED_ARRAYS``: ``freq_hz_at_speed``
(S, n_modes), ``tip_shapes_at_speed`` (S, n_modes, n_blades, n_tip, 3),
``force_shapes_at_speed`` (S, n_modes, n_blades, 3), optionally
``force_shapes_trailing_edge_at_speed``). Between them:

* every quantity -- ``omega_k^2 = (2 pi f_k)^2`` and every shape component -- is a natural
  cubic spline in ``s = Omega^2`` through the S samples (zero second derivative at both end
  samples). With S = 2 that is the straight line in ``Omega^2``: the Southwell form
  ``omega_k^2 = omega_k0^2 + kappa_k Omega^2`` (centrifugal stiffening minus spin softening is
  ``Omega^2`` times a constant matrix, ``K(Omega) = K_e + Omega^2 (K_g - K_s)``, so the
  eigenvalues are smooth in ``Omega^2`` and, to first order, linear in it);
* derivatives come from the same splines (``d/ds``; ``d/dt = 2 Omega alpha d/ds`` on a ramp);
* speeds above the last sample are refused (:func:`check_speed_range`): no extrapolation.

The damping ratio of each mode stays the model's ``damping_ratio`` at every speed.

Interpolating ``omega^2`` (not ``f``) keeps the Southwell form exact with two samples;
interpolating the shapes component-wise needs them aligned across speeds (same sign and
mode order, mass-normalised at each speed), which the model file promises. Nothing
re-normalises the interpolated shapes: between samples they are mass-normalised to the
interpolation error (second order in the sample spacing).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
from ..errors import BttsimError
from ..speed_spline import interpolate_freq_hz, speed_spline as _spline
from .modal_model import SPEED_ARRAYS, ModalModel

if TYPE_CHECKING:
    from scipy.interpolate import CubicSpline

__all__ = ["SpeedModes", "speed_modes", "is_speed_dependent", "check_speed_range", "models_at_speeds",
           "crossing_speeds", "interpolate_freq_hz",
           "southwell_model"]

RPM = 2.0 * np.pi / 60.0


def is_speed_dependent(model: ModalModel) -> bool:
    """Whether the model carries modes at several speeds (``SPEED_ARRAYS`` in ``extra``)."""
    return all(k in model.extra for k in SPEED_ARRAYS)


@dataclass(frozen=True, slots=True, eq=False)
class SpeedModes:
    """Natural cubic splines in ``s = Omega^2`` of a model's speed-dependent quantities.

    Attributes
    ----------
    speed_rad_s : ndarray, shape (S,)
        The model's sample speeds, rad/s (ascending from 0).
    omega2 : CubicSpline
        ``omega_k^2`` (rad^2/s^2) against ``s`` (rad^2/s^2), values of shape (n_modes,).
    """

    speed_rad_s: np.ndarray
    omega2: CubicSpline

    @property
    def max_speed_rad_s(self) -> float:
        return float(self.speed_rad_s[-1])

    def spline(self, values: np.ndarray) -> CubicSpline:
        """A natural cubic spline in ``s`` through ``values`` (S, ...) at the sample speeds."""
        return _spline(self.speed_rad_s, values)

    def freq_hz(self, omega) -> np.ndarray:
        """Natural frequencies (Hz) at speeds ``omega`` (rad/s): shape ``omega.shape + (n_modes,)``."""
        return np.sqrt(self.omega2(np.square(np.asarray(omega, float)))) / (2.0 * np.pi)


def speed_modes(model: ModalModel) -> SpeedModes | None:
    """The model's frequency spline (None for a model at zero speed only)."""
    if not is_speed_dependent(model):
        return None
    sp = np.asarray(model.extra["speed_rad_s"], float)
    w2 = (2.0 * np.pi * np.asarray(model.extra["freq_hz_at_speed"], float)) ** 2
    return SpeedModes(speed_rad_s=sp, omega2=_spline(sp, w2))


def check_speed_range(model: ModalModel, max_speed_rad_s: float, where: str = "[speed]") -> None:
    """Refuse a run faster than the model's last sample speed (one-line error).

    Raises
    ------
    BttsimError
    """
    if not is_speed_dependent(model):
        return
    top = float(model.extra["speed_rad_s"][-1])
    if max_speed_rad_s > top * (1.0 + 1e-12):
        raise BttsimError(
            f"{where}: the run reaches {max_speed_rad_s / RPM:.6g} rpm but the speed-dependent model's modes "
            f"stop at {top / RPM:.6g} rpm (speed_rad_s[-1] = {top:.6g} rad/s); give the model modes up to the "
            "run's top speed or slow the run down")


def models_at_speeds(model: ModalModel, omega) -> list[ModalModel]:
    """The modes frozen at each speed of ``omega`` (rad/s, interpolated) as zero-speed models
    (for estimates that take constant modes, e.g. the tip amplitude check)."""
    ex = model.extra
    sp = np.asarray(ex["speed_rad_s"], float)
    s = np.square(np.atleast_1d(np.asarray(omega, float)))
    keys = [k for k in ("tip_shapes_at_speed", "force_shapes_at_speed", "force_shapes_trailing_edge_at_speed")
            if k in ex]
    vals = {k: _spline(sp, ex[k])(s) for k in keys}
    w2 = _spline(sp, (2.0 * np.pi * np.asarray(ex["freq_hz_at_speed"], float)) ** 2)(s)
    base = {k: v for k, v in ex.items() if not (k.endswith("_at_speed") or k == "speed_rad_s")}
    out = []
    for i in range(s.size):
        extra = dict(base)
        if "force_shapes_trailing_edge_at_speed" in vals:
            extra["force_shapes_trailing_edge"] = vals["force_shapes_trailing_edge_at_speed"][i]
        out.append(replace(model, freq_hz=np.sqrt(w2[i]) / (2.0 * np.pi), tip_shapes=vals["tip_shapes_at_speed"][i],
                           force_shapes=vals["force_shapes_at_speed"][i], campbell_freq_hz=None, extra=extra))
    return out


def crossing_speeds(model: ModalModel, engine_orders, lo_rad_s: float, hi_rad_s: float) -> np.ndarray:
    """Speeds in ``[lo, hi]`` (rad/s) where an engine-order line ``EO Omega`` meets a mode's
    interpolated frequency ``w_k(Omega)`` (the Campbell diagram's crossings), ascending and
    rounded to 1e-3 rad/s (located on a 2001-point grid, then linearly)."""
    om = np.linspace(lo_rad_s, hi_rad_s, 2001)
    w = 2.0 * np.pi * speed_modes(model).freq_hz(om)  # (n, n_modes)
    out = []
    for eo in np.unique(np.asarray(engine_orders, float)):
        g = eo * om[:, None] - w
        i, k = np.nonzero(np.sign(g[:-1]) != np.sign(g[1:]))
        x = g[i, k] / (g[i, k] - g[i + 1, k])
        out.append(om[i] + x * (om[i + 1] - om[i]))
    return np.unique(np.round(np.concatenate(out + [np.zeros(0)]), 3))


def southwell_model(model: ModalModel, speed_rad_s, kappa, shape_change: float = 0.0) -> ModalModel:
    """A speed-dependent model from a zero-speed one, in the Southwell form (synthetic).

    ``omega_k(Omega)^2 = omega_k0^2 + kappa_k Omega^2`` at the sample speeds; the tip and force
    shapes change smoothly with ``s = Omega^2``: scaled by ``1 + shape_change * s / s_max``
    and their (radial, tangential, axial) components turned about the radial axis by
    ``shape_change * s / s_max`` rad (a blade twisting as it spins). For tests and
    benchmarks, until the FE model provides centrifugal effects itself; every sample is
    checked by :class:`ModalModel` (row 0 is the zero-speed model itself).

    Parameters
    ----------
    model : ModalModel
        Zero-speed model (its speed arrays, if any, are replaced).
    speed_rad_s : array_like, shape (S,)
        Sample speeds, rad/s, ascending from 0.
    kappa : float or array_like, shape (n_modes,)
        Southwell coefficients (dimensionless; about 1-2 for a blade's first flap mode).
    shape_change : float
        Relative shape change at the top sample.
    """
    sp = np.asarray(speed_rad_s, float)
    s = sp**2
    x = s / s[-1]
    w0 = 2.0 * np.pi * np.asarray(model.freq_hz, float)
    kap = np.broadcast_to(np.asarray(kappa, float), w0.shape)
    freq = np.sqrt(w0[None, :] ** 2 + kap[None, :] * s[:, None]) / (2.0 * np.pi)
    freq[0] = model.freq_hz

    def shapes(a: np.ndarray) -> np.ndarray:
        th = shape_change * x
        c, sn = np.cos(th), np.sin(th)
        out = np.repeat(a[None].astype(float), sp.size, axis=0)
        scale = (1.0 + shape_change * x).reshape((-1,) + (1,) * a.ndim)
        ut, uz = a[..., 1][None], a[..., 2][None]
        cc, ss = c.reshape((-1,) + (1,) * (a.ndim - 1)), sn.reshape((-1,) + (1,) * (a.ndim - 1))
        out[..., 1] = cc * ut - ss * uz
        out[..., 2] = ss * ut + cc * uz
        out *= scale
        out[0] = a
        return out

    extra = {k: v for k, v in model.extra.items() if not (k.endswith("_at_speed") or k == "speed_rad_s")}
    extra.update(speed_rad_s=sp, freq_hz_at_speed=freq, tip_shapes_at_speed=shapes(model.tip_shapes),
                 force_shapes_at_speed=shapes(model.force_shapes))
    if "force_shapes_trailing_edge" in model.extra:
        extra["force_shapes_trailing_edge_at_speed"] = shapes(model.extra["force_shapes_trailing_edge"])
    return replace(model, extra=extra)

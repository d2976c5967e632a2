"""Piecewise-linear rotor speed and its exact rotor angle (paper Eq. 6).

The speed is linear between knots, so the rotor angle is piecewise quadratic:
``phi(t) = phi_k + Omega_k s + alpha_k s^2 / 2`` with ``s = t - t_k``. The paper's linear
run-up (Table 1) is one segment: ``phi(t) = Omega_i t + (Omega_f - Omega_i) t^2 / (2 T_s)``.
Angles are in rad, anticlockwise, ``phi(0) = 0``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["SpeedProfile", "speed_profile_from_scenario"]

RPM = 2.0 * np.pi / 60.0


@dataclass(frozen=True, eq=False)
class SpeedProfile:
    """Speed knots; linear in between.

    Attributes
    ----------
    t_s : ndarray, shape (n_knots,)
        Knot times, s, strictly increasing from 0.
    omega : ndarray, shape (n_knots,)
        Speed at the knots, rad/s (> 0).
    """

    t_s: np.ndarray
    omega: np.ndarray

    def __post_init__(self) -> None:
        t = np.asarray(self.t_s, float)
        w = np.asarray(self.omega, float)
        if t.ndim != 1 or t.shape != w.shape or t.size < 2 or t[0] != 0.0 or np.any(np.diff(t) <= 0):
            raise ValueError("speed knots must be increasing from t = 0, with one speed per knot")
        if np.any(w <= 0) or not np.all(np.isfinite(w)):
            raise ValueError("speeds must be finite and > 0")
        alpha = np.diff(w) / np.diff(t)
        phi = np.concatenate(([0.0], np.cumsum(0.5 * (w[:-1] + w[1:]) * np.diff(t))))
        object.__setattr__(self, "t_s", t)
        object.__setattr__(self, "omega", w)
        object.__setattr__(self, "_alpha", np.append(alpha, 0.0))
        object.__setattr__(self, "_phi", phi)

    @property
    def duration_s(self) -> float:
        return float(self.t_s[-1])

    def rpm_range(self) -> tuple[float, float]:
        """Slowest and fastest speed of the profile, rpm."""
        rpm = self.omega / RPM
        return float(rpm.min()), float(rpm.max())

    @property
    def alpha(self) -> np.ndarray:
        """Angular acceleration of each segment, rad/s^2 (last entry 0: beyond the end)."""
        return self._alpha

    @property
    def phi_knots(self) -> np.ndarray:
        """Rotor angle at the knots, rad."""
        return self._phi

    def segment(self, t) -> np.ndarray:
        """Index of the segment holding each time (clipped to the profile)."""
        k = np.searchsorted(self.t_s, t, side="right") - 1
        return np.minimum(np.maximum(k, 0), self.t_s.size - 2)

    def state(self, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rotor angle (rad), speed (rad/s) and acceleration (rad/s^2) at times ``t``."""
        t = np.asarray(t, float)
        k = self.segment(t)
        s = t - self.t_s[k]
        a = self._alpha[k]
        w = self.omega[k]
        return self._phi[k] + s * (w + 0.5 * a * s), w + a * s, a

    def angle_change(self, t_ref, t, seg_ref=None) -> tuple[np.ndarray, np.ndarray]:
        """Rotor angle turned from ``t_ref`` to ``t`` (rad) and the speed at ``t`` (rad/s).

        Within the segment of ``t_ref`` the change is formed without the large rotor
        angles, ``(t - t_ref) (Omega_k + alpha_k (s_ref + s) / 2)`` (Eq. 6), so it keeps the
        relative precision of a small number; a time in another segment takes the difference
        of :meth:`state` (absolute precision of the rotor angle).

        Parameters
        ----------
        t_ref : ndarray
            Reference times, broadcastable against ``t``.
        t : ndarray
        seg_ref : ndarray of int, optional
            ``segment(t_ref)`` when already known.
        """
        t_ref = np.asarray(t_ref, float)
        t = np.asarray(t, float)
        k = self.segment(t_ref) if seg_ref is None else seg_ref
        t_k = self.t_s[k]
        a = self._alpha[k]
        s_ref = t_ref - t_k
        s = t - t_k
        d = (t - t_ref) * (self.omega[k] + 0.5 * a * (s_ref + s))
        om = self.omega[k] + a * s
        last = self.t_s.size - 2  # state() extends the first and last segments beyond the ends
        out = ((s < 0.0) & (k > 0)) | ((t >= self.t_s[k + 1]) & (k < last))
        if np.any(out):
            # another segment (a speed knot between t_ref and t): exact angles of both
            out = np.broadcast_to(out, d.shape)
            tb = np.broadcast_to(t, d.shape)[out]
            trb = np.broadcast_to(t_ref, d.shape)[out]
            phi_b, om_b, _ = self.state(tb)
            d = np.array(d, copy=True)
            om = np.array(np.broadcast_to(om, d.shape), copy=True)
            d[out] = phi_b - self.state(trb)[0]
            om[out] = om_b
        return d, om

    def angle(self, t) -> np.ndarray:
        return self.state(t)[0]

    def speed(self, t) -> np.ndarray:
        return self.state(t)[1]

    def time_at_angle(self, phi) -> np.ndarray:
        """Exact time at which the rotor angle reaches ``phi`` (inverse of :meth:`angle`)."""
        phi = np.asarray(phi, float)
        k = np.minimum(np.maximum(np.searchsorted(self._phi, phi, side="right") - 1, 0), self.t_s.size - 2)
        d = phi - self._phi[k]
        w = self.omega[k]
        a = self._alpha[k]
        # s = 2 d / (w + sqrt(w^2 + 2 a d)): no cancellation for a -> 0
        s = 2.0 * d / (w + np.sqrt(np.maximum(w * w + 2.0 * a * d, 0.0)))
        return self.t_s[k] + s


def speed_profile_from_scenario(scn, rng: np.random.Generator | None = None) -> SpeedProfile:
    """The scenario's speed profile, with its random speed fluctuation when enabled.

    The fluctuation (``[acquisition] speed_fluctuation_rpm``, a standard deviation) adds a
    Gaussian deviation at knots every 0.1 s, linear in between, so the profile stays
    piecewise linear and the integration stays exact.
    """
    t, rpm = scn.speed.breakpoints()
    sigma = scn.acquisition.speed_fluctuation_rpm
    if sigma > 0:
        if rng is None:
            rng = np.random.default_rng(np.random.SeedSequence([scn.run.seed, 0x5FEED]))
        tf = np.arange(0.0, t[-1], 0.1)
        tk = np.union1d(t, tf)
        base = np.interp(tk, t, rpm)
        dev = sigma * rng.standard_normal(tk.size)
        dev[0] = 0.0
        rpm_k = np.maximum(base + dev, 1e-3 * base)
        return SpeedProfile(tk, rpm_k * RPM)
    return SpeedProfile(np.asarray(t, float), np.asarray(rpm, float) * RPM)

"""``bttsim crb``: the Cramér-Rao lower bounds of a scenario's resonances, before running it.

For each engine order of the scenario's excitation, the crossing with the largest response in
the run's speed profile is predicted from the modal model's steady-state response at every
revolution's speed (the excitations of that order summed), and
:func:`~bttsim_stream.process.crb.resonance_bound` gives each blade's bound from:

* the layout: the probe angles and the orders the processing fits (jointly when it would,
  :func:`~bttsim_stream.process.options.fits_jointly`);
* the noise: a TOA standard deviation (the scenario's ``trigger_jitter_s`` and clock
  quantisation, or given), as a displacement ``Omega R sigma_t`` (Eq. 15);
* the revolutions used: those around the peak whose blade-mean predicted amplitude is at least
  a tenth of the peak (one crossing: a profile that comes back through the resonance crosses
  it again, apart); the SDOF parameters where the bound is evaluated: each blade's predicted
  peak amplitude, frequency and phase, and the damping of the half-power width (its
  frequencies, on a run-up or a run-down alike). A dwell, or a ramp that stops or turns at
  the resonance, crosses nothing: no bound.

Zero-speed modes (a speed-dependent model's crossings shift with its frequencies).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .process import crb
from .process.displacement import Geometry
from .process.options import fits_jointly
from .sim.core import load_scenario_model
from .sim.forcing import modal_forcing
from .sim.speed import speed_profile_from_scenario

__all__ = ["CrossingBound", "scenario_bounds", "bounds_table"]

TWO_PI = 2.0 * np.pi
#: revolutions whose predicted amplitude is at least this fraction of the peak are used
USED_LEVEL = 0.1


@dataclass(frozen=True, slots=True, eq=False)
class CrossingBound:
    """The bounds of one predicted crossing.

    Attributes
    ----------
    eo : int
    rpm, freq_hz, damping_ratio : float
        Speed and frequency of the blade-mean peak, half-power damping estimate.
    revolutions : tuple of int
        First and last revolution used (inclusive).
    toa_sigma_s, sigma_m : float
        TOA noise and the displacement noise at the peak (Eq. 15).
    joint : bool
        The orders are fitted jointly (the others' coefficients are nuisance parameters).
    amp_pkpk_m, crb_amp_m, crb_freq_hz : ndarray, shape (n_blades,)
        Predicted peak amplitude and the bounds (standard deviations).
    """

    eo: int
    rpm: float
    freq_hz: float
    damping_ratio: float
    revolutions: tuple
    toa_sigma_s: float
    sigma_m: float
    joint: bool
    amp_pkpk_m: np.ndarray
    crb_amp_m: np.ndarray
    crb_freq_hz: np.ndarray


def _revolution_speeds(scn) -> np.ndarray:
    """Mean speed of every whole revolution of the run, rad/s."""
    speed = speed_profile_from_scenario(scn)
    th0 = np.deg2rad(scn.probes.opr_angle_deg)
    n = int(np.floor((float(speed.angle(speed.duration_s)) - th0) / TWO_PI))
    if n < 3:
        raise ValueError(f"the run has {max(n, 0)} whole revolutions: too few for a crossing")
    t = speed.time_at_angle(th0 + TWO_PI * np.arange(n + 1))
    return TWO_PI / np.diff(t)


def _steady_response(model, C: np.ndarray, f_hz: np.ndarray, v_eqv: np.ndarray) -> np.ndarray:
    """Steady-state complex ``d_eqv`` envelope per blade and revolution, (n_blades, n_rev):
    ``sum_k v_eqv[k, b] C_k / (w_k^2 - W^2 + 2 i zeta_k w_k W)``, ``W = 2 pi f``."""
    w = TWO_PI * np.asarray(model.freq_hz, float)[:, None]
    W = TWO_PI * f_hz[None, :]
    H = C[:, None] / (w * w - W * W + 2j * np.asarray(model.damping_ratio, float)[:, None] * w * W)
    return v_eqv.T @ H


def _around(mask: np.ndarray, k: int) -> tuple[int, int]:
    """First and last index of the run of True in ``mask`` that holds ``k`` (one crossing: a
    profile that returns through the resonance crosses it again, apart)."""
    out = np.flatnonzero(~mask)
    before, after = out[out < k], out[out > k]
    return (int(before[-1]) + 1 if before.size else 0), (int(after[0]) - 1 if after.size else mask.size - 1)


def scenario_bounds(scn, toa_sigma_s: float | None = None, model=None) -> list[CrossingBound]:
    """The bounds of the scenario's predicted crossings, one per engine order with a peak
    inside the speed range (see the module docstring).

    Raises
    ------
    ValueError
        A layout that cannot separate the orders, or a run too short.
    """
    m = load_scenario_model(scn) if model is None else model
    omega = _revolution_speeds(scn)
    p = m.nominal_node
    stagger = np.deg2rad(float(m.meta["stagger_deg"]))
    shapes = m.tip_shapes[:, :, p, :]  # (n_modes, nb, 3): radial, tangential, axial
    v_eqv = shapes[..., 1] + shapes[..., 2] / np.tan(stagger)  # Eq. 3-4
    radius = float(np.mean(m.tip_ref[:, p, 0]))
    angles = np.deg2rad(np.asarray(scn.probes.angles_deg, float))
    C, eo_of = modal_forcing(m, scn.excitation)
    eos = tuple(int(e) for e in np.unique(eo_of))
    geo = Geometry(probe_angles_rad=angles, n_blades=m.n_blades, tip_radius_m=radius,
                   opr_angle_rad=np.deg2rad(scn.probes.opr_angle_deg))
    joint = fits_jointly(eos, geo)
    sig_t = (crb.toa_sigma(scn.acquisition.trigger_jitter_s, scn.acquisition.clock_hz) if toa_sigma_s is None
             else float(toa_sigma_s))
    blade_angle = m.tip_ref[:, p, 1]
    out = []
    for eo in eos:
        f = eo * omega / TWO_PI
        G = _steady_response(m, C[:, eo_of == eo].sum(axis=1), f, v_eqv)  # (nb, n_rev)
        amp = 2.0 * np.abs(G)
        mean = amp.mean(axis=0)
        k = int(np.argmax(mean))
        if k in (0, mean.size - 1) or not mean[k] > 0:
            continue  # no peak inside the run
        h0, h1 = _around(mean >= mean[k] / np.sqrt(2.0), k)  # this crossing's half-power band
        band = float(np.ptp(f[h0:h1 + 1]))  # its frequencies, run-up or run-down alike
        tol = 1e-6 * f[k]
        if not (abs(f[h0] - f[k]) > tol and abs(f[h1] - f[k]) > tol and (f[h0] - f[k]) * (f[h1] - f[k]) < 0):
            continue  # not crossed: a dwell at the resonance, or a ramp that stops or turns on it
        zeta = max(band / (2.0 * f[k]), 1e-4)
        lo, hi = _around(mean >= USED_LEVEL * mean[k], k)
        kb = lo + np.argmax(amp[:, lo:hi + 1], axis=1)
        cols = np.arange(m.n_blades)
        P = G[cols, kb] * np.exp(-1j * eo * blade_angle)
        sig = crb.displacement_sigma(omega[lo:hi + 1], radius, sig_t)
        fit_eos = eos if joint else (eo,)
        b = crb.resonance_bound(angles, fit_eos, fit_eos.index(eo), f[lo:hi + 1], sig, amp[cols, kb], f[kb], zeta,
                                np.angle(P))
        out.append(CrossingBound(eo=eo, rpm=float(omega[k] * 60.0 / TWO_PI), freq_hz=float(f[k]), damping_ratio=zeta,
                                 revolutions=(lo, hi), toa_sigma_s=sig_t, sigma_m=float(sig[k - lo]), joint=joint,
                                 amp_pkpk_m=amp[cols, kb], crb_amp_m=b.amp_pkpk_m, crb_freq_hz=b.freq_hz))
    return out


def _span(x: np.ndarray) -> str:
    """``min-max`` of the finite values (``nan``: none)."""
    x = np.asarray(x, float)[np.isfinite(x)]
    return f"{x.min():.4g}-{x.max():.4g}" if x.size else "nan"


def bounds_table(bounds: list[CrossingBound]) -> str:
    """The printed table: one line per crossing, the bounds' range over the blades."""
    head = (f"{'EO':>3}  {'rpm':>7}  {'freq Hz':>8}  {'zeta':>7}  {'revolutions':>11}  {'sigma_t ns':>10}  "
            f"{'sigma_d um':>10}  {'amp mm':>7}  {'CRB amp um':>17}  {'CRB freq mHz':>17}")
    lines = [head]
    for b in bounds:
        a, fq = 1e6 * b.crb_amp_m, 1e3 * b.crb_freq_hz
        lines.append(f"{b.eo:>3}  {b.rpm:>7.1f}  {b.freq_hz:>8.3f}  {b.damping_ratio:>7.5f}  "
                     f"{f'{b.revolutions[0]}-{b.revolutions[1]}':>11}  {1e9 * b.toa_sigma_s:>10.3f}  "
                     f"{1e6 * b.sigma_m:>10.4f}  {1e3 * float(np.mean(b.amp_pkpk_m)):>7.4f}  "
                     f"{_span(a):>17}  {_span(fq):>17}")
    if not bounds:
        lines.append("no crossing: no engine order's predicted response peaks inside the speed range")
    return "\n".join(lines)

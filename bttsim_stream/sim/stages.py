"""Acquisition stages: from the exact motion to what the acquisition system records.

Two kinds of parts:

- the TOA method of stage A (paper Sec. 2.2): :class:`HpToa` (converged root) or
  :class:`GridToa` (AD, Eq. 12, or PAD, Eq. 13-14, on an integrator time grid), chosen by
  :func:`toa_method`;
- the acquisition stages applied, in :data:`ACQUISITION_STAGES` order, to every batch of
  exact TOAs (:class:`Acquired`): the signal chain (``[acquisition.signal]``), trigger and OPR
  jitter, and the TOA clock. Each has ``from_scenario(scn, speed, sensing_radius_m)`` (None
  when the scenario does not ask for it) and ``apply(acq, passages)``.

Every random stage draws from its own ``SeedSequence([seed, i])`` stream (``i`` = 1 trigger
jitter, 2 OPR jitter, 3 and 4 the signal chain; 0 is the probe angle error), so that a stage
switched on or off does not change what the others draw.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Protocol

import numpy as np

from .signal import (Digitiser, LowFrequencyNoise, ProbeModel, PulseParameters, RawSignals, Trigger, apply_triggers,
                     centrifugal_growth_m, pulse_parameters, synthesise)
from .toa import eval_local, grid_crossings

__all__ = ["HpToa", "GridToa", "toa_method", "Acquired", "Passages", "AcquisitionStage", "SignalChain",
           "TriggerJitter", "OprJitter", "Clock", "ACQUISITION_STAGES", "acquisition_stages", "stream"]


def stream(seed: int, i: int) -> np.random.Generator:
    """The random stream ``i`` of a run (see the module notes)."""
    return np.random.default_rng(np.random.SeedSequence([seed, i]))


class HpToa:
    """HP: the converged Newton root of the crossing (Eq. 8), as it is."""

    def refine(self, lm, speed, target_rel, rad, t_det, u):
        """The crossing times ``t_det`` (q, n) and displacements ``u`` (q, 3, n) unchanged."""
        return t_det, u


class GridToa:
    """AD (Eq. 12) or PAD (Eq. 13-14): the crossing interpolated on an integrator time grid of
    step ``step_s`` (:func:`~bttsim_stream.sim.toa.grid_crossings`)."""

    def __init__(self, method: str, step_s: float) -> None:
        self.method, self.step_s = method, step_s

    def refine(self, lm, speed, target_rel, rad, t_det, u):
        """Crossing times from the grid, and the displacements there."""
        t_det = grid_crossings(lm, speed, target_rel, rad, t_det, self.step_s, self.method)
        u, _, _, _ = eval_local(lm, speed, t_det, derivative=False)
        return t_det, u


def toa_method(toa) -> HpToa | GridToa:
    """The scenario's ``[toa]`` method as a part."""
    if toa.method in ("AD", "PAD"):
        return GridToa(toa.method, toa.grid_step_s)
    return HpToa()


@dataclass(slots=True, eq=False)
class Acquired:
    """One batch's acquisition data, as the stages build it up (fields of
    :class:`~bttsim_stream.sim.core.RevolutionBatch`; arrays (n_rev, n_blades, n_probes)).

    ``from_signal``: the TOAs come from the signal chain (a missing pulse is NaN there).
    """

    toa_s: np.ndarray
    opr_s: np.ndarray
    toa_ticks: np.ndarray | None = None
    opr_ticks: np.ndarray | None = None
    n_edges: np.ndarray | None = None
    clearance_m: np.ndarray | None = None
    signal: RawSignals | None = None
    extra_passage: np.ndarray | None = None
    extra_toa_s: np.ndarray | None = None
    extra_toa_ticks: np.ndarray | None = None
    from_signal: bool = False


@dataclass(frozen=True, slots=True, eq=False)
class Passages:
    """The batch's passages, flattened in (revolution, blade, probe) order.

    Attributes
    ----------
    toa_s : ndarray, shape (n,)
        Exact TOAs, s.
    blade : ndarray of int, shape (n,)
    radial_m : callable
        ``radial_m()``: radial displacement of P_nom at the TOAs, m, shape (n,) (computed when
        a stage asks).
    """

    toa_s: np.ndarray
    blade: np.ndarray
    radial_m: Callable[[], np.ndarray]


class AcquisitionStage(Protocol):
    """What the simulator asks of an acquisition stage."""

    def apply(self, acq: Acquired, passages: Passages) -> None:
        """Change ``acq`` in place."""


class TriggerJitter:
    """Gaussian timing jitter of every TOA (``[acquisition] trigger_jitter_s``, s rms)."""

    def __init__(self, std_s: float, seed: int) -> None:
        self.std_s, self.rng = std_s, stream(seed, 1)

    @classmethod
    def from_scenario(cls, scn, speed, sensing_radius_m) -> TriggerJitter | None:
        s = scn.acquisition.trigger_jitter_s
        return cls(s, scn.run.seed) if s > 0 else None

    def apply(self, acq: Acquired, passages: Passages) -> None:
        acq.toa_s += self.std_s * self.rng.standard_normal(acq.toa_s.shape)


class OprJitter:
    """Gaussian timing jitter of every OPR pulse (``[acquisition] opr_jitter_s``, s rms)."""

    def __init__(self, std_s: float, seed: int) -> None:
        self.std_s, self.rng = std_s, stream(seed, 2)

    @classmethod
    def from_scenario(cls, scn, speed, sensing_radius_m) -> OprJitter | None:
        s = scn.acquisition.opr_jitter_s
        return cls(s, scn.run.seed) if s > 0 else None

    def apply(self, acq: Acquired, passages: Passages) -> None:
        acq.opr_s += self.std_s * self.rng.standard_normal(acq.opr_s.shape)


class Clock:
    """The TOA counter (``[acquisition] clock_hz``): times latched on the tick before them;
    a missing pulse of the signal chain is tick -1 and TOA NaN."""

    def __init__(self, clock_hz: float) -> None:
        self.clock_hz = clock_hz

    @classmethod
    def from_scenario(cls, scn, speed, sensing_radius_m) -> Clock | None:
        hz = scn.acquisition.clock_hz
        return cls(hz) if hz > 0 else None

    def apply(self, acq: Acquired, passages: Passages) -> None:
        hz, toa = self.clock_hz, acq.toa_s
        if not acq.from_signal:
            acq.toa_ticks = np.floor(toa * hz).astype(np.int64)
        else:  # the counter latches the trigger; no pulse: tick -1 and TOA NaN
            found = np.isfinite(toa)
            acq.toa_ticks = np.where(found, np.floor(np.where(found, toa, 0.0) * hz), -1).astype(np.int64)
        acq.opr_ticks = np.floor(acq.opr_s * hz).astype(np.int64)
        if acq.from_signal:
            acq.extra_toa_ticks = np.floor(acq.extra_toa_s * hz).astype(np.int64)
            acq.extra_toa_s = acq.extra_toa_ticks / hz
        acq.toa_s = acq.toa_ticks / hz
        if acq.from_signal:
            acq.toa_s[acq.toa_ticks < 0] = np.nan
        acq.opr_s = acq.opr_ticks / hz


class SignalChain:
    """The scenario's ``[acquisition.signal]``: exact passages in, triggered TOAs out.

    Random streams of their own (``SeedSequence([seed, 3])`` for the white noise,
    ``[seed, 4]`` for the low-frequency noise), so the other acquisition errors draw what
    they drew before; the white noise is drawn passage by passage, so the TOAs do not
    depend on how revolutions are batched.
    """

    def __init__(self, scn, n_probes: int, radius_m: float, speed=None, sensing_radius_m=None) -> None:
        sig, seed = scn.acquisition.signal, scn.run.seed
        self.sig = sig
        self.n_probes = n_probes
        self.speed = speed
        self.sensing_radius_m = sensing_radius_m

        def per_probe(v):
            return (v,) * n_probes if isinstance(v, str) else tuple(v)

        self.probes = [ProbeModel(kind=k,
                                  diameter_m=sig.spot_diameter_m if k == "optical" else sig.electrode_diameter_m,
                                  tip_thickness_m=sig.tip_thickness_m,
                                  reference_clearance_m=sig.reference_clearance_m,
                                  height_v=sig.height_v, fringe_factor=sig.fringe_factor,
                                  bandwidth_hz=sig.bandwidth_hz) for k in per_probe(sig.probe_type)]
        self.triggers = [Trigger(kind=k, level_v=sig.level_v, hysteresis_v=sig.hysteresis_v, edge=sig.edge,
                                 fraction=sig.fraction) for k in per_probe(sig.trigger)]
        self.dig = Digitiser(sample_rate_hz=sig.sample_rate_hz, bits=sig.bits, range_lo_v=sig.range_lo_v,
                             range_hi_v=sig.range_hi_v, noise_v=sig.noise_v, lf_noise_v=sig.lf_noise_v,
                             lf_corner_hz=sig.lf_corner_hz, offset_v=sig.offset_v,
                             offset_drift_v_per_s=sig.offset_drift_v_per_s, gain_drift_per_s=sig.gain_drift_per_s)
        self.rng = np.random.default_rng(np.random.SeedSequence([seed, 3]))
        self.lf = (LowFrequencyNoise(sig.lf_noise_v, sig.lf_corner_hz, n_probes,
                                     np.random.default_rng(np.random.SeedSequence([seed, 4])))
                   if sig.lf_noise_v > 0 else None)
        self.radius_m = radius_m
        self.tau_s = np.array([p.tau_s for p in self.probes])

    @classmethod
    def from_scenario(cls, scn, speed, sensing_radius_m) -> SignalChain | None:
        if not scn.acquisition.signal.enabled:
            return None
        return cls(scn, len(scn.probes.angles_deg), float(np.mean(sensing_radius_m)), speed, sensing_radius_m)

    def apply(self, acq: Acquired, passages: Passages) -> None:
        """The TOAs latched by the triggers replace the exact ones (NaN: no pulse)."""
        toa, blade = passages.toa_s, passages.blade
        probe = np.tile(np.arange(self.n_probes), toa.size // self.n_probes)
        out = self(toa, blade, probe, passages.radial_m(), self.speed.speed(toa), self.sensing_radius_m[blade])
        shape = acq.toa_s.shape
        acq.toa_s = out[0].reshape(shape)
        acq.n_edges, acq.clearance_m = out[1].reshape(shape), out[2].reshape(shape)
        acq.signal, acq.extra_passage, acq.extra_toa_s = out[3], out[4], out[5]
        acq.from_signal = True

    def __call__(self, toa, blade, probe, d_rad_m, omega, radius_m):
        """Triggered TOAs, edge counts and clearances of passages (all shape (n,)), their
        :class:`RawSignals` when the scenario publishes them (else None), and the later edges
        of double pulses (passage, time)."""
        sig = self.sig
        growth = centrifugal_growth_m(omega, self.radius_m, sig.density_kg_m3, sig.youngs_modulus_pa)
        clearance = sig.clearance_m - growth - d_rad_m
        speed = omega * (radius_m + growth + d_rad_m)
        height = np.empty(toa.size)
        half = np.empty(toa.size)
        scale = np.empty(toa.size)
        for j, pm in enumerate(self.probes):
            cols = probe == j
            pp = pulse_parameters(pm, clearance[cols], speed[cols])
            height[cols], half[cols], scale[cols] = pp.height_v, pp.half_width_s, pp.scale_s
        win = synthesise(toa, PulseParameters(height, half, scale), self.tau_s[probe], probe, self.dig, self.rng,
                         self.lf)
        out = apply_triggers(win, self.triggers, probe)
        raw = None
        if sig.publish:
            raw = RawSignals(win.first_sample, win.n_samples, win.codes, win.sample_rate_hz, self.dig.range_lo_v,
                             self.dig.lsb_v, self.dig.bits, tuple(t.kind for t in self.triggers), sig.level_v,
                             sig.hysteresis_v, sig.edge, sig.fraction)
        return out.toa_s, out.n_edges, clearance, raw, out.extra_passage, out.extra_toa_s


#: The acquisition stages in the order they act on a batch.
ACQUISITION_STAGES = (SignalChain, TriggerJitter, OprJitter, Clock)


def acquisition_stages(scn, speed, sensing_radius_m: np.ndarray) -> list:
    """The stages of :data:`ACQUISITION_STAGES` that the scenario asks for.

    Parameters
    ----------
    speed : SpeedProfile
    sensing_radius_m : ndarray, shape (n_blades,)
        Radius of each blade's P_nom, m.
    """
    found = (kind.from_scenario(scn, speed, sensing_radius_m) for kind in ACQUISITION_STAGES)
    return [s for s in found if s is not None]

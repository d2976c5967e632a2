"""The acquisition chain as hardware has it: probe pulses, digitisation, triggers -> TOAs.

A real BTT system never sees a crossing time: it sees a probe signal as each blade tip
passes, digitised by an ADC, and a trigger turns the samples into a time of arrival. This
module synthesises that signal around every exact passage (the simulator's TOA) and runs
the trigger on it, so that the published TOA carries the errors of the chain (trigger level
against a pulse whose height and width change with tip clearance and speed, noise on the
slope, sampling, quantisation, missing and double pulses).

Conventions
-----------
A *passage* is one (revolution, blade, probe) event; arrays of passages are 1-D, in the
simulator's row-major ``(revolution, blade, probe)`` order. Sample arrays are
``(sample, passage)``: the loops of the filters run over the (short) window, vectorised over
passages. Times in s, lengths in m, speeds in m/s, signals in V.

Probe pulse (before the front end)
----------------------------------
The tip is a strip of thickness ``T`` (its tangential width at the probe's axial station)
centred on the sensing point, moving past the probe at the passage speed ``v``; the probe
senses it through a spatial kernel. We take the kernel as a hyperbolic-secant-squared
(logistic) profile of scale ``s`` -- the same variance as a Gaussian of standard deviation
``sigma = s pi / sqrt(3)``, but with a closed-form integral, so that the noise-free pulse is

    p(x) = H [S((x + T/2) / s) - S((x - T/2) / s)],   S(u) = 1 / (1 + exp(-u)),

with ``x = v (t - t_toa)`` the position of the sensing point past the probe (the exact TOA
is the centre of the pulse). Its peak is ``H tanh(T / (4 s))``.

* **optical** (reflective, collimated beam): ``s = (D_spot / 4) sqrt(3) / pi`` (``D_spot``:
  1/e^2 spot diameter, ``sigma = D_spot / 4``); ``H = height_v`` independent of clearance.
* **capacitive**: the field of an electrode of diameter ``D_e`` spreads with the gap ``g``:
  ``sigma(g) = sqrt((D_e / 4)^2 + (kappa g)^2)`` (``kappa``: fringe factor) and the
  capacitance change, hence the pulse height, falls as ``1 / g``:
  ``H(g) = height_v g_ref / g`` (``g_ref``: the reference clearance, where ``H = height_v``). Both the
  height and the width of the pulse depend on the clearance; a pulse whose peak
  ``H(g) tanh(T / (4 s(g)))`` drops below the trigger level goes missing
  (:func:`missing_clearance_m`).

Tip clearance ``g = g_0 - Delta R(Omega) - u_rad``: the cold clearance minus the static
centrifugal growth of the rotor (:func:`centrifugal_growth_m`) and the modal radial
displacement of the sensing point at the passage.

Front end and digitiser
-----------------------
* Bandwidth: a first-order low-pass of time constant ``tau_f = 1 / (2 pi f_bw)`` (probe and
  amplifier), integrated exactly for a signal linear between samples (:func:`lowpass`). It
  delays the pulse by about ``tau_f`` and lowers it when the pulse is short (high speed).
* Gain and offset: ``v(t) = offset_v + offset_drift_v_per_s t + (1 + gain_drift_per_s t)
  p_f(t) + n(t) + n_lf(t)``.
* White noise ``n``: the front end's noise band-limited by the same low-pass, i.e. an
  Ornstein-Uhlenbeck process of rms ``noise_v`` sampled exactly:
  ``n_k = rho n_{k-1} + sqrt(1 - rho^2) noise_v e_k``, ``rho = exp(-dt / tau_f)``.
* Low-frequency noise ``n_lf``: a sum of ``K`` sinusoids with log-uniform frequencies in
  ``[lf_corner_hz / 1000, lf_corner_hz]`` and random phases (a 1/f-like spectrum), rms
  ``lf_noise_v``, a function of absolute time (constant over one window).
* ADC: sample instants on the absolute grid ``t_k = k / f_s``; ``bits`` over the input range
  ``[range_lo_v, range_hi_v]`` (code ``round((v - lo) / q)`` clipped, ``q = (hi - lo) /
  (2^bits - 1)``).

Signals exist only in a window around each passage, ``[t_toa - (T/2 + 9 s) / v,
t_toa + (T/2 + 9 s) / v + 7 tau_f]`` (the pulse is below 1e-4 of its height outside), so the
cost is proportional to passages, not to run time. Spurious triggers on pure noise between
windows are not simulated (Rice's rate ``f exp(-L^2 / 2 sigma^2)`` is negligible for a level
many ``noise_v`` above the baseline).

Triggers (:func:`apply_triggers`)
---------------------------------
* ``threshold``: a Schmitt trigger -- fires when the signal rises through ``level_v`` after
  having been at or below ``level_v - hysteresis_v`` (``falling`` edge: falls through
  ``level_v`` after having been at or above ``level_v + hysteresis_v``); the crossing is
  interpolated linearly between the two samples. The gate of a blade's window latches the
  *first* edge; further edges (noise re-crossing the level) are counted as a double pulse.
* ``constant_fraction``: the first sample reaching ``baseline + f (max - baseline)`` on the
  rising edge (baseline: mean of the window's first 4 samples), interpolated linearly:
  independent of the pulse height and of a slow offset.
* ``peak``: the pulse maximum, refined by the vertex of the parabola through the largest
  sample and its neighbours (the zero crossing of the interpolated derivative).

``constant_fraction`` and ``peak`` are armed only by a maximum at or above ``level_v``. No
edge, or no arming: a missing pulse (NaN TOA). Interpolation error of a linear threshold
crossing, for a noise-free signal ``y`` with crossing at ``t_c``:
``|dt| <= dt_s^2 |y''(t_c)| / (8 |y'(t_c)|)`` (:func:`interpolation_error_bound_s`); with
noise of rms ``sigma`` and adjacent-sample correlation ``rho`` the timing jitter is
``sigma_t = sigma / |y'(t_c)| sqrt((2 + rho) / 3)`` (:func:`trigger_jitter_s`, averaged over
the crossing's uniformly distributed position between samples).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..triggers import constant_fraction_level  # one constant-fraction rule: the views draw it too

__all__ = ["PROBE_KINDS", "TRIGGER_KINDS", "EDGES", "ProbeModel", "Digitiser", "Trigger", "PulseParameters",
           "SignalWindows", "TriggerResult", "RawSignals", "centrifugal_growth_m", "pulse_parameters", "pulse_shape",
           "edge_crossing_s", "missing_clearance_m", "lowpass", "synthesise", "apply_triggers",
           "interpolation_error_bound_s", "trigger_jitter_s", "LowFrequencyNoise", "constant_fraction_level",
           "latch_s"]

PROBE_KINDS = ("optical", "capacitive")
TRIGGER_KINDS = ("threshold", "constant_fraction", "peak")
EDGES = ("rising", "falling")
#: Logistic scale per Gaussian standard deviation (equal variances).
_LOGISTIC_PER_SIGMA = math.sqrt(3.0) / math.pi
#: Window half-extent beyond the tip strip, in logistic scales (pulse < 1e-4 of its height).
_WINDOW_SCALES = 9.0
#: Window extension after the pulse, in filter time constants (exp(-7) ~ 1e-3 of the tail).
_WINDOW_TAUS = 7.0
#: Samples averaged for the constant-fraction baseline.
#: Smallest clearance the capacitive model takes (a rubbing tip), m.
MIN_CLEARANCE_M = 1e-6


@dataclass(frozen=True, slots=True, eq=False)
class ProbeModel:
    """One probe's sensing model.

    Attributes
    ----------
    kind : {"optical", "capacitive"}
    diameter_m : float
        Optical: 1/e^2 spot diameter; capacitive: electrode diameter, m.
    tip_thickness_m : float
        Tangential width ``T`` of the blade tip at the probe's axial station, m.
    reference_clearance_m : float
        Clearance ``g_ref`` at which the capacitive pulse height scale is ``height_v``, m.
    height_v : float
        Pulse height scale ``H``, V.
    fringe_factor : float
        Capacitive field spreading ``kappa`` (kernel width grows as ``kappa g``).
    bandwidth_hz : float
        Front-end bandwidth (-3 dB of the first-order low-pass), Hz; 0: unlimited.
    """

    kind: str
    diameter_m: float
    tip_thickness_m: float
    reference_clearance_m: float
    height_v: float
    fringe_factor: float = 0.5
    bandwidth_hz: float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in PROBE_KINDS:
            raise ValueError(f"probe kind must be one of {PROBE_KINDS}, got {self.kind!r}")

    @property
    def tau_s(self) -> float:
        """Low-pass time constant ``1 / (2 pi f_bw)``, s (0: no filter)."""
        return 1.0 / (2.0 * math.pi * self.bandwidth_hz) if self.bandwidth_hz > 0 else 0.0


@dataclass(frozen=True, slots=True, eq=False)
class Digitiser:
    """Front-end noise, drifts and the ADC.

    Attributes
    ----------
    sample_rate_hz : float
    bits : int
    range_lo_v, range_hi_v : float
        ADC input range, V.
    noise_v : float
        rms of the band-limited white noise at the ADC input, V.
    lf_noise_v : float
        rms of the low-frequency noise, V.
    lf_corner_hz : float
        Highest frequency of the low-frequency noise, Hz.
    offset_v, offset_drift_v_per_s : float
        Baseline offset and its linear drift with run time.
    gain_drift_per_s : float
        Relative gain drift per second of run time.
    """

    sample_rate_hz: float
    bits: int = 12
    range_lo_v: float = -0.5
    range_hi_v: float = 1.5
    noise_v: float = 0.0
    lf_noise_v: float = 0.0
    lf_corner_hz: float = 10.0
    offset_v: float = 0.0
    offset_drift_v_per_s: float = 0.0
    gain_drift_per_s: float = 0.0

    @property
    def dt_s(self) -> float:
        return 1.0 / self.sample_rate_hz

    @property
    def lsb_v(self) -> float:
        """Quantisation step ``q``, V."""
        return (self.range_hi_v - self.range_lo_v) / (2 ** self.bits - 1)


@dataclass(frozen=True, slots=True, eq=False)
class Trigger:
    """A probe's trigger.

    Attributes
    ----------
    kind : {"threshold", "constant_fraction", "peak"}
    level_v : float
        Threshold (``threshold``) or arming level (the others), V.
    hysteresis_v : float
        Re-arming distance below (rising) or above (falling) the level, V.
    edge : {"rising", "falling"}
    fraction : float
        Constant fraction ``f`` in (0, 1).
    """

    kind: str
    level_v: float
    hysteresis_v: float = 0.0
    edge: str = "rising"
    fraction: float = 0.5

    def __post_init__(self) -> None:
        if self.kind not in TRIGGER_KINDS:
            raise ValueError(f"trigger kind must be one of {TRIGGER_KINDS}, got {self.kind!r}")
        if self.edge not in EDGES:
            raise ValueError(f"edge must be one of {EDGES}, got {self.edge!r}")


@dataclass(frozen=True, slots=True, eq=False)
class PulseParameters:
    """Per-passage pulse in time (all shape (n,)).

    Attributes
    ----------
    height_v : ndarray
        ``H``, V.
    half_width_s : ndarray
        ``T / (2 v)``, s.
    scale_s : ndarray
        Logistic scale ``s / v``, s.
    """

    height_v: np.ndarray
    half_width_s: np.ndarray
    scale_s: np.ndarray


@dataclass(frozen=True, slots=True, eq=False)
class SignalWindows:
    """Digitised windows around passages.

    Attributes
    ----------
    first_sample : ndarray of int64, shape (n,)
        Index ``k`` (``t_k = k / f_s``) of each window's first sample.
    n_samples : ndarray of int64, shape (n,)
        Samples in each window (rows beyond it repeat the last sample).
    volts : ndarray, shape (n_max, n)
        Quantised signal, V.
    codes : ndarray of int32, shape (n_max, n)
        ADC codes.
    sample_rate_hz : float
    """

    first_sample: np.ndarray
    n_samples: np.ndarray
    volts: np.ndarray
    codes: np.ndarray
    sample_rate_hz: float


@dataclass(frozen=True, slots=True, eq=False)
class RawSignals:
    """The digitiser's windows of a batch of passages, as a raw-signal channel carries them.

    Passages in the simulator's row-major ``(revolution, blade, probe)`` order; window ``i``
    holds samples ``k = first_sample[i] .. first_sample[i] + n_samples[i] - 1`` at
    ``t_k = k / sample_rate_hz`` with volts ``range_lo_v + code * lsb_v``.

    Attributes
    ----------
    first_sample, n_samples : ndarray of int64, shape (n,)
    codes : ndarray of int32, shape (n_max, n)
        ADC codes (rows beyond a window repeat its last sample).
    sample_rate_hz, range_lo_v, lsb_v : float
    bits : int
    trigger : tuple of str, one per probe
    level_v, hysteresis_v : float
        Trigger (or arming) level and threshold hysteresis, V.
    edge : str
    fraction : float
        Constant fraction.
    """

    first_sample: np.ndarray
    n_samples: np.ndarray
    codes: np.ndarray
    sample_rate_hz: float
    range_lo_v: float
    lsb_v: float
    bits: int
    trigger: tuple
    level_v: float
    hysteresis_v: float
    edge: str
    fraction: float = 0.5

    def __post_init__(self) -> None:
        n = self.first_sample.shape[0]
        if self.n_samples.shape != (n,) or self.codes.ndim != 2 or self.codes.shape[1] != n:
            raise ValueError(f"RawSignals: first_sample {self.first_sample.shape}, n_samples "
                             f"{self.n_samples.shape}, codes {self.codes.shape} do not agree")

    @staticmethod
    def concatenate(parts) -> "RawSignals":
        """Join batches along the passage axis (shorter windows padded by their last sample)."""
        parts = list(parts)
        n_max = max(p.codes.shape[0] for p in parts)
        codes = np.concatenate([np.pad(p.codes, ((0, n_max - p.codes.shape[0]), (0, 0)), mode="edge")
                                for p in parts], axis=1)
        p0 = parts[0]
        return RawSignals(np.concatenate([p.first_sample for p in parts]),
                          np.concatenate([p.n_samples for p in parts]), codes, p0.sample_rate_hz,
                          p0.range_lo_v, p0.lsb_v, p0.bits, p0.trigger, p0.level_v, p0.hysteresis_v, p0.edge,
                          p0.fraction)


@dataclass(frozen=True, slots=True, eq=False)
class TriggerResult:
    """Trigger output per passage (shape (n,)).

    Attributes
    ----------
    toa_s : ndarray
        Interpolated TOA, s (not yet latched on the counter clock); NaN: missing pulse.
    n_edges : ndarray of int64
        Edges in the window (threshold trigger; 0 or 1 for the others): 0 missing, > 1 double.
    extra_passage : ndarray of int64, shape (m,)
        Passage of each edge after its window's first (``m = sum(max(n_edges - 1, 0))``), in
        passage then time order.
    extra_toa_s : ndarray, shape (m,)
        Interpolated time of each such edge, s (not latched).
    """

    toa_s: np.ndarray
    n_edges: np.ndarray
    extra_passage: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    extra_toa_s: np.ndarray = field(default_factory=lambda: np.zeros(0))


def centrifugal_growth_m(omega_rad_s, radius_m: float, density_kg_m3: float, youngs_modulus_pa: float):
    """Static radial growth of the tip under centrifugal load, m.

    ``Delta R = rho Omega^2 R^3 / (3 E)``: the elongation of a uniform bar spinning about one
    end from the axis to the tip radius (stress ``rho Omega^2 (R^2 - r^2) / 2``, integrated);
    a solid disk's rim grows by ``(1 - nu) rho Omega^2 R^3 / (4 E)``, about half, so this is
    the upper end of a disk-plus-blade estimate. Titanium (4430 kg/m^3, 114 GPa) at 0.19 m:
    1.0 um at 1000 rpm, 16 um at 4000 rpm.
    """
    w = np.asarray(omega_rad_s, dtype=float)
    return density_kg_m3 * w * w * radius_m ** 3 / (3.0 * youngs_modulus_pa)


def pulse_parameters(probe: ProbeModel, clearance_m, speed_m_s) -> PulseParameters:
    """Height, half-width and edge scale of each passage's pulse (see the module notes).

    Parameters
    ----------
    probe : ProbeModel
    clearance_m, speed_m_s : array_like, shape (n,)
        Tip clearance (m) and passage speed (m/s) of each passage.
    """
    v = np.asarray(speed_m_s, dtype=float)
    g = np.maximum(np.asarray(clearance_m, dtype=float), MIN_CLEARANCE_M)
    if probe.kind == "optical":
        s_x = np.full_like(g, probe.diameter_m / 4.0 * _LOGISTIC_PER_SIGMA)
        height = np.full_like(g, probe.height_v)
    else:
        s_x = np.hypot(probe.diameter_m / 4.0, probe.fringe_factor * g) * _LOGISTIC_PER_SIGMA
        height = probe.height_v * probe.reference_clearance_m / g
    return PulseParameters(height_v=height, half_width_s=0.5 * probe.tip_thickness_m / v, scale_s=s_x / v)


def pulse_shape(tau_s, half_width_s, scale_s):
    """Unit-height pulse ``S((tau + h) / s) - S((tau - h) / s)`` before the front end.

    ``tau = t - t_toa``, s; broadcasts. ``S(u) = (1 + tanh(u / 2)) / 2``."""
    a = np.tanh(0.5 * (tau_s + half_width_s) / scale_s)
    b = np.tanh(0.5 * (tau_s - half_width_s) / scale_s)
    return 0.5 * (a - b)


def edge_crossing_s(level_fraction, half_width_s, scale_s, edge: str = "rising"):
    """Where the unfiltered pulse crosses ``level_fraction`` of ``H``, relative to the TOA, s.

    With ``u = exp(-tau / s)`` and ``A = exp(h / s)``, ``p = u (A - 1/A) / (1 + u (A + 1/A) + u^2)``;
    ``p = c`` is the quadratic ``c u^2 + (c (A + 1/A) - (A - 1/A)) u + c = 0`` whose larger root
    is the rising edge (``tau < 0``), the smaller the falling one. NaN where ``c`` is at or
    above the peak ``tanh(h / (2 s))``.
    """
    c = np.asarray(level_fraction, dtype=float)
    r = np.asarray(half_width_s, dtype=float) / np.asarray(scale_s, dtype=float)
    ch, sh = 2.0 * np.cosh(r), 2.0 * np.sinh(r)
    b = c * ch - sh
    disc = b * b - 4.0 * c * c
    with np.errstate(invalid="ignore", divide="ignore"):
        sq = np.sqrt(disc)
        u = (-b + sq) / (2.0 * c) if edge == "rising" else 2.0 * c / (-b + sq)
        tau = -np.log(u) * scale_s
    return np.where(disc > 0, tau, np.nan)


def missing_clearance_m(probe: ProbeModel, level_v: float) -> float:
    """The clearance beyond which a capacitive pulse's peak ``H(g) tanh(T / (4 s(g)))`` is
    below ``level_v`` (unfiltered pulse; the speed does not enter), m; inf for an optical
    probe whose peak reaches the level, 0 if it never does."""
    def peak(g):
        p = pulse_parameters(probe, np.array([g]), np.array([1.0]))
        return float(p.height_v[0] * np.tanh(0.5 * p.half_width_s[0] / p.scale_s[0]))
    if probe.kind == "optical":
        return math.inf if peak(1.0) >= level_v else 0.0
    lo, hi = MIN_CLEARANCE_M, 1.0
    if peak(lo) < level_v:
        return 0.0
    for _ in range(200):  # the peak falls monotonically with g: bisection
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if peak(mid) >= level_v else (lo, mid)
    return 0.5 * (lo + hi)


def lowpass(x: np.ndarray, dt_s: float, tau_s: float, y0=None) -> np.ndarray:
    """First-order low-pass ``tau y' + y = x`` along axis 0, exact for ``x`` linear between samples.

    ``y_k = a y_{k-1} + (1 - a) x_{k-1} + (x_k - x_{k-1}) (1 - tau (1 - a) / dt)``,
    ``a = exp(-dt / tau)``; ``y_0 = x_0`` (a window starts at rest) unless ``y0`` is given.
    ``tau_s = 0`` returns ``x``.

    Parameters
    ----------
    x : ndarray, shape (n_samples, ...)
    """
    if tau_s <= 0:
        return x
    a = math.exp(-dt_s / tau_s)
    c = 1.0 - tau_s * (1.0 - a) / dt_s
    y = np.empty_like(x)
    y[0] = x[0] if y0 is None else y0
    # forcing of each step, then the recursion y_k = a y_{k-1} + u_k in place
    np.multiply(x[:-1], 1.0 - a - c, out=y[1:])
    y[1:] += c * x[1:]
    for k in range(1, x.shape[0]):
        y[k] += a * y[k - 1]
    return y


class LowFrequencyNoise:
    """Low-frequency noise of each probe: ``sum_k A sqrt(2 / K) cos(2 pi f_k t + phi_k)``.

    Parameters
    ----------
    rms_v : float
    corner_hz : float
        ``f_k`` log-uniform in ``[corner_hz / 1000, corner_hz]``.
    n_probes : int
    rng : numpy.random.Generator
    n_terms : int
    """

    def __init__(self, rms_v: float, corner_hz: float, n_probes: int, rng: np.random.Generator,
                 n_terms: int = 16) -> None:
        self.amp = rms_v * math.sqrt(2.0 / n_terms)
        self.freq_hz = corner_hz * 10.0 ** rng.uniform(-3.0, 0.0, (n_probes, n_terms))
        self.phase = rng.uniform(0.0, 2.0 * math.pi, (n_probes, n_terms))

    def __call__(self, t_s: np.ndarray, probe: np.ndarray) -> np.ndarray:
        """Noise at times ``t_s`` of probes ``probe`` (both shape (n,)), V."""
        if self.amp == 0.0:
            return np.zeros(np.shape(t_s))
        arg = 2.0 * math.pi * self.freq_hz[probe] * np.asarray(t_s)[:, None] + self.phase[probe]
        return self.amp * np.cos(arg).sum(axis=1)


def window_samples(pulse: PulseParameters, tau_f_s, sample_rate_hz: float):
    """First sample index offset and sample count of each passage's window.

    Returns ``(lead_s, n_samples)``: the window starts ``lead_s`` before the TOA and spans
    ``lead_s + (h + 9 s) + 7 tau_f`` (the pulse's reach after the filter)."""
    lead = pulse.half_width_s + _WINDOW_SCALES * pulse.scale_s
    span = 2.0 * lead + _WINDOW_TAUS * np.asarray(tau_f_s, dtype=float)
    return lead, np.ceil(span * sample_rate_hz).astype(np.int64) + 2


def synthesise(toa_s, pulse: PulseParameters, tau_f_s, probe: np.ndarray, dig: Digitiser,
               rng: np.random.Generator, lf_noise: LowFrequencyNoise | None = None) -> SignalWindows:
    """Digitised probe signal in a window around each passage.

    Parameters
    ----------
    toa_s : ndarray, shape (n,)
        Exact TOAs (the pulse centres), s.
    pulse : PulseParameters
        Each passage's pulse (:func:`pulse_parameters`).
    tau_f_s : ndarray, shape (n,)
        Front-end time constant of each passage's probe, s (0: no filter).
    probe : ndarray of int, shape (n,)
        Probe index of each passage (low-frequency noise).
    dig : Digitiser
    rng : numpy.random.Generator
        Draws ``sum(n_samples)`` normals in passage order, window by window, so the result
        does not depend on how passages are batched.
    lf_noise : LowFrequencyNoise, optional

    Notes
    -----
    The filters run over the windows' samples (axis 0), vectorised over passages; passages
    with different time constants are filtered in one pass per distinct constant.
    """
    toa = np.asarray(toa_s, dtype=float)
    n = toa.size
    fs, dt = dig.sample_rate_hz, dig.dt_s
    tau_f = np.broadcast_to(np.asarray(tau_f_s, dtype=float), (n,))
    lead, n_samp = window_samples(pulse, tau_f, fs)
    first = np.floor((toa - lead) * fs).astype(np.int64)
    n_max = int(n_samp.max()) if n else 0
    k = np.arange(n_max, dtype=float)[:, None]
    # tau = t_k - toa from the sample index relative to toa * fs (no cancellation of large times)
    v = k + (first - toa * fs)[None, :]
    v *= dt
    v = pulse_shape(v, pulse.half_width_s, pulse.scale_s)
    v *= pulse.height_v
    for tf in np.unique(tau_f):
        if tf > 0:
            cols = slice(None) if tf == tau_f[0] and np.all(tau_f == tf) else np.flatnonzero(tau_f == tf)
            v[:, cols] = lowpass(v[:, cols], dt, float(tf))
    t0 = first / fs
    if dig.gain_drift_per_s:
        v *= 1.0 + dig.gain_drift_per_s * t0
    v += dig.offset_v + dig.offset_drift_v_per_s * t0
    if lf_noise is not None:
        v += lf_noise(t0, probe)
    if dig.noise_v > 0:
        # draws in passage order (window by window), then the Ornstein-Uhlenbeck recursion;
        # samples beyond a window get no new noise (they are replaced below)
        valid_pm = np.arange(n_max)[None, :] < n_samp[:, None]  # (n, n_max)
        e = np.zeros((n, n_max))
        e[valid_pm] = rng.standard_normal(int(n_samp.sum()))
        e = np.ascontiguousarray(e.T)
        e *= dig.noise_v
        for tf in np.unique(tau_f):
            rho = math.exp(-dt / tf) if tf > 0 else 0.0
            w = math.sqrt(1.0 - rho * rho)
            cols = slice(None) if np.all(tau_f == tf) else np.flatnonzero(tau_f == tf)
            ec = e[:, cols] if isinstance(cols, slice) else e[:, cols].copy()
            ec[1:] *= w
            for i in range(1, n_max):
                ec[i] += rho * ec[i - 1]
            if not isinstance(cols, slice):
                e[:, cols] = ec
        v += e
    q = dig.lsb_v
    v -= dig.range_lo_v
    v *= 1.0 / q
    v += 0.5
    np.floor(v, out=v)
    np.clip(v, 0, 2 ** dig.bits - 1, out=v)
    codes = v.astype(np.int32)
    # rows beyond a window repeat its last sample (what a trigger sees is the window only)
    cols = np.arange(n)
    codes = np.where(k < n_samp[None, :], codes, codes[n_samp - 1, cols][None, :])
    volts = dig.range_lo_v + codes * q
    return SignalWindows(first_sample=first, n_samples=n_samp, volts=volts, codes=codes, sample_rate_hz=fs)


def _interp_time(y, k1, level, t_first, dt):
    """Linear crossing of ``level`` between samples ``k1 - 1`` and ``k1`` of each column."""
    cols = np.arange(y.shape[1])
    k0 = np.maximum(k1 - 1, 0)
    y0, y1 = y[k0, cols], y[k1, cols]
    with np.errstate(invalid="ignore", divide="ignore"):
        frac = np.where(y1 != y0, (level - y0) / (y1 - y0), 0.0)
    return t_first + (k0 + np.clip(frac, 0.0, 1.0)) * dt


def _threshold(y, level, hysteresis, t_first, dt):
    """Schmitt trigger on rising ``y`` (columns are passages): (toa, n_edges, extra_column,
    extra_toa) -- the first edge of each column, the edge counts, and every later edge's
    column and interpolated time."""
    n_max, n = y.shape
    dec = np.where(y >= level, 1, np.where(y <= level - hysteresis, 0, -1)).astype(np.int8)
    idx = np.where(dec >= 0, np.arange(n_max)[:, None], -1)
    last = np.maximum.accumulate(idx, axis=0)
    state = np.where(last >= 0, np.take_along_axis(dec, np.maximum(last, 0), axis=0), 0) > 0
    edges = state.copy()
    edges[1:] &= ~state[:-1]
    edges[0] = False  # a window starts on the baseline: an edge needs the sample before it
    n_edges = edges.sum(axis=0).astype(np.int64)
    k1 = np.argmax(edges, axis=0)
    toa = _interp_time(y, k1, level, t_first, dt)
    # the edges after the first (double pulses): column, sample, time, in column then time order
    col, k = np.nonzero(edges.T)
    later = k > k1[col]
    col, k = col[later], k[later]
    y0, y1 = y[k - 1, col], y[k, col]
    with np.errstate(invalid="ignore", divide="ignore"):
        frac = np.where(y1 != y0, (level - y0) / (y1 - y0), 0.0)
    extra = t_first[col] + (k - 1 + np.clip(frac, 0.0, 1.0)) * dt
    return np.where(n_edges > 0, toa, np.nan), n_edges, col.astype(np.int64), extra


def _constant_fraction(y, level, fraction, t_first, dt):
    top = y.max(axis=0)
    cfd = constant_fraction_level(y, fraction)
    k1 = np.argmax(y >= cfd, axis=0)
    toa = _interp_time(y, k1, cfd, t_first, dt)
    armed = top >= level
    return np.where(armed, toa, np.nan), armed.astype(np.int64)


def _peak(y, level, t_first, dt):
    n_max = y.shape[0]
    cols = np.arange(y.shape[1])
    km = np.argmax(y, axis=0)
    top = y[km, cols]
    kc = np.clip(km, 1, n_max - 2)
    ym, y0, yp = y[kc - 1, cols], y[kc, cols], y[kc + 1, cols]
    den = ym - 2.0 * y0 + yp
    with np.errstate(invalid="ignore", divide="ignore"):
        delta = np.where(den < 0, 0.5 * (ym - yp) / den, 0.0)
    toa = t_first + (kc + np.clip(delta, -1.0, 1.0)) * dt
    armed = top >= level
    return np.where(armed, toa, np.nan), armed.astype(np.int64)


def apply_triggers(win: SignalWindows, triggers, probe: np.ndarray) -> TriggerResult:
    """Run each passage's probe trigger on its window.

    Parameters
    ----------
    win : SignalWindows
    triggers : sequence of Trigger
        One per probe.
    probe : ndarray of int, shape (n,)
        Probe index of each passage.
    """
    n = win.first_sample.size
    toa = np.full(n, np.nan)
    n_edges = np.zeros(n, dtype=np.int64)
    extra_p, extra_t = [], []
    dt = 1.0 / win.sample_rate_hz
    t_first = win.first_sample / win.sample_rate_hz
    for j, trig in enumerate(triggers):
        cols = np.flatnonzero(probe == j)
        if cols.size == 0:
            continue
        y = win.volts[:, cols]
        tf = t_first[cols]
        if trig.kind == "threshold":
            sign = 1.0 if trig.edge == "rising" else -1.0
            t, e, xc, xt = _threshold(sign * y, sign * trig.level_v, trig.hysteresis_v, tf, dt)
            extra_p.append(cols[xc])
            extra_t.append(xt)
        elif trig.kind == "constant_fraction":
            t, e = _constant_fraction(y, trig.level_v, trig.fraction, tf, dt)
        else:
            t, e = _peak(y, trig.level_v, tf, dt)
        toa[cols], n_edges[cols] = t, e
    ep = np.concatenate(extra_p) if extra_p else np.zeros(0, np.int64)
    et = np.concatenate(extra_t) if extra_t else np.zeros(0)
    order = np.lexsort((et, ep))
    return TriggerResult(toa_s=toa, n_edges=n_edges, extra_passage=ep[order], extra_toa_s=et[order])


def latch_s(t_s, clock_hz: float):
    """Times as the counter latches them, s: ``floor(t f_c) / f_c`` (the tick of the
    ``clock_hz`` counter at or before ``t``); NaN (no pulse) stays NaN.

    The simulator's acquisition (``RunUpSimulator``) latches its TOAs this way."""
    t = np.asarray(t_s, dtype=float)
    return np.floor(t * clock_hz) / clock_hz


def interpolation_error_bound_s(slope_v_s, curvature_v_s2, dt_s):
    """Largest error of a linear threshold crossing between samples ``dt_s`` apart, s:
    ``dt^2 |y''| / (8 |y'|)`` (the chord of ``y`` misses the curve by at most
    ``dt^2 |y''| / 8`` between the samples)."""
    return dt_s * dt_s * np.abs(curvature_v_s2) / (8.0 * np.abs(slope_v_s))


def trigger_jitter_s(noise_v, slope_v_s, rho: float = 1.0):
    """Timing jitter of a linearly interpolated crossing, s: ``sigma / |y'| sqrt((2 + rho) / 3)``.

    The interpolated noise at fraction ``x`` between samples is ``(1 - x) n_0 + x n_1``,
    variance ``sigma^2 ((1 - x)^2 + x^2 + 2 rho x (1 - x))``; its mean over ``x`` uniform in
    [0, 1] is ``sigma^2 (2 + rho) / 3``. ``rho = 1`` (noise much slower than the sampling)
    gives the textbook ``sigma / |y'|``."""
    return np.asarray(noise_v) / np.abs(slope_v_s) * math.sqrt((2.0 + rho) / 3.0)

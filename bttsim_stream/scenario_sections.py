"""The scenario's sections: one frozen dataclass per TOML table, and the checks within each.

Each field is declared once with :func:`~bttsim_stream.fieldspec.spec` (kind, unit, bounds,
default, comment); its check, its comment in the printed file, the ``Attributes`` of the
section's docstring and its row in ``schemas/scenario.md`` all come from that declaration.
Checks across the fields of one section are the small named functions here; the checks that
span sections, the file reading and writing are in :mod:`bttsim_stream.scenario`, which
re-exports every public name of this module (import them from there).
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from .defaults import DEFAULT_RIG, MAX_BLADES, MAX_ENGINE_ORDER, MAX_PROBES, MAX_REVOLUTIONS, MAX_RPM
from .errors import ScenarioError
from .fieldspec import FieldError as _FieldError
from .fieldspec import field_spec, section, spec, validate_fields
from .fieldspec import got as _got
from .fieldspec import show as _show
from .fieldspec import toml_key as _key


BUILTIN_MODEL = "builtin"
TOA_METHODS = ("HP", "AD", "PAD")
SPEED_INITIAL = ("steady", "rest")
FORCE_NODES = ("leading_edge", "trailing_edge")
MAX_FAMILIES = 20
#: Most speeds of a speed-dependent model (``[model] centrifugal_speeds``; the model file's limit).
MAX_MODEL_SPEEDS = 64
#: ``[model]`` keys written only when ``centrifugal`` is on (a default run's id, a hash of the
#: scenario text, stays what it was before they existed).
CENTRIFUGAL_KEYS = ("centrifugal", "centrifugal_speeds", "centrifugal_max_rpm")
MAX_TIP_NODES = 100
MIN_CLOCK_HZ, MAX_CLOCK_HZ = 1e3, 1e12
MAX_PROBE_ANGLE_ERROR_DEG = 5.0
MAX_TIP_RADIUS_M = 10.0
MAX_SEED = 2**63 - 1
SIGNAL_PROBES = ("optical", "capacitive")
SIGNAL_TRIGGERS = ("threshold", "constant_fraction", "peak")
SIGNAL_EDGES = ("rising", "falling")
MAX_WINDOW_SAMPLES = 4096
MAX_STALL_FREQUENCY_HZ = 1e6
MAX_BROADBAND_HZ = 1e5
MAX_BROADBAND_LINES = 256
MAX_SIGNAL_SIZE_M = 0.05
#: Slowest speed of a profile point, rpm: far below any run, far above a speed whose
#: rad/s underflows (the checks divide by it and square it).
MIN_RPM = 1e-3
#: Shortest and longest speed ramp or dwell, s: a shorter one's acceleration, a longer
#: one's revolution count overflow before the revolution limit can refuse them.
MIN_DURATION_S, MAX_DURATION_S = 1e-3, 1e9
_RIG_RE = re.compile(r"[A-Za-z0-9_-]+")


def did_you_mean(name: Any, candidates: Sequence[str]) -> str:
    close = difflib.get_close_matches(str(name), list(candidates), n=1)
    return f" (did you mean {close[0]}?)" if close else ""


def field_names(cls: type) -> tuple[str, ...]:
    return tuple(f.name for f in dataclasses.fields(cls))


def check_keys(where: str, table: Mapping[str, Any], cls: type) -> None:
    names = field_names(cls)
    for k in table:
        if k not in names:
            raise ScenarioError(f"unknown key {where} {_key(k)}{did_you_mean(k, names)}")


def set_normalised(obj: Any, name: str, value: Any) -> None:
    """Store a normalised value on a frozen dataclass (inside ``__post_init__`` only)."""
    object.__setattr__(obj, name, value)


# --------------------------------------------------------------------------------------
# Checks of one field beyond its kind and bounds
# --------------------------------------------------------------------------------------


def _check_rig(where: str, key: str, rig: str) -> str:
    if not _RIG_RE.fullmatch(rig):
        raise _FieldError(where, key, "must be non-empty and use only letters, digits, "
                          f"'_' and '-', got {_show(rig)}")
    return rig


def _check_source(where: str, key: str, source: str) -> str:
    if not source:
        raise _FieldError(where, key, 'must be "builtin" or a file path, got ""')
    return source


def _check_direction(where: str, key: str, direction: tuple[float, ...]) -> tuple[float, ...]:
    if len(direction) != 3:
        raise _FieldError(where, key, f"must have 3 components (radial, tangential, axial), got {len(direction)}")
    if not any(direction):
        raise _FieldError(where, key, "must not be the zero vector")
    norm2 = math.fsum(float(c) * float(c) for c in direction)  # Python floats: inf, not a warning
    if not 0.0 < norm2 < math.inf:
        raise _FieldError(where, key, f"cannot be normalised (its squared length is {norm2:g}): give components "
                          "of a usual size, e.g. (0, 0, 1)")
    return direction


def _check_distinct(where: str, key: str, values: tuple[float, ...]) -> tuple[float, ...]:
    first: dict[float, int] = {}
    for i, a in enumerate(values):
        if a in first:
            raise _FieldError(where, f"{key}[{i}]", f"duplicates {key}[{first[a]}] ({_show(a)})")
        first[a] = i
    return values


def _check_band(where: str, key: str, band: tuple[float, ...]) -> tuple[float, ...]:
    if len(band) != 2 or not band[0] < band[1]:
        raise _FieldError(where, key, f"must be [low, high] with low < high, got {_show(list(band))}")
    return band


def _check_segments(where: str, key: str, value: Any) -> tuple[tuple[float, float], ...]:
    from .fieldspec import check_sequence

    items = check_sequence(where, key, value, "an array of {duration_s = ..., end_rpm = ...} tables")
    return tuple(_segment(where, f"{key}[{i}]", s) for i, s in enumerate(items))


_SEGMENT_KEYS = ("duration_s", "end_rpm")


def _segment(where: str, key: str, value: Any) -> tuple[float, float]:
    """Check one speed segment: a ``{duration_s, end_rpm}`` mapping or a pair; its members
    have the bounds of ``[speed] duration_s`` and ``end_rpm``."""
    if isinstance(value, Mapping):
        for k in value:
            if k not in _SEGMENT_KEYS:
                raise _FieldError(where, key, f"has unknown key {_key(k)}{did_you_mean(k, _SEGMENT_KEYS)}"
                                  " (expected duration_s and end_rpm)")
        for k in _SEGMENT_KEYS:
            if k not in value:
                raise _FieldError(where, key, f"is missing {k}")
        d, r = value["duration_s"], value["end_rpm"]
    elif isinstance(value, (list, tuple, np.ndarray)) and len(value) == 2:
        d, r = value[0], value[1]
    else:
        raise _FieldError(where, key, f"must be a table {{duration_s = ..., end_rpm = ...}}, "
                          f"{_got(value)}")
    specs = {f.name: field_spec(f) for f in dataclasses.fields(Speed)}
    return (specs["duration_s"].validate(where, f"{key}.duration_s", d, None),
            specs["end_rpm"].validate(where, f"{key}.end_rpm", r, None))


def _check_signal_table(where: str, key: str, value: Any) -> "Signal":
    if isinstance(value, Mapping):
        check_keys("[acquisition.signal]", value, Signal)
        return Signal(**value)
    if not isinstance(value, Signal):
        raise _FieldError(where, key, f"must be a table ([acquisition.signal]), {_got(value)}")
    return value


def _force_fields() -> tuple[Any, Any]:
    """The ``direction`` and ``node`` fields shared by every force pattern."""
    direction = spec((0.0, 0.0, 1.0), kind="floats", check=_check_direction, doc=(
        "force direction (radial, tangential, axial) at the force node; normalised at use"))
    node = spec("leading_edge", kind="str", choices=FORCE_NODES, doc=(
        "tip-section edge where the force is applied: {range}"))
    return direction, node


# --------------------------------------------------------------------------------------
# Sections
# --------------------------------------------------------------------------------------


@section
@dataclass(frozen=True, slots=True)
class Run:
    """``[run]``: identity of the run and the seed of every random choice.

    The same scenario and seed give the same run.
    """

    rig: str = spec(DEFAULT_RIG, kind="str", check=_check_rig, doc=(
        "rig name, used as a Zenoh key segment: non-empty, only A-Z a-z 0-9 _ -"))
    seed: int = spec(0, kind="int", lo=0, hi=MAX_SEED, doc=(
        "seed of every random choice (random mistuning, acquisition errors); integer {range}"))

    def __post_init__(self) -> None:
        validate_fields(self, "[run]")


@section
@dataclass(frozen=True, slots=True)
class Rotor:
    """``[rotor]``: geometry of the built-in bladed disk and its tip section.

    The tip chord runs from the leading edge (LE) at axial position z = 0 to the trailing
    edge (TE) at z = ``tip_chord_m * sin(stagger_deg)``. The tip nodes lie on the chord,
    ``tip_node_spacing_m`` apart, starting at the TE.
    """

    n_blades: int = spec(29, kind="int", lo=2, hi=MAX_BLADES, doc=(
        "number of blades (the paper's rotor has 29); integer {range}"),
        note="The built-in model's memory grows as n_families * n_blades**2: about 0.6 GB at "
             "200 blades and 5 families")
    tip_radius_m: float = spec(0.19, kind="float", unit="m", lo=0, lo_open=True, hi=MAX_TIP_RADIUS_M, doc=(
        "blade tip radius, {unit}; {range}, and >= 1.1 x its rim radius (0.115 m) with the\n"
        "built-in model (our choice, small turbojet 1st compressor stage)"),
        note="The paper does not give it; 0.19 m is representative of the first compressor stage "
             "of a small turbojet. The rim condition is checked when the built-in model is built")
    stagger_deg: float = spec(41.5, kind="float", unit="deg", lo=0, lo_open=True, hi=90, hi_open=True, doc=(
        "tip stagger eta_tip, {unit}: tip chord angle from the tangential direction; {range}"))
    tip_chord_m: float = spec(0.0202523, kind="float", unit="m", lo=0, lo_open=True, hi="tip_radius_m", doc=(
        "tip chord length, {unit}; {range}. LE at z = 0, TE at z = tip_chord_m * sin(stagger)"))
    n_tip_nodes: int = spec(9, kind="int", lo=2, hi=MAX_TIP_NODES, doc=(
        "number of tip nodes along the chord; integer {range}"))
    tip_node_spacing_m: float = spec(0.0004375, kind="float", unit="m", lo=0, lo_open=True, doc=(
        "tip node spacing along the chord from the TE, {unit}; {range};\n"
        "(n_tip_nodes - 1) * tip_node_spacing_m <= tip_chord_m"))
    nominal_node: int = spec(5, kind="int", lo=1, hi="n_tip_nodes", doc=(
        "nominal node P_nom counted from the TE (TE node = 1); {range}"),
        note="The default is the paper's P_nom, 1.75 mm from the TE")

    def __post_init__(self) -> None:
        validate_fields(self, "[rotor]")
        span = (self.n_tip_nodes - 1) * self.tip_node_spacing_m
        if span > self.tip_chord_m * (1.0 + 1e-12):
            raise _FieldError("[rotor]", "tip_node_spacing_m", f"puts the tip nodes beyond the chord: "
                              f"(n_tip_nodes - 1) * tip_node_spacing_m = {span:.6g} m > "
                              f"tip_chord_m = {self.tip_chord_m:.6g} m")

    @property
    def tip_axial_extent_m(self) -> float:
        """Axial extent of the tip chord, m: the TE's z, ``tip_chord_m * sin(stagger)``."""
        return self.tip_chord_m * math.sin(math.radians(self.stagger_deg))

    @property
    def nominal_offset_from_te_m(self) -> float:
        """Distance of the nominal node from the TE along the chord, m."""
        return (self.nominal_node - 1) * self.tip_node_spacing_m


@section
@dataclass(frozen=True, slots=True)
class Model:
    """``[model]``: where the modal model comes from, its damping and its mistuning.

    :func:`load_scenario` resolves a relative ``source`` path against the scenario file's
    directory. The three ``centrifugal*`` keys are written only when ``centrifugal`` is on.
    """

    source: str = spec(BUILTIN_MODEL, kind="str", check=_check_source, doc=(
        '"builtin" (parametric bladed disk from [rotor]) or the path of a modal model .npz\n'
        "(a relative path is relative to this file's directory)"))
    damping_beta_s: float = spec(9e-6, kind="float", unit="s", lo=0, hi=1.0, doc=(
        "stiffness-proportional damping beta, {unit}; zeta = beta * omega / 2; {range}"))
    n_families: int = spec(5, kind="int", lo=1, hi=MAX_FAMILIES, doc=(
        "mode families kept per nodal diameter (modes = n_families * n_blades); {range}"))
    disk_asymmetry: bool = spec(False, kind="bool", doc=(
        "small deterministic disk asymmetry splitting the nodal-diameter pairs (paper's disk)"))
    stiffness_factors: tuple[float, ...] = spec((), kind="floats", lo=0, lo_open=True, doc=(
        "per-blade stiffness factors: [] = none, else n_blades finite values {range}"))
    mass_factors: tuple[float, ...] = spec((), kind="floats", lo=0, lo_open=True, doc=(
        "per-blade mass factors: [] = none, else n_blades finite values {range}"))
    stiffness_std: float = spec(0.0, kind="float", lo=0, hi=0.5, hi_open=True, doc=(
        "std of seeded random per-blade stiffness factors 1 + N(0, std); {range};\n"
        "exclusive with stiffness_factors"))
    mass_std: float = spec(0.0, kind="float", lo=0, hi=0.5, hi_open=True, doc=(
        "std of seeded random per-blade mass factors 1 + N(0, std); {range};\n"
        "exclusive with mass_factors"))
    centrifugal: bool = spec(False, kind="bool", doc=(
        "speed-dependent modes of the built-in model: centrifugal stiffening and spin\n"
        "softening (Coriolis neglected)"),
        note="Only with source = \"builtin\" (schemas/modal_model.md); a mistuned or asymmetric "
             "wheel is solved as a full wheel (seconds rather than 1 s)")
    centrifugal_speeds: int = spec(17, kind="int", lo=2, hi=MAX_MODEL_SPEEDS, doc=(
        "speeds at which the modes are solved (0 .. centrifugal_max_rpm); {range}"))
    centrifugal_max_rpm: float = spec(0.0, kind="float", unit="rpm", lo=0, hi=MAX_RPM, doc=(
        "highest of those speeds, {unit}; {range}; 0 = 1.2 x the speed profile's top speed;\n"
        "else >= it"), note="The default 0 is rounded up to 100 rpm")

    def __post_init__(self) -> None:
        validate_fields(self, "[model]")
        for kind in ("stiffness", "mass"):
            if getattr(self, f"{kind}_factors") and getattr(self, f"{kind}_std") > 0:
                raise _FieldError("[model]", f"{kind}_std", f"must be 0 when {kind}_factors is given "
                                  f"(use one or the other), got {_show(getattr(self, f'{kind}_std'))}")


@section
@dataclass(frozen=True, slots=True)
class Speed:
    """``[speed]``: the rotor speed profile.

    By default the paper's linear run-up (Eq. 6) from ``start_rpm`` to ``end_rpm`` in
    ``duration_s``. With ``segments``, a piecewise-linear profile: each segment ramps
    linearly from the previous segment's end speed (the first from ``start_rpm``) to its
    own ``end_rpm`` in its ``duration_s``; a dwell is a segment that keeps the speed. Then
    ``end_rpm`` and ``duration_s`` are derived (and must be absent from a file).
    Programmatically, segments may be pairs or mappings. The whole profile makes at most
    1,000,000 revolutions (:data:`~bttsim_stream.defaults.MAX_REVOLUTIONS`), and with the OPR
    sensor's angle at least one whole revolution between two OPR pulses (the scenario checks).
    """

    start_rpm: float = spec(1000.0, kind="float", unit="rpm", lo=MIN_RPM, hi=MAX_RPM, doc=(
        "speed at t = 0, {unit}; {range} (paper Eq. 6: linear run-up)"))
    end_rpm: float = spec(4000.0, kind="float", unit="rpm", lo=MIN_RPM, hi=MAX_RPM, doc=(
        "speed at the end of the run-up, {unit}; {range}. Leave out when segments is given"))
    duration_s: float = spec(130.0, kind="float", unit="s", lo=MIN_DURATION_S, hi=MAX_DURATION_S, doc=(
        "duration of the run-up, {unit}; {range}. Leave out when segments is given"))
    segments: tuple[tuple[float, float], ...] = spec((), kind="custom", check=_check_segments,
                                                     type_name="tuple of (float, float)", doc=(
        "piecewise-linear profile: segments from start_rpm, each {{duration_s ({f[duration_s].unit}, "
        "{f[duration_s].range}),\nend_rpm ({f[end_rpm].unit}, {f[end_rpm].range})}}; a dwell keeps end_rpm. "
        "Replaces end_rpm and duration_s"))
    initial: str = spec("steady", kind="str", choices=SPEED_INITIAL, doc=(
        'modal state at t = 0: "steady" (every mode in its quasi-steady forced response,\n'
        'near a resonance too) or "rest" (zero displacement and velocity)'))

    def __post_init__(self) -> None:
        w = "[speed]"
        validate_fields(self, w, skip=("end_rpm", "duration_s") if self._has_segments() else ())
        if self.segments:
            set_normalised(self, "end_rpm", self.segments[-1][1])
            set_normalised(self, "duration_s", math.fsum(d for d, _ in self.segments))
        revolutions = self.revolutions()
        if not revolutions <= MAX_REVOLUTIONS:
            raise _FieldError(w, "", f"makes {revolutions:.3g} revolutions, more than the "
                              f"{MAX_REVOLUTIONS:,} of one run: shorten duration_s or the segments")

    def revolutions(self) -> float:
        """Revolutions the profile makes (the area under its speed), a fraction."""
        t_s, rpm = self.breakpoints()
        return math.fsum(0.5 * (a + b) * d for a, b, d in zip(rpm[:-1], rpm[1:], np.diff(t_s))) / 60.0

    def _has_segments(self) -> bool:
        try:
            return len(self.segments) > 0
        except TypeError:  # not an array: the check of segments says so
            return False

    @property
    def total_duration_s(self) -> float:
        """Duration of the whole profile, s."""
        return self.duration_s

    def breakpoints(self) -> tuple[np.ndarray, np.ndarray]:
        """The piecewise-linear speed profile.

        Returns
        -------
        t_s : numpy.ndarray
            Breakpoint times, s, increasing from 0 to :attr:`total_duration_s`.
        rpm : numpy.ndarray
            Speed at each breakpoint, rpm; linear in between.
        """
        if not self.segments:
            return (np.array([0.0, self.duration_s]), np.array([self.start_rpm, self.end_rpm]))
        durations = np.array([d for d, _ in self.segments])
        t_s = np.concatenate(([0.0], np.cumsum(durations)))
        t_s[-1] = self.duration_s
        rpm = np.array([self.start_rpm] + [r for _, r in self.segments])
        return t_s, rpm


@section
@dataclass(frozen=True, slots=True)
class Excitation:
    """``[[excitation]]``: one engine-order force pattern applied at every blade tip."""

    engine_order: int = spec(8, kind="int", lo=1, hi=MAX_ENGINE_ORDER, doc=(
        "engine order EO (force cycles per revolution); integer {range}"))
    nodal_diameter: int = spec(1, kind="int", lo=0, cross_hi="n_blades", hi_open=True, doc=(
        "nodal diameter ND of the force pattern (inter-blade phase 2*pi*ND/n_blades);\n"
        "integer {range}"))
    amplitude_n: float = spec(2.25, kind="float", unit="N", lo=0, doc=(
        "force amplitude per blade, {unit}; {range}"))
    direction: tuple[float, float, float] = spec((0.0, 0.0, 1.0), kind="floats", check=_check_direction, doc=(
        "force direction (radial, tangential, axial) at the force node; 3 finite\n"
        "components, not all zero; normalised at use"))
    node: str = spec("leading_edge", kind="str", choices=FORCE_NODES, doc=(
        "tip-section edge where the force is applied: {range}"))

    def __post_init__(self) -> None:
        validate_fields(self, "[[excitation]]")


@section
@dataclass(frozen=True, slots=True)
class Probes:
    """``[probes]``: the BTT probes and the once-per-revolution (OPR) sensor.

    Angles are anticlockwise from +x seen from +z, like the rotation.
    """

    angles_deg: tuple[float, ...] = spec((5.0, 15.15, 23.82, 220.0, 301.5), kind="floats", unit="deg",
                                         lo=0, hi=360, hi_open=True, count=(1, MAX_PROBES),
                                         check=_check_distinct, doc=(
        "probe angular positions, {unit}, anticlockwise from +x; {count} distinct values\n"
        "{range}"))
    axial_position_m: float = spec(0.01226, kind="float", unit="m", doc=(
        "probe axial position z_j, {unit}; within the tip chord's axial extent\n"
        "[0, tip_chord_m * sin(stagger_deg)]"),
        note="With a user's model ([model] source), within the axial span of its tip nodes, checked "
             "when the model is loaded")
    opr_angle_deg: float = spec(0.0, kind="float", unit="deg", lo=0, hi=360, hi_open=True, doc=(
        "once-per-revolution (OPR) sensor angle, {unit}; {range}"))

    def __post_init__(self) -> None:
        validate_fields(self, "[probes]")


@section
@dataclass(frozen=True, slots=True)
class Toa:
    """``[toa]``: how times of arrival (TOAs) are computed (paper Sec. 2.2)."""

    method: str = spec("HP", kind="str", choices=TOA_METHODS, doc="TOA method (paper Sec. 2.2): {range}")
    grid_step_s: float = spec(1.2e-5, kind="float", unit="s", lo=1e-9, hi=1e-4, doc=(
        "integrator time grid step for the AD/PAD interpolation, {unit}; {range}"),
        note="1.2e-5 s gives PAD the paper's ~10 % noise-to-signal ratio at resonance")
    axial_interpolation: bool = spec(True, kind="bool", doc=(
        "true: interpolate between tip nodes at the probe z; false: nearest node (Fig. 7)"))

    def __post_init__(self) -> None:
        validate_fields(self, "[toa]")


def _signal_size(default: float, what: str) -> Any:
    return spec(default, kind="float", unit="m", lo=0, lo_open=True, hi=MAX_SIGNAL_SIZE_M,
                doc=what + ", {unit}; {range}")


@section
@dataclass(frozen=True, slots=True)
class Signal:
    """``[acquisition.signal]``: probe signals, digitisation and triggers (off by default).

    When ``enabled``, every published TOA comes out of the chain of
    :mod:`bttsim_stream.sim.signal` (probe pulse around the exact passage, front-end
    low-pass, noise, ADC, trigger, counter clock) instead of the exact TOA plus
    ``trigger_jitter_s``; the truth keeps the exact TOA of the same passage. A pulse that
    does not trigger is a missing TOA (NaN). The centrifugal tip growth is
    ``rho Omega^2 R^3 / (3 E)``.
    """

    enabled: bool = spec(False, kind="bool", doc=(
        "true: TOAs come from probe signals and triggers (truth keeps the exact TOAs)"))
    probe_type: Any = spec("optical", kind="choice_each", choices=SIGNAL_PROBES, doc=(
        "{range}; one value, or an array with one per probe"))
    trigger: Any = spec("threshold", kind="choice_each", choices=SIGNAL_TRIGGERS, doc=(
        "{range}; one value, or an array with one per probe"))
    edge: str = spec("rising", kind="str", choices=SIGNAL_EDGES, doc="threshold trigger edge: {range}")
    level_v: float = spec(0.5, kind="float", unit="V", doc=(
        "trigger level (arming level of constant_fraction and peak), {unit}; within the ADC range"))
    hysteresis_v: float = spec(0.05, kind="float", unit="V", lo=0, doc="threshold trigger hysteresis, {unit}; {range}")
    fraction: float = spec(0.5, kind="float", lo=0, lo_open=True, hi=1, hi_open=True, doc="constant fraction; {range}")
    spot_diameter_m: float = _signal_size(0.5e-3, "optical probe 1/e^2 spot diameter")
    electrode_diameter_m: float = _signal_size(1.5e-3, "capacitive probe electrode diameter")
    tip_thickness_m: float = _signal_size(1.0e-3, "tangential width of the blade tip at the probe")
    clearance_m: float = spec(0.5e-3, kind="float", unit="m", lo=0, lo_open=True, hi=MAX_SIGNAL_SIZE_M, doc=(
        "cold tip clearance, {unit}; {range}, above the centrifugal growth"))
    reference_clearance_m: float = _signal_size(
        0.5e-3, "clearance at which the capacitive pulse height scale is height_v")
    height_v: float = spec(1.0, kind="float", unit="V", lo=0, lo_open=True, doc=(
        "pulse height scale, {unit} (capacitive: at reference_clearance_m, falls as 1 / clearance); {range}"))
    fringe_factor: float = spec(0.5, kind="float", lo=0, hi=10, doc=(
        "capacitive field spreading with clearance (kernel sigma^2 = (D/4)^2 + (k g)^2); {range}"))
    bandwidth_hz: float = spec(1.0e6, kind="float", unit="Hz", lo=0, doc=(
        "front-end bandwidth (first-order low-pass), {unit}; {range}, 0 = unlimited"))
    sample_rate_hz: float = spec(2.0e6, kind="float", unit="Hz", lo=1e5, hi=1e9, doc="ADC sample rate, {unit}; {range}")
    bits: int = spec(12, kind="int", lo=4, hi=24, doc="ADC resolution, bits; {range}")
    range_lo_v: float = spec(-0.5, kind="float", unit="V", doc="ADC input range low end, {unit}")
    range_hi_v: float = spec(1.5, kind="float", unit="V", lo="range_lo_v", lo_open=True, doc=(
        "ADC input range high end, {unit}; {range}"))
    noise_v: float = spec(0.005, kind="float", unit="V", lo=0, doc=(
        "rms of the white noise at the ADC input (band-limited by the front end), {unit}; {range}"))
    lf_noise_v: float = spec(0.0, kind="float", unit="V", lo=0, doc="rms of the low-frequency noise, {unit}; {range}")
    lf_corner_hz: float = spec(10.0, kind="float", unit="Hz", lo=0, lo_open=True, hi=1e6, doc=(
        "highest frequency of the low-frequency noise, {unit}; {range}"))
    offset_v: float = spec(0.0, kind="float", unit="V", doc="baseline offset, {unit}")
    offset_drift_v_per_s: float = spec(0.0, kind="float", unit="V/s", doc="baseline drift, {unit}")
    gain_drift_per_s: float = spec(0.0, kind="float", unit="1/s", doc="relative gain drift, {unit}")
    density_kg_m3: float = spec(4430.0, kind="float", unit="kg/m^3", lo=0, lo_open=True, doc=(
        "rotor density for the centrifugal tip growth, {unit}; {range}"))
    youngs_modulus_pa: float = spec(1.14e11, kind="float", unit="Pa", lo=0, lo_open=True, doc=(
        "rotor Young's modulus for the centrifugal tip growth, {unit}; {range}"))
    publish: bool = spec(False, kind="bool", doc=(
        "true: also publish the raw windows (ADC codes) on bttsim/<rig>/signal/<probe>"),
        note="Needs enabled = true; the messages are bttsim.v1.SignalBatch (schemas/bus.md)")

    def __post_init__(self) -> None:
        w = "[acquisition.signal]"
        validate_fields(self, w)
        if self.publish and not self.enabled:  # asked for signals that would never come
            raise _FieldError(w, "publish", "= true needs enabled = true (no signal is synthesised with the "
                              "chain off)")
        if not self.range_lo_v < self.level_v < self.range_hi_v:
            raise _FieldError(w, "level_v", f"must lie inside the ADC range ({_show(self.range_lo_v)}, "
                              f"{_show(self.range_hi_v)}), got {_show(self.level_v)}")


@section
@dataclass(frozen=True, slots=True)
class Acquisition:
    """``[acquisition]``: errors of the acquisition system; all off (0) by default.

    The jitters and the speed fluctuation are standard deviations; the probe angle errors are
    drawn once per run. The upper limits relative to the speed profile, and the clock counting
    the whole run in 62 bits, are checked by :class:`Scenario`.
    """

    clock_hz: float = spec(0.0, kind="float", unit="Hz", lo=MIN_CLOCK_HZ, hi=MAX_CLOCK_HZ,
                           zero_off="no quantisation", doc=(
        "TOA counter clock, {unit}; 0 = no quantisation, else {range} (TOAs become whole ticks)"))
    trigger_jitter_s: float = spec(0.0, kind="float", unit="s", lo=0, doc=(
        "std of the Gaussian jitter on each TOA, {unit}; {range}, at most 1 % of the shortest revolution"))
    probe_angle_error_deg: float = spec(0.0, kind="float", unit="deg", lo=0, hi=MAX_PROBE_ANGLE_ERROR_DEG, doc=(
        "std of static random probe angular position errors, {unit}; {range}"))
    opr_jitter_s: float = spec(0.0, kind="float", unit="s", lo=0, doc=(
        "std of the Gaussian jitter on each OPR timestamp, {unit}; {range}, at most 1 % of the shortest\n"
        "revolution"))
    speed_fluctuation_rpm: float = spec(0.0, kind="float", unit="rpm", lo=0, doc=(
        "std of the random speed fluctuation about the speed profile, {unit}; {range}, at most 10 %\n"
        "of the slowest speed"))
    signal: Signal = spec(kind="custom", default_factory=Signal, check=_check_signal_table, type_name="Signal",
                          doc="the probe signal and trigger chain: the [acquisition.signal] table")

    def __post_init__(self) -> None:
        validate_fields(self, "[acquisition]")


@section
@dataclass(frozen=True, slots=True)
class RotatingStall:
    """``[[rotating_stall]]``: a non-synchronous force pattern of ``cells`` lobes rotating in the
    stationary frame (rotating stall, or any non-integral forcing); none by default.

    Blade ``b`` (rotor angle ``theta_b = 2 pi b / N_b``) sees
    ``F cos(N_s (1 - r) phi(t) + N_s theta_b)`` (cells turning at ``r`` times the shaft speed:
    a non-integer engine order ``N_s (1 - r)``), or with ``frequency_hz = f_s > 0``,
    ``F cos(N_s phi(t) + N_s theta_b - 2 pi f_s t)`` (a pattern of fixed frequency ``f_s`` in
    the stationary frame). The spatial pattern is nodal diameter ``N_s mod N_b``
    (:mod:`bttsim_stream.sim.nsv`).
    """

    cells: int = spec(5, kind="int", lo=1, hi=MAX_ENGINE_ORDER, doc=(
        "number of stall cells (lobes) N_s; integer {range}"))
    speed_fraction: float = spec(0.5, kind="float", lo=0, hi=1, hi_open=True, doc=(
        "cell speed in the stationary frame over the shaft speed; {range}"))
    frequency_hz: float = spec(0.0, kind="float", unit="Hz", lo=0, hi=MAX_STALL_FREQUENCY_HZ, doc=(
        "stationary-frame frequency of the pattern, {unit}; {range}; 0: off (cells follow\n"
        "speed_fraction); > 0 replaces speed_fraction"))
    amplitude_n: float = spec(0.5, kind="float", unit="N", lo=0, doc="force amplitude per blade, {unit}; {range}")
    direction: tuple[float, float, float]
    node: str
    direction, node = _force_fields()

    def __post_init__(self) -> None:
        validate_fields(self, "[[rotating_stall]]")


@section
@dataclass(frozen=True, slots=True)
class Flutter:
    """``[flutter]``: a self-excited travelling wave of one mode family and nodal diameter
    (off by default).

    Negative aerodynamic damping ``aero_damping_ratio`` beyond the mode's structural damping
    makes the wave grow from ``seed_amplitude_m`` at the onset (``start_s``, or the first time
    the speed reaches ``start_rpm``) to ``limit_amplitude_m`` along the logistic law of the
    averaged Van der Pol oscillator, at the mode's damped frequency
    (:mod:`bttsim_stream.sim.nsv`). Amplitudes are peak-to-peak ``d_eqv`` at P_nom of the
    blade with the largest. The nodal diameter's sign follows
    :mod:`bttsim_stream.process.travelling_wave`.
    """

    enabled: bool = spec(False, kind="bool", doc="simulate a flutter travelling wave")
    family: int = spec(1, kind="int", lo=1, hi=MAX_FAMILIES, doc=(
        "mode family, 1-based (1: first bending); integer {range}"))
    nodal_diameter: int = spec(3, kind="int", doc=(
        "signed nodal diameter: > 0 forward, < 0 backward travelling wave; |nd| <= n_blades / 2"))
    start_s: float = spec(0.0, kind="float", unit="s", lo=0, doc=(
        "onset time, {unit}; {range} (when start_rpm is 0)"), note="Before the end of the run")
    start_rpm: float = spec(0.0, kind="float", unit="rpm", lo=0, hi=MAX_RPM, doc=(
        "onset speed, {unit}; {range}; 0: off, > 0: the first time the speed profile reaches it"),
        note="It must lie within the speed profile")
    aero_damping_ratio: float = spec(0.02, kind="float", lo=0, lo_open=True, hi=1, hi_open=True, doc=(
        "negative aerodynamic damping ratio; {range}, above the mode's structural damping"),
        note="The structural damping (0.0098 for family 1 of the built-in model) is checked once the "
             "model is built")
    limit_amplitude_m: float = spec(2e-4, kind="float", unit="m", lo=0, lo_open=True, doc=(
        "limit-cycle amplitude, {unit} pk-pk (d_eqv at P_nom); {range}"))
    seed_amplitude_m: float = spec(1e-9, kind="float", unit="m", lo=0, lo_open=True, hi="limit_amplitude_m",
                                   hi_open=True, doc="amplitude at onset, {unit} pk-pk; {range}")
    phase_deg: float = spec(0.0, kind="float", unit="deg", doc="phase of the wave at onset, {unit}")

    def __post_init__(self) -> None:
        validate_fields(self, "[flutter]")


@section
@dataclass(frozen=True, slots=True)
class Broadband:
    """``[broadband]``: random blade forcing with a flat force spectrum in a band (off by
    default).

    Realised as ``n_lines`` sinusoids at the centres of equal sub-bands of ``band_hz``, each
    of amplitude ``sqrt(2 psd_n2_per_hz df)`` per blade with a random phase per blade and line
    (seeded by ``[run] seed``): every line is an exact carrier of the envelope recursion, so
    the cost grows with ``n_lines`` like as many excitations (:mod:`bttsim_stream.sim.nsv`).
    """

    enabled: bool = spec(False, kind="bool", doc="simulate broadband (random) blade forcing")
    band_hz: tuple[float, float] = spec((300.0, 400.0), kind="floats", unit="Hz", lo=0, lo_open=True,
                                        hi=MAX_BROADBAND_HZ, check=_check_band, doc=(
        "frequency band [low, high] of the force spectrum, {unit}; low < high, each {range}"))
    psd_n2_per_hz: float = spec(1e-4, kind="float", unit="N^2/Hz", lo=0, doc=(
        "one-sided force PSD per blade, {unit}; {range}"))
    n_lines: int = spec(16, kind="int", lo=1, hi=MAX_BROADBAND_LINES, doc=(
        "sinusoids realising the spectrum (random phase per blade and line); {range}"))
    direction: tuple[float, float, float]
    node: str
    direction, node = _force_fields()

    def __post_init__(self) -> None:
        validate_fields(self, "[broadband]")

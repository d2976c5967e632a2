"""The scenario: one TOML file that configures a run, read into frozen dataclasses.

Every field has a default: the paper's Table 1 (Nour, Bonello et al.) plus the rotor
geometry we chose where the paper gives none. ``bttsim scenario`` prints the default file
(:func:`default_toml`); the user edits it and passes it back (:func:`load_scenario`).

Rules, the same for a file and for programmatic construction:

* All values are SI with the unit in the name (``_m``, ``_s``, ``_n``, ``_hz``), except
  angles in degrees (``_deg``) and speeds in rpm (``_rpm``), as in the paper.
* Each section dataclass validates itself in ``__post_init__``; :class:`Scenario` adds
  the checks that span sections. Any problem raises
  :class:`~bttsim_stream.errors.ScenarioError` with a one-line message naming the field,
  e.g. ``[probes] angles_deg[2] must be finite, got nan``; :func:`load_scenario` and
  :func:`scenario_from_dict` prefix it with the file (``scenario.toml: ...``).
* An integer is accepted where a float is expected, never the reverse; a boolean is never
  accepted as a number. Floats must be finite. Lists are stored as tuples.
* In a file, unknown sections and keys are errors; a missing section or key takes its
  default. Array indices in messages count from 0.

The file is read with :mod:`tomllib`; :func:`dumps_toml` is a small emitter for the few
value types used here, written so that ``load(dumps(s)) == s`` exactly (floats by
``repr``).
"""

from __future__ import annotations

import dataclasses
import difflib
import json
import math
import numbers
import os
import re
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .defaults import MAX_BLADES, MAX_ENGINE_ORDER, MAX_PROBES, MAX_REVOLUTIONS, MAX_RPM
from .errors import ScenarioError

__all__ = [
    "Run",
    "Rotor",
    "Model",
    "Speed",
    "Excitation",
    "Probes",
    "Toa",
    "Acquisition",
    "Signal",
    "RotatingStall",
    "Flutter",
    "Broadband",
    "Scenario",
    "SECTIONS",
    "load_scenario",
    "scenario_from_dict",
    "scenario_to_dict",
    "dumps_toml",
    "default_toml",
]

BUILTIN_MODEL = "builtin"
TOA_METHODS = ("HP", "AD", "PAD")
SPEED_INITIAL = ("steady", "rest")
FORCE_NODES = ("leading_edge", "trailing_edge")
MAX_FAMILIES = 20
#: Most speeds of a speed-dependent model (``[model] centrifugal_speeds``; the model file's limit).
MAX_MODEL_SPEEDS = 64
#: ``[model]`` keys written only when ``centrifugal`` is on (a default run's id, a hash of the
#: scenario text, stays what it was before they existed).
_CENTRIFUGAL_KEYS = ("centrifugal", "centrifugal_speeds", "centrifugal_max_rpm")
MAX_TIP_NODES = 100
MIN_CLOCK_HZ, MAX_CLOCK_HZ = 1e3, 1e12
MAX_PROBE_ANGLE_ERROR_DEG = 5.0
MAX_TIP_RADIUS_M = 10.0
MAX_SEED = 2**63 - 1
_RIG_RE = re.compile(r"[A-Za-z0-9_-]+")
_BARE_KEY_RE = re.compile(r"[A-Za-z0-9_-]+")


# --------------------------------------------------------------------------------------
# Errors and value checks
# --------------------------------------------------------------------------------------


class _FieldError(ScenarioError):
    """A :class:`ScenarioError` that remembers where it happened, so it can be relabelled.

    Parameters
    ----------
    where : str
        Section label, e.g. ``"[probes]"`` or ``"[[excitation]][1]"``.
    key : str
        Field (with an index if any), e.g. ``"angles_deg[2]"``; may be empty.
    problem : str
        What is wrong, e.g. ``"must be finite, got nan"``.
    """

    def __init__(self, where: str, key: str, problem: str) -> None:
        self.where, self.key, self.problem = where, key, problem
        text = " ".join(part for part in (where, key, problem) if part)
        super().__init__(_one_line(text))

    def relabel(self, where: str) -> "_FieldError":
        """The same error under another section label."""
        return _FieldError(where, self.key, self.problem)


def _one_line(text: str) -> str:
    return " ".join(str(text).split()) if ("\n" in text or "\r" in text) else text


def _toml_type(value: Any) -> str:
    """The TOML name of a value's type (for messages)."""
    if isinstance(value, bool):
        return "boolean"
    if isinstance(value, numbers.Integral):
        return "integer"
    if isinstance(value, numbers.Real):
        return "float"
    if isinstance(value, str):
        return "string"
    if isinstance(value, Mapping):
        return "table"
    if isinstance(value, (list, tuple)):
        return "array"
    return type(value).__name__


def _show(value: Any, limit: int = 60) -> str:
    """A short one-line TOML-like rendering of a value (for messages)."""
    if isinstance(value, bool):
        text = "true" if value else "false"
    elif isinstance(value, numbers.Integral):
        text = str(int(value))
    elif isinstance(value, numbers.Real):
        text = repr(float(value))
    elif isinstance(value, str):
        text = json.dumps(value, ensure_ascii=False)
    elif isinstance(value, Mapping):
        text = "{" + ", ".join(f"{_key(k)} = {_show(v, limit)}" for k, v in value.items()) + "}"
    elif isinstance(value, (list, tuple)):
        text = "[" + ", ".join(_show(v, limit) for v in value) + "]"
    else:
        text = repr(value)
    text = _one_line(text)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _got(value: Any) -> str:
    """``"got <type> <value>"`` for a value of the wrong type."""
    return f"got {_toml_type(value)} {_show(value)}"


def _num(x: float) -> str:
    """A bound for a message: ``0``, ``0.5``, ``360``."""
    return f"{x:g}"


def _is_real(value: Any) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))


def _is_int(value: Any) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, (bool, np.bool_))


def _real(where: str, key: str, value: Any, *, lo: float | None = None, lo_open: bool = False,
          hi: float | None = None, hi_open: bool = False) -> float:
    """Check a finite real number within optional bounds; return it as a float."""
    if not _is_real(value):
        raise _FieldError(where, key, f"must be a number, {_got(value)}")
    try:
        x = float(value)
    except OverflowError:  # an integer beyond any float
        raise _FieldError(where, key, f"must be finite, got an integer of {len(str(int(value)))} digits") from None
    if not math.isfinite(x):
        raise _FieldError(where, key, f"must be finite, got {_show(x)}")
    too_low = lo is not None and (x <= lo if lo_open else x < lo)
    too_high = hi is not None and (x >= hi if hi_open else x > hi)
    if too_low or too_high:
        if lo is not None and hi is not None:
            rng = f"in {'(' if lo_open else '['}{_num(lo)}, {_num(hi)}{')' if hi_open else ']'}"
        elif lo is not None:
            rng = f"{'>' if lo_open else '>='} {_num(lo)}"
        else:
            rng = f"{'<' if hi_open else '<='} {_num(hi)}"  # type: ignore[arg-type]
        raise _FieldError(where, key, f"must be {rng}, got {_show(x)}")
    return x


def _integer(where: str, key: str, value: Any, *, lo: int | None = None,
             hi: int | None = None) -> int:
    """Check an integer (not a bool, not a float) within optional inclusive bounds."""
    if lo is not None and hi is not None:
        what = f"an integer in [{lo}, {hi}]"
    elif lo is not None:
        what = f"an integer >= {lo}"
    elif hi is not None:
        what = f"an integer <= {hi}"
    else:
        what = "an integer"
    if not _is_int(value):
        raise _FieldError(where, key, f"must be {what}, {_got(value)}")
    n = int(value)
    if (lo is not None and n < lo) or (hi is not None and n > hi):
        raise _FieldError(where, key, f"must be {what}, got {_show(n)}")
    return n


def _boolean(where: str, key: str, value: Any) -> bool:
    """Check a boolean (``true``/``false``; 0 and 1 are not booleans)."""
    if not isinstance(value, (bool, np.bool_)):
        raise _FieldError(where, key, f"must be true or false, {_got(value)}")
    return bool(value)


def _string(where: str, key: str, value: Any, *, choices: Sequence[str] | None = None) -> str:
    """Check a string, optionally one of ``choices`` (case-sensitive)."""
    if choices is not None:
        allowed = ", ".join(json.dumps(c) for c in choices)
        if not isinstance(value, str):
            raise _FieldError(where, key, f"must be one of {allowed}, {_got(value)}")
        if value not in choices:
            raise _FieldError(where, key, f"must be one of {allowed}, got {_show(value)}")
        return value
    if not isinstance(value, str):
        raise _FieldError(where, key, f"must be a string, {_got(value)}")
    return value


def _sequence(where: str, key: str, value: Any, what: str) -> list[Any]:
    """Check an array (list, tuple or 1-D numpy array) and return its items as a list."""
    if isinstance(value, np.ndarray) and value.ndim == 1:
        return value.tolist()
    if not isinstance(value, (list, tuple)):
        raise _FieldError(where, key, f"must be {what}, {_got(value)}")
    return list(value)


def _real_tuple(where: str, key: str, value: Any, **bounds: Any) -> tuple[float, ...]:
    """Check an array of finite reals, each within ``bounds`` (see :func:`_real`)."""
    items = _sequence(where, key, value, "an array of numbers")
    return tuple(_real(where, f"{key}[{i}]", v, **bounds) for i, v in enumerate(items))


def _set(obj: Any, name: str, value: Any) -> None:
    """Store a normalised value on a frozen dataclass (inside ``__post_init__`` only)."""
    object.__setattr__(obj, name, value)


def _doc(text: str) -> dict[str, str]:
    """Field metadata: the comment written above the key in the emitted TOML."""
    return {"toml": text}


# --------------------------------------------------------------------------------------
# Sections
# --------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Run:
    """``[run]``: identity of the run and the seed of every random choice.

    Attributes
    ----------
    rig : str
        Rig name, default ``"rig1"``. It becomes a Zenoh key segment, so it must be
        non-empty and use only ``A-Z a-z 0-9 _ -``.
    seed : int
        Seed of every random choice of the run (random mistuning, acquisition errors),
        default 0; integer in [0, 2**63 - 1]. The same scenario and seed give the same run.
    """

    rig: str = field(default="rig1", metadata=_doc(
        "rig name, used as a Zenoh key segment: non-empty, only A-Z a-z 0-9 _ -"))
    seed: int = field(default=0, metadata=_doc(
        "seed of every random choice (random mistuning, acquisition errors); integer in [0, 2**63 - 1]"))

    def __post_init__(self) -> None:
        w = "[run]"
        rig = _string(w, "rig", self.rig)
        if not _RIG_RE.fullmatch(rig):
            raise _FieldError(w, "rig", "must be non-empty and use only letters, digits, "
                              f"'_' and '-', got {_show(rig)}")
        _set(self, "rig", rig)
        _set(self, "seed", _integer(w, "seed", self.seed, lo=0, hi=MAX_SEED))


@dataclass(frozen=True, slots=True)
class Rotor:
    """``[rotor]``: geometry of the built-in bladed disk and its tip section.

    The tip chord runs from the leading edge (LE) at axial position z = 0 to the trailing
    edge (TE) at z = ``tip_chord_m * sin(stagger_deg)``. The tip nodes lie on the chord,
    ``tip_node_spacing_m`` apart, starting at the TE.

    Attributes
    ----------
    n_blades : int
        Number of blades, default 29 (the paper's rotor); integer in [2, 200]
        (:data:`~bttsim_stream.defaults.MAX_BLADES`: the built-in model's memory grows as
        ``n_families * n_blades**2``).
    tip_radius_m : float
        Blade tip radius, m, default 0.19; in (0, 10]; the built-in model also needs it
        beyond its rim (0.115 m). Our choice (the first compressor stage of
        a small turbojet): the paper does not give it.
    stagger_deg : float
        Tip stagger angle eta_tip, deg: angle of the tip chord from the tangential
        direction. Default 41.5; in (0, 90).
    tip_chord_m : float
        Chord length of the tip section, m, default 0.0202523; > 0 and at most
        ``tip_radius_m``.
    n_tip_nodes : int
        Number of tip nodes along the chord, default 9; integer in [2, 100].
    tip_node_spacing_m : float
        Spacing of the tip nodes along the chord, m, starting at the TE; default
        0.0004375; > 0. The nodes must fit on the chord:
        ``(n_tip_nodes - 1) * tip_node_spacing_m <= tip_chord_m``.
    nominal_node : int
        The nominal tip node P_nom, counted from the TE (TE node = 1). Default 5 (the
        paper's P_nom, 1.75 mm from the TE); integer in [1, n_tip_nodes].
    """

    n_blades: int = field(default=29, metadata=_doc(
        "number of blades (the paper's rotor has 29); integer in [2, 200]"))
    tip_radius_m: float = field(default=0.19, metadata=_doc(
        "blade tip radius, m; in (0, 10] (our choice, small turbojet 1st compressor stage)"))
    stagger_deg: float = field(default=41.5, metadata=_doc(
        "tip stagger eta_tip, deg: tip chord angle from the tangential direction; in (0, 90)"))
    tip_chord_m: float = field(default=0.0202523, metadata=_doc(
        "tip chord length, m; in (0, tip_radius_m]. LE at z = 0, TE at z = tip_chord_m * sin(stagger)"))
    n_tip_nodes: int = field(default=9, metadata=_doc(
        "number of tip nodes along the chord; integer in [2, 100]"))
    tip_node_spacing_m: float = field(default=0.0004375, metadata=_doc(
        "tip node spacing along the chord from the TE, m; > 0;\n"
        "(n_tip_nodes - 1) * tip_node_spacing_m <= tip_chord_m"))
    nominal_node: int = field(default=5, metadata=_doc(
        "nominal node P_nom counted from the TE (TE node = 1); in [1, n_tip_nodes]"))

    def __post_init__(self) -> None:
        w = "[rotor]"
        _set(self, "n_blades", _integer(w, "n_blades", self.n_blades, lo=2, hi=MAX_BLADES))
        _set(self, "tip_radius_m", _real(w, "tip_radius_m", self.tip_radius_m, lo=0,
                                         lo_open=True, hi=MAX_TIP_RADIUS_M))
        _set(self, "stagger_deg", _real(w, "stagger_deg", self.stagger_deg, lo=0,
                                        lo_open=True, hi=90, hi_open=True))
        _set(self, "tip_chord_m", _real(w, "tip_chord_m", self.tip_chord_m, lo=0,
                                        lo_open=True, hi=self.tip_radius_m))
        _set(self, "n_tip_nodes", _integer(w, "n_tip_nodes", self.n_tip_nodes, lo=2, hi=MAX_TIP_NODES))
        _set(self, "tip_node_spacing_m", _real(w, "tip_node_spacing_m",
                                               self.tip_node_spacing_m, lo=0, lo_open=True))
        _set(self, "nominal_node", _integer(w, "nominal_node", self.nominal_node, lo=1))
        if self.nominal_node > self.n_tip_nodes:
            raise _FieldError(w, "nominal_node", f"must be <= n_tip_nodes = "
                              f"{self.n_tip_nodes}, got {self.nominal_node}")
        span = (self.n_tip_nodes - 1) * self.tip_node_spacing_m
        if span > self.tip_chord_m * (1.0 + 1e-12):
            raise _FieldError(w, "tip_node_spacing_m", f"puts the tip nodes beyond the chord: "
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


@dataclass(frozen=True, slots=True)
class Model:
    """``[model]``: where the modal model comes from, its damping and its mistuning.

    Attributes
    ----------
    source : str
        ``"builtin"`` (default: the parametric bladed disk built from ``[rotor]``) or the
        path of a user's modal model ``.npz``. :func:`load_scenario` resolves a relative
        path against the scenario file's directory; the string is not checked further here.
    damping_beta_s : float
        Stiffness-proportional damping coefficient beta, s, default 9e-6; >= 0. The modal
        damping ratio is zeta = beta * omega / 2.
    n_families : int
        Mode families kept per nodal diameter, default 5 (5 families * 29 blades = 145
        modes); integer in [1, 20].
    disk_asymmetry : bool
        Default false. If true, a small deterministic disk asymmetry splits the
        nodal-diameter mode pairs, as in the paper's scanned disk.
    stiffness_factors : tuple of float
        Per-blade stiffness factors (dimensionless). Empty (default) = none; else exactly
        ``n_blades`` finite values > 0. Exclusive with ``stiffness_std > 0``.
    mass_factors : tuple of float
        Per-blade mass factors, as ``stiffness_factors``. Exclusive with ``mass_std > 0``.
    stiffness_std : float
        Standard deviation of seeded random per-blade stiffness factors 1 + N(0, std),
        dimensionless; default 0.0; in [0, 0.5).
    mass_std : float
        As ``stiffness_std``, for the blade masses.
    centrifugal : bool
        Default false (the paper's zero-speed model). If true, the built-in model gains its
        centrifugal effects (stress stiffening and spin softening; Coriolis neglected): modes
        at ``centrifugal_speeds`` speeds from 0 to ``centrifugal_max_rpm``, tracked across
        speeds (``schemas/modal_model.md``). Only with ``source = "builtin"``; a mistuned or
        asymmetric wheel is solved as a full wheel (slower: seconds).
    centrifugal_speeds : int
        Speeds at which the modes are solved, default 17; integer in [2, 64].
    centrifugal_max_rpm : float
        Highest of those speeds, rpm; default 0.0 = 1.2 times the speed profile's top speed
        (rounded up to 100 rpm); else in [top speed, 1e6].
    """

    source: str = field(default=BUILTIN_MODEL, metadata=_doc(
        '"builtin" (parametric bladed disk from [rotor]) or the path of a modal model .npz\n'
        "(a relative path is relative to this file's directory)"))
    damping_beta_s: float = field(default=9e-6, metadata=_doc(
        "stiffness-proportional damping beta, s; zeta = beta * omega / 2; >= 0"))
    n_families: int = field(default=5, metadata=_doc(
        "mode families kept per nodal diameter (modes = n_families * n_blades); in [1, 20]"))
    disk_asymmetry: bool = field(default=False, metadata=_doc(
        "small deterministic disk asymmetry splitting the nodal-diameter pairs (paper's disk)"))
    stiffness_factors: tuple[float, ...] = field(default=(), metadata=_doc(
        "per-blade stiffness factors: [] = none, else n_blades finite values > 0"))
    mass_factors: tuple[float, ...] = field(default=(), metadata=_doc(
        "per-blade mass factors: [] = none, else n_blades finite values > 0"))
    stiffness_std: float = field(default=0.0, metadata=_doc(
        "std of seeded random per-blade stiffness factors 1 + N(0, std); in [0, 0.5);\n"
        "exclusive with stiffness_factors"))
    mass_std: float = field(default=0.0, metadata=_doc(
        "std of seeded random per-blade mass factors 1 + N(0, std); in [0, 0.5);\n"
        "exclusive with mass_factors"))
    centrifugal: bool = field(default=False, metadata=_doc(
        "speed-dependent modes of the built-in model: centrifugal stiffening and spin\n"
        "softening (Coriolis neglected)"))
    centrifugal_speeds: int = field(default=17, metadata=_doc(
        "speeds at which the modes are solved (0 .. centrifugal_max_rpm); in [2, 64]"))
    centrifugal_max_rpm: float = field(default=0.0, metadata=_doc(
        "highest of those speeds, rpm; 0 = 1.2 x the speed profile's top speed; else >= it"))

    def __post_init__(self) -> None:
        w = "[model]"
        _set(self, "centrifugal", _boolean(w, "centrifugal", self.centrifugal))
        _set(self, "centrifugal_speeds", _integer(w, "centrifugal_speeds", self.centrifugal_speeds, lo=2,
                                                  hi=MAX_MODEL_SPEEDS))
        _set(self, "centrifugal_max_rpm", _real(w, "centrifugal_max_rpm", self.centrifugal_max_rpm, lo=0,
                                                hi=MAX_RPM))
        source = _string(w, "source", self.source)
        if not source:
            raise _FieldError(w, "source", 'must be "builtin" or a file path, got ""')
        _set(self, "source", source)
        _set(self, "damping_beta_s", _real(w, "damping_beta_s", self.damping_beta_s, lo=0))
        _set(self, "n_families", _integer(w, "n_families", self.n_families, lo=1,
                                          hi=MAX_FAMILIES))
        _set(self, "disk_asymmetry", _boolean(w, "disk_asymmetry", self.disk_asymmetry))
        for kind in ("stiffness", "mass"):
            factors = _real_tuple(w, f"{kind}_factors", getattr(self, f"{kind}_factors"),
                                  lo=0, lo_open=True)
            std = _real(w, f"{kind}_std", getattr(self, f"{kind}_std"), lo=0, hi=0.5,
                        hi_open=True)
            if factors and std > 0:
                raise _FieldError(w, f"{kind}_std", f"must be 0 when {kind}_factors is given "
                                  f"(use one or the other), got {_show(std)}")
            _set(self, f"{kind}_factors", factors)
            _set(self, f"{kind}_std", std)


@dataclass(frozen=True, slots=True)
class Speed:
    """``[speed]``: the rotor speed profile.

    By default the paper's linear run-up (Eq. 6) from ``start_rpm`` to ``end_rpm`` in
    ``duration_s``. With ``segments``, a piecewise-linear profile: each segment ramps
    linearly from the previous segment's end speed (the first from ``start_rpm``) to its
    own ``end_rpm`` in its ``duration_s``; a dwell is a segment that keeps the speed.

    Attributes
    ----------
    start_rpm : float
        Speed at t = 0, rpm, default 1000.0; in (0, 1e6].
    end_rpm : float
        Speed at the end of the profile, rpm, default 4000.0; in (0, 1e6]. With ``segments`` it is
        derived (the last segment's ``end_rpm``) and must be absent from the file.
    duration_s : float
        Duration of the profile, s, default 130.0; > 0. With ``segments`` it is derived
        (the sum of the segment durations) and must be absent from the file.
    segments : tuple of (float, float)
        ``(duration_s, end_rpm)`` pairs, default empty (plain ramp). In a file, an array
        of inline tables ``{duration_s = 10.0, end_rpm = 2000.0}``. Durations > 0, speeds
        in (0, 1e6].
        Programmatically, pairs or such mappings are accepted.
    initial : str
        Modal state at t = 0, default ``"steady"``: every mode in its quasi-steady response
        to the forcing (the first segment's sweep extended back in time; at or near a
        resonance too); ``"rest"``: zero displacement and velocity (the free vibration of
        the start is simulated exactly).

    The whole profile makes at most 1,000,000 revolutions
    (:data:`~bttsim_stream.defaults.MAX_REVOLUTIONS`).
    """

    start_rpm: float = field(default=1000.0, metadata=_doc(
        "speed at t = 0, rpm; in (0, 1e6] (paper Eq. 6: linear run-up)"))
    end_rpm: float = field(default=4000.0, metadata=_doc(
        "speed at the end of the run-up, rpm; in (0, 1e6]. Leave out when segments is given"))
    duration_s: float = field(default=130.0, metadata=_doc(
        "duration of the run-up, s; > 0. Leave out when segments is given"))
    segments: tuple[tuple[float, float], ...] = field(default=(), metadata=_doc(
        "piecewise-linear profile: segments from start_rpm, each {duration_s (s, > 0),\n"
        "end_rpm (rpm, in (0, 1e6])}; a dwell keeps end_rpm. Replaces end_rpm and duration_s"))
    initial: str = field(default="steady", metadata=_doc(
        'modal state at t = 0: "steady" (every mode in its quasi-steady forced response,\n'
        'near a resonance too) or "rest" (zero displacement and velocity)'))

    def __post_init__(self) -> None:
        w = "[speed]"
        _set(self, "initial", _string(w, "initial", self.initial, choices=SPEED_INITIAL))
        _set(self, "start_rpm", _real(w, "start_rpm", self.start_rpm, lo=0, lo_open=True, hi=MAX_RPM))
        items = _sequence(w, "segments", self.segments,
                          "an array of {duration_s = ..., end_rpm = ...} tables")
        segments = tuple(_segment(w, f"segments[{i}]", s) for i, s in enumerate(items))
        _set(self, "segments", segments)
        if segments:
            _set(self, "end_rpm", segments[-1][1])
            _set(self, "duration_s", math.fsum(d for d, _ in segments))
        else:
            _set(self, "end_rpm", _real(w, "end_rpm", self.end_rpm, lo=0, lo_open=True, hi=MAX_RPM))
            _set(self, "duration_s", _real(w, "duration_s", self.duration_s, lo=0,
                                           lo_open=True))
        t_s, rpm = self.breakpoints()
        revolutions = math.fsum(0.5 * (a + b) * d for a, b, d in zip(rpm[:-1], rpm[1:], np.diff(t_s))) / 60.0
        if not revolutions <= MAX_REVOLUTIONS:
            raise _FieldError(w, "", f"makes {revolutions:.3g} revolutions, more than the "
                              f"{MAX_REVOLUTIONS:,} of one run: shorten duration_s or the segments")

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


_SEGMENT_KEYS = ("duration_s", "end_rpm")


def _segment(where: str, key: str, value: Any) -> tuple[float, float]:
    """Check one speed segment: a ``{duration_s, end_rpm}`` mapping or a pair."""
    if isinstance(value, Mapping):
        for k in value:
            if k not in _SEGMENT_KEYS:
                raise _FieldError(where, key, f"has unknown key {_key(k)}{_hint(k, _SEGMENT_KEYS)}"
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
    return (_real(where, f"{key}.duration_s", d, lo=0, lo_open=True),
            _real(where, f"{key}.end_rpm", r, lo=0, lo_open=True, hi=MAX_RPM))


@dataclass(frozen=True, slots=True)
class Excitation:
    """``[[excitation]]``: one engine-order force pattern applied at every blade tip.

    Attributes
    ----------
    engine_order : int
        Engine order EO (force cycles per revolution), default 8; integer in [1, 1000].
    nodal_diameter : int
        Nodal diameter ND of the force pattern across the blades (inter-blade phase
        2*pi*ND/n_blades), default 1; integer in [0, n_blades) (checked by
        :class:`Scenario`).
    amplitude_n : float
        Force amplitude per blade, N, default 2.25; >= 0.
    direction : tuple of float
        Force direction as 3 components in the local (radial, tangential, axial) frame at
        the force node, default (0, 0, 1). Finite, not all zero; stored as given and
        normalised at use.
    node : str
        The tip-section edge where the force is applied: ``"leading_edge"`` (default) or
        ``"trailing_edge"``.
    """

    engine_order: int = field(default=8, metadata=_doc(
        "engine order EO (force cycles per revolution); integer in [1, 1000]"))
    nodal_diameter: int = field(default=1, metadata=_doc(
        "nodal diameter ND of the force pattern (inter-blade phase 2*pi*ND/n_blades);\n"
        "integer in [0, n_blades)"))
    amplitude_n: float = field(default=2.25, metadata=_doc(
        "force amplitude per blade, N; >= 0"))
    direction: tuple[float, float, float] = field(default=(0.0, 0.0, 1.0), metadata=_doc(
        "force direction (radial, tangential, axial) at the force node; 3 finite\n"
        "components, not all zero; normalised at use"))
    node: str = field(default="leading_edge", metadata=_doc(
        'tip-section edge where the force is applied: "leading_edge" or "trailing_edge"'))

    def __post_init__(self) -> None:
        w = "[[excitation]]"
        _set(self, "engine_order", _integer(w, "engine_order", self.engine_order, lo=1,
                                                   hi=MAX_ENGINE_ORDER))
        _set(self, "nodal_diameter", _integer(w, "nodal_diameter", self.nodal_diameter, lo=0))
        _set(self, "amplitude_n", _real(w, "amplitude_n", self.amplitude_n, lo=0))
        direction = _real_tuple(w, "direction", self.direction)
        if len(direction) != 3:
            raise _FieldError(w, "direction", "must have 3 components (radial, tangential, "
                              f"axial), got {len(direction)}")
        if not any(direction):
            raise _FieldError(w, "direction", "must not be the zero vector")
        _set(self, "direction", direction)
        _set(self, "node", _string(w, "node", self.node, choices=FORCE_NODES))


@dataclass(frozen=True, slots=True)
class Probes:
    """``[probes]``: the BTT probes and the once-per-revolution (OPR) sensor.

    Angles are anticlockwise from +x seen from +z, like the rotation.

    Attributes
    ----------
    angles_deg : tuple of float
        Probe angular positions, deg, default (5.0, 15.15, 23.82, 220.0, 301.5) (the
        paper's); 1 to 64 distinct finite values in [0, 360).
    axial_position_m : float
        Axial position z_j of the probes, m, default 0.01226; within the tip chord's
        axial extent [0, ``tip_chord_m * sin(stagger_deg)``] (checked by
        :class:`Scenario`).
    opr_angle_deg : float
        Angular position of the OPR sensor, deg, default 0.0; in [0, 360).
    """

    angles_deg: tuple[float, ...] = field(default=(5.0, 15.15, 23.82, 220.0, 301.5),
                                          metadata=_doc(
        "probe angular positions, deg, anticlockwise from +x; 1 to 64 distinct values\n"
        "in [0, 360)"))
    axial_position_m: float = field(default=0.01226, metadata=_doc(
        "probe axial position z_j, m; within the tip chord's axial extent\n"
        "[0, tip_chord_m * sin(stagger_deg)]"))
    opr_angle_deg: float = field(default=0.0, metadata=_doc(
        "once-per-revolution (OPR) sensor angle, deg; in [0, 360)"))

    def __post_init__(self) -> None:
        w = "[probes]"
        angles = _real_tuple(w, "angles_deg", self.angles_deg, lo=0, hi=360, hi_open=True)
        if not 1 <= len(angles) <= MAX_PROBES:
            raise _FieldError(w, "angles_deg", f"must hold 1 to {MAX_PROBES} angles, "
                              f"got {len(angles)}")
        first: dict[float, int] = {}
        for i, a in enumerate(angles):
            if a in first:
                raise _FieldError(w, f"angles_deg[{i}]", f"duplicates angles_deg[{first[a]}] "
                                  f"({_show(a)})")
            first[a] = i
        _set(self, "angles_deg", angles)
        _set(self, "axial_position_m", _real(w, "axial_position_m", self.axial_position_m))
        _set(self, "opr_angle_deg", _real(w, "opr_angle_deg", self.opr_angle_deg, lo=0,
                                          hi=360, hi_open=True))


@dataclass(frozen=True, slots=True)
class Toa:
    """``[toa]``: how times of arrival (TOAs) are computed (paper Sec. 2.2).

    Attributes
    ----------
    method : str
        TOA method of the paper's Sec. 2.2: ``"HP"`` (default), ``"AD"`` or ``"PAD"``.
    grid_step_s : float
        Step of the integrator time grid used for the AD/PAD interpolation, s, default
        1.2e-5; > 0.
    axial_interpolation : bool
        Default true: interpolate between the tip nodes at the probe's z. False: use the
        nearest node (reproduces the paper's Fig. 7).
    """

    method: str = field(default="HP", metadata=_doc(
        'TOA method (paper Sec. 2.2): "HP", "AD" or "PAD"'))
    grid_step_s: float = field(default=1.2e-5, metadata=_doc(
        "integrator time grid step for the AD/PAD interpolation, s; > 0"))
    axial_interpolation: bool = field(default=True, metadata=_doc(
        "true: interpolate between tip nodes at the probe z; false: nearest node (Fig. 7)"))

    def __post_init__(self) -> None:
        w = "[toa]"
        _set(self, "method", _string(w, "method", self.method, choices=TOA_METHODS))
        _set(self, "grid_step_s", _real(w, "grid_step_s", self.grid_step_s, lo=0,
                                        lo_open=True))
        _set(self, "axial_interpolation", _boolean(w, "axial_interpolation",
                                                   self.axial_interpolation))


SIGNAL_PROBES = ("optical", "capacitive")
SIGNAL_TRIGGERS = ("threshold", "constant_fraction", "peak")
SIGNAL_EDGES = ("rising", "falling")
MAX_WINDOW_SAMPLES = 4096


def _choices(where: str, key: str, value: Any, choices: Sequence[str]) -> str | tuple[str, ...]:
    """One of ``choices``, or an array of them (one per probe, checked by :class:`Scenario`)."""
    if isinstance(value, str):
        return _string(where, key, value, choices=choices)
    items = _sequence(where, key, value, "a string or an array of strings (one per probe)")
    if not items:
        raise _FieldError(where, key, "must not be an empty array")
    return tuple(_string(where, f"{key}[{i}]", v, choices=choices) for i, v in enumerate(items))


@dataclass(frozen=True, slots=True)
class Signal:
    """``[acquisition.signal]``: probe signals, digitisation and triggers (off by default).

    When ``enabled``, every published TOA comes out of the chain of
    :mod:`bttsim_stream.sim.signal` (probe pulse around the exact passage, front-end
    low-pass, noise, ADC, trigger, counter clock) instead of the exact TOA plus
    ``trigger_jitter_s``; the truth keeps the exact TOA of the same passage. A pulse that
    does not trigger is a missing TOA (NaN).

    Attributes
    ----------
    enabled : bool
        Default false.
    probe_type : str or tuple of str
        ``"optical"`` (default) or ``"capacitive"``; one value for every probe or one per probe.
    trigger : str or tuple of str
        ``"threshold"`` (default), ``"constant_fraction"`` or ``"peak"``; one or one per probe.
    edge : str
        Threshold trigger edge, ``"rising"`` (default) or ``"falling"``.
    level_v, hysteresis_v : float
        Trigger level (arming level of constant fraction and peak), V, default 0.5, and the
        threshold trigger's hysteresis, V, default 0.05; the level within the ADC range.
    fraction : float
        Constant fraction, default 0.5; in (0, 1).
    spot_diameter_m, electrode_diameter_m : float
        Optical 1/e^2 spot diameter (default 0.5 mm) and capacitive electrode diameter
        (default 1.5 mm), m; in (0, 0.05].
    tip_thickness_m : float
        Tangential width of the tip at the probe, m, default 1 mm; in (0, 0.05].
    clearance_m : float
        Cold tip clearance, m, default 0.5 mm; in (0, 0.05], larger than the centrifugal growth.
    reference_clearance_m : float
        Clearance at which the capacitive pulse height scale is ``height_v``, m, default 0.5 mm;
        in (0, 0.05] (the height falls as ``1 / clearance``).
    height_v : float
        Pulse height scale, V, default 1.0; > 0.
    fringe_factor : float
        Capacitive kernel spreading with clearance, default 0.5; in [0, 10].
    bandwidth_hz : float
        Front-end bandwidth, Hz, default 1e6; 0 = unlimited.
    sample_rate_hz : float
        ADC sample rate, Hz, default 2e6; in [1e5, 1e9].
    bits : int
        ADC resolution, default 12; in [4, 24].
    range_lo_v, range_hi_v : float
        ADC input range, V, default -0.5 .. 1.5.
    noise_v, lf_noise_v : float
        rms of the band-limited white noise (default 0.005 V) and of the low-frequency noise
        (default 0), V; >= 0.
    lf_corner_hz : float
        Highest frequency of the low-frequency noise, Hz, default 10; > 0.
    offset_v, offset_drift_v_per_s, gain_drift_per_s : float
        Baseline offset, V, its drift, V/s, and the relative gain drift, 1/s; default 0.
    density_kg_m3, youngs_modulus_pa : float
        Rotor material for the centrifugal tip growth ``rho Omega^2 R^3 / (3 E)``; default
        titanium, 4430 kg/m^3 and 1.14e11 Pa.
    publish : bool
        Also publish the digitised windows on ``bttsim/<rig>/signal/<probe>``
        (``bttsim.v1.SignalBatch``); default false.
    """

    enabled: bool = field(default=False, metadata=_doc(
        "true: TOAs come from probe signals and triggers (truth keeps the exact TOAs)"))
    probe_type: Any = field(default="optical", metadata=_doc(
        '"optical" or "capacitive"; one value, or an array with one per probe'))
    trigger: Any = field(default="threshold", metadata=_doc(
        '"threshold", "constant_fraction" or "peak"; one value, or an array with one per probe'))
    edge: str = field(default="rising", metadata=_doc('threshold trigger edge: "rising" or "falling"'))
    level_v: float = field(default=0.5, metadata=_doc(
        "trigger level (arming level of constant_fraction and peak), V; within the ADC range"))
    hysteresis_v: float = field(default=0.05, metadata=_doc("threshold trigger hysteresis, V; >= 0"))
    fraction: float = field(default=0.5, metadata=_doc("constant fraction; in (0, 1)"))
    spot_diameter_m: float = field(default=0.5e-3, metadata=_doc(
        "optical probe 1/e^2 spot diameter, m; in (0, 0.05]"))
    electrode_diameter_m: float = field(default=1.5e-3, metadata=_doc(
        "capacitive probe electrode diameter, m; in (0, 0.05]"))
    tip_thickness_m: float = field(default=1.0e-3, metadata=_doc(
        "tangential width of the blade tip at the probe, m; in (0, 0.05]"))
    clearance_m: float = field(default=0.5e-3, metadata=_doc(
        "cold tip clearance, m; in (0, 0.05], above the centrifugal growth"))
    reference_clearance_m: float = field(default=0.5e-3, metadata=_doc(
        "clearance at which the capacitive pulse height scale is height_v, m; in (0, 0.05]"))
    height_v: float = field(default=1.0, metadata=_doc(
        "pulse height scale, V (capacitive: at reference_clearance_m, falls as 1 / clearance); > 0"))
    fringe_factor: float = field(default=0.5, metadata=_doc(
        "capacitive field spreading with clearance (kernel sigma^2 = (D/4)^2 + (k g)^2); in [0, 10]"))
    bandwidth_hz: float = field(default=1.0e6, metadata=_doc(
        "front-end bandwidth (first-order low-pass), Hz; 0 = unlimited"))
    sample_rate_hz: float = field(default=2.0e6, metadata=_doc("ADC sample rate, Hz; in [1e5, 1e9]"))
    bits: int = field(default=12, metadata=_doc("ADC resolution, bits; in [4, 24]"))
    range_lo_v: float = field(default=-0.5, metadata=_doc("ADC input range low end, V"))
    range_hi_v: float = field(default=1.5, metadata=_doc("ADC input range high end, V; > range_lo_v"))
    noise_v: float = field(default=0.005, metadata=_doc(
        "rms of the white noise at the ADC input (band-limited by the front end), V; >= 0"))
    lf_noise_v: float = field(default=0.0, metadata=_doc("rms of the low-frequency noise, V; >= 0"))
    lf_corner_hz: float = field(default=10.0, metadata=_doc(
        "highest frequency of the low-frequency noise, Hz; > 0"))
    offset_v: float = field(default=0.0, metadata=_doc("baseline offset, V"))
    offset_drift_v_per_s: float = field(default=0.0, metadata=_doc("baseline drift, V/s"))
    gain_drift_per_s: float = field(default=0.0, metadata=_doc("relative gain drift, 1/s"))
    density_kg_m3: float = field(default=4430.0, metadata=_doc(
        "rotor density for the centrifugal tip growth, kg/m^3; > 0"))
    youngs_modulus_pa: float = field(default=1.14e11, metadata=_doc(
        "rotor Young's modulus for the centrifugal tip growth, Pa; > 0"))
    publish: bool = field(default=False, metadata=_doc(
        "true: also publish the raw windows (ADC codes) on bttsim/<rig>/signal/<probe>"))

    def __post_init__(self) -> None:
        w = "[acquisition.signal]"
        _set(self, "enabled", _boolean(w, "enabled", self.enabled))
        _set(self, "publish", _boolean(w, "publish", self.publish))
        if self.publish and not self.enabled:  # asked for signals that would never come
            raise _FieldError(w, "publish", "= true needs enabled = true (no signal is synthesised with the "
                              "chain off)")
        _set(self, "probe_type", _choices(w, "probe_type", self.probe_type, SIGNAL_PROBES))
        _set(self, "trigger", _choices(w, "trigger", self.trigger, SIGNAL_TRIGGERS))
        _set(self, "edge", _string(w, "edge", self.edge, choices=SIGNAL_EDGES))
        _set(self, "bits", _integer(w, "bits", self.bits, lo=4, hi=24))
        bounds = {"fraction": dict(lo=0, lo_open=True, hi=1, hi_open=True),
                  "sample_rate_hz": dict(lo=1e5, hi=1e9), "fringe_factor": dict(lo=0, hi=10),
                  "lf_corner_hz": dict(lo=0, lo_open=True, hi=1e6)}
        for name in ("spot_diameter_m", "electrode_diameter_m", "tip_thickness_m", "clearance_m",
                     "reference_clearance_m"):
            bounds[name] = dict(lo=0, lo_open=True, hi=0.05)
        for name in ("height_v", "density_kg_m3", "youngs_modulus_pa"):
            bounds[name] = dict(lo=0, lo_open=True)
        for name in ("hysteresis_v", "noise_v", "lf_noise_v", "bandwidth_hz"):
            bounds[name] = dict(lo=0)
        for f in dataclasses.fields(self):
            if f.name not in ("enabled", "probe_type", "trigger", "edge", "bits", "publish"):
                _set(self, f.name, _real(w, f.name, getattr(self, f.name), **bounds.get(f.name, {})))
        if not self.range_hi_v > self.range_lo_v:
            raise _FieldError(w, "range_hi_v", f"must be above range_lo_v = {_show(self.range_lo_v)}, "
                              f"got {_show(self.range_hi_v)}")
        if not self.range_lo_v < self.level_v < self.range_hi_v:
            raise _FieldError(w, "level_v", f"must lie inside the ADC range ({_show(self.range_lo_v)}, "
                              f"{_show(self.range_hi_v)}), got {_show(self.level_v)}")


@dataclass(frozen=True, slots=True)
class Acquisition:
    """``[acquisition]``: errors of the acquisition system; all off (0) by default.

    Attributes
    ----------
    clock_hz : float
        TOA counter clock, Hz. 0 (default) = no quantisation; else in [1e3, 1e12] and the
        TOAs are whole ticks of this clock (which must count the whole run in 62 bits).
    trigger_jitter_s : float
        Standard deviation of a Gaussian jitter on each TOA, s; >= 0 and at most 1 % of the
        shortest revolution period (checked by :class:`Scenario`).
    probe_angle_error_deg : float
        Standard deviation of static random errors of the probe angular positions, deg
        (drawn once per run); in [0, 5].
    opr_jitter_s : float
        Standard deviation of a Gaussian jitter on each OPR timestamp, s; as
        ``trigger_jitter_s``.
    speed_fluctuation_rpm : float
        Standard deviation of a random speed fluctuation about the speed profile, rpm;
        >= 0 and at most 10 % of the slowest speed (checked by :class:`Scenario`).
    signal : Signal
        ``[acquisition.signal]``: the probe signal and trigger chain (off by default).
    """

    clock_hz: float = field(default=0.0, metadata=_doc(
        "TOA counter clock, Hz; 0 = no quantisation, else in [1e3, 1e12] (TOAs become whole ticks)"))
    trigger_jitter_s: float = field(default=0.0, metadata=_doc(
        "std of the Gaussian jitter on each TOA, s; >= 0, at most 1 % of the shortest revolution"))
    probe_angle_error_deg: float = field(default=0.0, metadata=_doc(
        "std of static random probe angular position errors, deg; in [0, 5]"))
    opr_jitter_s: float = field(default=0.0, metadata=_doc(
        "std of the Gaussian jitter on each OPR timestamp, s; >= 0, at most 1 % of the shortest\nrevolution"))
    speed_fluctuation_rpm: float = field(default=0.0, metadata=_doc(
        "std of the random speed fluctuation about the speed profile, rpm; >= 0, at most 10 %\nof the slowest speed"))
    signal: Signal = field(default_factory=Signal, metadata=_doc(
        "the probe signal and trigger chain: the [acquisition.signal] table"))

    def __post_init__(self) -> None:
        w = "[acquisition]"
        if isinstance(self.signal, Mapping):
            _check_keys("[acquisition.signal]", self.signal, Signal)
            _set(self, "signal", Signal(**self.signal))
        elif not isinstance(self.signal, Signal):
            raise _FieldError(w, "signal", f"must be a table ([acquisition.signal]), {_got(self.signal)}")
        for f in dataclasses.fields(self):
            if f.name == "signal":
                continue
            _set(self, f.name, _real(w, f.name, getattr(self, f.name), lo=0,
                                     hi=MAX_PROBE_ANGLE_ERROR_DEG if f.name == "probe_angle_error_deg" else None))
        if self.clock_hz and not MIN_CLOCK_HZ <= self.clock_hz <= MAX_CLOCK_HZ:
            raise _FieldError(w, "clock_hz", f"must be 0 (no quantisation) or in [{_num(MIN_CLOCK_HZ)}, "
                              f"{_num(MAX_CLOCK_HZ)}], got {_show(self.clock_hz)}")


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

    Attributes
    ----------
    cells : int
        Number of stall cells (lobes) ``N_s``, default 5; integer in [1, 1000].
    speed_fraction : float
        Cell speed in the stationary frame over the shaft speed ``r``, default 0.5; in [0, 1).
    frequency_hz : float
        Stationary-frame frequency ``f_s`` of the pattern, Hz, default 0 (off: the cells follow
        ``speed_fraction``); > 0 replaces ``speed_fraction``.
    amplitude_n : float
        Force amplitude per blade, N, default 0.5; >= 0.
    direction : tuple of float
        As :class:`Excitation`, default (0, 0, 1).
    node : str
        As :class:`Excitation`, default ``"leading_edge"``.
    """

    cells: int = field(default=5, metadata=_doc("number of stall cells (lobes) N_s; integer in [1, 1000]"))
    speed_fraction: float = field(default=0.5, metadata=_doc(
        "cell speed in the stationary frame over the shaft speed; in [0, 1)"))
    frequency_hz: float = field(default=0.0, metadata=_doc(
        "stationary-frame frequency of the pattern, Hz; 0: off (cells follow speed_fraction);\n"
        "> 0 replaces speed_fraction"))
    amplitude_n: float = field(default=0.5, metadata=_doc("force amplitude per blade, N; >= 0"))
    direction: tuple[float, float, float] = field(default=(0.0, 0.0, 1.0), metadata=_doc(
        "force direction (radial, tangential, axial) at the force node; normalised at use"))
    node: str = field(default="leading_edge", metadata=_doc(
        'tip-section edge where the force is applied: "leading_edge" or "trailing_edge"'))

    def __post_init__(self) -> None:
        w = "[[rotating_stall]]"
        _set(self, "cells", _integer(w, "cells", self.cells, lo=1, hi=MAX_ENGINE_ORDER))
        _set(self, "speed_fraction", _real(w, "speed_fraction", self.speed_fraction, lo=0, hi=1, hi_open=True))
        _set(self, "frequency_hz", _real(w, "frequency_hz", self.frequency_hz, lo=0, hi=1e6))
        _set(self, "amplitude_n", _real(w, "amplitude_n", self.amplitude_n, lo=0))
        _set(self, "direction", _direction(w, self.direction))
        _set(self, "node", _string(w, "node", self.node, choices=FORCE_NODES))


@dataclass(frozen=True, slots=True)
class Flutter:
    """``[flutter]``: a self-excited travelling wave of one mode family and nodal diameter
    (off by default).

    Negative aerodynamic damping ``aero_damping_ratio`` beyond the mode's structural damping
    makes the wave grow from ``seed_amplitude_m`` at the onset (``start_s``, or the first time
    the speed reaches ``start_rpm``) to ``limit_amplitude_m`` along the logistic law of the
    averaged Van der Pol oscillator, at the mode's damped frequency
    (:mod:`bttsim_stream.sim.nsv`). Amplitudes are peak-to-peak ``d_eqv`` at P_nom of the
    blade with the largest.

    Attributes
    ----------
    enabled : bool
        Default false.
    family : int
        Mode family, 1-based (1: first bending), default 1; in [1, 20].
    nodal_diameter : int
        Signed nodal diameter: > 0 forward, < 0 backward travelling wave (the sign convention of
        :mod:`bttsim_stream.process.travelling_wave`), default 3; ``|nd| <= n_blades / 2``.
    start_s : float
        Onset time, s, default 0; >= 0 (used when ``start_rpm`` is 0).
    start_rpm : float
        Onset speed, rpm, default 0 (off); > 0: the first time the speed profile reaches it.
    aero_damping_ratio : float
        Aerodynamic (negative) damping ratio ``zeta_aero``, default 0.02; in (0, 1); must
        exceed the mode's structural damping ratio.
    limit_amplitude_m : float
        Limit-cycle amplitude, m pk-pk, default 2e-4; > 0.
    seed_amplitude_m : float
        Amplitude at onset, m pk-pk, default 1e-9; in (0, limit_amplitude_m).
    phase_deg : float
        Phase of the wave at onset, deg, default 0.
    """

    enabled: bool = field(default=False, metadata=_doc("simulate a flutter travelling wave"))
    family: int = field(default=1, metadata=_doc("mode family, 1-based (1: first bending); integer in [1, 20]"))
    nodal_diameter: int = field(default=3, metadata=_doc(
        "signed nodal diameter: > 0 forward, < 0 backward travelling wave; |nd| <= n_blades / 2"))
    start_s: float = field(default=0.0, metadata=_doc("onset time, s; >= 0 (when start_rpm is 0)"))
    start_rpm: float = field(default=0.0, metadata=_doc(
        "onset speed, rpm; 0: off, > 0: the first time the speed profile reaches it"))
    aero_damping_ratio: float = field(default=0.02, metadata=_doc(
        "negative aerodynamic damping ratio; in (0, 1), above the mode's structural damping"))
    limit_amplitude_m: float = field(default=2e-4, metadata=_doc(
        "limit-cycle amplitude, m pk-pk (d_eqv at P_nom); > 0"))
    seed_amplitude_m: float = field(default=1e-9, metadata=_doc(
        "amplitude at onset, m pk-pk; in (0, limit_amplitude_m)"))
    phase_deg: float = field(default=0.0, metadata=_doc("phase of the wave at onset, deg"))

    def __post_init__(self) -> None:
        w = "[flutter]"
        _set(self, "enabled", _boolean(w, "enabled", self.enabled))
        _set(self, "family", _integer(w, "family", self.family, lo=1, hi=MAX_FAMILIES))
        _set(self, "nodal_diameter", _integer(w, "nodal_diameter", self.nodal_diameter))
        _set(self, "start_s", _real(w, "start_s", self.start_s, lo=0))
        _set(self, "start_rpm", _real(w, "start_rpm", self.start_rpm, lo=0, hi=MAX_RPM))
        _set(self, "aero_damping_ratio", _real(w, "aero_damping_ratio", self.aero_damping_ratio, lo=0, lo_open=True,
                                               hi=1, hi_open=True))
        _set(self, "limit_amplitude_m", _real(w, "limit_amplitude_m", self.limit_amplitude_m, lo=0, lo_open=True))
        _set(self, "seed_amplitude_m", _real(w, "seed_amplitude_m", self.seed_amplitude_m, lo=0, lo_open=True,
                                             hi=self.limit_amplitude_m, hi_open=True))
        _set(self, "phase_deg", _real(w, "phase_deg", self.phase_deg))


@dataclass(frozen=True, slots=True)
class Broadband:
    """``[broadband]``: random blade forcing with a flat force spectrum in a band (off by
    default).

    Realised as ``n_lines`` sinusoids at the centres of equal sub-bands of ``band_hz``, each
    of amplitude ``sqrt(2 psd_n2_per_hz df)`` per blade with a random phase per blade and line
    (seeded by ``[run] seed``): every line is an exact carrier of the envelope recursion, so
    the cost grows with ``n_lines`` like as many excitations (:mod:`bttsim_stream.sim.nsv`).

    Attributes
    ----------
    enabled : bool
        Default false.
    band_hz : tuple of float
        ``(low, high)``, Hz, default (300, 400); 0 < low < high <= 1e5.
    psd_n2_per_hz : float
        One-sided force PSD per blade, N^2/Hz, default 1e-4; >= 0.
    n_lines : int
        Number of lines, default 16; in [1, 256].
    direction : tuple of float
        As :class:`Excitation`, default (0, 0, 1).
    node : str
        As :class:`Excitation`, default ``"leading_edge"``.
    """

    enabled: bool = field(default=False, metadata=_doc("simulate broadband (random) blade forcing"))
    band_hz: tuple[float, float] = field(default=(300.0, 400.0), metadata=_doc(
        "frequency band [low, high] of the force spectrum, Hz; 0 < low < high <= 1e5"))
    psd_n2_per_hz: float = field(default=1e-4, metadata=_doc("one-sided force PSD per blade, N^2/Hz; >= 0"))
    n_lines: int = field(default=16, metadata=_doc(
        "sinusoids realising the spectrum (random phase per blade and line); in [1, 256]"))
    direction: tuple[float, float, float] = field(default=(0.0, 0.0, 1.0), metadata=_doc(
        "force direction (radial, tangential, axial) at the force node; normalised at use"))
    node: str = field(default="leading_edge", metadata=_doc(
        'tip-section edge where the force is applied: "leading_edge" or "trailing_edge"'))

    def __post_init__(self) -> None:
        w = "[broadband]"
        _set(self, "enabled", _boolean(w, "enabled", self.enabled))
        band = _real_tuple(w, "band_hz", self.band_hz, lo=0, lo_open=True, hi=1e5)
        if len(band) != 2 or not band[0] < band[1]:
            raise _FieldError(w, "band_hz", f"must be [low, high] with low < high, got {_show(list(band))}")
        _set(self, "band_hz", band)
        _set(self, "psd_n2_per_hz", _real(w, "psd_n2_per_hz", self.psd_n2_per_hz, lo=0))
        _set(self, "n_lines", _integer(w, "n_lines", self.n_lines, lo=1, hi=256))
        _set(self, "direction", _direction(w, self.direction))
        _set(self, "node", _string(w, "node", self.node, choices=FORCE_NODES))


def _direction(w: str, value: Any) -> tuple[float, ...]:
    direction = _real_tuple(w, "direction", value)
    if len(direction) != 3:
        raise _FieldError(w, "direction", f"must have 3 components (radial, tangential, axial), got {len(direction)}")
    if not any(direction):
        raise _FieldError(w, "direction", "must not be the zero vector")
    return direction


def _default_excitation() -> tuple[Excitation, ...]:
    return (Excitation(),)


@dataclass(frozen=True, slots=True)
class Scenario:
    """A whole scenario: one instance of each section, and the checks across sections.

    Attributes
    ----------
    run : Run
        ``[run]``.
    rotor : Rotor
        ``[rotor]``.
    model : Model
        ``[model]``.
    speed : Speed
        ``[speed]``.
    excitation : tuple of Excitation
        ``[[excitation]]``: at least one entry; default one :class:`Excitation`.
    probes : Probes
        ``[probes]``.
    toa : Toa
        ``[toa]``.
    acquisition : Acquisition
        ``[acquisition]``.
    rotating_stall : tuple of RotatingStall
        ``[[rotating_stall]]``: default none.
    flutter : Flutter
        ``[flutter]``: default off.
    broadband : Broadband
        ``[broadband]``: default off.

    Notes
    -----
    Cross-section checks: each ``nodal_diameter < n_blades``; the probes' axial position
    within ``[0, rotor.tip_axial_extent_m]`` with the built-in model (a user's model: within
    its tip nodes, checked by the simulator once the model is loaded); non-empty mistuning
    factor lists hold
    ``n_blades`` values.
    """

    run: Run = field(default_factory=Run)
    rotor: Rotor = field(default_factory=Rotor)
    model: Model = field(default_factory=Model)
    speed: Speed = field(default_factory=Speed)
    excitation: tuple[Excitation, ...] = field(default_factory=_default_excitation)
    probes: Probes = field(default_factory=Probes)
    toa: Toa = field(default_factory=Toa)
    acquisition: Acquisition = field(default_factory=Acquisition)
    rotating_stall: tuple[RotatingStall, ...] = ()
    flutter: Flutter = field(default_factory=Flutter)
    broadband: Broadband = field(default_factory=Broadband)

    def __post_init__(self) -> None:
        stall = self.rotating_stall
        if isinstance(stall, RotatingStall) or not isinstance(stall, (list, tuple)):
            raise _FieldError("[[rotating_stall]]", "", "must be a sequence of RotatingStall, "
                              f"got {type(stall).__name__}")
        for i, e in enumerate(stall):
            if not isinstance(e, RotatingStall):
                raise _FieldError(f"[[rotating_stall]][{i}]", "", f"must be a RotatingStall, got {type(e).__name__}")
        _set(self, "rotating_stall", tuple(stall))
        if 2 * abs(self.flutter.nodal_diameter) > self.rotor.n_blades:
            raise _FieldError("[flutter]", "nodal_diameter", f"must be within +-[rotor] n_blades / 2 = "
                              f"{self.rotor.n_blades / 2:g}, got {self.flutter.nodal_diameter}")
        if self.flutter.enabled and self.flutter.start_rpm > 0:
            _, rpm = self.speed.breakpoints()
            if not float(np.min(rpm)) <= self.flutter.start_rpm <= float(np.max(rpm)):
                raise _FieldError("[flutter]", "start_rpm", f"must lie within the speed profile "
                                  f"({float(np.min(rpm)):g} .. {float(np.max(rpm)):g} rpm), got {_show(self.flutter.start_rpm)}")
        if self.flutter.enabled and self.flutter.start_rpm == 0 and self.flutter.start_s >= self.speed.duration_s:
            raise _FieldError("[flutter]", "start_s", f"must be before the end of the run ({self.speed.duration_s:g} s), "
                              f"got {_show(self.flutter.start_s)}")
        for name, cls in SECTIONS.items():
            if name == "excitation":
                continue
            value = getattr(self, name)
            if not isinstance(value, cls):
                raise _FieldError(f"[{name}]", "", f"must be a {cls.__name__}, "
                                  f"got {type(value).__name__}")
        exc = self.excitation
        if isinstance(exc, Excitation) or not isinstance(exc, (list, tuple)):
            raise _FieldError("[[excitation]]", "", "must be a sequence of Excitation, "
                              f"got {type(exc).__name__}")
        exc = tuple(exc)
        if not exc:
            raise _FieldError("[[excitation]]", "", "must have at least one entry, got none")
        for i, e in enumerate(exc):
            if not isinstance(e, Excitation):
                raise _FieldError(f"[[excitation]][{i}]", "", "must be an Excitation, "
                                  f"got {type(e).__name__}")
        _set(self, "excitation", exc)

        n = self.rotor.n_blades
        for i, e in enumerate(exc):
            if e.nodal_diameter >= n:
                raise _FieldError(f"[[excitation]][{i}]", "nodal_diameter",
                                  f"must be < [rotor] n_blades = {n}, got {e.nodal_diameter}")
        z, z_max = self.probes.axial_position_m, self.rotor.tip_axial_extent_m
        # a user's model has its own tip nodes: the simulator checks z against them
        if self.model.source == "builtin" and not 0.0 <= z <= z_max:
            raise _FieldError("[probes]", "axial_position_m", "must lie within the tip "
                              f"chord's axial extent [0, {z_max:.6g}] m ([rotor] tip_chord_m * "
                              f"sin(stagger_deg)), got {_show(z)}")
        self._check_centrifugal()
        for kind in ("stiffness_factors", "mass_factors"):
            factors = getattr(self.model, kind)
            if factors and len(factors) != n:
                raise _FieldError("[model]", kind, f"must hold [rotor] n_blades = {n} values "
                                  f"(or be empty), got {len(factors)}")
        acq, (_, rpm) = self.acquisition, self.speed.breakpoints()
        shortest = 60.0 / float(np.max(rpm))  # s, the shortest revolution
        for name in ("trigger_jitter_s", "opr_jitter_s"):
            if getattr(acq, name) > 0.01 * shortest:
                raise _FieldError("[acquisition]", name, f"must be at most 1 % of the shortest revolution "
                                  f"({0.01 * shortest:.3g} s at {float(np.max(rpm)):g} rpm), got "
                                  f"{_show(getattr(acq, name))}")
        if acq.speed_fluctuation_rpm > 0.1 * float(np.min(rpm)):
            raise _FieldError("[acquisition]", "speed_fluctuation_rpm", "must be at most 10 % of the slowest "
                              f"speed ({0.1 * float(np.min(rpm)):g} rpm), got {_show(acq.speed_fluctuation_rpm)}")
        sig = acq.signal
        if sig.enabled:
            self._check_signal(sig, float(np.min(rpm)), float(np.max(rpm)))
        if acq.clock_hz * self.speed.duration_s >= 2.0**62:
            raise _FieldError("[acquisition]", "clock_hz", f"cannot count a run of {self.speed.duration_s:g} s "
                              f"in 62 bits, got {_show(acq.clock_hz)}")


    def _check_centrifugal(self) -> None:
        m = self.model
        if not m.centrifugal:
            return
        if m.source != BUILTIN_MODEL:
            raise _FieldError("[model]", "centrifugal", "applies to the built-in model only (a model file "
                              "brings its own speed-dependent arrays, schemas/modal_model.md); got it with "
                              f"source = {_show(m.source)}")
        top = float(np.max(self.speed.breakpoints()[1]))
        if m.centrifugal_max_rpm and m.centrifugal_max_rpm < top:
            raise _FieldError("[model]", "centrifugal_max_rpm", f"must cover the speed profile's top speed "
                              f"{top:g} rpm (or be 0 for 1.2 x it), got {_show(m.centrifugal_max_rpm)}")

    def centrifugal_max_rpm(self) -> float:
        """Top speed of a speed-dependent built-in model, rpm: ``[model] centrifugal_max_rpm``, or
        1.2 times the speed profile's top speed rounded up to 100 rpm."""
        if self.model.centrifugal_max_rpm:
            return float(self.model.centrifugal_max_rpm)
        return float(math.ceil(1.2 * float(np.max(self.speed.breakpoints()[1])) / 100.0 - 1e-9) * 100.0)

    def _check_signal(self, sig: Signal, rpm_min: float, rpm_max: float) -> None:
        w = "[acquisition.signal]"
        n = len(self.probes.angles_deg)
        for name in ("probe_type", "trigger"):
            value = getattr(sig, name)
            if isinstance(value, tuple) and len(value) != n:
                raise _FieldError(w, name, f"must be one value or one per probe ({n}), got {len(value)}")
        if self.acquisition.trigger_jitter_s > 0:
            raise _FieldError("[acquisition]", "trigger_jitter_s", "must be 0 when [acquisition.signal] is enabled "
                              "(the trigger chain makes its own jitter)")
        radius = self.rotor.tip_radius_m
        omega = rpm_max * math.pi / 30.0
        growth = sig.density_kg_m3 * omega**2 * radius**3 / (3.0 * sig.youngs_modulus_pa)
        if growth >= sig.clearance_m:
            raise _FieldError(w, "clearance_m", f"must exceed the centrifugal tip growth at {rpm_max:g} rpm "
                              f"({growth * 1e3:.4g} mm): the tip would rub, got {_show(sig.clearance_m)}")
        # the longest window: slowest tip speed, widest kernel (see bttsim_stream.sim.signal)
        types = (sig.probe_type,) if isinstance(sig.probe_type, str) else sig.probe_type
        d = max(sig.spot_diameter_m if t == "optical" else math.hypot(sig.electrode_diameter_m,
                4 * sig.fringe_factor * sig.clearance_m) for t in types)
        scale = d / 4.0 * math.sqrt(3.0) / math.pi
        v = max(rpm_min * math.pi / 30.0 * radius, 1e-9)
        tau = 1.0 / (2 * math.pi * sig.bandwidth_hz) if sig.bandwidth_hz > 0 else 0.0
        samples = (2.0 * (0.5 * sig.tip_thickness_m + 9.0 * scale) / v + 7.0 * tau) * sig.sample_rate_hz
        if samples > MAX_WINDOW_SAMPLES:
            raise _FieldError(w, "sample_rate_hz", f"gives windows of {samples:.0f} samples per blade passage at "
                              f"{rpm_min:g} rpm, above {MAX_WINDOW_SAMPLES}: lower it, or the spot, electrode or "
                              f"tip size, got {_show(sig.sample_rate_hz)}")


#: Section name -> dataclass, in file order (``excitation`` is an array of tables).
SECTIONS: dict[str, type] = {
    "run": Run,
    "rotor": Rotor,
    "model": Model,
    "speed": Speed,
    "excitation": Excitation,
    "probes": Probes,
    "toa": Toa,
    "acquisition": Acquisition,
    "flutter": Flutter,
    "broadband": Broadband,
}

#: Arrays of tables besides ``excitation`` that may be empty (default none).
OPTIONAL_ARRAYS: dict[str, type] = {"rotating_stall": RotatingStall}

_SECTION_COMMENTS: dict[str, str] = {
    "run": "Identity of the run.",
    "rotor": "Geometry of the built-in bladed disk and its tip section.",
    "model": "Modal model: source, damping, mistuning.",
    "speed": "Speed profile: the paper's linear run-up (Eq. 6), or segments.",
    "excitation": "Engine-order excitation; repeat the [[excitation]] block for more.",
    "probes": "BTT probes and once-per-revolution (OPR) sensor.",
    "toa": "Time-of-arrival computation (paper Sec. 2.2).",
    "acquisition": "Acquisition errors (all off by default).",
    "rotating_stall": "Rotating stall / non-integral forcing (none by default); repeat the block for more.",
    "flutter": "Flutter: a self-excited travelling wave growing to a limit cycle (off by default).",
    "broadband": "Broadband (random) blade forcing (off by default).",
    "acquisition.signal": "Probe signals, digitisation and triggers (off by default): the TOAs as\n"
                          "hardware extracts them; the truth keeps the exact TOAs.",
}

#: Sections written only when they differ from their defaults (off by default).
_OPTIONAL_TABLES = ("flutter", "broadband")

_SEGMENTS_EXAMPLE = """\
# Example (then delete end_rpm and duration_s above):
# segments = [
#     {duration_s = 30.0, end_rpm = 2500.0},  # ramp 1000 -> 2500 rpm in 30 s
#     {duration_s = 20.0, end_rpm = 2500.0},  # dwell 20 s
#     {duration_s = 60.0, end_rpm = 4000.0},  # ramp 2500 -> 4000 rpm in 60 s
# ]"""


# --------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------


def _key(k: Any) -> str:
    """A key as written in TOML: bare if possible, else quoted."""
    k = str(k)
    return k if _BARE_KEY_RE.fullmatch(k) else _toml_string(k)


def _hint(name: Any, candidates: Sequence[str]) -> str:
    close = difflib.get_close_matches(str(name), list(candidates), n=1)
    return f" (did you mean {close[0]}?)" if close else ""


def _field_names(cls: type) -> tuple[str, ...]:
    return tuple(f.name for f in dataclasses.fields(cls))


def _check_keys(where: str, table: Mapping[str, Any], cls: type) -> None:
    names = _field_names(cls)
    for k in table:
        if k not in names:
            raise ScenarioError(f"unknown key {where} {_key(k)}{_hint(k, names)}")


def _resolve_source(source: Any, base_dir: Path | None) -> Any:
    if base_dir is None or not isinstance(source, str) or source in ("", BUILTIN_MODEL):
        return source
    path = Path(source).expanduser()
    if not path.is_absolute():
        path = base_dir / path
    return os.path.normpath(path)


def _build(d: Mapping[str, Any], base_dir: Path | None) -> Scenario:
    if not isinstance(d, Mapping):
        raise ScenarioError(f"must be a table of sections, {_got(d)}")
    for name, value in d.items():
        if name not in SECTIONS and name not in OPTIONAL_ARRAYS:
            if isinstance(value, Mapping):
                what = f"unknown section [{_key(name)}]"
            elif isinstance(value, list) and value and all(isinstance(v, Mapping) for v in value):
                what = f"unknown section [[{_key(name)}]]"
            else:
                owners = [s for s, c in SECTIONS.items() if name in _field_names(c)]
                hint = f" (keys belong in a section: put it under [{owners[0]}])" if owners else ""
                raise ScenarioError(f"unknown top-level key {_key(name)}{hint}")
            raise ScenarioError(what + _hint(name, list(SECTIONS) + list(OPTIONAL_ARRAYS)))

    # Structure first (tables, unknown keys), then values.
    tables: dict[str, Mapping[str, Any]] = {}
    for name, cls in SECTIONS.items():
        if name == "excitation":
            continue
        table = d.get(name, {})
        if not isinstance(table, Mapping):
            raise ScenarioError(f"[{name}] must be a table, {_got(table)}")
        _check_keys(f"[{name}]", table, cls)
        tables[name] = table
    entries = d.get("excitation", [{}])
    if not isinstance(entries, list):
        raise ScenarioError("excitation must be an array of tables ([[excitation]] blocks), "
                            + _got(entries))
    if not entries:
        raise ScenarioError("[[excitation]] must have at least one entry, got none")
    for i, entry in enumerate(entries):
        if not isinstance(entry, Mapping):
            raise ScenarioError(f"[[excitation]][{i}] must be a table, {_got(entry)}")
        _check_keys(f"[[excitation]][{i}]", entry, Excitation)

    speed = tables["speed"]
    if speed.get("segments"):
        for k in ("end_rpm", "duration_s"):
            if k in speed:
                raise ScenarioError(f"[speed] {k} must be absent when segments is given "
                                    "(the segments set the end speed and the duration)")

    sections: dict[str, Any] = {}
    for name, table in tables.items():
        kwargs = dict(table)
        if name == "model" and "source" in kwargs:
            kwargs["source"] = _resolve_source(kwargs["source"], base_dir)
        sections[name] = SECTIONS[name](**kwargs)
    excitation = []
    for i, entry in enumerate(entries):
        try:
            excitation.append(Excitation(**entry))
        except _FieldError as exc:
            raise exc.relabel(f"[[excitation]][{i}]") from None
    arrays: dict[str, tuple] = {}
    for name, cls in OPTIONAL_ARRAYS.items():
        items = d.get(name, [])
        if not isinstance(items, list):
            raise ScenarioError(f"{name} must be an array of tables ([[{name}]] blocks), " + _got(items))
        out = []
        for i, entry in enumerate(items):
            if not isinstance(entry, Mapping):
                raise ScenarioError(f"[[{name}]][{i}] must be a table, {_got(entry)}")
            _check_keys(f"[[{name}]][{i}]", entry, cls)
            try:
                out.append(cls(**entry))
            except _FieldError as exc:
                raise exc.relabel(f"[[{name}]][{i}]") from None
        arrays[name] = tuple(out)
    return Scenario(excitation=tuple(excitation), **sections, **arrays)


def scenario_from_dict(d: Mapping[str, Any], source: str = "<dict>", *,
                       base_dir: str | os.PathLike[str] | None = None) -> Scenario:
    """Build and validate a :class:`Scenario` from a parsed-TOML dict.

    Parameters
    ----------
    d : mapping
        ``{section: {key: value}}`` as :func:`tomllib.loads` returns it, with
        ``"excitation"`` a list of tables. Missing sections and keys take their defaults.
    source : str
        Name of the origin (a file name), used as the prefix of error messages.
    base_dir : path-like, optional
        Directory against which a relative ``[model] source`` path is resolved; if None
        it is kept as given.

    Returns
    -------
    Scenario

    Raises
    ------
    ScenarioError
        ``"<source>: <what is wrong>"`` for an unknown section or key, a wrong type, or
        an impossible value.
    """
    try:
        return _build(d, Path(base_dir) if base_dir is not None else None)
    except ScenarioError as exc:
        raise ScenarioError(f"{source}: {_one_line(str(exc))}") from None


def load_scenario(path: str | os.PathLike[str]) -> Scenario:
    """Read, parse and validate a scenario TOML file.

    Parameters
    ----------
    path : path-like
        The scenario file (UTF-8 TOML). A relative ``[model] source`` path in it is
        resolved against the file's directory.

    Returns
    -------
    Scenario

    Raises
    ------
    ScenarioError
        One line starting with the path as given: no such file, a directory, unreadable,
        not UTF-8, malformed TOML, or any error of :func:`scenario_from_dict`.
    """
    name = os.fspath(path)
    p = Path(name)
    try:
        data = p.read_bytes()
    except FileNotFoundError:
        raise ScenarioError(f"{name}: no such file") from None
    except IsADirectoryError:
        raise ScenarioError(f"{name}: is a directory, not a scenario file") from None
    except PermissionError:
        raise ScenarioError(f"{name}: permission denied") from None
    except OSError as exc:
        if p.is_dir():
            raise ScenarioError(f"{name}: is a directory, not a scenario file") from None
        raise ScenarioError(f"{name}: cannot read ({exc.strerror or exc})") from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ScenarioError(f"{name}: not UTF-8 text (byte 0x{data[exc.start]:02x} at "
                            f"offset {exc.start})") from None
    text = text.removeprefix("\ufeff")
    try:
        d = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(f"{name}: malformed TOML: {_one_line(str(exc))}") from None
    except ValueError as exc:  # e.g. an integer of more than 4300 digits
        raise ScenarioError(f"{name}: malformed TOML: {_one_line(str(exc))}") from None
    except RecursionError:
        raise ScenarioError(f"{name}: malformed TOML: arrays or tables nested too deep") from None
    return scenario_from_dict(d, source=name, base_dir=p.absolute().parent)


# --------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------


def _section_dict(obj: Any) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        out[f.name] = list(value) if isinstance(value, tuple) else value
    return out


def scenario_to_dict(scn: Scenario) -> dict[str, Any]:
    """The scenario as plain TOML-ready data (dicts, lists, str, int, float, bool).

    ``scenario_from_dict(scenario_to_dict(s)) == s``. With speed segments, ``[speed]``
    holds ``start_rpm`` and ``segments`` (a list of ``{duration_s, end_rpm}`` dicts) only.

    Parameters
    ----------
    scn : Scenario

    Returns
    -------
    dict
        ``{section: {key: value}}``; ``"excitation"`` is a list of dicts.
    """
    out: dict[str, Any] = {}
    for name in SECTIONS:
        if name == "excitation":
            out[name] = [_section_dict(e) for e in scn.excitation]
            continue
        table = _section_dict(getattr(scn, name))
        if name == "acquisition":
            table["signal"] = _section_dict(scn.acquisition.signal)
        if name == "speed":
            table["segments"] = [{"duration_s": d, "end_rpm": r} for d, r in scn.speed.segments]
            if table["segments"]:
                del table["end_rpm"], table["duration_s"]
        out[name] = table
    for name in OPTIONAL_ARRAYS:
        if getattr(scn, name):
            out[name] = [_section_dict(e) for e in getattr(scn, name)]
    return out


def _toml_string(s: str) -> str:
    """A TOML basic string."""
    out = ['"']
    for ch in s:
        code = ord(ch)
        if ch == '"':
            out.append('\\"')
        elif ch == "\\":
            out.append("\\\\")
        elif ch in "\b\t\n\f\r":
            out.append({"\b": "\\b", "\t": "\\t", "\n": "\\n", "\f": "\\f", "\r": "\\r"}[ch])
        elif code < 0x20 or code == 0x7F:
            out.append(f"\\u{code:04X}")
        else:
            out.append(ch)
    out.append('"')
    return "".join(out)


def _toml_value(v: Any) -> str:
    """One TOML value: str, int, float, bool, list of values, or an inline table."""
    if isinstance(v, (bool, np.bool_)):
        return "true" if v else "false"
    if isinstance(v, numbers.Integral):
        return str(int(v))
    if isinstance(v, numbers.Real):
        return repr(float(v))  # shortest repr: parses back to the same float
    if isinstance(v, str):
        return _toml_string(v)
    if isinstance(v, Mapping):
        return "{" + ", ".join(f"{_key(k)} = {_toml_value(x)}" for k, x in v.items()) + "}"
    if isinstance(v, (list, tuple)):
        if v and all(isinstance(x, Mapping) for x in v):
            return "[\n" + "".join(f"    {_toml_value(x)},\n" for x in v) + "]"
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} as TOML")


def _comment(text: str) -> list[str]:
    return [f"# {line}".rstrip() for line in text.splitlines()]


def _emit_table(lines: list[str], cls: type, table: Mapping[str, Any], comments: bool) -> None:
    docs = {f.name: f.metadata.get("toml", "") for f in dataclasses.fields(cls)}
    for k, v in table.items():
        if k == "segments" and not v:
            if comments:
                lines.extend(_comment(docs[k]))
                lines.append(_SEGMENTS_EXAMPLE)
            continue
        if comments and docs.get(k):
            lines.extend(_comment(docs[k]))
        lines.append(f"{_key(k)} = {_toml_value(v)}")


def dumps_toml(scn: Scenario, *, comments: bool = False) -> str:
    """Write a scenario as TOML that :func:`load_scenario` reads back equal.

    Parameters
    ----------
    scn : Scenario
    comments : bool
        If true, write a header and a comment (meaning, unit, constraint) above every
        section and key.

    Returns
    -------
    str
        The TOML text, ending with a newline. A relative ``[model] source`` is written as
        is (and resolved against the file's directory when loaded).
    """
    d = scenario_to_dict(scn)
    lines: list[str] = []
    if comments:
        lines += [
            "# bttsim scenario: one file configures a run. Defaults: the paper's Table 1",
            "# (Nour, Bonello et al.) plus our rotor geometry. SI units (name suffix _m, _s,",
            "# _n, _hz), angles in degrees (_deg), speeds in rpm (_rpm). A missing key or",
            "# section takes its default; unknown keys are errors.",
            "# Check an edited file with: bttsim scenario --check FILE",
        ]
    for name, cls in SECTIONS.items():
        if name == "excitation":
            for i, entry in enumerate(d[name]):
                lines.append("")
                if comments and i == 0:
                    lines.extend(_comment(_SECTION_COMMENTS[name]))
                lines.append("[[excitation]]")
                _emit_table(lines, cls, entry, comments and i == 0)
            continue
        if name in _OPTIONAL_TABLES and not comments and getattr(scn, name) == cls():
            continue  # written only when changed: a default run's id (a hash of this text) stays
        lines.append("")
        if comments:
            lines.extend(_comment(_SECTION_COMMENTS[name]))
        lines.append(f"[{name}]")
        table = dict(d[name])
        sub = table.pop("signal", None)
        if name == "speed" and not comments and table.get("initial") == "steady":
            del table["initial"]  # written only when changed: a default run's id (a hash of this text) stays
        if name == "model" and not comments and not scn.model.centrifugal:
            for k in _CENTRIFUGAL_KEYS:  # written only when on: a default run's id stays
                table.pop(k, None)
        _emit_table(lines, cls, table, comments)
        # only a changed [acquisition.signal] is written (the run id of a default run, a hash
        # of this text, stays what it was before the section existed); the commented file shows it
        if sub is not None and (comments or scn.acquisition.signal != Signal()):
            lines.append("")
            if comments:
                lines.extend(_comment(_SECTION_COMMENTS["acquisition.signal"]))
            lines.append("[acquisition.signal]")
            _emit_table(lines, Signal, sub, comments)
    for name, cls in OPTIONAL_ARRAYS.items():
        for i, entry in enumerate(d.get(name, [])):
            lines.append("")
            if comments and i == 0:
                lines.extend(_comment(_SECTION_COMMENTS[name]))
            lines.append(f"[[{name}]]")
            _emit_table(lines, cls, entry, comments and i == 0)
    if lines and lines[0] == "":
        lines.pop(0)
    return "\n".join(lines) + "\n"


def default_toml() -> str:
    """The default scenario as commented TOML (what ``bttsim scenario`` prints).

    Returns
    -------
    str
    """
    return dumps_toml(Scenario(), comments=True)

"""The scenario: one TOML file that configures a run, read into frozen dataclasses.

Every field has a default: the paper's Table 1 (Nour, Bonello et al.) plus the rotor
geometry we chose where the paper gives none. ``bttsim scenario`` prints the default file
(:func:`default_toml`); the user edits it and passes it back (:func:`load_scenario`).

Rules, the same for a file and for programmatic construction:

* All values are SI with the unit in the name (``_m``, ``_s``, ``_n``, ``_hz``), except
  angles in degrees (``_deg``) and speeds in rpm (``_rpm``), as in the paper.
* Each field is declared once (:func:`~bttsim_stream.fieldspec.spec`: kind, unit, bounds,
  default, comment); its check, its comment in the printed file, the ``Attributes`` of the
  section's docstring and its row in ``schemas/scenario.md`` all come from that declaration.
  The sections and the checks across their fields (small named functions) are in
  :mod:`bttsim_stream.scenario_sections`, re-exported here; :class:`Scenario` adds the checks
  that span sections. Any problem raises :class:`~bttsim_stream.errors.ScenarioError` with a
  one-line message naming the field, e.g. ``[probes] angles_deg[2] must be finite, got nan``;
  :func:`load_scenario` and :func:`scenario_from_dict` prefix it with the file
  (``scenario.toml: ...``).
* An integer is accepted where a float is expected, never the reverse; a boolean is never
  accepted as a number. Floats must be finite. Lists are stored as tuples.
* In a file, unknown sections and keys are errors; a missing section or key takes its
  default. Array indices in messages count from 0.

The file is read with :mod:`tomllib`; :func:`dumps_toml` is a small emitter for the few
value types used here, written so that ``load(dumps(s)) == s`` exactly (floats by
``repr``). ``python -m bttsim_stream.scenario --schema-md FILE`` rewrites the generated
field tables of ``schemas/scenario.md``.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import sys
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .errors import ScenarioError
from .fieldspec import FieldError as _FieldError
from .fieldspec import comments as _comments
from .fieldspec import markdown_table
from .fieldspec import got as _got
from .fieldspec import one_line as _one_line
from .fieldspec import show as _show
from .fieldspec import toml_key as _key
from .fieldspec import toml_value as _toml_value
from .scenario_sections import (
    CENTRIFUGAL_KEYS,
    BUILTIN_MODEL,
    MAX_WINDOW_SAMPLES,
    Acquisition,
    Broadband,
    Excitation,
    Flutter,
    Model,
    Probes,
    RotatingStall,
    Rotor,
    Run,
    Signal,
    Speed,
    Toa,
    check_keys,
    field_names,
    did_you_mean,
    set_normalised,
)

# Re-exported: the sections' bounds and choices, importable from here as before the split.
from .defaults import DEFAULT_RIG, MAX_BLADES, MAX_ENGINE_ORDER, MAX_PROBES, MAX_REVOLUTIONS, MAX_RPM  # noqa: F401
from .scenario_sections import (  # noqa: F401
    FORCE_NODES,
    MAX_BROADBAND_HZ,
    MAX_BROADBAND_LINES,
    MAX_CLOCK_HZ,
    MAX_FAMILIES,
    MAX_MODEL_SPEEDS,
    MAX_PROBE_ANGLE_ERROR_DEG,
    MAX_SEED,
    MAX_SIGNAL_SIZE_M,
    MAX_STALL_FREQUENCY_HZ,
    MAX_TIP_NODES,
    MAX_TIP_RADIUS_M,
    MIN_CLOCK_HZ,
    SIGNAL_EDGES,
    SIGNAL_PROBES,
    SIGNAL_TRIGGERS,
    SPEED_INITIAL,
    TOA_METHODS,
)

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
    "read_toml_file",
    "scenario_from_dict",
    "scenario_to_dict",
    "dumps_toml",
    "default_toml",
    "schema_markdown",
]


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
    Cross-section checks, one named method each: each ``nodal_diameter < n_blades``; the
    probes' axial position within ``[0, rotor.tip_axial_extent_m]`` with the built-in model (a
    user's model: within its tip nodes, checked by the simulator once the model is loaded);
    non-empty mistuning factor lists hold ``n_blades`` values; the flutter onset within the
    run; the acquisition errors against the speed profile; the signal chain against the rotor.
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
        set_normalised(self, "rotating_stall",
                       _entries("rotating_stall", self.rotating_stall, RotatingStall, allow_empty=True))
        self._check_flutter()
        self._check_section_types()
        self._check_revolutions()
        set_normalised(self, "excitation", _entries("excitation", self.excitation, Excitation, allow_empty=False))
        self._check_nodal_diameters()
        self._check_probe_position()
        self._check_centrifugal()
        self._check_mistuning()
        self._check_acquisition()

    def _check_revolutions(self) -> None:
        """At least one whole revolution between two OPR pulses: the run's first pulse comes
        when the OPR mark passes the sensor, ``opr_angle_deg`` into the first revolution."""
        total = self.speed.revolutions()
        past = total - self.probes.opr_angle_deg / 360.0
        if not past >= 1.0:
            raise _FieldError("[speed]", "", f"makes {total:.3g} revolutions, {max(past, 0.0):.3g} of them after the "
                              f"first OPR pulse ([probes] opr_angle_deg {self.probes.opr_angle_deg:g}): no whole "
                              "revolution between two pulses; raise the speed or duration_s")

    def _check_section_types(self) -> None:
        for name, cls in SECTIONS.items():
            value = getattr(self, name)
            if name != "excitation" and not isinstance(value, cls):
                raise _FieldError(f"[{name}]", "", f"must be a {cls.__name__}, got {type(value).__name__}")

    def _check_flutter(self) -> None:
        fl, n = self.flutter, self.rotor.n_blades
        if 2 * abs(fl.nodal_diameter) > n:
            raise _FieldError("[flutter]", "nodal_diameter", f"must be within +-[rotor] n_blades / 2 = "
                              f"{n / 2:g}, got {fl.nodal_diameter}")
        if fl.enabled and fl.start_rpm > 0:
            _, rpm = self.speed.breakpoints()
            lo, hi = float(np.min(rpm)), float(np.max(rpm))
            if not lo <= fl.start_rpm <= hi:
                raise _FieldError("[flutter]", "start_rpm", f"must lie within the speed profile "
                                  f"({lo:g} .. {hi:g} rpm), got {_show(fl.start_rpm)}")
        if fl.enabled and fl.start_rpm == 0 and fl.start_s >= self.speed.duration_s:
            raise _FieldError("[flutter]", "start_s", f"must be before the end of the run "
                              f"({self.speed.duration_s:g} s), got {_show(fl.start_s)}")

    def _check_nodal_diameters(self) -> None:
        n = self.rotor.n_blades
        for i, e in enumerate(self.excitation):
            if e.nodal_diameter >= n:
                raise _FieldError(f"[[excitation]][{i}]", "nodal_diameter",
                                  f"must be < [rotor] n_blades = {n}, got {e.nodal_diameter}")

    def _check_probe_position(self) -> None:
        z, z_max = self.probes.axial_position_m, self.rotor.tip_axial_extent_m
        # a user's model has its own tip nodes: the simulator checks z against them
        if self.model.source == BUILTIN_MODEL and not 0.0 <= z <= z_max:
            raise _FieldError("[probes]", "axial_position_m", "must lie within the tip "
                              f"chord's axial extent [0, {z_max:.6g}] m ([rotor] tip_chord_m * "
                              f"sin(stagger_deg)), got {_show(z)}")

    def _check_mistuning(self) -> None:
        n = self.rotor.n_blades
        for kind in ("stiffness_factors", "mass_factors"):
            factors = getattr(self.model, kind)
            if factors and len(factors) != n:
                raise _FieldError("[model]", kind, f"must hold [rotor] n_blades = {n} values "
                                  f"(or be empty), got {len(factors)}")

    def _check_acquisition(self) -> None:
        acq, (_, rpm) = self.acquisition, self.speed.breakpoints()
        rpm_min, rpm_max = float(np.min(rpm)), float(np.max(rpm))
        shortest = 60.0 / rpm_max  # s, the shortest revolution
        for name in ("trigger_jitter_s", "opr_jitter_s"):
            if getattr(acq, name) > 0.01 * shortest:
                raise _FieldError("[acquisition]", name, f"must be at most 1 % of the shortest revolution "
                                  f"({0.01 * shortest:.3g} s at {rpm_max:g} rpm), got "
                                  f"{_show(getattr(acq, name))}")
        if acq.speed_fluctuation_rpm > 0.1 * rpm_min:
            raise _FieldError("[acquisition]", "speed_fluctuation_rpm", "must be at most 10 % of the slowest "
                              f"speed ({0.1 * rpm_min:g} rpm), got {_show(acq.speed_fluctuation_rpm)}")
        if acq.signal.enabled:
            self._check_signal(acq.signal, rpm_min, rpm_max)
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




def _entries(name: str, value: Any, cls: type, *, allow_empty: bool) -> tuple[Any, ...]:
    """An array-of-tables section given programmatically: a sequence of ``cls``."""
    if isinstance(value, cls) or not isinstance(value, (list, tuple)):
        raise _FieldError(f"[[{name}]]", "", f"must be a sequence of {cls.__name__}, got {type(value).__name__}")
    if not value and not allow_empty:
        raise _FieldError(f"[[{name}]]", "", "must have at least one entry, got none")
    for i, e in enumerate(value):
        if not isinstance(e, cls):
            article = "an" if cls.__name__[0] in "AEIOU" else "a"
            raise _FieldError(f"[[{name}]][{i}]", "", f"must be {article} {cls.__name__}, got {type(e).__name__}")
    return tuple(value)


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


def _resolve_source(source: Any, base_dir: Path | None) -> Any:
    if base_dir is None or not isinstance(source, str) or source in ("", BUILTIN_MODEL):
        return source
    path = Path(source).expanduser()
    if not path.is_absolute():
        path = base_dir / path
    return os.path.normpath(path)


def _check_top_level(d: Any) -> None:
    """Only known sections at the top of the file."""
    if not isinstance(d, Mapping):
        raise ScenarioError(f"must be a table of sections, {_got(d)}")
    for name, value in d.items():
        if name in SECTIONS or name in OPTIONAL_ARRAYS:
            continue
        if isinstance(value, Mapping):
            what = f"unknown section [{_key(name)}]"
        elif isinstance(value, list) and value and all(isinstance(v, Mapping) for v in value):
            what = f"unknown section [[{_key(name)}]]"
        else:
            owners = [s for s, c in SECTIONS.items() if name in field_names(c)]
            hint = f" (keys belong in a section: put it under [{owners[0]}])" if owners else ""
            raise ScenarioError(f"unknown top-level key {_key(name)}{hint}")
        raise ScenarioError(what + did_you_mean(name, list(SECTIONS) + list(OPTIONAL_ARRAYS)))


def _tables(d: Mapping[str, Any]) -> dict[str, Mapping[str, Any]]:
    """The single-table sections, their keys checked (a missing one is empty)."""
    tables: dict[str, Mapping[str, Any]] = {}
    for name, cls in SECTIONS.items():
        if name == "excitation":
            continue
        table = d.get(name, {})
        if not isinstance(table, Mapping):
            raise ScenarioError(f"[{name}] must be a table, {_got(table)}")
        check_keys(f"[{name}]", table, cls)
        tables[name] = table
    speed = tables["speed"]
    if speed.get("segments"):
        for k in ("end_rpm", "duration_s"):
            if k in speed:
                raise ScenarioError(f"[speed] {k} must be absent when segments is given "
                                    "(the segments set the end speed and the duration)")
    return tables


def _array_tables(d: Mapping[str, Any], name: str, default: list[Any]) -> list[Mapping[str, Any]]:
    """An array of tables (``[[name]]`` blocks), its keys checked."""
    entries = d.get(name, default)
    if not isinstance(entries, list):
        raise ScenarioError(f"{name} must be an array of tables ([[{name}]] blocks), " + _got(entries))
    for i, entry in enumerate(entries):
        if not isinstance(entry, Mapping):
            raise ScenarioError(f"[[{name}]][{i}] must be a table, {_got(entry)}")
        check_keys(f"[[{name}]][{i}]", entry, SECTIONS.get(name) or OPTIONAL_ARRAYS[name])
    return entries


def _build_entries(name: str, entries: list[Mapping[str, Any]]) -> tuple[Any, ...]:
    cls = SECTIONS.get(name) or OPTIONAL_ARRAYS[name]
    out = []
    for i, entry in enumerate(entries):
        try:
            out.append(cls(**entry))
        except _FieldError as exc:
            raise exc.relabel(f"[[{name}]][{i}]") from None
    return tuple(out)


def _build(d: Mapping[str, Any], base_dir: Path | None) -> Scenario:
    _check_top_level(d)
    # Structure first (tables, unknown keys), then values.
    tables = _tables(d)
    entries = _array_tables(d, "excitation", [{}])
    if not entries:
        raise ScenarioError("[[excitation]] must have at least one entry, got none")
    sections: dict[str, Any] = {}
    for name, table in tables.items():
        kwargs = dict(table)
        if name == "model" and "source" in kwargs:
            kwargs["source"] = _resolve_source(kwargs["source"], base_dir)
        sections[name] = SECTIONS[name](**kwargs)
    excitation = _build_entries("excitation", entries)
    arrays = {name: _build_entries(name, _array_tables(d, name, [])) for name in OPTIONAL_ARRAYS}
    return Scenario(excitation=excitation, **sections, **arrays)


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


def read_toml_file(path, what: str, error: type[Exception]) -> dict:
    """A UTF-8 TOML file as a dict (a leading BOM allowed); any problem is one ``error`` starting
    with the path as given: no such file, a directory (not ``what``), unreadable, not UTF-8,
    malformed TOML."""
    name = os.fspath(path)
    p = Path(name)
    try:
        data = p.read_bytes()
    except FileNotFoundError:
        raise error(f"{name}: no such file") from None
    except IsADirectoryError:
        raise error(f"{name}: is a directory, not {what}") from None
    except PermissionError:
        raise error(f"{name}: permission denied") from None
    except OSError as exc:
        if p.is_dir():
            raise error(f"{name}: is a directory, not {what}") from None
        raise error(f"{name}: cannot read ({exc.strerror or exc})") from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise error(f"{name}: not UTF-8 text (byte 0x{data[exc.start]:02x} at "
                    f"offset {exc.start})") from None
    text = text.removeprefix("\ufeff")
    try:
        d = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{name}: malformed TOML: {_one_line(str(exc))}") from None
    except ValueError as exc:  # e.g. an integer of more than 4300 digits
        raise error(f"{name}: malformed TOML: {_one_line(str(exc))}") from None
    except RecursionError:
        raise error(f"{name}: malformed TOML: arrays or tables nested too deep") from None
    return d


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
    d = read_toml_file(name, "a scenario file", ScenarioError)
    return scenario_from_dict(d, source=name, base_dir=Path(name).absolute().parent)


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


def _comment(text: str) -> list[str]:
    return [f"# {line}".rstrip() for line in text.splitlines()]


def _emit_table(lines: list[str], cls: type, table: Mapping[str, Any], comments: bool) -> None:
    docs = _comments(cls) if comments else {}  # the comments cost more than the rest of the text
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
            for k in CENTRIFUGAL_KEYS:  # written only when on: a default run's id stays
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


# --------------------------------------------------------------------------------------
# The schema document
# --------------------------------------------------------------------------------------

_TABLE_BLOCK = re.compile(r"(<!-- fields: (\S+) [^\n]*-->\n)(.*?)(<!-- end fields -->)", re.S)


def _section_class(name: str) -> type:
    if name == "acquisition.signal":
        return Signal
    if name in SECTIONS:
        return SECTIONS[name]
    if name in OPTIONAL_ARRAYS:
        return OPTIONAL_ARRAYS[name]
    raise ScenarioError(f"schemas/scenario.md: no section {name!r} (a fields block names a section)")


def schema_markdown(text: str) -> str:
    """``schemas/scenario.md`` with its field tables regenerated from the declarations.

    Each table sits between ``<!-- fields: SECTION ... -->`` and ``<!-- end fields -->``;
    the prose around the tables is kept as written.

    Parameters
    ----------
    text : str
        The current document.

    Returns
    -------
    str
    """
    return _TABLE_BLOCK.sub(lambda m: m.group(1) + markdown_table(_section_class(m.group(2))) + m.group(4), text)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m bttsim_stream.scenario --schema-md FILE [--check]``: rewrite (or check) the
    field tables of the scenario schema document."""
    import argparse

    parser = argparse.ArgumentParser(prog="python -m bttsim_stream.scenario", description=main.__doc__)
    parser.add_argument("--schema-md", metavar="FILE", required=True, help="schemas/scenario.md")
    parser.add_argument("--check", action="store_true", help="exit 1 if FILE is not up to date, write nothing")
    options = parser.parse_args(argv)
    path = Path(options.schema_md)
    text = path.read_text(encoding="utf-8")
    new = schema_markdown(text)
    if options.check:
        if new != text:
            print(f"{path}: field tables out of date; run python -m bttsim_stream.scenario "
                  f"--schema-md {path}", file=sys.stderr)
        return int(new != text)
    if new != text:
        path.write_text(new, encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())

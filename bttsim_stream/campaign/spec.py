"""The campaign spec: a base scenario, axes to vary, seeds and the processors to score.

A spec is one TOML file (``docs/campaign.md``)::

    [campaign]
    name = "jitter"                 # a label for the report
    scenario = "base.toml"          # optional base scenario (relative to the spec)
    seed = 0                        # master seed: the run seeds derive from it
    seeds = 4                       # replicates per axis point (or a list of run seeds)
    processors = ["peak", "sdof", {name = "peak_raw", method = "peak", prep = false},
                  "my_pkg.my_module:my_processor"]
    retries = 2                     # Dask retries of a run whose task failed
    mcap = false                    # true: each run goes through a temporary MCAP file

    [scenario.speed]                # optional inline base scenario (over the file's)
    start_rpm = 2400.0

    [axes]                          # scenario fields by dotted name: grid of every axis
    "acquisition.trigger_jitter_s" = [0.0, 1e-6]
    "speed.duration_s" = {start = 4.0, stop = 8.0, num = 3}
    "model.stiffness_std" = {uniform = [0.0, 0.02], n = 3}   # seeded random draws

:func:`expand` turns a spec into :class:`RunSpec` s: the cross product of the axes times the
replicates. A replicate's run seed depends only on the master seed and the replicate number,
so every axis point of one replicate shares its seed (paired comparisons). Every run's
scenario is validated when the spec is loaded, so a bad value ends the campaign before any
work starts, as one line naming the axis.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from .. import __version__
from ..errors import BttsimError
from ..process.pipeline import METHODS
from ..scenario import (MAX_SEED, Scenario, dumps_toml, load_scenario, read_toml_file, scenario_from_dict,
                        scenario_to_dict)

__all__ = ["SpecError", "Processor", "Axis", "CampaignSpec", "RunSpec", "load_spec", "spec_from_dict", "expand",
           "run_seed", "MAX_RUNS"]

#: Most runs one spec may expand to (a typo in a range must not submit a billion tasks): a
#: spec of this many expands in about 3 s (twice: when read and when the campaign starts).
MAX_RUNS = 100_000
_CAMPAIGN_KEYS = ("name", "scenario", "seed", "seeds", "processors", "retries", "mcap")
_TOP_KEYS = ("campaign", "scenario", "axes")
_PROCESSOR_KEYS = ("name", "method", "prep", "window")


class SpecError(BttsimError):
    """A campaign spec is missing, malformed or impossible (one line, exit status 2)."""


@dataclass(frozen=True, slots=True)
class Processor:
    """One processor to score.

    Attributes
    ----------
    name : str
        The ``method`` column of the results (``"peak"``, ``"peak_raw"``, ``"pkg.mod:fn"``).
    method : str
        ``"peak"``, ``"sdof"``, ``"cff"`` (:mod:`~bttsim_stream.process.methods`) or
        ``"user"``.
    prep : bool
        Data preparation (Sec. 2.3) on or off (built-in methods).
    window : int
        Revolutions per sine fit (built-in methods).
    target : str
        ``"module:function"`` of a user's processor, else ``""``.
    """

    name: str
    method: str
    prep: bool = True
    window: int = 1
    target: str = ""


@dataclass(frozen=True, slots=True)
class Axis:
    """One axis: a scenario field by dotted name and its values (TOML-ready)."""

    name: str
    values: tuple


@dataclass(frozen=True, slots=True)
class CampaignSpec:
    """A validated campaign spec (:func:`load_spec`)."""

    name: str
    base: dict
    axes: tuple
    seeds: tuple
    processors: tuple
    retries: int = 2
    mcap: bool = False
    source: str = "<spec>"
    base_dir: str = "."

    @property
    def axis_names(self) -> tuple:
        return tuple(a.name for a in self.axes)


@dataclass(frozen=True, slots=True)
class RunSpec:
    """One run of a campaign: a resolved scenario and the processors that score it.

    Attributes
    ----------
    run_id : str
        16 hex digits of the SHA-256 of the resolved scenario TOML, the processors and the
        software version: the same run has the same id in every campaign.
    index : int
        Position in the expansion (axis points in grid order, replicates innermost).
    replicate : int
    seed : int
        The scenario's ``[run] seed``.
    point : dict
        Axis name -> value of this run.
    scenario_toml : str
        The resolved scenario (what ``bttsim simulate`` takes to repeat the run).
    processors : tuple of Processor
    mcap : bool
        Go through a temporary MCAP file (the worker's scratch) rather than in memory.
    """

    run_id: str
    index: int
    replicate: int
    seed: int
    point: dict
    scenario_toml: str
    processors: tuple
    mcap: bool = False


def _fail(source: str, text: str) -> SpecError:
    return SpecError(f"{source}: {text}")


def load_spec(path) -> CampaignSpec:
    """Read and validate a campaign spec file (:class:`SpecError`, one line, on any problem)."""
    name = os.fspath(path)
    d = read_toml_file(name, "a campaign spec", SpecError)
    return spec_from_dict(d, source=name, base_dir=Path(name).absolute().parent)


def _hint(key: str, known) -> str:
    import difflib

    close = difflib.get_close_matches(str(key), list(known), n=1)
    return f" (did you mean {close[0]!r}?)" if close else ""


def spec_from_dict(d: dict, source: str = "<spec>", *, base_dir=".") -> CampaignSpec:
    """Build and validate a :class:`CampaignSpec` from parsed TOML (``source`` prefixes errors)."""
    base_dir = Path(base_dir)
    for k in d:
        if k not in _TOP_KEYS:
            raise _fail(source, f"unknown table [{k}]{_hint(k, _TOP_KEYS)}; a spec has [campaign], [scenario], [axes]")
    c = d.get("campaign", {})
    if not isinstance(c, dict):
        raise _fail(source, "[campaign] must be a table")
    for k in c:
        if k not in _CAMPAIGN_KEYS:
            raise _fail(source, f"[campaign] unknown key {k!r}{_hint(k, _CAMPAIGN_KEYS)}")
    name = c.get("name", Path(source).stem)
    if not isinstance(name, str):
        raise _fail(source, "[campaign] name must be a string")
    base = _base_scenario(c.get("scenario"), d.get("scenario", {}), source, base_dir)
    master = _int(c.get("seed", 0), "[campaign] seed", source, 0, MAX_SEED)
    seeds = _seeds(c.get("seeds", 1), master, source)
    retries = _int(c.get("retries", 2), "[campaign] retries", source, 0, 100)
    mcap = c.get("mcap", False)
    if not isinstance(mcap, bool):
        raise _fail(source, f"[campaign] mcap must be true or false, got {mcap!r}")
    processors = _processors(c.get("processors", ["peak"]), source)
    axes_d = d.get("axes", {})
    if not isinstance(axes_d, dict):
        raise _fail(source, "[axes] must be a table of dotted scenario field names")
    axes = tuple(_axis(n, v, base, master, source) for n, v in _flatten(axes_d))
    spec = CampaignSpec(name=name, base=base, axes=axes, seeds=seeds, processors=processors, retries=retries,
                        mcap=mcap, source=source, base_dir=str(base_dir))
    n = len(seeds) * math.prod(len(a.values) for a in axes)
    if n > MAX_RUNS:
        raise _fail(source, f"the spec expands to {n} runs (at most {MAX_RUNS})")
    expand(spec)  # every run's scenario is checked now
    return spec


def _int(v, what: str, source: str, lo: int, hi: int) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
        raise _fail(source, f"{what} must be an integer in [{lo}, {hi}], got {v!r}")
    return v


def _seeds(v, master: int, source: str) -> tuple:
    if isinstance(v, list):
        if not v:
            raise _fail(source, "[campaign] seeds must not be empty")
        out = tuple(_int(s, "[campaign] seeds[]", source, 0, MAX_SEED) for s in v)
        if len(set(out)) != len(out):
            raise _fail(source, "[campaign] seeds must be distinct")
        return out
    n = _int(v, "[campaign] seeds (a count, or a list of run seeds)", source, 1, MAX_RUNS)
    return tuple(run_seed(master, k) for k in range(n))


def run_seed(master: int, replicate: int) -> int:
    """The ``[run] seed`` of replicate ``replicate``: a hash of the master seed and the number,
    the same in every campaign and on every machine."""
    h = hashlib.sha256(f"bttsim-campaign/{int(master)}/{int(replicate)}".encode()).digest()
    return int.from_bytes(h[:8], "big") % (MAX_SEED + 1)


def _processors(v, source: str) -> tuple:
    if not isinstance(v, list) or not v:
        raise _fail(source, "[campaign] processors must be a non-empty list (peak, sdof, cff, module:function "
                            "or {name, method, prep, window} tables)")
    out = []
    for p in v:
        if isinstance(p, str):
            out.append(_processor({"name": p, "method": p}, source))
        elif isinstance(p, dict):
            out.append(_processor(p, source))
        else:
            raise _fail(source, f"[campaign] processors: {p!r} is neither a name nor a table")
    names = [p.name for p in out]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise _fail(source, f"[campaign] processors: name {dup[0]!r} given twice (give tables a distinct name)")
    return tuple(out)


def _processor(t: dict, source: str) -> Processor:
    for k in t:
        if k not in _PROCESSOR_KEYS:
            raise _fail(source, f"[campaign] processors: unknown key {k!r}{_hint(k, _PROCESSOR_KEYS)}")
    method = t.get("method", t.get("name"))
    name = t.get("name", method)
    if not isinstance(method, str) or not isinstance(name, str) or not name:
        raise _fail(source, f"[campaign] processors: method and name must be strings, got {t!r}")
    prep = t.get("prep", True)
    if not isinstance(prep, bool):
        raise _fail(source, f"[campaign] processors: prep must be true or false, got {prep!r}")
    window = _int(t.get("window", 1), "[campaign] processors: window", source, 1, 1000)
    if ":" in method:
        mod, _, fn = method.partition(":")
        if not all(part.isidentifier() for part in mod.split(".")) or not fn.isidentifier():
            raise _fail(source, f"[campaign] processors: {method!r} is not module:function")
        return Processor(name=name, method="user", target=method)
    if method not in METHODS:
        raise _fail(source, f"[campaign] processors: unknown method {method!r}{_hint(method, METHODS)} "
                            f"({', '.join(METHODS)} or module:function)")
    return Processor(name=name, method=method, prep=prep, window=window)


def _base_scenario(path, inline, source: str, base_dir: Path) -> dict:
    """The base scenario as a dict: the file's (if any), then the inline tables over it."""
    if not isinstance(inline, dict):
        raise _fail(source, "[scenario] must be a table of scenario tables")
    if path is not None:
        if not isinstance(path, str):
            raise _fail(source, f"[campaign] scenario must be a file path, got {path!r}")
        p = Path(path) if Path(path).is_absolute() else base_dir / path
        try:
            d = scenario_to_dict(load_scenario(p))
        except BttsimError as exc:
            raise _fail(source, f"[campaign] scenario: {exc}") from None
    else:
        d = {}
    d = _merge(d, inline)
    try:
        scenario_from_dict(d, source="[scenario]", base_dir=base_dir)
    except BttsimError as exc:
        raise _fail(source, str(exc)) from None
    return d


def _merge(a: dict, b: dict) -> dict:
    out = dict(a)
    for k, v in b.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def _flatten(d: dict, prefix: str = ""):
    """``[axes]`` entries as (dotted name, value): quoted keys and nested tables alike; a table
    with range keys is a value."""
    for k, v in d.items():
        name = f"{prefix}{k}"
        if isinstance(v, dict) and not (set(v) & {"start", "uniform"}):
            yield from _flatten(v, name + ".")
        else:
            yield name, v


def _axis(name: str, v, base: dict, master: int, source: str) -> Axis:
    where = f"[axes] {name!r}"
    if name == "run.seed":
        raise _fail(source, f"{where}: vary seeds with [campaign] seeds (a count or a list)")
    _check_path(name, base, source)
    if isinstance(v, list):
        values = v
    elif isinstance(v, dict):
        values = _range(v, name, master, source)
    else:
        raise _fail(source, f"{where} must be a list of values or a range table ({{start, stop, num}}, "
                            f"{{start, stop, step}}, {{uniform = [lo, hi], n}}), got {v!r}")
    if not values:
        raise _fail(source, f"{where} has no values")
    keys = [json.dumps(x, sort_keys=True) for x in values]
    if len(set(keys)) != len(keys):
        raise _fail(source, f"{where} repeats a value")
    return Axis(name=name, values=tuple(values))


def _range(v: dict, name: str, master: int, source: str) -> list:
    where = f"[axes] {name!r}"
    num = lambda x: isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)  # noqa: E731
    if "uniform" in v:
        if set(v) - {"uniform", "n"}:
            raise _fail(source, f"{where}: a draw takes uniform = [lo, hi] and n only")
        lo_hi, n = v["uniform"], v.get("n")
        if not (isinstance(lo_hi, list) and len(lo_hi) == 2 and all(map(num, lo_hi)) and lo_hi[0] < lo_hi[1]):
            raise _fail(source, f"{where}: uniform must be [lo, hi] with lo < hi, got {lo_hi!r}")
        n = _int(n, f"{where}: n", source, 1, MAX_RUNS)
        seq = np.random.SeedSequence([int(master), int.from_bytes(hashlib.sha256(name.encode()).digest()[:4], "big")])
        return [float(x) for x in np.random.default_rng(seq).uniform(lo_hi[0], lo_hi[1], n)]
    if set(v) - {"start", "stop", "num", "step"} or ("num" in v) == ("step" in v):
        raise _fail(source, f"{where}: a range is {{start, stop, num}} or {{start, stop, step}}, got {v!r}")
    start, stop = v.get("start"), v.get("stop")
    if not (num(start) and num(stop)):
        raise _fail(source, f"{where}: start and stop must be finite numbers, got {start!r}, {stop!r}")
    if "num" in v:
        n = _int(v["num"], f"{where}: num", source, 1, MAX_RUNS)
        return [float(x) for x in np.linspace(start, stop, n)]
    step = v["step"]
    if not num(step) or step == 0 or (stop - start) / step < 0:
        raise _fail(source, f"{where}: step must be a non-zero number towards stop, got {step!r}")
    n = int(math.floor((stop - start) / step * (1 + 1e-12))) + 1
    if n > MAX_RUNS:
        raise _fail(source, f"{where}: {n} values (at most {MAX_RUNS})")
    vals = [start + i * step for i in range(n)]
    return vals if all(isinstance(x, int) for x in (start, step)) else [float(x) for x in vals]


def _check_path(name: str, d: dict, source: str) -> None:
    """A dotted name must name a scenario field: ``section.key``, ``acquisition.signal.key``,
    ``excitation.key`` (every entry) or ``excitation.N.key``."""
    from ..scenario import SECTIONS, Scenario, scenario_to_dict as _to_dict

    full = _to_dict(Scenario())
    parts = name.split(".")
    node: Any = full
    for i, part in enumerate(parts):
        if isinstance(node, list):
            if part.isdigit():
                if int(part) >= len(d.get(parts[0], node)):
                    raise _fail(source, f"[axes] {name!r}: the base scenario has no entry {part} of [[{parts[0]}]]")
                node = node[0] if node else {}
                continue
            node = node[0] if node else {}
        if not isinstance(node, dict) or part not in node:
            known = list(node) if isinstance(node, dict) else []
            what = "section" if i == 0 else "key"
            raise _fail(source, f"[axes] {name!r}: no scenario {what} {part!r}"
                                f"{_hint(part, known or list(SECTIONS))} (a dotted name like "
                                f"acquisition.trigger_jitter_s)")
        node = node[part]
    if isinstance(node, dict):
        raise _fail(source, f"[axes] {name!r} names a table, not a field")


def _set_path(d: dict, name: str, value) -> dict:
    """A copy of the scenario dict ``d`` with the dotted field set (every excitation entry
    unless an index is given)."""
    out = json.loads(json.dumps(d))
    parts = name.split(".")

    def put(node, rest):
        if isinstance(node, list):
            if rest[0].isdigit():
                put(node[int(rest[0])], rest[1:])
            else:
                for e in node:
                    put(e, rest)
            return
        if len(rest) == 1:
            node[rest[0]] = value
            return
        node.setdefault(rest[0], [{}] if rest[0] == "excitation" else {})
        put(node[rest[0]], rest[1:])

    put(out, parts)
    return out


def expand(spec: CampaignSpec) -> list[RunSpec]:
    """Every run of the spec, validated: axis points in grid order (first axis outermost),
    replicates innermost. A bad value is a :class:`SpecError` naming the axis values.

    Each axis point's scenario is built and validated once: its runs differ only in ``[run]
    seed`` (checked when the spec is read; no check of a scenario reads it), so their TOML is
    the point's with the seed line changed (:func:`_seed_tomls`)."""
    runs, seen = [], {}
    grids = [a.values for a in spec.axes]
    for point in itertools.product(*grids):
        values = dict(zip(spec.axis_names, point))
        d = spec.base
        for n, v in values.items():
            d = _set_path(d, n, v)
        d = _set_path(d, "run.seed", spec.seeds[0])
        where = ", ".join(f"{n} = {v!r}" for n, v in values.items()) or "the base scenario"
        try:
            scn = scenario_from_dict(d, source="[scenario]", base_dir=spec.base_dir)
        except BttsimError as exc:
            raise _fail(spec.source, f"run with {where}: {exc}") from None
        for r, (seed, toml) in enumerate(zip(spec.seeds, _seed_tomls(scn, spec.seeds))):
            run_id = _run_id(toml, spec.processors)
            if run_id in seen:
                raise _fail(spec.source, f"runs {seen[run_id]} and {len(runs)} are the same scenario ({where})")
            seen[run_id] = len(runs)
            runs.append(RunSpec(run_id=run_id, index=len(runs), replicate=r, seed=seed, point=values,
                                scenario_toml=toml, processors=spec.processors, mcap=spec.mcap))
    return runs


def _seed_tomls(scn: Scenario, seeds) -> list[str]:
    """``dumps_toml`` of ``scn`` with each of ``seeds`` as its ``[run] seed``: two texts are
    written, and the others made from them by their one differing line (``seed = N``); the
    texts themselves when they differ otherwise."""
    def dumps(seed):
        return dumps_toml(replace(scn, run=replace(scn.run, seed=seed)))

    first = dumps(seeds[0])
    if len(seeds) == 1:
        return [first]
    other = seeds[1]
    a, b = first.split("\n"), dumps(other).split("\n")
    diff = [i for i, (x, y) in enumerate(zip(a, b)) if x != y]
    if len(a) != len(b) or len(diff) != 1 or (a[diff[0]], b[diff[0]]) != (f"seed = {seeds[0]}", f"seed = {other}"):
        return [dumps(seed) for seed in seeds]
    head, tail = "\n".join(a[:diff[0]]) + "\nseed = ", "\n" + "\n".join(a[diff[0] + 1:])
    return [f"{head}{seed}{tail}" for seed in seeds]


def _run_id(scenario_toml: str, processors) -> str:
    key = json.dumps({"scenario": scenario_toml, "processors": [repr(p) for p in processors],
                      "version": __version__}, sort_keys=True)
    return hashlib.sha256(key.encode()).hexdigest()[:16]

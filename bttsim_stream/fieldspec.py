"""Declared fields of the scenario's section dataclasses: one :class:`Spec` per field.

A field is declared once, with :func:`spec`: its default, kind, unit, bounds and a comment
template. From that one declaration come

* the validation (:func:`validate_fields`, called by each section's ``__post_init__``),
* the comment above the key in the TOML that ``bttsim scenario`` prints (:meth:`Spec.comment`),
* the ``Attributes`` section of the section's docstring (:func:`attributes_doc`),
* the row of the field table in ``schemas/scenario.md`` (:func:`markdown_table`).

The comment template may hold ``{unit}`` and ``{range}``; both are required when the field has
a unit or a bound, so a bound can never be missing from (or differ between) the file's comment,
the docstring and the schema table. Checks that span fields (``tip_chord_m <= tip_radius_m`` is
declared as a bound naming the sibling; the rest are small functions in
:mod:`bttsim_stream.scenario`) are stated in words in the template.

Every check raises :class:`~bttsim_stream.errors.ScenarioError` with one line naming the field,
e.g. ``[probes] angles_deg[2] must be finite, got nan``.
"""

from __future__ import annotations

import dataclasses
import json
import math
import numbers
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from .errors import ScenarioError

__all__ = ["Spec", "spec", "field_spec", "validate_fields", "comments", "attributes_doc", "markdown_table", "section"]


_BARE_KEY_RE = re.compile(r"[A-Za-z0-9_-]+")


# --------------------------------------------------------------------------------------
# TOML values
# --------------------------------------------------------------------------------------


def toml_key(k: Any) -> str:
    """A key as written in TOML: bare if possible, else quoted."""
    k = str(k)
    return k if _BARE_KEY_RE.fullmatch(k) else toml_string(k)


def toml_string(s: str) -> str:
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


def toml_value(v: Any) -> str:
    """One TOML value: str, int, float, bool, list of values, or an inline table."""
    if isinstance(v, (bool, np.bool_)):
        return "true" if v else "false"
    if isinstance(v, numbers.Integral):
        return str(int(v))
    if isinstance(v, numbers.Real):
        return repr(float(v))  # shortest repr: parses back to the same float
    if isinstance(v, str):
        return toml_string(v)
    if isinstance(v, Mapping):
        return "{" + ", ".join(f"{toml_key(k)} = {toml_value(x)}" for k, x in v.items()) + "}"
    if isinstance(v, (list, tuple)):
        if v and all(isinstance(x, Mapping) for x in v):
            return "[\n" + "".join(f"    {toml_value(x)},\n" for x in v) + "]"
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} as TOML")


# --------------------------------------------------------------------------------------
# Errors and value checks
# --------------------------------------------------------------------------------------


class FieldError(ScenarioError):
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
        super().__init__(one_line(text))

    def relabel(self, where: str) -> "FieldError":
        """The same error under another section label."""
        return FieldError(where, self.key, self.problem)


def one_line(text: str) -> str:
    return " ".join(str(text).split()) if ("\n" in text or "\r" in text) else text


def toml_type(value: Any) -> str:
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


def show(value: Any, limit: int = 60) -> str:
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
        text = "{" + ", ".join(f"{toml_key(k)} = {show(v, limit)}" for k, v in value.items()) + "}"
    elif isinstance(value, (list, tuple)):
        text = "[" + ", ".join(show(v, limit) for v in value) + "]"
    else:
        text = repr(value)
    text = one_line(text)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def got(value: Any) -> str:
    """``"got <type> <value>"`` for a value of the wrong type."""
    return f"got {toml_type(value)} {show(value)}"


def _num(x: float) -> str:
    """A bound in a message: ``0``, ``0.5``, ``1e+06``."""
    return f"{x:g}"


def _is_real(value: Any) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))


def _is_int(value: Any) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, (bool, np.bool_))


def check_real(where: str, key: str, value: Any, *, lo: float | None = None, lo_open: bool = False,
               hi: float | None = None, hi_open: bool = False, names: tuple[str, str] = ("", "")) -> float:
    """Check a finite real number within optional bounds; return it as a float.

    ``names`` are the fields the bounds come from, if any (shown as ``name = value``).
    """
    if not _is_real(value):
        raise FieldError(where, key, f"must be a number, {got(value)}")
    try:
        x = float(value)
    except OverflowError:  # an integer beyond any float
        raise FieldError(where, key, f"must be finite, got an integer of {len(str(int(value)))} digits") from None
    if not math.isfinite(x):
        raise FieldError(where, key, f"must be finite, got {show(x)}")
    too_low = lo is not None and (x <= lo if lo_open else x < lo)
    too_high = hi is not None and (x >= hi if hi_open else x > hi)
    if too_low or too_high:
        shown = [None if b is None else f"{n} = {show(b)}" if n else _num(b) for b, n in zip((lo, hi), names)]
        raise FieldError(where, key, f"must be {_interval(*shown, lo_open, hi_open, str)}, got {show(x)}")
    return x


def _interval(lo: Any, hi: Any, lo_open: bool, hi_open: bool, fmt: Callable[[Any], str]) -> str:
    """``in [lo, hi)``, ``> lo`` or ``<= hi``; the bounds written by ``fmt``."""
    if lo is not None and hi is not None:
        return f"in {'(' if lo_open else '['}{fmt(lo)}, {fmt(hi)}{')' if hi_open else ']'}"
    if lo is not None:
        return f"{'>' if lo_open else '>='} {fmt(lo)}"
    return f"{'<' if hi_open else '<='} {fmt(hi)}"


def check_integer(where: str, key: str, value: Any, *, lo: int | None = None,
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
        raise FieldError(where, key, f"must be {what}, {got(value)}")
    n = int(value)
    if (lo is not None and n < lo) or (hi is not None and n > hi):
        raise FieldError(where, key, f"must be {what}, got {show(n)}")
    return n


def check_boolean(where: str, key: str, value: Any) -> bool:
    """Check a boolean (``true``/``false``; 0 and 1 are not booleans)."""
    if not isinstance(value, (bool, np.bool_)):
        raise FieldError(where, key, f"must be true or false, {got(value)}")
    return bool(value)


def check_string(where: str, key: str, value: Any, *, choices: Sequence[str] | None = None) -> str:
    """Check a string, optionally one of ``choices`` (case-sensitive)."""
    if choices:
        allowed = ", ".join(json.dumps(c) for c in choices)
        if not isinstance(value, str):
            raise FieldError(where, key, f"must be one of {allowed}, {got(value)}")
        if value not in choices:
            raise FieldError(where, key, f"must be one of {allowed}, got {show(value)}")
        return value
    if not isinstance(value, str):
        raise FieldError(where, key, f"must be a string, {got(value)}")
    return value


def check_sequence(where: str, key: str, value: Any, what: str) -> list[Any]:
    """Check an array (list, tuple or 1-D numpy array) and return its items as a list."""
    if isinstance(value, np.ndarray) and value.ndim == 1:
        return value.tolist()
    if not isinstance(value, (list, tuple)):
        raise FieldError(where, key, f"must be {what}, {got(value)}")
    return list(value)


def check_real_tuple(where: str, key: str, value: Any, **bounds: Any) -> tuple[float, ...]:
    """Check an array of finite reals, each within ``bounds`` (see :func:`check_real`)."""
    items = check_sequence(where, key, value, "an array of numbers")
    return tuple(check_real(where, f"{key}[{i}]", v, **bounds) for i, v in enumerate(items))


def check_choices(where: str, key: str, value: Any, choices: Sequence[str]) -> str | tuple[str, ...]:
    """One of ``choices``, or a non-empty array of them (one per probe)."""
    if isinstance(value, str):
        return check_string(where, key, value, choices=choices)
    items = check_sequence(where, key, value, "a string or an array of strings (one per probe)")
    if not items:
        raise FieldError(where, key, "must not be an empty array")
    return tuple(check_string(where, f"{key}[{i}]", v, choices=choices) for i, v in enumerate(items))


# --------------------------------------------------------------------------------------
# The declaration
# --------------------------------------------------------------------------------------

#: Kinds of field: how a value is checked and what type the docstring names.
KINDS = {
    "float": "float",
    "int": "int",
    "bool": "bool",
    "str": "str",
    "floats": "tuple of float",
    "choice_each": "str or tuple of str",
    "custom": "",
}


@dataclass(frozen=True, slots=True)
class _Shown:
    unit: str
    range: str


@dataclass(frozen=True, slots=True)
class Spec:
    """How one scenario field is checked and documented.

    Attributes
    ----------
    kind : str
        One of :data:`KINDS`: ``"float"`` (finite real; an integer is accepted), ``"int"``,
        ``"bool"``, ``"str"`` (optionally one of ``choices``), ``"floats"`` (an array of finite
        reals, each within the bounds), ``"choice_each"`` (one of ``choices`` or an array of
        them, one per probe) or ``"custom"`` (``check`` does everything).
    template : str
        The comment above the key in the commented TOML (lines split on ``\\n``), with ``{unit}``
        and ``{range}`` where the unit and the bounds go.
    unit : str
        Unit, e.g. ``"m"``, ``"rpm"``; empty for a dimensionless value.
    lo, hi : float, int, str or None
        Bounds; a string names an earlier field of the same section (its checked value).
    lo_open, hi_open : bool
        Exclusive bounds.
    zero_off : str
        If set, 0 is also allowed and means this (e.g. ``"no quantisation"``); the bounds
        apply to any other value.
    choices : tuple of str
        Allowed strings of ``"str"`` and ``"choice_each"``.
    check : callable or None
        ``check(where, key, value) -> value``: run after the kind's check (for ``"custom"``,
        instead of it) and returns the stored value.
    count : tuple of int or None
        ``(fewest, most)`` items of a ``"floats"`` array; shown by ``{count}``.
    cross_hi : str
        An upper bound that depends on another section (e.g. ``"n_blades"``): documented in
        ``{range}`` with ``hi_open``, checked by :class:`~bttsim_stream.scenario.Scenario`.
    type_name : str
        The type the docstring names, for ``"custom"``.
    note : str
        More detail for the docstring and the schema table (not the TOML comment).
    """

    kind: str
    template: str
    unit: str = ""
    lo: float | int | str | None = None
    hi: float | int | str | None = None
    lo_open: bool = False
    hi_open: bool = False
    zero_off: str = ""
    choices: tuple[str, ...] = ()
    check: Callable[[str, str, Any], Any] | None = None
    count: tuple[int, int] | None = None
    cross_hi: str = ""
    type_name: str = ""
    note: str = ""

    def range_text(self) -> str:
        """The bounds in words, as the comment and the schema write them: ``in (0, 10]``."""
        if self.choices:
            quoted = [json.dumps(c) for c in self.choices]
            return ", ".join(quoted[:-1]) + " or " + quoted[-1] if len(quoted) > 1 else quoted[0]
        hi = self.hi if self.hi is not None else (self.cross_hi or None)
        if self.lo is None and hi is None:
            return ""
        return _interval(self.lo, hi, self.lo_open, self.hi_open, _doc_num)

    def count_text(self) -> str:
        """``1 to 64`` (or ``3``) items of an array."""
        if self.count is None:
            return ""
        a, b = self.count
        return str(a) if a == b else f"{a} to {b}"

    def comment(self, siblings: Mapping[str, "Spec"] | None = None) -> str:
        """The comment written above the key in the commented TOML (may span lines).

        ``siblings`` (the section's specs) serve ``{f[name].unit}`` and ``{f[name].range}``.
        """
        return self._formatted(_shown(siblings or {}))

    def _formatted(self, shown: Mapping[str, _Shown]) -> str:
        return self.template.format(unit=self.unit, range=self.range_text(), count=self.count_text(), f=shown)

    def validate(self, where: str, key: str, value: Any, siblings: Any) -> Any:
        """Check ``value`` against this spec; return it normalised (floats, tuples).

        ``siblings`` is the section being checked, for bounds that name another field.
        """
        lo = getattr(siblings, self.lo) if isinstance(self.lo, str) else self.lo
        hi = getattr(siblings, self.hi) if isinstance(self.hi, str) else self.hi
        if self.kind == "float":
            value = self._real(where, key, value, lo, hi)
        elif self.kind == "int":
            value = check_integer(where, key, value, lo=lo, hi=None if isinstance(self.hi, str) else hi)
            if isinstance(self.hi, str) and value > hi:  # type: ignore[operator]
                raise FieldError(where, key, f"must be <= {self.hi} = {hi}, got {value}")
        elif self.kind == "floats":
            value = check_real_tuple(where, key, value, lo=lo, lo_open=self.lo_open, hi=hi, hi_open=self.hi_open)
            if self.count is not None and not self.count[0] <= len(value) <= self.count[1]:
                raise FieldError(where, key, f"must hold {self.count_text()} values, got {len(value)}")
        elif self.kind in _SIMPLE_CHECKS:
            value = _SIMPLE_CHECKS[self.kind](where, key, value, self.choices)
        return self.check(where, key, value) if self.check is not None else value

    def _real(self, where: str, key: str, value: Any, lo: Any, hi: Any) -> float:
        if not self.zero_off:
            names = (self.lo if isinstance(self.lo, str) else "", self.hi if isinstance(self.hi, str) else "")
            return check_real(where, key, value, lo=lo, lo_open=self.lo_open, hi=hi, hi_open=self.hi_open,
                              names=names)
        value = check_real(where, key, value, lo=0)
        if value and not (lo <= value <= hi):
            raise FieldError(where, key, f"must be 0 ({self.zero_off}) or "
                             f"{_interval(lo, hi, False, False, _num)}, got {show(value)}")
        return value


#: Checks of the kinds that need no bounds: ``(where, key, value, choices) -> value``.
_SIMPLE_CHECKS: dict[str, Callable[[str, str, Any, tuple[str, ...]], Any]] = {
    "bool": lambda where, key, value, choices: check_boolean(where, key, value),
    "str": lambda where, key, value, choices: check_string(where, key, value, choices=choices),
    "choice_each": check_choices,
}


def spec(default: Any = dataclasses.MISSING, *, kind: str, doc: str,
         default_factory: Any = dataclasses.MISSING, **options: Any) -> Any:
    """A dataclass field declared by its :class:`Spec` (the keyword arguments besides ``default``).

    Raises
    ------
    ValueError
        At import, if the comment template leaves out the unit or the bounds of the field.
    """
    s = Spec(kind=kind, template=doc, **options)
    if kind not in KINDS:
        raise ValueError(f"unknown field kind {kind!r}")
    if s.unit and "{unit}" not in doc:
        raise ValueError(f"comment {doc!r} does not show the unit {s.unit!r} ({{unit}})")
    if s.count and "{count}" not in doc:
        raise ValueError(f"comment {doc!r} does not show the item count ({{count}})")
    if s.choices and "{range}" not in doc and not all(json.dumps(c) in doc for c in s.choices):
        raise ValueError(f"comment {doc!r} does not show every choice of {s.choices}")
    if not s.choices and s.range_text() and "{range}" not in doc:
        raise ValueError(f"comment {doc!r} does not show the bounds {s.range_text()!r} ({{range}})")
    return dataclasses.field(default=default, default_factory=default_factory, metadata={"spec": s})


def field_spec(f: dataclasses.Field) -> Spec:
    """The :class:`Spec` of a section field."""
    return f.metadata["spec"]


def validate_fields(obj: Any, where: str, skip: Sequence[str] = ()) -> None:
    """Check every declared field of a frozen section dataclass in order, storing the
    normalised values (inside ``__post_init__`` only)."""
    for f in dataclasses.fields(obj):
        if f.name not in skip:
            object.__setattr__(obj, f.name, field_spec(f).validate(where, f.name, getattr(obj, f.name), obj))


def _doc_num(x: Any) -> str:
    """A bound in the documentation: ``200``, ``0.5``, ``1e6``, or a field name."""
    if isinstance(x, str):
        return x
    if _is_int(x):
        bits = int(x).bit_length()
        return f"2**{bits} - 1" if bits > 32 and x == 2**bits - 1 else str(x)
    exponent = round(math.log10(abs(x))) if x else 0
    if abs(x) >= 1e3 and x == 10.0**exponent:
        return f"1e{exponent}"
    return f"{x:g}"


# --------------------------------------------------------------------------------------
# Documentation generated from the declarations
# --------------------------------------------------------------------------------------


def _default(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    return f.default_factory()  # type: ignore[misc]


def _toml_default(f: dataclasses.Field) -> str:
    value = _default(f)
    if dataclasses.is_dataclass(value):
        return "table"
    return toml_value(list(value) if isinstance(value, tuple) else value)


def _specs(cls: type) -> dict[str, Spec]:
    return {f.name: field_spec(f) for f in dataclasses.fields(cls)}


def comments(cls: type) -> dict[str, str]:
    """The TOML comment of every field of a section dataclass."""
    specs = _specs(cls)
    shown = _shown(specs)  # once a section, not once a field (every section's docstring is made at import)
    return {name: s._formatted(shown) for name, s in specs.items()}


def _shown(specs: Mapping[str, Spec]) -> dict[str, _Shown]:
    return {k: _Shown(v.unit, v.range_text()) for k, v in specs.items()}


def _sentence(text: str) -> str:
    """One sentence for the docstring and the schema: capitalised, ends with a full stop."""
    text = " ".join(text.split())
    text = text[:1].upper() + text[1:] if text[:1].islower() else text
    return text if text.endswith(".") else text + "."


def attributes_doc(cls: type) -> str:
    """The numpydoc ``Attributes`` section of a section dataclass, from its declarations."""
    lines = ["", "    Attributes", "    ----------"]
    text_of = comments(cls)
    for f in dataclasses.fields(cls):
        s = field_spec(f)
        lines.append(f"    {f.name} : {s.type_name or KINDS[s.kind]}")
        text = _sentence(text_of[f.name]) + f" Default ``{_toml_default(f)}``."
        if s.note:
            text += " " + _sentence(s.note)
        words, line = text.split(), "       "
        for w in words:
            if len(line) + 1 + len(w) > 92:
                lines.append(line)
                line = "       "
            line += " " + w
        lines.append(line)
    return "\n".join(lines) + "\n"


def section(cls: type) -> type:
    """Class decorator: append the generated ``Attributes`` section to the docstring."""
    cls.__doc__ = (cls.__doc__ or "").rstrip() + "\n" + attributes_doc(cls)
    return cls


def markdown_table(cls: type) -> str:
    """The schema table of a section: key, unit, default, constraint and meaning."""
    rows = ["| key | unit | default | meaning and constraint |", "|---|---|---|---|"]
    text_of = comments(cls)
    for f in dataclasses.fields(cls):
        s = field_spec(f)
        text = _sentence(text_of[f.name])
        if s.note:
            text += " " + _sentence(s.note)
        text = text.replace("|", "\\|")
        rows.append(f"| `{f.name}` | {s.unit or '–'} | `{_toml_default(f)}` | {text} |")
    return "\n".join(rows) + "\n"

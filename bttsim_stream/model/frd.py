"""CalculiX ``.frd`` results (ASCII) of ``*FREQUENCY`` steps, with or without cyclic symmetry.

The ``.frd`` format (CalculiX GraphiX manual, "Result Format") is a sequence of blocks, each
opened by a key line and closed by `` -3``:

* ``    2C`` nodes: `` -1`` + node number + x, y, z;
* ``    3C`` elements (skipped here);
* ``    1P...`` parameter lines before a result block: ``1PMODE`` (mode number), ``1PGM``
  (generalised mass), ``1PGK`` (eigenvalue) and, in a cyclic symmetry analysis, ``1PHID``
  (harmonic index = nodal diameter) and ``1PAX`` (the cyclic axis: a point and a direction);
* ``  100C`` result block: the value field holds the frequency (cycles per time unit) of a
  ``MODAL`` step; then `` -4  NAME  ncomps``, the component lines `` -5``, one `` -1`` line per
  node (node number I5 or I10 by the block's format flag 0 or 1, values E12.5);
* `` 9999`` ends the file.

With ``*CYCLIC SYMMETRY MODEL`` CalculiX writes, for every nodal diameter and every mode pair
(it finds each eigenvalue twice), the real part of the complex sector mode as ``DISP`` and its
imaginary part as ``DISPI``, on the ``NGRAPH`` sectors it is asked to draw; the modes are
mass-normalised (``1PGM`` = 1) on the cyclic-reduced sector. Node numbers of the copies drawn
beyond the first sector are offset by the largest node number of the model.

This module only reads; :mod:`bttsim_stream.model.importers` turns the result into a
:class:`~bttsim_stream.model.cyclic.CyclicSector`.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

from ..errors import ModelFileError

__all__ = ["FrdMode", "FrdResults", "read_frd", "MAX_ABS_VALUE", "MAX_COMPONENTS"]

_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")


@dataclass(frozen=True, slots=True, eq=False)
class FrdMode:
    """One eigenmode's displacement result.

    Attributes
    ----------
    step : int
        Step number (``1PSTEP``), 0 if not given.
    mode : int
        ``1PMODE`` (CalculiX numbering within its nodal diameter).
    freq_hz : float
        Frequency, cycles per time unit (Hz in SI decks).
    harmonic_index : int or None
        ``1PHID`` (nodal diameter) of a cyclic symmetry result; None otherwise.
    generalised_mass : float
        ``1PGM`` (1 for mass-normalised modes); NaN if absent.
    u : ndarray, shape (n_nodes, 3)
        ``DISP`` (the real part for a cyclic result), in the order of :attr:`FrdResults.node_ids`.
    u_imag : ndarray, shape (n_nodes, 3), or None
        ``DISPI`` (imaginary part) of a cyclic result.
    """

    step: int
    mode: int
    freq_hz: float
    harmonic_index: int | None
    generalised_mass: float
    u: np.ndarray
    u_imag: np.ndarray | None


@dataclass(frozen=True, slots=True, eq=False)
class FrdResults:
    """What a ``.frd`` file holds that the importer needs.

    Attributes
    ----------
    node_ids : ndarray of int64, shape (n_nodes,)
    xyz : ndarray, shape (n_nodes, 3)
        Undeformed node coordinates.
    modes : tuple of FrdMode
        Every displacement result of a MODAL step, in file order (``DISP`` and ``DISPI`` of
        a cyclic mode merged into one).
    cyclic_axis : ndarray, shape (6,), or None
        ``1PAX``: a point of the axis and its direction.
    """

    node_ids: np.ndarray
    xyz: np.ndarray
    modes: tuple
    cyclic_axis: np.ndarray | None

    def index_of(self, ids) -> np.ndarray:
        """Row indices of node numbers ``ids`` (:class:`ModelFileError` for an unknown one)."""
        ids = np.asarray(ids, dtype=np.int64)
        order = np.argsort(self.node_ids)
        pos = np.searchsorted(self.node_ids, ids, sorter=order)
        pos = np.minimum(pos, self.node_ids.size - 1)
        rows = order[pos]
        bad = ids[self.node_ids[rows] != ids]
        if bad.size:
            raise ModelFileError(f"node(s) {', '.join(map(str, bad[:5].tolist()))} not in the results")
        return rows


#: A fixed-width number as CalculiX prints it (``%12.5E``, ``%10d``): digits, a point, an
#: exponent; Python's extras (``nan``, ``inf``, ``1_000``, hex) are not numbers here.
_FLOAT_FIELD = re.compile(r"\s*[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?\s*\Z")
_INT_FIELD = re.compile(r"\s*[-+]?\d+\s*\Z")
#: Components a result block may announce (CalculiX writes at most a few dozen: a 3x3 tensor
#: and its invariants); a larger count is a corrupt header, refused before anything is read.
MAX_COMPONENTS = 64
#: The largest magnitude of a value: beyond it no coordinate, displacement or frequency is a
#: result, and squares and products of such values (an SVD of the tip line, a mode's energy)
#: would overflow to inf.
MAX_ABS_VALUE = 1e100
#: The largest harmonic index (nodal diameter) and mode number accepted from a 1P parameter line.
MAX_PARAMETER = 10**6


class _Lines:
    """The lines of one file and the checks of its fixed-width fields: every error is one line
    naming the file, the line number, the columns and what was expected."""

    def __init__(self, where: str, lines: list):
        self.where, self.lines = where, lines

    def error(self, j: int, message: str) -> ModelFileError:
        return ModelFileError(f"{self.where}:{j + 1}: {message}")

    def _field(self, j: int, a: int, b: int, what: str, expected: str) -> str:
        field = self.lines[j][a:b]
        if not field.strip():
            ends = len(self.lines[j].rstrip())
            where = f"the line ends at column {ends}" if ends < b else "blank"
            raise self.error(j, f"{what}: expected {expected} in columns {a + 1}-{b}, {where}")
        return field

    def int(self, j: int, a: int, b: int, what: str, lo: int = 0, hi: int = 2**31 - 1) -> int:
        """The integer in columns [a, b) of line j, within [lo, hi]."""
        field = self._field(j, a, b, what, "an integer")
        if not _INT_FIELD.match(field):
            raise self.error(j, f"{what}: expected an integer in columns {a + 1}-{b}, got {field.strip()!r}")
        v = int(field)
        if not lo <= v <= hi:
            raise self.error(j, f"{what}: expected an integer in [{lo}, {hi}], got {v}")
        return v

    def float(self, j: int, a: int, b: int, what: str) -> float:
        """The number in columns [a, b) of line j, within +-:data:`MAX_ABS_VALUE`."""
        field = self._field(j, a, b, what, "a number")
        if not _FLOAT_FIELD.match(field):
            raise self.error(j, f"{what}: expected a number (E12.5) in columns {a + 1}-{b}, got {field.strip()!r}")
        v = float(field)
        if not abs(v) <= MAX_ABS_VALUE:
            raise self.error(j, f"{what}: expected a number within +-{MAX_ABS_VALUE:g} in columns {a + 1}-{b}, "
                                f"got {field.strip()!r}")
        return v

    def word(self, j: int, text: str, what: str, lo: int = 0, hi: int = MAX_PARAMETER) -> int:
        """An integer given as free text (the value of a 1P parameter line)."""
        if not _INT_FIELD.match(text):
            raise self.error(j, f"{what}: expected an integer, got {text.strip()[:40]!r}")
        v = int(text)
        if not lo <= v <= hi:
            raise self.error(j, f"{what}: expected an integer in [{lo}, {hi}], got {v}")
        return v


def _format_flag(lines: _Lines, j: int, a: int, b: int) -> bool:
    """True for the long (I10 node number) layout: format flag 1 (or blank), 0 the short one."""
    flag = lines.lines[j][a:b].strip() or "1"
    if flag not in ("0", "1"):
        hint = " (2 is binary: not supported)" if flag == "2" else ""
        raise lines.error(j, f"format flag in columns {a + 1}-{b}: expected 0 (short) or 1 (long), got {flag!r}{hint}")
    return flag == "1"


def _block_rows(lines: _Lines, i0: int, long_ids: bool, ncomp: int, what: str, count: int, head: int):
    """The ``-1`` rows of a block from line ``i0``: node numbers, values (ncomp per row, E12.5
    after the node number) and the index of its `` -3`` line. ``ncomp = 0`` reads node numbers
    only (a block whose values are not needed, whose layout is then not checked)."""
    n = len(lines.lines)
    if count > n - i0:  # bounded before anything is read: a row per line at most
        raise lines.error(head, f"truncated .frd file: the {what} block announces {count} nodes, "
                                f"the file has {n - i0} lines left")
    w = 10 if long_ids else 5
    end = 3 + w + 12 * ncomp
    ids: list[int] = []
    vals: list[list[float]] = []
    seen: set[int] = set()
    j = i0
    while j < n:
        ln = lines.lines[j]
        key = ln[:3]
        if key == " -3":
            if len(ids) != count:
                raise lines.error(head, f"the {what} block announces {count} nodes, holds {len(ids)} "
                                        f"(lines {i0 + 1}-{j + 1})")
            return ids, vals, j
        if key == " -1":
            if len(ids) == count:
                raise lines.error(j, f"more rows than the {count} the {what} block announces (line {head + 1})")
            k = lines.int(j, 3, 3 + w, f"node number of the {what} block", lo=1)
            if k in seen:
                raise lines.error(j, f"node {k} twice in the {what} block")
            seen.add(k)
            ids.append(k)
            if ncomp:
                if ln[end:].strip():
                    raise lines.error(j, f"{what} row: expected the node number and {ncomp} values (E12.5) "
                                         f"in columns 4-{end}, found more after column {end}")
                vals.append([lines.float(j, 3 + w + 12 * c, 3 + w + 12 * (c + 1), f"{what} value {c + 1}")
                             for c in range(ncomp)])
        elif key == " -2" and not ncomp:
            pass  # continuation of a row with more than 6 values (not read)
        else:
            raise lines.error(j, f"unexpected line in the {what} block (expected ' -1' rows and ' -3')")
        j += 1
    raise ModelFileError(f"{lines.where}: truncated .frd file (the {what} block is not closed)")


def _parameter(lines: _Lines, j: int, key: str, value: str):
    """A parsed 1P parameter value (None for one this reader does not use)."""
    what = f"1P{key}"
    if key == "MODE":
        return lines.word(j, value, what, lo=0)
    if key == "HID":
        return lines.word(j, value, what + " (harmonic index)", lo=-1)  # -1: not a cyclic result
    if key == "STEP":  # result-set counter, increment, step number
        parts = value.split()
        if len(parts) < 3:
            return 0
        return lines.word(j, parts[2], what + " step number", lo=0, hi=2**31 - 1)
    if key == "GM":
        field = value.split()[0] if value.split() else ""
        v = float(field) if _FLOAT_FIELD.match(field) else math.nan
        if not (math.isfinite(v) and v > 0):
            raise lines.error(j, f"1PGM (generalised mass): expected a positive number, got {value.strip()[:40]!r}")
        return v
    return None


def _frd_lines(path) -> _Lines:
    """The lines of an ASCII ``.frd`` file, numbered as an editor does; refuses what is not one."""
    where = str(path)
    try:
        with open(path, "rb") as fh:
            raw = fh.read()
    except FileNotFoundError:
        raise ModelFileError(f"{where}: no such file") from None
    except IsADirectoryError:
        raise ModelFileError(f"{where}: a directory, not a .frd file") from None
    except OSError as exc:
        raise ModelFileError(f"{where}: cannot read ({exc.strerror or exc})") from None
    try:
        text = raw.decode("ascii")
    except UnicodeDecodeError:
        raise ModelFileError(f"{where}: not an ASCII .frd file (binary results are not supported: "
                             "leave *NODE FILE output in CalculiX's default ASCII format)") from None
    if "\0" in text:
        raise ModelFileError(f"{where}: not a text file (NUL bytes)")
    lines = _Lines(where, [ln.rstrip("\r") for ln in text.split("\n")])  # numbered as an editor does
    if not lines.lines or not lines.lines[0].lstrip().startswith("1C"):
        raise ModelFileError(f"{where}: not a CalculiX .frd file (it must start with '1C')")
    return lines


def read_frd(path) -> FrdResults:
    """Read the nodes and the eigenmode displacements of an ASCII CalculiX ``.frd`` file.

    Every field the importer uses is checked as it is read: node numbers and values in their
    columns, finite numbers, block sizes against their headers, component counts, parameter
    values.

    Raises
    ------
    ModelFileError
        Missing, binary, truncated or malformed file (one line: the file, the line number, the
        columns and what was expected); no node block; no displacement result.
    """
    lines = _frd_lines(path)
    where, n = lines.where, len(lines.lines)
    node_ids = xyz = None
    row_of: dict[int, int] = {}
    modes: list[FrdMode] = []
    params: dict[str, object] = {}
    axis = None
    pending: dict[tuple, dict] = {}
    ended = False
    i = 0

    while i < n:
        ln = lines.lines[i]
        s = ln.strip()
        if s.startswith("2C"):
            # (1X,'   2','C',18X,I12,37X,I1)
            count = lines.int(i, 24, 36, "node count of the node block")
            ids, vals, i_end = _block_rows(lines, i + 1, _format_flag(lines, i, 73, 74), 3, "node", count, i)
            if node_ids is not None and ids != node_ids.tolist():
                raise lines.error(i, "a second node block (2C) with other nodes than the first")
            node_ids = np.array(ids, dtype=np.int64)
            xyz = np.array(vals, dtype=float).reshape(-1, 3)
            row_of = {k: r for r, k in enumerate(ids)}
            i = i_end
        elif s.startswith("3C"):
            j = i + 1
            while j < n and lines.lines[j][:3] != " -3":
                j += 1
            if j >= n:
                raise ModelFileError(f"{where}: truncated .frd file (the element block is not closed)")
            i = j
        elif s.startswith("1P"):
            key = s[:8].split()[0]
            value = ln[len(ln) - len(ln.lstrip()) + len(key):]
            params[key[2:]] = _parameter(lines, i, key[2:], value)
            if key == "1PAX":
                nums = _NUMBER.findall(value)
                ax = np.array([float(v) for v in nums]) if len(nums) == 6 else None
                if ax is None or not np.all(np.abs(ax) <= MAX_ABS_VALUE) or not np.any(np.abs(ax[3:]) > 1e-100):
                    raise lines.error(i, "1PAX: expected 6 numbers (axis point and a non-zero direction), "
                                         f"got {value.strip()[:80]!r}")
                axis = ax
        elif s.startswith("100C"):
            if node_ids is None:
                raise lines.error(i, "results before the node block (2C)")
            # (1X,' 100','C',6A1,E12.5,I12,20A1,I2,I5,10A1,I2)
            analysis = ln[63:73].strip()
            long_ids = _format_flag(lines, i, 73, 75)
            freq = lines.float(i, 12, 24, "value (the frequency) of the result block")
            count = lines.int(i, 24, 36, "node count of the result block")
            j = i + 1
            if j >= n or not lines.lines[j].startswith(" -4"):
                raise lines.error(j if j < n else i, "a result block without its ' -4' header")
            # (1X,' -4',2X,8A1,2I5): name, number of components, type
            name = lines.lines[j][5:13].strip()
            ncomp = lines.int(j, 13, 18, f"number of components of {name or 'the result'}", 0, MAX_COMPONENTS)
            disp = name in ("DISP", "DISPI")
            if disp and ncomp < 3:
                raise lines.error(j, f"{name} with {ncomp} components: expected 3 (D1, D2, D3) or 4 (and ALL)")
            j += 1
            while j < n and lines.lines[j].startswith(" -5"):
                j += 1
            i_head = i
            ids, vals, i = _block_rows(lines, j, long_ids, 3 if disp else 0, name or "result", count, i)
            if disp and analysis.upper().startswith("MODAL"):
                head = i_head
                hid = params.get("HID")
                mode_no = params.get("MODE") or 0
                step = params.get("STEP") or 0
                gm = params.get("GM")
                u = np.zeros((node_ids.size, 3))
                try:
                    sel = [row_of[k] for k in ids]
                except KeyError as exc:
                    raise ModelFileError(f"{where}: result for node {exc.args[0]} that has no coordinates") from None
                u[sel] = vals
                key = (step, mode_no, hid, freq)
                d = pending.setdefault(key, {"freq": freq, "hid": hid, "gm": float("nan") if gm is None else gm,
                                             "mode": mode_no, "step": step, "line": head})
                if name in d:
                    raise lines.error(i, f"{name} of mode {mode_no} (harmonic index {hid}, {freq:g} Hz) twice")
                d[name] = u
        elif s == "9999":
            ended = True
            break
        i += 1
    if not ended:
        raise ModelFileError(f"{where}: truncated .frd file (no end record 9999)")
    if node_ids is None:
        raise ModelFileError(f"{where}: no node block (2C) in the file")
    for d in pending.values():
        if "DISP" not in d:
            raise ModelFileError(f"{where}:{d['line'] + 1}: DISPI of mode {d['mode']} (harmonic index {d['hid']}, "
                                 f"{d['freq']:g} Hz) has no DISP with the same 1PSTEP, 1PMODE, 1PHID and frequency")
        modes.append(FrdMode(step=d["step"], mode=d["mode"], freq_hz=d["freq"], harmonic_index=d["hid"],
                             generalised_mass=d["gm"], u=d["DISP"], u_imag=d.get("DISPI")))
    if not modes:
        raise ModelFileError(f"{where}: no eigenmode displacements (a *FREQUENCY step with *NODE FILE U)")
    return FrdResults(node_ids=node_ids, xyz=xyz, modes=tuple(modes), cyclic_axis=axis)

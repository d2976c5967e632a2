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

import re
from dataclasses import dataclass

import numpy as np

from ..errors import ModelFileError

__all__ = ["FrdMode", "FrdResults", "read_frd"]

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


def _float(s: str, where: str) -> float:
    try:
        return float(s)
    except ValueError:
        raise ModelFileError(f"{where}: not a number {s.strip()!r}") from None


def _values(line: str, start: int, n: int, where: str) -> list[float]:
    out = []
    for i in range(n):
        field = line[start + 12 * i:start + 12 * (i + 1)]
        out.append(_float(field, where) if field.strip() else 0.0)
    return out


def read_frd(path) -> FrdResults:
    """Read the nodes and the eigenmode displacements of an ASCII CalculiX ``.frd`` file.

    Raises
    ------
    ModelFileError
        Missing, binary, truncated or malformed file; no node block; no displacement result.
    """
    where = str(path)
    try:
        with open(path, "rb") as fh:
            raw = fh.read()
    except FileNotFoundError:
        raise ModelFileError(f"{where}: no such file") from None
    except OSError as exc:
        raise ModelFileError(f"{where}: cannot read ({exc.strerror or exc})") from None
    try:
        text = raw.decode("ascii")
    except UnicodeDecodeError:
        raise ModelFileError(f"{where}: not an ASCII .frd file (binary results are not supported: "
                             "leave *NODE FILE output in CalculiX's default ASCII format)") from None
    lines = text.splitlines()
    if not lines or lines[0].strip() not in ("1C",) and not lines[0].lstrip().startswith("1C"):
        raise ModelFileError(f"{where}: not a CalculiX .frd file (it must start with '1C')")
    node_ids = xyz = None
    modes: list[FrdMode] = []
    params: dict[str, str] = {}
    axis = None
    pending: dict[tuple, dict] = {}
    ended = False
    i, n = 0, len(lines)

    def block_rows(i0: int, long_ids: bool, ncomp: int, what: str):
        """Rows of a -1 block from line i0; returns (ids, values, index of the -3 line)."""
        ids, vals = [], []
        w = 10 if long_ids else 5
        j = i0
        while j < n:
            ln = lines[j]
            key = ln[:3]
            if key == " -3":
                return ids, vals, j
            if key == " -1":
                try:
                    ids.append(int(ln[3:3 + w]))
                except ValueError:
                    raise ModelFileError(f"{where}:{j + 1}: bad node number in the {what} block") from None
                vals.append(_values(ln, 3 + w, ncomp, f"{where}:{j + 1}"))
            elif key != " -2" and key != " -5" and key != " -4":
                raise ModelFileError(f"{where}:{j + 1}: unexpected line in the {what} block")
            j += 1
        raise ModelFileError(f"{where}: truncated .frd file (the {what} block is not closed)")

    while i < n:
        ln = lines[i]
        s = ln.strip()
        if s.startswith("2C"):
            fmt = ln[-2:].strip() if len(ln) >= 74 else "1"
            ids, vals, i = block_rows(i + 1, fmt != "0", 3, "node")
            node_ids = np.array(ids, dtype=np.int64)
            xyz = np.array(vals, dtype=float).reshape(-1, 3)
        elif s.startswith("3C"):
            j = i + 1
            while j < n and lines[j][:3] != " -3":
                j += 1
            if j >= n:
                raise ModelFileError(f"{where}: truncated .frd file (the element block is not closed)")
            i = j
        elif s.startswith("1P"):
            key = s[:8].split()[0] if s[:8].split() else s[:8]
            params[key[1:]] = ln[len(ln) - len(ln.lstrip()) + len(key):]
            if key == "1PAX":
                nums = _NUMBER.findall(ln[len(ln) - len(ln.lstrip()) + 4:])
                if len(nums) != 6:
                    raise ModelFileError(f"{where}:{i + 1}: 1PAX needs 6 numbers (axis point and direction)")
                axis = np.array([float(v) for v in nums])
        elif s.startswith("100C"):
            if node_ids is None:
                raise ModelFileError(f"{where}: results before the node block")
            head = ln
            # (1X,' 100','C',6A1,E12.5,I12,20A1,I2,I5,10A1,I2)
            analysis = head[63:73].strip()
            fmt = head[73:75].strip() or "1"
            freq = _float(head[12:24], f"{where}:{i + 1}")
            j = i + 1
            if j >= n or not lines[j].startswith(" -4"):
                raise ModelFileError(f"{where}:{j + 1}: a result block without its ' -4' header")
            parts = lines[j].split()
            name = parts[1] if len(parts) > 1 else ""
            ncomp = int(parts[2]) if len(parts) > 2 and parts[2].isdigit() else 0
            j += 1
            while j < n and lines[j].startswith(" -5"):
                j += 1
            ids, vals, i = block_rows(j, fmt != "0", min(ncomp, 3) if name in ("DISP", "DISPI") else 0, name)
            if name in ("DISP", "DISPI") and analysis.upper().startswith("MODAL"):
                hid = params.get("PHID")
                mode_no = int(params.get("PMODE", "0").split()[0] or 0)
                # 1PSTEP: result-set counter, increment, step number
                pstep = params.get("PSTEP", "").split()
                step = int(pstep[2]) if len(pstep) > 2 else 0
                gm = params.get("PGM")
                u = np.zeros((node_ids.size, 3))
                rows = {int(k): r for r, k in enumerate(node_ids)}
                try:
                    sel = [rows[k] for k in ids]
                except KeyError as exc:
                    raise ModelFileError(f"{where}: result for node {exc.args[0]} that has no coordinates") from None
                u[sel] = np.array(vals, dtype=float).reshape(-1, 3)
                key = (step, mode_no, hid, freq)
                d = pending.setdefault(key, {"freq": freq, "hid": None if hid is None else int(hid.split()[0]),
                                             "gm": float(gm.split()[0]) if gm else float("nan"),
                                             "mode": mode_no, "step": step})
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
            raise ModelFileError(f"{where}: mode {d['mode']} (harmonic index {d['hid']}) has DISPI but no DISP")
        modes.append(FrdMode(step=d["step"], mode=d["mode"], freq_hz=d["freq"], harmonic_index=d["hid"],
                             generalised_mass=d["gm"], u=d["DISP"], u_imag=d.get("DISPI")))
    if not modes:
        raise ModelFileError(f"{where}: no eigenmode displacements (a *FREQUENCY step with *NODE FILE U)")
    return FrdResults(node_ids=node_ids, xyz=xyz, modes=tuple(modes), cyclic_axis=axis)

"""``bttsim model import``: a user's cyclic-symmetry FE results -> the project's model file.

Formats: ``npz`` (the neutral sector format, :mod:`bttsim_stream.model.cyclic`) and ``frd``
(CalculiX ``*FREQUENCY`` with ``*CYCLIC SYMMETRY MODEL``, :mod:`bttsim_stream.model.frd`).

For a ``.frd`` file the importer needs the number of sectors and which nodes are the tip
nodes and the excitation node. They come from :class:`ImportOptions` (a small TOML file and/or
command-line flags): nodes by number, by a named node set of the CalculiX input deck
(``*NSET``, read through its ``*INCLUDE`` files), or the nodes nearest to given coordinates;
the number of sectors from the deck's ``*CYCLIC SYMMETRY MODEL, N=...`` when not given.

Conventions: the FE model's frame must be the rotor frame (``+z`` the rotation axis, rotor
turning anticlockwise seen from ``+z``, trailing edge at larger ``z``). CalculiX writes the
complex sector mode ``DISP + i DISPI`` with the travelling-wave phase ``e^{+i k theta}`` about
the axis it reports (``1PAX``); when that axis is ``-z`` the mode is conjugated to the
project's convention (``e^{+i k theta_s}`` for sector ``s`` at ``+theta_s`` about ``+z``,
checked against a direct full-wheel solve by ``tests/test_model_import.py``).
"""

from __future__ import annotations

import math
import re
import tomllib
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

import numpy as np

from ..defaults import MAX_BLADES
from ..errors import ModelFileError
from .cyclic import TIP_RADIUS_RANGE_M, CyclicSector, expand_sector, load_sector
from .frd import read_frd

__all__ = ["ImportOptions", "ImportResult", "Deck", "load_import_options", "check_options", "import_model",
           "import_model_speeds", "read_deck_sets", "sector_from_frd", "format_report", "FORMATS"]

FORMATS = ("frd", "npz")
#: Length and mass scale of a deck's unit system to SI, and the shape factor that keeps the
#: modes mass-normalised: phi_SI = phi * length * sqrt(1 / mass-unit-in-kg) ... see _UNITS.
_UNITS = {"SI": 1.0, "mm-t-s": 1e-3}


@dataclass(frozen=True, slots=True)
class ImportOptions:
    """How to read a user's sector results (every field optional; see ``schemas/cyclic_sector.md``).

    Attributes
    ----------
    format : {"frd", "npz"} or None
        None: from the file's extension.
    deck : str or None
        CalculiX input deck (``.inp``) for node sets and ``N``; default: the results file with
        the ``.inp`` extension, if it exists.
    n_sectors : int or None
    tip_nodes : tuple of int
        Tip node numbers.
    tip_nset : str or None
        Name of the deck's node set of the tip nodes.
    tip_xyz : tuple of (x, y, z)
        Take the node nearest to each point (m in the deck's units).
    force_node : int or None
    force_nset : str or None
        A node set of exactly one node.
    force_xyz : tuple (x, y, z) or None
    nominal_node : int or None
        0-based tip node of P_nom (default: the middle one).
    stagger_deg : float or None
        Default: measured from the tip nodes.
    units : {"SI", "mm-t-s"}
        The deck's unit system (mm-t-s: mm, tonne, s, N, MPa).
    damping_beta_s : float
        Stiffness-proportional damping of the model file.
    n_families : int or None
        Families kept per nodal diameter (default: all that every ND has).
    speeds_rpm : tuple of float
        A speed-dependent model (:func:`import_model_speeds`): the speed of each results file,
        or of each ``*FREQUENCY`` step of one ``.frd`` file, rpm; strictly ascending from 0.
        Empty (default): one speed, zero.
    """

    format: str | None = None
    deck: str | None = None
    n_sectors: int | None = None
    tip_nodes: tuple = ()
    tip_nset: str | None = None
    tip_xyz: tuple = ()
    force_node: int | None = None
    force_nset: str | None = None
    force_xyz: tuple | None = None
    nominal_node: int | None = None
    stagger_deg: float | None = None
    units: str = "SI"
    damping_beta_s: float = 9e-6
    n_families: int | None = None
    speeds_rpm: tuple = ()


_FIELDS = {f.name for f in fields(ImportOptions)}


def load_import_options(path) -> ImportOptions:
    """Read an import options TOML file (relative paths are relative to it)."""
    where = str(path)
    try:
        data = tomllib.loads(Path(path).read_text())
    except FileNotFoundError:
        raise ModelFileError(f"{where}: no such file") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ModelFileError(f"{where}: not valid TOML ({exc})") from None
    unknown = sorted(set(data) - _FIELDS)
    if unknown:
        raise ModelFileError(f"{where}: unknown option(s) {', '.join(unknown)} (known: {', '.join(sorted(_FIELDS))})")
    if isinstance(data.get("deck"), str):
        data["deck"] = str((Path(path).parent / data["deck"]).resolve())
    for key in ("tip_nodes", "tip_xyz"):
        if key in data:
            data[key] = tuple(tuple(v) if isinstance(v, list) else v for v in data[key])
    if "force_xyz" in data:
        data["force_xyz"] = tuple(data["force_xyz"])
    if isinstance(data.get("speeds_rpm"), list):
        data["speeds_rpm"] = tuple(data["speeds_rpm"])
    try:
        return _checked(ImportOptions(**data), where)
    except TypeError as exc:
        raise ModelFileError(f"{where}: {exc}") from None


def check_options(o: ImportOptions, where: str = "import options") -> ImportOptions:
    """``o`` if its values are possible, else a one-line :class:`ModelFileError`."""
    return _checked(o, where)


def _checked(o: ImportOptions, where: str) -> ImportOptions:
    def bad(msg):
        raise ModelFileError(f"{where}: {msg}")

    if o.format is not None and o.format not in FORMATS + ("rst",):  # rst: import_model says why not
        bad(f"format must be one of {', '.join(FORMATS)}, got {o.format!r}")
    if o.units not in _UNITS:
        bad(f"units must be one of {', '.join(_UNITS)}, got {o.units!r}")
    if o.n_sectors is not None and (isinstance(o.n_sectors, bool) or not isinstance(o.n_sectors, int)
                                    or not 2 <= o.n_sectors <= MAX_BLADES):
        bad(f"n_sectors must be an integer in [2, {MAX_BLADES}] (the blades of a run), got {o.n_sectors!r}")
    if sum(bool(x) for x in (o.tip_nodes, o.tip_nset, o.tip_xyz)) > 1:
        bad("give the tip nodes one way: tip_nodes, tip_nset or tip_xyz")
    if sum(x is not None for x in (o.force_node, o.force_nset, o.force_xyz)) > 1:
        bad("give the excitation node one way: force_node, force_nset or force_xyz")
    if o.tip_nodes and not all(isinstance(i, int) for i in o.tip_nodes):
        bad("tip_nodes must be node numbers")
    if o.tip_xyz and not all(isinstance(p, tuple) and len(p) == 3 for p in o.tip_xyz):
        bad("tip_xyz must be a list of [x, y, z] points")
    if o.force_xyz is not None and len(o.force_xyz) != 3:
        bad("force_xyz must be [x, y, z]")
    if not isinstance(o.speeds_rpm, tuple) or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v >= 0
            for v in o.speeds_rpm):
        bad(f"speeds_rpm must be a list of speeds >= 0 rpm, got {o.speeds_rpm!r}")
    if o.speeds_rpm and (o.speeds_rpm[0] != 0 or any(b <= a for a, b in zip(o.speeds_rpm, o.speeds_rpm[1:]))):
        bad(f"speeds_rpm must be strictly ascending from 0, got {', '.join(f'{v:g}' for v in o.speeds_rpm)}")
    if o.n_families is not None and (isinstance(o.n_families, bool) or not isinstance(o.n_families, int)
                                     or o.n_families < 1):
        bad(f"n_families must be an integer >= 1 (families kept per nodal diameter), got {o.n_families!r}")
    if not (isinstance(o.damping_beta_s, (int, float)) and 0 <= o.damping_beta_s < 1e-2):
        bad(f"damping_beta_s must be a number in [0, 0.01) s, got {o.damping_beta_s!r}")
    return o


# ---- CalculiX deck: node sets and N ----------------------------------------------------

@dataclass(frozen=True, slots=True, eq=False)
class Deck:
    """What the importer reads from a CalculiX input deck.

    Attributes
    ----------
    node_sets : dict of str -> ndarray of int64
        ``*NSET`` sets (names upper-cased; ``*NODE, NSET=`` and ``GENERATE`` included).
    n_sectors : int or None
        ``N`` of ``*CYCLIC SYMMETRY MODEL``.
    nodes : dict of int -> (x, y, z)
        ``*NODE`` coordinates at full precision (the ``.frd`` prints 6 digits).
    """

    node_sets: dict
    n_sectors: int | None
    nodes: dict


def read_deck_sets(path) -> Deck:
    """Node sets, node coordinates and the ``N`` of ``*CYCLIC SYMMETRY MODEL`` of a CalculiX
    deck, following ``*INCLUDE``."""
    sets: dict[str, list] = {}
    nodes: dict[int, tuple] = {}
    n_sectors = None

    def walk(p: Path, depth: int):
        nonlocal n_sectors
        if depth > 10:
            raise ModelFileError(f"{p}: *INCLUDE nested too deep")
        try:
            lines = p.read_text(errors="replace").splitlines()
        except OSError as exc:
            raise ModelFileError(f"{p}: cannot read the deck ({exc.strerror or exc})") from None
        current, generate, in_nodes = None, False, False
        for ln in lines:
            s = ln.strip()
            if not s or s.startswith("**"):
                continue
            if s.startswith("*"):
                current, in_nodes = None, False
                kw = [t.strip() for t in s.split(",")]
                name = kw[0].upper()
                opts = {k.split("=")[0].strip().upper(): (k.split("=", 1)[1].strip() if "=" in k else "")
                        for k in kw[1:]}
                if name == "*INCLUDE" and "INPUT" in opts:
                    walk((p.parent / opts["INPUT"]).resolve(), depth + 1)
                elif name == "*NSET" and "NSET" in opts:
                    current = opts["NSET"].upper()
                    generate = "GENERATE" in opts
                    sets.setdefault(current, [])
                elif name == "*NODE":
                    in_nodes = True
                    node_set = opts.get("NSET", "").upper() or None
                elif name == "*CYCLIC SYMMETRY MODEL" and "N" in opts:
                    try:
                        n_sectors = int(opts["N"])
                    except ValueError:
                        raise ModelFileError(f"{p}: *CYCLIC SYMMETRY MODEL, N={opts['N']} is not a number") from None
                continue
            if in_nodes:
                t = s.split(",")
                try:
                    i = int(t[0])
                    nodes[i] = tuple(float(v) for v in (t[1:4] + ["0", "0"])[:3])
                except (ValueError, IndexError):
                    raise ModelFileError(f"{p}: bad *NODE line {s[:40]!r}") from None
                if node_set:
                    sets.setdefault(node_set, []).append(i)
                continue
            if current is None:
                continue
            items = [t.strip() for t in s.split(",") if t.strip()]
            if generate:
                a, b, *c = (int(float(t)) for t in items)
                sets[current].extend(range(a, b + 1, c[0] if c else 1))
            else:
                for t in items:
                    if re.fullmatch(r"\d+", t):
                        sets[current].append(int(t))
                    else:  # a set name inside a set
                        sets[current].extend(sets.get(t.upper(), []))

    walk(Path(path), 0)
    return Deck(node_sets={k: np.array(v, dtype=np.int64) for k, v in sets.items()}, n_sectors=n_sectors,
                nodes=nodes)


# ---- node selection -------------------------------------------------------------------

@dataclass(frozen=True, slots=True, eq=False)
class _Selection:
    rows: np.ndarray
    ids: np.ndarray
    how: str
    distance: np.ndarray  # to the requested points (0 when picked by number / set)


def _nearest(xyz: np.ndarray, pts: np.ndarray, rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    cand = np.arange(xyz.shape[0]) if rows is None else rows
    d = np.linalg.norm(xyz[cand][None, :, :] - pts[:, None, :], axis=2)
    k = np.argmin(d, axis=1)
    return cand[k], d[np.arange(pts.shape[0]), k]


def _select(res, ids, nset, pts, sets, what: str, where: str, single: bool = False) -> _Selection:
    if ids:
        idx = np.atleast_1d(np.asarray(ids, dtype=np.int64))
        try:
            rows = res.index_of(idx)
        except ModelFileError as exc:
            raise ModelFileError(f"{where}: {what}: {exc}") from None
        return _Selection(rows, idx, "by number", np.zeros(idx.size))
    if nset:
        if sets is None:
            raise ModelFileError(f"{where}: {what}: node set {nset!r} needs the CalculiX deck (option deck)")
        key = nset.upper()
        if key not in sets:
            raise ModelFileError(f"{where}: {what}: no node set {nset!r} in the deck "
                                 f"(it has {', '.join(sorted(sets)) or 'none'})")
        idx = np.unique(sets[key])
        if single and idx.size != 1:
            raise ModelFileError(f"{where}: {what}: node set {nset!r} holds {idx.size} nodes, not 1")
        try:
            rows = res.index_of(idx)
        except ModelFileError as exc:
            raise ModelFileError(f"{where}: {what}: node set {nset!r}: {exc}") from None
        return _Selection(rows, idx, f"node set {nset}", np.zeros(idx.size))
    if pts is not None and len(pts):
        p = np.atleast_2d(np.asarray(pts, dtype=float))
        rows, dist = _nearest(res.xyz, p)
        if np.unique(rows).size != rows.size:
            raise ModelFileError(f"{where}: {what}: two points have the same nearest node (a finer mesh, or "
                                 "points further apart)")
        return _Selection(rows, res.node_ids[rows], "nearest node", dist)
    raise ModelFileError(f"{where}: {what} not given (by node numbers, a node set, or coordinates)")


def _order_from_te(xyz: np.ndarray) -> np.ndarray:
    """Order tip nodes along their chord line, the trailing edge (larger z) first."""
    c = xyz - xyz.mean(axis=0)
    _, _, vt = np.linalg.svd(c, full_matrices=False)
    s = c @ vt[0]
    if vt[0][2] > 0:  # walk towards smaller z
        s = -s
    return np.argsort(s, kind="stable")


# ---- frd -> sector ---------------------------------------------------------------------

@dataclass(frozen=True, slots=True, eq=False)
class ImportResult:
    """A sector read from the user's results, and what was found on the way.

    Attributes
    ----------
    sector : CyclicSector
    notes : dict
        ``source``, ``tip`` / ``force`` selections (how, node numbers, distances), ``axis``,
        ``conjugated``, ``units``, ``steps``.
    """

    sector: CyclicSector
    notes: dict = field(default_factory=dict)


def sector_from_frd(path, options: ImportOptions = ImportOptions(), *, step: int | None = None,
                    results=None) -> ImportResult:
    """Read a CalculiX cyclic-symmetry ``.frd`` file into a :class:`CyclicSector`.

    Parameters
    ----------
    step : int, optional
        The ``*FREQUENCY`` step to read (its number in the file); default the last one.
    results : FrdResults, optional
        ``read_frd(path)`` already read.
    """
    where = str(path)
    res = read_frd(path) if results is None else results
    deck = options.deck
    if deck is None and Path(path).with_suffix(".inp").is_file():
        deck = str(Path(path).with_suffix(".inp"))
    dk = read_deck_sets(deck) if deck else None
    sets, n_deck = (dk.node_sets, dk.n_sectors) if dk else (None, None)
    N = options.n_sectors or n_deck
    if N is None:
        raise ModelFileError(f"{where}: the number of sectors is not known: give n_sectors (or the deck with its "
                             "*CYCLIC SYMMETRY MODEL, N=...)")
    cyc = [m for m in res.modes if m.harmonic_index is not None]
    if not cyc:
        raise ModelFileError(f"{where}: no cyclic symmetry modes (no 1PHID): a *FREQUENCY step with "
                             "*CYCLIC SYMMETRY MODEL and *SELECT CYCLIC SYMMETRY MODES is needed")
    steps = sorted({m.step for m in cyc})
    if step is not None:
        if step not in steps:
            raise ModelFileError(f"{where}: no cyclic frequency step {step} (steps {', '.join(map(str, steps))})")
        cyc = [m for m in cyc if m.step == step]
    elif len(steps) > 1:  # several frequency steps (e.g. several speeds): the last one
        cyc = [m for m in cyc if m.step == steps[-1]]
    if any(m.u_imag is None for m in cyc):
        raise ModelFileError(f"{where}: cyclic modes without their imaginary part (DISPI)")
    ax = res.cyclic_axis
    if ax is None:
        raise ModelFileError(f"{where}: no cyclic axis (1PAX) in the results")
    d = ax[3:] / np.linalg.norm(ax[3:])
    scale = _UNITS[options.units]
    if abs(abs(d[2]) - 1.0) > 1e-6 or np.hypot(ax[0], ax[1]) * scale > 1e-9:
        raise ModelFileError(f"{where}: the cyclic axis (point {ax[:3].tolist()}, direction {ax[3:].tolist()}) is "
                             "not the z axis: the model must be in the rotor frame (+z the rotation axis)")
    conj = d[2] < 0
    tip = _select(res, options.tip_nodes, options.tip_nset,
                  [tuple(p) for p in options.tip_xyz] if options.tip_xyz else None, sets, "tip nodes", where)
    if tip.rows.size < 2:
        raise ModelFileError(f"{where}: tip nodes: need at least 2, got {tip.rows.size}")
    order = _order_from_te(res.xyz[tip.rows])
    tip = _Selection(tip.rows[order], tip.ids[order], tip.how, tip.distance[order])
    force = _select(res, [options.force_node] if options.force_node is not None else (), options.force_nset,
                    options.force_xyz, sets, "excitation node", where, single=True)
    xyz = res.xyz
    if dk is not None and dk.nodes:  # the deck's coordinates at full precision, if it is these results' deck
        rows = np.concatenate([tip.rows, force.rows])
        try:
            exact = np.array([dk.nodes[int(i)] for i in res.node_ids[rows]])
        except KeyError as exc:
            raise ModelFileError(f"{where}: node {exc.args[0]} is not in the deck {deck}: "
                                 "not these results' deck") from None
        if np.max(np.abs(exact - xyz[rows])) > 1e-5 * max(1.0, np.abs(exact).max()):
            raise ModelFileError(f"{where}: the deck {deck} places the nodes elsewhere than the results: "
                                 "not these results' deck")
        xyz = xyz.copy()
        xyz[rows] = exact
    # unit sanity: a rotor tip radius between 5 mm and 10 m
    r_tip = float(np.mean(np.hypot(*xyz[tip.rows, :2].T))) * scale
    if not TIP_RADIUS_RANGE_M[0] <= r_tip <= TIP_RADIUS_RANGE_M[1]:
        hint = " (the deck looks like mm: units = \"mm-t-s\")" if options.units == "SI" and r_tip > 10 else ""
        raise ModelFileError(f"{where}: the tip radius would be {r_tip:.4g} m with units = {options.units!r}{hint}")
    # a mode is mass-normalised in the deck's units; in SI: x m = x * L, M kg = M * m_unit
    # (mm-t-s: L = 1e-3, tonne = 1e3 kg) -> phi_SI = phi * L / sqrt(m_unit)
    shape_scale = scale / math.sqrt(1e3) if options.units == "mm-t-s" else 1.0
    rows = np.concatenate([tip.rows, force.rows])
    U = np.array([(m.u[rows] + 1j * m.u_imag[rows]) for m in cyc]) * shape_scale
    if conj:
        U = U.conj()
    gm = np.array([m.generalised_mass for m in cyc])
    if np.any(np.isfinite(gm) & (np.abs(gm - 1.0) > 1e-6)):
        raise ModelFileError(f"{where}: modes are not mass-normalised (generalised mass {gm[np.isfinite(gm)][0]:g})")
    nominal = options.nominal_node if options.nominal_node is not None else tip.rows.size // 2
    try:
        sector = CyclicSector(
            n_sectors=int(N), harmonic_index=np.array([m.harmonic_index for m in cyc], np.int64),
            freq_hz=np.array([m.freq_hz for m in cyc]), tip_xyz=xyz[tip.rows] * scale,
            tip_shapes=U[:, :tip.rows.size], force_xyz=xyz[force.rows[0]] * scale,
            force_shapes=U[:, tip.rows.size], nominal_node=int(nominal), stagger_deg=options.stagger_deg,
            normalisation="sector",
            provenance={"builder": "CalculiX cyclic symmetry (.frd) via bttsim model import",
                        "source": Path(path).name, "tip_nodes": tip.ids.tolist(),
                        "force_node": int(force.ids[0]), "units": options.units})
    except ModelFileError as exc:
        raise ModelFileError(f"{where}: {exc}") from None
    notes = {"source": where, "format": "frd", "deck": deck, "tip": tip, "force": force, "axis": ax.tolist(),
             "conjugated": bool(conj), "units": options.units, "steps": steps, "scale": scale}
    return ImportResult(sector=sector, notes=notes)


def import_model(path, options: ImportOptions = ImportOptions()):
    """Read sector results (``.frd`` or neutral ``.npz``) and expand them to the model file.

    Returns
    -------
    model : ModalModel
    report : dict
        :func:`~bttsim_stream.model.cyclic.expand_sector`'s report plus the import notes.
    """
    fmt = options.format or Path(path).suffix.lower().lstrip(".")
    if fmt == "rst":
        raise ModelFileError(f"{path}: ANSYS .rst results are not read yet (no cyclic-symmetry .rst file was "
                             "available to test a reader on): write the sector to the neutral .npz format, "
                             "see schemas/cyclic_sector.md")
    if fmt not in FORMATS:
        raise ModelFileError(f"{path}: unknown results format {fmt!r} (give --format {' or '.join(FORMATS)}; "
                             "ANSYS .rst is not supported yet, see schemas/cyclic_sector.md)")
    if fmt == "npz":
        sector = load_sector(path)
        if options.nominal_node is not None or options.stagger_deg is not None:
            sector = replace(sector, **{k: v for k, v in (("nominal_node", options.nominal_node),
                                                          ("stagger_deg", options.stagger_deg)) if v is not None})
        result = ImportResult(sector=sector, notes={"source": str(path), "format": "npz"})
    else:
        result = sector_from_frd(path, options)
    try:
        model, report = expand_sector(result.sector, damping_beta_s=options.damping_beta_s,
                                      n_families=options.n_families)
    except ModelFileError as exc:
        raise ModelFileError(f"{path}: {exc}") from None
    report.update(notes=result.notes, sector=result.sector)
    return model, report


def import_model_speeds(paths, options: ImportOptions):
    """Sector results at several speeds -> a speed-dependent model file
    (:func:`~bttsim_stream.model.cyclic.expand_sectors_at_speeds`).

    Either one results file per speed (``.frd``: its last frequency step; neutral ``.npz``),
    or one ``.frd`` whose cyclic ``*FREQUENCY`` steps are the speeds in order (e.g. each after
    a ``*STATIC`` step with a ``CENTRIF`` load, as a ``PERTURBATION`` step). The speeds are
    ``options.speeds_rpm``.

    Returns
    -------
    model : ModalModel
    report : dict
        As :func:`import_model`, plus ``speed_rad_s`` and ``min_mac``.
    """
    from .cyclic import expand_sectors_at_speeds

    paths = [Path(p) for p in paths]
    speeds = options.speeds_rpm
    where = str(paths[0]) if len(paths) == 1 else f"{paths[0]} .. {paths[-1].name}"
    if len(speeds) < 2:
        raise ModelFileError(f"{where}: a speed-dependent import needs speeds_rpm (--speeds-rpm), one speed per "
                             "results file or frequency step, at least 2, from 0")
    fmts = [options.format or p.suffix.lower().lstrip(".") for p in paths]
    for p, fmt in zip(paths, fmts):
        if fmt not in FORMATS:
            raise ModelFileError(f"{p}: unknown results format {fmt!r} (give --format {' or '.join(FORMATS)})")
    results = []
    if len(paths) == 1:
        if fmts[0] != "frd":
            raise ModelFileError(f"{where}: {len(speeds)} speeds but one neutral sector file: give one file per speed")
        res = read_frd(paths[0])
        steps = sorted({m.step for m in res.modes if m.harmonic_index is not None})
        if len(steps) != len(speeds):
            raise ModelFileError(f"{where}: {len(steps)} cyclic frequency step(s) in the file but {len(speeds)} speeds "
                                 "given: one speed per step, in order")
        results = [sector_from_frd(paths[0], options, step=st, results=res) for st in steps]
    else:
        if len(paths) != len(speeds):
            raise ModelFileError(f"{where}: {len(paths)} results files but {len(speeds)} speeds given: "
                                 "one speed per file")
        for p, fmt in zip(paths, fmts):
            if fmt == "frd":
                results.append(sector_from_frd(p, options))
            else:
                sec = load_sector(p)
                if options.nominal_node is not None or options.stagger_deg is not None:
                    sec = replace(sec, **{k: v for k, v in (("nominal_node", options.nominal_node),
                                                            ("stagger_deg", options.stagger_deg)) if v is not None})
                results.append(ImportResult(sector=sec, notes={"source": str(p), "format": "npz"}))
    try:
        model, report = expand_sectors_at_speeds([r.sector for r in results],
                                                 np.asarray(speeds, float) * np.pi / 30.0,
                                                 damping_beta_s=options.damping_beta_s, n_families=options.n_families)
    except ModelFileError as exc:
        raise ModelFileError(f"{where}: {exc}") from None
    report.update(notes=results[0].notes, sector=results[0].sector)
    return model, report


def format_report(report: dict) -> str:
    """What was read: sectors, families per ND, the frequency table, tip chord and stagger."""
    notes, sec = report["notes"], report["sector"]
    lines = [f"read {notes['source']} ({notes['format']}): {report['n_sectors']} sectors, "
             f"{len(sec.freq_hz)} sector solutions over harmonic indices 0..{report['n_sectors'] // 2}"]
    if notes["format"] == "frd":
        t, f = notes["tip"], notes["force"]
        lines.append(f"  tip nodes ({t.how}, from the TE): {', '.join(map(str, t.ids.tolist()))}"
                     + (f"; farthest {1e3 * notes['scale'] * t.distance.max():.3g} mm from its point"
                        if t.how == "nearest node" else ""))
        lines.append(f"  excitation node ({f.how}): {int(f.ids[0])}"
                     + (f", {1e3 * notes['scale'] * f.distance[0]:.3g} mm from its point"
                        if f.how == "nearest node" else ""))
        lines.append(f"  cyclic axis {notes['axis'][3:]}: "
                     + ("modes conjugated to the +z convention" if notes["conjugated"] else "+z convention as read")
                     + f"; units {notes['units']}")
    fam = report["families_per_nd"]
    lines.append("  solutions per ND: " + ", ".join(f"{k}:{v}" for k, v in fam.items())
                 + f" -> {report['n_families']} families kept"
                 + (f" ({report['dropped']} solutions left out)" if report["dropped"] else ""))
    tip = report["tip"]
    lines.append(f"  tip: {tip['n_tip']} nodes, chord {1e3 * tip['chord_m']:.3f} mm, stagger "
                 f"{tip['stagger_deg']:.2f} deg, radius {1e3 * tip['radius_m']:.2f} mm, axial "
                 f"{1e3 * tip['axial_m'][0]:.3f} .. {1e3 * tip['axial_m'][1]:.3f} mm, "
                 f"P_nom = node {tip['nominal_node']}")
    camp = report["campbell_freq_hz"]
    lines.append("  ND " + "".join(f"  family {f + 1:<2d}(Hz)" for f in range(camp.shape[0])))
    for k in range(camp.shape[1]):
        lines.append(f"  {k:2d} " + "".join(f"  {camp[f, k]:12.3f}" for f in range(camp.shape[0])))
    lines.append(f"  -> {report['n_modes']} full-wheel modes (ND 0 and N/2 single, the others pairs)")
    if "speed_rad_s" in report:
        rpm = np.asarray(report["speed_rad_s"]) * 30.0 / np.pi
        camp = report["campbell_freq_hz_at_speed"]
        lines.append(f"  speeds: {', '.join(f'{v:g}' for v in rpm)} rpm; modes tracked (smallest MAC between "
                     f"consecutive speeds {report['min_mac']:.4f}); family 1 ND 0 .. {camp.shape[2] - 1}: "
                     f"{camp[0, 0].min():.2f} .. {camp[0, 0].max():.2f} Hz at 0 rpm, "
                     f"{camp[-1, 0].min():.2f} .. {camp[-1, 0].max():.2f} Hz at {rpm[-1]:g} rpm")
    return "\n".join(lines)

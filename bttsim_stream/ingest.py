"""Measured data in: a rig's pulse trains (or an export folder) to a recording.

``bttsim ingest`` writes the same MCAP a simulated run has -- the run metadata message (with
``has_truth = false``), one ``Opr`` and one ``ToaBatch`` per probe per revolution -- through
the stream layer's one producer (:class:`~bttsim_stream.bus.stream.MessageStream`, as
:class:`~bttsim_stream.acquisition.AcquisitionStream` uses it) and the
:class:`~bttsim_stream.bus.recording.McapRecorder`, so ``bttsim process``, ``view``,
``export`` and ``replay`` treat it like a simulated run. The ``bttsim.run`` metadata record
also holds ``source`` (what was read) and ``ingest`` (a JSON object of the counts).

* :func:`ingest_export`: the labelled ``opr`` / ``toa`` (/ ``extra_edge``) tables of
  ``bttsim export`` and its ``run.json``: the TOAs go in unchanged, to the bit.
* :func:`ingest_pulses`: unlabelled pulse trains (one OPR file, one file per probe),
  labelled by :func:`~bttsim_stream.process.identify.identify_pulses`.

Files are read in blocks (:func:`read_times`): a CSV whose first column (or ``column``)
holds times in s, an optional header line, or a Parquet file; memory holds the times
(8 bytes each), never the text. Every problem with the input (empty, not numbers, NaN,
times going backwards, an implausible speed, a blade count the data do not show) is a
one-line :class:`~bttsim_stream.errors.BttsimError`, raised before the output is touched:
the recording is written to a temporary file and renamed at the end.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from dataclasses import dataclass, fields, replace
from pathlib import Path

import numpy as np

from . import __version__
from .bus.recording import McapRecorder
from .bus.stream import MessageStream
from .defaults import DEFAULT_RIG
from .errors import BttsimError
from .process.displacement import Geometry
from .process.identify import identify_pulses, pulses_per_revolution
from .sim.core import RevolutionBatch, RunInfo

__all__ = ["read_times", "ingest_export", "ingest_pulses", "IngestResult", "parse_probe", "MIN_RPM", "MAX_RPM"]

#: Slowest and fastest plausible median shaft speed, rpm: beyond, the times are not in s.
MIN_RPM = 30.0
MAX_RPM = 300_000.0
_BLOCK_BYTES = 4 << 20
_MAX_LINE = 64 << 10
_REVS_PER_BATCH = 64


@dataclass(frozen=True, slots=True)
class IngestResult:
    """What an ingest wrote.

    Attributes
    ----------
    path : str
    run_id : str
    revolutions, n_blades, n_probes : int
    toas : int
        TOAs recorded (cells with a pulse).
    missing, extra, stray, outside : int
        Empty cells; pulses in a blade's window not kept (double triggers); pulses in no
        blade's window; pulses before the first or after the last recorded revolution.
    median_rpm : float
    per_probe : tuple of dict
        The same counts per probe, with its angle and median pulses per revolution.
    notes : tuple of str
        What the metadata assumed (e.g. no engine order given).
    """

    path: str
    run_id: str
    revolutions: int
    n_blades: int
    n_probes: int
    toas: int
    missing: int = 0
    extra: int = 0
    stray: int = 0
    outside: int = 0
    median_rpm: float = 0.0
    per_probe: tuple = ()
    notes: tuple = ()

    def counts(self) -> dict:
        return {"revolutions": self.revolutions, "toas": self.toas, "missing": self.missing, "extra": self.extra,
                "stray": self.stray, "outside": self.outside, "median_rpm": round(self.median_rpm, 3),
                "per_probe": list(self.per_probe), "notes": list(self.notes)}


# -- reading ---------------------------------------------------------------------------

def _is_parquet(path: Path) -> bool:
    with open(path, "rb") as fh:
        return fh.read(4) == b"PAR1"


def _split(line: str, delim: str | None) -> list[str]:
    return line.split(delim) if delim else line.split()


def _blocks_csv(path: Path, column: str | None):
    """Yield ``(first_line_number, float array)`` blocks of one CSV column."""
    idx = 0 if column is None else None
    delim: str | None = None
    line_no = 0
    started = False
    carry = ""
    with open(path, "r", encoding="utf-8", errors="strict", newline="") as fh:
        while True:
            try:
                text = fh.read(_BLOCK_BYTES)
            except UnicodeDecodeError:
                raise BttsimError(f"{path}: not a text CSV file (undecodable bytes near line {line_no + 1}); "
                                  f"give times in s, one per line, or a Parquet file") from None
            last = not text
            text = carry + text
            if last:
                lines, carry = text.splitlines(), ""
            else:
                cut = text.rfind("\n")
                if cut < 0:
                    if len(text) > _MAX_LINE:
                        raise BttsimError(f"{path}: line {line_no + 1} is longer than {_MAX_LINE // 1024} KiB: "
                                          f"not a CSV of times")
                    carry = text
                    continue
                lines, carry = text[:cut].splitlines(), text[cut + 1:]
            if len(carry) > _MAX_LINE:
                raise BttsimError(f"{path}: a line is longer than {_MAX_LINE // 1024} KiB: not a CSV of times")
            first = line_no + 1
            line_no += len(lines)
            nums = lines
            for k, ln in enumerate([] if started else lines):  # up to the first data (or header) line
                s = ln.strip()
                if not s or s.startswith("#"):
                    continue
                delim = next((d for d in (",", ";", "\t") if d in s), None)
                head = [c.strip().strip('"') for c in _split(s, delim)]
                try:
                    float(head[0 if idx is None else idx])
                    is_header = False
                except (ValueError, IndexError):
                    is_header = True
                if column is not None:
                    if not is_header:
                        raise BttsimError(f"{path}: --column {column!r} needs a header line naming the columns")
                    if column not in head:
                        raise BttsimError(f"{path}: no column {column!r} (the header has {', '.join(head)})")
                    idx = head.index(column)
                started = True
                first = first + k + (1 if is_header else 0)
                nums = lines[k + (1 if is_header else 0):]
                break
            if not started:
                if last:
                    break
                continue
            if not nums:
                if last:
                    break
                continue
            skip = [k for k, ln in enumerate(nums) if not ln.strip() or ln.lstrip().startswith("#")]
            rows = None
            if skip:  # blank and comment lines are left out; the others keep their line numbers
                rows = np.delete(np.arange(first, first + len(nums)), skip)
                gone = set(skip)
                nums = [ln for k, ln in enumerate(nums) if k not in gone]
            try:
                vals = ([ln.split()[idx] for ln in nums] if delim is None
                        else [ln.split(delim, idx + 1)[idx] for ln in nums])
                arr = np.array(vals, dtype=float)
            except (ValueError, IndexError):
                for k, ln in enumerate(nums):
                    try:
                        float(_split(ln.strip(), delim)[idx])
                    except (ValueError, IndexError):
                        where = first + k if rows is None else int(rows[k])
                        raise BttsimError(f"{path}: line {where}: not a time in s: {ln.strip()[:40]!r}") from None
                raise
            yield (first if rows is None else rows), arr
            if last:
                break


def _blocks_parquet(path: Path, column: str | None):
    try:
        import pyarrow.parquet as pq
    except ImportError:
        raise BttsimError(f"{path}: reading Parquet needs pyarrow: pip install 'bttsim-stream[parquet]' "
                          f"(or give a CSV file)") from None
    try:
        pf = pq.ParquetFile(path)
        names = pf.schema_arrow.names
        if not names:
            raise BttsimError(f"{path}: the Parquet file has no column")
        name = names[0] if column is None else column
        if name not in names:
            raise BttsimError(f"{path}: no column {column!r} (the file has {', '.join(names)})")
        row = 1
        for batch in pf.iter_batches(batch_size=1 << 20, columns=[name]):
            arr = batch.column(0).to_numpy(zero_copy_only=False)
            try:
                arr = np.asarray(arr, dtype=float)
            except (TypeError, ValueError):
                raise BttsimError(f"{path}: column {name!r} does not hold numbers (times in s)") from None
            yield row, arr
            row += arr.size
    except BttsimError:
        raise
    except Exception as exc:  # pyarrow's errors of a corrupt file: one line
        raise BttsimError(f"{path}: not a readable Parquet file ({type(exc).__name__}: {str(exc)[:120]})") from None


def read_times(path, column: str | None = None, *, what: str = "pulse times", strict: bool = False) -> np.ndarray:
    """Times in s from a CSV or Parquet file, read in blocks.

    Parameters
    ----------
    path : path-like
        CSV (first column, or ``column`` named in a header line; comma, semicolon, tab or
        blank separated; a header line and ``#`` comment lines allowed before the data) or
        Parquet (recognised by its magic bytes; first column or ``column``).
    column : str, optional
    what : str
        What the file holds (for the messages).
    strict : bool
        Times must strictly increase (OPR); else they must not decrease.

    Returns
    -------
    ndarray, shape (n,)
        Finite, sorted times, s.

    Raises
    ------
    BttsimError
        Missing or empty file, a value that is not a number, NaN or infinite, times going
        backwards (one line naming the file and the line or row).
    """
    p = Path(path)
    if not p.is_file():
        raise BttsimError(f"{p}: no such file ({what})")
    blocks = _blocks_parquet(p, column) if _is_parquet(p) else _blocks_csv(p, column)
    out, prev = [], -math.inf
    unit = "row" if _is_parquet(p) else "line"
    for first, arr in blocks:
        at = (lambda i: first + i) if isinstance(first, int) else (lambda i: int(first[i]))  # noqa: E731
        bad = np.flatnonzero(~np.isfinite(arr))
        if bad.size:
            raise BttsimError(f"{p}: {unit} {at(int(bad[0]))}: {float(arr[bad[0]])!r} is not a time ({what} "
                              f"must be finite numbers in s)")
        steps = np.diff(np.r_[prev, arr])
        back = np.flatnonzero(steps <= 0 if strict else steps < 0)
        if back.size:
            i = int(back[0])
            before = prev if i == 0 else float(arr[i - 1])
            raise BttsimError(f"{p}: {unit} {at(i)}: time {float(arr[i])!r} s is not after the previous one "
                              f"({before!r} s): {what} must {'strictly ' if strict else ''}increase")
        if arr.size:
            prev = float(arr[-1])
            out.append(arr)
    if not out:
        raise BttsimError(f"{p}: no times in the file ({what})")
    return np.concatenate(out)


# -- writing ---------------------------------------------------------------------------

def _run_id(*parts) -> str:
    h = hashlib.sha256()
    for x in parts:
        h.update(x if isinstance(x, bytes) else str(x).encode())
    return h.hexdigest()[:16]


def _check_out(out) -> None:
    """Refuse an output path that cannot be written, before anything is read."""
    out = Path(out)
    if out.is_dir():
        raise BttsimError(f"{out}: is a folder (--out takes the recording's file name)")
    if not out.parent.is_dir():
        raise BttsimError(f"{out}: cannot write (no folder {out.parent})")
    if not os.access(out.parent, os.W_OK):
        raise BttsimError(f"{out}: cannot write (folder {out.parent} not writable)")


def _write(out, info: RunInfo, revolution: np.ndarray, opr_s: np.ndarray, toa_s: np.ndarray,
           extra_passage: np.ndarray, extra_toa_s: np.ndarray, record: dict) -> None:
    """The recording, written to ``out`` through a temporary file (``out`` untouched on error).

    ``extra_passage`` indexes ``(revolution, blade, probe)`` of the whole run flattened."""
    out = Path(out)
    stream = MessageStream(info.run_id, info.rig)
    nr, nb, npr = toa_s.shape
    tmp = out.with_name(f".{out.name}.{os.getpid()}.partial")
    per_rev = nb * npr
    order = np.argsort(extra_passage, kind="stable")
    extra_passage, extra_toa_s = extra_passage[order], extra_toa_s[order]
    try:
        with McapRecorder(tmp, run_metadata=record) as rec:
            rec.write_message(stream.run_metadata(info))
            for lo in range(0, nr, _REVS_PER_BATCH):
                hi = min(nr, lo + _REVS_PER_BATCH)
                a, b = np.searchsorted(extra_passage, [lo * per_rev, hi * per_rev])
                batch = RevolutionBatch(
                    revolution=revolution[lo:hi], opr_s=opr_s[lo:hi], toa_s=toa_s[lo:hi], opr_ticks=None,
                    toa_ticks=None, truth=None, residual_s=0.0, bracketed=np.ones((hi - lo, nb, npr), bool),
                    extra_passage=extra_passage[a:b] - lo * per_rev, extra_toa_s=extra_toa_s[a:b])
                rec.write_all(stream.acquisition(batch, include_truth=False))
        os.replace(tmp, out)
    except OSError as exc:
        raise BttsimError(f"{out}: cannot write ({exc.strerror or exc})") from None
    except BttsimError as exc:  # the recorder names the temporary file
        raise BttsimError(f"{out}: cannot write ({str(exc).replace(str(tmp), out.name)})") from None
    finally:
        if tmp.exists():
            tmp.unlink()


# -- from an export folder -------------------------------------------------------------

_ARRAY_FIELDS = {"probe_angles_rad", "sensing_angles_rad", "family_freq_hz", "family_speed_rad_s",
                 "family_freq_hz_at_speed"}
_TUPLE_FIELDS = {"engine_orders", "nodal_diameters", "speed_range_rpm"}


def _run_info(doc: dict, where: str) -> RunInfo:
    kw = {}
    names = {f.name for f in fields(RunInfo)}
    for k, v in doc.items():
        if k not in names:
            continue
        if k in _ARRAY_FIELDS:
            v = None if v is None else np.asarray(v, dtype=float)
        elif k in _TUPLE_FIELDS:
            v = tuple(v)
        kw[k] = v
    try:
        return RunInfo(**kw)
    except TypeError as exc:
        raise BttsimError(f"{where}: run metadata incomplete ({exc})") from None


def _table(folder: Path, doc: dict, name: str, columns: tuple) -> dict | None:
    d = doc.get("tables", {}).get(name)
    if d is None:
        return None
    file = folder / d["file"]
    if not file.is_file():
        raise BttsimError(f"{file}: no such file (table {name!r} of {folder / 'run.json'})")
    if doc.get("format") == "parquet":
        try:
            import pyarrow.parquet as pq
        except ImportError:
            raise BttsimError(f"{file}: reading Parquet needs pyarrow: pip install 'bttsim-stream[parquet]'") from None
        try:
            tab = pq.read_table(file, columns=list(columns))
        except Exception as exc:
            raise BttsimError(f"{file}: not a readable Parquet table ({type(exc).__name__}: {str(exc)[:120]})") from None
        return {k: tab.column(k).to_numpy(zero_copy_only=False) for k in columns}
    with open(file, encoding="utf-8", errors="replace") as fh:
        head = fh.readline().strip().split(",")
    missing = [c for c in columns if c not in head]
    if missing:
        raise BttsimError(f"{file}: no column(s) {', '.join(missing)} (header: {','.join(head)[:80]})")
    try:
        raw = np.loadtxt(file, delimiter=",", skiprows=1, usecols=[head.index(c) for c in columns], ndmin=2,
                         dtype=float)
    except ValueError as exc:
        raise BttsimError(f"{file}: not a table of numbers ({str(exc)[:120]})") from None
    return {c: raw[:, i] for i, c in enumerate(columns)}


def ingest_export(folder, out, *, rig: str | None = None) -> IngestResult:
    """A recording from the ``opr`` and ``toa`` tables of ``bttsim export`` (and its
    ``extra_edge`` table when present); the TOAs go in unchanged.

    Parameters
    ----------
    folder : path-like
        The export folder (``run.json`` and the tables, CSV or Parquet).
    out : path-like
        The recording to write (MCAP).
    rig : str, optional
        Rig name on the bus (default: the export's).
    """
    _check_out(out)
    folder = Path(folder)
    meta_file = folder / "run.json"
    if not meta_file.is_file():
        raise BttsimError(f"{folder}: no run.json (not a `bttsim export` folder)")
    try:
        doc = json.loads(meta_file.read_text())
        run = doc["run"]
    except (ValueError, KeyError, UnicodeDecodeError) as exc:
        raise BttsimError(f"{meta_file}: not an export's run.json ({type(exc).__name__})") from None
    info = _run_info(run, str(meta_file))
    opr = _table(folder, doc, "opr", ("revolution", "opr_s"))
    toa = _table(folder, doc, "toa", ("revolution", "blade", "probe", "toa_s"))
    if opr is None or toa is None:
        raise BttsimError(f"{meta_file}: the export lists no {'opr' if opr is None else 'toa'} table")
    rev = np.asarray(opr["revolution"], dtype=np.int64)
    if rev.size < 3:
        raise BttsimError(f"{folder}: {rev.size} OPR pulse(s): at least 3 revolutions needed")
    if np.any(np.diff(rev) != 1):
        raise BttsimError(f"{folder}: opr table: revolutions must be consecutive")
    opr_s = np.asarray(opr["opr_s"], dtype=float)
    nr, nb, npr = rev.size, info.n_blades, info.n_probes
    r = np.asarray(toa["revolution"], dtype=np.int64) - rev[0]
    b = np.asarray(toa["blade"], dtype=np.int64)
    j = np.asarray(toa["probe"], dtype=np.int64)
    ok = (r >= 0) & (r < nr) & (b >= 0) & (b < nb) & (j >= 0) & (j < npr)
    if not ok.all():
        raise BttsimError(f"{folder}: toa table: {int((~ok).sum())} row(s) outside revolutions "
                          f"{rev[0]}..{rev[-1]}, blades 0..{nb - 1}, probes 0..{npr - 1}")
    toa_s = np.full((nr, nb, npr), np.nan)
    toa_s[r, b, j] = np.asarray(toa["toa_s"], dtype=float)
    ex_pass, ex_t = np.zeros(0, np.int64), np.zeros(0)
    edges = _table(folder, doc, "extra_edge", ("revolution", "probe", "blade", "toa_s"))
    if edges is not None and np.size(edges["toa_s"]):
        er = np.asarray(edges["revolution"], np.int64) - rev[0]
        ej = np.asarray(edges["probe"], np.int64)
        eb = np.clip(np.asarray(edges["blade"], np.int64), 0, nb - 1)  # -1 (no window): its batch is what counts
        keep = (er >= 0) & (er < nr) & (ej >= 0) & (ej < npr)
        ex_pass = ((er * nb + eb) * npr + ej)[keep]
        ex_t = np.asarray(edges["toa_s"], float)[keep]
    source = {"kind": "export", "path": str(folder), "format": doc.get("format"),
              "run_id": run.get("run_id"), "software_version": doc.get("software_version")}
    run_id = _run_id("export", opr_s.tobytes(), toa_s.tobytes(), ex_t.tobytes(), json.dumps(run, sort_keys=True))
    info = replace(info, run_id=run_id, has_truth=False, rig=rig or info.rig, software_version=__version__)
    n_missing = int(np.count_nonzero(np.isnan(toa_s)))
    res = IngestResult(path=str(out), run_id=run_id, revolutions=nr, n_blades=nb, n_probes=npr,
                       toas=int(toa_s.size - n_missing), missing=n_missing, extra=int(ex_t.size),
                       median_rpm=float(60.0 / np.median(np.diff(opr_s))))
    record = {"run_id": run_id, "rig": info.rig, "scenario_toml": info.scenario_toml,
              "software_version": __version__, "source": json.dumps(source), "ingest": json.dumps(res.counts())}
    _write(out, info, rev, opr_s, toa_s, ex_pass, ex_t, record)
    return res


# -- from pulse trains -----------------------------------------------------------------

def parse_probe(text: str) -> tuple[float, str]:
    """``"23.82=probe2.csv"`` -> ``(23.82, "probe2.csv")`` (angle in deg)."""
    angle, sep, path = str(text).partition("=")
    try:
        deg = float(angle)
    except ValueError:
        deg = math.nan
    if not sep or not path or not math.isfinite(deg):
        raise BttsimError(f"--probe must be ANGLE_DEG=FILE (e.g. 23.82=probe2.csv), got {text!r}")
    return deg, path


def _geometry(probes_deg: list, n_blades, tip_radius_m, scenario_path, engine_orders, rig) -> tuple[RunInfo, list]:
    """The run metadata of a measured run (``n_revolutions``, times and run id left to fill)."""
    from .scenario import MAX_BLADES, Scenario, load_scenario

    notes = []
    angles = np.asarray(probes_deg, dtype=float)
    if np.any((angles < 0) | (angles >= 360)):
        raise BttsimError(f"--probe angles must be in [0, 360) deg, got {angles.tolist()}")
    if np.unique(angles).size != angles.size:
        raise BttsimError(f"--probe angles must be distinct, got {angles.tolist()}")
    if scenario_path:
        from .sim.core import RunUpSimulator

        scn = load_scenario(scenario_path)
        base = RunUpSimulator(scn).info  # the model's sensing angles, radius and mode families
        if n_blades is not None and n_blades != base.n_blades:
            raise BttsimError(f"--blades {n_blades} but {scenario_path} has {base.n_blades} blades")
        sensing = base.sensing_angles_rad
        tip = base.tip_radius_m if tip_radius_m is None else tip_radius_m
        eos = tuple(engine_orders) if engine_orders else tuple(base.engine_orders)
        nds = tuple(base.nodal_diameters) if not engine_orders else tuple(0 for _ in eos)
        kw = dict(n_blades=base.n_blades, probe_axial_m=base.probe_axial_m, opr_angle_rad=base.opr_angle_rad,
                  stagger_deg=base.stagger_deg, family_freq_hz=base.family_freq_hz,
                  family_speed_rad_s=base.family_speed_rad_s, family_freq_hz_at_speed=base.family_freq_hz_at_speed,
                  sensing_angles_rad=sensing, rig=rig or scn.run.rig, scenario_toml=base.scenario_toml)
    else:
        if n_blades is None or tip_radius_m is None:
            raise BttsimError("--blades N and --tip-radius-m R are required (or --scenario S.toml)")
        eos = tuple(engine_orders) if engine_orders else (8,)
        if not engine_orders:
            notes.append("no --eo: EO 8 recorded as the expected engine order (process with --eo or --eo-range)")
        nds = tuple(0 for _ in eos)
        kw = dict(n_blades=int(n_blades), probe_axial_m=0.0, opr_angle_rad=0.0,
                  stagger_deg=Scenario().rotor.stagger_deg, rig=rig or DEFAULT_RIG)
        tip = tip_radius_m
    if not 2 <= kw["n_blades"] <= MAX_BLADES:
        raise BttsimError(f"--blades must be in [2, {MAX_BLADES}], got {kw['n_blades']}")
    if not (tip is not None and math.isfinite(tip) and 0 < tip < 10):
        raise BttsimError(f"--tip-radius-m must be a radius in m in (0, 10), got {tip!r}")
    info = RunInfo(n_probes=int(angles.size), n_revolutions=0, probe_angles_rad=np.deg2rad(angles),
                   tip_radius_m=float(tip), clock_hz=0.0, engine_orders=eos, nodal_diameters=nds,
                   toa_method="measured", duration_s=0.0, seed=0, **kw)
    return info, notes


def ingest_pulses(opr_path, probes: list, out, *, n_blades: int | None = None, tip_radius_m: float | None = None,
                  rig: str | None = None, engine_orders=None, scenario_path=None, column: str | None = None,
                  tolerance: float = 0.25) -> IngestResult:
    """A recording from unlabelled pulse trains: one OPR file and one file per probe.

    Parameters
    ----------
    opr_path : path-like
        OPR pulse times, s (:func:`read_times`), strictly increasing.
    probes : list of (float, path-like)
        Each probe's angle (deg, anticlockwise from +x) and its pulse times, s.
    out : path-like
        The recording to write (MCAP).
    n_blades, tip_radius_m : optional
        Required without ``scenario_path``; with it, they must agree with it / override it.
    rig : str, optional
    engine_orders : sequence of int, optional
        Expected engine orders (run metadata); default the scenario's, else 8 (with a note).
    scenario_path : path-like, optional
        Geometry from a scenario: blade count, tip radius, OPR angle, the model's sensing
        angles and mode families.
    column : str, optional
        Column of every time file (default: the first).
    tolerance : float
        Blade window half-width, in blade pitches (:func:`identify_pulses`).

    Returns
    -------
    IngestResult
    """
    _check_out(out)
    info, notes = _geometry([a for a, _ in probes], n_blades, tip_radius_m, scenario_path, engine_orders, rig)
    nb, npr = info.n_blades, info.n_probes
    opr = read_times(opr_path, column, what="OPR times", strict=True)
    if opr.size < 3:
        raise BttsimError(f"{opr_path}: {opr.size} OPR pulse(s): at least 3 (two revolutions) needed")
    rpm = 60.0 / np.diff(opr)
    med_rpm = float(np.median(rpm))
    if not MIN_RPM <= med_rpm <= MAX_RPM:
        hint = " (times in ms? they must be in s)" if med_rpm < MIN_RPM else ""
        raise BttsimError(f"{opr_path}: median speed {med_rpm:.4g} rpm from the OPR pulses is implausible "
                          f"(expected {MIN_RPM:g} to {MAX_RPM:g} rpm){hint}")
    geometry = Geometry(n_blades=nb, probe_angles_rad=info.probe_angles_rad, tip_radius_m=info.tip_radius_m,
                        opr_angle_rad=info.opr_angle_rad, blade_angles_rad=info.sensing_angles_rad)
    psi = geometry.nominal_arrival_angles()
    labelled, per_probe = [], []
    for j, (deg, path) in enumerate(probes):
        t = read_times(path, column, what=f"pulse times of the probe at {deg:g} deg")
        ppr = pulses_per_revolution(opr, t)
        med = float(np.median(ppr))
        if med != nb:
            raise BttsimError(f"{path}: median {med:g} pulses per revolution between OPR pulses, not the "
                              f"{nb} blades given (wrong --blades, or times not in the OPR's clock and unit?)")
        ident = identify_pulses(opr, t, psi[:, j], calibrate=True, tolerance=tolerance)
        labelled.append(ident)
        per_probe.append({"probe": j, "angle_deg": float(deg), "file": str(path), "pulses": int(t.size),
                          "median_pulses_per_revolution": med})
    toa = np.stack([r.toa_s for r in labelled], axis=2)  # (n_opr, nb, npr)
    # a revolution is kept when every probe saw at least half the blades (the ends of a
    # recording: the probes started late or stopped before the revolution's end)
    full = np.all(np.mean(np.isfinite(toa), axis=1) >= 0.5, axis=1)
    good = np.flatnonzero(full)
    if good.size < 3:
        raise BttsimError(f"{opr_path}: fewer than 3 revolutions with pulses on every probe "
                          f"({good.size}); do the probe files cover the OPR file's time span?")
    lo, hi = int(good[0]), int(good[-1]) + 1
    toa = toa[lo:hi]
    nr = hi - lo
    passages, times = [], []
    tot = {"missing": 0, "extra": 0, "stray": 0, "outside": 0}
    for j, r in enumerate(labelled):
        sel_e = (r.extra_revolution >= lo) & (r.extra_revolution < hi)
        sel_s = (r.stray_revolution >= lo) & (r.stray_revolution < hi)
        cells = r.toa_s[lo:hi]
        dropped = (int(np.isfinite(r.toa_s).sum() - np.isfinite(cells).sum())
                   + int((~sel_e).sum()) + int((~sel_s).sum()))
        passages += [((r.extra_revolution[sel_e] - lo) * nb + r.extra_blade[sel_e]) * npr + j,
                     (r.stray_revolution[sel_s] - lo) * nb * npr + j]
        times += [r.extra_toa_s[sel_e], r.stray_toa_s[sel_s]]
        c = {"toas": int(np.isfinite(cells).sum()), "missing": int(np.isnan(cells).sum()),
             "extra": int(sel_e.sum()), "stray": int(sel_s.sum()), "outside": r.outside + dropped}
        per_probe[j].update(c)
        for k in tot:
            tot[k] += c[k]
    opr_k = opr[lo:hi]
    rpm_k = 60.0 / np.diff(opr[lo:min(hi + 1, opr.size)])
    ex_pass = np.concatenate(passages).astype(np.int64)
    ex_t = np.concatenate(times)
    run_id = _run_id("pulses", opr_k.tobytes(), toa.tobytes(), ex_t.tobytes())
    info = replace(info, n_revolutions=nr, duration_s=float(opr_k[-1] - opr_k[0]), run_id=run_id,
                   speed_range_rpm=(float(rpm_k.min()), float(rpm_k.max())), software_version=__version__,
                   has_truth=False)
    res = IngestResult(path=str(out), run_id=run_id, revolutions=nr, n_blades=nb, n_probes=npr,
                       toas=int(np.isfinite(toa).sum()), median_rpm=med_rpm, per_probe=tuple(per_probe),
                       notes=tuple(notes), **tot)
    source = {"kind": "pulses", "opr": str(opr_path), "probes": [[float(a), str(p)] for a, p in probes],
              "column": column, "scenario": None if scenario_path is None else str(scenario_path),
              "first_opr_pulse": lo}
    record = {"run_id": run_id, "rig": info.rig, "scenario_toml": info.scenario_toml,
              "software_version": __version__, "source": json.dumps(source), "ingest": json.dumps(res.counts())}
    _write(out, info, np.arange(nr, dtype=np.int64), opr_k, toa, ex_pass, ex_t, record)
    return res

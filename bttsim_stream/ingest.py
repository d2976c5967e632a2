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
  labelled by :func:`~bttsim_stream.process.identify.identify_pulses`; or raw probe signals
  (volts, :class:`SignalOptions`) turned into pulses first by the simulator's own trigger
  (:class:`~bttsim_stream.process.trigger.PulseTrigger`); the OPR file may be a K-pulse
  shaft encoder (:func:`~bttsim_stream.process.identify.encoder_revolutions`).

Files are read in blocks (:mod:`~bttsim_stream.timefiles`): a CSV whose first column (or
``column``) holds times in s, an optional header line, or a Parquet file. Pulse trains are streamed:
each block, once checked, is spilled as float64 to a temporary folder beside the output
(:class:`_Train`); the identification runs on windows of revolutions
(:func:`~bttsim_stream.process.identify.identify_window`), spilling the TOAs, and the
recording is written from that spill, so memory does not grow with the number of pulses.
Every problem with the input (empty, not numbers, NaN, times going backwards, an
implausible speed, a blade count the data do not show) is a one-line
:class:`~bttsim_stream.errors.BttsimError`, raised before the output is touched: the
recording is written to a temporary file and renamed at the end; the spill is removed.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import tempfile
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

import numpy as np

from . import __version__
from .bus.recording import McapRecorder
from .bus.stream import MessageStream
from .defaults import DEFAULT_RIG
from .errors import BttsimError, replaceable_file
from .process.displacement import Geometry, rotor_phase_from_opr
from .process.identify import (calibration_end, encoder_revolutions, identification_params, identify_window,
                               last_pulse_s, window_revolutions)
from .process.trigger import PulseTrigger
from .sim.core import RevolutionBatch, RunInfo
from .sim.signal import TRIGGER_KINDS, Trigger
from .timefiles import checked_blocks, read_columns, read_times, signal_blocks

__all__ = ["read_times", "read_signal_pulses", "ingest_export", "ingest_pulses", "IngestResult", "SignalOptions",
           "parse_probe", "MIN_RPM", "MAX_RPM"]

#: Slowest and fastest plausible median shaft speed, rpm: beyond, the times are not in s.
MIN_RPM = 30.0
MAX_RPM = 300_000.0
_REVS_PER_BATCH = 64
_CHUNK_REVS = 2048  # revolutions identified at a time


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
    double : int
        Raw signals: later trigger edges in a pulse's window (the signal chain's double
        pulses), recorded as extra edges of the pulse's cell (not in ``extra``).
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
    double: int = 0
    median_rpm: float = 0.0
    per_probe: tuple = ()
    notes: tuple = ()

    def counts(self) -> dict:
        return {"revolutions": self.revolutions, "toas": self.toas, "missing": self.missing, "extra": self.extra,
                "stray": self.stray, "outside": self.outside, "double": self.double,
                "median_rpm": round(self.median_rpm, 3),
                "per_probe": list(self.per_probe), "notes": list(self.notes)}


# -- reading ---------------------------------------------------------------------------

@dataclass(frozen=True, slots=True)
class SignalOptions:
    """How raw probe signals become pulses (``--signal``); None: the scenario's
    ``[acquisition.signal]`` (and ``[acquisition] clock_hz``) when one is given, else the
    defaults of that table (no latch without a clock).

    Attributes
    ----------
    sample_rate_hz : float
    start_s : float
        Time of each file's first sample, s (on the counter grid ``k / f_s`` when
        ``start_s f_s`` is whole).
    trigger : str or tuple of str
        ``threshold``, ``constant_fraction`` or ``peak`` (one, or one per probe in order).
    level_v, hysteresis_v, fraction : float
    edge : str
    clock_hz : float
        Counter that latches the trigger; 0: none.
    holdoff : float
        Hold-off between pulses, in blade passing periods at the local speed.
    """

    sample_rate_hz: float | None = None
    start_s: float = 0.0
    trigger: str | tuple | None = None
    level_v: float | None = None
    hysteresis_v: float | None = None
    edge: str | None = None
    fraction: float | None = None
    clock_hz: float | None = None
    holdoff: float = 0.25

    def resolve(self, scenario_path=None) -> "SignalOptions":
        """Every field filled (flags over the scenario over the table's defaults)."""
        from .scenario import Scenario, load_scenario

        scn = load_scenario(scenario_path) if scenario_path else Scenario()
        sig = scn.acquisition.signal
        kw = {}
        for name in ("sample_rate_hz", "trigger", "level_v", "hysteresis_v", "edge", "fraction"):
            v = getattr(self, name)
            kw[name] = getattr(sig, name) if v is None else v
        kw["clock_hz"] = ((scn.acquisition.clock_hz if scenario_path else 0.0) if self.clock_hz is None
                          else self.clock_hz)
        kinds = (kw["trigger"],) if isinstance(kw["trigger"], str) else tuple(kw["trigger"])
        bad = [k for k in kinds if k not in TRIGGER_KINDS]
        if bad:
            raise BttsimError(f"--trigger must be one of {', '.join(TRIGGER_KINDS)}, got {bad[0]!r}")
        if kw["edge"] not in ("rising", "falling"):
            raise BttsimError(f"--edge must be rising or falling, got {kw['edge']!r}")
        if not (kw["sample_rate_hz"] and math.isfinite(kw["sample_rate_hz"]) and kw["sample_rate_hz"] > 0):
            raise BttsimError(f"--sample-rate must be a rate in Hz > 0, got {kw['sample_rate_hz']!r}")
        if not kw["sample_rate_hz"] <= MAX_SAMPLE_RATE_HZ:
            raise BttsimError(f"--sample-rate must be at most {MAX_SAMPLE_RATE_HZ:g} Hz, got {kw['sample_rate_hz']!r}")
        if not 0.0 < kw["fraction"] < 1.0:
            raise BttsimError(f"--fraction must be in (0, 1), got {kw['fraction']!r}")
        if not (math.isfinite(kw["clock_hz"]) and kw["clock_hz"] >= 0):
            raise BttsimError(f"--clock-hz must be >= 0, got {kw['clock_hz']!r}")
        if not 0.0 < self.holdoff < 1.0:
            raise BttsimError(f"--holdoff must be in (0, 1) blade passing periods, got {self.holdoff!r}")
        if not (math.isfinite(self.start_s) and abs(self.start_s) <= MAX_START_S):
            raise BttsimError(f"--signal-start-s must be a time in s within +-{MAX_START_S:g}, got {self.start_s!r}")
        return replace(self, **kw)

    def trigger_of(self, j: int) -> Trigger:
        kinds = self.trigger
        kind = kinds if isinstance(kinds, str) else kinds[min(j, len(kinds) - 1)]
        return Trigger(kind=kind, level_v=float(self.level_v), hysteresis_v=float(self.hysteresis_v),
                       edge=self.edge, fraction=float(self.fraction))


def read_signal_pulses(path, trigger: Trigger, options: SignalOptions, holdoff_s):
    """Pulse times of one probe's raw signal, read in blocks.

    Returns ``(toa_s, double_pulse, double_toa_s, n_samples, unfired)``
    (:class:`~bttsim_stream.process.trigger.TriggeredPulses`, joined)."""
    toa, dp, dt_, count = [], [], [], [0]

    def keep(res):
        dp.append(res.double_pulse + count[0])
        toa.append(res.toa_s)
        dt_.append(res.double_toa_s)
        count[0] += res.toa_s.size

    n, unfired = _trigger_file(path, trigger, options, holdoff_s, keep)
    return np.concatenate(toa), np.concatenate(dp), np.concatenate(dt_), n, unfired


def _trigger_file(path, trigger: Trigger, options: SignalOptions, holdoff_s, sink) -> tuple[int, int]:
    """One probe's raw signal through the trigger block by block, each block's
    :class:`~bttsim_stream.process.trigger.TriggeredPulses` to ``sink``; returns the
    sample count and the unfired windows."""
    p = Path(path)
    if not p.is_file():
        raise BttsimError(f"{p}: no such file (probe signal)")
    pt = PulseTrigger(trigger, options.sample_rate_hz, options.start_s, holdoff_s, options.clock_hz)
    n, unfired, n_pulses = 0, 0, 0
    unit = "sample" if p.suffix.lower() == ".npy" else "line"
    blocks = signal_blocks(p)
    pending = next(blocks, None)
    while pending is not None:
        first, arr = pending
        pending = next(blocks, None)
        inf = np.flatnonzero(np.isinf(arr))
        if inf.size:
            where = first + int(inf[0]) if isinstance(first, int) else int(first[inf[0]])
            raise BttsimError(f"{p}: {unit} {where}: {float(arr[inf[0]])!r} is not a voltage")
        n += arr.size
        try:
            res = pt.feed(arr, final=pending is None)
        except ValueError as exc:
            raise BttsimError(f"{p}: {exc}") from None
        sink(res)
        n_pulses += res.toa_s.size
        unfired += res.unfired
    if n == 0:
        raise BttsimError(f"{p}: no samples in the file (probe signal)")
    if n_pulses == 0:
        raise BttsimError(f"{p}: no pulse reaches the trigger level {trigger.level_v:g} V ({trigger.kind}, "
                          f"{trigger.edge}) in {n} samples")
    return n, unfired


# -- writing ---------------------------------------------------------------------------

def _run_id(*parts) -> str:
    h = hashlib.sha256()
    for x in parts:
        h.update(x if isinstance(x, bytes) else str(x).encode())
    return h.hexdigest()[:16]


def _check_out(out, inputs=()) -> None:
    """Refuse an output path that cannot be written, or that is one of the ``inputs`` (files),
    before anything is read."""
    real = replaceable_file(out)  # a folder, device, pipe or socket is refused here
    out = Path(out)
    for path in inputs:
        if real == Path(os.path.realpath(path)):
            raise BttsimError(f"--out {out}: that is the input {path}; it would be overwritten")
    if not out.parent.is_dir():
        raise BttsimError(f"{out}: cannot write (no folder {out.parent})")
    if not os.access(out.parent, os.W_OK):
        raise BttsimError(f"{out}: cannot write (folder {out.parent} not writable)")


class _Rows:
    """``toa_rows(a, b)`` as an array of shape ``(n_rev, ...)`` sliced by revolutions."""

    def __init__(self, toa_rows, n_rev: int) -> None:
        self._rows, self.shape = toa_rows, (int(n_rev),)

    def __getitem__(self, s: slice) -> np.ndarray:
        return self._rows(s.start, min(s.stop, self.shape[0]))


def _checked_info(info: RunInfo, where) -> RunInfo:
    """``info`` as the recording's readers will decode it: its metadata message encoded and
    decoded (every check of :func:`~.bus.codec.decode_run_metadata`), so that nothing is
    written that ``process``, ``export`` or ``view`` would refuse."""
    from .bus import codec, keys

    try:
        rig = keys.validate_rig(info.rig)
        payload = codec.encode_run_metadata(codec.Header(info.run_id, 0, -1, 0.0), info)
        return replace(codec.decode_run_metadata(payload, keys.meta_key(rig)).body, run_id=info.run_id)
    except (BttsimError, ValueError, TypeError, OverflowError) as exc:
        raise BttsimError(f"{where}: impossible run metadata: {' '.join(str(exc).split())}") from None


def _check_run(where, info: RunInfo, revolution: np.ndarray, opr_s: np.ndarray, toa_rows, shape: tuple) -> None:
    """What a recording's readers check (:func:`~.offline.load_run`), before it is written:
    its metadata, its revolutions within the run's count, OPR times increasing, each TOA NaN
    or within a revolution of its OPR pulse."""
    from .offline import check_times

    _checked_info(info, where)
    if revolution.size and int(revolution[-1]) >= info.n_revolutions:
        raise BttsimError(f"{where}: revolution {int(revolution[-1])} in the data, but the run has "
                          f"{info.n_revolutions} revolution(s) (n_revolutions)")
    check_times(where, revolution, opr_s, _Rows(toa_rows, shape[0]))


def _write(out, info: RunInfo, revolution: np.ndarray, opr_s: np.ndarray, toa_rows, shape: tuple,
           extra_passage: np.ndarray, extra_toa_s: np.ndarray, record: dict, where) -> None:
    """The recording, written to ``out`` through a temporary file (``out`` untouched on error),
    once :func:`_check_run` (naming ``where``, the input) finds nothing its readers refuse.

    ``toa_rows(a, b)`` gives the TOAs of revolutions ``a:b``, ``shape`` those of the run
    ``(revolution, blade, probe)``; ``extra_passage`` indexes it flattened."""
    _check_run(where, info, revolution, opr_s, toa_rows, shape)
    out = replaceable_file(out)  # through a link: its target
    stream = MessageStream(info.run_id, info.rig)
    nr, nb, npr = shape
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
                    revolution=revolution[lo:hi], opr_s=opr_s[lo:hi], toa_s=toa_rows(lo, hi), opr_ticks=None,
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
_INT_FIELDS = {"n_blades", "n_probes", "n_revolutions", "seed"}
_STR_FIELDS = {"rig", "toa_method", "scenario_toml", "software_version", "run_id"}


def _export_doc(meta_file: Path) -> dict:
    """An export's ``run.json``: an object with a ``run`` object and ``tables`` naming their
    files (one-line errors otherwise)."""
    try:
        doc = json.loads(meta_file.read_text())
    except (ValueError, UnicodeDecodeError, RecursionError) as exc:
        raise BttsimError(f"{meta_file}: not an export's run.json ({type(exc).__name__})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("run"), dict):
        raise BttsimError(f"{meta_file}: not an export's run.json (no \"run\" object)")
    tables = doc.get("tables", {})
    if not isinstance(tables, dict) or not all(isinstance(t, dict) and isinstance(t.get("file"), str) and t["file"]
                                               for t in tables.values()):
        raise BttsimError(f"{meta_file}: not an export's run.json (\"tables\" must map each table to "
                          "{\"file\": NAME, ...})")
    return doc


def _numbers(values, folder, table: str, column: str, *, integer: bool = True, nan: bool = False) -> np.ndarray:
    """A table column as int64 (integer values only) or float64 (finite; NaN too with ``nan``)."""
    try:
        x = np.asarray(values, dtype=float)
    except (ValueError, TypeError) as exc:
        raise BttsimError(f"{folder}: {table} table: column {column} is not numbers "
                          f"({' '.join(str(exc).split())[:80]})") from None
    bad = ~np.isfinite(x) & ~(nan & np.isnan(x)) if x.ndim == 1 else np.ones(1, bool)
    if integer and x.ndim == 1:
        with np.errstate(invalid="ignore"):
            bad |= (x != np.round(x)) | (np.abs(x) > 2.0 ** 53)
    if bad.any():
        i = int(np.flatnonzero(bad)[0]) if x.ndim == 1 else 0
        what = "integers" if integer else "finite numbers" + (" or NaN" if nan else "")
        raise BttsimError(f"{folder}: {table} table: column {column} must hold {what}, one a row"
                          + (f" (row {i}: {float(x[i])!r})" if x.ndim == 1 else ""))
    return x.astype(np.int64) if integer else x


def _run_info(doc: dict, where: str) -> RunInfo:
    kw = {}
    names = {f.name for f in fields(RunInfo)}
    try:
        for k, v in doc.items():
            if k not in names:
                continue
            if k in _INT_FIELDS and (not isinstance(v, int) or isinstance(v, bool)):
                raise ValueError(f"{k} must be an integer, got {v!r}"[:120])
            if k in _STR_FIELDS and not isinstance(v, str):
                raise ValueError(f"{k} must be a string, got {v!r}"[:120])
            if k in _ARRAY_FIELDS:
                v = None if v is None else np.asarray(v, dtype=float)
            elif k in _TUPLE_FIELDS:
                v = tuple(v)
            kw[k] = v
        return RunInfo(**kw)
    except (TypeError, ValueError) as exc:
        raise BttsimError(f"{where}: run metadata incomplete or malformed ({' '.join(str(exc).split())[:120]})") \
            from None


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
            raise BttsimError(f"{file}: not a readable Parquet table "
                              f"({type(exc).__name__}: {' '.join(str(exc).split())[:120]})") from None
        return {k: tab.column(k).to_numpy(zero_copy_only=False) for k in columns}
    return read_columns(file, columns)


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
    folder = Path(folder)
    meta_file = folder / "run.json"
    if not meta_file.is_file():
        _check_out(out)
        raise BttsimError(f"{folder}: no run.json (not a `bttsim export` folder)")
    doc = _export_doc(meta_file)
    _check_out(out, [meta_file, *(folder / t["file"] for t in doc.get("tables", {}).values())])
    run = doc["run"]
    info = _checked_info(_run_info(run, str(meta_file)), meta_file)
    opr = _table(folder, doc, "opr", ("revolution", "opr_s"))
    toa = _table(folder, doc, "toa", ("revolution", "blade", "probe", "toa_s"))
    if opr is None or toa is None:
        raise BttsimError(f"{meta_file}: the export lists no {'opr' if opr is None else 'toa'} table")
    rev = _numbers(opr["revolution"], folder, "opr", "revolution")
    if rev.size < 3:
        raise BttsimError(f"{folder}: {rev.size} OPR pulse(s): at least 3 revolutions needed")
    if np.any(np.diff(rev) != 1):
        raise BttsimError(f"{folder}: opr table: revolutions must be consecutive")
    opr_s = _numbers(opr["opr_s"], folder, "opr", "opr_s", integer=False)
    nr, nb, npr = rev.size, info.n_blades, info.n_probes
    r = _numbers(toa["revolution"], folder, "toa", "revolution") - rev[0]
    b = _numbers(toa["blade"], folder, "toa", "blade")
    j = _numbers(toa["probe"], folder, "toa", "probe")
    ok = (r >= 0) & (r < nr) & (b >= 0) & (b < nb) & (j >= 0) & (j < npr)
    if not ok.all():
        raise BttsimError(f"{folder}: toa table: {int((~ok).sum())} row(s) outside revolutions "
                          f"{rev[0]}..{rev[-1]}, blades 0..{nb - 1}, probes 0..{npr - 1}")
    cell = (r * nb + b) * npr + j
    if np.unique(cell).size != cell.size:
        raise BttsimError(f"{folder}: toa table: {cell.size - np.unique(cell).size} row(s) repeat a (revolution, "
                          "blade, probe) already given")
    toa_s = np.full((nr, nb, npr), np.nan)
    toa_s[r, b, j] = _numbers(toa["toa_s"], folder, "toa", "toa_s", integer=False, nan=True)
    ex_pass, ex_t = np.zeros(0, np.int64), np.zeros(0)
    edges = _table(folder, doc, "extra_edge", ("revolution", "probe", "blade", "toa_s"))
    if edges is not None and np.size(edges["toa_s"]):
        er = _numbers(edges["revolution"], folder, "extra_edge", "revolution") - rev[0]
        ej = _numbers(edges["probe"], folder, "extra_edge", "probe")
        # -1 (no window): its batch is what counts
        eb = np.clip(_numbers(edges["blade"], folder, "extra_edge", "blade"), 0, nb - 1)
        keep = (er >= 0) & (er < nr) & (ej >= 0) & (ej < npr)
        ex_pass = ((er * nb + eb) * npr + ej)[keep]
        ex_t = _numbers(edges["toa_s"], folder, "extra_edge", "toa_s", integer=False)[keep]
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
    _write(out, info, rev, opr_s, lambda a, b: toa_s[a:b], toa_s.shape, ex_pass, ex_t, record, folder)
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


#: The latest time a signal file may start at, s, either side of 0 (a Unix time in seconds is
#: well inside; beyond, a start on the counter grid ``k / f_s`` is no 64-bit integer).
MAX_START_S = 4e9
#: The fastest sampling a signal file may have, Hz (the scenario's own bound: with
#: :data:`MAX_START_S`, every sample's number on the counter grid is a 64-bit integer).
MAX_SAMPLE_RATE_HZ = 1e9


def parse_signal(text: str) -> tuple[float, str, str, float | None]:
    """``"23.82=probe2.npy"`` -> ``(23.82, "probe2.npy", "signal", None)``;
    ``"23.82=probe2.npy@0.0125"`` -> ``(23.82, "probe2.npy", "signal", 0.0125)``: the time of
    the file's first sample, s (else ``--signal-start-s``). A file whose own name is the
    whole text after ``=`` is taken as it is."""
    try:
        deg, path = parse_probe(text)
    except BttsimError:
        raise BttsimError(f"--signal must be ANGLE_DEG=FILE[@START_S] (e.g. 23.82=probe2.npy@0.0125), "
                          f"got {text!r}") from None
    head, at, tail = path.rpartition("@")
    if not at or not head or Path(path).is_file():
        return deg, path, "signal", None
    try:
        start = float(tail)
    except ValueError:
        start = math.nan
    if not (math.isfinite(start) and abs(start) <= MAX_START_S):
        raise BttsimError(f"--signal {text!r}: the start time after '@' must be a time in s within "
                          f"+-{MAX_START_S:g}, got {tail!r}")
    return deg, head, "signal", start


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


def _read_opr(opr_path, column, encoder_pulses, encoder_index, notes: list):
    """The OPR pulse times, s, and the encoder decoding (or None); a note when an encoder."""
    if encoder_pulses is not None and not 1 <= encoder_pulses <= 100_000:
        raise BttsimError(f"--encoder-pulses must be in [1, 100000], got {encoder_pulses}")
    opr = read_times(opr_path, column, what="encoder times" if encoder_pulses else "OPR times", strict=True)
    encoder = None
    if encoder_pulses:
        try:
            encoder = encoder_revolutions(opr, encoder_pulses, encoder_index)
        except ValueError as exc:
            raise BttsimError(f"{opr_path}: {exc}") from None
        opr = encoder.opr_s
        notes.append(f"OPR from a {encoder_pulses}-pulse encoder (pulse 0 by {encoder.rule}); "
                     f"rotor angle from its pulses")
    elif encoder_index is not None:
        raise BttsimError("--encoder-index needs --encoder-pulses K")
    return opr, encoder


def _median_rpm(opr_path, opr: np.ndarray) -> float:
    """The median speed of the OPR pulses, rpm, checked plausible (times in s, not ms)."""
    if opr.size < 3:
        raise BttsimError(f"{opr_path}: {opr.size} OPR pulse(s): at least 3 (two revolutions) needed")
    rpm = 60.0 / np.diff(opr)
    med_rpm = float(np.median(rpm))
    if not MIN_RPM <= med_rpm <= MAX_RPM:
        hint = " (times in ms? they must be in s)" if med_rpm < MIN_RPM else ""
        raise BttsimError(f"{opr_path}: median speed {med_rpm:.4g} rpm from the OPR pulses is implausible "
                          f"(expected {MIN_RPM:g} to {MAX_RPM:g} rpm){hint}")
    return med_rpm


class _Train:
    """One probe's pulse times, s, spilled as float64 to a file while they are read, with the
    count of pulses before each OPR pulse (``offset[n]``: before ``opr[n]``; ``offset[-1]``:
    all)."""

    def __init__(self, path: Path, opr: np.ndarray):
        self.path, self._opr = path, opr
        self._cnt = np.zeros(opr.size + 1, np.int64)
        self._fh = open(path, "wb")
        self.offset = None

    def add(self, t: np.ndarray) -> None:
        np.asarray(t, dtype="<f8").tofile(self._fh)
        self._cnt += np.bincount(np.searchsorted(self._opr, t, side="right"), minlength=self._cnt.size)

    def close(self) -> "_Train":
        self._fh.close()
        self.offset = np.cumsum(self._cnt)
        return self

    @property
    def size(self) -> int:
        return int(self._cnt.sum())

    @property
    def per_revolution(self) -> np.ndarray:
        """Pulses in ``[OPR_n, OPR_n+1)`` (:func:`~bttsim_stream.process.identify.pulses_per_revolution`)."""
        return self._cnt[1:-1]

    def read(self, i0: int, i1: int) -> np.ndarray:
        return np.fromfile(self.path, dtype="<f8", count=max(int(i1) - int(i0), 0), offset=8 * int(i0))

    def until(self, i0: int, end_s: float) -> np.ndarray:
        """The pulses from number ``i0`` on that come before ``end_s``, read in blocks."""
        parts, i, n = [], int(i0), int(self.offset[-1])
        while i < n:
            blk = self.read(i, min(n, i + (1 << 20)))
            k = int(np.searchsorted(blk, end_s))
            parts.append(blk[:k])
            i += blk.size
            if k < blk.size:
                break
        return np.concatenate(parts) if parts else np.zeros(0)

    def window(self, lo: int, hi: int, end_s: float) -> np.ndarray:
        """The pulses of OPR intervals ``lo:hi`` (:func:`window_revolutions`) from the first
        OPR pulse on and before ``end_s`` (:func:`last_pulse_s`): the others are outside."""
        return self.read(self.offset[lo], self.offset[hi]) if hi < self.offset.size - 1 \
            else self.until(self.offset[lo], end_s)


def _read_probe(j, probe, opr, tmp: Path, signal, column, holdoff_s):
    """Probe ``j``'s pulses spilled (:class:`_Train`), its report row and (a signal) the
    times of its pulses with a double edge and of those edges."""
    deg, path, *kind = probe
    train, extra_info, doubles = _Train(tmp / f"pulses{j}.f8", opr), {}, None
    try:
        if kind:
            sig = signal if len(kind) < 2 or kind[1] is None else replace(signal, start_s=float(kind[1]))
            trig = sig.trigger_of(j)
            parent, dbl = [np.zeros(0)], [np.zeros(0)]

            def spill(res):  # the pulses to the spill; the double edges (few) and their pulses kept
                train.add(res.toa_s)
                parent.append(res.toa_s[res.double_pulse])
                dbl.append(res.double_toa_s)

            n_samp, unfired = _trigger_file(path, trig, sig, holdoff_s, spill)
            doubles = (np.concatenate(parent), np.concatenate(dbl))
            extra_info = {"signal": {"samples": n_samp, "trigger": trig.kind, "unfired_windows": unfired,
                                     "start_s": sig.start_s}}
        else:
            what = f"pulse times of the probe at {deg:g} deg"
            for arr in checked_blocks(path, column, what, False):
                train.add(arr)
            if train.size == 0:
                raise BttsimError(f"{Path(path)}: no times in the file ({what})")
    finally:
        train.close()
    return train, {"probe": j, "angle_deg": float(deg), "file": str(path), "pulses": train.size, **extra_info}, doubles


def _read_probes(opr, probes: list, info: RunInfo, signal, column, tolerance, encoder, phase, tmp: Path):
    """Each probe's pulses read (or triggered from its signal) into a :class:`_Train`, the
    blade count checked, and its identification parameters found on the calibration span."""
    nb = info.n_blades
    geometry = Geometry(n_blades=nb, probe_angles_rad=info.probe_angles_rad, tip_radius_m=info.tip_radius_m,
                        opr_angle_rad=info.opr_angle_rad, blade_angles_rad=info.sensing_angles_rad)
    psi = geometry.nominal_arrival_angles()
    trains, params, per_probe, doubles = [], [], [], []
    period = np.diff(opr)

    def holdoff_s(t):
        i = np.clip(np.searchsorted(opr, t) - 1, 0, period.size - 1)
        return signal.holdoff * period[i] / nb

    for j, probe in enumerate(probes):
        train, row, dbl = _read_probe(j, probe, opr, tmp, signal, column, holdoff_s)
        med = float(np.median(train.per_revolution))
        if med != nb:
            raise BttsimError(f"{probe[1]}: median {med:g} pulses per revolution between OPR pulses, not the "
                              f"{nb} blades given (wrong --blades, or times not in the OPR's clock and unit?)")
        k, end = calibration_end(opr, float(train.read(0, 1)[0]))
        span = train.read(train.offset[0], train.offset[k - 1]) if k < opr.size else train.until(train.offset[0], end)
        params.append(identification_params(opr, span, psi[:, j], calibrate=True, tolerance=tolerance,
                                            encoder=encoder, phase=phase))
        trains.append(train)
        doubles.append(dbl)
        per_probe.append({**row, "median_pulses_per_revolution": med})
    return trains, params, per_probe, doubles


@dataclass(eq=False)
class _Labels:
    """One probe's labelling gathered over the windows (all but its TOAs, which are spilled)."""

    extra: list = field(default_factory=list)  # (revolution, blade, time) per window
    stray: list = field(default_factory=list)  # (revolution, time) per window
    outside: int = 0
    parent_rev: np.ndarray | None = None  # a signal's double edges: cell of their pulse, -1: not kept
    parent_blade: np.ndarray | None = None


def _match_parents(lab: _Labels, parent_t: np.ndarray, toa: np.ndarray, start: int) -> None:
    """Cells (revolution, blade) of the kept pulses ``toa`` (revolutions from ``start``) that
    are the pulses of double edges (``parent_t``, increasing)."""
    flat = toa.ravel()
    have = np.flatnonzero(np.isfinite(flat))
    if not have.size:
        return
    srt = have[np.argsort(flat[have], kind="stable")]
    vals = flat[srt]
    i0, i1 = np.searchsorted(parent_t, vals[0], side="left"), np.searchsorted(parent_t, vals[-1], side="right")
    k = np.clip(np.searchsorted(vals, parent_t[i0:i1]), 0, vals.size - 1)
    hit = np.flatnonzero(vals[k] == parent_t[i0:i1])
    cell = srt[k[hit]]
    lab.parent_rev[i0 + hit] = start + cell // toa.shape[1]
    lab.parent_blade[i0 + hit] = cell % toa.shape[1]


def _identify(opr, trains: list, params: list, doubles: list, encoder, phase, nb: int, toa_path: Path):
    """Every probe labelled window by window (:func:`identify_window`); the TOAs spilled to
    ``toa_path`` as float64 ``(revolution, blade, probe)``. Returns the labels and, per
    revolution and probe, the TOA count and whether at least half the blades were seen."""
    nr, npr = opr.size, len(trains)
    labs = [_Labels() for _ in trains]
    for lab, dbl in zip(labs, doubles):
        if dbl is not None:
            lab.parent_rev, lab.parent_blade = np.full(dbl[0].size, -1, np.int64), np.zeros(dbl[0].size, np.int64)
    fin = np.zeros((nr, npr), np.int32)
    half = np.zeros((nr, npr), bool)
    end_s = last_pulse_s(opr)
    with open(toa_path, "wb") as fh:
        for a in range(0, nr, _CHUNK_REVS):
            b = min(nr, a + _CHUNK_REVS)
            lo, hi = window_revolutions(a, b, nr)
            toa = np.empty((b - a, nb, npr))
            for j, (train, lab) in enumerate(zip(trains, labs)):
                t = train.window(lo, hi, end_s)
                r = identify_window(opr, t, params[j], a, b, encoder=encoder, phase=phase)
                toa[:, :, j] = r.toa_s
                lab.extra.append((r.extra_revolution, r.extra_blade, r.extra_toa_s))
                lab.stray.append((r.stray_revolution, r.stray_toa_s))
                # before the first OPR pulse, after the last pulse of the last revolution
                lab.outside += r.outside + (int(train.offset[0]) if a == 0 else 0) + (
                    int(train.offset[-1] - train.offset[lo]) - t.size if b == nr else 0)
                if doubles[j] is not None:
                    _match_parents(lab, doubles[j][0], r.toa_s, a)
            toa.tofile(fh)
            seen = np.isfinite(toa)
            fin[a:b] = seen.sum(axis=1)
            # a revolution is kept when every probe saw at least half the blades (the ends of a
            # recording: the probes started late or stopped before the revolution's end)
            half[a:b] = np.mean(seen, axis=1) >= 0.5
    return labs, fin, half


def _extra_pulses(opr, labs: list, doubles: list, fin: np.ndarray, per_probe: list, lo: int, hi: int, nb: int):
    """The pulses besides the TOAs (extra, stray, double) of revolutions ``lo:hi``, and the counts.

    Returns the flat passage index ``(revolution * nb + blade) * npr + probe`` and time, s,
    of each such pulse, and the totals; each probe's counts go into its ``per_probe`` row.
    """
    npr = len(labs)
    passages, times = [], []
    tot = {"missing": 0, "extra": 0, "stray": 0, "outside": 0, "double": 0}
    for j, lab in enumerate(labs):
        ex_r, ex_b, ex_t = (np.concatenate([x[k] for x in lab.extra]) for k in range(3))
        st_r, st_t = (np.concatenate([x[k] for x in lab.stray]) for k in range(2))
        n_double = 0
        if doubles[j] is not None and doubles[j][0].size:
            # a double edge joins the cell its pulse was kept in (where the signal chain puts it)
            dbl_t = doubles[j][1]
            hit = (lab.parent_rev >= lo) & (lab.parent_rev < hi)
            passages.append(((lab.parent_rev[hit] - lo) * nb + lab.parent_blade[hit]) * npr + j)
            times.append(dbl_t[hit])
            n_double = int(hit.sum())
            # the others' pulse was extra, stray or outside: they count as stray (or outside)
            lost = dbl_t[~hit]
            rev_l = np.clip(np.searchsorted(opr, lost, side="right") - 1, 0, opr.size - 1).astype(np.int64)
            st_r, st_t = np.r_[st_r, rev_l], np.r_[st_t, lost]
        sel_e = (ex_r >= lo) & (ex_r < hi)
        sel_s = (st_r >= lo) & (st_r < hi)
        toas = int(fin[lo:hi, j].sum())
        dropped = int(fin[:, j].sum()) - toas + int((~sel_e).sum()) + int((~sel_s).sum())
        passages += [((ex_r[sel_e] - lo) * nb + ex_b[sel_e]) * npr + j, (st_r[sel_s] - lo) * nb * npr + j]
        times += [ex_t[sel_e], st_t[sel_s]]
        c = {"toas": toas, "missing": (hi - lo) * nb - toas, "extra": int(sel_e.sum()), "stray": int(sel_s.sum()),
             "outside": lab.outside + dropped, "double": n_double}
        per_probe[j].update(c)
        for k in tot:
            tot[k] += c[k]
    return np.concatenate(passages).astype(np.int64), np.concatenate(times), tot


def ingest_pulses(opr_path, probes: list, out, *, n_blades: int | None = None, tip_radius_m: float | None = None,
                  rig: str | None = None, engine_orders=None, scenario_path=None, column: str | None = None,
                  tolerance: float = 0.25, signal: SignalOptions | None = None, encoder_pulses: int | None = None,
                  encoder_index: int | None = None) -> IngestResult:
    """A recording from unlabelled pulse trains: one OPR file and one file per probe.

    Parameters
    ----------
    opr_path : path-like
        OPR pulse times, s (:func:`read_times`), strictly increasing.
    probes : list of (float, path-like) or (float, path-like, "signal"[, start_s])
        Each probe's angle (deg, anticlockwise from +x) and its pulse times, s; or (with
        ``"signal"``) its raw signal, volts (``.npy`` or one-column CSV), triggered as
        ``signal`` says, its first sample at ``start_s`` (None or absent:
        ``signal.start_s``).
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
    signal : SignalOptions, optional
        Sample rate, trigger and clock of the raw-signal probes.
    encoder_pulses : int, optional
        The OPR file is a shaft encoder of this many tooth positions per revolution
        (:func:`~bttsim_stream.process.identify.encoder_revolutions`): pulse 0 of each
        revolution after a missing-tooth gap, or pulse ``encoder_index`` and every K-th.

    Returns
    -------
    IngestResult
    """
    _check_out(out, [opr_path, *(pr[1] for pr in probes)])
    info, notes = _geometry([pr[0] for pr in probes], n_blades, tip_radius_m, scenario_path, engine_orders, rig)
    nb, npr = info.n_blades, info.n_probes
    opr, encoder = _read_opr(opr_path, column, encoder_pulses, encoder_index, notes)
    if any(len(pr) > 2 for pr in probes):
        signal = (signal or SignalOptions()).resolve(scenario_path)
    med_rpm = _median_rpm(opr_path, opr)
    phase = rotor_phase_from_opr(opr)
    out = Path(out)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".spill", dir=out.parent))
    try:
        trains, params, per_probe, doubles = _read_probes(opr, probes, info, signal, column, tolerance, encoder,
                                                          phase, tmp)
        labs, fin, half = _identify(opr, trains, params, doubles, encoder, phase, nb, tmp / "toa.f8")
        good = np.flatnonzero(np.all(half, axis=1))
        if good.size < 3:
            raise BttsimError(f"{opr_path}: fewer than 3 revolutions with pulses on every probe "
                              f"({good.size}); do the probe files cover the OPR file's time span?")
        lo, hi = int(good[0]), int(good[-1]) + 1
        nr = hi - lo
        ex_pass, ex_t, tot = _extra_pulses(opr, labs, doubles, fin, per_probe, lo, hi, nb)
        del labs, doubles

        def toa_rows(a: int, b: int) -> np.ndarray:
            return np.fromfile(tmp / "toa.f8", dtype=float, count=(b - a) * nb * npr,
                               offset=8 * (lo + a) * nb * npr).reshape(b - a, nb, npr)

        opr_k = opr[lo:hi]
        rpm_k = 60.0 / np.diff(opr[lo:min(hi + 1, opr.size)])
        h = hashlib.sha256(b"pulses" + opr_k.tobytes())
        for a in range(0, nr, _CHUNK_REVS):
            h.update(toa_rows(a, min(nr, a + _CHUNK_REVS)).tobytes())
        h.update(ex_t.tobytes())
        run_id = h.hexdigest()[:16]
        info = replace(info, n_revolutions=nr, duration_s=float(opr_k[-1] - opr_k[0]), run_id=run_id,
                       speed_range_rpm=(float(rpm_k.min()), float(rpm_k.max())), software_version=__version__,
                       has_truth=False)
        res = IngestResult(path=str(out), run_id=run_id, revolutions=nr, n_blades=nb, n_probes=npr,
                           toas=int(fin[lo:hi].sum()), median_rpm=med_rpm, per_probe=tuple(per_probe),
                           notes=tuple(notes), **tot)
        source = {"kind": "pulses", "opr": str(opr_path),
                  "probes": [[float(a), str(p), *kind] for a, p, *kind in probes], "column": column,
                  "encoder_pulses": encoder_pulses, "encoder_index": encoder_index,
                  "signal": None if signal is None else {f.name: getattr(signal, f.name) for f in fields(signal)},
                  "scenario": None if scenario_path is None else str(scenario_path), "first_opr_pulse": lo}
        record = {"run_id": run_id, "rig": info.rig, "scenario_toml": info.scenario_toml,
                  "software_version": __version__, "source": json.dumps(source), "ingest": json.dumps(res.counts())}
        _write(out, info, np.arange(nr, dtype=np.int64), opr_k, toa_rows, (nr, nb, npr), ex_pass, ex_t, record,
               opr_path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return res

"""One campaign run on a worker: simulate, process with every processor, score against truth.

:func:`execute_run` is the Dask task: it takes a :class:`~bttsim_stream.campaign.spec.RunSpec`
and returns its result rows (one per crossing x blade x processor; a processor that fails or
finds no resonance gives one row with ``status`` and ``error`` saying why). It never raises
for a problem of the run itself, so one bad run is rows with their reason, never a failed
campaign; a worker that dies is Dask's business (the task is retried elsewhere).

A user's processor is ``module:function`` called as ``function(tables, run)``: the run's
acquisition as the tidy tables of ``bttsim export`` (``schemas/export.md``), built in memory
by :func:`user_tables`: ``tables`` maps ``"opr"`` and ``"toa"`` to pyarrow Tables with the
columns and dtypes of the exported Parquet files, ``run`` is ``run.json``'s ``run`` object
(the run metadata); never the truth. It returns its per-blade estimates as a table (a pyarrow
Table, a pandas or polars DataFrame, or a dict of columns): ``blade`` and ``amp_pkpk_m``, and
optionally ``eo``, ``amp_std_m``, ``amp_ci95_lo_m``, ``amp_ci95_hi_m``, ``freq_hz``
(:data:`USER_COLUMNS`), scored against the truth's per-blade peak of the run at that engine
order (``truth_peaks``). A processor that raises, or returns anything else, is one ``error``
row with the reason on one line.
"""

from __future__ import annotations

import copy
import importlib
import math
import os
import tempfile
import time
from collections.abc import Mapping
from dataclasses import fields

import numpy as np

from ..process.pipeline import ProcessOptions, check_window, process_arrays
from ..process.resonance import truth_peaks
from ..scenario import Scenario
from .spec import Processor, RunSpec

__all__ = ["execute_run", "user_tables", "warm_up", "ROW_COLUMNS", "USER_COLUMNS", "Z95"]

#: Two-sided 95 % normal quantile: ``amp_ci95 = amp +- Z95 * amp_std_m`` when a method gives
#: a standard uncertainty but no interval.
Z95 = 1.959963984540054

#: The per-row columns (besides the axis values), in order; ``worker`` and the ``*_s``
#: timings are the only ones that differ between two campaigns of one spec.
ROW_COLUMNS = ("run_id", "index", "replicate", "seed", "worker", "method", "status", "error", "crossing", "eo",
               "nd", "rpm", "cn", "blade", "amp_pkpk_m", "amp_std_m", "amp_ci95_lo_m", "amp_ci95_hi_m", "freq_hz",
               "truth_amp_pkpk_m", "truth_freq_hz", "E_A_pct", "E_f_pct", "simulate_s", "process_s")
TIMING_COLUMNS = ("worker", "simulate_s", "process_s")


#: The columns a user's processor may return, with the one-letter kind each must have
#: (``i`` an integer, ``f`` a float); ``blade`` and ``amp_pkpk_m`` are required.
USER_COLUMNS = {"blade": "i", "eo": "i", "amp_pkpk_m": "f", "amp_std_m": "f", "amp_ci95_lo_m": "f",
                "amp_ci95_hi_m": "f", "freq_hz": "f"}


def warm_up() -> int:
    """Import what a run needs (a worker's first task would pay it otherwise); the process id."""
    from .. import acquisition, offline  # noqa: F401
    from ..sim import core  # noqa: F401

    return os.getpid()


def _worker_name() -> str:
    try:
        from distributed import get_worker

        return str(get_worker().name)
    except (ImportError, ValueError):
        return f"local-{os.getpid()}"


def _scratch() -> str | None:
    try:
        from distributed import get_worker

        return get_worker().local_directory
    except (ImportError, ValueError):
        return None


def one_line(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {' '.join(str(exc).split())}"[:500]


def _simulate(run: RunSpec, scn: Scenario):
    """(opr_s, toa_s, revolution, info, truth, mcap path or None): in memory, or through a
    temporary MCAP in the worker's scratch when the campaign asks for files."""
    from ..acquisition import AcquisitionStream, simulate_to_mcap
    from ..sim.core import collect

    if not run.mcap:
        stream = AcquisitionStream(scn, include_truth=True, chunk_revolutions=None)
        b = collect(list(stream.sim))
        return b.opr_s, b.toa_s, b.revolution, stream.info, b.truth, None
    from ..offline import load_run

    fd, path = tempfile.mkstemp(prefix=f"bttsim-{run.run_id}-", suffix=".mcap", dir=_scratch())
    os.close(fd)
    simulate_to_mcap(scn, path)
    rec = load_run(path)
    return rec.opr_s, rec.toa_s, rec.revolution, rec.meta, rec.truth, path


def execute_run(run: RunSpec) -> list[dict]:
    """Simulate ``run`` and score each of its processors (the Dask task).

    Returns
    -------
    list of dict
        Rows of :data:`ROW_COLUMNS` plus the axis values.
    """
    from threadpoolctl import threadpool_limits

    from ..scenario import scenario_from_dict
    import tomllib

    base = {"run_id": run.run_id, "index": run.index, "replicate": run.replicate, "seed": run.seed,
            "worker": _worker_name(), **{k: axis_value(v) for k, v in run.point.items()}}
    rows: list[dict] = []
    with threadpool_limits(1):
        t0 = time.perf_counter()
        path = None
        try:
            scn = scenario_from_dict(tomllib.loads(run.scenario_toml), source=f"run {run.run_id}")
            opr_s, toa_s, revolution, info, truth, path = _simulate(run, scn)
        except Exception as exc:  # noqa: BLE001 -- the run's failure is a result row, not a crash
            t_sim = time.perf_counter() - t0
            why = f"simulation: {one_line(exc)}"
            return [failed_row(base, p.name, "error", why, t_sim, 0.0) for p in run.processors]
        t_sim = time.perf_counter() - t0
        tables = None  # the user processors' input, built for the first one
        try:
            for p in run.processors:
                t1 = time.perf_counter()
                try:
                    if p.method == "user":
                        tables = tables or user_tables(revolution, opr_s, toa_s, info)
                        new = _score_user(base, p, *tables, truth)
                    else:
                        new = _score_builtin(base, p, opr_s, toa_s, revolution, info, truth)
                except (Exception, SystemExit) as exc:  # noqa: BLE001 -- a user's code may even exit
                    new = [failed_row(base, p.name, "error", one_line(exc), t_sim, 0.0)]
                dt = time.perf_counter() - t1
                for r in new:
                    r["simulate_s"], r["process_s"] = t_sim, dt
                rows += new
        finally:
            if path is not None:
                try:
                    os.unlink(path)
                except OSError:
                    pass
    return rows


def axis_value(v):
    """An axis value as one Parquet cell: a list (probe layout, factors) as its comma-joined text."""
    if isinstance(v, list):
        return ",".join(repr(x) if isinstance(x, float) else str(x) for x in v)
    return v


def failed_row(base: dict, method: str, status: str, error: str, t_sim: float, t_proc: float) -> dict:
    nan = math.nan
    return dict(base, method=method, status=status, error=error, crossing=-1, eo=-1, nd=0, rpm=nan, cn=nan,
                blade=-1, amp_pkpk_m=nan, amp_std_m=nan, amp_ci95_lo_m=nan, amp_ci95_hi_m=nan, freq_hz=nan,
                truth_amp_pkpk_m=nan, truth_freq_hz=nan, E_A_pct=nan, E_f_pct=nan, simulate_s=t_sim,
                process_s=t_proc)


def f64(row: dict, key: str) -> float:
    v = row.get(key)
    return math.nan if v is None else float(v)


def _score_builtin(base: dict, p: Processor, opr_s, toa_s, revolution, info, truth) -> list[dict]:
    """Rows of one built-in method: one per resonance crossing and blade (``bttsim process``'s
    numbers exactly: the same :func:`process_arrays` on the same arrays)."""
    opts = ProcessOptions(method=p.method, prep=p.prep, window=p.window)
    check_window(opts.window, int(np.size(opr_s)))  # as bttsim process: an error row
    result = process_arrays(opr_s, toa_s, info, opts, truth=truth, revolution0=int(revolution[0]))
    summary = result.summary
    crossings = [e for e in summary.get("resonances", []) if e.get("kind", "crossing") != "dwell"]
    if not crossings:
        notes = "; ".join(summary.get("notes", [])) or f"status {summary.get('status')!r}"
        return [failed_row(base, p.name, "none", f"no resonance found: {notes}"[:500], 0.0, 0.0)]
    rows = []
    for i, e in enumerate(crossings):
        for b in e["blades"]:
            amp, std = f64(b, "amp_pkpk_m"), f64(b, "amp_std_m")
            lo, hi = (b["amp_ci95_m"] if "amp_ci95_m" in b else (amp - Z95 * std, amp + Z95 * std))
            rows.append(dict(base, method=p.name, status="ok", error="", crossing=i, eo=int(e["eo"]),
                             nd=int(e["nd"]), rpm=f64(e, "rpm"), cn=f64(e, "cn"), blade=int(b["blade"]),
                             amp_pkpk_m=amp, amp_std_m=std, amp_ci95_lo_m=float(lo), amp_ci95_hi_m=float(hi),
                             freq_hz=f64(b, "freq_hz"), truth_amp_pkpk_m=f64(b, "truth_amp_pkpk_m"),
                             truth_freq_hz=f64(b, "truth_freq_hz"), E_A_pct=f64(b, "E_A_pct"),
                             E_f_pct=f64(b, "E_f_pct")))
    return rows


def load_processor(target: str):
    """The function of ``module:function`` (ImportError / AttributeError name it)."""
    mod, _, fn = target.partition(":")
    return getattr(importlib.import_module(mod), fn)


def user_tables(revolution, opr_s, toa_s, info) -> tuple[dict, dict]:
    """What a user's processor gets: the acquisition tables of ``bttsim export``, in memory.

    Parameters
    ----------
    revolution : ndarray of int, shape (n_rev,)
    opr_s : ndarray, shape (n_rev,)
    toa_s : ndarray, shape (n_rev, n_blades, n_probes)
    info : RunInfo
        The run metadata.

    Returns
    -------
    tables : dict of str -> pyarrow.Table
        ``"opr"`` (``revolution`` int64, ``opr_s`` float64) and ``"toa"`` (``revolution,
        blade, probe`` int64, ``toa_s`` float64, NaN: missing), row for row and type for type
        the ``opr.parquet`` and ``toa.parquet`` that ``bttsim export`` writes of this run.
    run : dict
        ``run.json``'s ``run`` object: the metadata as JSON values (lists; None for NaN).
    """
    import pyarrow as pa

    from ..export import f64, jsonable, long_cols

    rev = np.asarray(revolution, dtype=np.int64)
    cols = {"opr": {"revolution": rev.copy(), "opr_s": f64(opr_s)},
            "toa": dict(long_cols(np.shape(toa_s), ("revolution", "blade", "probe"), rev), toa_s=f64(toa_s))}
    tables = {name: pa.table({k: pa.array(v) for k, v in c.items()}) for name, c in cols.items()}
    return tables, jsonable({f.name: getattr(info, f.name) for f in fields(info)})


def _user_columns(out, target: str, n_blades: int) -> dict:
    """The columns of what a user's processor returned, checked: name -> 1-D ndarray (a
    scalar is repeated over the rows); ValueError naming the first problem."""
    if hasattr(out, "column_names") and hasattr(out, "column"):  # a pyarrow Table
        cols = {str(c): out.column(c).to_numpy(zero_copy_only=False) for c in out.column_names}
    elif isinstance(out, Mapping):
        cols = {str(k): v for k, v in out.items()}
    elif hasattr(out, "columns") and hasattr(out, "__getitem__"):  # a pandas / polars DataFrame
        cols = {str(c): out[c] for c in out.columns}
    else:
        raise ValueError(f"{target} returned {type(out).__name__}, not a table of per-blade estimates "
                         "(a pyarrow Table, a DataFrame or a dict of columns)")
    unknown = sorted(set(cols) - set(USER_COLUMNS))
    missing = [c for c in ("blade", "amp_pkpk_m") if c not in cols]
    if unknown or missing:
        what = f"unknown column(s) {', '.join(unknown)}" if unknown else f"no column {', '.join(missing)}"
        raise ValueError(f"{target} returned {what}; the columns are {', '.join(USER_COLUMNS)}")
    n = np.size(cols["blade"])
    out_cols = {}
    for k, v in cols.items():
        a = np.asarray(v)
        if a.ndim > 1 or (a.ndim == 1 and a.size != n) or a.dtype.kind not in "iuf":
            raise ValueError(f"{target} returned column {k} of shape {a.shape} and dtype {a.dtype}, "
                             f"expected {n} numbers (one per row of its blade column)")
        a = np.broadcast_to(a.astype(float), (n,))
        if np.isinf(a).any():
            raise ValueError(f"{target} returned an infinite {k}")
        if USER_COLUMNS[k] == "i" and not np.all(a == np.round(a)):
            raise ValueError(f"{target} returned a {k} that is not an integer: {a[a != np.round(a)][0]!r}")
        if k in ("amp_pkpk_m", "amp_std_m") and (a < 0).any():
            raise ValueError(f"{target} returned a negative {k}: {a[a < 0][0]!r}")
        out_cols[k] = a
    blade = out_cols["blade"]
    if ((blade < 0) | (blade >= n_blades)).any():
        raise ValueError(f"{target} returned blade {int(blade[(blade < 0) | (blade >= n_blades)][0])}, "
                         f"not in 0..{n_blades - 1}")
    return out_cols


def _score_user(base: dict, p: Processor, tables: dict, run: dict, truth) -> list[dict]:
    """Rows of a user's processor: one per engine order it returned (``crossing`` by ascending
    EO) and blade (a blade it left out: NaN), scored against the truth's per-blade peak."""
    nb = int(run["n_blades"])
    fn = load_processor(p.target)
    cols = _user_columns(fn(tables, copy.deepcopy(run)), p.target, nb)  # its own copy: it may change it
    if "eo" not in cols:
        if not run.get("engine_orders"):
            raise ValueError(f"{p.target} returned no eo column and the run announces no engine order")
        cols["eo"] = np.full(cols["blade"].size, float(run["engine_orders"][0]))
    if (cols["eo"] <= 0).any():
        raise ValueError(f"{p.target} returned eo {int(cols['eo'].min())}, not a positive engine order")
    eo_all, blade_all = cols["eo"].astype(np.int64), cols["blade"].astype(np.int64)
    if len(set(zip(eo_all.tolist(), blade_all.tolist()))) < eo_all.size:
        raise ValueError(f"{p.target} returned two rows for one blade and engine order")
    eos = sorted(set(eo_all.tolist()))
    if not eos:  # no rows: every blade unestimated at the run's first engine order
        if not run.get("engine_orders"):
            raise ValueError(f"{p.target} returned no rows and the run announces no engine order")
        eos = [int(run["engine_orders"][0])]
    rows = []
    for crossing, eo in enumerate(eos):
        sel = eo_all == eo

        def arr(key):
            a = np.full(nb, np.nan)
            if key in cols:
                a[blade_all[sel]] = cols[key][sel]
            return a

        amp, std, f = arr("amp_pkpk_m"), arr("amp_std_m"), arr("freq_hz")
        lo, hi = arr("amp_ci95_lo_m"), arr("amp_ci95_hi_m")
        if (lo > hi).any():
            raise ValueError(f"{p.target} returned amp_ci95_lo_m above amp_ci95_hi_m "
                             f"(blade {int(np.argmax(lo > hi))}, eo {eo})")
        no_ci = np.isnan(lo) & np.isnan(hi)
        lo, hi = np.where(no_ci, amp - Z95 * std, lo), np.where(no_ci, amp + Z95 * std, hi)
        tp = truth_peaks(truth, eo) if truth is not None else None
        t_amp = tp.amp_pkpk_m if tp is not None else np.full(nb, np.nan)
        t_f = tp.freq_hz if tp is not None else np.full(nb, np.nan)
        with np.errstate(all="ignore"):
            e_a = 100.0 * np.abs(amp - t_amp) / t_amp
            e_f = 100.0 * np.abs(f - t_f) / t_f
        for b in range(nb):
            rows.append(dict(base, method=p.name, status="ok", error="", crossing=crossing, eo=eo, nd=0,
                             rpm=math.nan, cn=math.nan, blade=b, amp_pkpk_m=float(amp[b]), amp_std_m=float(std[b]),
                             amp_ci95_lo_m=float(lo[b]), amp_ci95_hi_m=float(hi[b]), freq_hz=float(f[b]),
                             truth_amp_pkpk_m=float(t_amp[b]), truth_freq_hz=float(t_f[b]),
                             E_A_pct=float(e_a[b]), E_f_pct=float(e_f[b])))
    return rows

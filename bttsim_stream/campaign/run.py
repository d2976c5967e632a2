"""One campaign run on a worker: simulate, process with every processor, score against truth.

:func:`execute_run` is the Dask task: it takes a :class:`~bttsim_stream.campaign.spec.RunSpec`
and returns its result rows (one per crossing x blade x processor; a processor that fails or
finds no resonance gives one row with ``status`` and ``error`` saying why). It never raises
for a problem of the run itself, so one bad run is rows with their reason, never a failed
campaign; a worker that dies is Dask's business (the task is retried elsewhere).

A user's processor is ``module:function`` called as ``function(run)`` with a :class:`RunData`
(the acquisition arrays and metadata; never the truth). It returns the per-blade peak-to-peak
amplitudes, m: an array of shape (n_blades,), or a mapping with ``amp_pkpk_m`` and optionally
``amp_ci95_lo_m``, ``amp_ci95_hi_m``, ``amp_std_m``, ``freq_hz`` (each (n_blades,)) and
``eo``. It is scored against the truth's per-blade peak of the run (``truth_peaks``).
"""

from __future__ import annotations

import importlib
import math
import os
import tempfile
import time
from dataclasses import dataclass

import numpy as np

from ..process.pipeline import ProcessOptions, process_arrays
from ..process.resonance import truth_peaks
from ..scenario import Scenario
from .spec import Processor, RunSpec

__all__ = ["RunData", "execute_run", "warm_up", "ROW_COLUMNS", "Z95"]

#: Two-sided 95 % normal quantile: ``amp_ci95 = amp +- Z95 * amp_std_m`` when a method gives
#: a standard uncertainty but no interval.
Z95 = 1.959963984540054

#: The per-row columns (besides the axis values), in order; ``worker`` and the ``*_s``
#: timings are the only ones that differ between two campaigns of one spec.
ROW_COLUMNS = ("run_id", "index", "replicate", "seed", "worker", "method", "status", "error", "crossing", "eo",
               "nd", "rpm", "cn", "blade", "amp_pkpk_m", "amp_std_m", "amp_ci95_lo_m", "amp_ci95_hi_m", "freq_hz",
               "truth_amp_pkpk_m", "truth_freq_hz", "E_A_pct", "E_f_pct", "simulate_s", "process_s")
TIMING_COLUMNS = ("worker", "simulate_s", "process_s")


@dataclass(frozen=True, slots=True, eq=False)
class RunData:
    """What a user's processor gets: the acquisition of one run (no truth).

    Attributes
    ----------
    run_id : str
    opr_s : ndarray, shape (n_rev,)
        OPR pulse times, s.
    toa_s : ndarray, shape (n_rev, n_blades, n_probes)
        TOAs, s (NaN: missing).
    revolution : ndarray of int64, shape (n_rev,)
    probe_angles_rad : ndarray, shape (n_probes,)
    n_blades : int
    tip_radius_m : float
    engine_orders : tuple of int
        The excitation's engine orders (what the run metadata announces).
    info : RunInfo
        The whole run metadata (``bttsim_stream.sim.core.RunInfo``).
    scenario : Scenario
    mcap_path : str or None
        The run's recording when the campaign has ``mcap = true`` (deleted after the run).
    """

    run_id: str
    opr_s: np.ndarray
    toa_s: np.ndarray
    revolution: np.ndarray
    probe_angles_rad: np.ndarray
    n_blades: int
    tip_radius_m: float
    engine_orders: tuple
    info: object
    scenario: Scenario
    mcap_path: str | None = None


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


def _one_line(exc: BaseException) -> str:
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
            "worker": _worker_name(), **{k: _axis_value(v) for k, v in run.point.items()}}
    rows: list[dict] = []
    with threadpool_limits(1):
        t0 = time.perf_counter()
        path = None
        try:
            scn = scenario_from_dict(tomllib.loads(run.scenario_toml), source=f"run {run.run_id}")
            opr_s, toa_s, revolution, info, truth, path = _simulate(run, scn)
        except Exception as exc:  # noqa: BLE001 -- the run's failure is a result row, not a crash
            t_sim = time.perf_counter() - t0
            return [_failed(base, p.name, "error", f"simulation: {_one_line(exc)}", t_sim, 0.0) for p in run.processors]
        t_sim = time.perf_counter() - t0
        try:
            for p in run.processors:
                t1 = time.perf_counter()
                try:
                    if p.method == "user":
                        data = RunData(run_id=run.run_id, opr_s=opr_s, toa_s=toa_s, revolution=revolution,
                                       probe_angles_rad=np.asarray(info.probe_angles_rad, float),
                                       n_blades=int(info.n_blades), tip_radius_m=float(info.tip_radius_m),
                                       engine_orders=tuple(int(e.engine_order) for e in scn.excitation),
                                       info=info, scenario=scn, mcap_path=path)
                        new = _score_user(base, p, data, truth)
                    else:
                        new = _score_builtin(base, p, opr_s, toa_s, revolution, info, truth)
                except Exception as exc:  # noqa: BLE001
                    new = [_failed(base, p.name, "error", _one_line(exc), t_sim, 0.0)]
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


def _axis_value(v):
    """An axis value as one Parquet cell: a list (probe layout, factors) as its comma-joined text."""
    if isinstance(v, list):
        return ",".join(repr(x) if isinstance(x, float) else str(x) for x in v)
    return v


def _failed(base: dict, method: str, status: str, error: str, t_sim: float, t_proc: float) -> dict:
    nan = math.nan
    return dict(base, method=method, status=status, error=error, crossing=-1, eo=-1, nd=0, rpm=nan, cn=nan,
                blade=-1, amp_pkpk_m=nan, amp_std_m=nan, amp_ci95_lo_m=nan, amp_ci95_hi_m=nan, freq_hz=nan,
                truth_amp_pkpk_m=nan, truth_freq_hz=nan, E_A_pct=nan, E_f_pct=nan, simulate_s=t_sim,
                process_s=t_proc)


def _f(row: dict, key: str) -> float:
    v = row.get(key)
    return math.nan if v is None else float(v)


def _score_builtin(base: dict, p: Processor, opr_s, toa_s, revolution, info, truth) -> list[dict]:
    """Rows of one built-in method: one per resonance crossing and blade (``bttsim process``'s
    numbers exactly: the same :func:`process_arrays` on the same arrays)."""
    opts = ProcessOptions(method=p.method, prep=p.prep, window=p.window)
    result = process_arrays(opr_s, toa_s, info, opts, truth=truth, revolution0=int(revolution[0]))
    summary = result.summary
    crossings = [e for e in summary.get("resonances", []) if e.get("kind", "crossing") != "dwell"]
    if not crossings:
        notes = "; ".join(summary.get("notes", [])) or f"status {summary.get('status')!r}"
        return [_failed(base, p.name, "none", f"no resonance found: {notes}"[:500], 0.0, 0.0)]
    rows = []
    for i, e in enumerate(crossings):
        for b in e["blades"]:
            amp, std = _f(b, "amp_pkpk_m"), _f(b, "amp_std_m")
            lo, hi = (b["amp_ci95_m"] if "amp_ci95_m" in b else (amp - Z95 * std, amp + Z95 * std))
            rows.append(dict(base, method=p.name, status="ok", error="", crossing=i, eo=int(e["eo"]),
                             nd=int(e["nd"]), rpm=_f(e, "rpm"), cn=_f(e, "cn"), blade=int(b["blade"]),
                             amp_pkpk_m=amp, amp_std_m=std, amp_ci95_lo_m=float(lo), amp_ci95_hi_m=float(hi),
                             freq_hz=_f(b, "freq_hz"), truth_amp_pkpk_m=_f(b, "truth_amp_pkpk_m"),
                             truth_freq_hz=_f(b, "truth_freq_hz"), E_A_pct=_f(b, "E_A_pct"),
                             E_f_pct=_f(b, "E_f_pct")))
    return rows


def load_processor(target: str):
    """The function of ``module:function`` (ImportError / AttributeError name it)."""
    mod, _, fn = target.partition(":")
    return getattr(importlib.import_module(mod), fn)


def _score_user(base: dict, p: Processor, data: RunData, truth) -> list[dict]:
    """Rows of a user's processor, scored against the truth's per-blade peak."""
    out = load_processor(p.target)(data)
    if not isinstance(out, dict):
        out = {"amp_pkpk_m": out}
    nb = data.n_blades

    def arr(key):
        if key not in out or out[key] is None:
            return np.full(nb, np.nan)
        a = np.asarray(out[key], dtype=float).reshape(-1)
        if a.shape != (nb,):
            raise ValueError(f"{p.target} returned {key} of shape {a.shape}, expected ({nb},)")
        return a

    amp, std, f = arr("amp_pkpk_m"), arr("amp_std_m"), arr("freq_hz")
    lo, hi = arr("amp_ci95_lo_m"), arr("amp_ci95_hi_m")
    no_ci = np.isnan(lo) & np.isnan(hi)
    lo, hi = np.where(no_ci, amp - Z95 * std, lo), np.where(no_ci, amp + Z95 * std, hi)
    eo = int(out.get("eo", data.engine_orders[0] if data.engine_orders else 0))
    tp = truth_peaks(truth, eo) if truth is not None else None
    t_amp = tp.amp_pkpk_m if tp is not None else np.full(nb, np.nan)
    t_f = tp.freq_hz if tp is not None else np.full(nb, np.nan)
    with np.errstate(all="ignore"):
        e_a = 100.0 * np.abs(amp - t_amp) / t_amp
        e_f = 100.0 * np.abs(f - t_f) / t_f
    rows = []
    for b in range(nb):
        rows.append(dict(base, method=p.name, status="ok", error="", crossing=0, eo=eo, nd=0, rpm=math.nan,
                         cn=math.nan, blade=b, amp_pkpk_m=float(amp[b]), amp_std_m=float(std[b]),
                         amp_ci95_lo_m=float(lo[b]), amp_ci95_hi_m=float(hi[b]), freq_hz=float(f[b]),
                         truth_amp_pkpk_m=float(t_amp[b]), truth_freq_hz=float(t_f[b]), E_A_pct=float(e_a[b]),
                         E_f_pct=float(e_f[b])))
    return rows

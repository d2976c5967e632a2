"""``bttsim campaign``: submit a spec's runs to Dask distributed and gather the results.

Without a scheduler address an embedded ``LocalCluster`` runs on loopback (one
single-threaded worker process per core, BLAS threads 1, the dashboard on a free loopback
port when bokeh is installed); with one,
the runs go to that scheduler's workers. Each run is one task (``Client.submit`` with the
spec's ``retries``); results are taken as they finish (``as_completed``) and written at once,
one part file per run, so an interrupted campaign keeps every finished run and ``resume``
skips them. Scheduling, placement and retries are Dask's; this module only submits and
gathers.
"""

from __future__ import annotations

import json
import logging
import math
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from .. import __version__
from ..errors import BttsimError
from .report import write_report
from .results import PARTS, read_part, sort_rows, write_rows
from .run import execute_run, warm_up
from .spec import CampaignSpec, RunSpec, expand

__all__ = ["CampaignOutcome", "run_campaign", "connect", "tls_security", "spec_record", "MAX_WORKERS"]

#: Most workers of the embedded cluster (``--workers``); it never starts more than there are
#: runs to do.
MAX_WORKERS = 256

#: The files a campaign writes in its folder (besides ``runs/`` and the figures).
OUTPUTS = ("spec.json", "campaign.json", "results.parquet", "report.md")


@dataclass(frozen=True, slots=True)
class CampaignOutcome:
    """What a campaign did.

    Attributes
    ----------
    runs : int
        Runs in the spec.
    executed, skipped : int
        Run now, and taken from an earlier campaign in the folder (``resume``).
    failed : int
        Runs with at least one ``error`` or ``lost`` row.
    rows : int
        Rows of ``results.parquet``.
    wall_s : float
        From the start to the last result (cluster start-up included).
    compute_s : float
        From the first submission to the last result.
    workers : int
        Workers of the cluster when the campaign started.
    results, report : Path
    """

    runs: int
    executed: int
    skipped: int
    failed: int
    rows: int
    wall_s: float
    compute_s: float
    workers: int
    results: Path
    report: Path

    @property
    def runs_per_s(self) -> float:
        """Runs per second of compute (after the cluster is up)."""
        return self.executed / self.compute_s if self.compute_s > 0 else math.nan


def _dask():
    try:
        import distributed
    except ImportError:
        raise BttsimError("bttsim campaign needs Dask: pip install 'bttsim-stream[campaign]'") from None
    return distributed


def tls_security(tls_dir, name: str = "campaign"):
    """Dask's ``Security`` for a client with the certificates of ``bttsim certs``: ``ca.pem``
    and ``NAME.pem`` / ``NAME-key.pem`` of ``tls_dir``, encryption required."""
    distributed = _dask()
    d = Path(tls_dir)
    files = {"ca": d / "ca.pem", "cert": d / f"{name}.pem", "key": d / f"{name}-key.pem"}
    missing = [str(f) for f in files.values() if not f.is_file()]
    if missing:
        raise BttsimError(f"--tls-dir {d}: missing {', '.join(missing)} (bttsim certs {d} --names scheduler,"
                          f"worker,{name} --host SCHEDULER_HOST)")
    return distributed.Security(tls_ca_file=str(files["ca"]), tls_client_cert=str(files["cert"]),
                                tls_client_key=str(files["key"]), require_encryption=True)


def connect(scheduler: str | None, n_workers: int | None, *, timeout_s: float = 10.0, dashboard: str | None = None,
            security=None):
    """``(client, cluster or None)``: a client of ``scheduler`` (with Dask ``security`` for a
    ``tls://`` address), or of a new loopback ``LocalCluster`` of ``n_workers``
    single-threaded worker processes (default: one per core). An unreachable scheduler, or
    one that refuses the client's TLS handshake, is a one-line :class:`BttsimError`."""
    distributed = _dask()
    import dask

    if scheduler:
        try:
            return distributed.Client(scheduler, timeout=timeout_s, security=security), None
        except (OSError, TimeoutError, ValueError, TypeError) as exc:
            hint = ("; a tls:// scheduler needs --tls-dir (or Dask's distributed.comm.tls configuration)"
                    if scheduler.startswith("tls://") and security is None and "ssl_context" in str(exc) else "")
            raise BttsimError(f"cannot reach the Dask scheduler at {scheduler} "
                              f"({' '.join(str(exc).split())[:200]}){hint}") from None
    n = int(n_workers) if n_workers else (os.cpu_count() or 1)
    if not 1 <= n <= MAX_WORKERS:
        raise BttsimError(f"--workers must be in 1..{MAX_WORKERS}, got {n}")
    # the scheduler's HTTP server (health, metrics; the dashboard with bokeh) always starts:
    # on a free loopback port unless an address is asked for
    try:
        with dask.config.set(EMBEDDED_CONFIG | {"distributed.nanny.pre-spawn-environ": worker_environ()}):
            cluster = distributed.LocalCluster(n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1",
                                               dashboard_address=dashboard or "127.0.0.1:0",
                                               silence_logs=logging.CRITICAL)
    except (OSError, RuntimeError) as exc:  # Dask's "Cluster failed to start: [Errno 99] ..."
        where = f" with --dashboard {dashboard}" if dashboard else ""
        raise BttsimError(f"cannot start the embedded Dask cluster{where} ({' '.join(str(exc).split())[:200]})"
                          ) from None
    return distributed.Client(cluster), cluster


#: Dask configuration of the embedded cluster. No statistical profiler in the workers: its
#: history (a snapshot of the task stacks every second, the last 1000 kept) grew a worker by
#: 10 MB per 100 short runs. Slower housekeeping loops (event-loop tick, system and memory
#: monitors, work stealing): an idle one-worker cluster then costs about 1 % of a core
#: instead of 3 %, CPU that every run paid in proportion to its wall time.
EMBEDDED_CONFIG = {
    "distributed.worker.profile.enabled": False,
    "distributed.admin.tick.interval": "500ms",
    "distributed.admin.system-monitor.interval": "2s",
    "distributed.worker.memory.monitor-interval": "1s",
    "distributed.scheduler.work-stealing-interval": "1s",
}


def worker_environ() -> dict:
    """The environment a nanny gives its worker: Dask's, without ``MALLOC_TRIM_THRESHOLD_``.

    Dask sets it (65536) to hand freed memory back to the OS at once; setting it also turns
    off glibc's dynamic mmap threshold, so every array over 128 kB of a run is mapped and
    unmapped afresh: about 40,000 page faults and a third more CPU per short run than the same
    run in a plain process. Without it a worker allocates as ``bttsim simulate`` does and its
    memory stays flat at one run's peak (``bench/bench_campaign.py``)."""
    import dask

    env = dict(dask.config.get("distributed.nanny.pre-spawn-environ", default={}) or {})
    env.pop("MALLOC_TRIM_THRESHOLD_", None)
    env["OMP_NUM_THREADS"] = env["MKL_NUM_THREADS"] = env["OPENBLAS_NUM_THREADS"] = 1
    return env


def _dashboard(client, scheduler: str | None, asked: str | None) -> str | None:
    """The dashboard's address when one is served: a remote scheduler's (if it has one), or
    the embedded cluster's when asked for or when bokeh is there to serve it (on loopback)."""
    try:
        link = client.dashboard_link
    except (KeyError, AttributeError):
        return None
    if not link or scheduler or asked:
        return link or None
    import importlib.util

    return link if importlib.util.find_spec("bokeh") is not None else None


def _lost_rows(run: RunSpec, exc: BaseException) -> list[dict]:
    """Rows of a run whose task failed on the cluster after Dask's retries (a worker died
    each time, or the task could not be unpickled): ``status = "lost"``, rerun by ``resume``."""
    from .run import axis_value, failed_row, one_line

    base = {"run_id": run.run_id, "index": run.index, "replicate": run.replicate, "seed": run.seed, "worker": "",
            **{k: axis_value(v) for k, v in run.point.items()}}
    return [failed_row(base, p.name, "lost", f"the cluster gave up on the task: {one_line(exc)}", math.nan, math.nan)
            for p in run.processors]


def _write_summary(path: Path, outcome: CampaignOutcome, *, resume: bool, scheduler: str | None,
                   interrupted: bool) -> None:
    """``campaign.json``: this call's numbers in ``calls`` (after those of the earlier calls
    when resuming), and the campaign's totals over every call: ``executed``, ``wall_s`` and
    ``compute_s`` summed, ``runs_per_s`` of the sums, ``workers`` the most any call had."""
    call = {"executed": outcome.executed, "skipped": outcome.skipped, "wall_s": outcome.wall_s,
            "compute_s": outcome.compute_s, "workers": outcome.workers, "scheduler": scheduler or "LocalCluster",
            "interrupted": interrupted}
    keys = tuple(call)
    calls = []
    if resume and path.is_file():
        try:
            prev = json.loads(path.read_text())
            # a campaign.json without calls (an older version's) was one call
            calls = [{k: c.get(k) for k in keys} for c in prev.get("calls", [prev]) if isinstance(c, dict)
                     and all(isinstance(c.get(k), (int, float)) and math.isfinite(c[k]) for k in keys[:5])]
        except (OSError, ValueError, AttributeError):
            calls = []  # unreadable: the numbers start again from this call
    calls.append(call)
    total = {k: sum(float(c[k]) for c in calls) for k in ("wall_s", "compute_s")}
    executed = sum(int(c["executed"]) for c in calls)
    path.write_text(json.dumps({
        "runs": outcome.runs, "executed": executed, "failed": outcome.failed, "rows": outcome.rows, **total,
        "runs_per_s": executed / total["compute_s"] if total["compute_s"] > 0 else None,
        "workers": max(int(c["workers"]) for c in calls), "scheduler": call["scheduler"],
        "interrupted": interrupted, "calls": calls, "python": sys.version.split()[0],
        "software_version": __version__}, indent=2, allow_nan=False) + "\n")


def spec_record(spec: CampaignSpec) -> dict:
    """``spec.json``: the expanded spec as JSON values (what ``--resume`` compares, but for the
    spec file's path and the software version)."""
    return json.loads(json.dumps({"name": spec.name, "source": spec.source, "base": spec.base,
                                  "axes": {a.name: list(a.values) for a in spec.axes}, "seeds": list(spec.seeds),
                                  "processors": [{"name": p.name, "method": p.method, "prep": p.prep,
                                                  "window": p.window, "target": p.target} for p in spec.processors],
                                  "software_version": __version__}))


def _same_study(a: dict, b: dict) -> bool:
    def key(d):
        return {k: v for k, v in d.items() if k not in ("source", "software_version")}

    return isinstance(a, dict) and key(a) == key(b)


def _check_folder(out: Path, record: dict, resume: bool) -> None:
    """Refuse an output folder (one-line :class:`BttsimError`, nothing written) that is not a
    folder, holds a campaign without ``resume``, or with ``resume`` holds another study's
    (its ``spec.json`` differs) or campaign outputs without a ``spec.json``."""
    if out.exists() and not out.is_dir():
        raise BttsimError(f"{out}: not a folder")
    for name in OUTPUTS:
        if (out / name).exists() and not (out / name).is_file():
            raise BttsimError(f"{out / name}: not a file (the campaign writes it there); use another --out")
    found = [n for n in OUTPUTS if (out / n).exists()]
    if (out / PARTS).is_dir() and any((out / PARTS).glob("*.parquet")):
        found.append(f"{PARTS}/")
    if not found:
        return
    if not resume:
        raise BttsimError(f"{out} already holds a campaign: --resume to finish it, or another --out")
    path = out / "spec.json"
    if "spec.json" not in found:
        raise BttsimError(f"{out}: holds {', '.join(found)} but no spec.json (not a campaign to resume); "
                          "use another --out")
    try:
        prev = json.loads(path.read_text())
    except (OSError, ValueError):
        raise BttsimError(f"{path}: unreadable, not a campaign's spec; use another --out") from None
    if not _same_study(prev, record):
        raise BttsimError(f"{path}: the folder holds another study (its spec differs); use another --out")


def _kept_runs(parts: Path, runs: list[RunSpec], spec: CampaignSpec, progress) -> dict:
    """run_id -> rows of the runs already in ``parts`` (``--resume``). A part file that is
    unreadable, of other columns or of another run is not trusted: its run runs again."""
    have = {p.stem for p in parts.glob("*.parquet")} if parts.is_dir() else set()
    kept = {}
    for r in runs:
        if r.run_id in have:
            path = parts / f"{r.run_id}.parquet"
            try:
                kept[r.run_id] = read_part(path, spec, r.run_id)
            except ValueError as exc:
                if progress is not None:
                    progress.note(f"campaign: {path}: {exc}; the run runs again")
    return kept


def _start_folder(out: Path, record: dict) -> None:
    """Create ``out`` and ``out/runs`` and write ``spec.json``."""
    try:
        (out / PARTS).mkdir(parents=True, exist_ok=True)
        (out / "spec.json").write_text(json.dumps(record, indent=2) + "\n")
    except OSError as exc:
        raise BttsimError(f"{out}: cannot write ({exc.strerror or exc})") from None


def run_campaign(spec: CampaignSpec, out_dir, *, scheduler: str | None = None, n_workers: int | None = None,
                 resume: bool = False, progress=None, timeout_s: float = 10.0,
                 dashboard: str | None = None, security=None) -> CampaignOutcome:
    """Run every run of ``spec`` on Dask and write ``results.parquet`` and ``report.md``.

    Parameters
    ----------
    spec : CampaignSpec
    out_dir : path-like
        Output folder: ``results.parquet``, ``report.md``, ``campaign.json``, ``spec.json``,
        ``runs/`` (one part file per finished run).
    scheduler : str, optional
        ``tcp://HOST:PORT`` of a running Dask scheduler; None: an embedded ``LocalCluster``.
    n_workers : int, optional
        Workers of the embedded cluster (default: one per core).
    security : distributed.Security, optional
        TLS for a ``tls://`` scheduler (:func:`tls_security`).
    resume : bool
        Keep the runs already in ``out_dir``; without it a folder holding a campaign is refused.
    progress : Progress, optional
        Progress line (``update(text)``, ``note(text)``, ``close()``).
    """
    from .results import pyarrow_modules

    pyarrow_modules()  # the extra is there before anything runs
    out = Path(out_dir)
    runs = expand(spec)
    record = spec_record(spec)
    _check_folder(out, record, resume)
    parts = out / PARTS
    kept = _kept_runs(parts, runs, spec, progress) if resume else {}
    todo = [r for r in runs if r.run_id not in kept]
    skipped = len(runs) - len(todo)
    by_run = dict(kept)  # run_id -> its rows
    lost: list[dict] = []
    t0 = time.perf_counter()
    t_submit = t_last = t0
    done = failed = 0
    n_workers_seen = 0
    interrupted = False
    if not todo:
        _start_folder(out, record)
    else:
        # no more workers than runs; the folder is written once the cluster is up (a failed
        # start leaves nothing)
        n = None if scheduler else min(n_workers or os.cpu_count() or 1, len(todo))
        client, cluster = connect(scheduler, n, timeout_s=timeout_s, dashboard=dashboard, security=security)
        try:
            _start_folder(out, record)
            distributed = _dask()
            n_workers_seen = len(client.scheduler_info().get("workers", {}))
            client.run(warm_up)  # imports on every worker now, not in the first runs' timings
            t_submit = time.perf_counter()
            link = _dashboard(client, scheduler, dashboard)
            if progress is not None and link:
                progress.note(f"campaign: Dask dashboard at {link}")
            by_key = {}
            futures = []
            for r in todo:
                fut = client.submit(execute_run, r, key=f"bttsim-run-{r.run_id}", retries=spec.retries, pure=False)
                by_key[fut.key] = r
                futures.append(fut)
            try:
                for fut in distributed.as_completed(futures):
                    r = by_key[fut.key]
                    if fut.status == "finished":
                        rows = fut.result()
                        write_rows(parts / f"{r.run_id}.parquet", rows, spec)
                        by_run[r.run_id] = rows
                        bad = any(x["status"] == "error" for x in rows)
                    else:
                        rows = _lost_rows(r, fut.exception())
                        lost += rows
                        bad = True
                    fut.release()
                    t_last = time.perf_counter()
                    done += 1
                    failed += bad
                    if progress is not None:
                        dt = time.perf_counter() - t_submit
                        progress.update(f"campaign: {done}/{len(todo)} runs ({failed} failed), "
                                        f"{done / dt:.2f} runs/s" + (f", {skipped} resumed" if skipped else ""))
            except KeyboardInterrupt:
                interrupted = True
                client.cancel(futures)
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
    wall, compute = t_last - t0, t_last - t_submit
    if progress is not None:
        progress.close()
    rows = sort_rows([row for rs in by_run.values() for row in rs] + lost, spec)
    results = out / "results.parquet"
    write_rows(results, rows, spec)
    report = out / "report.md"
    write_report(report, rows, spec, interrupted=interrupted, n_runs=len(runs))
    outcome = CampaignOutcome(runs=len(runs), executed=done, skipped=skipped,
                              failed=len({r["run_id"] for r in rows if r["status"] in ("error", "lost")}),
                              rows=len(rows), wall_s=wall, compute_s=compute, workers=n_workers_seen,
                              results=results, report=report)
    _write_summary(out / "campaign.json", outcome, resume=resume, scheduler=scheduler, interrupted=interrupted)
    if interrupted:
        raise KeyboardInterrupt
    return outcome

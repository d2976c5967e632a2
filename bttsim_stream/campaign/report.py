"""``report.md`` of a campaign: error distributions, interval coverage and failures.

First a Table-2-shaped summary (per processor, the largest and the mean error over a run's
blades, E_A and E_f, as the mean over runs with its 95 % confidence interval, by the first
axis) and the figures of :mod:`.figures` (PNG beside the report; a note without the ``plot``
extra). Then, per processor (the ``method`` column) and per value of each axis: the number of runs and of
scored blades, percentiles of ``E_A`` (Eq. 18, percent; median, 90 %, 95 %, max), the mean
``E_A`` with its 95 % confidence interval over runs (a blade's errors within one run are not
independent, so the run means are the samples), and the coverage of the 95 % amplitude
intervals (the fraction of blades whose truth lies in ``[amp_ci95_lo_m, amp_ci95_hi_m]``,
beside its binomial 95 % range); then every failed or empty run with its reason.
"""

from __future__ import annotations

import math
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np

from .._plotting import PlotExtraMissing
from .figures import axis_key, write_figures
from .spec import CampaignSpec

__all__ = ["write_report", "method_stats", "ci95_half_width"]


def ci95_half_width(x) -> float:
    """Half width of the 95 % confidence interval of the mean of the samples ``x`` (Student's
    t with ``n - 1`` degrees of freedom; NaN below two samples)."""
    from scipy.stats import t

    x = np.asarray(x, float)
    if x.size < 2:
        return math.nan
    return float(t.ppf(0.975, x.size - 1) * np.std(x, ddof=1) / math.sqrt(x.size))


def _ok(rows):
    return [r for r in rows if r["status"] == "ok"]


def method_stats(rows: list[dict]) -> dict:
    """Statistics of one group of rows (one processor, maybe one axis value).

    Returns
    -------
    dict
        ``runs``, ``blades`` (scored), ``failed_runs``, ``E_A_p50``, ``E_A_p90``, ``E_A_p95``,
        ``E_A_max``, ``E_A_mean``, ``E_A_mean_ci95`` (half width over the run means, Student's t),
        ``coverage`` (fraction, NaN without intervals), ``coverage_n``.
    """
    ok = [r for r in _ok(rows) if math.isfinite(r["E_A_pct"])]
    e = np.array([r["E_A_pct"] for r in ok], float)
    per_run = defaultdict(list)
    for r in ok:
        per_run[r["run_id"]].append(r["E_A_pct"])
    means = np.array([np.mean(v) for v in per_run.values()], float)
    with_ci = [r for r in ok if math.isfinite(r["amp_ci95_lo_m"]) and math.isfinite(r["amp_ci95_hi_m"])
               and math.isfinite(r["truth_amp_pkpk_m"])]
    inside = sum(r["amp_ci95_lo_m"] <= r["truth_amp_pkpk_m"] <= r["amp_ci95_hi_m"] for r in with_ci)
    pct = (lambda q: float(np.percentile(e, q))) if e.size else (lambda q: math.nan)
    half = ci95_half_width(means)
    return {"runs": len({r["run_id"] for r in rows}), "blades": int(e.size),
            "failed_runs": len({r["run_id"] for r in rows if r["status"] != "ok"}),
            "E_A_p50": pct(50), "E_A_p90": pct(90), "E_A_p95": pct(95),
            "E_A_max": float(e.max()) if e.size else math.nan,
            "E_A_mean": float(means.mean()) if means.size else math.nan, "E_A_mean_ci95": half,
            "coverage": inside / len(with_ci) if with_ci else math.nan, "coverage_n": len(with_ci)}


def _g(x: float, fmt: str = ".3g") -> str:
    return "–" if not math.isfinite(x) else format(x, fmt)


def _cov(s: dict) -> str:
    n = s["coverage_n"]
    if not n:
        return "–"
    lo = max(0.0, 0.95 - 1.96 * math.sqrt(0.95 * 0.05 / n))
    flag = "" if s["coverage"] >= lo else " (low)"
    return f"{100 * s['coverage']:.1f} % of {n}{flag}"


_HEAD = ("| {label} | runs | blades | failed | E_A p50 % | p90 % | p95 % | max % | mean E_A % (95 % CI) | "
         "95 % interval coverage |")


def _line(label: str, s: dict) -> str:
    mean = (f"{_g(s['E_A_mean'])} ± {_g(s['E_A_mean_ci95'], '.2g')}" if math.isfinite(s["E_A_mean_ci95"])
            else _g(s["E_A_mean"]))
    return (f"| {label} | {s['runs']} | {s['blades']} | {s['failed_runs']} | {_g(s['E_A_p50'])} | "
            f"{_g(s['E_A_p90'])} | {_g(s['E_A_p95'])} | {_g(s['E_A_max'])} | {mean} | {_cov(s)} |")


def _run_values(rows: list[dict], key: str, fn) -> np.ndarray:
    """``fn`` of ``key`` over each run's scored blades: one value per run."""
    per_run = defaultdict(list)
    for r in rows:
        if r["status"] == "ok" and math.isfinite(r[key]):
            per_run[r["run_id"]].append(r[key])
    return np.array([fn(v) for v in per_run.values()], float)


def _mean_ci(x: np.ndarray) -> str:
    if not x.size:
        return "–"
    if x.size == 1:
        return _g(float(x[0]))
    return f"{_g(float(x.mean()))} ± {_g(ci95_half_width(x), '.2g')}"


def _summary(by_method: dict, spec: CampaignSpec) -> list[str]:
    """The Table-2-shaped table: processor x (max, mean over blades) against the first axis's
    values, for E_A and E_f; each cell the mean over runs with its 95 % CI."""
    axis = spec.axes[0] if spec.axes else None
    keys = [axis_key(v) for v in axis.values] if axis else ["all runs"]
    cols = [f"E_A % @ {k}" for k in keys] + [f"E_f % @ {k}" for k in keys]
    out = ["| processor | over blades | " + " | ".join(cols) + " |", "|---|---|" + "---|" * len(cols)]
    for m, rows in by_method.items():
        groups = [[r for r in rows if axis is None or axis_key(r.get(axis.name)) == k] for k in keys]
        for label, fn in (("max", np.max), ("mean", np.mean)):
            cells = [_mean_ci(_run_values(g, key, fn)) for key in ("E_A_pct", "E_f_pct") for g in groups]
            out.append(f"| {m} | {label} | " + " | ".join(cells) + " |")
    return out


def _table(label: str, groups) -> list[str]:
    head = _HEAD.format(label=label)
    return [head, "|" + "---|" * (head.count("|") - 1), *(_line(k, method_stats(v)) for k, v in groups)]


def write_report(path, rows: list[dict], spec: CampaignSpec, *, interrupted: bool = False, n_runs: int = 0) -> None:
    """Write the campaign's ``report.md`` from its result rows."""
    methods = [p.name for p in spec.processors]
    by_method = {m: [r for r in rows if r["method"] == m] for m in methods}
    done = len({r["run_id"] for r in rows})
    out = [f"# Campaign {spec.name}", ""]
    out.append(f"{done} of {n_runs} runs in `results.parquet`"
               + (" (interrupted: the rest did not run)" if interrupted else "")
               + f"; {len(spec.seeds)} seed(s) per axis point; processors: {', '.join(methods)}.")
    if spec.axes:
        out.append("Axes: " + "; ".join(f"`{a.name}` = {', '.join(map(_show, a.values))}" for a in spec.axes) + ".")
    out += ["", "E_A (Eq. 18) and E_f (Eq. 19) are per blade and crossing, percent of the truth's peak-to-peak "
            "amplitude and resonance frequency. Coverage: blades whose truth lies in their 95 % amplitude interval "
            "(\"low\": below the binomial 95 % range of a calibrated interval).", "",
            "## Summary", "", "Per run, the largest and the mean error over its blades (as the paper's Table 2); "
            "each cell the mean over the runs ± the half width of its 95 % confidence interval"
            + (f", by `{spec.axes[0].name}`." if spec.axes else "."), ""]
    out += _summary(by_method, spec)
    out += _figures(Path(path).parent, rows, spec)
    out += ["", "## Per processor", ""]
    out += _table("processor", by_method.items())
    for a in spec.axes:
        out += ["", f"## By `{a.name}`", ""]
        groups = []
        for m in methods:
            for v in a.values:
                key = axis_key(v)
                groups.append((f"{m} @ {key}", [r for r in by_method[m] if axis_key(r.get(a.name)) == key]))
        out += _table(f"processor @ {a.name}", groups)
    out += ["", "## Failures", ""]
    bad = [r for r in rows if r["status"] != "ok"]
    if not bad:
        out.append("None: every processor reported a resonance in every run.")
    else:
        runs_bad = {(r["run_id"], r["method"]): r for r in bad}
        counts = Counter((r["method"], r["status"], r["error"]) for r in runs_bad.values())
        out += ["| processor | status | runs | reason |", "|---|---|---|---|"]
        for (m, st, err), n in counts.most_common():
            out.append(f"| {m} | {st} | {n} | {err.replace('|', '/')} |")
        out += ["", "status `none`: the processor found no resonance (no amplitude claimed); `error`: it "
                "raised; `lost`: the cluster gave up on the run after Dask's retries (`--resume` reruns it)."]
    Path(path).write_text("\n".join(out) + "\n")


def _figures(folder: Path, rows: list[dict], spec: CampaignSpec) -> list[str]:
    try:
        figs = write_figures(folder, rows, spec)
    except PlotExtraMissing as exc:
        return ["", f"(No figures: {exc}.)"]
    out = []
    for title, name in figs:
        out += ["", f"![{title}]({name})"]
    return out


def _show(v) -> str:
    if isinstance(v, list):
        return ",".join(_show(x) for x in v)
    if isinstance(v, float):
        return format(v, ".6g")
    return str(v)

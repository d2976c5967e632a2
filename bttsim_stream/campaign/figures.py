"""The figures of a campaign's ``report.md`` (matplotlib, the ``plot`` extra).

* ``ea_by_processor.png``: the distribution of ``E_A`` (Eq. 18) per processor over every
  scored blade of every run (box: quartiles; whiskers: 5 and 95 %);
* ``ea_vs_<axis>.png``, one per axis: per processor, the median ``E_A`` against the axis
  value and its 90 % band (5 to 95 % of the blades at that value);
* ``coverage.png`` (when a processor gives intervals): per processor and axis point, the
  fraction of blades whose truth lies in their 95 % amplitude interval, against the binomial
  95 % range of a calibrated interval.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from .._plotting import pyplot
from .run import axis_value
from .spec import CampaignSpec

__all__ = ["write_figures", "axis_key"]


def axis_key(v) -> str:
    """The text that identifies an axis value, the same for the spec's value and its cell."""
    v = axis_value(v)
    return format(v, ".6g") if isinstance(v, float) else str(v)


def _slug(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9]+", "_", name).strip("_")


def _ea(rows, method: str, axis: str | None = None, key: str | None = None) -> np.ndarray:
    return np.array([r["E_A_pct"] for r in rows if r["method"] == method and (axis is None or
                     axis_key(r.get(axis)) == key)], float)


def _numeric(values) -> bool:
    return all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)


def _vs_axis(plt, folder: Path, ok: list, methods: list, axis) -> str:
    keys = [axis_key(v) for v in axis.values]
    numeric = _numeric(axis.values) and len(set(axis.values)) == len(axis.values)
    x = np.asarray(axis.values, float) if numeric else np.arange(len(keys), dtype=float)
    order = np.argsort(x)
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    for m in methods:
        q = np.full((len(keys), 3), np.nan)
        for i, k in enumerate(keys):
            e = _ea(ok, m, axis.name, k)
            if e.size:
                q[i] = np.percentile(e, [5, 50, 95])
        (line,) = ax.plot(x[order], q[order, 1], "o-", label=m)
        ax.fill_between(x[order], q[order, 0], q[order, 2], color=line.get_color(), alpha=0.18, lw=0)
    if not numeric:
        ax.set_xticks(x, [k if len(k) <= 24 else k[:22] + "…" for k in keys], rotation=20, ha="right")
    elif np.all(x > 0) and x.max() / x.min() > 20:
        ax.set_xscale("log")
    ax.set_xlabel(axis.name)
    ax.set_ylabel("E_A, %  (median; band 5-95 %)")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    name = f"ea_vs_{_slug(axis.name)}.png"
    fig.tight_layout()
    fig.savefig(folder / name, dpi=110)
    plt.close(fig)
    return name


def _by_processor(plt, folder: Path, ok: list, methods: list) -> str:
    data = [_ea(ok, m) for m in methods]
    fig, ax = plt.subplots(figsize=(max(4.0, 1.2 * len(methods) + 2), 3.6))
    keep = [i for i, d in enumerate(data) if d.size]
    ax.boxplot([data[i] for i in keep], whis=(5, 95), showfliers=False)
    ax.set_xticks(np.arange(1, len(keep) + 1), [methods[i] for i in keep], rotation=15)
    ax.set_ylabel("E_A, %  (box: quartiles; whiskers: 5-95 %)")
    ax.grid(alpha=0.3, axis="y")
    fig.tight_layout()
    fig.savefig(folder / "ea_by_processor.png", dpi=110)
    plt.close(fig)
    return "ea_by_processor.png"


def _coverage(plt, folder: Path, ok: list, methods: list, spec: CampaignSpec) -> str | None:
    def covered(rows):
        c = [r["amp_ci95_lo_m"] <= r["truth_amp_pkpk_m"] <= r["amp_ci95_hi_m"] for r in rows
             if math.isfinite(r["amp_ci95_lo_m"]) and math.isfinite(r["amp_ci95_hi_m"])
             and math.isfinite(r["truth_amp_pkpk_m"])]
        return (sum(c) / len(c), len(c)) if c else (math.nan, 0)

    axis = spec.axes[0] if spec.axes else None
    keys = [axis_key(v) for v in axis.values] if axis else ["all"]
    fig, ax = plt.subplots(figsize=(6.4, 3.8))
    width = 0.8 / max(1, len(methods))
    any_ci = False
    for j, m in enumerate(methods):
        frac, n = zip(*(covered([r for r in ok if r["method"] == m and (axis is None or
                                  axis_key(r.get(axis.name)) == k)]) for k in keys))
        if not any(n):
            continue
        any_ci = True
        ax.bar(np.arange(len(keys)) + (j - (len(methods) - 1) / 2) * width, 100 * np.asarray(frac), width, label=m)
        lo = [100 * max(0.0, 0.95 - 1.96 * math.sqrt(0.0475 / k)) if k else math.nan for k in n]
        ax.plot(np.arange(len(keys)) + (j - (len(methods) - 1) / 2) * width, lo, "k_", ms=10)
    if not any_ci:
        plt.close(fig)
        return None
    ax.axhline(95, color="k", lw=0.8, ls="--")
    ax.set_xticks(np.arange(len(keys)), keys, rotation=15)
    ax.set_xlabel(axis.name if axis else "")
    ax.set_ylabel("truth inside the 95 % interval, %")
    ax.set_ylim(0, 102)
    ax.legend(fontsize=8, loc="lower left")
    ax.set_title("dashes: lower end of a calibrated interval's binomial 95 % range", fontsize=8)
    fig.tight_layout()
    fig.savefig(folder / "coverage.png", dpi=110)
    plt.close(fig)
    return "coverage.png"


def write_figures(folder, rows: list[dict], spec: CampaignSpec) -> list[tuple[str, str]]:
    """Write the report's PNG figures into ``folder``; ``(title, file name)`` of each.

    Raises :class:`~bttsim_stream._plotting.PlotExtraMissing` without matplotlib.
    """
    plt = pyplot("the campaign report's figures")
    folder = Path(folder)
    methods = [p.name for p in spec.processors]
    ok = [r for r in rows if r["status"] == "ok" and math.isfinite(r["E_A_pct"])]
    if not ok:
        return []
    out = [("E_A per processor", _by_processor(plt, folder, ok, methods))]
    out += [(f"E_A against `{a.name}`", _vs_axis(plt, folder, ok, methods, a)) for a in spec.axes]
    cov = _coverage(plt, folder, ok, methods, spec)
    if cov:
        out.append(("Coverage of the 95 % amplitude intervals", cov))
    return out

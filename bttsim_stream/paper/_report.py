"""Output helpers shared by the paper's studies and benchmark: Markdown tables, files, figures."""

from __future__ import annotations

import json
from pathlib import Path

from .._plotting import pyplot as _pyplot

__all__ = ["md_table", "out_dir_mk", "pyplot", "savefig", "write_study"]


def md_table(headers, rows) -> str:
    """A Markdown table: one header row, then one row per item of ``rows`` (cells via ``str``)."""
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


def out_dir_mk(out_dir) -> Path:
    """``out_dir`` as a :class:`~pathlib.Path`, created with its parents."""
    p = Path(out_dir)
    p.mkdir(parents=True, exist_ok=True)
    return p


def write_study(out_dir, name: str, text: str, data: dict) -> None:
    """Write ``<out_dir>/<name>.md`` (``text``) and ``<out_dir>/<name>.json`` (``data``)."""
    out_dir = out_dir_mk(out_dir)
    (out_dir / f"{name}.md").write_text(text.rstrip() + "\n")
    (out_dir / f"{name}.json").write_text(json.dumps(data, indent=1, default=float) + "\n")


def pyplot():
    """``matplotlib.pyplot`` (Agg); :class:`~bttsim_stream._plotting.PlotExtraMissing` without it."""
    return _pyplot("drawing the study figures")


def savefig(fig, path: Path) -> str:
    """Save ``fig`` as a PNG at ``path``, close it, and return the file name."""
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    pyplot().close(fig)
    return path.name

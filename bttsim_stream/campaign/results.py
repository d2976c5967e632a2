"""The campaign's results table: rows to Parquet and back (pyarrow, the ``campaign`` extra).

Columns: :data:`~bttsim_stream.campaign.run.ROW_COLUMNS` then one column per axis, named by
the axis's dotted scenario field. Each finished run is written at once to
``DIR/runs/RUN_ID.parquet`` (the part files that ``--resume`` reads and a crash keeps);
``DIR/results.parquet`` joins the parts of the spec's runs in expansion order.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

from ..errors import BttsimError
from .run import ROW_COLUMNS
from .spec import CampaignSpec

__all__ = ["pyarrow_modules", "schema", "write_rows", "read_rows", "read_part", "sort_rows", "PARTS"]

#: The folder of per-run part files under the output folder.
PARTS = "runs"

_INT = ("index", "replicate", "seed", "crossing", "eo", "nd", "blade")
_STR = ("run_id", "worker", "method", "status", "error")


def pyarrow_modules():
    """``(pyarrow, pyarrow.parquet)``, or a one-line error naming the extra."""
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        raise BttsimError("bttsim campaign needs pyarrow: pip install 'bttsim-stream[campaign]'") from None
    return pa, pq


def _axis_type(pa, values):
    if all(isinstance(v, bool) for v in values):
        return pa.bool_()
    if all(isinstance(v, int) and not isinstance(v, bool) for v in values):
        return pa.int64()
    if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
        return pa.float64()
    return pa.string()


def schema(spec: CampaignSpec):
    """The pyarrow schema of the spec's results."""
    pa, _ = pyarrow_modules()
    fields = []
    for c in ROW_COLUMNS:
        t = pa.int64() if c in _INT else pa.string() if c in _STR else pa.float64()
        fields.append(pa.field(c, t))
    for a in spec.axes:
        fields.append(pa.field(a.name, _axis_type(pa, a.values)))
    return pa.schema(fields)


def _cell(v, t, pa):
    if t == pa.string() and v is not None and not isinstance(v, str):
        return str(v)
    if t == pa.float64() and v is not None:
        return float(v)
    return v


def write_rows(path, rows: list[dict], spec: CampaignSpec) -> None:
    """Write ``rows`` as Parquet at ``path``, atomically (a temporary file renamed); a path
    that cannot be written is a one-line :class:`BttsimError` naming it (no temporary left)."""
    pa, pq = pyarrow_modules()
    sch = schema(spec)
    cols = {f.name: pa.array([_cell(r.get(f.name), f.type, pa) for r in rows], type=f.type) for f in sch}
    path = Path(path)
    tmp = path.with_name(path.name + f".tmp{os.getpid()}")
    try:
        pq.write_table(pa.table(cols, schema=sch), tmp)
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise BttsimError(f"{path}: cannot write ({exc.strerror or exc})") from None


def read_rows(path) -> list[dict]:
    """The rows of a results (or part) file as dicts."""
    _, pq = pyarrow_modules()
    return pq.read_table(path).to_pylist()


def read_part(path, spec: CampaignSpec, run_id: str) -> list[dict]:
    """The rows of a run's part file, checked: a readable Parquet file of the spec's columns
    and types holding rows of ``run_id`` only. ValueError saying why otherwise (a damaged,
    truncated or foreign file: ``--resume`` runs the run again)."""
    pa, pq = pyarrow_modules()
    try:
        table = pq.read_table(path)
    except (pa.ArrowException, OSError) as exc:
        raise ValueError(f"unreadable ({' '.join(str(exc).split())[:200]})") from None
    if not table.schema.equals(schema(spec)):
        raise ValueError("not the columns of this campaign's results")
    ids = set(table.column("run_id").to_pylist())
    if ids != {run_id}:
        raise ValueError(f"rows of run(s) {', '.join(sorted(map(str, ids))) or 'none'}, not of run {run_id}")
    return table.to_pylist()


def sort_rows(rows: list[dict], spec: CampaignSpec) -> list[dict]:
    """Expansion order, then processor order (the spec's), crossing, blade."""
    order = {p.name: i for i, p in enumerate(spec.processors)}
    return sorted(rows, key=lambda r: (r["index"], order.get(r["method"], math.inf), r["crossing"], r["blade"]))

"""Time and signal files read in blocks: the text or columns are never held whole.

* :func:`read_times` / :func:`checked_blocks`: times in s from a CSV (first column, or a
  named one; a header line and ``#`` comments allowed) or a Parquet file (its magic bytes),
  each block checked (finite, in order) as it is read;
* :func:`signal_blocks`: a probe's voltages from a ``.npy`` array (memory-mapped,
  ``allow_pickle=False``) or a one-column CSV (NaN: not recorded).

Every problem is a one-line :class:`~bttsim_stream.errors.BttsimError` naming the file and
the line (or row).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .errors import BttsimError

__all__ = ["read_times", "read_columns", "checked_blocks", "signal_blocks"]

_BLOCK_BYTES = 4 << 20
_MAX_LINE = 64 << 10
_SIGNAL_BLOCK = 1 << 20
_PARQUET_ROWS = 1 << 20


def _is_parquet(path: Path) -> bool:
    with open(path, "rb") as fh:
        return fh.read(4) == b"PAR1"


def _split(line: str, delim: str | None) -> list[str]:
    return line.split(delim) if delim else line.split()


def _plural(kind: str) -> str:
    return "times" if kind == "a time in s" else "numbers"


def _blocks_csv(path: Path, column: str | None, kind: str = "a time in s"):
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
                                          f"not a CSV of {_plural(kind)}")
                    carry = text
                    continue
                lines, carry = text[:cut].splitlines(), text[cut + 1:]
            if len(carry) > _MAX_LINE:
                raise BttsimError(f"{path}: a line is longer than {_MAX_LINE // 1024} KiB: "
                                  f"not a CSV of {_plural(kind)}")
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
                        raise BttsimError(f"{path}: line {where}: not {kind}: {ln.strip()[:40]!r}") from None
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
        pf = pq.ParquetFile(path, pre_buffer=False, buffer_size=1 << 20)  # pre-buffered: memory grows
        names = pf.schema_arrow.names
        if not names:
            raise BttsimError(f"{path}: the Parquet file has no column")
        name = names[0] if column is None else column
        if name not in names:
            raise BttsimError(f"{path}: no column {column!r} (the file has {', '.join(names)})")
        row = 1
        for batch in pf.iter_batches(batch_size=_PARQUET_ROWS, columns=[name]):
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
    out = list(checked_blocks(path, column, what, strict))
    if not out:
        raise BttsimError(f"{Path(path)}: no times in the file ({what})")
    return np.concatenate(out)


def checked_blocks(path, column: str | None, what: str, strict: bool):
    """The blocks of :func:`read_times`, each checked (finite, in order) as it is read."""
    p = Path(path)
    if not p.is_file():
        raise BttsimError(f"{p}: no such file ({what})")
    blocks = _blocks_parquet(p, column) if _is_parquet(p) else _blocks_csv(p, column)
    prev = -math.inf
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
            yield arr


def signal_blocks(p: Path):
    """Volts of a signal file in blocks: ``.npy`` (memory-mapped, ``allow_pickle=False``) or
    a one-column CSV (NaN: not recorded)."""
    if p.suffix.lower() == ".npy":
        try:
            arr = np.load(p, mmap_mode="r", allow_pickle=False)
        except (ValueError, OSError, EOFError) as exc:
            raise BttsimError(f"{p}: not a readable .npy array ({str(exc)[:120]})") from None
        if arr.ndim == 2 and 1 in arr.shape:
            arr = arr.reshape(-1)
        if arr.ndim != 1 or arr.dtype.kind not in "fiu":
            raise BttsimError(f"{p}: a signal must be a 1-D array of volts, got shape {arr.shape} {arr.dtype}")
        for lo in range(0, arr.size, _SIGNAL_BLOCK):
            yield lo + 1, np.asarray(arr[lo:lo + _SIGNAL_BLOCK], dtype=float)
        return
    with open(p, "rb") as fh:  # a time column before the volts would be read as volts: refuse
        lines = [ln.strip() for ln in fh.read(_MAX_LINE).decode("utf-8", "replace").splitlines()[:-1]]
    first = next((ln for ln in lines if ln and not ln.startswith("#")), "")
    cols = next((first.split(d) for d in (",", ";", "\t") if d in first), first.split())
    if len(cols) > 1:
        raise BttsimError(f"{p}: a signal CSV holds one column, volts (this one has {len(cols)}: "
                          f"{first[:40]!r}); the time of sample i is START + i / --sample-rate")
    yield from _blocks_csv(p, None)


def read_columns(path, columns) -> dict:
    """Named columns of numbers of a CSV with a header line, read in blocks (one pass per
    column); a garbage file fails at its first block."""
    p = Path(path)
    return {c: np.concatenate([np.zeros(0)] + [a for _, a in _blocks_csv(p, c, "a number")]) for c in columns}

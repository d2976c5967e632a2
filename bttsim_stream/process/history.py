"""The per-revolution state of a live run, in memory that does not grow with the run.

* :class:`RecentRows`: rows appended along axis 0 of which the owner needs only the recent ones
  (the live displacements and speeds: the NSV block and the fit window being worked on); the
  older rows are dropped.
* :class:`SpilledRows`: rows appended along axis 0 that are all needed once more at the end
  (the live processor's TOAs and truth, for its final report): the recent rows in memory, the
  older ones in an unnamed scratch file (:func:`tempfile.TemporaryFile`: in ``TMPDIR``,
  deleted when closed or when the process ends), read back when asked for.
* :class:`ScratchRows`: a run-sized array written in order by blocks of rows, and read back
  by rows or by blocks of columns (the report's TOAs, displacements and arrival times):
  held in unnamed scratch files, row-major (and column-major once columns are read), not
  in memory.
* :class:`SparseRows`: rows indexed by any integer (a revolution number), written in any order
  and read back by ranges, rows never written reading as zeros (a whole recording's
  travelling-wave spectra, for the view drawn at its end): in unnamed scratch files.

Pure numpy and the standard library; no bus, no formats.
"""

from __future__ import annotations

import errno
import os
import tempfile
import weakref

import numpy as np

__all__ = ["RecentRows", "SpilledRows", "ScratchRows", "SparseRows", "SPILL_BYTES"]

#: Bytes of recent rows a :class:`SpilledRows` keeps in memory before it writes the older half
#: to its scratch file (twice this at most).
SPILL_BYTES = 4 << 20


class RecentRows:
    """Rows appended along axis 0, indexed by their absolute row number; the rows before
    :meth:`drop_before`'s number may be dropped (the buffer is compacted when it is full and
    at least half of it can go; else it doubles)."""

    def __init__(self, shape_tail: tuple = (), dtype=np.float64, capacity: int = 256, fill=np.nan) -> None:
        self._fill = fill
        self._a = np.full((max(int(capacity), 4),) + tuple(shape_tail), fill, dtype=dtype)
        self._start = 0  # the row number of _a[0]
        self._keep = 0  # rows before it are not needed any more
        self.n = 0

    def drop_before(self, k: int) -> None:
        """Rows before row ``k`` are not needed any more."""
        self._keep = min(max(self._keep, int(k)), self.n)

    def _room(self) -> None:
        size = self._a.shape[0]
        if self.n - self._start < size:
            return
        drop = self._keep - self._start
        if 2 * drop >= size:  # compact: the kept rows to the front
            m = self.n - self._keep
            self._a[:m] = self._a[drop:drop + m]
            self._a[m:] = self._fill
            self._start = self._keep
        else:
            self._a = np.concatenate([self._a, np.full_like(self._a, self._fill)])

    def append(self, row) -> None:
        self._room()
        self._a[self.n - self._start] = row
        self.n += 1

    def next_row(self) -> np.ndarray:
        """Append a row (the fill value) and return it, to be written in place."""
        self._room()
        self.n += 1
        return self._a[self.n - 1 - self._start]

    def row(self, k: int):
        """Row ``k`` (a view: valid until the next append)."""
        i = k - self._start
        if i < 0 or k >= self.n:
            raise IndexError(f"row {k} is not held (rows {self._start} .. {self.n - 1})")
        return self._a[i]

    def rows(self, a: int, b: int) -> np.ndarray:
        """Rows ``a .. b - 1`` (a view: valid until the next append)."""
        if a < self._start or b > self.n:
            raise IndexError(f"rows {a} .. {b - 1} are not held (rows {self._start} .. {self.n - 1})")
        return self._a[a - self._start:b - self._start]


class SpilledRows:
    """Rows appended along axis 0, all kept: the recent ones in memory (at least ``keep``
    rows, at most twice that), the older ones in a scratch file, in order.

    Rows still in memory may be changed in place (:meth:`row`); a spilled row is final.
    """

    def __init__(self, shape_tail: tuple = (), dtype=np.float64, keep: int | None = None, fill=np.nan) -> None:
        self.shape_tail = tuple(shape_tail)
        self.dtype = np.dtype(dtype)
        self._row_bytes = int(np.prod(self.shape_tail, dtype=np.int64)) * self.dtype.itemsize
        self._keep = max(4, int(keep) if keep is not None else SPILL_BYTES // max(self._row_bytes, 1))
        self._fill = fill
        self._buf = np.full((2 * self._keep,) + self.shape_tail, fill, dtype=self.dtype)
        self._start = 0  # the row number of _buf[0]: rows before it are in the file
        self._file = None
        self.n = 0

    @property
    def spilled(self) -> int:
        """Rows in the scratch file."""
        return self._start

    def _room(self) -> None:
        if self.n - self._start < self._buf.shape[0]:
            return
        k = self._keep
        if self._file is None:
            self._file = tempfile.TemporaryFile(prefix="bttsim-history-")
            self._finalizer = weakref.finalize(self, self._file.close)  # closed when dropped, too
        self._file.seek(0, 2)
        self._file.write(memoryview(self._buf[:k]).cast("B"))
        self._buf[:k] = self._buf[k:2 * k]
        self._buf[k:] = self._fill
        self._start += k

    def append(self, row) -> None:
        self._room()
        self._buf[self.n - self._start] = row
        self.n += 1

    def row(self, k: int) -> np.ndarray:
        """Row ``k``, still in memory (a view: changes write through; valid until the next
        append)."""
        i = k - self._start
        if i < 0 or k >= self.n:
            raise IndexError(f"row {k} is not in memory (rows {self._start} .. {self.n - 1})")
        return self._buf[i]

    def rows(self, a: int, b: int) -> np.ndarray:
        """A copy of rows ``a .. b - 1``, from the file and from memory."""
        a, b = max(int(a), 0), min(int(b), self.n)
        out = np.empty((max(b - a, 0),) + self.shape_tail, self.dtype)
        m = min(b, self._start) - a  # rows from the file
        if m > 0:
            self._file.seek(a * self._row_bytes)
            view = memoryview(out[:m]).cast("B")
            got = self._file.readinto(view)
            if got != view.nbytes:
                raise OSError(errno.EIO, f"the scratch file of the run's history is short "
                                         f"({got} of {view.nbytes} bytes)")
        m = max(m, 0)
        out[m:] = self._buf[a + m - self._start:b - self._start]
        return out

    def array(self) -> np.ndarray:
        """Every row, in one array."""
        return self.rows(0, self.n)

    def scratch(self, block: int = 4096) -> "ScratchRows":
        """Every row, in a :class:`ScratchRows` (copied ``block`` rows at a time: never all
        in memory)."""
        out = ScratchRows(self.shape_tail, self.dtype)
        for a in range(0, self.n, max(int(block), 1)):
            out.write(self.rows(a, a + block))
        return out

    def close(self) -> None:
        """Delete the scratch file (the rows spilled to it are gone)."""
        if self._file is not None:
            self._file.close()
            self._file = None


class ScratchRows:
    """A run-sized array of rows of shape ``tail`` appended in order by blocks (:meth:`write`;
    a row already written may be replaced, :meth:`patch`) and read back: ``rows[a:b]`` (or an
    integer array of rows) and :meth:`columns` (every row of some columns of the array seen
    as ``(n_rows, n_cols)``) are copies of the values written, the same numbers. Held in an
    unnamed scratch file (``TMPDIR``; deleted when closed or when the process ends), row by
    row; a second one, column by column, is made the first time columns are read, so that
    both reads are contiguous. ``shape`` is that of the rows written so far.
    """

    def __init__(self, tail: tuple = (), dtype=np.float64) -> None:
        self.tail = tuple(int(n) for n in tail)
        self.dtype = np.dtype(dtype)
        self.ndim = 1 + len(self.tail)
        self._n_cols = int(np.prod(self.tail, dtype=np.int64))
        self._rows = tempfile.TemporaryFile(prefix="bttsim-rows-")
        self._cols = None  # the column-major copy, of the first _cols_n rows
        self._cols_n = 0
        self.written = 0
        self._files = [self._rows]
        self._finalizer = weakref.finalize(self, _close_all, self._files)  # closed when dropped, too

    @property
    def shape(self) -> tuple:
        return (self.written,) + self.tail

    @classmethod
    def of(cls, array: np.ndarray, block: int = 4096) -> "ScratchRows":
        """A copy of ``array`` in a scratch file, written ``block`` rows at a time."""
        a = np.asarray(array)
        out = cls(a.shape[1:], a.dtype)
        for lo in range(0, a.shape[0], max(int(block), 1)):
            out.write(a[lo:lo + block])
        return out

    def write(self, block) -> None:
        """Append rows ``written .. written + len(block) - 1``."""
        block = np.ascontiguousarray(block, dtype=self.dtype)
        block = block.reshape(block.shape[0] if block.ndim > len(self.tail) else 1, self._n_cols)
        if block.size:
            _write_all(self._rows, block, self.written * self._n_cols * self.dtype.itemsize)
        self.written += block.shape[0]

    def patch(self, i: int, row) -> None:
        """Replace row ``i`` (written already)."""
        if not 0 <= i < self.written:
            raise IndexError(f"row {i} is not written (rows 0 .. {self.written - 1})")
        row = np.ascontiguousarray(row, dtype=self.dtype).reshape(self._n_cols)
        _write_all(self._rows, row, i * self._n_cols * self.dtype.itemsize)
        self._cols_n = 0  # the column-major copy is made again when read

    def _read(self, f, offset: int, out: np.ndarray) -> None:
        """``out`` from element ``offset`` of file ``f`` (in as many reads as it takes)."""
        view = memoryview(out).cast("B") if out.size else memoryview(b"")
        at, pos = 0, offset * self.dtype.itemsize
        while at < view.nbytes:
            got = os.preadv(f.fileno(), [view[at:]], pos + at)
            if got <= 0:
                raise OSError(errno.EIO, f"a scratch file of the run's arrays is short ({at} of {view.nbytes} bytes)")
            at += got

    def __getitem__(self, rows) -> np.ndarray:
        """Rows ``rows`` (a slice, an int or an integer array; or a tuple whose first item is
        one of these, the rest indexing each row, e.g. ``[a:b, blades]``), a copy."""
        if isinstance(rows, tuple):
            if any(k is Ellipsis or k is None for k in rows) or sum(np.ndim(k) > 0 for k in rows) > 1:
                raise IndexError("ScratchRows takes [rows] or [rows, basic indices of each row]")
            head = self[rows[0]]
            one = not isinstance(rows[0], slice) and np.ndim(rows[0]) == 0
            return head[rows[1:]] if one else head[(slice(None),) + rows[1:]]
        n = self.written
        if isinstance(rows, slice) and rows.step in (None, 1):
            a, b, _ = rows.indices(n)
            out = np.empty((max(b - a, 0), self._n_cols), self.dtype)
            self._read(self._rows, a * self._n_cols, out)
            return out.reshape((out.shape[0],) + self.tail)
        idx = _row_numbers(rows, n)
        flat = np.atleast_1d(idx)
        out = np.empty((flat.size, self._n_cols), self.dtype)
        cuts = np.flatnonzero(np.diff(flat) != 1) + 1  # runs of consecutive rows, one read each
        for s, e in zip(np.r_[0, cuts], np.r_[cuts, flat.size]):
            if e > s:
                self._read(self._rows, int(flat[s]) * self._n_cols, out[s:e])
        out = out.reshape(flat.shape + self.tail)
        return out[0] if idx.ndim == 0 else out.reshape(idx.shape + self.tail)

    def __array__(self, dtype=None, copy=None):
        raise TypeError("a ScratchRows is read by rows (x[a:b], x[rows, ...]): not made into the whole array "
                        "implicitly")

    def _transpose(self, block: int = 4096) -> None:
        """The column-major copy of every row written, from the row-major file by blocks."""
        if self._cols is None:
            self._cols = tempfile.TemporaryFile(prefix="bttsim-cols-")
            self._files.append(self._cols)
        n, size = self.written, self.dtype.itemsize
        for a in range(0, n, block):
            cols = np.ascontiguousarray(self[a:a + block].reshape(-1, self._n_cols).T)
            for j in range(self._n_cols):  # each column's segment of these rows
                _write_all(self._cols, cols[j], (j * n + a) * size)
        self._cols_n = n

    def columns(self, cols: slice) -> np.ndarray:
        """Columns ``cols`` (a slice of the ``n_cols`` columns) of every row written, shape
        ``(n_rows, n)``, row-major (as a block of columns of the array is laid out: numpy
        and BLAS give the same numbers on it)."""
        a, b, step = cols.indices(self._n_cols)
        if step != 1:
            raise IndexError("ScratchRows.columns takes a slice of consecutive columns")
        if self._cols_n != self.written:
            self._transpose()
        out = np.empty((max(b - a, 0), self.written), self.dtype)
        self._read(self._cols, a * self.written, out)
        return np.ascontiguousarray(out.T)

    def close(self) -> None:
        """Delete the scratch files (also done when the object is dropped)."""
        self._finalizer()


class SparseRows:
    """Rows of shape ``tail`` indexed by any integer, written in any order (:meth:`write`: a
    row written again is replaced) and read back by ranges of indices (:meth:`read`: a copy,
    the values written; a row never written reads as zeros). Held in unnamed scratch files
    (``TMPDIR``; deleted when closed or when dropped), not in memory: the rows from the first
    index written upwards in one file, those below it (in reverse) in another; the gaps
    between rows written are the files' holes (on a file system without sparse files, zeros
    on disk).
    """

    def __init__(self, tail: tuple = (), dtype=np.float64) -> None:
        self.tail = tuple(int(n) for n in tail)
        self.dtype = np.dtype(dtype)
        self._n_cols = int(np.prod(self.tail, dtype=np.int64))
        self._origin: int | None = None  # the index of the first row of the upward file
        self._files: list = []
        self._up = self._down = None
        self._finalizer = weakref.finalize(self, _close_all, self._files)

    def _file(self, up: bool):
        f = self._up if up else self._down
        if f is None:
            f = tempfile.TemporaryFile(prefix="bttsim-sparse-")
            self._files.append(f)
            if up:
                self._up = f
            else:
                self._down = f
        return f

    def write(self, index, rows) -> None:
        """Rows ``rows`` (shape ``(k,) + tail``) at indices ``index`` (k,); of an index given
        twice, the later row holds."""
        idx = np.asarray(index, np.int64).reshape(-1)
        rows = np.ascontiguousarray(rows, dtype=self.dtype).reshape(idx.size, self._n_cols)
        if idx.size == 0:
            return
        last = idx.size - 1 - np.unique(idx[::-1], return_index=True)[1]  # sorted, the later of each
        idx, rows = idx[last], rows[last]
        if self._origin is None:
            self._origin = int(idx[0])
        below = int(np.searchsorted(idx, self._origin))
        # upwards: position index - origin; downwards: origin - 1 - index (reversed, ascending)
        for up, pos, block in ((True, idx[below:] - self._origin, rows[below:]),
                               (False, self._origin - 1 - idx[:below][::-1], rows[:below][::-1])):
            if pos.size == 0:
                continue
            f = self._file(up)
            cuts = np.flatnonzero(np.diff(pos) != 1) + 1
            for a, b in zip(np.r_[0, cuts], np.r_[cuts, pos.size]):  # one write per run of positions
                _write_all(f, block[a:b], int(pos[a]) * self._n_cols * self.dtype.itemsize)

    def read(self, a: int, b: int) -> np.ndarray:
        """Rows of indices ``a .. b - 1``, shape ``(b - a,) + tail`` (zeros where none)."""
        a, b = int(a), max(int(b), int(a))
        out = np.zeros((b - a, self._n_cols), self.dtype)
        o = self._origin
        if o is not None and b > o and self._up is not None:
            lo = max(a, o)
            self._read(self._up, lo - o, out[lo - a:])
        if o is not None and a < o and self._down is not None:
            hi = min(b, o)
            part = np.zeros((hi - a, self._n_cols), self.dtype)
            self._read(self._down, o - hi, part)  # positions o - hi .. o - 1 - a: indices hi - 1 .. a
            out[:hi - a] = part[::-1]
        return out.reshape((b - a,) + self.tail)

    def _read(self, f, position: int, out: np.ndarray) -> None:
        """``out`` from row ``position`` of file ``f``; what lies beyond its end stays zero."""
        view = memoryview(out).cast("B") if out.size else memoryview(b"")
        at, pos = 0, position * self._n_cols * self.dtype.itemsize
        while at < view.nbytes:
            got = os.preadv(f.fileno(), [view[at:]], pos + at)
            if got <= 0:
                break
            at += got

    def close(self) -> None:
        """Delete the scratch files (also done when the object is dropped)."""
        self._finalizer()


def _row_numbers(rows, n: int) -> np.ndarray:
    """The row numbers ``rows`` (a slice, an int, a 1-D integer or boolean array) picks among
    ``n``, as ``np.arange(n)[rows]`` without making that array; IndexError as numpy's."""
    if isinstance(rows, slice):
        return np.arange(*rows.indices(n))
    idx = np.asarray(rows)
    if idx.dtype == bool:
        if idx.shape != (n,):
            raise IndexError(f"a boolean index of {idx.shape} for {n} rows")
        return np.flatnonzero(idx)
    if idx.dtype.kind not in "iu" or idx.ndim > 1:
        raise IndexError(f"ScratchRows takes a slice, an int or a 1-D integer array of rows, got {rows!r:.60}")
    idx = np.where(idx < 0, idx + n, idx).astype(np.intp)
    if np.any((idx < 0) | (idx >= n)):
        raise IndexError(f"row index out of range for {n} rows")
    return idx


def _write_all(f, a: np.ndarray, offset: int) -> None:
    """All of ``a``'s bytes into file ``f`` at byte ``offset`` (in as many writes as it takes)."""
    view, at = memoryview(np.ascontiguousarray(a)).cast("B"), 0
    while at < view.nbytes:
        at += os.pwrite(f.fileno(), view[at:], offset + at)


def _close_all(files: list) -> None:
    for f in files:
        f.close()

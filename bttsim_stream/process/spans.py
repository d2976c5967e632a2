"""Per-revolution arrays held only on some spans of revolutions (:class:`SpanRows`).

The report of a run reads its per-revolution fits only in and around the crossings and the
dwells (``docs/processing.md``); a long run holds most of its revolutions elsewhere. A
:class:`SpanRows` stands for a whole run's array, shape ``(n_rev, ...)``, of which only the
held revolutions are stored: indexing it by revolution gives the numbers the whole array
would hold there, and the fill value (NaN) for every revolution not held. The row index is
the run's own (absolute) revolution, never a span's offset.
"""

from __future__ import annotations

import numpy as np

__all__ = ["SpanRows", "as_rows", "angle"]


class SpanRows:
    """A run's array of shape ``(n_rev, ...)`` held on some revolutions only.

    Parameters
    ----------
    data : ndarray, shape (n_held + 1, ...)
        The held revolutions' rows, in revolution order, and a last row of the fill value.
    pos : ndarray of int, shape (n_rev,)
        Each revolution's row of ``data`` (``n_held``, the fill row, where not held).

    Notes
    -----
    ``x[rows, ...]`` (an int, a slice or an integer or boolean array of revolutions, with any
    further index) is ``whole[rows, ...]`` of the whole array with the fill value in every
    revolution not held. ``x[:, ...]`` and ``x[..., k]`` (every revolution, basic indices
    after it) stay a :class:`SpanRows` (a view of ``data``). Element-wise numpy ufuncs and
    arithmetic with scalars and per-blade arrays act on the held rows (a :class:`SpanRows`
    again). Writing ``x[rows] = v`` needs every revolution of ``rows`` held. Anything that
    would make the whole run's array (``np.asarray(x)``) is refused: index the revolutions
    wanted first (:func:`as_rows`).
    """

    __slots__ = ("data", "pos")

    def __init__(self, data: np.ndarray, pos: np.ndarray) -> None:
        self.data = data
        self.pos = pos

    @classmethod
    def filled(cls, n_rev: int, spans, tail: tuple, dtype=float, fill=np.nan) -> "SpanRows":
        """Held on ``spans`` (sorted, non-overlapping ``[start, stop)``), uninitialised there,
        ``fill`` elsewhere."""
        pos = np.empty(n_rev, np.intp)
        at = 0
        starts = []
        for a, b in spans:
            starts.append(at)
            at += b - a
        pos.fill(at)
        for (a, b), s in zip(spans, starts):
            pos[a:b] = np.arange(s, s + b - a)
        data = np.empty((at + 1,) + tuple(tail), dtype)
        data[at] = fill
        return cls(data, pos)

    def like(self, tail: tuple, dtype=float, fill=np.nan) -> "SpanRows":
        """Another array held on the same revolutions, uninitialised there, ``fill`` elsewhere."""
        data = np.empty((self.data.shape[0],) + tuple(tail), dtype)
        data[-1] = fill
        return SpanRows(data, self.pos)

    @property
    def shape(self) -> tuple:
        return (self.pos.size,) + self.data.shape[1:]

    @property
    def ndim(self) -> int:
        return self.data.ndim

    @property
    def dtype(self):
        return self.data.dtype

    def held(self) -> np.ndarray:
        """Which revolutions are held, shape (n_rev,) of bool."""
        return self.pos < self.data.shape[0] - 1

    def copy(self) -> "SpanRows":
        return SpanRows(self.data.copy(), self.pos)

    def _key(self, key) -> tuple:
        key = key if isinstance(key, tuple) else (key,)
        if any(k is Ellipsis for k in key):
            i = next(j for j, k in enumerate(key) if k is Ellipsis)
            key = key[:i] + (slice(None),) * (self.ndim - len(key) + 1) + key[i + 1:]
        return key

    def __getitem__(self, key):
        key = self._key(key)
        rows, rest = key[0], key[1:]
        basic = all(isinstance(k, (slice, int, np.integer)) for k in rest)
        if isinstance(rows, slice) and rows == slice(None) and basic:
            return SpanRows(self.data[(slice(None),) + rest], self.pos)
        if isinstance(rows, (slice, int, np.integer)):  # whole[rows][rest] is whole[rows, rest]
            got = self.data[self.pos[rows]]
            return got[(slice(None),) * isinstance(rows, slice) + rest] if rest else got
        return self.data[(self.pos[np.asarray(rows)],) + rest]

    def __setitem__(self, key, value) -> None:
        key = self._key(key)
        if len(key) != 1 or not isinstance(key[0], (slice, int, np.integer, np.ndarray)):
            raise TypeError("SpanRows: write whole rows, x[rows] = v")
        r = self.pos[key[0]]
        if np.any(r == self.data.shape[0] - 1):
            raise IndexError("SpanRows: a revolution written to is not held")
        self.data[r] = value

    def __array__(self, dtype=None, copy=None):
        raise TypeError("a SpanRows holds some revolutions only: index the revolutions wanted "
                        "(x[lo:hi], x[rows, cols]) instead of making the whole run's array")

    def __array_ufunc__(self, ufunc, method, *inputs, **kwargs):
        if method != "__call__" or kwargs.get("out") is not None:
            return NotImplemented
        args = []
        for x in inputs:
            if isinstance(x, SpanRows):
                if x.pos is not self.pos and not np.array_equal(x.pos, self.pos):
                    return NotImplemented
                args.append(x.data)
            elif np.ndim(x) == 0 or np.shape(x)[0] == 1 or np.ndim(x) < self.ndim:
                args.append(x)  # a scalar, or broadcast over the revolutions
            else:
                return NotImplemented
        out = getattr(ufunc, method)(*args, **kwargs)
        return tuple(SpanRows(o, self.pos) for o in out) if isinstance(out, tuple) else SpanRows(out, self.pos)

    def __add__(self, other):
        return np.add(self, other)

    def __radd__(self, other):
        return np.add(other, self)

    def __sub__(self, other):
        return np.subtract(self, other)

    def __rsub__(self, other):
        return np.subtract(other, self)

    def __mul__(self, other):
        return np.multiply(self, other)

    def __rmul__(self, other):
        return np.multiply(other, self)

    def __truediv__(self, other):
        return np.true_divide(self, other)

    def __neg__(self):
        return np.negative(self)

    def __abs__(self):
        return np.absolute(self)


def as_rows(x, dtype=float):
    """``x`` itself when it is a :class:`SpanRows` (indexed by revolution later), else
    ``np.asarray(x, dtype)``."""
    return x if isinstance(x, SpanRows) else np.asarray(x, dtype=dtype)


def angle(x):
    """``np.angle`` of an array or of a :class:`SpanRows` (of its held rows)."""
    return SpanRows(np.angle(x.data), x.pos) if isinstance(x, SpanRows) else np.angle(x)

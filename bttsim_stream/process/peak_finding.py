"""Interior peaks of a curve and their prominences, in numpy alone.

:func:`interior_peaks` gives, bit for bit, what ``scipy.signal.find_peaks(x, prominence=0.0)``
gives for ``peaks``, ``prominences``, ``left_bases`` and ``right_bases`` (its tests compare the
two); scipy.signal takes 0.7 s to import, which every command and node that processes a run
would pay. The definitions are scipy's (``_local_maxima_1d`` and ``_peak_prominences`` with
no window):

* a **peak** is a run of equal samples ``x[l..r]`` with a smaller sample on either side,
  ``x[l-1] < x[l]`` and ``x[r+1] < x[r]``; its index is the run's middle, ``(l + r) // 2``
  (rounded down). The first and last samples are never peaks, nor is a run that reaches
  either end;
* from a peak of height ``v`` the curve is walked left, and right, while ``x[i] <= v`` (equal
  samples, other peaks of the same height too, do not stop it). A side's **base** is the
  lowest sample of its walk -- of several equally low, the one nearest the peak -- and the
  **prominence** is ``v - max(x[left_base], x[right_base])``.

NaN compares false with everything: it is never a peak nor part of a run, a sample next to
it is not a peak, and a walk stops at it as at higher ground. ``inf`` is an ordinary value.

The walks' ends are found by binary lifting on a sparse table of block maxima (``log2 n``
arrays of up to ``n`` samples); the bases by one ``minimum.reduceat`` per side over each walk,
as much work as scipy's own walks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Peaks", "interior_peaks"]


@dataclass(frozen=True, slots=True, eq=False)
class Peaks:
    """The interior peaks of a curve, in index order; every array has shape ``(n_peaks,)``.

    Attributes
    ----------
    index : ndarray of intp
        Sample index of each peak (the middle of a flat top, rounded down).
    prominence : ndarray of float64
        Height above the higher of the two bases, in the curve's unit.
    left_base, right_base : ndarray of intp
        Index of the lowest sample of the walk on each side.
    """

    index: np.ndarray
    prominence: np.ndarray
    left_base: np.ndarray
    right_base: np.ndarray


def interior_peaks(x: np.ndarray) -> Peaks:
    """Every interior peak of ``x`` with its prominence and bases (module docstring).

    Parameters
    ----------
    x : array_like, shape (n,)
        The curve; converted to float64.

    Returns
    -------
    Peaks
        Equal to ``scipy.signal.find_peaks(x, prominence=0.0)``'s ``peaks``, ``prominences``,
        ``left_bases`` and ``right_bases``.
    """
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 1:
        raise ValueError(f"x must be one-dimensional, got shape {x.shape}")
    index = _local_maxima(x)
    if index.size == 0:
        none = np.empty(0, dtype=np.intp)
        return Peaks(index=none, prominence=np.empty(0), left_base=none.copy(), right_base=none.copy())
    lo, hi = _walk_ends(x, index)
    left_base, right_base = _bases(x, index, lo, hi)
    prominence = x[index] - np.maximum(x[left_base], x[right_base])
    return Peaks(index=index, prominence=prominence, left_base=left_base, right_base=right_base)


def _local_maxima(x: np.ndarray) -> np.ndarray:
    """The middle of every run of equal samples that is higher than both its neighbours."""
    n = x.size
    if n < 3:
        return np.empty(0, dtype=np.intp)
    first = np.flatnonzero(np.concatenate(([True], x[1:] != x[:-1])))  # NaN != NaN: a run of its own
    last = np.append(first[1:], n) - 1
    inner = (first >= 1) & (last <= n - 2)
    first, last = first[inner], last[inner]
    top = (x[first - 1] < x[first]) & (x[last + 1] < x[last])
    return (first[top] + last[top]) // 2


def _walk_ends(x: np.ndarray, peaks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First and last index of each peak's walks: the longest ``x[lo..p]`` and ``x[p..hi]``
    with every sample ``<= x[p]``."""
    n = x.size
    v = x[peaks]
    # table[k][i] = max(x[i : i + 2**k]); np.maximum passes NaN on, so a block holding a NaN
    # fails ``<= v`` and stops the walk
    table = [x]
    while 2 ** len(table) <= n:
        h = 2 ** (len(table) - 1)
        table.append(np.maximum(table[-1][:-h], table[-1][h:]))
    lo, hi = peaks.copy(), peaks.copy()
    for k in range(len(table) - 1, -1, -1):  # the longest walk, one power of two at a time
        t, step = table[k], 2 ** k
        start = lo - step  # the block x[lo - step : lo]
        ok = (start >= 0) & (t[np.maximum(start, 0)] <= v)
        lo = np.where(ok, start, lo)
        start = hi + 1  # the block x[hi + 1 : hi + 1 + step]
        ok = (start + step <= n) & (t[np.minimum(start, t.size - 1)] <= v)
        hi = np.where(ok, hi + step, hi)
    return lo, hi


def _bases(x: np.ndarray, peaks: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The lowest sample of each walk, of equally low ones the nearest to the peak."""
    n = x.size
    # one integer key a side: the sample's rank among the distinct values (0.0 and -0.0 are
    # one value, as they are to scipy's ``<``), then its distance from the peak's side
    rank = np.unique(x, return_inverse=True)[1].reshape(n).astype(np.int64)
    i = np.arange(n, dtype=np.int64)
    left = np.minimum.reduceat(rank * n + (n - 1 - i), np.column_stack((lo, peaks + 1)).ravel())[::2]
    # one more sample: a right walk may end at the last index, and reduceat needs its end < size
    right = np.minimum.reduceat(np.append(rank * n + i, 0), np.column_stack((peaks, hi + 1)).ravel())[::2]
    return (n - 1 - left % n).astype(np.intp), (right % n).astype(np.intp)

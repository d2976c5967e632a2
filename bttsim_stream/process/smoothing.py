"""Noise reduction of BTT displacements along revolutions (paper Sec. 2.3, step 3 of
:mod:`.prep`): a local quadratic regression (LOESS, tricube kernel) per blade and probe,
with a half-width per revolution and Eq. 15 weights.

The kernel (:class:`Smoother`) is computed per block of revolutions, never for the whole
run; :func:`smooth_revolutions` smooths an array, :class:`PreparedRows` the revolutions
asked for (the same numbers, bit for bit, as the whole array's rows), and
:func:`smoothing_gain` is the noise gain of the smoothing at some revolutions.
Pure numpy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["smooth_revolutions", "smoothing_gain", "smoother", "smooth", "Smoother", "PreparedRows", "SMOOTH_ALIGN",
           "SMOOTH_BLOCK"]

#: Samples (revolutions x columns, and the kernels' ``2 H + 1`` offsets) of the blocks of
#: revolutions the smoother works on, at most, rounded down to :data:`SMOOTH_ALIGN`
#: revolutions: the temporaries are bounded by the block (a few dozen arrays of it).
SMOOTH_BLOCK = 1 << 19


def _local_quadratic_weights(K: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Equivalent kernel of a local quadratic fit evaluated at its centre.

    ``K`` (m, L) holds the sample weights (kernel x noise weights x validity) at offsets
    ``j`` (L,); returns ``L`` (m, L) with ``estimate = sum_j L x_j``; rows whose 3x3 moment
    matrix is singular get NaN.
    """
    M = np.stack([K @ j ** k for k in range(5)], axis=-1)  # (m, 5)
    A = np.stack([M[:, 0:3], M[:, 1:4], M[:, 2:5]], axis=-2)  # (m, 3, 3)
    det = np.linalg.det(A)
    scale = np.maximum(np.abs(A).max(axis=(1, 2)) ** 3, 1e-300)
    good = np.abs(det) > 1e-12 * scale
    A[~good] = np.eye(3)
    c = np.linalg.solve(A, np.broadcast_to(np.array([1.0, 0.0, 0.0]), (A.shape[0], 3))[..., None])[..., 0]
    L = K * (c[:, 0:1] + c[:, 1:2] * j + c[:, 2:3] * j * j)
    L[~good] = np.nan
    return L


def smooth_revolutions(d_m: np.ndarray, half_width: np.ndarray | float,
                       weights: np.ndarray | None = None) -> np.ndarray:
    """Local quadratic regression (tricube kernel) along the revolution axis.

    Parameters
    ----------
    d_m : ndarray, shape (n_rev, ...)
        Data; NaN samples are skipped and stay NaN in the output.
    half_width : float or ndarray, shape (n_rev,)
        Kernel half-width per revolution (revolutions, >= 1): the kernel is
        ``(1 - |j / (h + 1)|^3)^3`` for ``|j| <= h``.
    weights : ndarray, shape (n_rev,), optional
        Sample weights along revolutions (e.g. inverse noise variance).

    Returns
    -------
    ndarray, same shape as ``d_m``

    Notes
    -----
    Without NaN every column shares the per-revolution equivalent kernel, applied as
    ``2 H + 1`` shifted multiply-adds; the few outputs whose window holds a NaN solve their
    own local fit. Windows are truncated at the ends of the run (the local quadratic then
    extrapolates without the bias of a symmetric average). The kernels are computed in
    blocks of revolutions (:class:`Smoother`): the memory held besides the input and the
    output does not grow with the run.
    """
    d = np.asarray(d_m, dtype=float)
    return smooth(d, smoother(d.shape[0], half_width, weights))


#: Alignment of the blocks of revolutions in which the smoother's kernels are computed: the
#: moments ``K @ j**k`` are matrix-vector products, which OpenBLAS's ``dgemv`` kernels compute
#: for groups of 4 rows (the rest of the matrix, its last ``n % 4`` rows, by another kernel
#: that sums in another order; numpy computes a one-row product as a dot product, in yet
#: another order): blocks of a multiple of this many rows, the last one ending with the run
#: and at least this long, give every row the whole product's numbers, bit for bit.
SMOOTH_ALIGN = 64


@dataclass(frozen=True, slots=True, eq=False)
class Smoother:
    """The kernel of :func:`smooth_revolutions` over ``n`` revolutions, computed on demand
    for blocks of revolutions (:meth:`rows`): each row of ``K`` depends only on that
    revolution's half-width, the weights around it and its position, each row of ``L`` only
    on that row of ``K``.

    Attributes
    ----------
    h : ndarray, shape (n,)
        Half-width per revolution.
    w_rev : ndarray, shape (n,)
        Sample weight per revolution.
    H : int
        The largest half-width, rounded up (the kernels hold ``2 H + 1`` offsets).
    j : ndarray, shape (2 H + 1,)
        The offsets ``-H .. H``.
    """

    h: np.ndarray
    w_rev: np.ndarray
    H: int
    j: np.ndarray

    @property
    def n(self) -> int:
        return self.h.shape[0]

    def blocks(self, n_col: int) -> list:
        """Blocks ``(a, b)`` of revolutions for data of ``n_col`` columns: a multiple of
        :data:`SMOOTH_ALIGN` revolutions each, the last one taking the rest (and a rest
        shorter than :data:`SMOOTH_ALIGN`), with the kernels' and the data's block at most
        about :data:`SMOOTH_BLOCK` samples."""
        n = self.n
        step = SMOOTH_BLOCK // max(n_col, 2 * self.H + 1, 1)
        step = max(SMOOTH_ALIGN, step // SMOOTH_ALIGN * SMOOTH_ALIGN)
        starts = list(range(0, n, step))
        if len(starts) > 1 and n - starts[-1] < SMOOTH_ALIGN:
            starts.pop()
        return [(a, starts[i + 1] if i + 1 < len(starts) else n) for i, a in enumerate(starts)]

    def kernel(self, a: int, b: int) -> np.ndarray:
        """Sample weights ``K`` of revolutions ``a:b``, shape ``(b - a, 2 H + 1)`` (elementwise:
        any rows give the numbers of the whole array)."""
        n, H, j = self.n, self.H, self.j
        idx = np.arange(a, b)[:, None] + np.arange(-H, H + 1)[None, :]
        inside = (idx >= 0) & (idx < n)
        u = np.abs(j)[None, :] / (self.h[a:b, None] + 1.0)
        return (np.where(u < 1.0, (1.0 - u ** 3) ** 3, 0.0)
                * np.where(inside, self.w_rev[np.clip(idx, 0, n - 1)], 0.0))

    def rows(self, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
        """``K`` and the equivalent kernel ``L`` (:func:`_local_quadratic_weights`) of
        revolutions ``a:b``, one of :meth:`blocks` (``a`` a multiple of :data:`SMOOTH_ALIGN`,
        ``b`` too or the end of the run: then ``L`` has the whole array's numbers)."""
        K = self.kernel(a, b)
        return K, _local_quadratic_weights(K, self.j)


def smoother(n: int, half_width, weights) -> Smoother:
    """The kernel of :func:`smooth_revolutions` over ``n`` revolutions (rows on demand)."""
    h = np.broadcast_to(np.asarray(half_width, dtype=float), (n,))
    if np.any(~np.isfinite(h)) or np.any(h < 1):
        raise ValueError("half_width must be finite and >= 1")
    H = int(np.ceil(h.max()))
    j = np.arange(-H, H + 1, dtype=float)
    w_rev = np.ones(n) if weights is None else np.asarray(weights, dtype=float)
    return Smoother(h=h, w_rev=w_rev, H=H, j=j)


class PreparedRows:
    """Prepared displacements computed for the revolutions asked for, not held: ``rows[a:b]``
    (a slice) is ``d_m - baseline``, smoothed, of revolutions ``a .. b - 1`` -- the same
    numbers as :func:`prepare`'s whole array (every smoother block is computed as the whole
    array's is, from the offset-removed input around it; the last block is kept for the next
    rows asked for).

    Parameters
    ----------
    d_m : ndarray, shape (n_rev, n_blades, n_probes)
        The displacements before preparation.
    baseline : :class:`~.prep.Baseline` or None
        The offsets to subtract (``baseline[a:b]``: those revolutions'; None: none).
    smoother : Smoother or None
        The smoother's kernel (None: no smoothing).
    """

    def __init__(self, d_m: np.ndarray, baseline, smoother: "Smoother | None") -> None:
        self.d_m, self.baseline, self.smoother = d_m, baseline, smoother
        n, nb, npr = d_m.shape
        self._blocks = smoother.blocks(nb * npr) if smoother is not None else []
        self._block = (0, 0, None)  # (a, b, smoothed revolutions a .. b - 1)

    @property
    def shape(self) -> tuple:
        return self.d_m.shape

    def _flat(self, a: int, b: int) -> np.ndarray:
        """Offset-removed, unsmoothed revolutions ``a .. b - 1``."""
        d = self.d_m[a:b]
        return d if self.baseline is None else d - self.baseline[a:b]

    def __getitem__(self, rows: slice) -> np.ndarray:
        if not isinstance(rows, slice):
            raise TypeError(f"PreparedRows takes a slice of revolutions, got {type(rows).__name__}")
        a, b, step = rows.indices(self.d_m.shape[0])
        if step != 1:
            raise IndexError("PreparedRows takes slices of consecutive revolutions")
        if self.smoother is None:
            return self._flat(a, b)
        out = np.empty((max(b - a, 0),) + self.d_m.shape[1:])
        n, H = self.d_m.shape[0], self.smoother.H
        for ba, bb in self._blocks:
            if bb <= a or ba >= b:
                continue
            if self._block[:2] != (ba, bb):
                lo, hi = max(0, ba - H), min(n, bb + H)
                src = self._flat(lo, hi).reshape(hi - lo, -1)
                self._block = (ba, bb, _smooth_block(src, lo, ba, bb, n, self.smoother).reshape(
                    (bb - ba,) + self.d_m.shape[1:]))
            lo, hi = max(a, ba), min(b, bb)
            out[lo - a:hi - a] = self._block[2][lo - ba:hi - ba]
        return out


def smooth(d: np.ndarray, sm: Smoother, in_place: bool = False) -> np.ndarray:
    """:func:`smooth_revolutions` of ``d`` with the kernel ``sm``, by blocks of revolutions
    (:meth:`Smoother.blocks`): a block's outputs read the input's revolutions ``a - H ..
    b + H - 1``, so besides the input and the output only block-sized arrays are held.
    ``in_place``: the output is written into ``d`` when it is contiguous (the ``H`` input
    revolutions before the next block are kept aside); the result is returned either way."""
    n = d.shape[0]
    H = sm.H
    flat = d.reshape(n, -1)
    ncol = flat.shape[1]
    res = flat if in_place else np.empty_like(flat)
    carry = None  # input revolutions max(0, a - H) .. a - 1, when they are overwritten
    for a, b in sm.blocks(ncol):
        lo, hi = max(0, a - H), min(n, b + H)
        src = flat[lo:hi] if carry is None else np.concatenate([carry, flat[a:hi]])
        if in_place:
            carry = src[max(0, b - H) - lo:b - lo].copy()
        res[a:b] = _smooth_block(src, lo, a, b, n, sm)
    return res.reshape(d.shape)


def _smooth_block(src: np.ndarray, lo: int, a: int, b: int, n: int, sm: Smoother) -> np.ndarray:
    """Smoothed revolutions ``a:b`` of ``n`` from ``src``, the input's revolutions ``lo = max(0,
    a - H) .. min(n, b + H) - 1``: per element, the operations (and their order) of the whole
    run's computation."""
    H, j = sm.H, sm.j
    m, ncol = b - a, src.shape[1]
    K, L = sm.rows(a, b)
    nan = np.isnan(src)
    # pad[i] is revolution a - H + i (zeros outside the run and for missing samples)
    pad = np.zeros((m + 2 * H, ncol))
    pad[lo - (a - H):lo - (a - H) + src.shape[0]] = np.where(nan, 0.0, src)
    own = src[a - lo:b - lo]
    out = np.zeros((m, ncol))
    Lz = np.nan_to_num(L)
    for k in range(2 * H + 1):
        rows = np.flatnonzero(Lz[:, k])
        if rows.size:
            r0, r1 = rows[0], rows[-1] + 1
            out[r0:r1] += Lz[r0:r1, k, None] * pad[k + r0:k + r1]
    bad = np.any(np.isnan(L), axis=1)
    out[bad] = own[bad]
    if np.any(nan):
        # outputs whose window holds a missing sample: their own local fit, from the
        # complete-data moments minus those of the missing samples (sparse), in u = j / (H + 1)
        uj = j / (H + 1.0)
        M_full = np.stack([K @ uj ** k for k in range(5)])  # (5, m)
        r0, c0 = np.nonzero(nan)
        rows = (r0 + lo - a)[:, None] - np.arange(-H, H + 1)[None, :]  # outputs that see the sample at offset j
        ok = (rows >= 0) & (rows < m)
        rows_c = np.clip(rows, 0, m - 1)
        kw = np.where(ok, K[rows_c, np.arange(2 * H + 1)[None, :]], 0.0)
        lin = (rows_c * ncol + c0[:, None]).ravel()
        hit = np.bincount(lin, weights=(kw > 0).ravel().astype(float), minlength=m * ncol) > 0
        r, c = np.divmod(np.flatnonzero(hit), ncol)
        pos = np.full(m * ncol, -1, dtype=np.int64)
        pos[np.flatnonzero(hit)] = np.arange(r.size)
        M = M_full[:, r].copy()  # (5, n_hit)
        sel = pos[lin]
        for k in range(5):
            M[k] -= np.bincount(sel[sel >= 0], weights=(kw * uj ** k).ravel()[sel >= 0], minlength=r.size)
        Y = np.zeros((3, r.size))
        for jj in range(2 * H + 1):
            rr = r + a + jj - H
            inside_r = (rr >= 0) & (rr < n)
            kv = np.where(inside_r, K[r, jj], 0.0)
            if not np.any(kv):
                continue
            xv = pad[r + jj, c] * kv
            Y[0] += xv
            Y[1] += xv * uj[jj]
            Y[2] += xv * uj[jj] ** 2
        m0, m1, m2, m3, m4 = M
        c00 = m2 * m4 - m3 * m3
        c01 = m3 * m2 - m1 * m4
        c02 = m1 * m3 - m2 * m2
        det = m0 * c00 + m1 * c01 + m2 * c02
        scale = np.maximum(np.abs(M).max(axis=0) ** 3, 1e-300)
        good = np.abs(det) > 1e-10 * scale
        with np.errstate(all="ignore"):
            val = (c00 * Y[0] + c01 * Y[1] + c02 * Y[2]) / det
        out[r, c] = np.where(good, val, own[r, c])
        out[nan[a - lo:b - lo]] = np.nan
    return out


def smoothing_gain(half_width: np.ndarray, weights: np.ndarray | None, rows) -> np.ndarray:
    """White-noise gain ``||L||_2`` of :func:`smooth_revolutions` at some revolutions.

    Parameters
    ----------
    half_width : ndarray, shape (n_rev,)
        The smoother's half-width per revolution (NaN: no smoothing, gain 1).
    weights : ndarray, shape (n_rev,), optional
    rows : array_like of int

    Returns
    -------
    ndarray, shape (len(rows),)
        The standard deviation of the smoothed value over that of one white-noise sample
        (for equal sample variances).
    """
    h_all = np.asarray(half_width, dtype=float)
    rows = np.atleast_1d(np.asarray(rows, dtype=np.int64))
    n = h_all.size
    out = np.ones(rows.size)
    if n == 0 or not np.isfinite(h_all).any():
        return out
    w_rev = np.ones(n) if weights is None else np.asarray(weights, dtype=float)
    for i, r in enumerate(rows):
        h = h_all[r]
        if not np.isfinite(h):
            continue
        H = int(np.ceil(h))
        j = np.arange(-H, H + 1, dtype=float)
        idx = r + np.arange(-H, H + 1)
        inside = (idx >= 0) & (idx < n)
        u = np.abs(j) / (h + 1.0)
        K = np.where(u < 1.0, (1.0 - u ** 3) ** 3, 0.0) * np.where(inside, w_rev[np.clip(idx, 0, n - 1)], 0.0)
        L = _local_quadratic_weights(K[None], j)[0]
        if np.all(np.isfinite(L)):
            # sample variance proportional to 1 / weight (Eq. 15): gain relative to the centre sample
            var = np.where(inside, 1.0 / np.where(inside, w_rev[np.clip(idx, 0, n - 1)], 1.0), 0.0)
            out[i] = float(np.sqrt(np.sum(L * L * var) * w_rev[r]))
    return out

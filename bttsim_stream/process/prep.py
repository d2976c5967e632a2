"""Data preparation of BTT displacements before the sine fit (paper Sec. 2.3).

Raw Eq. 1 displacements carry, besides the blade vibration, (i) a slowly varying offset
per blade and probe -- static deflection, probe and blade angle errors, the OPR model's
error and, for interpolated TOAs (PAD), a bias that grows with speed -- and (ii) noise whose
level grows with speed (Eq. 15: ``delta d = Omega R delta t``). Preparation removes the
first and reduces the second without eating the resonance. Each step can be switched off
(:class:`PrepOptions`); all steps work on ``(revolution, blade, probe)`` arrays, tolerate NaN
(missing arrivals stay NaN) and are vectorised over blades and probes.

1. **Resonance location** (:func:`locate_resonance`): a first pass fits Eq. 16 to the raw
   data (per-probe median removed), smooths the amplitude along revolutions (running median
   then mean) and finds, per blade, the peak, its half-power width ``W`` (revolutions) and
   the *resonance region*: the contiguous revolutions around the peak where the amplitude
   exceeds ``exclusion_level`` times the peak (and twice the run's median amplitude),
   widened by ``exclusion_margin * W`` on each side.
2. **Offset removal** (:func:`remove_offset`): per blade and probe, a polynomial in speed
   (degree ``offset_degree``) fitted to the revolutions *outside* the resonance region by
   iteratively reweighted least squares (Tukey bisquare, MAD scale) with Eq. 15 weights
   ``1 / Omega^2``, and subtracted everywhere, so the region is bridged by a smooth
   baseline instead of being flattened. The non-resonant forced response is part of the
   baseline; at the peak it is in quadrature with the resonant response and barely changes
   its amplitude.
3. **Noise reduction** (:func:`smooth_revolutions`): a local quadratic regression (LOESS,
   tricube kernel) along revolutions per blade and probe -- the per-probe sequence of an
   integral-EO response varies slowly from one revolution to the next, so it can be
   smoothed without distorting the response as long as the kernel is narrow compared to
   the resonance. The half-width is ``smooth_width_fraction`` of the half-power width ``W``
   at the resonance speed and **adapts to speed** as ``(Omega / Omega_res)^2``: with the
   noise proportional to ``Omega`` (Eq. 15) this keeps the smoothed noise level constant,
   and for a run-up at a fixed sweep rate a resonance spans a number of revolutions that
   grows at least as ``Omega^2``, so the relative smoothing bias stays constant too. The
   local fits are weighted by Eq. 15 (``1 / Omega^2``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .fit import fit_revolutions
from .history import ScratchRows
from .smoothing import PreparedRows, smooth, smoother, smooth_revolutions, smoothing_gain

__all__ = [
    "PrepOptions",
    "ResonanceRegion",
    "PreparedData",
    "PreparedRows",
    "Baseline",
    "locate_resonance",
    "fit_baseline",
    "remove_offset",
    "median_then_mean",
    "smooth_revolutions",
    "speed_adaptive_half_width",
    "prepare",
    "smoothing_gain",
]


@dataclass(frozen=True, slots=True)
class PrepOptions:
    """Switches and parameters of the data preparation.

    Attributes
    ----------
    remove_offset : bool
        Subtract the per blade/probe baseline (polynomial in speed outside the resonance).
    offset_degree : int
        Degree of the baseline polynomial in speed.
    exclusion_level : float
        Resonance region: amplitude above this fraction of the first-pass peak...
    exclusion_margin : float
        ...widened by this many half-power widths on each side.
    robust : bool
        Bisquare reweighting of the baseline fit (3 iterations).
    smooth : bool
        Local quadratic regression along revolutions.
    smooth_half_width : float or None
        Kernel half-width at the resonance speed, revolutions; None: ``smooth_width_fraction``
        of the first-pass half-power width.
    smooth_width_fraction : float
    min_half_width, max_half_width : float
        Limits of the (speed-adaptive) half-width, revolutions.
    speed_adaptive : bool
        Scale the half-width as ``(Omega / Omega_res)^2``.
    noise_weighting : bool
        Weight samples by the Eq. 15 error model, ``1 / Omega^2``.
    """

    remove_offset: bool = True
    offset_degree: int = 2
    exclusion_level: float = 0.1
    exclusion_margin: float = 1.0
    robust: bool = True
    smooth: bool = True
    smooth_half_width: float | None = None
    smooth_width_fraction: float = 0.125
    min_half_width: float = 2.0
    max_half_width: float = 40.0
    speed_adaptive: bool = True
    noise_weighting: bool = True

    def __post_init__(self) -> None:
        if self.offset_degree < 0:
            raise ValueError("offset_degree must be >= 0")
        if not 0 < self.min_half_width <= self.max_half_width:
            raise ValueError("need 0 < min_half_width <= max_half_width")
        if self.smooth_half_width is not None and self.smooth_half_width <= 0:
            raise ValueError("smooth_half_width must be > 0")


@dataclass(frozen=True, slots=True, eq=False)
class ResonanceRegion:
    """First-pass location of the resonance of each blade.

    Attributes
    ----------
    amp_pkpk_m : ndarray, shape (n_rev, n_blades), or None
        Smoothed first-pass amplitude (all engine orders combined), m (None where not made:
        the report alone).
    peak_revolution : ndarray of int, shape (n_blades,)
    half_power_width : ndarray, shape (n_blades,)
        Revolutions where the smoothed amplitude exceeds ``peak / sqrt(2)``.
    significant : ndarray of bool, shape (n_blades,)
        Peak above 3x the run's median amplitude (else the region is empty).
    mask : ndarray of bool, shape (n_rev, n_blades)
        The resonance region (excluded from the baseline fit).
    """

    amp_pkpk_m: np.ndarray
    peak_revolution: np.ndarray
    half_power_width: np.ndarray
    significant: np.ndarray
    mask: np.ndarray


@dataclass(frozen=True, slots=True, eq=False)
class PreparedData:
    """Prepared displacements and what the preparation did.

    Attributes
    ----------
    d_m : ndarray or PreparedRows, shape (n_rev, n_blades, n_probes)
        The prepared displacements; with ``prepare(..., rows_only=True)`` a
        :class:`PreparedRows` (``d_m[a:b]`` prepares those revolutions, the same numbers).
    offset_m : ndarray or Baseline, shape (n_rev, n_blades, n_probes)
        The subtracted baseline (zeros when off). With ``prepare(..., keep_offset=False)`` not
        held as a whole array: the :class:`Baseline` itself (``offset_m[rows]`` gives the
        rows' offsets, the same numbers), or a read-only broadcast zero when off.
    region : ResonanceRegion
    half_width : ndarray, shape (n_rev,)
        Smoother half-width per revolution (NaN when off).
    options : PrepOptions
    baseline : Baseline or None
        The fitted baseline (None when the offset removal is off).
    """

    d_m: np.ndarray
    offset_m: np.ndarray | Baseline
    region: ResonanceRegion
    half_width: np.ndarray
    options: PrepOptions
    baseline: Baseline | None = None


def median_then_mean(x: np.ndarray, size: int) -> np.ndarray:
    """A running median, then a running mean, of ``size`` samples along axis 0 (edges:
    nearest value): robust smoothing of per-revolution curves, shape kept.

    Bit for bit ``scipy.ndimage.uniform_filter1d(scipy.ndimage.median_filter(x, size=(size, 1,
    ..), mode="nearest"), size, axis=0, mode="nearest")``, in numpy (scipy.ndimage takes
    0.2 s to import): the window of sample ``i`` is ``i - size // 2 .. i - size // 2 + size -
    1``, the median its element of rank ``size // 2``, the mean a running sum (the first
    window's sum, then what enters minus what leaves, in order) divided by ``size``. For
    finite values (the callers fill NaN first).
    """
    x = np.asarray(x, dtype=float)
    size = int(size)
    return _running_mean(_running_median(x, size), size)


#: Samples times window length of the running median's block (its copy of the windows: 4 MB).
MEDIAN_BLOCK = 1 << 19


def _nearest_ends(x: np.ndarray, size: int) -> np.ndarray:
    """``x`` extended along axis 0 by its first value ``size // 2`` times and its last value
    ``size - size // 2 - 1`` times."""
    lo = size // 2
    return np.concatenate([np.repeat(x[:1], lo, axis=0), x, np.repeat(x[-1:], size - lo - 1, axis=0)])


def _running_median(x: np.ndarray, size: int) -> np.ndarray:
    from numpy.lib.stride_tricks import sliding_window_view

    ext = _nearest_ends(x, size)
    out = np.empty_like(x)
    n = x.shape[0]
    per = max(1, MEDIAN_BLOCK // (size * max(1, int(np.prod(x.shape[1:])))))
    for a in range(0, n, per):
        b = min(n, a + per)
        out[a:b] = np.partition(sliding_window_view(ext[a:b + size - 1], size, axis=0), size // 2,
                                axis=-1)[..., size // 2]
    return out


def _running_mean(x: np.ndarray, size: int) -> np.ndarray:
    ext = _nearest_ends(x, size)
    n = x.shape[0]
    v = np.empty_like(x)
    v[0] = np.cumsum(ext[:size], axis=0)[-1]
    v[1:] = ext[size:size + n - 1] - ext[:n - 1]
    return np.cumsum(v, axis=0, out=v) / size

def _contiguous(above: np.ndarray, peak: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First and last index of the run of ``above`` (n, m) that contains ``peak`` (m,)."""
    n = above.shape[0]
    idx = np.arange(n)[:, None]
    lo = np.max(np.where(~above & (idx < peak), idx, -1), axis=0) + 1
    hi = np.min(np.where(~above & (idx > peak), idx, n), axis=0) - 1
    return lo, hi


def _masked_median(x: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Median along axis 0 of the entries where ``mask`` (NaN for an empty column); faster
    than ``nanmedian`` on wide arrays."""
    n = np.sum(mask, axis=0)
    srt = np.sort(np.where(mask, x, np.inf).T, axis=1)  # contiguous rows sort fast
    cols = np.arange(x.shape[1])
    lo = srt[cols, np.clip((n - 1) // 2, 0, None)]
    hi = srt[cols, np.clip(n // 2, 0, None)]
    return np.where(n > 0, 0.5 * (lo + hi), np.nan)


def _fill_nan(x: np.ndarray) -> np.ndarray:
    """NaN replaced by the column's median (for filters that cannot skip NaN)."""
    if not np.any(np.isnan(x)):
        return x
    ok = ~np.isnan(x)
    med = np.nan_to_num(_masked_median(np.where(ok, x, 0.0), ok))
    return np.where(ok, x, med)


def locate_resonance(d_m: np.ndarray, probe_angles_rad, engine_orders, *,
                     exclusion_level: float = 0.1, exclusion_margin: float = 1.0,
                     filter_revolutions: int = 11) -> ResonanceRegion:
    """First pass: where is each blade's resonance, and how wide is it?

    Parameters
    ----------
    d_m : ndarray, shape (n_rev, n_blades, n_probes)
        Raw displacements, m.
    probe_angles_rad : array_like, shape (n_probes,)
    engine_orders : int or sequence of int
    exclusion_level, exclusion_margin : float
        See :class:`PrepOptions`.
    filter_revolutions : int
        Length of the running median and running mean applied to the amplitude.

    Returns
    -------
    ResonanceRegion
    """
    d = np.asarray(d_m, dtype=float)
    flat = d.reshape(d.shape[0], -1)
    ok = np.isfinite(flat)
    base = np.nan_to_num(_masked_median(np.where(ok, flat, 0.0), ok)).reshape(d.shape[1:])
    fit = fit_revolutions(d - base[None], probe_angles_rad, engine_orders)
    amp = np.sqrt(np.sum(fit.amp_pkpk_m ** 2, axis=2))
    n_rev, nb = amp.shape
    size = max(1, min(int(filter_revolutions), n_rev))
    amp_s = median_then_mean(_fill_nan(amp), size)
    peak = np.argmax(amp_s, axis=0)
    p_val = amp_s[peak, np.arange(nb)]
    background = np.median(amp_s, axis=0)
    significant = p_val > 3.0 * background
    lo, hi = _contiguous(amp_s >= p_val / math.sqrt(2.0), peak)
    width = (hi - lo + 1).astype(float)
    thr = np.maximum(exclusion_level * p_val, 2.0 * background)
    lo_x, hi_x = _contiguous(amp_s >= thr, peak)
    margin = np.ceil(exclusion_margin * width).astype(np.int64)
    idx = np.arange(n_rev)[:, None]
    mask = (idx >= lo_x - margin) & (idx <= hi_x + margin) & significant
    return ResonanceRegion(amp_pkpk_m=amp_s, peak_revolution=peak.astype(np.int64),
                           half_power_width=width, significant=significant, mask=mask)


#: Matrix products (``M x K`` times ``K x N``) with ``M N K`` at most this many multiply-adds run
#: in OpenBLAS's small-matrix ``dgemm`` kernels on AVX-512 cores (SkylakeX), which sum in
#: another order than its blocked kernels: a product cut in blocks gives the whole product's
#: numbers bit for bit only when every block runs in the same regime as the whole.
GEMM_SMALL = 1_000_000

#: Alignment of the column blocks of the baseline fit (the blocked ``dgemm`` kernels work on
#: tiles of 16 rows of the column-major output: a block starting on a tile boundary keeps
#: every column in the same kind of tile as in the whole product).
FIT_ALIGN = 16

#: Alignment of the row windows in which a baseline is evaluated (3 x the ``dgemm`` kernel's
#: column unroll of 2, times 8: OpenBLAS packs and runs the output's columns, here
#: revolutions, in groups of 6).
ROW_ALIGN = 48


def _aligned_blocks(n: int, per: int, other: int, align: int) -> list:
    """Slices of ``n`` (a dimension of a matrix product's output, ``per`` the multiply-adds of
    one of its lines, ``other`` times the inner dimension) in which the product gives the whole
    product's numbers: the whole when it is small (:data:`GEMM_SMALL`), else blocks of a
    multiple of ``align`` lines above the small-matrix limit, the last one taking a short rest."""
    if n * other <= GEMM_SMALL:
        return [slice(0, n)]
    step = max(1, per, GEMM_SMALL // max(other, 1) + 1)
    step = -(-step // align) * align
    starts = list(range(0, n, step))
    if len(starts) > 1 and ((n - starts[-1]) * other <= GEMM_SMALL or n - starts[-1] < 2):
        starts.pop()
    return [slice(a, starts[i + 1] if i + 1 < len(starts) else n) for i, a in enumerate(starts)]


def _row_windows(n_rev: int, n_col: int, p: int) -> list:
    """Windows of revolutions in which ``V @ coef`` (``V`` (n_rev, p), ``coef`` (p, n_col)) is
    evaluated: fixed for a run, so a revolution's numbers do not depend on the rows asked for."""
    if n_rev == 0:
        return [slice(0, 0)]
    return _aligned_blocks(n_rev, PREP_BLOCK // max(n_col, 1), n_col * p, ROW_ALIGN)


def _product_columns(V: np.ndarray, coef: np.ndarray, cols: slice, windows: list) -> np.ndarray:
    """Columns ``cols`` of ``V @ coef``, computed in the row ``windows`` over all columns."""
    if len(windows) == 1 and cols.start == 0 and cols.stop == coef.shape[1]:
        return V @ coef
    out = np.empty((V.shape[0], cols.stop - cols.start))
    for w in windows:
        out[w] = (V[w] @ coef)[:, cols]
    return out


@dataclass(frozen=True, slots=True, eq=False)
class Baseline:
    """Fitted per blade/probe baselines in speed (:func:`fit_baseline`), evaluated on demand.

    ``baseline[rows]`` gives the offsets of some revolutions, shape ``(len, n_blades,
    n_probes)``, bit for bit the rows of the whole array (:meth:`to_array`, what
    :func:`remove_offset` subtracts), without holding the whole array: they are computed in
    fixed windows of :attr:`window` revolutions (the matrix product's numbers depend on its
    shape, so a row is always computed inside the same window).

    Attributes
    ----------
    x : ndarray, shape (n_rev,)
        Normalised speed per revolution, ``(Omega - centre_rad_s) / half_span_rad_s``.
    coef : ndarray, shape (degree + 1, n_col)
        Polynomial coefficients in ``x`` per column (``n_col = n_blades * n_probes``, blade
        major), lowest degree first.
    lo, hi : ndarray, shape (n_col,), or None
        Clip bounds of ``x`` (the speeds of the revolutions each column was fitted to: no
        extrapolation), ``-inf``/``inf`` for columns without enough data; None when no column
        needs clipping (then evaluated as a matrix product ``V @ coef``).
    enough : ndarray of bool, shape (n_col,)
        Columns with enough usable revolutions for the polynomial.
    mean_m : ndarray, shape (n_col,)
        The weighted mean of each column (the constant baseline of the columns without enough
        data; 0 for a column without any), m.
    shape : tuple
        ``(n_rev, n_blades, n_probes)``.
    centre_rad_s, half_span_rad_s : float
        Normalisation of the speed, rad/s.
    """

    x: np.ndarray
    coef: np.ndarray
    lo: np.ndarray | None
    hi: np.ndarray | None
    enough: np.ndarray
    mean_m: np.ndarray
    shape: tuple
    centre_rad_s: float
    half_span_rad_s: float

    @property
    def window(self) -> int:
        """Revolutions per evaluation window (the last window takes a short rest)."""
        return self._windows()[0].stop

    def _windows(self) -> list:
        return _row_windows(self.shape[0], self.coef.shape[1], self.coef.shape[0])

    def _window(self, a: int, b: int) -> np.ndarray:
        """Offsets of revolutions ``a:b`` (one whole window), shape ``(b - a, n_col)``."""
        x = self.x[a:b]
        if self.lo is None:
            off = np.vander(x, self.coef.shape[0], increasing=True) @ self.coef
        else:
            xc = np.clip(x[:, None], self.lo, self.hi)
            off = np.zeros_like(xc)
            for k in range(self.coef.shape[0] - 1, -1, -1):  # Horner
                off = off * xc + self.coef[k][None, :]
        off[:, ~self.enough] = self.mean_m[~self.enough]
        return off

    def __getitem__(self, rows) -> np.ndarray:
        """Offsets of the revolutions ``rows`` (an int, a slice or an integer array), m."""
        n_rev, nb, npr = self.shape
        if isinstance(rows, slice) and rows.step in (None, 1):
            a, b, _ = rows.indices(n_rev)
            b = max(a, b)
            out = np.empty((b - a, nb * npr))
            for w in self._windows():
                lo, hi = max(a, w.start), min(b, w.stop)
                if lo < hi:
                    out[lo - a:hi - a] = self._window(w.start, w.stop)[lo - w.start:hi - w.start]
            return out.reshape(b - a, nb, npr)
        idx = np.arange(n_rev)[rows]
        scalar = idx.ndim == 0
        idx = np.atleast_1d(idx)
        out = np.empty((idx.size, nb * npr))
        for w in self._windows():
            sel = np.flatnonzero((idx >= w.start) & (idx < w.stop))
            if sel.size:
                out[sel] = self._window(w.start, w.stop)[idx[sel] - w.start]
        out = out.reshape(idx.shape + (nb, npr))
        return out[0] if scalar else out

    rows = __getitem__

    def to_array(self) -> np.ndarray:
        """The whole baseline, shape ``(n_rev, n_blades, n_probes)``, m."""
        return self[:]

    def subtract(self, d_m: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """``d_m - baseline`` window by window (into ``out`` when given; ``out`` may be
        ``d_m`` itself), m."""
        d = np.asarray(d_m, dtype=float)
        if out is None:
            out = np.empty_like(d)
        for w in self._windows():
            out[w] = d[w] - self[w]
        return out


def fit_baseline(d_m: np.ndarray, omega_rad_s: np.ndarray, exclude: np.ndarray | None = None, *,
                 degree: int = 2, robust: bool = True, noise_weighting: bool = True,
                 iterations: int = 3) -> Baseline:
    """Fit a per blade/probe polynomial baseline in speed outside ``exclude``.

    The fit of :func:`remove_offset`, without evaluating the baseline: every column (blade and
    probe) is fitted on its own, in blocks of columns, so the temporaries are bounded by a
    block (:data:`PREP_BLOCK` samples, or the fewest columns whose normal equations are
    computed by the same ``dgemm`` kernels as the whole run's, see :data:`GEMM_SMALL`): the
    same numbers as a fit of all columns at once.

    Parameters
    ----------
    d_m : ndarray or ScratchRows, shape (n_rev, n_blades, n_probes)
        (:class:`~.history.ScratchRows`: its columns read block by block.)
    omega_rad_s : ndarray, shape (n_rev,)
    exclude : ndarray of bool, shape (n_rev, n_blades), optional
        Revolutions left out of each blade's fit (the resonance region).
    degree : int
    robust : bool
        Tukey bisquare reweighting (``c = 4.685`` MAD-scaled residuals).
    noise_weighting : bool
        Eq. 15 weights ``1 / Omega^2``.
    iterations : int
        Reweighting iterations when ``robust``.

    Returns
    -------
    Baseline
    """
    d = d_m if isinstance(d_m, ScratchRows) else np.asarray(d_m, dtype=float)
    n_rev, nb, npr = d.shape
    om = np.asarray(omega_rad_s, dtype=float)
    span = max(float(om.max() - om.min()), 1e-12)
    centre = 0.5 * (om.max() + om.min())
    x = (om - centre) / (0.5 * span)
    V = np.vander(x, int(degree) + 1, increasing=True)  # (n_rev, p)
    # a block of columns: a view of the array, or read from the scratch file (the same numbers)
    y = None if isinstance(d, ScratchRows) else d.reshape(n_rev, nb * npr)
    n_col = nb * npr
    keep = None if exclude is None else ~np.asarray(exclude, bool)
    rel = om * om / np.mean(om * om) if noise_weighting else None
    p = V.shape[1]
    VV = (V[:, :, None] * V[:, None, :]).reshape(n_rev, p * p)
    n_it = 1 + (int(iterations) if robust else 0)
    blocks = _aligned_blocks(n_col, PREP_BLOCK // max(n_rev, 1), n_rev * p, FIT_ALIGN)
    windows = _row_windows(n_rev, n_col, p)
    coef = np.empty((n_col, p))
    enough = np.empty(n_col, bool)
    small, big = np.empty(n_col), np.empty(n_col)
    sw, swy = np.empty(n_col), np.empty(n_col)
    # every column has its own baseline: blocks of columns, each with the kernels the whole
    # run's matrix products would use, give the same numbers with bounded temporaries; the
    # fitted baselines of the robust reweighting come from the product of all columns, in row
    # windows (a product cut in columns may sum in another order than the whole one)
    for it in range(n_it):
        prev, coef = coef, np.empty((n_col, p))
        for c in blocks:
            yc = d.columns(c) if y is None else y[:, c]
            ok = np.isfinite(yc)
            w0 = ok.astype(float)
            if keep is not None:
                w0 *= keep[:, np.arange(c.start, c.stop) // npr]
            if rel is not None:
                w0 /= rel[:, None]
            yz = np.where(ok, yc, 0.0)
            del ok, yc
            if it == 0:
                enough[c] = np.sum(w0 > 0, axis=0) >= 3 * p
                # no extrapolation: outside the speeds of its reference revolutions (e.g. a
                # crossing near the start of a run), a column's baseline keeps its value at the
                # nearest end
                used = w0 > 0
                big[c] = np.where(used, x[:, None], -np.inf).max(axis=0)
                small[c] = np.where(used, x[:, None], np.inf).min(axis=0)
                del used
                sw[c] = w0.sum(axis=0)
                swy[c] = (w0 * yz).sum(axis=0)
                w = w0
            else:
                r = yz - _product_columns(V, prev.T, c, windows)
                sc = 1.4826 * _masked_median(np.abs(r), w0 > 0)
                sc = np.where(np.isfinite(sc) & (sc > 0), sc, np.inf)
                u = r / (4.685 * sc)
                del r
                w = w0 * np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0)
                del u
            G = (w.T @ VV).reshape(-1, p, p)
            G[~enough[c]] = np.eye(p)
            rhs = (w * yz).T @ V
            del w, w0, yz
            coef[c] = np.linalg.solve(G, rhs[..., None])[..., 0]
    del prev
    # columns without enough reference revolutions: weighted mean, or nothing at all
    with np.errstate(all="ignore"):
        mean = np.where(sw > 0, swy / sw, 0.0)
    lo = hi = None
    if np.any(enough & ((x.min() < small) | (x.max() > big))):
        lo, hi = np.where(enough, small, -np.inf), np.where(enough, big, np.inf)
    return Baseline(x=x, coef=coef.T, lo=lo, hi=hi, enough=enough, mean_m=mean, shape=(n_rev, nb, npr),
                    centre_rad_s=float(centre), half_span_rad_s=float(0.5 * span))


def remove_offset(d_m: np.ndarray, omega_rad_s: np.ndarray, exclude: np.ndarray | None = None, *,
                  degree: int = 2, robust: bool = True, noise_weighting: bool = True,
                  iterations: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Subtract a per blade/probe polynomial baseline in speed fitted outside ``exclude``
    (:func:`fit_baseline`, whose parameters these are).

    Returns
    -------
    d_m, offset_m : ndarray, shape (n_rev, n_blades, n_probes)
        Displacement minus baseline, and the baseline. The polynomial is not extrapolated:
        outside the speeds of the revolutions it was fitted to, the baseline keeps its value
        at the nearest of them. A column with fewer than ``3 (degree + 1)`` usable
        revolutions gets a constant (weighted mean) baseline, one with none a zero baseline.

    See Also
    --------
    fit_baseline : the fit alone (a :class:`Baseline` evaluated on demand: no whole arrays).
    """
    d = np.asarray(d_m, dtype=float)
    baseline = fit_baseline(d, omega_rad_s, exclude, degree=degree, robust=robust,
                            noise_weighting=noise_weighting, iterations=iterations)
    offset = baseline.to_array()
    return d - offset, offset


def speed_adaptive_half_width(omega_rad_s: np.ndarray, half_width_at_res: float, omega_res: float, *,
                              adaptive: bool = True, lo: float = 2.0, hi: float = 40.0) -> np.ndarray:
    """Smoother half-width per revolution: ``h_res (Omega / Omega_res)^2`` clipped to ``[lo, hi]``.

    Returns
    -------
    ndarray, shape (n_rev,)
    """
    om = np.asarray(omega_rad_s, dtype=float)
    h = np.full(om.shape, float(half_width_at_res))
    if adaptive:
        h = h * (om / float(omega_res)) ** 2
    return np.clip(h, lo, hi)


#: Samples (revolutions x blades x probes) of the blocks in which :func:`prepare` removes
#: the offsets and smooths, with temporaries bounded by the block (a few dozen arrays of it).
#: The baseline's column blocks and row windows are at least this size, rounded up to
#: :data:`FIT_ALIGN` / :data:`ROW_ALIGN` and above the small-matrix limit :data:`GEMM_SMALL`
#: (the smoother's blocks: :data:`~.smoothing.SMOOTH_BLOCK`).
PREP_BLOCK = 1 << 19


def prepare(d_m: np.ndarray, omega_rad_s: np.ndarray, probe_angles_rad, engine_orders,
            options: PrepOptions = PrepOptions(), *, region: ResonanceRegion | None = None,
            half_width: np.ndarray | None = None,
            exclude_revolutions: np.ndarray | None = None, keep_offset: bool = True,
            rows_only: bool = False) -> PreparedData:
    """Run the data preparation (resonance location, offset removal, noise reduction).

    Parameters
    ----------
    d_m : ndarray or ScratchRows, shape (n_rev, n_blades, n_probes)
        Raw Eq. 1 displacements, m (:class:`~.history.ScratchRows`: read from its scratch
        files by columns and rows with ``rows_only``, else read whole).
    omega_rad_s : ndarray, shape (n_rev,)
        Mean speed per revolution, rad/s.
    probe_angles_rad : array_like, shape (n_probes,)
    engine_orders : int or sequence of int
    options : PrepOptions
    region : ResonanceRegion, optional
        Where the resonances are (e.g. from the crossings of :mod:`.detect`); default the
        single-resonance first pass :func:`locate_resonance`.
    half_width : ndarray, shape (n_rev,), optional
        Smoother half-width per revolution; default from ``region`` (one resonance).
    exclude_revolutions : ndarray of bool, shape (n_rev,), optional
        Further revolutions left out of the baseline fit (e.g. dwells: at one speed, their
        vibration cannot be told from an offset).
    keep_offset : bool
        Hold the subtracted baseline as a whole array in ``offset_m`` (as before); False:
        ``offset_m`` is the :class:`Baseline` (rows evaluated on demand, the same numbers),
        which saves an array of the run's size.
    rows_only : bool
        Do not make the whole prepared array: ``d_m`` is a :class:`PreparedRows` that
        prepares the revolutions asked for (``d_m[a:b]``, the same numbers), and ``offset_m``
        the :class:`Baseline` (as with ``keep_offset=False``).

    Returns
    -------
    PreparedData

    Notes
    -----
    The baseline is fitted in blocks of columns (:func:`fit_baseline`) and subtracted in
    windows of revolutions, into the array that is then smoothed in place by blocks of
    revolutions (the smoother's kernels computed block by block): besides the input and the
    output, only the offsets (when kept), per-revolution vectors and block-sized temporaries
    are held.
    """
    if isinstance(d_m, ScratchRows) and not rows_only:  # the whole prepared array is made: read whole
        d_m = d_m[:]
    d = d_m if isinstance(d_m, ScratchRows) else np.asarray(d_m, dtype=float)
    om = np.asarray(omega_rad_s, dtype=float)
    n_rev = d.shape[0]
    if region is None:
        region = locate_resonance(d, probe_angles_rad, engine_orders,
                                  exclusion_level=options.exclusion_level,
                                  exclusion_margin=options.exclusion_margin)
    half = np.full(n_rev, np.nan)
    kernel = None
    if options.smooth and n_rev >= 3:
        if half_width is not None:
            half = np.clip(np.asarray(half_width, dtype=float), max(options.min_half_width, 1.0),
                           options.max_half_width)
        else:
            sig = region.significant
            if options.smooth_half_width is not None:
                h_res = float(options.smooth_half_width)
            elif np.any(sig):
                h_res = options.smooth_width_fraction * float(np.median(region.half_power_width[sig]))
            else:
                h_res = options.min_half_width
            i_res = int(np.median(region.peak_revolution[sig])) if np.any(sig) else int(np.argmax(om))
            half = speed_adaptive_half_width(om, h_res, om[i_res], adaptive=options.speed_adaptive,
                                             lo=max(options.min_half_width, 1.0), hi=options.max_half_width)
        # the smoother (its kernels are computed block by block while smoothing)
        kernel = smoother(n_rev, half, 1.0 / (om * om) if options.noise_weighting else None)
    keep_offset = keep_offset and not rows_only
    out = d
    offset = np.zeros_like(d) if keep_offset else np.broadcast_to(np.zeros(()), d.shape)
    baseline = None
    if options.remove_offset:
        exclude = region.mask
        if exclude_revolutions is not None:
            exclude = exclude | np.asarray(exclude_revolutions, bool)[:, None]
        baseline = fit_baseline(d, om, exclude, degree=options.offset_degree, robust=options.robust,
                                noise_weighting=options.noise_weighting)
        del exclude
        offset = baseline.to_array() if keep_offset else baseline
        if rows_only:
            return PreparedData(d_m=PreparedRows(d, baseline, kernel), offset_m=offset, region=region,
                                half_width=half, options=options, baseline=baseline)
        out = baseline.subtract(d)  # window by window: no whole offset array besides the kept one
    if rows_only:
        return PreparedData(d_m=PreparedRows(d, None, kernel), offset_m=offset, region=region, half_width=half,
                            options=options, baseline=baseline)
    if kernel is not None:
        # by blocks of revolutions, written back in place when the offset-removed array is this
        # function's own
        out = smooth(out, kernel, in_place=out is not d)
    return PreparedData(d_m=out, offset_m=offset, region=region, half_width=half, options=options,
                        baseline=baseline)

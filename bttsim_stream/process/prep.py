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
    amp_pkpk_m : ndarray, shape (n_rev, n_blades)
        Smoothed first-pass amplitude (all engine orders combined), m.
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
    d_m : ndarray, shape (n_rev, n_blades, n_probes)
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
    d = np.asarray(d_m, dtype=float)
    n_rev, nb, npr = d.shape
    om = np.asarray(omega_rad_s, dtype=float)
    span = max(float(om.max() - om.min()), 1e-12)
    centre = 0.5 * (om.max() + om.min())
    x = (om - centre) / (0.5 * span)
    V = np.vander(x, int(degree) + 1, increasing=True)  # (n_rev, p)
    y = d.reshape(n_rev, nb * npr)
    n_col = y.shape[1]
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
            yc = y[:, c]
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
    """Subtract a per blade/probe polynomial baseline in speed fitted outside ``exclude``.

    Parameters
    ----------
    d_m : ndarray, shape (n_rev, n_blades, n_probes)
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
    blocks of revolutions (:class:`_Smoother`): the memory held besides the input and the
    output does not grow with the run.
    """
    d = np.asarray(d_m, dtype=float)
    return _smooth(d, _smoother(d.shape[0], half_width, weights))


#: Alignment of the blocks of revolutions in which the smoother's kernels are computed: the
#: moments ``K @ j**k`` are matrix-vector products, which OpenBLAS's ``dgemv`` kernels compute
#: for groups of 4 rows (the rest of the matrix, its last ``n % 4`` rows, by another kernel
#: that sums in another order; numpy computes a one-row product as a dot product, in yet
#: another order): blocks of a multiple of this many rows, the last one ending with the run
#: and at least this long, give every row the whole product's numbers, bit for bit.
SMOOTH_ALIGN = 64


@dataclass(frozen=True, slots=True, eq=False)
class _Smoother:
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
        about :data:`PREP_BLOCK` samples."""
        n = self.n
        step = PREP_BLOCK // max(n_col, 2 * self.H + 1, 1)
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


def _smoother(n: int, half_width, weights) -> _Smoother:
    """The kernel of :func:`smooth_revolutions` over ``n`` revolutions (rows on demand)."""
    h = np.broadcast_to(np.asarray(half_width, dtype=float), (n,))
    if np.any(~np.isfinite(h)) or np.any(h < 1):
        raise ValueError("half_width must be finite and >= 1")
    H = int(np.ceil(h.max()))
    j = np.arange(-H, H + 1, dtype=float)
    w_rev = np.ones(n) if weights is None else np.asarray(weights, dtype=float)
    return _Smoother(h=h, w_rev=w_rev, H=H, j=j)


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
    baseline : Baseline or None
        The offsets to subtract (None: none).
    smoother : _Smoother or None
        The smoother's kernel (None: no smoothing).
    """

    def __init__(self, d_m: np.ndarray, baseline: "Baseline | None", smoother: "_Smoother | None") -> None:
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


def _smooth(d: np.ndarray, sm: _Smoother, in_place: bool = False) -> np.ndarray:
    """:func:`smooth_revolutions` of ``d`` with the kernel ``sm``, by blocks of revolutions
    (:meth:`_Smoother.blocks`): a block's outputs read the input's revolutions ``a - H ..
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


def _smooth_block(src: np.ndarray, lo: int, a: int, b: int, n: int, sm: _Smoother) -> np.ndarray:
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


#: Samples (revolutions x blades x probes) of the blocks in which :func:`prepare` removes
#: the offsets and smooths, with temporaries bounded by the block (a few dozen arrays of it).
#: The baseline's column blocks and row windows are at least this size, rounded up to
#: :data:`FIT_ALIGN` / :data:`ROW_ALIGN` and above the small-matrix limit :data:`GEMM_SMALL`;
#: the smoother's blocks of revolutions (all columns, and the kernels' ``2 H + 1`` offsets) at
#: most this size, rounded down to :data:`SMOOTH_ALIGN` revolutions.
PREP_BLOCK = 1 << 19


def prepare(d_m: np.ndarray, omega_rad_s: np.ndarray, probe_angles_rad, engine_orders,
            options: PrepOptions = PrepOptions(), *, region: ResonanceRegion | None = None,
            half_width: np.ndarray | None = None,
            exclude_revolutions: np.ndarray | None = None, keep_offset: bool = True,
            rows_only: bool = False) -> PreparedData:
    """Run the data preparation (resonance location, offset removal, noise reduction).

    Parameters
    ----------
    d_m : ndarray, shape (n_rev, n_blades, n_probes)
        Raw Eq. 1 displacements, m.
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
    d = np.asarray(d_m, dtype=float)
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
        kernel = _smoother(n_rev, half, 1.0 / (om * om) if options.noise_weighting else None)
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
        out = _smooth(out, kernel, in_place=out is not d)
    return PreparedData(d_m=out, offset_m=offset, region=region, half_width=half, options=options,
                        baseline=baseline)

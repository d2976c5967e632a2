"""Resonance amplitude and frequency per blade, errors against the truth (paper Eq. 17-19).

Resonance is the revolution at which the fitted amplitude peaks (Sec. 2.3):
``A_BTT^(peak)`` and ``f_BTT^(peak) = EO Omega / (2 pi)`` there. :func:`find_peaks` picks
the largest amplitude (``"max"``, the paper's definition), or refines it below one
revolution by a least-squares parabola through the top of the peak (``"parabolic"``) or a
single-degree-of-freedom amplitude curve fitted through the resonance (``"sdof"``, which
also estimates the damping ratio; it describes a steady-state response, so on a fast sweep
it is biased against a transient truth).

The benchmark (Sec. 2.4) is the truth's peak-to-peak envelope of ``d_eqv`` (Eq. 3):
``A_eqv^(peak)`` is its largest value over the revolutions and ``f_eqv^(peak)`` the
frequency ``EO Omega_mean / (2 pi)`` of that revolution. Errors (percent):
``E_A = 100 |A_BTT - A_eqv| / A_eqv`` (Eq. 18), ``E_f = 100 |f_BTT - f_eqv| / f_eqv`` (Eq. 19).

Blades are numbered from 0, as on the bus. Amplitudes are peak-to-peak, m; frequencies Hz.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = [
    "ResonancePeaks",
    "TruthPeaks",
    "TruthPeakTracker",
    "ResonanceReport",
    "find_peaks",
    "truth_peaks",
    "resonance_errors",
    "resonance_report",
    "summary_table",
    "PEAK_METHODS",
]

TWO_PI = 2.0 * np.pi
PEAK_METHODS = ("max", "parabolic", "sdof")


@dataclass(frozen=True, slots=True, eq=False)
class ResonancePeaks:
    """Resonance of each blade.

    Attributes
    ----------
    revolution : ndarray, shape (n_blades,)
        Revolution of the peak (fractional for the refined methods).
    amp_pkpk_m : ndarray, shape (n_blades,)
    freq_hz : ndarray, shape (n_blades,)
    damping_ratio : ndarray, shape (n_blades,)
        From the ``"sdof"`` fit (NaN otherwise).
    method : str
    """

    revolution: np.ndarray
    amp_pkpk_m: np.ndarray
    freq_hz: np.ndarray
    damping_ratio: np.ndarray
    method: str


@dataclass(frozen=True, slots=True, eq=False)
class TruthPeaks:
    """The truth's resonance per blade (``A_eqv^(peak)``, ``f_eqv^(peak)``).

    Attributes
    ----------
    revolution : ndarray of int, shape (n_blades,)
    amp_pkpk_m, freq_hz : ndarray, shape (n_blades,)
    """

    revolution: np.ndarray
    amp_pkpk_m: np.ndarray
    freq_hz: np.ndarray


def truth_peaks(truth, engine_order: int) -> TruthPeaks:
    """Truth peaks from a truth-like object (``Truth`` of the simulator, or anything with
    ``d_eqv_pkpk_m`` (n_rev, n_blades) and ``omega_mean`` (n_rev,) in rad/s)."""
    pk = np.asarray(truth.d_eqv_pkpk_m, dtype=float)
    om = np.asarray(truth.omega_mean, dtype=float)
    rev = np.argmax(pk, axis=0)
    return TruthPeaks(revolution=rev.astype(np.int64), amp_pkpk_m=pk[rev, np.arange(pk.shape[1])],
                      freq_hz=int(engine_order) * om[rev] / TWO_PI)


class TruthPeakTracker:
    """Running truth peaks for a stream: feed each revolution's truth, read the peaks.

    Parameters
    ----------
    engine_order : int

    Examples
    --------
    >>> tr = TruthPeakTracker(8)
    >>> tr.update(0, np.array([1e-3, 2e-3]), 300.0)
    >>> tr.update(1, np.array([3e-3, 1e-3]), 301.0)
    >>> tr.peaks().revolution.tolist()
    [1, 0]
    """

    def __init__(self, engine_order: int) -> None:
        self.engine_order = int(engine_order)
        self._amp: np.ndarray | None = None
        self._rev: np.ndarray | None = None
        self._omega: np.ndarray | None = None

    def update(self, revolution: int, d_eqv_pkpk_m: np.ndarray, omega_mean_rad_s: float) -> None:
        """Add one revolution: ``d_eqv_pkpk_m`` (n_blades,) m, mean speed rad/s."""
        a = np.asarray(d_eqv_pkpk_m, dtype=float)
        if self._amp is None:
            self._amp = np.full(a.shape, -np.inf)
            self._rev = np.full(a.shape, -1, dtype=np.int64)
            self._omega = np.full(a.shape, np.nan)
        better = a > self._amp
        self._amp = np.where(better, a, self._amp)
        self._rev = np.where(better, int(revolution), self._rev)
        self._omega = np.where(better, float(omega_mean_rad_s), self._omega)

    def peaks(self) -> TruthPeaks | None:
        """The peaks so far (None before any update)."""
        if self._amp is None:
            return None
        return TruthPeaks(revolution=self._rev.copy(), amp_pkpk_m=self._amp.copy(),
                          freq_hz=self.engine_order * self._omega / TWO_PI)


def _parabolic(amp: np.ndarray, peak: np.ndarray, half: int) -> tuple[np.ndarray, np.ndarray]:
    """Vertex of a least-squares parabola through ``peak +- half`` revolutions, per blade."""
    n, nb = amp.shape
    j = np.arange(-half, half + 1)
    idx = peak[None, :] + j[:, None]
    ok = (idx >= 0) & (idx < n)
    y = amp[np.clip(idx, 0, n - 1), np.arange(nb)[None, :]]
    ok &= np.isfinite(y)
    w = ok.astype(float)
    V = np.stack([np.ones_like(j), j, j * j], axis=1).astype(float)
    G = np.einsum("jb,jp,jq->bpq", w, V, V)
    rhs = np.einsum("jb,jp->bp", w * np.where(ok, y, 0.0), V)
    bad = np.linalg.matrix_rank(G) < 3
    G[bad] = np.eye(3)
    c = np.linalg.solve(G, rhs[..., None])[..., 0]
    concave = (c[:, 2] < 0) & ~bad
    with np.errstate(all="ignore"):
        x = np.where(concave, -c[:, 1] / (2 * c[:, 2]), 0.0)
    x = np.clip(x, -half, half)
    val = np.where(concave, c[:, 0] + c[:, 1] * x + c[:, 2] * x * x, amp[peak, np.arange(nb)])
    x = np.where(concave, x, 0.0)
    return peak + x, val


def _sdof(amp: np.ndarray, freq: np.ndarray, peak: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """SDOF amplitude curve through the half-amplitude region of each blade's peak."""
    from scipy.optimize import least_squares

    n, nb = amp.shape
    f_pk = np.full(nb, np.nan)
    a_pk = np.full(nb, np.nan)
    zeta = np.full(nb, np.nan)
    for b in range(nb):
        a, p = amp[:, b], int(peak[b])
        if not np.isfinite(a[p]):
            continue
        lo = p
        while lo > 0 and np.isfinite(a[lo - 1]) and a[lo - 1] >= 0.5 * a[p]:
            lo -= 1
        hi = p
        while hi < n - 1 and np.isfinite(a[hi + 1]) and a[hi + 1] >= 0.5 * a[p]:
            hi += 1
        sel = slice(lo, hi + 1)
        f, y = freq[sel], a[sel]
        ok = np.isfinite(f) & np.isfinite(y)
        f, y = f[ok], y[ok]
        if f.size < 5:
            continue
        width = max(float(f.max() - f.min()), 1e-9)
        z0 = max(width / (2.0 * freq[p]) / 2.0, 1e-4)

        def model(q, f=f):
            ap, fp, z = q
            fn = fp / math.sqrt(max(1.0 - 2.0 * z * z, 1e-12))
            r = f / fn
            return ap * 2.0 * z * math.sqrt(max(1.0 - z * z, 0.0)) / np.sqrt((1 - r * r) ** 2 + (2 * z * r) ** 2)

        res = least_squares(lambda q: (model(q) - y) / a[p], x0=[a[p], freq[p], z0],
                            bounds=([0.0, f.min(), 1e-5], [np.inf, f.max(), 0.3]))
        a_pk[b], f_pk[b], zeta[b] = res.x
    return a_pk, f_pk, zeta


def find_peaks(amp_pkpk_m: np.ndarray, freq_hz: np.ndarray, *, method: str = "max",
               half_width: int = 5) -> ResonancePeaks:
    """Peak amplitude and frequency of each blade.

    Parameters
    ----------
    amp_pkpk_m : ndarray, shape (n_rev, n_blades)
        Fitted amplitude per revolution, m (NaN skipped).
    freq_hz : ndarray, shape (n_rev,)
        ``f_BTT`` per revolution (Eq. 17), Hz.
    method : {"max", "parabolic", "sdof"}
    half_width : int
        Revolutions each side of the maximum for ``"parabolic"``.

    Returns
    -------
    ResonancePeaks
    """
    if method not in PEAK_METHODS:
        raise ValueError(f"method must be one of {PEAK_METHODS}, got {method!r}")
    amp = np.asarray(amp_pkpk_m, dtype=float)
    f = np.asarray(freq_hz, dtype=float)
    n, nb = amp.shape
    has = np.any(np.isfinite(amp), axis=0)
    peak = np.argmax(np.where(np.isfinite(amp), amp, -np.inf), axis=0)
    cols = np.arange(nb)
    rev = peak.astype(float)
    val = amp[peak, cols]
    zeta = np.full(nb, np.nan)
    fr = f[peak]
    if method == "parabolic":
        rev, val = _parabolic(amp, peak, int(half_width))
        fr = np.interp(rev, np.arange(n), f)
    elif method == "sdof":
        a_s, f_s, z_s = _sdof(amp, f, peak)
        ok = np.isfinite(a_s)
        val = np.where(ok, a_s, val)
        fr = np.where(ok, f_s, fr)
        rev = np.where(ok, np.interp(fr, f, np.arange(n)) if np.all(np.diff(f) > 0) else rev, rev)
        zeta = z_s
    nan = np.full(nb, np.nan)
    return ResonancePeaks(revolution=np.where(has, rev, nan), amp_pkpk_m=np.where(has, val, nan),
                          freq_hz=np.where(has, fr, nan), damping_ratio=zeta, method=method)


def resonance_errors(peaks: ResonancePeaks, truth: TruthPeaks) -> tuple[np.ndarray, np.ndarray]:
    """``E_A`` and ``E_f`` per blade, percent (Eq. 18-19)."""
    e_a = 100.0 * np.abs(peaks.amp_pkpk_m - truth.amp_pkpk_m) / truth.amp_pkpk_m
    e_f = 100.0 * np.abs(peaks.freq_hz - truth.freq_hz) / truth.freq_hz
    return e_a, e_f


@dataclass(frozen=True, slots=True, eq=False)
class ResonanceReport:
    """The resonance of every blade, with errors when the truth is known.

    Attributes
    ----------
    nd : int
        Identified nodal diameter (signed: negative for a backward wave, see
        :mod:`~bttsim_stream.process.travelling_wave`).
    eo : int
    cn : float
        Condition number of ``B`` (Eq. 16).
    peaks : ResonancePeaks
    truth : TruthPeaks or None
    e_a_pct, e_f_pct : ndarray, shape (n_blades,), or None
    """

    nd: int
    eo: int
    cn: float
    peaks: ResonancePeaks
    truth: TruthPeaks | None = None
    e_a_pct: np.ndarray | None = None
    e_f_pct: np.ndarray | None = None

    def to_summary(self) -> dict:
        """The brief's summary JSON dict (truth fields only when the truth is known)."""
        blades = []
        for b in range(self.peaks.amp_pkpk_m.size):
            row = {"blade": b, "amp_pkpk_m": float(self.peaks.amp_pkpk_m[b]),
                   "freq_hz": float(self.peaks.freq_hz[b])}
            if self.truth is not None:
                row.update(truth_amp_pkpk_m=float(self.truth.amp_pkpk_m[b]),
                           truth_freq_hz=float(self.truth.freq_hz[b]),
                           E_A_pct=float(self.e_a_pct[b]), E_f_pct=float(self.e_f_pct[b]))
            blades.append(row)
        out = {"nd": int(self.nd), "eo": int(self.eo), "cn": float(self.cn), "blades": blades}
        if self.truth is not None:
            out.update(mean_E_A_pct=float(np.nanmean(self.e_a_pct)), max_E_A_pct=float(np.nanmax(self.e_a_pct)),
                       mean_E_f_pct=float(np.nanmean(self.e_f_pct)), max_E_f_pct=float(np.nanmax(self.e_f_pct)))
        return out

    def table(self) -> str:
        """A fixed-width text table of the report (amplitudes in mm, for printing)."""
        return summary_table(self.to_summary())


def summary_table(summary: dict) -> str:
    """Format a summary dict (the brief's JSON form) as a text table."""
    truth = "mean_E_A_pct" in summary
    head = f"{'blade':>5}  {'amp mm pk-pk':>12}  {'freq Hz':>9}"
    if truth:
        head += f"  {'truth mm':>9}  {'truth Hz':>9}  {'E_A %':>7}  {'E_f %':>7}"
    lines = [f"EO {summary['eo']}  ND {summary['nd']}  CN {summary['cn']:.3g}", head]
    for r in summary["blades"]:
        s = f"{r['blade']:>5}  {1e3 * r['amp_pkpk_m']:>12.4f}  {r['freq_hz']:>9.3f}"
        if truth:
            s += (f"  {1e3 * r['truth_amp_pkpk_m']:>9.4f}  {r['truth_freq_hz']:>9.3f}"
                  f"  {r['E_A_pct']:>7.3f}  {r['E_f_pct']:>7.4f}")
        lines.append(s)
    if truth:
        lines.append(f"E_A mean {summary['mean_E_A_pct']:.3f} %  max {summary['max_E_A_pct']:.3f} %   "
                     f"E_f mean {summary['mean_E_f_pct']:.4f} %  max {summary['max_E_f_pct']:.4f} %")
    if summary.get("complete") is False:
        lines.append(f"INCOMPLETE: {summary['revolutions_processed']} of {summary['revolutions_expected']} "
                     f"revolutions processed, {summary['lost']} messages lost, {summary['duplicates']} "
                     f"duplicates, {summary['rejected']} rejected: this is not the whole run")
    return "\n".join(lines)


def resonance_report(peaks: ResonancePeaks, *, nd: int, eo: int, cn: float,
                     truth: TruthPeaks | None = None) -> ResonanceReport:
    """Bundle peaks (and errors against ``truth`` when given) into a :class:`ResonanceReport`."""
    if truth is None:
        return ResonanceReport(nd=int(nd), eo=int(eo), cn=float(cn), peaks=peaks)
    e_a, e_f = resonance_errors(peaks, truth)
    return ResonanceReport(nd=int(nd), eo=int(eo), cn=float(cn), peaks=peaks, truth=truth,
                           e_a_pct=e_a, e_f_pct=e_f)

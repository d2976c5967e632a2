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

A run may hold several resonances (engine orders, crossings) and steady-state dwells, or
none: :class:`ResonanceEntry` is one (EO, crossing) or one dwell, with its detection statistic
and its own per-blade table; :class:`ResonanceReport` holds them all, a ``status``
(``"resonance"``, ``"steady"`` or ``"none"``) and, for existing readers, the legacy top-level
fields of the strongest one (:meth:`ResonanceReport.to_summary`, the brief's summary JSON).

Blades are numbered from 0, as on the bus. Amplitudes are peak-to-peak, m; frequencies Hz.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from .history import ScratchRows, SpilledRows

__all__ = [
    "STATUSES",
    "Detection",
    "ResonanceEntry",
    "window_truth",
    "ResonancePeaks",
    "TruthPeaks",
    "TruthPeakTracker",
    "TruthRows",
    "ResonanceReport",
    "find_peaks",
    "truth_peaks",
    "own_envelope",
    "truth_envelope",
    "resonance_errors",
    "resonance_report",
    "summary_table",
    "PEAK_METHODS",
]

TWO_PI = 2.0 * np.pi
PEAK_METHODS = ("fit", "max", "parabolic", "sdof")
STATUSES = ("resonance", "steady", "none")


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
    phase_rad : ndarray, shape (n_blades,), or None
        Phase of the response at the peak (Eq. 16's ``psi``), rad.
    amp_std_m, freq_std_hz : ndarray, shape (n_blades,), or None
        Standard uncertainty of the amplitude (pk-pk, m) and of the frequency (Hz).
    steady_amp_pkpk_m, natural_freq_hz : ndarray, shape (n_blades,), or None
        SDOF method only: the sweep-corrected steady-state resonant amplitude and the
        natural frequency.
    amp_ci95_m, freq_ci95_hz, phase_ci95_rad : ndarray, shape (n_blades, 2), or None
        95 % intervals ``[lo, hi]`` of the amplitude (pk-pk, m), frequency (Hz) and phase
        (rad) (:mod:`~bttsim_stream.process.intervals`).
    crb_amp_m, crb_freq_hz : ndarray, shape (n_blades,), or None
        Cramér-Rao lower bounds (standard deviations) of the pk-pk amplitude and of the
        frequency for the run's layout, noise and revolutions (:mod:`~bttsim_stream.process.crb`).
    offset_m : ndarray of complex, shape (n_blades,), or None
        SDOF method only: the fitted constant ``c`` (what the zeroing left in the responses
        ``a1 + i a2``, m); not reported, it checks the zeroing correction of the other methods.
    misfit_m : ndarray, shape (n_blades,), or None
        SDOF method only: rms of the fit's complex residuals, m (how far the one-mode model
        holds; an error of that size may sit in ``offset_m``).
    """

    revolution: np.ndarray
    amp_pkpk_m: np.ndarray
    freq_hz: np.ndarray
    damping_ratio: np.ndarray
    method: str
    phase_rad: np.ndarray | None = None
    amp_std_m: np.ndarray | None = None
    freq_std_hz: np.ndarray | None = None
    steady_amp_pkpk_m: np.ndarray | None = None
    natural_freq_hz: np.ndarray | None = None
    amp_ci95_m: np.ndarray | None = None
    freq_ci95_hz: np.ndarray | None = None
    phase_ci95_rad: np.ndarray | None = None
    crb_amp_m: np.ndarray | None = None
    crb_freq_hz: np.ndarray | None = None
    offset_m: np.ndarray | None = None
    misfit_m: np.ndarray | None = None

    @property
    def n_blades(self) -> int:
        return int(np.asarray(self.amp_pkpk_m).size)

    @classmethod
    def empty(cls, method: str = "none") -> "ResonancePeaks":
        """No blade at all (a report that claims no amplitude)."""
        e = np.zeros(0)
        return cls(revolution=e, amp_pkpk_m=e, freq_hz=e, damping_ratio=e, method=method)


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


def own_envelope(truth, engine_order: int, rows: slice = slice(None)) -> np.ndarray | None:
    """The truth's envelope of ``engine_order``'s own response, (n_rev, n_blades): the column
    of ``eo_pkpk_m`` (n_rev, n_blades, n_eo) whose ``eo_engine_order`` (n_eo,), or
    (n_rev, n_eo) with the same orders on every row, is ``engine_order``; None when the truth
    does not carry it (then only the sum over the engine orders, ``d_eqv_pkpk_m``, is known).
    ``rows``: of those revolutions only (the arrays may be
    :class:`~.history.ScratchRows`, read for those rows)."""
    amp = getattr(truth, "eo_pkpk_m", None)
    orders = getattr(truth, "eo_engine_order", None)
    if amp is None or orders is None:
        return None
    orders = np.asarray(orders)
    if orders.ndim == 2:
        orders = orders[0] if orders.shape[0] else np.zeros(0, np.int64)
    j = np.flatnonzero(orders == int(engine_order))
    return np.asarray(_rows_of(amp, rows), dtype=float)[..., int(j[0])] if j.size else None


def truth_envelope(truth, engine_order: int, rows: slice = slice(None)) -> np.ndarray:
    """The truth envelope a crossing of ``engine_order`` is scored against, (n_rev, n_blades):
    its own response (:func:`own_envelope`) when the truth carries it, else the sum over the
    engine orders ``d_eqv_pkpk_m`` (the same with one engine order). ``rows``: of those
    revolutions only."""
    own = own_envelope(truth, engine_order, rows)
    return np.asarray(_rows_of(truth.d_eqv_pkpk_m, rows), dtype=float) if own is None else own


def _rows_of(a, rows: slice):
    """Rows ``rows`` of an array (a view) or of a :class:`~.history.ScratchRows` (read)."""
    return a[rows] if isinstance(a, ScratchRows) else np.asarray(a)[rows]


def truth_peaks(truth, engine_order: int) -> TruthPeaks:
    """Truth peaks from a truth-like object (``Truth`` of the simulator, or anything with
    ``d_eqv_pkpk_m`` (n_rev, n_blades) and ``omega_mean`` (n_rev,) in rad/s; with
    ``eo_pkpk_m`` / ``eo_engine_order``, ``engine_order``'s own response)."""
    pk = truth_envelope(truth, engine_order)
    om = np.asarray(truth.omega_mean, dtype=float)
    rev = np.argmax(pk, axis=0)
    return TruthPeaks(revolution=rev.astype(np.int64), amp_pkpk_m=pk[rev, np.arange(pk.shape[1])],
                      freq_hz=int(engine_order) * om[rev] / TWO_PI)


@dataclass(frozen=True, slots=True, eq=False)
class TruthRows:
    """Per-revolution truth envelopes (what :func:`window_truth` needs).

    Attributes
    ----------
    d_eqv_pkpk_m : ndarray or ScratchRows, shape (n_rev, n_blades)
        NaN for revolutions without truth. (Here and in ``eo_pkpk_m``, a
        :class:`~.history.ScratchRows` for a long run's report: read by rows.)
    omega_mean : ndarray, shape (n_rev,)
        Mean speed, rad/s (NaN without truth).
    eo_engine_order : ndarray of int64, shape (n_eo,), or None
    eo_pkpk_m : ndarray or ScratchRows, shape (n_rev, n_blades, n_eo), or None
        Each engine order's own envelope (:func:`own_envelope`); None: not carried.
    """

    d_eqv_pkpk_m: np.ndarray
    omega_mean: np.ndarray
    eo_engine_order: np.ndarray | None = None
    eo_pkpk_m: np.ndarray | None = None


class TruthPeakTracker:
    """Running truth for a stream: feed each revolution's truth, read the peaks (or, for the
    per-crossing truths of the final report, the rows: :meth:`rows`).

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
        # per revolution, in arrival order: (revolution, speed, envelope per blade), and
        # (revolution, which orders, each order's envelope per blade); the older rows in a
        # scratch file (a long live run's truth, read back once for the final report)
        self._rows: SpilledRows | None = None
        self._nsv: dict[int, tuple] = {}  # the revolutions with NSV components
        self._nsv_seen = False  # a truth that carries NSV components (maybe none)
        self._eo: dict[int, SpilledRows] = {}  # by the table's size: (revolution, orders, arrival, table)
        self._eo_orders: list[np.ndarray] = []  # the distinct sets of orders, in order of arrival
        self._eo_arrivals = 0

    def update(self, revolution: int, d_eqv_pkpk_m: np.ndarray, omega_mean_rad_s: float, nsv=None,
               eo=None) -> None:
        """Add one revolution: ``d_eqv_pkpk_m`` (n_blades,) m, mean speed rad/s; ``nsv``: its
        non-synchronous components ``(kind, freq_hz, nd, amp_pkpk_m)``, each (k,), when the
        truth carries them (to score NSV detections); ``eo``: each engine order's own envelope
        ``(engine_orders (n_eo,), eo_pkpk_m (n_blades, n_eo))`` when the truth carries it."""
        a = np.asarray(d_eqv_pkpk_m, dtype=float)
        if self._rows is None:
            self._rows = SpilledRows((a.size + 2,))
        if a.shape == (self._rows.shape_tail[0] - 2,):  # another shape is never read back
            self._rows.append(np.concatenate(([revolution, omega_mean_rad_s], a)))
        if nsv is not None:
            self._nsv_seen = True
            parts = tuple(np.asarray(x).reshape(-1) for x in nsv)
            if any(p.size for p in parts):  # the revolutions without any: nothing to keep
                self._nsv[int(revolution)] = parts
            else:
                self._nsv.pop(int(revolution), None)  # a repeated revolution: the later one holds
        if eo is not None and np.size(eo[0]):
            self._add_eo(int(revolution), np.asarray(eo[0], np.int64).reshape(-1), np.asarray(eo[1], dtype=float))
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

    def rows(self, first_revolution: int, n_revolutions: int) -> TruthRows | None:
        """The truth of revolutions ``first_revolution ..`` (``n_revolutions`` rows; NaN where
        none was received), None before any update."""
        if self._amp is None:
            return None
        nb = self._amp.size
        amp = np.full((int(n_revolutions), nb), np.nan)
        om = np.full(int(n_revolutions), np.nan)
        if self._rows.shape_tail == (nb + 2,):
            rows, i = _latest(self._rows.array(), first_revolution, n_revolutions)
            amp[i], om[i] = rows[:, 2:], rows[:, 1]
        orders, own = self._eo_rows(first_revolution, n_revolutions, nb)
        return TruthRows(d_eqv_pkpk_m=amp, omega_mean=om, eo_engine_order=orders, eo_pkpk_m=own)

    def _add_eo(self, revolution: int, orders: np.ndarray, own: np.ndarray) -> None:
        """Keep one revolution's engine orders' own envelopes (``own``: (n_blades, n_eo)),
        with which orders they are and when they came (a repeated revolution: the later one)."""
        if own.ndim != 2 or own.shape[1] != orders.size:
            return  # not a table of these orders (the codec refuses it): never read back
        code = next((j for j, o in enumerate(self._eo_orders) if np.array_equal(o, orders)), None)
        if code is None:
            code = len(self._eo_orders)
            self._eo_orders.append(orders.copy())
        store = self._eo.get(own.size)
        if store is None:
            store = self._eo[own.size] = SpilledRows((3 + own.size,))
        store.append(np.concatenate(([revolution, code, self._eo_arrivals], own.ravel())))
        self._eo_arrivals += 1

    def _eo_rows(self, first_revolution: int, n_revolutions: int, nb: int):
        """The engine orders' own envelopes of the rows (NaN where a revolution carried none,
        or other orders than the earliest revolution that did), or (None, None)."""
        if not self._eo:
            return None, None
        tables = {size: store.array() for size, store in self._eo.items()}
        head = np.concatenate([t[:, :3] for t in tables.values()])  # revolution, orders, arrival
        latest, _ = _latest(head[np.argsort(head[:, 2])], None, None)  # in arrival order first
        code = int(latest[np.argmin(latest[:, 0]), 1])
        orders = self._eo_orders[code]
        own = np.full((int(n_revolutions), nb, orders.size), np.nan)
        rows = tables.get(nb * orders.size)
        if rows is not None:
            last = latest[np.searchsorted(latest[:, 0], rows[:, 0]), 2]  # latest: by revolution
            mine = (rows[:, 1] == code) & (rows[:, 2] == last)
            i = rows[:, 0].astype(np.int64) - int(first_revolution)
            ok = mine & (i >= 0) & (i < int(n_revolutions))
            own[i[ok]] = rows[ok, 3:].reshape(-1, nb, orders.size)
        return orders.copy(), own

    def nsv_rows(self, first_revolution: int, n_revolutions: int):
        """The non-synchronous truth of revolutions ``first_revolution ..``
        (:class:`~bttsim_stream.process.nsv.NsvTruthRows`; NaN amplitude where none was
        received), None when no truth carried NSV components."""
        from .nsv import NsvTruthRows

        if not self._nsv_seen:
            return None
        n = int(n_revolutions)
        k = max((len(v[0]) for v in self._nsv.values()), default=0)
        kind = np.full((n, k), "", dtype=object)
        freq, amp = np.full((n, k), np.nan), np.full((n, k), np.nan)
        nd = np.zeros((n, k), np.int64)
        for rev, (kd, f, d, a) in self._nsv.items():
            i = rev - int(first_revolution)
            if 0 <= i < n and len(kd) == len(f) == len(d) == len(a):
                m = len(kd)
                kind[i, :m], freq[i, :m], nd[i, :m], amp[i, :m] = kd, f, d, a
        return NsvTruthRows(kind=kind.astype(str), freq_hz=freq, nd=nd, amp_pkpk_m=amp)


def _latest(rows: np.ndarray, first_revolution, n_revolutions):
    """The rows (column 0: the revolution) of each revolution's last arrival, in revolution
    order, and, given ``first_revolution``, only those of revolutions ``first_revolution ..``
    (``n_revolutions`` of them) with their index there."""
    rev = rows[:, 0].astype(np.int64)
    _, last = np.unique(rev[::-1], return_index=True)  # a repeated revolution: the later one
    keep = rev.size - 1 - last
    rows, rev = rows[keep], rev[keep]
    if first_revolution is None:
        return rows, rev
    i = rev - int(first_revolution)
    ok = (i >= 0) & (i < int(n_revolutions))
    return rows[ok], i[ok]


def parabolic_peak(amp: np.ndarray, peak: np.ndarray, half: int) -> tuple[np.ndarray, np.ndarray]:
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
    if method not in ("max", "parabolic", "sdof"):
        raise ValueError(f"method must be one of ('max', 'parabolic', 'sdof'), got {method!r}")
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
        rev, val = parabolic_peak(amp, peak, int(half_width))
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


def _num(x) -> float | None:
    """A JSON-safe float: None for NaN / inf."""
    x = float(x)
    return x if math.isfinite(x) else None


def _blade_rows(peaks: ResonancePeaks, truth: TruthPeaks | None, e_a, e_f, *, extended: bool) -> list[dict]:
    rows = []
    opt = (("phase_rad", peaks.phase_rad), ("amp_std_m", peaks.amp_std_m), ("freq_std_hz", peaks.freq_std_hz),
           ("damping_ratio", peaks.damping_ratio), ("steady_amp_pkpk_m", peaks.steady_amp_pkpk_m),
           ("natural_freq_hz", peaks.natural_freq_hz), ("crb_amp_m", peaks.crb_amp_m),
           ("crb_freq_hz", peaks.crb_freq_hz))
    cis = (("amp_ci95_m", peaks.amp_ci95_m), ("freq_ci95_hz", peaks.freq_ci95_hz),
           ("phase_ci95_rad", peaks.phase_ci95_rad))
    for b in range(peaks.n_blades):
        row = {"blade": b, "amp_pkpk_m": float(peaks.amp_pkpk_m[b]), "freq_hz": float(peaks.freq_hz[b])}
        if extended:
            for name, arr in opt:
                if arr is not None and np.size(arr) == peaks.n_blades and np.isfinite(arr[b]):
                    row[name] = float(arr[b])
        for name, arr in cis:
            if arr is not None and np.shape(arr) == (peaks.n_blades, 2) and np.all(np.isfinite(arr[b])):
                row[name] = [float(arr[b, 0]), float(arr[b, 1])]
        if truth is not None:
            row.update(truth_amp_pkpk_m=float(truth.amp_pkpk_m[b]), truth_freq_hz=float(truth.freq_hz[b]),
                       E_A_pct=float(e_a[b]), E_f_pct=float(e_f[b]))
        rows.append(row)
    return rows


def _error_stats(e_a, e_f) -> dict:
    with np.errstate(all="ignore"):
        import warnings
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            return {"mean_E_A_pct": float(np.nanmean(e_a)), "max_E_A_pct": float(np.nanmax(e_a)),
                    "mean_E_f_pct": float(np.nanmean(e_f)), "max_E_f_pct": float(np.nanmax(e_f))}


@dataclass(frozen=True, slots=True)
class Detection:
    """Why a resonance (or a steady response) was reported.

    Attributes
    ----------
    statistic : str
        ``"prominence_ratio"`` for a crossing (peak of the blade-RMS amplitude over the higher
        of its two bases, see :mod:`~bttsim_stream.process.detect`), ``"amplitude_snr"`` for a
        dwell (mean amplitude over its standard uncertainty).
    value, threshold : float
    snr, snr_threshold : float
        Signal-to-noise ratio of the crossing's peak over its base, and its threshold
        (for a dwell, the same as ``value`` / ``threshold``).
    """

    statistic: str
    value: float
    threshold: float
    snr: float
    snr_threshold: float

    @property
    def detected(self) -> bool:
        return bool(self.value >= self.threshold and self.snr >= self.snr_threshold)

    def to_dict(self) -> dict:
        return {"statistic": self.statistic, "value": _num(self.value), "threshold": _num(self.threshold),
                "snr": _num(self.snr), "snr_threshold": _num(self.snr_threshold)}


@dataclass(frozen=True, slots=True, eq=False)
class ResonanceEntry:
    """One (engine order, crossing) or one steady-state dwell, with its blade table.

    Attributes
    ----------
    kind : {"crossing", "dwell"}
    eo, nd : int
        Engine order and identified nodal diameter (signed: negative for a backward wave).
    cn : float
        Condition number of ``B`` (Eq. 16) of the fit.
    method : str
        ``"peak"``, ``"sdof"`` or ``"cff"`` for a crossing, ``"mean"`` for a dwell.
    rpm : float
        Speed at the crossing's peak (or the dwell's mean speed), rpm.
    freq_hz : float
        Blade mean of the resonant (or dwell) frequency ``EO Omega / 2 pi``, Hz.
    damping_ratio : float
        Blade mean, from the SDOF method (NaN otherwise).
    detection : Detection
    first_revolution, last_revolution : int
        Revolutions used (inclusive, numbered as in the run).
    peak_revolution : int
        Revolution of the crossing's detection peak (-1 for a dwell).
    peaks : ResonancePeaks
    truth : TruthPeaks or None
    e_a_pct, e_f_pct : ndarray or None
    sweep_rate : float
        Dimensionless sweep rate ``|d omega / dt| / omega_n^2`` of the SDOF method (NaN otherwise).
    zeroing_correction : float
        The response the zeroing reference held, added back to this crossing's responses, as a
        fraction of the peak response (blade mean; NaN: none applied).
    notes : tuple of str
        What spoils this entry's estimate (a poor layout, a fast sweep, a short window, an
        overlapping NSV or engine order; :func:`~bttsim_stream.process.intervals.crossing_notes`).
    """

    kind: str
    eo: int
    nd: int
    cn: float
    method: str
    rpm: float
    freq_hz: float
    damping_ratio: float
    detection: Detection
    first_revolution: int
    last_revolution: int
    peak_revolution: int
    peaks: ResonancePeaks
    truth: TruthPeaks | None = None
    e_a_pct: np.ndarray | None = None
    e_f_pct: np.ndarray | None = None
    sweep_rate: float = math.nan
    zeroing_correction: float = math.nan
    notes: tuple = ()

    @property
    def mean_amp_pkpk_m(self) -> float:
        a = np.asarray(self.peaks.amp_pkpk_m, float)
        return float(np.nanmean(a)) if a.size and np.isfinite(a).any() else 0.0

    def with_truth(self, truth: TruthPeaks | None) -> "ResonanceEntry":
        """The same entry scored against ``truth`` (E_A, E_f; Eq. 18-19)."""
        if truth is None:
            return replace(self, truth=None, e_a_pct=None, e_f_pct=None)
        e_a, e_f = resonance_errors(self.peaks, truth)
        return replace(self, truth=truth, e_a_pct=e_a, e_f_pct=e_f)

    def to_summary(self) -> dict:
        """This entry as one element of the summary's ``resonances`` / ``steady`` lists."""
        out = {"kind": self.kind, "eo": int(self.eo), "nd": int(self.nd), "rpm": _num(self.rpm),
               "freq_hz": _num(self.freq_hz), "method": self.method, "cn": _num(self.cn),
               "detection": self.detection.to_dict(),
               "revolutions": {"first": int(self.first_revolution), "last": int(self.last_revolution),
                               "peak": int(self.peak_revolution)}}
        if math.isfinite(self.damping_ratio):
            out["damping_ratio"] = float(self.damping_ratio)
        if math.isfinite(self.sweep_rate):
            out["sweep_rate"] = float(self.sweep_rate)
        if math.isfinite(self.zeroing_correction):
            out["zeroing_correction_pct"] = 100.0 * float(self.zeroing_correction)
        out["blades"] = _blade_rows(self.peaks, self.truth, self.e_a_pct, self.e_f_pct, extended=True)
        if self.truth is not None:
            out.update(_error_stats(self.e_a_pct, self.e_f_pct))
        out["notes"] = list(self.notes)
        return out


@dataclass(frozen=True, slots=True, eq=False)
class ResonanceReport:
    """What the run shows: resonances, steady dwells, or nothing; with errors when the
    truth is known.

    The first seven fields are the legacy top-level report (the strongest resonance, or
    the strongest dwell when the run crosses none; no blade at all when ``status`` is
    ``"none"``).

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
    status : {"resonance", "steady", "none"} or ""
        ``""``: a legacy report (e.g. decoded from an old recording) that did not say.
    resonances, steady : tuple of ResonanceEntry
    reference : dict or None
        The zeroing reference: ``{"method", "first", "last", "contamination_pct", "reason"}``.
    notes : tuple of str
        Why nothing (or less than expected) is reported.
    non_synchronous : tuple of NsvDetection
        Non-synchronous vibrations detected (:mod:`~bttsim_stream.process.nsv`); never
        resonances.
    """

    nd: int
    eo: int
    cn: float
    peaks: ResonancePeaks
    truth: TruthPeaks | None = None
    e_a_pct: np.ndarray | None = None
    e_f_pct: np.ndarray | None = None
    status: str = ""
    resonances: tuple = ()
    steady: tuple = ()
    reference: dict | None = None
    notes: tuple = ()
    non_synchronous: tuple = ()

    @classmethod
    def from_entries(cls, resonances, steady, *, eo: int, cn: float, reference: dict | None = None,
                     notes=(), non_synchronous=()) -> "ResonanceReport":
        """Build the report: status, and the legacy fields from the strongest entry
        (largest blade-mean amplitude among the resonances, else among the dwells whose
        response was detected; none: ``eo``, ``cn`` given, ND 0, no blade)."""
        resonances, steady = tuple(resonances), tuple(steady)
        live = [e for e in steady if e.detection.detected]
        if resonances:
            status, top = "resonance", max(resonances, key=lambda e: e.mean_amp_pkpk_m)
        elif live:
            status, top = "steady", max(live, key=lambda e: e.mean_amp_pkpk_m)
        else:
            status, top = "none", None
        if top is None:
            return cls(nd=0, eo=int(eo), cn=float(cn), peaks=ResonancePeaks.empty(), status=status,
                       resonances=resonances, steady=steady, reference=reference, notes=tuple(notes),
                       non_synchronous=tuple(non_synchronous))
        return cls(nd=top.nd, eo=top.eo, cn=top.cn, peaks=top.peaks, truth=top.truth, e_a_pct=top.e_a_pct,
                   e_f_pct=top.e_f_pct, status=status, resonances=resonances, steady=steady,
                   reference=reference, notes=tuple(notes), non_synchronous=tuple(non_synchronous))

    def to_summary(self) -> dict:
        """The brief's summary JSON dict (truth fields only when the truth is known).

        Legacy keys (``nd``, ``eo``, ``cn``, ``blades`` and the error statistics) describe the
        strongest resonance; with ``status == "steady"`` the strongest dwell; with
        ``status == "none"`` ``blades`` is empty, ``nd`` is 0 and there are no error
        statistics (no amplitude is claimed). Then ``status``, ``resonances``, ``steady``,
        ``reference`` and ``notes``; ``non_synchronous`` (a list) only when a non-synchronous
        vibration was detected (absent: none; the check always runs), never counted in
        ``status``.
        """
        out = {"nd": int(self.nd), "eo": int(self.eo), "cn": _num(self.cn),
               "blades": _blade_rows(self.peaks, self.truth, self.e_a_pct, self.e_f_pct, extended=False)}
        if self.truth is not None and self.peaks.n_blades:
            out.update(_error_stats(self.e_a_pct, self.e_f_pct))
        status = self.status or ("resonance" if self.peaks.n_blades else "none")
        out["status"] = status
        out["resonances"] = [e.to_summary() for e in self.resonances]
        out["steady"] = [e.to_summary() for e in self.steady]
        if self.reference is not None:
            out["reference"] = dict(self.reference)
        out["notes"] = list(self.notes)
        if self.non_synchronous:
            out["non_synchronous"] = [n.to_summary() if hasattr(n, "to_summary") else dict(n)
                                      for n in self.non_synchronous]
        return out

    def table(self) -> str:
        """A fixed-width text table of the report (amplitudes in mm, for printing)."""
        return summary_table(self.to_summary())


#: Micrometres in the printed tables.
_UM = "\u00b5m"


def _f(x) -> float:
    """A table cell's number: NaN for a missing (None) value."""
    return math.nan if x is None else float(x)


def _amp_unit(rows: list[dict]) -> tuple[str, float]:
    """The amplitude unit of one table: mm, or um when every amplitude is below 0.1 mm."""
    amps = [abs(_f(r.get(k))) for r in rows for k in ("amp_pkpk_m", "truth_amp_pkpk_m")]
    amps = [a for a in amps if math.isfinite(a)]
    return ("mm", 1e3) if not amps or max(amps) >= 1e-4 else (_UM, 1e6)


def _blade_table(title: str, entry: dict) -> list[str]:
    """One entry's per-blade rows: amplitude (mm, or um for small ones), its standard
    uncertainty in um, the ends of its 95 % interval relative to it in um, its Cramér-Rao lower
    bound in um, frequency, phase in degrees, and the truth with E_A / E_f when the entry has them."""
    rows = entry["blades"]
    truth = "mean_E_A_pct" in entry
    unc = any("amp_std_m" in r for r in rows)
    ci = any("amp_ci95_m" in r for r in rows)
    crb = any("crb_amp_m" in r for r in rows)
    phase = any("phase_rad" in r for r in rows)
    unit, scale = _amp_unit(rows)
    head = f"{'blade':>5}  {f'amp {unit} pk-pk':>12}"
    if unc:
        head += f"  {'+- ' + _UM:>8}"
    if ci:
        head += f"  {'95% ' + _UM + ' (lo/hi)':>19}"
    if crb:
        head += f"  {'CRB ' + _UM:>8}"
    head += f"  {'freq Hz':>9}"
    if phase:
        head += f"  {'phase deg':>9}"
    if truth:
        head += f"  {f'truth {unit}':>9}  {'truth Hz':>9}  {'E_A %':>7}  {'E_f %':>7}"
    lines = [title, head]
    for r in rows:
        s = f"{r['blade']:>5}  {scale * _f(r['amp_pkpk_m']):>12.4f}"
        if unc:
            s += f"  {1e6 * _f(r.get('amp_std_m')):>8.3f}"
        if ci:
            lo_hi = r.get("amp_ci95_m") or (None, None)
            a = _f(r["amp_pkpk_m"])
            s += f"  {f'{1e6 * (_f(lo_hi[0]) - a):+.3f}/{1e6 * (_f(lo_hi[1]) - a):+.3f}':>19}"
        if crb:
            s += f"  {1e6 * _f(r.get('crb_amp_m')):>8.3f}"
        s += f"  {_f(r['freq_hz']):>9.3f}"
        if phase:
            s += f"  {_phase_deg(r.get('phase_rad')):>9.1f}"
        if truth:
            s += (f"  {scale * _f(r['truth_amp_pkpk_m']):>9.4f}  {_f(r['truth_freq_hz']):>9.3f}"
                  f"  {_f(r['E_A_pct']):>7.3f}  {_f(r['E_f_pct']):>7.4f}")
        lines.append(s)
    for n in entry.get("notes", []) if "kind" in entry else []:
        lines.append(f"note: {n}")
    if truth:
        lines.append(f"E_A mean {entry['mean_E_A_pct']:.3f} %  max {entry['max_E_A_pct']:.3f} %   "
                     f"E_f mean {entry['mean_E_f_pct']:.4f} %  max {entry['max_E_f_pct']:.4f} %")
    return lines


def _phase_deg(phase_rad) -> float:
    """A phase in degrees, wrapped to [-180, 180)."""
    return (math.degrees(_f(phase_rad)) + 180.0) % 360.0 - 180.0


def _entry_title(e: dict) -> str:
    det = e["detection"]
    rev = e["revolutions"]
    cn = e["cn"] if e["cn"] is not None else math.inf
    if e["kind"] == "dwell":
        head = (f"STEADY  EO {e['eo']}  ND {e['nd']}  CN {cn:.3g}  {e['rpm']:.1f} rpm  {e['freq_hz']:.3f} Hz  "
                f"revolutions {rev['first']}-{rev['last']}  amplitude/uncertainty {det['value']:.3g} "
                f"(threshold {det['threshold']:g})")
    else:
        head = (f"RESONANCE  EO {e['eo']}  ND {e['nd']}  CN {cn:.3g}  {e['rpm']:.1f} rpm  {e['freq_hz']:.3f} Hz  "
                f"method {e['method']}  revolutions {rev['first']}-{rev['last']} (peak {rev['peak']})  "
                f"prominence ratio {det['value']:.3g} (>= {det['threshold']:g}), SNR {det['snr']:.3g} "
                f"(>= {det['snr_threshold']:g})")
        if "damping_ratio" in e:
            head += f"  damping ratio {e['damping_ratio']:.5f}"
    return head


def summary_table(summary: dict) -> str:
    """Format a summary dict (the brief's JSON form) as a text table: every resonance and
    dwell found, or a line saying that none was found and why; then the ``INCOMPLETE``
    line when the result is not the whole run."""
    lines: list[str] = []
    legacy = "status" not in summary or (summary["blades"] and not summary.get("resonances")
                                         and not summary.get("steady"))
    if legacy:  # a legacy summary (or report without entries): the one table
        truth = "mean_E_A_pct" in summary
        lines += _blade_table(f"EO {summary['eo']}  ND {summary['nd']}  CN {summary['cn']:.3g}",
                              dict(summary, **({} if truth else {})))
    else:
        for e in summary.get("resonances", []):
            lines += _blade_table(_entry_title(e), e) + [""]
        for e in summary.get("steady", []):
            lines += _blade_table(_entry_title(e), e) + [""]
        ref = summary.get("reference")
        if ref:
            where = (f"revolutions {ref['first']}-{ref['last']}" if ref.get("first") is not None
                     else "no reference window")
            lines.append(f"zeroing: {ref['method']}, {where}: {ref['reason']}")
        if summary["status"] == "none":
            why = "; ".join(summary.get("notes", [])) or "no crossing passed the detection thresholds"
            lines.append(f"NO RESONANCE FOUND (status none, no amplitude claimed): {why}")
        else:
            for n in summary.get("notes", []):
                lines.append(f"note: {n}")
            k = len(summary.get("resonances", []))
            lines.append(f"status {summary['status']}: {k} resonance{'s' if k != 1 else ''}, "
                         f"{len(summary.get('steady', []))} dwell(s)")
    from .nsv import nsv_table_lines
    lines += nsv_table_lines(summary)
    if summary.get("missing_toas"):
        lines.append(f"missing pulses: {summary['missing_toas']} TOAs did not trigger (NaN, left out of the fits)")
    if summary.get("double_pulses") or summary.get("stray_edges"):
        stray = f"; {summary['stray_edges']} in no blade's window" if summary.get("stray_edges") else ""
        lines.append(f"double pulses: {summary['double_pulses']} TOAs had extra trigger edges "
                     f"({summary['extra_edges']} edges in their blade's window{stray}; the first edge kept)")
    recording = summary.get("recording") or {}
    bad_recording = recording.get("complete") is False
    whole_result = not summary.get("lost") and \
        summary.get("revolutions_processed") == summary.get("revolutions_expected")
    if summary.get("complete") is False and not (bad_recording and whole_result):
        lines.append(f"INCOMPLETE: {summary['revolutions_processed']} of {summary['revolutions_expected']} "
                     f"revolutions processed, {summary['lost']} messages lost, {summary['duplicates']} "
                     f"duplicates, {summary['rejected']} rejected: this is not the whole run")
    if bad_recording:  # the result may be whole, its recording is not (``bttsim run``)
        lines.append(f"INCOMPLETE RECORDING: {recording.get('incomplete') or 'see recorder.log'}")
    return "\n".join(lines)


def resonance_report(peaks: ResonancePeaks, *, nd: int, eo: int, cn: float,
                     truth: TruthPeaks | None = None) -> ResonanceReport:
    """Bundle one set of peaks (and errors against ``truth`` when given) into a legacy
    :class:`ResonanceReport` (no detection: ``status`` is left unsaid)."""
    if truth is None:
        return ResonanceReport(nd=int(nd), eo=int(eo), cn=float(cn), peaks=peaks)
    e_a, e_f = resonance_errors(peaks, truth)
    return ResonanceReport(nd=int(nd), eo=int(eo), cn=float(cn), peaks=peaks, truth=truth,
                           e_a_pct=e_a, e_f_pct=e_f)


def window_truth(truth, engine_order: int, first: int, last: int, *, mean: bool = False) -> TruthPeaks | None:
    """The truth attributable to one crossing (or dwell): per blade, the largest (``mean``:
    the average) truth envelope ``d_eqv_pkpk`` over revolutions ``first .. last`` (indices of
    the truth's rows), and ``EO Omega / 2 pi`` there.

    Parameters
    ----------
    truth : Truth-like or TruthPeaks
        Anything with ``d_eqv_pkpk_m`` (n_rev, n_blades) and ``omega_mean`` (n_rev,); rows
        may be NaN (revolutions without truth). A :class:`TruthPeaks` (peaks only) applies
        to the blades whose peak revolution lies in the window (NaN elsewhere).
    engine_order : int
    first, last : int
    mean : bool

    Returns
    -------
    TruthPeaks or None
        None when the window holds no truth.

    Notes
    -----
    The crossing is scored against its engine order's own response when the truth carries it
    (:func:`truth_envelope`); a truth without it (a recording made before it was recorded)
    gives only the sum over the engine orders, which includes the other orders'
    off-resonance response.
    """
    if truth is None:
        return None
    if isinstance(truth, TruthPeaks):
        rev = np.asarray(truth.revolution)
        inside = (rev >= first) & (rev <= last)
        if not inside.any():
            return None
        nan = np.full(rev.shape, np.nan)
        return TruthPeaks(revolution=np.where(inside, rev, -1), amp_pkpk_m=np.where(inside, truth.amp_pkpk_m, nan),
                          freq_hz=np.where(inside, truth.freq_hz, nan))
    pk = truth_envelope(truth, engine_order, slice(first, last + 1))
    om = np.asarray(truth.omega_mean, dtype=float)[first:last + 1]
    if pk.size == 0 or not np.isfinite(pk).any():
        return None
    nb = pk.shape[1]
    if mean:
        import warnings
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            amp = np.nanmean(pk, axis=0)
            f = int(engine_order) * np.nanmean(om) / TWO_PI
        return TruthPeaks(revolution=np.full(nb, first, np.int64), amp_pkpk_m=amp, freq_hz=np.full(nb, f))
    i = np.argmax(np.where(np.isfinite(pk), pk, -np.inf), axis=0)
    return TruthPeaks(revolution=(first + i).astype(np.int64), amp_pkpk_m=pk[i, np.arange(nb)],
                      freq_hz=int(engine_order) * om[i] / TWO_PI)

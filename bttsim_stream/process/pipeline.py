"""The processing pipeline: OPR + TOAs in, fits, travelling waves and resonances out.

Two entry points share every numerical step:

* :func:`process_arrays` -- offline, on whole ``(revolution, blade, probe)`` arrays
  (a recording, or the simulator's :func:`~bttsim_stream.sim.core.collect`);
* :class:`StreamingProcessor` -- fed one revolution at a time (OPR time and the
  ``(n_blades, n_probes)`` TOAs); each :meth:`~StreamingProcessor.push` returns the
  per-revolution outputs that became computable, one revolution late (revolution ``n``
  needs OPR ``n + 1`` for its speed), and :meth:`~StreamingProcessor.finish` runs the
  offline pipeline over the stored history (``n_rev x n_blades x n_probes`` floats, small)
  for the final resonance report, so the report is identical to :func:`process_arrays`.

Steps (each in its own module): displacements by Eq. 1 with OPR-based expected times
calibrated on a low-speed window (or the exact expected times of the truth)
(:mod:`.displacement`); data preparation (:mod:`.prep`); windowed sine fits, Eq. 16-17
(:mod:`.fit`); travelling-wave spectra (:mod:`.travelling_wave`); resonance peaks and
E_A / E_f, Eq. 18-19 (:mod:`.resonance`).

The streaming per-revolution fits are computed on the displacements as they come (no
smoothing, which would need future revolutions), with the nominal blade geometry until the
calibration window is complete and calibrated arrival angles afterwards.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from .displacement import (TWO_PI, Displacements, Geometry, calibrate_arrival_angles, compute_displacements,
                           displacements_from_phase, rotor_phase_from_opr)
from .fit import SineFit, design_matrix, fit_revolutions
from .prep import PreparedData, PrepOptions, prepare
from .resonance import (ResonanceReport, TruthPeaks, TruthPeakTracker, find_peaks, resonance_report,
                        truth_peaks as _truth_peaks)
from .travelling_wave import ProbeWave, TravellingWaveSpectra, fit_spectra, identify_nd, probe_spectra

__all__ = ["ProcessOptions", "ProcessingResult", "RevolutionFit", "RevolutionOutput", "StreamingProcessor",
           "process_arrays", "engine_orders_of"]

EXPECTED_TIMES = ("opr", "exact")


@dataclass(frozen=True, slots=True)
class ProcessOptions:
    """Options of the processing.

    Attributes
    ----------
    engine_orders : tuple of int or None
        EOs to fit (the first one is reported); None: the run metadata's
        ``engine_orders`` (the Campbell diagram's choice), else ``(8,)``.
    expected_times : {"opr", "exact"}
        ``"opr"``: from the OPR times and calibrated arrival angles (what a real system
        does); ``"exact"``: the truth's exact expected times (reproduces the paper).
    calibration : int, (start, stop) or None
        Reference window for the arrival angles (int: the first revolutions); None or 0:
        nominal geometry.
    prep : bool
        Data preparation (Sec. 2.3) before the fits of the report.
    prep_options : PrepOptions
    window : int
        Revolutions per sine fit (centred).
    peak_method : {"max", "parabolic", "sdof"}
    """

    engine_orders: tuple | None = None
    expected_times: str = "opr"
    calibration: int | tuple | None = 64
    prep: bool = True
    prep_options: PrepOptions = field(default_factory=PrepOptions)
    window: int = 1
    peak_method: str = "max"

    def __post_init__(self) -> None:
        if self.expected_times not in EXPECTED_TIMES:
            raise ValueError(f"expected_times must be one of {EXPECTED_TIMES}, got {self.expected_times!r}")
        if int(self.window) < 1:
            raise ValueError(f"window must be >= 1, got {self.window}")
        if self.engine_orders is not None:
            eos = tuple(int(e) for e in self.engine_orders)
            if not eos or any(e < 1 for e in eos):
                raise ValueError(f"engine_orders must be positive integers, got {self.engine_orders}")
            object.__setattr__(self, "engine_orders", eos)


def engine_orders_of(info, options: ProcessOptions) -> tuple:
    """The EOs to fit: the options', else the metadata's, else ``(8,)``."""
    if options.engine_orders:
        return tuple(options.engine_orders)
    eos = tuple(int(e) for e in (getattr(info, "engine_orders", None) or ()))
    return tuple(dict.fromkeys(eos)) or (8,)


@dataclass(frozen=True, slots=True, eq=False)
class ProcessingResult:
    """Everything the offline pipeline computed.

    Attributes
    ----------
    geometry : Geometry
    options : ProcessOptions
    engine_orders : tuple of int
    opr_s : ndarray, shape (n_rev,)
    displacements : Displacements
        Raw Eq. 1 displacements.
    prepared : PreparedData or None
    fit : SineFit
        Fits of the prepared displacements (raw when ``prep`` is off).
    probe_tw : TravellingWaveSpectra
        Per revolution and probe, shape (n_rev, n_probes, n_nd), first EO.
    fit_tw : TravellingWaveSpectra
        Per revolution from the fits, shape (n_rev, n_nd), first EO.
    resonance_revolutions : ndarray of bool, shape (n_rev,)
        Where the blade-mean amplitude exceeds half its peak (used to identify the ND).
    report : ResonanceReport
    """

    geometry: Geometry
    options: ProcessOptions
    engine_orders: tuple
    opr_s: np.ndarray
    displacements: Displacements
    prepared: PreparedData | None
    fit: SineFit
    probe_tw: TravellingWaveSpectra
    fit_tw: TravellingWaveSpectra
    resonance_revolutions: np.ndarray
    report: ResonanceReport

    @property
    def summary(self) -> dict:
        """The summary JSON dict of the brief."""
        return self.report.to_summary()


def _as_truth_peaks(truth, engine_order: int) -> TruthPeaks | None:
    if truth is None or isinstance(truth, TruthPeaks):
        return truth
    if isinstance(truth, TruthPeakTracker):
        return truth.peaks()
    return _truth_peaks(truth, engine_order)


def process_arrays(opr_s: np.ndarray, toa_s: np.ndarray, info, options: ProcessOptions = ProcessOptions(),
                   truth=None) -> ProcessingResult:
    """Process a whole run.

    Parameters
    ----------
    opr_s : ndarray, shape (n_rev,)
        OPR times, s.
    toa_s : ndarray, shape (n_rev, n_blades, n_probes)
        TOAs, s (NaN: missing).
    info : Geometry, RunInfo or RunMetadataMsg
        Probe angles, blade count, tip radius, OPR angle (and engine orders).
    options : ProcessOptions
    truth : Truth-like, TruthPeaks or TruthPeakTracker, optional
        For ``expected_times="exact"`` (``truth.t_exp_s``) and for E_A / E_f
        (``truth.d_eqv_pkpk_m``, ``truth.omega_mean``). Never used otherwise.

    Returns
    -------
    ProcessingResult
    """
    geometry = Geometry.from_info(info)
    eos = engine_orders_of(info, options)
    opr = np.asarray(opr_s, dtype=float)
    toa = np.asarray(toa_s, dtype=float)
    if options.expected_times == "exact":
        t_exp = getattr(truth, "t_exp_s", None)
        if t_exp is None:
            raise ValueError('expected_times="exact" needs the truth (its t_exp_s)')
        disp = compute_displacements(opr, toa, geometry, t_exp_s=t_exp)
    else:
        disp = compute_displacements(opr, toa, geometry, calibration=options.calibration)
    prepared = None
    d = disp.d_m
    if options.prep:
        prepared = prepare(d, disp.omega_rad_s, geometry.probe_angles_rad, eos, options.prep_options)
        d = prepared.d_m
    fit = fit_revolutions(d, geometry.probe_angles_rad, eos, omega_rad_s=disp.omega_rad_s,
                          window=options.window)
    eo = eos[0]
    amp = fit.amp_pkpk_m[..., 0]
    peaks = find_peaks(amp, fit.freq_hz[:, 0], method=options.peak_method)
    fit_tw = fit_spectra(fit.phasor[..., 0], eo, geometry.blade_angles_rad)
    probe_tw = probe_spectra(d, eo)
    ok = np.isfinite(amp)
    mean_amp = np.where(ok, amp, 0.0).sum(axis=1) / np.maximum(ok.sum(axis=1), 1)
    res_revs = mean_amp >= 0.5 * mean_amp.max() if mean_amp.size else np.zeros(0, bool)
    nd = identify_nd(fit_tw, res_revs)
    report = resonance_report(peaks, nd=nd, eo=eo, cn=fit.cn, truth=_as_truth_peaks(truth, eo))
    return ProcessingResult(geometry=geometry, options=options, engine_orders=eos, opr_s=opr,
                            displacements=disp, prepared=prepared, fit=fit, probe_tw=probe_tw,
                            fit_tw=fit_tw, resonance_revolutions=res_revs, report=report)


@dataclass(frozen=True, slots=True, eq=False)
class RevolutionFit:
    """One revolution's sine fits of every blade at one engine order (Eq. 16-17): what the
    processor publishes per revolution and EO (``bttsim.v1.BladeFits``).

    Attributes
    ----------
    engine_order : int
    omega_rad_s : float
        Mean speed of the revolution, rad/s.
    freq_hz : float
        ``f_BTT = EO Omega / (2 pi)`` (Eq. 17), Hz.
    cn : float
        Condition number of ``B`` (Eq. 16).
    amp_pkpk_m, phase_rad, dc_m, residual_rms_m, amp_std_m : ndarray, shape (n_blades,)
        Peak-to-peak amplitude (m), phase (rad), DC offset ``a0`` (m), RMS fit residual (m)
        and the amplitude's standard deviation (m).
    """

    engine_order: int
    omega_rad_s: float
    freq_hz: float
    cn: float
    amp_pkpk_m: np.ndarray
    phase_rad: np.ndarray
    dc_m: np.ndarray
    residual_rms_m: np.ndarray
    amp_std_m: np.ndarray

    @property
    def n_blades(self) -> int:
        return int(self.amp_pkpk_m.size)


@dataclass(frozen=True, slots=True, eq=False)
class RevolutionOutput:
    """What the streaming processor emits for one revolution.

    Attributes
    ----------
    revolution : int
    opr_s : float
        The revolution's OPR time, s.
    omega_rad_s : float
        Mean speed of the revolution, rad/s.
    engine_orders : tuple of int
    freq_hz : ndarray, shape (n_eo,)
        ``EO Omega / (2 pi)`` (Eq. 17).
    cn : float
    d_m : ndarray, shape (n_blades, n_probes)
        Eq. 1 displacements (raw).
    amp_pkpk_m, phase_rad, amp_std_m : ndarray, shape (n_blades, n_eo)
    dc_m, residual_rms_m : ndarray, shape (n_blades,)
    probe_tw : TravellingWaveSpectra
        Shape (n_probes, n_nd), first EO.
    fit_tw : TravellingWaveSpectra
        Shape (n_nd,), first EO.
    calibrated : bool
        False while the calibration window is not complete (nominal geometry).
    """

    revolution: int
    opr_s: float
    omega_rad_s: float
    engine_orders: tuple
    freq_hz: np.ndarray
    cn: float
    d_m: np.ndarray
    amp_pkpk_m: np.ndarray
    phase_rad: np.ndarray
    amp_std_m: np.ndarray
    dc_m: np.ndarray
    residual_rms_m: np.ndarray
    probe_tw: TravellingWaveSpectra
    fit_tw: TravellingWaveSpectra
    calibrated: bool

    def fits(self) -> tuple[RevolutionFit, ...]:
        """The revolution's fits, one per engine order (as published)."""
        return tuple(RevolutionFit(
            engine_order=int(eo), omega_rad_s=float(self.omega_rad_s), freq_hz=float(self.freq_hz[i]),
            cn=float(self.cn), amp_pkpk_m=self.amp_pkpk_m[:, i], phase_rad=self.phase_rad[:, i],
            dc_m=self.dc_m, residual_rms_m=self.residual_rms_m, amp_std_m=self.amp_std_m[:, i])
            for i, eo in enumerate(self.engine_orders))

    def probe_waves(self) -> tuple[ProbeWave, ...]:
        """Each probe's travelling-wave spectrum (first EO), labelled with the ND identified
        from the fits of all probes: a single probe cannot tell a wave from its image
        ``2 EO - ND``."""
        nd = int(self.fit_tw.dominant_nd)
        tw = self.probe_tw
        return tuple(ProbeWave(probe=p, forward_m=tw.forward_m[p], backward_m=tw.backward_m[p], nd=nd)
                     for p in range(tw.forward_m.shape[0]))


class _Growable:
    """An array that grows along axis 0 by doubling."""

    def __init__(self, shape_tail: tuple, capacity: int = 1024) -> None:
        self._a = np.full((max(capacity, 4),) + shape_tail, np.nan)
        self.n = 0

    def append(self, row) -> None:
        if self.n == self._a.shape[0]:
            self._a = np.concatenate([self._a, np.full_like(self._a, np.nan)])
        self._a[self.n] = row
        self.n += 1

    def __getitem__(self, i):
        return self._a[: self.n][i]

    @property
    def array(self) -> np.ndarray:
        return self._a[: self.n]


class StreamingProcessor:
    """Process a stream revolution by revolution.

    Parameters
    ----------
    info : Geometry, RunInfo or RunMetadataMsg
    options : ProcessOptions
        ``expected_times`` must be ``"opr"`` (a stream carries no exact expected times).

    Notes
    -----
    Latency: the outputs of revolution ``n`` come out of ``push`` of revolution
    ``n + 1 + window // 2`` (:attr:`latency_revolutions`; revolution 0 waits one more for the
    acceleration of revolution 1, as offline). A gap in the revolution numbers
    (lost messages) is filled with revolutions without arrivals and interpolated OPR times.

    Examples
    --------
    >>> proc = StreamingProcessor(info)                       # doctest: +SKIP
    >>> for n, opr, toa in stream:                            # doctest: +SKIP
    ...     for out in proc.push(n, opr, toa):
    ...         publish(out)
    >>> for out in proc.flush(): publish(out)                 # doctest: +SKIP
    >>> summary = proc.finish(truth_peaks)                    # doctest: +SKIP
    """

    def __init__(self, info, options: ProcessOptions = ProcessOptions()) -> None:
        if options.expected_times != "opr":
            raise ValueError('the streaming processor uses OPR-based expected times (expected_times="opr")')
        self.info = info
        self.options = options
        self.geometry = Geometry.from_info(info)
        self.engine_orders = engine_orders_of(info, options)
        g = self.geometry
        self._shape = (g.n_blades, g.n_probes)
        cap = int(getattr(info, "n_revolutions", 0) or 0) + 8
        self._opr = _Growable((), cap)
        self._toa = _Growable(self._shape, cap)
        self._d = _Growable(self._shape, cap)
        self._omega = _Growable((), cap)
        self._was_calibrated: list[bool] = []
        self._first_rev: int | None = None
        self._n_done = 0  # displacements computed for revolutions [0, _n_done)
        self._n_emitted = 0
        cal = options.calibration
        if not cal:
            self._cal_window = None
        elif isinstance(cal, (int, np.integer)):
            self._cal_window = (0, int(cal))
        else:
            self._cal_window = (int(cal[0]), int(cal[1]))
        self._psi = g.nominal_arrival_angles()
        self._calibrated = False
        self._window = int(options.window)
        self.latency_revolutions = 1 + self._window // 2
        B = design_matrix(g.probe_angles_rad, self.engine_orders)
        self._B = B
        self._pinv = np.linalg.pinv(B) if B.shape[0] >= B.shape[1] else None
        gi = np.linalg.inv(B.T @ B) if self._pinv is not None else None
        i1 = np.arange(1, B.shape[1], 2)
        self._i1 = i1
        self._ginv = None if gi is None else (gi[i1, i1], gi[i1 + 1, i1 + 1], gi[i1, i1 + 1])
        self._g12x2 = None if gi is None else 2.0 * gi[i1, i1 + 1]
        self._cn = float(np.linalg.cond(B))
        self._eo_arr = np.asarray(self.engine_orders, float)
        npr, p = B.shape
        self._pinvT = None if self._pinv is None else np.ascontiguousarray(self._pinv.T)
        self._BT = np.ascontiguousarray(B.T)
        self._inv_dof = 1.0 / (npr - p) if npr > p else math.nan
        self._residual = None if self._pinv is None else np.eye(npr) - self._pinv.T @ B.T
        self._freq_per_omega = self._eo_arr / TWO_PI
        self._F_probe, self._F_fit, self._n_nd = _spectrum_matrices(g, self.engine_orders[0])
        self._solvers: dict = {}
        self._finished = False
        self.result: ProcessingResult | None = None
        self.last_outputs: list[RevolutionOutput] = []

    # -- input ---------------------------------------------------------------------------
    def push(self, revolution: int, opr_s: float, toa_s: np.ndarray) -> list[RevolutionOutput]:
        """Add one revolution; return the per-revolution outputs now computable.

        Parameters
        ----------
        revolution : int
            Revolution number (consecutive; a gap is filled, a repeat or step back raises).
        opr_s : float
            The revolution's OPR time, s.
        toa_s : ndarray, shape (n_blades, n_probes)
            TOAs, s (NaN: missing).
        """
        if self._finished:
            raise RuntimeError("push after finish")
        toa = np.asarray(toa_s, dtype=float)
        if toa.shape != self._shape:
            raise ValueError(f"toa_s must have shape {self._shape}, got {toa.shape}")
        revolution = int(revolution)
        if self._first_rev is None:
            self._first_rev = revolution
        expected = self._first_rev + self._opr.n
        if revolution < expected:
            raise ValueError(f"revolution {revolution} pushed after revolution {expected - 1}")
        if revolution > expected:  # lost revolutions: no arrivals, OPR times interpolated
            last = self._opr[self._opr.n - 1]
            gap = revolution - expected
            for k in range(1, gap + 1):
                self._opr.append(last + (float(opr_s) - last) * k / (gap + 1))
                self._toa.append(np.full(self._shape, np.nan))
        self._opr.append(float(opr_s))
        self._toa.append(toa)
        out = []
        # revolution k needs OPR k+1 for its speed (and revolution 0 also OPR 2, for the
        # acceleration of revolution 1)
        while self._n_done < self._opr.n - 1 and (self._n_done > 0 or self._opr.n >= 3):
            self._displace(self._n_done, final=False)
            self._n_done += 1
            out.extend(self._emit_ready(final=False))
        return out

    def flush(self) -> list[RevolutionOutput]:
        """Outputs of the revolutions still pending at the end of the stream (the last
        revolution uses an extrapolated speed)."""
        out = []
        while self._opr.n >= 2 and self._n_done < self._opr.n:
            self._displace(self._n_done, final=self._n_done == self._opr.n - 1)
            self._n_done += 1
        out.extend(self._emit_ready(final=True))
        return out

    def finish(self, truth_peaks=None) -> dict:
        """Final resonance report over the whole history (the offline pipeline).

        Parameters
        ----------
        truth_peaks : TruthPeaks, TruthPeakTracker or Truth-like, optional
            Only for E_A and E_f.

        Returns
        -------
        dict
            The brief's summary JSON dict; the full :class:`ProcessingResult` is kept in
            :attr:`result`. Outputs still pending when :meth:`flush` was not called are kept
            in :attr:`last_outputs`.
        """
        if not self._finished:
            self.last_outputs = self.flush()
            self._finished = True
        if self._opr.n < 3:
            raise ValueError("at least three revolutions are needed for a resonance report")
        opts = self.options
        self.result = process_arrays(self._opr.array, self._toa.array, self.geometry,
                                     _with_eos(opts, self.engine_orders),
                                     truth=_as_truth_peaks(truth_peaks, self.engine_orders[0]))
        return self.result.summary

    # -- per revolution -------------------------------------------------------------------
    def _displace(self, k: int, final: bool) -> None:
        """Eq. 1 of revolution ``k`` with the offline pipeline's rotor phase: the quadratic
        model through OPR pulses ``k-1, k, k+1`` (revolution 0 takes revolution 1's
        acceleration; the last one, at the end, an extrapolated speed), so that the streamed
        displacements are the offline ones."""
        opr = self._opr.array
        if self._cal_window is not None and not self._calibrated and k + 1 >= self._cal_window[1]:
            # the same arrival angles as offline: the window's phase model from its OPRs
            stop = self._cal_window[1]
            n_opr = min(stop + 1, self._opr.n)
            phase = rotor_phase_from_opr(opr[:n_opr])
            psi = calibrate_arrival_angles(phase, self._toa.array[:n_opr], self._cal_window)
            self._psi = np.where(np.isfinite(psi), psi, self._psi)
            self._calibrated = True
        lo = max(0, k - 2) if final else max(0, k - 1)
        row = k - lo
        hi = k + 1 if final else max(k + 2, 3)
        fast = _phase_row(opr, lo, hi, row)
        if fast is None:  # a degenerate OPR window (e.g. repeated pulses): the array code
            phase = rotor_phase_from_opr(opr[lo:hi]).rows(slice(row, row + 1))
            d, _ = displacements_from_phase(phase, self._toa.array[k][None], self._psi, self.geometry.tip_radius_m)
            d, om = d[0], float(phase.omega_mean_rad_s[0])
        else:
            d, om = _displacement_row(float(opr[k]), *fast, self._toa.array[k], self._psi,
                                      self.geometry.tip_radius_m)
        self._d.append(d)
        self._omega.append(om)
        self._was_calibrated.append(self._calibrated or self._cal_window is None)

    def _solver(self, present: tuple):
        """Pseudo-inverse and covariance terms of ``B`` restricted to the present probes
        (cached per pattern of missing probes); None if they cannot separate the unknowns."""
        if present not in self._solvers:
            Bp = self._B[list(present)]
            npr, p = Bp.shape
            if npr < p or np.linalg.cond(Bp) > 1e10:
                self._solvers[present] = None
            else:
                gi = np.linalg.inv(Bp.T @ Bp)
                i1 = self._i1
                self._solvers[present] = (np.linalg.pinv(Bp).T, np.ascontiguousarray(Bp.T),
                                          (gi[i1, i1], gi[i1 + 1, i1 + 1], gi[i1, i1 + 1]), npr, p)
        return self._solvers[present]

    def _fit_patterns(self, d_k: np.ndarray):
        """Window-1 fits of one revolution with missing samples: complete blades through the
        shared pseudo-inverse, the others one by one (solvers cached per pattern)."""
        ok = ~np.isnan(d_k)
        full = ok.all(axis=1)
        a = np.where(ok, d_k, 0.0) @ self._pinvT
        r = np.where(ok, d_k, 0.0) - a @ self._BT
        rss = (r * r).sum(axis=1)
        s2 = rss * self._inv_dof
        n_used = np.full(d_k.shape[0], float(self._B.shape[0]))
        g = [np.repeat(gt[None, :], d_k.shape[0], axis=0) for gt in self._ginv]
        for b in np.flatnonzero(~full):
            present = tuple(np.flatnonzero(ok[b]).tolist())
            sol = self._solver(present)
            n_used[b] = max(len(present), 1)
            if sol is None:
                a[b], rss[b], s2[b] = np.nan, np.nan, np.nan
                continue
            pinvT, BT, gi, n, q = sol
            x = d_k[b, list(present)]
            a[b] = x @ pinvT
            rb = x - a[b] @ BT
            rss[b] = rb @ rb
            s2[b] = rss[b] / (n - q) if n > q else np.nan
            for t in range(3):
                g[t][b] = gi[t]
        return a, rss, s2, g[0], g[1], g[2], n_used

    def _emit_ready(self, final: bool) -> list[RevolutionOutput]:
        out = []
        half_after = self._window // 2
        while self._n_emitted < self._n_done and (final or self._n_emitted + half_after < self._n_done):
            out.append(self._output(self._n_emitted))
            self._n_emitted += 1
        return out

    def _output(self, k: int) -> RevolutionOutput:
        d_k = self._d.array[k]
        w = self._window
        eo = self.engine_orders[0]
        om = float(self._omega[k])
        if w == 1 and self._pinv is not None:
            # the fit and both spectra as a few small matrix products (precomputed)
            missing = np.isnan(d_k.sum())
            if missing:
                a, rss, s2, g11, g22, g12, n_used = self._fit_patterns(d_k)
                g12x2 = 2.0 * g12
            else:
                a = d_k @ self._pinvT  # (nb, p)
                r = d_k @ self._residual  # (I - B B^+) applied to each blade's samples
                rss = (r * r).sum(axis=1)
                s2 = rss * self._inv_dof
                g11, g22, g12 = self._ginv
                g12x2 = self._g12x2
                n_used = self._B.shape[0]
            a1, a2 = a[:, 1::2], a[:, 2::2]
            amp2 = a1 * a1 + a2 * a2
            num = a1 * (g11 * a1 + g12x2 * a2) + g22 * a2 * a2  # (a1, a2) G (a1, a2)^T
            amp = np.sqrt(amp2)
            if not amp2.all():  # no direction: the mean of the two variances
                zero = amp2 == 0
                num = np.where(zero, 0.5 * (g11 + g22), num)
                amp2 = np.where(zero, 1.0, amp2)
            amp_pkpk, phase = 2.0 * amp, np.arctan2(a2, a1)
            amp_std = 2.0 * np.sqrt(s2[:, None] * num / amp2)
            dc, res = a[:, 0], np.sqrt(rss / n_used)
            phasor = a[:, 1] + 1j * a[:, 2]
            nb = self.geometry.n_blades
            if missing:  # the conventions of probe_spectra / fit_spectra for NaN
                okd = ~np.isnan(d_k)
                cnt = okd.sum(axis=0)
                mean = np.where(cnt > 0, np.where(okd, d_k, 0.0).sum(axis=0) / np.maximum(cnt, 1), 0.0)
                X = np.abs(np.where(okd, d_k, mean).T @ self._F_probe)
                okp = ~np.isnan(phasor)
                n_ok = int(okp.sum())
                Q = np.abs(np.where(okp, phasor, 0.0) @ self._F_fit) * (nb / n_ok if n_ok else np.nan)
            else:
                X = np.abs(d_k.T @ self._F_probe)  # (n_probes, 2 n_nd)
                Q = np.abs(phasor @ self._F_fit)  # (2 n_nd,)
            n_nd = self._n_nd
            probe_tw = TravellingWaveSpectra(X[:, :n_nd], X[:, n_nd:], nb)
            fit_tw = TravellingWaveSpectra(Q[:n_nd], Q[n_nd:], nb)
        else:
            lo = max(0, k - (w - 1) // 2)
            hi = min(self._d.n, k + w // 2 + 1)
            f = fit_revolutions(self._d.array[lo:hi], self.geometry.probe_angles_rad, self.engine_orders,
                                window=w)
            i = k - lo
            amp_pkpk, phase, amp_std = f.amp_pkpk_m[i], f.phase_rad[i], f.amp_std_m[i]
            dc, res = f.dc_m[i], f.residual_rms_m[i]
            phasor = f.phasor[i, :, 0]
            probe_tw = probe_spectra(d_k, eo)
            fit_tw = fit_spectra(phasor, eo, self.geometry.blade_angles_rad)
        return RevolutionOutput(
            revolution=self._first_rev + k, opr_s=float(self._opr[k]), omega_rad_s=om,
            engine_orders=self.engine_orders, freq_hz=om * self._freq_per_omega, cn=self._cn,
            d_m=d_k, amp_pkpk_m=amp_pkpk, phase_rad=phase, amp_std_m=amp_std, dc_m=dc,
            residual_rms_m=res, probe_tw=probe_tw, fit_tw=fit_tw, calibrated=self._was_calibrated[k])


def _phase_row(opr: np.ndarray, lo: int, hi: int, row: int):
    """Rotor phase of row ``row`` of ``rotor_phase_from_opr(opr[lo:hi])`` (2 or 3 pulses), as
    Python floats ``(omega0, alpha, omega_mean)``, by the same floating-point operations in the
    same order (so the streamed displacements stay the offline ones bit for bit); None when
    the window is degenerate (the array code then handles it)."""
    o = opr[lo:hi].tolist()
    n = len(o)
    try:
        om = [TWO_PI / (o[j + 1] - o[j]) for j in range(n - 1)]  # mean_speed_from_opr
        om.append(2.0 * om[-1] - om[-2] if len(om) >= 2 else om[-1])
        period = [TWO_PI / w for w in om]

        def coeff(s_, t_):  # _phase_coefficients
            alpha = 2.0 * TWO_PI * (s_ - t_) / (t_ * s_ * (t_ + s_))
            if not math.isfinite(alpha):
                alpha = 0.0
            return (TWO_PI - 0.5 * alpha * t_ * t_) / t_, alpha

        if row == 0:  # the first revolution takes the second one's acceleration
            alpha = coeff(period[0], period[1])[1] if n >= 2 else 0.0
            w0 = (TWO_PI - 0.5 * alpha * period[0] ** 2) / period[0]
        else:
            w0, alpha = coeff(period[row - 1], period[row])
    except (ZeroDivisionError, OverflowError, IndexError):
        return None
    if not all(math.isfinite(v) for v in (w0, alpha, om[row])):
        return None
    return w0, alpha, om[row]


def _displacement_row(opr_k: float, w0: float, alpha: float, om: float, toa: np.ndarray, psi: np.ndarray,
                      tip_radius_m: float) -> tuple[np.ndarray, float]:
    """Eq. 1 displacements of one revolution: :func:`displacements_from_phase` of one row,
    with the rotor phase as scalars (the same operations in the same order)."""
    tau = toa - opr_k
    ang = tau * (w0 + 0.5 * alpha * tau)  # RotorPhase.angle
    k = np.round((ang - psi) / TWO_PI)
    a = psi + TWO_PI * np.where(np.isfinite(k), k, 0.0)
    tau_exp = 2.0 * a / (w0 + np.sqrt(w0 * w0 + 2.0 * alpha * a))  # RotorPhase.delay_at_angle
    return (om * float(tip_radius_m)) * (tau_exp - tau), om


def _spectrum_matrices(g: Geometry, eo: int) -> tuple[np.ndarray, np.ndarray, int]:
    """The DFT columns of :func:`probe_spectra` and :func:`fit_spectra` as matrices, so that
    a complete revolution's spectra are two matrix products (forward then backward ND)."""
    nb = g.n_blades
    n_nd = nb // 2 + 1
    nd = np.arange(n_nd)
    b = np.arange(nb)
    scale = np.full(nb, 4.0 / nb)
    scale[0] = 2.0 / nb
    if nb % 2 == 0:
        scale[nb // 2] = 2.0 / nb
    bins_f, bins_b = (nd - eo) % nb, (-nd - eo) % nb
    F = np.exp(-2j * np.pi * np.outer(b, np.arange(nb)) / nb) * scale[None, :]
    F_probe = np.concatenate([F[:, bins_f], F[:, bins_b]], axis=1)
    rot = np.exp(1j * eo * g.blade_angles_rad)[:, None]
    G = rot * np.exp(-2j * np.pi * np.outer(b, np.arange(nb)) / nb) * (2.0 / nb)
    F_fit = np.concatenate([G[:, nd % nb], G[:, (-nd) % nb]], axis=1)
    return F_probe, F_fit, n_nd


def _with_eos(options: ProcessOptions, eos: tuple) -> ProcessOptions:
    return replace(options, engine_orders=tuple(eos))

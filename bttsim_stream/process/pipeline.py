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

from .detect import (Crossing, DetectOptions, Reference, RunSegments, choose_reference, detect_crossings,
                     predicted_contamination, predicted_response, resolve_engine_orders, speed_segments)
from .displacement import (TWO_PI, Displacements, Geometry, calibrate_arrival_angles, compute_displacements,
                           displacements_from_phase, rotor_phase_from_opr)
from .fit import SineFit, design_matrix, fit_revolutions
from .methods import METHODS, cff_method, cff_window, peak_method, sdof_method
from .nsv import (NsvDetection, NsvOptions, NsvScan, detect_nsv, detections, nsv_note, nsv_truth_rows, scan_blocks,
                  score_nsv, screen_block)
from .prep import PreparedData, PrepOptions, ResonanceRegion, prepare, smoothing_gain
from .probes import CN_SINGULAR, LayoutError, condition_number
from .resonance import (PEAK_METHODS, Detection, ResonanceEntry, ResonancePeaks, ResonanceReport, TruthPeaks,
                        TruthPeakTracker, TruthRows, find_peaks, window_truth)
from .travelling_wave import ProbeWave, TravellingWaveSpectra, fit_spectra, identify_nd, probe_spectra

__all__ = ["ProcessOptions", "ProcessingResult", "RevolutionFit", "RevolutionOutput", "StreamingProcessor",
           "process_arrays", "engine_orders_of", "METHODS"]

EXPECTED_TIMES = ("opr", "exact")
#: Calibration window of the streaming processor's live outputs when the final report's is
#: chosen automatically (the live outputs cannot wait for the whole run).
LIVE_CALIBRATION = 64
#: Joint fits of several engine orders are used when their condition number is below this;
#: above, each order is fitted on its own (and the orders are told apart by their residuals).
CN_JOINT_MAX = 100.0
#: The data preparation's baseline is fitted where every crossing's predicted response is below
#: this fraction of its peak (the skirts of the resonances are not offsets).
SKIRT_LEVEL = 0.1


@dataclass(frozen=True, slots=True)
class ProcessOptions:
    """Options of the processing.

    Attributes
    ----------
    engine_orders : tuple of int or None
        EOs to fit; None: the run metadata's ``engine_orders`` (the Campbell diagram's
        choice), else ``(8,)``.
    eo_range : (int, int) or None
        When the EO is not known: scan every EO ``lo .. hi`` (each fitted on its own) for
        crossings; overrides ``engine_orders`` for the final report.
    expected_times : {"opr", "exact"}
        ``"opr"``: from the OPR times and calibrated arrival angles (what a real system
        does); ``"exact"``: the truth's exact expected times (reproduces the paper).
    calibration : "auto", int, (start, stop) or None
        Reference (zeroing) window of the arrival angles. ``"auto"``: chosen away from every
        detected resonance (:func:`~bttsim_stream.process.detect.choose_reference`); int: the
        first revolutions; (start, stop): those; None or 0: nominal geometry.
    prep : bool
        Data preparation (Sec. 2.3) before the fits of the report.
    prep_options : PrepOptions
    window : int
        Revolutions per sine fit (centred).
    method : {"peak", "sdof", "cff"}
        Resonance method (:mod:`~bttsim_stream.process.methods`).
    peak_method : {"max", "parabolic", "sdof"}
        Refinement of the ``"peak"`` method (legacy: ``"sdof"`` here is an amplitude-only
        curve fit without uncertainty; the method ``"sdof"`` is the swept complex fit).
    detect : DetectOptions
        Segmentation, detection thresholds, reference window.
    sampling_angles : bool
        Fit each sample at its sampling angle ``theta_j - d_j / R`` rather than at the probe
        angle (:mod:`~bttsim_stream.process.fit`); the per-revolution streaming outputs
        always use the probe angles.
    nsv : NsvOptions
        Non-synchronous vibration detection (:mod:`~bttsim_stream.process.nsv`).
    """

    engine_orders: tuple | None = None
    eo_range: tuple | None = None
    expected_times: str = "opr"
    calibration: int | tuple | str | None = "auto"
    prep: bool = True
    prep_options: PrepOptions = field(default_factory=PrepOptions)
    window: int = 1
    method: str = "peak"
    peak_method: str = "max"
    detect: DetectOptions = field(default_factory=DetectOptions)
    sampling_angles: bool = True
    nsv: NsvOptions = field(default_factory=NsvOptions)

    def __post_init__(self) -> None:
        if self.expected_times not in EXPECTED_TIMES:
            raise ValueError(f"expected_times must be one of {EXPECTED_TIMES}, got {self.expected_times!r}")
        if int(self.window) < 1:
            raise ValueError(f"window must be >= 1, got {self.window}")
        if self.method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {self.method!r}")
        if self.peak_method not in PEAK_METHODS:
            raise ValueError(f"peak_method must be one of {PEAK_METHODS}, got {self.peak_method!r}")
        if self.engine_orders is not None:
            eos = tuple(int(e) for e in self.engine_orders)
            if not eos or any(e < 1 for e in eos):
                raise ValueError(f"engine_orders must be positive integers, got {self.engine_orders}")
            object.__setattr__(self, "engine_orders", eos)
        if self.eo_range is not None:
            lo, hi = (int(v) for v in self.eo_range)
            if lo < 1 or hi < lo:
                raise ValueError(f"eo_range must be (lo, hi) with 1 <= lo <= hi, got {self.eo_range}")
            if hi - lo > 200:
                raise ValueError(f"eo_range spans {hi - lo + 1} engine orders (at most 201)")
            object.__setattr__(self, "eo_range", (lo, hi))
        cal = self.calibration
        if isinstance(cal, str) and cal != "auto":
            raise ValueError(f'calibration must be "auto", an int, (start, stop) or None, got {cal!r}')


def engine_orders_of(info, options: ProcessOptions) -> tuple:
    """The EOs of the per-revolution fits: the options', else the metadata's, else ``(8,)``."""
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
        The orders of :attr:`fit` (after a scan: those with a crossing).
    opr_s : ndarray, shape (n_rev,)
    displacements : Displacements
        Raw Eq. 1 displacements (zeroed on :attr:`reference`).
    prepared : PreparedData or None
    fit : SineFit
        Fits of the prepared displacements (raw when ``prep`` is off).
    probe_tw : TravellingWaveSpectra
        Per revolution and probe, shape (n_rev, n_probes, n_nd), first EO.
    fit_tw : TravellingWaveSpectra
        Per revolution from the fits, shape (n_rev, n_nd), first EO.
    resonance_revolutions : ndarray of bool, shape (n_rev,)
        The half-power regions of the first EO's crossings (or, without any, where the
        blade-mean amplitude exceeds half its peak).
    report : ResonanceReport
    segments : RunSegments
    crossings : tuple of Crossing
    reference : Reference or None
    joint : bool
        Whether the engine orders were fitted jointly.
    nsv_scan : NsvScan or None
        Every block's non-synchronous analysis (:mod:`~bttsim_stream.process.nsv`).
    nsv : tuple of NsvDetection
        The non-synchronous vibrations detected (also in :attr:`report`).
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
    segments: RunSegments | None = None
    crossings: tuple = ()
    reference: Reference | None = None
    joint: bool = True
    nsv_scan: NsvScan | None = None
    nsv: tuple = ()

    @property
    def summary(self) -> dict:
        """The summary JSON dict of the brief."""
        return self.report.to_summary()


def _as_truth_peaks(truth, engine_order: int) -> TruthPeaks | None:
    """Legacy helper: the global truth peaks of a truth-like object."""
    from .resonance import truth_peaks as _truth_peaks

    if truth is None or isinstance(truth, TruthPeaks):
        return truth
    if isinstance(truth, TruthPeakTracker):
        return truth.peaks()
    return _truth_peaks(truth, engine_order)


def _truth_rows(truth, n_rev: int, revolution0: int):
    """Per-revolution truth rows (or TruthPeaks) for :func:`window_truth`."""
    if truth is None:
        return None
    if isinstance(truth, TruthPeakTracker):
        rows = truth.rows(revolution0, n_rev)
        return rows if rows is not None else None
    if isinstance(truth, (TruthPeaks, TruthRows)):
        return truth
    pk = getattr(truth, "d_eqv_pkpk_m", None)
    om = getattr(truth, "omega_mean", None)
    if pk is None or om is None:
        return None
    pk, om = np.asarray(pk, float), np.asarray(om, float)
    if pk.shape[0] != n_rev:
        raise ValueError(f"the truth has {pk.shape[0]} revolutions, the data {n_rev}")
    return TruthRows(d_eqv_pkpk_m=pk, omega_mean=om)


def _fit(d: np.ndarray, angles, eos: tuple, joint: bool, omega, window: int, radius: float | None = None) -> SineFit:
    """Eq. 16 fits of every order, jointly or one order at a time (stacked as one SineFit);
    ``radius``: at the sampling angles (:func:`~bttsim_stream.process.fit.fit_revolutions`)."""
    if joint or len(eos) == 1:
        return fit_revolutions(d, angles, eos, omega_rad_s=omega, window=window, tip_radius_m=radius)
    fits = [fit_revolutions(d, angles, (eo,), omega_rad_s=omega, window=window, tip_radius_m=radius) for eo in eos]
    coeffs = np.concatenate([fits[0].coeffs[..., :1]] + [f.coeffs[..., 1:] for f in fits], axis=-1)
    cat = lambda name: np.concatenate([getattr(f, name) for f in fits], axis=-1)  # noqa: E731
    return SineFit(engine_orders=tuple(eos), window=window, coeffs=coeffs, amp_pkpk_m=cat("amp_pkpk_m"),
                   phase_rad=cat("phase_rad"), amp_std_m=cat("amp_std_m"), dc_m=fits[0].dc_m,
                   residual_rms_m=fits[0].residual_rms_m, n_samples=fits[0].n_samples,
                   omega_rad_s=fits[0].omega_rad_s, freq_hz=None if fits[0].freq_hz is None else cat("freq_hz"),
                   cn=max(f.cn for f in fits))


def _merge_spans(spans) -> list:
    """Sorted, non-overlapping ``[start, stop)`` revolution spans."""
    out: list = []
    for a, b in sorted(spans):
        if out and a <= out[-1][1]:
            out[-1] = (out[-1][0], max(out[-1][1], b))
        else:
            out.append((a, b))
    return out


def _fit_spans(d: np.ndarray, angles, eos: tuple, joint: bool, omega, window: int, radius, spans) -> SineFit:
    """Fits at the probe angles everywhere and, inside ``spans`` (the crossings and dwells,
    where results are read), at the sampling angles. Outside them the response is small, and
    the two agree (the correction is proportional to the displacement)."""
    fit = _fit(d, angles, eos, joint, omega, window, None)
    if radius is None or not spans:
        return fit
    arrays = {k: getattr(fit, k).copy() for k in ("coeffs", "amp_pkpk_m", "phase_rad", "amp_std_m", "dc_m",
                                                    "residual_rms_m", "n_samples")}
    h = window // 2
    n = d.shape[0]
    for a, b in spans:
        lo, hi = max(0, a - h), min(n, b + h)
        f = _fit(d[lo:hi], angles, eos, joint, omega[lo:hi], window, radius)
        for k, arr in arrays.items():
            arr[a:b] = getattr(f, k)[a - lo:b - lo]
    return replace(fit, **arrays)


def _column_median(d: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
    x = d if rows is None else d[rows]
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        med = np.nanmedian(x, axis=0)
    return np.where(np.isfinite(med), med, 0.0)


def _layout_cns(eos, geometry: Geometry, scan: bool) -> tuple[tuple, dict, list]:
    """Per-EO condition numbers; a singular order is an error (a scan skips it)."""
    deg = np.rad2deg(geometry.probe_angles_rad)
    cns, keep, notes = {}, [], []
    for eo in eos:
        cn = condition_number(eo, deg) if geometry.n_probes >= 3 else math.inf
        if not cn < CN_SINGULAR:
            msg = (f"the probe layout ({', '.join(f'{a:g}' for a in np.mod(deg, 360.0))} deg) cannot separate "
                   f"EO {eo} (condition number {cn:.3g}): add or move probes")
            if not scan:
                raise LayoutError(msg)
            notes.append(msg)
            continue
        cns[eo] = cn
        keep.append(eo)
    if not keep:
        raise LayoutError(notes[0] if notes else "no engine order to fit")
    return tuple(keep), cns, notes


def process_arrays(opr_s: np.ndarray, toa_s: np.ndarray, info, options: ProcessOptions = ProcessOptions(),
                   truth=None, *, revolution0: int = 0) -> ProcessingResult:
    """Process a whole run: find every resonance crossing and dwell, and report them.

    Parameters
    ----------
    opr_s : ndarray, shape (n_rev,)
        OPR times, s.
    toa_s : ndarray, shape (n_rev, n_blades, n_probes)
        TOAs, s (NaN: missing).
    info : Geometry, RunInfo or RunMetadataMsg
        Probe angles, blade count, tip radius, OPR angle (and engine orders).
    options : ProcessOptions
    truth : Truth-like, TruthRows, TruthPeaks or TruthPeakTracker, optional
        For ``expected_times="exact"`` (``truth.t_exp_s``) and for E_A / E_f
        (``truth.d_eqv_pkpk_m``, ``truth.omega_mean``). Never used otherwise.
    revolution0 : int
        Number of the first revolution (for the report's revolution numbers and a tracker's
        truth).

    Returns
    -------
    ProcessingResult

    Raises
    ------
    LayoutError
        The probes cannot separate an engine order (a ``ValueError``).
    ValueError
        Fewer than three revolutions, inconsistent shapes, exact times without the truth.

    Notes
    -----
    Steps: Eq. 1 displacements on the nominal geometry, zeroed on the run's median, and
    their Eq. 16 fits (a first pass); speed segments, crossings per engine order
    (:mod:`.detect`); the zeroing reference away from every crossing and Eq. 1 again;
    data preparation with the crossings left out of the baseline; Eq. 16 fits; per crossing
    the chosen method (:mod:`.methods`), per dwell the steady-state mean; errors against
    the truth attributable to each (:func:`~bttsim_stream.process.resonance.window_truth`).
    """
    geometry = Geometry.from_info(info)
    opr = np.asarray(opr_s, dtype=float)
    toa = np.asarray(toa_s, dtype=float)
    n_rev = opr.size
    if n_rev < 3:
        raise ValueError(f"at least three revolutions are needed for a resonance report, got {n_rev}")
    det = options.detect
    scan = options.eo_range is not None
    eos_asked = tuple(range(options.eo_range[0], options.eo_range[1] + 1)) if scan else engine_orders_of(info, options)
    eos_asked, cns, notes = _layout_cns(eos_asked, geometry, scan)
    notes = list(notes)
    angles = geometry.probe_angles_rad
    joint = (not scan and len(eos_asked) > 1 and geometry.n_probes >= 1 + 2 * len(eos_asked)
             and condition_number(eos_asked, np.rad2deg(angles)) < CN_JOINT_MAX)
    if len(eos_asked) > 1 and not scan and not joint:
        notes.append(f"EO {'+'.join(map(str, eos_asked))} cannot be fitted jointly with these probes: each order "
                     f"is fitted on its own and their responses leak into each other")
    rows_truth = _truth_rows(truth, n_rev, revolution0)
    t_exp = None
    if options.expected_times == "exact":
        t_exp = getattr(truth, "t_exp_s", None)
        if t_exp is None:
            raise ValueError('expected_times="exact" needs the truth (its t_exp_s)')
    # 1. first pass: nominal geometry (or exact times) zeroed on the run's median
    first = compute_displacements(opr, toa, geometry, t_exp_s=t_exp, calibration=None)
    omega = first.omega_rad_s
    d0 = first.d_m - _column_median(first.d_m)[None]
    fit0 = _fit(d0, angles, eos_asked, joint, omega, 1)
    segments = speed_segments(opr, omega, det)
    crossings: list[Crossing] = []
    for i, eo in enumerate(eos_asked):
        crossings += detect_crossings(fit0.amp_pkpk_m[..., i], eo, segments, det)
    if len(eos_asked) > 1 and not joint:
        crossings = resolve_engine_orders(crossings, _misfits(d0, angles, eos_asked, fit0))
    psi0 = first.arrival_angles_rad if first.arrival_angles_rad is not None else geometry.nominal_arrival_angles()
    nsv_scan, nsv = detect_nsv(d0, omega, psi0, options.nsv, revolution0=revolution0)
    nsv_truth = (truth.nsv_rows(revolution0, n_rev) if isinstance(truth, TruthPeakTracker)
                 else nsv_truth_rows(truth, n_rev))
    if nsv and nsv_truth is not None:  # scored only: the truth never steers the processing
        nsv = tuple(replace(n, truth=score_nsv(n, nsv_truth, revolution0)) for n in nsv)
    if nsv:
        crossings = _not_nsv(crossings, nsv, revolution0, omega, notes)
    crossings = _separate(crossings)
    eos = tuple(sorted({c.eo for c in crossings})) if scan else eos_asked
    if scan and not eos:
        eos = (_best_dwell_eo(fit0, eos_asked, segments) or eos_asked[0],)
    if scan:
        joint = len(eos) > 1 and geometry.n_probes >= 1 + 2 * len(eos) and \
            condition_number(eos, np.rad2deg(angles)) < CN_JOINT_MAX
    # 2. zeroing reference, Eq. 1 again
    reference = None
    cal = options.calibration
    if t_exp is not None:
        disp = first
        ref_info = {"method": "exact", "first": None, "last": None, "contamination_pct": None,
                    "reason": "the truth's exact expected arrival times"}
    elif cal is None or cal is False or (isinstance(cal, (int, np.integer)) and int(cal) == 0):
        disp = first
        ref_info = {"method": "nominal", "first": None, "last": None, "contamination_pct": None,
                    "reason": "nominal geometry (calibration off)"}
    elif cal == "auto":
        reference = choose_reference(omega, segments, crossings, det)
        if reference.start is None:
            disp = first
            ref_info = {"method": "nominal", "first": None, "last": None, "contamination_pct": None,
                        "reason": reference.reason}
        else:
            disp = compute_displacements(opr, toa, geometry, calibration=(reference.start, reference.stop))
            ref_info = {"method": "calibrated", "first": revolution0 + reference.start,
                        "last": revolution0 + reference.stop - 1,
                        "contamination_pct": _num(100.0 * reference.contamination), "reason": reference.reason}
            if crossings and reference.contamination > det.contamination_limit:
                notes.append(f"no quiet reference window: the zeroing holds a response of about "
                             f"{100 * reference.contamination:.0f} % of a peak, estimated from the response's growth "
                             f"and added back (each resonance's zeroing_correction_pct)")
    else:
        disp = compute_displacements(opr, toa, geometry, calibration=cal)
        w = (0, int(cal)) if isinstance(cal, (int, np.integer)) else (int(cal[0]), int(cal[1]))
        ref_info = {"method": "calibrated", "first": revolution0 + w[0], "last": revolution0 + min(w[1], n_rev) - 1,
                    "contamination_pct": None, "reason": "the window given in the options"}
    # 3. data preparation with every crossing (and dwell) out of the baseline: the baseline
    # (offsets slowly varying with speed) is fitted where no crossing's response is predicted
    # above the reference's limit, so it does not take the forced response's skirts
    dwell_mask = segments.dwell_mask(n_rev)
    skirts = predicted_contamination(omega, crossings) > SKIRT_LEVEL
    prepared = None
    d = disp.d_m
    hw = _half_widths(omega, crossings, options.prep_options)
    if options.prep:
        region = _region(fit0.amp_pkpk_m, crossings, n_rev)
        prep_opts = options.prep_options
        bridge = _baseline_bridges(omega, ~(dwell_mask | skirts | region.mask.any(axis=1)))
        if prep_opts.remove_offset and crossings and not bridge:
            prep_opts = replace(prep_opts, remove_offset=False)
            notes.append("no offset removal: the run holds too little data on both sides of the crossings for a "
                         "baseline in speed to bridge them (the zeroing reference alone is used)")
        prepared = prepare(d, omega, angles, eos, prep_opts, region=region, half_width=hw,
                           exclude_revolutions=dwell_mask | skirts)
        d = prepared.d_m
    radius = geometry.tip_radius_m if options.sampling_angles else None
    spans = _merge_spans([(c.lo, c.hi + 1) for c in crossings] + [(dw.start, dw.stop) for dw in segments.dwells])
    fit = _fit_spans(d, angles, eos, joint, omega, options.window, radius, spans)
    d_flat = disp.d_m - (prepared.offset_m if prepared is not None else 0.0)  # offset removed, unsmoothed
    if (prepared is None or not options.prep_options.smooth) and options.window == 1:
        raw = _Raw(fit.amp_pkpk_m, fit.phasor)
    else:  # unsmoothed fits, only where a crossing or a dwell needs them (noise, SDOF)
        amp_r = np.full(fit.amp_pkpk_m.shape, np.nan)
        ph_r = np.full(fit.amp_pkpk_m.shape, np.nan + 0j)
        for a, b in spans:
            f_r = _fit(d_flat[a:b], angles, eos, joint, omega[a:b], 1, radius)
            amp_r[a:b], ph_r[a:b] = f_r.amp_pkpk_m, f_r.phasor
        raw = _Raw(amp_r, ph_r)
    # 4. per crossing and per dwell
    gain_w = 1.0 / (omega * omega) if options.prep_options.noise_weighting else None
    ctx = _Context(geometry=geometry, eos=eos, joint=joint, cns=cns, fit=fit, raw=raw, d_flat=d_flat, omega=omega,
                   opr=opr, toa=toa, half_width=(prepared.half_width if prepared is not None else None),
                   gain_weights=gain_w, truth=rows_truth, revolution0=revolution0, options=options,
                   reference=reference, crossings=tuple(crossings),
                   offset_removed=bool(prepared is not None and prepared.options.remove_offset))
    entries = [_crossing_entry(ctx, c) for c in crossings if c.eo in eos]
    steady = [e for dw in segments.dwells for e in _dwell_entries(ctx, dw)]
    if not entries:
        notes.append(_why_none(eos_asked, segments, omega, info, det))
    notes += [nsv_note(n.to_summary()) for n in nsv]
    if rows_truth is not None and len(eos) > 1:
        notes.append("the truth envelope sums every excitation's response: a crossing's E_A also holds the other "
                     "engine orders' off-resonance response at its speed")
    report = ResonanceReport.from_entries(entries, steady, eo=eos[0], cn=cns.get(eos[0], fit.cn),
                                          reference=ref_info, notes=notes, non_synchronous=nsv)
    eo = eos[0]
    fit_tw = fit_spectra(fit.phasor[..., 0], eo, geometry.blade_angles_rad)
    probe_tw = probe_spectra(d, eo)
    res_revs = np.zeros(n_rev, bool)
    for c in crossings:
        if c.eo == eo:
            res_revs[c.hp_lo:c.hp_hi + 1] = True
    if not res_revs.any():
        amp = fit.amp_pkpk_m[..., 0]
        ok = np.isfinite(amp)
        mean_amp = np.where(ok, amp, 0.0).sum(axis=1) / np.maximum(ok.sum(axis=1), 1)
        res_revs = mean_amp >= 0.5 * mean_amp.max() if mean_amp.size else res_revs
    return ProcessingResult(geometry=geometry, options=options, engine_orders=eos, opr_s=opr,
                            displacements=disp, prepared=prepared, fit=fit, probe_tw=probe_tw,
                            fit_tw=fit_tw, resonance_revolutions=res_revs, report=report, segments=segments,
                            crossings=tuple(crossings), reference=reference, joint=bool(joint),
                            nsv_scan=nsv_scan, nsv=nsv)


#: A crossing candidate is the non-synchronous vibration's leak into the engine-order fits
#: (not a resonance) when a detection overlapping its half-power region is at least this
#: fraction of the candidate's peak amplitude.
NSV_DOMINANCE = 0.5


def _not_nsv(crossings: list, nsv: tuple, revolution0: int, omega: np.ndarray, notes: list) -> list:
    """The crossing candidates that are not a non-synchronous vibration seen through the
    engine-order fits (those are dropped, each with a note)."""
    keep = []
    for c in crossings:
        hit = [n for n in nsv if n.first_revolution - revolution0 <= c.hp_hi
               and n.last_revolution - revolution0 >= c.hp_lo and n.amp_pkpk_m >= NSV_DOMINANCE * c.amp_peak_m]
        if not hit:
            keep.append(c)
            continue
        n = max(hit, key=lambda x: x.amp_pkpk_m)
        rpm = float(omega[c.peak]) * 60 / TWO_PI
        notes.append(f"EO {c.eo} peak at revolution {revolution0 + c.peak} ({rpm:.0f} rpm, "
                     f"{1e3 * c.amp_peak_m:.4f} mm) not reported as a resonance: it is the non-synchronous vibration "
                     f"at order {n.order:.3f}, ND {n.nd:+d} ({1e3 * n.amp_pkpk_m:.4f} mm) seen through the EO fits")
    return keep


def _separate(crossings: list[Crossing]) -> list[Crossing]:
    """Crossings in revolution order, each window cut halfway to its neighbours' peaks (so
    that a blade's peak and the truth of one crossing are never taken from another)."""
    out = sorted(crossings, key=lambda c: c.peak)
    for k in range(len(out) - 1):
        a, b = out[k], out[k + 1]
        mid = (a.peak + b.peak) // 2
        if a.hi > mid:
            out[k] = replace(a, hi=max(mid, a.hp_hi), excl_hi=max(min(a.excl_hi, b.excl_hi), a.hp_hi))
        if b.lo <= mid:
            out[k + 1] = replace(b, lo=min(mid + 1, b.hp_lo))
    return out


def _num(x):
    x = float(x)
    return x if math.isfinite(x) else None


def _misfits(d: np.ndarray, angles, eos: tuple, fit: SineFit) -> dict:
    """Per order: relative misfit of its own single-order fit over a range of revolutions."""
    out = {}
    for i, eo in enumerate(eos):
        f = fit if len(eos) == 1 else fit_revolutions(d, angles, (eo,))
        res = f.residual_rms_m
        amp = f.amp_pkpk_m[..., 0]

        def m(lo, hi, res=res, amp=amp):
            r = res[lo:hi + 1]
            a = amp[lo:hi + 1]
            with np.errstate(all="ignore"):
                return float(np.sqrt(np.nanmean(r * r)) / max(np.sqrt(np.nanmean(a * a)), 1e-300))
        out[eo] = m
    return out


def _best_dwell_eo(fit0: SineFit, eos: tuple, segments: RunSegments):
    """In a scan without crossing: the order with the largest response over the dwells."""
    if not segments.dwells:
        return None
    mask = segments.dwell_mask(fit0.amp_pkpk_m.shape[0])
    with np.errstate(all="ignore"):
        amp = np.nanmean(fit0.amp_pkpk_m[mask], axis=(0, 1))
    return int(eos[int(np.nanargmax(amp))]) if np.isfinite(amp).any() else None


def _baseline_bridges(omega: np.ndarray, usable: np.ndarray) -> bool:
    """Whether a baseline in speed fitted to the ``usable`` revolutions can bridge the others:
    usable speeds on both sides of the excluded ones, each side spanning at least half the
    excluded span (otherwise the polynomial extrapolates, or interpolates a long gap, and
    turns the resonances' skirts or noise into a first-order amplitude error)."""
    if usable.all():
        return True
    if not usable.any():
        return False
    ex = omega[~usable]
    lo, hi = float(ex.min()), float(ex.max())
    below, above = omega[usable & (omega < lo)], omega[usable & (omega > hi)]
    gap = hi - lo
    return bool(below.size and above.size and np.ptp(below) >= 0.5 * gap and np.ptp(above) >= 0.5 * gap)


def _half_widths(omega: np.ndarray, crossings, prep: PrepOptions) -> np.ndarray:
    """Smoother half-width per revolution: ``fraction x W_k (Omega / Omega_k)^2`` of the
    nearest-in-effect crossing (the smallest), clipped; the minimum without any."""
    h = np.full(omega.size, np.inf)
    for c in crossings:
        h_res = (prep.smooth_half_width if prep.smooth_half_width is not None
                 else prep.smooth_width_fraction * c.half_power_width)
        hk = np.full(omega.size, float(h_res))
        if prep.speed_adaptive:
            hk = hk * (omega / omega[c.peak]) ** 2
        h = np.minimum(h, hk)
    if not crossings:
        h[:] = prep.smooth_half_width if prep.smooth_half_width is not None else prep.min_half_width
    return np.clip(h, max(prep.min_half_width, 1.0), prep.max_half_width)


def _region(amp0: np.ndarray, crossings, n_rev: int) -> ResonanceRegion:
    """The data preparation's view of the crossings: every blade's baseline leaves out each
    crossing's exclusion region."""
    nb = amp0.shape[1]
    mask = np.zeros((n_rev, nb), bool)
    for c in crossings:
        mask[c.excl_lo:c.excl_hi + 1] = True
    strongest = max(crossings, key=lambda c: c.amp_peak_m) if crossings else None
    combined = np.sqrt(np.nansum(amp0 ** 2, axis=2))
    return ResonanceRegion(
        amp_pkpk_m=combined, peak_revolution=np.full(nb, strongest.peak if strongest else 0, np.int64),
        half_power_width=np.full(nb, float(strongest.half_power_width) if strongest else np.nan),
        significant=np.full(nb, bool(crossings)), mask=mask)


@dataclass(frozen=True, slots=True, eq=False)
class _Raw:
    """Unsmoothed (offset-removed) fits: amplitude and complex response."""

    amp_pkpk_m: np.ndarray
    phasor: np.ndarray


@dataclass(frozen=True, slots=True, eq=False)
class _Context:
    geometry: Geometry
    eos: tuple
    joint: bool
    cns: dict
    fit: SineFit
    raw: _Raw
    d_flat: np.ndarray
    omega: np.ndarray
    opr: np.ndarray
    toa: np.ndarray
    half_width: np.ndarray | None
    gain_weights: np.ndarray | None
    truth: object
    revolution0: int
    options: ProcessOptions
    reference: Reference | None = None
    crossings: tuple = ()
    offset_removed: bool = False


#: The zeroing correction fits the response's growth where the predicted response is at most
#: this fraction of the peak (the skirt between the reference and the crossing).
TAIL_LEVEL = 0.3


def _zeroing_correction(ctx: _Context, c: Crossing, i: int) -> np.ndarray | None:
    """The response the zeroing reference held, per blade, to add back to the crossing's
    complex responses (None: not needed or not estimable).

    The reference subtracted the response ``P_ref`` it held from every revolution. Between
    the reference and the crossing the measured response is ``P(n) = K (h(n) - h_ref)``,
    ``h`` the crossing's predicted SDOF shape (:func:`~.detect.predicted_response`): a complex
    ``K`` per blade fitted there by least squares gives ``P_ref = K h_ref``. Only the growth
    law ``h`` is assumed, not the phase of the peak, so it also holds for a blade whose peak
    mixes several (mistuned) modes. When the data preparation removed a baseline fitted
    around the reference, that baseline took the reference's response already: no
    correction.
    """
    ref = ctx.reference
    if ref is None or ref.start is None or ctx.offset_removed:
        return None
    same = [k for k in ctx.crossings if k.eo == c.eo]
    h = predicted_response(ctx.omega, same)
    h_ref = complex(np.mean(h[ref.start:ref.stop]))
    idx = np.arange(ref.start, c.peak) if ref.start < c.peak else np.arange(c.peak + 1, ref.stop)
    idx = idx[np.abs(h[idx]) <= TAIL_LEVEL]
    if idx.size < 16:
        return None
    g = h[idx] - h_ref
    P = ctx.fit.phasor[idx, :, i]
    ok = np.isfinite(P)
    w = np.where(ok, np.abs(g)[:, None] ** 2, 0.0).sum(axis=0)
    with np.errstate(all="ignore"):
        K = np.where(ok, np.conj(g)[:, None] * np.where(ok, P, 0.0), 0.0).sum(axis=0) / w
    return np.where(w > 0, K * h_ref, 0.0)


def _correction_size(corr, P) -> float:
    """Blade mean of ``|correction| / |peak response|`` (NaN: no correction)."""
    if corr is None:
        return math.nan
    with _quiet():
        peak = np.nanmax(np.abs(P), axis=0)
        return float(np.nanmean(np.abs(corr) / peak))


def _nd(ctx: _Context, i: int, eo: int, rows) -> int:
    tw = fit_spectra(ctx.fit.phasor[rows, :, i], eo, ctx.geometry.blade_angles_rad)
    return identify_nd(tw)


def _crossing_entry(ctx: _Context, c: Crossing) -> ResonanceEntry:
    i = ctx.eos.index(c.eo)
    fit, opts = ctx.fit, ctx.options
    freq = ctx.omega * c.eo / TWO_PI
    amp, ph = fit.amp_pkpk_m[..., i], fit.phase_rad[..., i]
    corr = _zeroing_correction(ctx, c, i)
    if corr is not None:  # the response the reference held, added back in the crossing's window
        P = fit.phasor[..., i].copy()
        P[c.lo:c.hi + 1] += corr[None, :]
        amp, ph = 2.0 * np.abs(P), np.angle(P)
    method, sweep = opts.method, math.nan
    if opts.method == "peak" and opts.peak_method != "max":
        pk = find_peaks(amp[c.lo:c.hi + 1], freq[c.lo:c.hi + 1], method=opts.peak_method)
        pk = replace(pk, revolution=pk.revolution + c.lo, method=f"peak/{opts.peak_method}")
        method = pk.method
    else:
        pk = peak_method(amp, ph, freq, c.lo, c.hi, amp_raw_m=ctx.raw.amp_pkpk_m[..., i])
        if ctx.half_width is not None and np.isfinite(ctx.half_width).any():  # the smoother's noise gain
            rev = pk.revolution
            ok = np.isfinite(rev)
            uniq, inv = np.unique(rev[ok].astype(np.int64), return_inverse=True)
            g = np.ones(rev.size)
            g[ok] = smoothing_gain(ctx.half_width, ctx.gain_weights, uniq)[inv]
            pk = replace(pk, amp_std_m=pk.amp_std_m * g)
        if opts.method == "cff":
            eos_fit = ctx.eos if ctx.joint else (c.eo,)
            pk = cff_method(ctx.d_flat, ctx.geometry.probe_angles_rad, eos_fit, eos_fit.index(c.eo), ctx.omega,
                            c.lo, c.hi, cff_window(c.half_power_width),
                            tip_radius_m=ctx.geometry.tip_radius_m if opts.sampling_angles else None, offset=corr)
        elif opts.method == "sdof":
            with np.errstate(all="ignore"), _quiet():
                t_sample = np.nanmean(ctx.toa, axis=2)
            pk, sweep = sdof_method(ctx.raw.phasor[..., i], t_sample, ctx.opr, rotor_phase_from_opr(ctx.opr), c.eo,
                                    c.lo, c.hi, fn0_hz=pk.freq_hz, zeta0=c.damping_estimate(ctx.omega))
    with _quiet():
        damping = float(np.nanmean(pk.damping_ratio)) if np.isfinite(pk.damping_ratio).any() else math.nan
        f_mean = float(np.nanmean(pk.freq_hz)) if np.isfinite(pk.freq_hz).any() else math.nan
    r0 = ctx.revolution0
    entry = ResonanceEntry(
        kind="crossing", eo=c.eo, nd=_nd(ctx, i, c.eo, slice(c.hp_lo, c.hp_hi + 1)), cn=ctx.cns.get(c.eo, fit.cn),
        method=method, rpm=float(ctx.omega[c.peak]) * 60.0 / TWO_PI, freq_hz=f_mean, damping_ratio=damping,
        detection=Detection("prominence_ratio", c.ratio, opts.detect.ratio_threshold, c.snr,
                            opts.detect.snr_threshold),
        first_revolution=r0 + c.lo, last_revolution=r0 + c.hi, peak_revolution=r0 + c.peak, peaks=pk,
        sweep_rate=sweep, zeroing_correction=_correction_size(corr, fit.phasor[c.lo:c.hi + 1, :, i]))
    return entry.with_truth(window_truth(ctx.truth, c.eo, c.lo, c.hi))


def _dwell_entries(ctx: _Context, dw) -> list[ResonanceEntry]:
    """Steady-state results of one dwell, one entry per engine order: the mean of the
    complex responses over the dwell (its first ``settle`` revolutions skipped)."""
    n = dw.stop - dw.start
    rate = float(np.mean(ctx.omega[dw.start:dw.stop])) / TWO_PI
    skip = min(max(int(math.ceil(0.5 * rate)), n // 10), n // 2)
    a, b = dw.start + skip, dw.stop  # revolutions [a, b)
    out = []
    opts = ctx.options
    for i, eo in enumerate(ctx.eos):
        P = ctx.fit.phasor[a:b, :, i]
        Praw = ctx.raw.phasor[a:b, :, i]
        with _quiet():
            mean = np.nanmean(P, axis=0)
            cnt = np.sum(np.isfinite(Praw), axis=0)
            spread = np.sqrt(np.nansum(np.abs(Praw - np.nanmean(Praw, axis=0)) ** 2, axis=0) / np.maximum(cnt - 1, 1))
        amp = 2.0 * np.abs(mean)
        std = 2.0 * spread / np.sqrt(np.maximum(cnt, 1))
        f = eo * float(np.mean(ctx.omega[a:b])) / TWO_PI
        nb = amp.size
        with _quiet():
            snr = float(np.nanmean(amp) / max(np.nanmean(std), 1e-300)) if np.isfinite(amp).any() else 0.0
        peaks = ResonancePeaks(revolution=np.full(nb, float(a)), amp_pkpk_m=amp, freq_hz=np.full(nb, f),
                               damping_ratio=np.full(nb, np.nan), method="mean", phase_rad=np.angle(mean),
                               amp_std_m=std, freq_std_hz=np.full(nb, float(np.std(ctx.omega[a:b])) * eo / TWO_PI))
        nd = identify_nd(fit_spectra(mean, eo, ctx.geometry.blade_angles_rad))
        r0 = ctx.revolution0
        entry = ResonanceEntry(
            kind="dwell", eo=eo, nd=nd, cn=ctx.cns.get(eo, ctx.fit.cn), method="mean",
            rpm=float(np.mean(ctx.omega[a:b])) * 60.0 / TWO_PI, freq_hz=f, damping_ratio=math.nan,
            detection=Detection("amplitude_snr", min(snr, 1e9), opts.detect.dwell_snr_threshold, min(snr, 1e9),
                                opts.detect.dwell_snr_threshold),
            first_revolution=r0 + a, last_revolution=r0 + b - 1, peak_revolution=-1, peaks=peaks)
        out.append(entry.with_truth(window_truth(ctx.truth, eo, a, b - 1, mean=True)))
    return out


def _why_none(eos, segments: RunSegments, omega, info, det: DetectOptions) -> str:
    """A sentence on why no crossing was reported."""
    if not segments.sweeps:
        return "the run has no speed sweep (it is a dwell): no resonance can be crossed"
    lo_rpm = float(np.min(omega)) * 60 / TWO_PI
    hi_rpm = float(np.max(omega)) * 60 / TWO_PI
    msg = (f"no crossing at EO {', '.join(map(str, eos))} over {lo_rpm:.0f}-{hi_rpm:.0f} rpm: no interior peak of "
           f"the amplitude falls below 1/{det.ratio_threshold:g} of its height on both sides with SNR >= "
           f"{det.snr_threshold:g}")
    fam = getattr(info, "family_freq_hz", None)
    speeds, fam_at = getattr(info, "family_speed_rad_s", None), getattr(info, "family_freq_hz_at_speed", None)
    if fam is not None and np.size(fam):
        fam = np.asarray(fam, float)
        if speeds is not None and fam_at is not None:  # speed-dependent families: the swept stretch of each curve
            from ..speed_spline import interpolate_freq_hz

            om = np.linspace(float(np.min(omega)), min(float(np.max(omega)), float(speeds[-1])), 65)
            f_sw = interpolate_freq_hz(speeds, fam_at, om)  # (65, n_families, n_nd)
            inside = [eo for eo in eos
                      if np.any(np.diff(np.sign(eo * om / TWO_PI - f_sw.reshape(om.size, -1).T), axis=1) != 0)]
        else:
            inside = [eo for eo in eos if np.any((fam >= eo * lo_rpm / 60) & (fam <= eo * hi_rpm / 60))]
        if not inside:
            msg += (f"; no mode family frequency of the run's model lies in the swept range "
                    f"({min(eos) * lo_rpm / 60:.1f}-{max(eos) * hi_rpm / 60:.1f} Hz)")
    return msg


class _quiet:
    """Silence numpy's empty-slice warnings (NaN is the answer)."""

    def __enter__(self):
        import warnings
        self._w = warnings.catch_warnings()
        self._w.__enter__()
        warnings.simplefilter("ignore", RuntimeWarning)

    def __exit__(self, *exc):
        return self._w.__exit__(*exc)


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

    def next_row(self) -> np.ndarray:
        """Append a row (NaN) and return it, to be written in place."""
        if self.n == self._a.shape[0]:
            self._a = np.concatenate([self._a, np.full_like(self._a, np.nan)])
        self.n += 1
        return self._a[self.n - 1]

    def __getitem__(self, i):
        return self._a[: self.n][i]

    def row(self, k: int):
        """Row ``k`` (``0 <= k < n``, unchecked): ``self[k]`` without the slice."""
        return self._a[k]

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
        eos, _, _ = _layout_cns(engine_orders_of(info, options), self.geometry, False)  # LayoutError if singular
        if len(eos) > 1 and not (self.geometry.n_probes >= 1 + 2 * len(eos) and condition_number(
                eos, np.rad2deg(self.geometry.probe_angles_rad)) < CN_JOINT_MAX):
            eos = eos[:1]  # the live fits cannot hold them jointly: the first order (the report has them all)
        self.engine_orders = eos
        g = self.geometry
        self._shape = (g.n_blades, g.n_probes)
        cap = int(getattr(info, "n_revolutions", 0) or 0) + 8
        self._opr = _Growable((), cap)
        self._toa = _Growable(self._shape, cap)
        self._d = _Growable(self._shape, cap)
        self._omega = _Growable((), cap)
        self._was_calibrated: list[bool] = []
        self._row_sum: list[float] = []  # per revolution, the sum of the displacements (NaN: one is missing)
        self._first_rev: int | None = None
        self._n_done = 0  # displacements computed for revolutions [0, _n_done)
        self._n_emitted = 0
        cal = options.calibration
        if isinstance(cal, str):  # "auto": the final report chooses; the live outputs use the start
            cal = LIVE_CALIBRATION
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
        # the same terms as columns (n_eo, 1), for the (order, blade) rows of _output
        self._ginv_col = None if gi is None else tuple(g[:, None] for g in (*self._ginv[:2], self._g12x2))
        self._g1122_col = None if gi is None else _interleave(*self._ginv_col[:2])
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
        self._nsv_next = 0  # first revolution (index) of the next NSV block
        self._nsv_run = 0  # consecutive detected blocks so far
        self._nsv_last = None  # the last block's scan
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
        truth_peaks : TruthPeakTracker, Truth-like, TruthRows or TruthPeaks, optional
            Only for E_A and E_f (a tracker or per-revolution truth scores every crossing and
            dwell against its own window; peaks only, the crossings that contain them).

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
        if opts.engine_orders is None and opts.eo_range is None:
            opts = _with_eos(opts, engine_orders_of(self.info, opts))
        self.result = process_arrays(self._opr.array, self._toa.array, self.info, opts,
                                     truth=truth_peaks, revolution0=self._first_rev or 0)
        return self.result.summary

    def nsv_ready(self) -> list[NsvDetection]:
        """Non-synchronous vibration of the blocks of revolutions completed since the last
        call (:mod:`.nsv`, ``options.nsv.block`` revolutions each): each detected block, once
        it is the ``min_blocks``-th consecutive one or later, as a one-block
        :class:`NsvDetection` (the final report groups the blocks over the whole run).

        A block in which the calibration of the arrival angles switched on is skipped (its
        displacements change their zeroing mid-block)."""
        opts = self.options.nsv
        L = int(opts.block)
        out = []
        while self._nsv_next + L <= self._n_done:
            s = self._nsv_next
            self._nsv_next += L
            cal = self._was_calibrated[s:s + L]
            if any(cal) != all(cal):
                self._nsv_run, self._nsv_last = 0, None
                continue
            d = self._d.array[s:s + L]
            finite = all(map(math.isfinite, self._row_sum[s:s + L]))  # a finite sum: finite samples
            if not screen_block(d, opts, finite=finite):  # the statistic alone first (most blocks stop here)
                self._nsv_run, self._nsv_last = 0, None
                continue
            scan = scan_blocks(d, self._omega.array[s:s + L], self._psi, opts, starts=[0])
            if not scan.detected[0]:
                self._nsv_run, self._nsv_last = 0, None
                continue
            last = self._nsv_last
            same = last is not None and any(abs(scan.order[0] - o) <= 3.0 / L and scan.nd[0] == n for o, n in
                                            ((last.order[0], last.nd[0]), *last.alternatives[0]))
            self._nsv_run = self._nsv_run + 1 if same else 1
            self._nsv_last = scan
            if self._nsv_run >= int(opts.min_blocks):
                one = replace(opts, min_blocks=1)
                out += list(detections(scan, d, self._psi, one, revolution0=(self._first_rev or 0) + s,
                                       omega_rad_s=self._omega.array[s:s + L]))
        return out

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
            self._d.append(d)
        else:
            d = self._d.next_row()  # written in place
            om = _displacement_row(float(opr[k]), *fast, self._toa.array[k], self._psi, self.geometry.tip_radius_m,
                                   d)
        self._row_sum.append(_add_all(d))
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
        d_k = self._d.row(k)
        w = self._window
        eo = self.engine_orders[0]
        om = float(self._omega.row(k))
        if w == 1 and self._pinv is not None:
            # the fit and both spectra as a few small matrix products (precomputed); the
            # element-wise steps run on contiguous (order, blade) rows (the same operations
            # on the same values as on the (blade, order) columns, fewer strided loops)
            missing = math.isnan(self._row_sum[k])  # np.isnan(d_k.sum())
            if missing:
                a, rss, s2, g11, g22, g12, n_used = self._fit_patterns(d_k)
                g11, g22, g12x2 = g11.T, g22.T, 2.0 * g12.T
                g1122 = _interleave(g11, g22)
            else:
                a = d_k @ self._pinvT  # (nb, p)
                r = d_k @ self._residual  # (I - B B^+) applied to each blade's samples
                rss = _add_rows(np.multiply(r, r, out=r), axis=1)
                s2 = rss * self._inv_dof
                g11, g22, g12x2 = self._ginv_col
                g1122 = self._g1122_col
                n_used = self._B.shape[0]
            # each operation with its operands in the original order (a NaN from both keeps
            # the first one's sign), in place where a temporary is not needed
            at = a.T.copy()  # (p, nb)
            a1, a2 = at[1::2], at[2::2]  # (n_eo, nb)
            sq = at[1:] * at[1:]  # a1 * a1, a2 * a2 interleaved
            amp2 = sq[0::2] + sq[1::2]
            ga = g1122 * at[1:]  # g11 * a1, g22 * a2 interleaved
            t = g12x2 * a2
            num = np.add(ga[0::2], t, out=t)
            num = np.multiply(a1, num, out=num)
            ga2 = ga[1::2]
            ga2 *= a2
            num += ga2  # a1 * (g11 * a1 + g12x2 * a2) + g22 * a2 * a2: (a1, a2) G (a1, a2)^T
            amp = np.sqrt(amp2)
            if not _all(amp2):  # no direction: the mean of the two variances
                zero = amp2 == 0
                num = np.where(zero, 0.5 * (g11 + g22), num)
                amp2 = np.where(zero, 1.0, amp2)
            amp = np.multiply(2.0, amp, out=amp)
            phase = np.arctan2(a2, a1)
            num = np.multiply(s2, num, out=num)
            num /= amp2
            amp_std = np.sqrt(num, out=num)
            amp_std = np.multiply(2.0, amp_std, out=amp_std)
            rss /= n_used
            dc, res = at[0], np.sqrt(rss, out=rss)
            if a1.shape[0] == 1:  # one EO: (1, nb) rows are (nb, 1) C-contiguous columns as they are
                amp_pkpk, phase, amp_std = amp.T, phase.T, amp_std.T
            else:
                amp_pkpk, phase, amp_std = _columns(amp), _columns(phase), _columns(amp_std)
            phasor = at[1] + 1j * at[2]
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
            revolution=self._first_rev + k, opr_s=float(self._opr.row(k)), omega_rad_s=om,
            engine_orders=self.engine_orders, freq_hz=om * self._freq_per_omega, cn=self._cn,
            d_m=d_k, amp_pkpk_m=amp_pkpk, phase_rad=phase, amp_std_m=amp_std, dc_m=dc,
            residual_rms_m=res, probe_tw=probe_tw, fit_tw=fit_tw, calibrated=self._was_calibrated[k])


_add_rows = np.add.reduce  # ndarray.sum without its Python wrapper (the same reduction)


def _add_all(x: np.ndarray) -> float:
    """``float(x.sum())``: the same pairwise reduction, without ndarray.sum's Python wrapper."""
    return float(np.add.reduce(x, axis=None))


def _all(x: np.ndarray) -> bool:
    """``x.all()`` (NaN counts as true there too), by the faster ``count_nonzero``."""
    return np.count_nonzero(x) == x.size


def _interleave(g11: np.ndarray, g22: np.ndarray) -> np.ndarray:
    """Rows ``g11[0], g22[0], g11[1], ...`` of two (n_eo, m) arrays, shape (2 n_eo, m)."""
    out = np.empty((2 * g11.shape[0], g11.shape[1]))
    out[0::2], out[1::2] = g11, g22
    return out


def _columns(x: np.ndarray) -> np.ndarray:
    """(n_eo, n_blades) rows as C-contiguous (n_blades, n_eo) columns."""
    return np.ascontiguousarray(x.T)


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
                      tip_radius_m: float, out: np.ndarray) -> float:
    """Eq. 1 displacements of one revolution into ``out`` (returns ``om``):
    :func:`displacements_from_phase` of one row, with the rotor phase as scalars (the same
    operations in the same order, operands included, in place on two work arrays)."""
    tau = np.subtract(toa, opr_k)
    x = np.multiply(0.5 * alpha, tau)
    x = np.add(w0, x, out=x)
    x = np.multiply(tau, x, out=x)  # ang = tau * (w0 + 0.5 * alpha * tau), RotorPhase.angle
    x -= psi
    x /= TWO_PI
    k = np.rint(x, out=x)  # np.round(x): the revolution number
    a = np.where(np.isfinite(k), k, 0.0)
    a = np.multiply(TWO_PI, a, out=a)
    a = np.add(psi, a, out=a)  # a = psi + 2 pi k
    y = np.multiply(2.0 * alpha, a, out=x)
    y = np.add(w0 * w0, y, out=y)
    y = np.sqrt(y, out=y)
    y = np.add(w0, y, out=y)
    a = np.multiply(2.0, a, out=a)
    a /= y  # tau_exp = 2 a / (w0 + sqrt(w0^2 + 2 alpha a)), RotorPhase.delay_at_angle
    a -= tau
    np.multiply(om * float(tip_radius_m), a, out=out)
    return om


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

"""The offline processing pipeline: OPR + TOAs of a whole run in, fits, travelling waves and
resonances out (:func:`process_arrays`).

Steps (each numerical step in its own module): displacements by Eq. 1 with OPR-based
expected times calibrated on a low-speed window (or the exact expected times of the truth)
(:mod:`.displacement`); what the run holds -- speed segments, crossings per engine order,
non-synchronous vibration (:mod:`.detect`, :mod:`.nsv`); data preparation (:mod:`.prep`);
windowed sine fits, Eq. 16-17 (:mod:`.fit`); per crossing the resonance method
(:mod:`.methods`); travelling-wave spectra (:mod:`.travelling_wave`); resonance entries and
E_A / E_f, Eq. 18-19 (:mod:`.resonance`).

The streaming processor (:mod:`.streaming`) shares every numerical step and runs this
pipeline over its history for the final report. Options are in :mod:`.options`, results in
:mod:`.results`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from functools import partial

import numpy as np

from .detect import (Crossing, DetectOptions, Reference, RunSegments, choose_reference, detect_crossings,
                     predicted_contamination, resolve_engine_orders, speed_segments)
from .displacement import (DISPLACEMENT_CHUNK, TWO_PI, DisplacementRows, Displacements, Geometry,
                           compute_displacements, first_pass_rows, rotor_phase_from_opr)
from .history import ScratchRows
from .fit import SineFit, fit_revolutions, quiet
from .intervals import crossing_intervals, crossing_notes, layout_gain, no_crossing_note
from .steady import dwell_entries
from .span_fits import (blade_mean, chunk_fits, fit_spans, held_fit, merge_spans, order_phasors, overlap_spans,
                        read_spans, run_amplitudes, span_phasors)
from .spans import SpanRows, angle
from .zeroing import correction_size, tail_revolutions, zeroing_correction
from .methods import METHODS, amplitude_noise, cff_method, cff_window, peak_method, sdof_method
from . import crb
from .nsv import NsvScan, detect_nsv, is_rigid_body, nsv_note, nsv_truth_rows, rigid_body_note, score_nsv
from .options import ProcessOptions, engine_orders_of, fits_jointly, layout_condition_numbers
from .prep import PREP_BLOCK, Baseline, PreparedData, PrepOptions, ResonanceRegion, prepare, smoothing_gain
from .scratch_result import scratch_result
from .resonance import (Detection, ResonanceEntry, ResonancePeaks, ResonanceReport, TruthPeaks, TruthPeakTracker,
                        TruthRows, find_peaks, own_envelope, window_truth)
from .results import ProcessingResult, RevolutionFit, RevolutionOutput
from .travelling_wave import fit_spectra, identify_nd, probe_spectra

# ProcessOptions, RevolutionFit, RevolutionOutput and engine_orders_of are re-exported for
# the callers that import them from here.
__all__ = ["ProcessOptions", "ProcessingResult", "RevolutionFit", "RevolutionOutput", "process_arrays",
           "check_window", "engine_orders_of", "METHODS"]

#: The data preparation's baseline is fitted where every crossing's predicted response is below
#: this fraction of its peak (the skirts of the resonances are not offsets).
SKIRT_LEVEL = 0.1


def _truth_rows(truth, n_rev: int, revolution0: int, scratch: bool = False):
    """Per-revolution truth rows (or TruthPeaks) for :func:`window_truth`. ``scratch``: the
    envelopes a live run's tracker gives are moved to scratch files (read by rows); those
    of a truth given are kept as they are (arrays, or scratch rows already)."""
    if truth is None:
        return None
    if isinstance(truth, TruthPeakTracker):
        rows = truth.rows(revolution0, n_rev)
        if rows is not None and scratch:  # the tracker's arrays are this function's own
            rows = replace(rows, d_eqv_pkpk_m=ScratchRows.of(rows.d_eqv_pkpk_m),
                           eo_pkpk_m=None if rows.eo_pkpk_m is None else ScratchRows.of(rows.eo_pkpk_m))
        return rows
    if isinstance(truth, (TruthPeaks, TruthRows)):
        return truth
    pk = getattr(truth, "d_eqv_pkpk_m", None)
    om = getattr(truth, "omega_mean", None)
    if pk is None or om is None:
        return None
    pk, om = _float_rows(pk), np.asarray(om, float)
    if pk.shape[0] != n_rev:
        raise ValueError(f"the truth has {pk.shape[0]} revolutions, the data {n_rev}")
    orders, own = getattr(truth, "eo_engine_order", None), getattr(truth, "eo_pkpk_m", None)
    if orders is None or own is None or np.shape(orders)[0] == 0:
        return TruthRows(d_eqv_pkpk_m=pk, omega_mean=om)
    return TruthRows(d_eqv_pkpk_m=pk, omega_mean=om, eo_engine_order=np.asarray(orders)[0],
                     eo_pkpk_m=_float_rows(own))


def _float_rows(a):
    """A float array, or scratch rows as they are."""
    return a if isinstance(a, ScratchRows) else np.asarray(a, float)


def _first_amplitudes(d0: "_Flat", angles, eos: tuple, joint: bool, omega: np.ndarray) -> np.ndarray:
    """The first pass's Eq. 16 amplitudes (one revolution per fit), shape (n_rev, n_blades,
    n_orders), fitted by chunks (:func:`~.span_fits.chunk_fits`), without the run's other fit arrays or
    the zeroed displacements held whole."""
    n_rev, nb = d0.shape[:2]
    amp = np.empty((n_rev, nb, len(eos)))
    for lo, hi, f in chunk_fits(d0, 0, n_rev, angles, eos, joint, omega, None):
        amp[lo:hi] = f.amp_pkpk_m
    return amp


def _column_median(d: DisplacementRows) -> np.ndarray:
    """Each column's (blade's and probe's) median over the run (0 where it has none), shape
    (n_blades, n_probes): computed on blocks of blades (a column's median is its own: the
    same numbers as on the whole array)."""
    import warnings

    n_rev, nb, npr = d.shape
    step = max(1, PREP_BLOCK // max(n_rev * npr, 1))
    med = np.empty((nb, npr))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for b in range(0, nb, step):
            med[b:b + step] = np.nanmedian(d.blades(slice(b, b + step)), axis=0)
    return np.where(np.isfinite(med), med, 0.0)


def check_window(window: int, n_rev: int) -> None:
    """A sine-fit window must fit in a recorded run (``bttsim process``, a campaign's
    processors): ValueError, one line, when ``window`` revolutions are more than the run's
    ``n_rev``. Not checked by :func:`process_arrays` itself: the live processor's final report
    of a run cut short reports what it holds."""
    if window > n_rev:
        raise ValueError(f"a sine-fit window of {window} revolutions is longer than the run's {n_rev}")


def process_arrays(opr_s: np.ndarray, toa_s: np.ndarray, info, options: ProcessOptions = ProcessOptions(),
                   truth=None, *, revolution0: int = 0, spectra: bool = True,
                   scratch: bool = False) -> ProcessingResult:
    """Process a whole run: find every resonance crossing and dwell, and report them.

    Parameters
    ----------
    opr_s : ndarray, shape (n_rev,)
        OPR times, s.
    toa_s : ndarray or ScratchRows, shape (n_rev, n_blades, n_probes)
        TOAs, s (NaN: missing). The report alone reads them by blocks from scratch files
        (:class:`~.history.ScratchRows`: the one given, or a copy of the array).
    info : Geometry, RunInfo or RunMetadataMsg
        Probe angles, blade count, tip radius, OPR angle (and engine orders).
    options : ProcessOptions
    truth : Truth-like, TruthRows, TruthPeaks or TruthPeakTracker, optional
        For ``expected_times="exact"`` (``truth.t_exp_s``) and for E_A / E_f
        (``truth.d_eqv_pkpk_m``, ``truth.omega_mean``). Never used otherwise.
    revolution0 : int
        Number of the first revolution (for the report's revolution numbers and a tracker's
        truth).
    spectra : bool
        Compute the per-revolution travelling-wave spectra (``probe_tw``, ``fit_tw``: two
        run-sized arrays that the report does not use) and keep the prepared displacements
        (False: the report only, for the callers that need nothing else: the spectra are
        None, ``displacements.toa_s`` is None (the TOAs are not held past Eq. 1), ``prepared.d_m``
        and ``prepared.region`` are None, freed once the report's fits are made,
        ``prepared.offset_m`` is the :class:`~.prep.Baseline` (not a whole array), and, with one
        revolution per fit, so are the fit's ``amp_std_m``, ``residual_rms_m`` and
        ``n_samples``, which the report does not read, and its other arrays are held on the
        revolutions the report reads only, :class:`~.spans.SpanRows`, NaN elsewhere).
    scratch : bool
        With ``spectra``, one revolution per fit: the full result's run-sized arrays in scratch
        files, the same numbers read by rows (``bttsim export``; the report as ``spectra=False``
        makes it; ``prepared.d_m`` a :class:`~.smoothing.PreparedRows`; the fits and spectra
        :func:`~.scratch_result.scratch_result`'s).

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
    rows = spectra and scratch and options.window == 1  # the full result in scratch files
    lean = not spectra or rows  # the report made with bounded memory
    toa, given = _toas(toa_s, lean)
    del toa_s  # (a handed-over array is freed)
    n_rev = opr.size
    if n_rev < 3:
        raise ValueError(f"at least three revolutions are needed for a resonance report, got {n_rev}")
    notes: list[str] = []
    eos_asked, cns, joint = _orders_asked(info, geometry, options, notes)
    rows_truth = _truth_rows(truth, n_rev, revolution0, scratch=lean)
    t_exp = _exact_times(truth, options)
    # 1. first pass: nominal geometry (or exact times) zeroed on the run's median
    first = first_pass_rows(opr, toa, geometry, t_exp_s=t_exp)  # computed by blocks when needed, not held
    survey = _survey(first, opr, geometry, eos_asked, joint, options, truth, revolution0, notes)
    # 2. zeroing reference, Eq. 1 again
    # the report alone, one revolution per fit: the displacements are read by rows and columns from scratch files
    disp, reference, ref_info = _zeroing(opr, toa, geometry, survey, options, t_exp, revolution0, notes,
                                         scratch=lean and options.window == 1)
    del first
    t_sample = _sample_times(toa, scratch=lean) if survey.crossings else None
    if not spectra:  # the report alone: this function's last use of the TOAs
        disp = replace(disp, toa_s=None)
        if not given:  # its own scratch files
            toa.close()
        del toa
    # 3. data preparation, and the fits of the report
    # the report alone (one revolution per fit): the prepared displacements made by blocks as the fits read them
    region = _region(survey.amp0, survey.crossings, n_rev, combined=not lean) if options.prep else None
    if lean:  # the first pass's amplitudes are done with
        survey = replace(survey, amp0=None)
    prepared = _prepare(disp.d_m, geometry.probe_angles_rad, survey, region, options, notes, keep_offset=not lean,
                        rows_only=lean and options.window == 1)
    d = prepared.d_m if prepared is not None else disp.d_m
    fit, raw, d_flat, (tails, dwells) = _report_fits(d, disp, prepared, geometry, survey, options, lean, reference)
    eo = survey.eos[0]
    probe_tw = probe_spectra(d, eo) if not lean else None
    del d
    if not spectra and prepared is not None:  # the report alone: the prepared displacements are done with
        prepared = replace(prepared, d_m=None, region=None)
    # 4. per crossing and per dwell
    ctx = _Context(geometry=geometry, eos=survey.eos, joint=survey.joint, cns=cns, fit=fit, raw=raw, d_flat=d_flat,
                   omega=survey.omega, opr=opr, t_sample=t_sample,
                   half_width=(prepared.half_width if prepared is not None else None),
                   gain_weights=1.0 / (survey.omega * survey.omega) if options.prep_options.noise_weighting else None,
                   truth=rows_truth, revolution0=revolution0, options=options, reference=reference,
                   crossings=tuple(survey.crossings),
                   offset_removed=bool(prepared is not None and prepared.options.remove_offset), nsv=tuple(survey.nsv),
                   tail_phasors=tails, dwell_fits=dwells)
    report = _report(ctx, survey, eos_asked, info, ref_info, notes)
    # 5. travelling waves and the resonance revolutions of the first order
    res_revs = _resonance_revolutions(fit, survey.crossings, eo, n_rev, raw.mean_m)
    fit_tw = fit_spectra(_first_phasor(fit), eo, geometry.blade_angles_rad) if not lean else None
    if rows:  # the report's fits freed first: every revolution's fits and spectra, by blocks, to scratch files
        cn, fit, ctx, raw, d_flat = fit.cn, None, None, None, None
        fit, probe_tw, fit_tw = _scratch_arrays(prepared.d_m if prepared is not None else disp.d_m, geometry,
                                                survey, options, cn)
    return ProcessingResult(geometry=geometry, options=options, engine_orders=survey.eos, opr_s=opr,
                            displacements=disp, prepared=prepared, fit=fit, probe_tw=probe_tw, fit_tw=fit_tw,
                            resonance_revolutions=res_revs, report=report, segments=survey.segments,
                            crossings=tuple(survey.crossings), reference=reference, joint=bool(survey.joint),
                            nsv_scan=survey.nsv_scan, nsv=survey.nsv)


def _toas(toa_s, lean: bool) -> tuple:
    """The TOAs as the pipeline reads them (``lean``: :class:`~.history.ScratchRows`, the one
    given or a copy of the array, read back by blocks; else a float array) and whether they
    are the caller's scratch rows."""
    given = isinstance(toa_s, ScratchRows) and toa_s.dtype == np.float64  # (else: read and converted)
    toa = toa_s if given and lean else np.asarray(toa_s[:] if isinstance(toa_s, ScratchRows) else toa_s, dtype=float)
    return (ScratchRows.of(toa) if lean and not given else toa), given


def _scratch_arrays(d, geometry: Geometry, survey: "_Survey", options: ProcessOptions, cn: float) -> tuple:
    """Every revolution's fits and first-order spectra of ``d`` (prepared rows, or the
    displacements) in scratch files (:func:`~.scratch_result.scratch_result`)."""
    return scratch_result(d, geometry.probe_angles_rad, survey.eos, survey.joint, survey.omega,
                          geometry.tip_radius_m if options.sampling_angles else None, _spans(survey),
                          geometry.blade_angles_rad, cn)


def _sample_times(toa: np.ndarray, scratch: bool = False) -> np.ndarray:
    """Each blade's mean arrival time over the probes per revolution, shape (n_rev, n_blades)
    (NaN: no arrival), for the swept SDOF fits; in blocks of revolutions (a row's mean is its
    own: the same numbers as on the whole array, without its run-sized temporaries).
    ``scratch``: written to a :class:`~.history.ScratchRows`, read back by rows."""
    out = ScratchRows(toa.shape[1:2]) if scratch else np.empty(toa.shape[:2])
    with np.errstate(all="ignore"), quiet():
        for a in range(0, toa.shape[0], DISPLACEMENT_CHUNK):
            mean = np.nanmean(toa[a:a + DISPLACEMENT_CHUNK], axis=2)
            if scratch:
                out.write(mean)
            else:
                out[a:a + DISPLACEMENT_CHUNK] = mean
    return out


def _first_phasor(fit: SineFit) -> np.ndarray:
    """``fit.phasor[..., 0]`` without the other orders' (the same numbers)."""
    return fit.coeffs[..., 1] + 1j * fit.coeffs[..., 2]


def _orders_asked(info, geometry: Geometry, options: ProcessOptions, notes: list) -> tuple[tuple, dict, bool]:
    """The engine orders to look for, their condition numbers and whether they are fitted
    jointly (a scan: each on its own); the layout's notes are appended to ``notes``."""
    scan = options.eo_range is not None
    eos = tuple(range(options.eo_range[0], options.eo_range[1] + 1)) if scan else engine_orders_of(info, options)
    eos, cns, layout_notes = layout_condition_numbers(eos, geometry, scan)
    notes += layout_notes
    joint = not scan and fits_jointly(eos, geometry)
    if len(eos) > 1 and not scan and not joint:
        notes.append(f"EO {'+'.join(map(str, eos))} cannot be fitted jointly with these probes: each order "
                     f"is fitted on its own and their responses leak into each other")
    return eos, cns, joint


def _exact_times(truth, options: ProcessOptions) -> np.ndarray | None:
    """The truth's exact expected times when the options ask for them, else None."""
    if options.expected_times != "exact":
        return None
    t_exp = getattr(truth, "t_exp_s", None)
    if t_exp is None:
        raise ValueError('expected_times="exact" needs the truth (its t_exp_s)')
    return t_exp


@dataclass(frozen=True, slots=True, eq=False)
class _Survey:
    """What the first pass found: the speeds, the first-pass amplitudes (``amp0``, their
    fits' ``amp_pkpk_m``; None once the data preparation has used them, for the report
    alone), the segments, the crossings (the NSV's leaks dropped) and the non-synchronous
    vibration, and the orders to report."""

    omega: np.ndarray
    amp0: np.ndarray | None
    segments: RunSegments
    crossings: list
    nsv_scan: NsvScan | None
    nsv: tuple
    eos: tuple
    joint: bool


def _survey(first: DisplacementRows, opr: np.ndarray, geometry: Geometry, eos_asked: tuple, joint: bool,
            options: ProcessOptions, truth, revolution0: int, notes: list) -> _Survey:
    """Step 1: Eq. 16 fits of the first-pass displacements zeroed on the run's median, speed
    segments, crossings per engine order and non-synchronous vibration."""
    det = options.detect
    scan = options.eo_range is not None
    angles = geometry.probe_angles_rad
    omega = first.omega_rad_s
    d0 = _Flat(first, np.broadcast_to(_column_median(first), first.shape))  # zeroed on the median, by rows
    amp0 = _first_amplitudes(d0, angles, eos_asked, joint, omega)
    segments = speed_segments(opr, omega, det)
    crossings: list[Crossing] = []
    for i, eo in enumerate(eos_asked):
        dropped: list = []
        crossings += detect_crossings(amp0[..., i], eo, segments, det, dropped)
        notes += [f"EO {eo}: the peak at revolution {revolution0 + r} ({omega[r] * 60 / TWO_PI:.0f} rpm, SNR {snr:.3g} "
                  f"against the per-revolution noise) is not reported as a resonance: the amplitude's own scatter "
                  f"over {det.filter_revolutions} revolutions makes it as large (SNR {slow:.2g} < "
                  f"{det.snr_threshold:g}; noise correlated over several revolutions, e.g. a speed fluctuation)"
                  for r, snr, slow in dropped]
    if len(eos_asked) > 1 and not joint:  # each order on its own: their misfits tell them apart
        crossings = resolve_engine_orders(crossings, _misfits(d0, angles, eos_asked))
    nsv_scan, nsv = _detect_nsv(first, d0, geometry, options, truth, revolution0)
    notes += [rigid_body_note(n) for n in nsv if is_rigid_body(n)]
    nsv = tuple(n for n in nsv if not is_rigid_body(n))
    if nsv:
        crossings = _not_nsv(crossings, nsv, revolution0, omega, notes)
    crossings = _separate(crossings)
    eos = tuple(sorted({c.eo for c in crossings})) if scan else eos_asked
    if scan and not eos:
        eos = (_best_dwell_eo(amp0, eos_asked, segments) or eos_asked[0],)
    if scan:
        joint = fits_jointly(eos, geometry)
    return _Survey(omega=omega, amp0=amp0, segments=segments, crossings=crossings, nsv_scan=nsv_scan,
                   nsv=nsv, eos=eos, joint=joint)


def _detect_nsv(first: DisplacementRows, d0: "_Flat", geometry: Geometry, options: ProcessOptions, truth,
                revolution0: int) -> tuple[NsvScan | None, tuple]:
    """Non-synchronous vibration of the first pass (``d0`` read by blocks of revolutions),
    scored against the truth when given (scored only: the truth never steers the processing)."""
    n_rev = d0.shape[0]
    psi0 = first.arrival_angles_rad if first.arrival_angles_rad is not None else geometry.nominal_arrival_angles()
    nsv_scan, nsv = detect_nsv(d0, first.omega_rad_s, psi0, options.nsv, revolution0=revolution0)
    nsv_truth = (truth.nsv_rows(revolution0, n_rev) if isinstance(truth, TruthPeakTracker)
                 else nsv_truth_rows(truth, n_rev))
    if nsv and nsv_truth is not None:
        nsv = tuple(replace(n, truth=score_nsv(n, nsv_truth, revolution0)) for n in nsv)
    return nsv_scan, nsv


def _zeroing(opr: np.ndarray, toa: np.ndarray, geometry: Geometry, survey: _Survey, options: ProcessOptions,
             t_exp: np.ndarray | None, revolution0: int, notes: list,
             scratch: bool = False) -> tuple[Displacements, Reference | None, dict]:
    """Step 2: the zeroing reference (the options' window, or one chosen away from every
    crossing) and Eq. 1 again on it; returns the displacements, the reference and the
    summary's description of it. ``scratch``: the displacements in scratch files, not held
    (:class:`~.history.ScratchRows`)."""
    n_rev = opr.size
    det = options.detect
    exact = t_exp is not None

    def first() -> Displacements:  # the first pass's displacements, whole: Eq. 1 once more
        return compute_displacements(opr, toa, geometry, t_exp_s=t_exp, calibration=None, scratch=scratch)

    reference = None
    cal = options.calibration
    if exact:
        disp = first()
        ref_info = {"method": "exact", "first": None, "last": None, "contamination_pct": None,
                    "reason": "the truth's exact expected arrival times"}
    elif cal is None or cal is False or (isinstance(cal, (int, np.integer)) and int(cal) == 0):
        disp = first()
        ref_info = {"method": "nominal", "first": None, "last": None, "contamination_pct": None,
                    "reason": "nominal geometry (calibration off)"}
    elif cal == "auto":
        reference = choose_reference(survey.omega, survey.segments, survey.crossings, det)
        if reference.start is None:
            disp = first()
            ref_info = {"method": "nominal", "first": None, "last": None, "contamination_pct": None,
                        "reason": reference.reason}
        else:
            disp = compute_displacements(opr, toa, geometry, calibration=(reference.start, reference.stop),
                                         scratch=scratch)
            ref_info = {"method": "calibrated", "first": revolution0 + reference.start,
                        "last": revolution0 + reference.stop - 1,
                        "contamination_pct": _num(100.0 * reference.contamination), "reason": reference.reason}
            if survey.crossings and reference.contamination > det.contamination_limit:
                notes.append(f"no quiet reference window: the zeroing holds a response of about "
                             f"{100 * reference.contamination:.0f} % of a peak, estimated from the response's growth "
                             f"and added back (each resonance's zeroing_correction_pct)")
    else:
        disp = compute_displacements(opr, toa, geometry, calibration=cal, scratch=scratch)
        w = (0, int(cal)) if isinstance(cal, (int, np.integer)) else (int(cal[0]), int(cal[1]))
        ref_info = {"method": "calibrated", "first": revolution0 + w[0], "last": revolution0 + min(w[1], n_rev) - 1,
                    "contamination_pct": None, "reason": "the window given in the options"}
    return disp, reference, ref_info


def _prepare(d: np.ndarray, angles: np.ndarray, survey: _Survey, region: ResonanceRegion | None,
             options: ProcessOptions, notes: list, keep_offset: bool = True,
             rows_only: bool = False) -> PreparedData | None:
    """Step 3: data preparation (None when off) with every crossing (and dwell) out of the
    baseline: the baseline (offsets slowly varying with speed) is fitted where no crossing's
    response is predicted above the reference's limit, so it does not take the forced
    response's skirts."""
    if not options.prep:
        return None
    n_rev = d.shape[0]
    omega, crossings = survey.omega, survey.crossings
    dwell_mask = survey.segments.dwell_mask(n_rev)
    skirts = predicted_contamination(omega, crossings) > SKIRT_LEVEL
    hw = _half_widths(omega, crossings, options.prep_options)
    prep_opts = options.prep_options
    bridge = _baseline_bridges(omega, ~(dwell_mask | skirts | region.mask.any(axis=1)))
    if prep_opts.remove_offset and crossings and not bridge:
        prep_opts = replace(prep_opts, remove_offset=False)
        notes.append("no offset removal: the run holds too little data on both sides of the crossings for a "
                     "baseline in speed to bridge them (the zeroing reference alone is used)")
    return prepare(d, omega, angles, survey.eos, prep_opts, region=region, half_width=hw,
                   exclude_revolutions=dwell_mask | skirts, keep_offset=keep_offset, rows_only=rows_only)


def _report_fits(d: np.ndarray, disp: Displacements, prepared: PreparedData | None, geometry: Geometry,
                 survey: _Survey, options: ProcessOptions, report_only: bool,
                 reference: Reference | None = None) -> tuple[SineFit, "_Raw", "_Flat", object]:
    """Eq. 16 fits of the prepared displacements ``d`` (at the sampling angles inside the
    crossings and dwells, :func:`~.span_fits.fit_spans`), the unsmoothed fits where those need them, and
    the offset-removed, unsmoothed displacements (:class:`_Flat`: computed for the revolutions
    asked for). ``report_only`` with one revolution per fit: what the report reads -- the
    coefficients, amplitudes and phases of the revolutions it reads (:func:`~.span_fits.read_spans`,
    ``reference`` the zeroing's), :func:`~.span_fits.held_fit` -- and no run-sized fit; the
    skirts the zeroing corrections read, as long as the run between the reference and a crossing,
    are fitted again when read (the last item: ``(i, revolutions) -> phasors``,
    :func:`~.span_fits.order_phasors`; None: read from the fit)."""
    angles, omega, eos, joint = geometry.probe_angles_rad, survey.omega, survey.eos, survey.joint
    radius = geometry.tip_radius_m if options.sampling_angles else None
    spans = _spans(survey)
    held = report_only and options.window == 1
    removed = bool(prepared is not None and prepared.options.remove_offset)
    refit = held and any(tail_revolutions(reference, removed, survey.crossings, omega, c) is not None
                         for c in survey.crossings)
    raw_spans = spans  # the unsmoothed fits: the crossings' and dwells' revolutions (NaN elsewhere)
    if held:  # the crossings' fits, with what their readers reach; a dwell's (as long as the dwell) are
        # fitted again as its means read them, the zeroing skirts' as the corrections read them
        read = read_spans(survey.crossings, omega, merge_spans([(c.lo, c.hi + 1) for c in survey.crossings]),
                          reference, removed, d.shape[0], tails=False)
        fit = held_fit(d, angles, eos, joint, omega, radius, spans, read)
        raw_spans = overlap_spans(read, spans)
    else:
        fit = fit_spans(d, angles, eos, joint, omega, options.window, radius, spans)
    d_flat = _Flat(disp.d_m, prepared.offset_m if prepared is not None else 0.0)  # offset removed, unsmoothed
    unsmoothed = (prepared is None or not options.prep_options.smooth) and options.window == 1
    if unsmoothed:  # the fits are the unsmoothed fits
        raw = _Raw(fit.amp_pkpk_m, fit.phasor)
    else:  # unsmoothed fits, only where a crossing or a dwell needs them (noise, SDOF)
        if held:  # held where the crossings' readers reach (NaN elsewhere, as the whole arrays)
            amp_r = SpanRows.filled(d.shape[0], raw_spans, fit.amp_pkpk_m.shape[1:])
            ph_r = amp_r.like(amp_r.shape[1:], complex, np.nan + 0j)
        else:
            amp_r = np.full(fit.amp_pkpk_m.shape, np.nan)
            ph_r = np.full(fit.amp_pkpk_m.shape, np.nan + 0j)
        for a, b in raw_spans:
            for lo, hi, f_r in chunk_fits(d_flat, a, b, angles, eos, joint, omega, radius):
                amp_r[lo:hi], ph_r[lo:hi] = f_r.amp_pkpk_m, f_r.phasor
        raw = _Raw(amp_r, ph_r)
    if held:
        raw = replace(raw, **run_amplitudes(d, survey.crossings, eos, joint, angles, omega, radius, spans))
    tails = partial(order_phasors, d, angles, eos, joint, omega, radius, spans) if refit else None
    dwells = partial(span_phasors, d, None if unsmoothed else d_flat, angles, eos, joint, omega, radius, spans) \
        if held and survey.segments.dwells else None
    return fit, raw, d_flat, (tails, dwells)


def _spans(survey: _Survey) -> list:
    """The revolutions fitted at the sampling angles: the crossings and dwells (merged)."""
    return merge_spans([(c.lo, c.hi + 1) for c in survey.crossings]
                       + [(dw.start, dw.stop) for dw in survey.segments.dwells])


def _report(ctx: "_Context", survey: _Survey, eos_asked: tuple, info, ref_info: dict, notes: list) -> ResonanceReport:
    """Step 4: one entry per crossing and per dwell, and the report's notes."""
    eos = ctx.eos
    entries = [_crossing_entry(ctx, c) for c in survey.crossings if c.eo in eos]
    steady = [e for dw in survey.segments.dwells for e in dwell_entries(ctx, dw)]
    if not entries:
        notes.append(_why_none(eos_asked, survey.segments, survey.omega, info, ctx.options.detect))
        # the fits held on some revolutions: the whole run's blade medians, computed by blocks
        skirt = no_crossing_note(ctx.fit.amp_pkpk_m if ctx.raw.median_m is None else None, ctx.omega, ctx.eos,
                                 ctx.options.detect.ratio_threshold, medians=ctx.raw.median_m)
        # only where a mode family's frequency lies in the swept range (a resonance is expected)
        notes += [skirt] if skirt and survey.segments.sweeps and "no mode family" not in notes[-1] else []
    notes += [nsv_note(n.to_summary()) for n in survey.nsv]
    if ctx.truth is not None and len(eos) > 1 and any(own_envelope(ctx.truth, eo, slice(0, 0)) is None for eo in eos):
        notes.append("the truth envelope sums every excitation's response: a crossing's E_A also holds the other "
                     "engine orders' off-resonance response at its speed")
    return ResonanceReport.from_entries(entries, steady, eo=eos[0], cn=ctx.cns.get(eos[0], ctx.fit.cn),
                                        reference=ref_info, notes=notes, non_synchronous=survey.nsv)


def _resonance_revolutions(fit: SineFit, crossings: list, eo: int, n_rev: int, mean_amp=None) -> np.ndarray:
    """The half-power regions of the crossings of ``eo`` (or, without any, where the
    blade-mean amplitude exceeds half its peak; ``mean_amp``: that mean when computed by
    blocks, :func:`~.span_fits.run_amplitudes`), shape (n_rev,) of bool."""
    res_revs = np.zeros(n_rev, bool)
    for c in crossings:
        if c.eo == eo:
            res_revs[c.hp_lo:c.hp_hi + 1] = True
    if not res_revs.any():
        if mean_amp is None:
            mean_amp = blade_mean(fit.amp_pkpk_m[..., 0])
        res_revs = mean_amp >= 0.5 * mean_amp.max() if mean_amp.size else res_revs
    return res_revs


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


def _misfits(d: "_Flat", angles, eos: tuple) -> dict:
    """Per order: relative misfit of its own single-order fit over a range of revolutions
    ``lo .. hi``, fitted when asked for on those revolutions only (one revolution per fit:
    the numbers of a fit of the whole run)."""
    out = {}
    for eo in eos:
        def m(lo, hi, eo=eo):
            rows = slice(lo, hi + 1)
            if not len(range(d.shape[0])[rows]):
                return math.nan
            f = fit_revolutions(d[rows], angles, (eo,))
            r, a = f.residual_rms_m, f.amp_pkpk_m[..., 0]
            with np.errstate(all="ignore"):
                return float(np.sqrt(np.nanmean(r * r)) / max(np.sqrt(np.nanmean(a * a)), 1e-300))
        out[eo] = m
    return out


def _best_dwell_eo(amp0: np.ndarray, eos: tuple, segments: RunSegments):
    """In a scan without crossing: the order with the largest response over the dwells
    (``amp0``: the first pass's amplitudes, (n_rev, n_blades, n_orders))."""
    if not segments.dwells:
        return None
    mask = segments.dwell_mask(amp0.shape[0])
    with np.errstate(all="ignore"):
        amp = np.nanmean(amp0[mask], axis=(0, 1))
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


def _region(amp0: np.ndarray, crossings, n_rev: int, combined: bool = True) -> ResonanceRegion:
    """The data preparation's view of the crossings: every blade's baseline leaves out each
    crossing's exclusion region. ``combined``: its ``amp_pkpk_m`` (the orders' first-pass
    amplitudes combined, which the preparation does not read; else None)."""
    nb = amp0.shape[1]
    mask = np.zeros((n_rev, nb), bool)
    for c in crossings:
        mask[c.excl_lo:c.excl_hi + 1] = True
    strongest = max(crossings, key=lambda c: c.amp_peak_m) if crossings else None
    combined = np.sqrt(np.nansum(amp0 ** 2, axis=2)) if combined else None
    return ResonanceRegion(
        amp_pkpk_m=combined, peak_revolution=np.full(nb, strongest.peak if strongest else 0, np.int64),
        half_power_width=np.full(nb, float(strongest.half_power_width) if strongest else np.nan),
        significant=np.full(nb, bool(crossings)), mask=mask)


@dataclass(frozen=True, slots=True, eq=False)
class _Flat:
    """The offset-removed, unsmoothed displacements ``d_m - offset_m``, computed for the
    revolutions asked for (``flat[rows]``: the same numbers as the whole array's rows) instead
    of held for the whole run. ``d_m``: an array or rows computed or read when asked for
    (:class:`~.displacement.DisplacementRows`, :class:`~.history.ScratchRows`); ``offset_m``: an array (e.g. a column's
    median broadcast over the run), a :class:`~.prep.Baseline` (evaluated for those rows) or
    a float."""

    d_m: np.ndarray
    offset_m: "np.ndarray | Baseline | float"

    @property
    def shape(self) -> tuple:
        return self.d_m.shape

    def __getitem__(self, rows) -> np.ndarray:
        off = self.offset_m if isinstance(self.offset_m, (int, float)) else self.offset_m[rows]
        if isinstance(self.d_m, np.ndarray):  # a view of the array: a new one
            return self.d_m[rows] - off
        d = self.d_m[rows]  # rows read or computed for this call: subtracted in place (the same numbers)
        d -= off
        return d


@dataclass(frozen=True, slots=True, eq=False)
class _Raw:
    """Unsmoothed (offset-removed) fits: amplitude and complex response (arrays, or
    :class:`~.spans.SpanRows` held on the revolutions the report reads); with the fits so
    held, what the report reads of the whole run's fitted amplitudes, or None
    (:func:`~.span_fits.run_amplitudes`)."""

    amp_pkpk_m: "np.ndarray | SpanRows"
    phasor: "np.ndarray | SpanRows"
    median_m: np.ndarray | None = None
    mean_m: np.ndarray | None = None


@dataclass(frozen=True, slots=True, eq=False)
class _Context:
    geometry: Geometry
    eos: tuple
    joint: bool
    cns: dict
    fit: SineFit
    raw: _Raw
    d_flat: "_Flat"
    omega: np.ndarray
    opr: np.ndarray
    t_sample: np.ndarray | None
    half_width: np.ndarray | None
    gain_weights: np.ndarray | None
    truth: object
    revolution0: int
    options: ProcessOptions
    reference: Reference | None = None
    crossings: tuple = ()
    offset_removed: bool = False
    nsv: tuple = ()
    #: ``(i, revolutions) -> phasors`` of the zeroing skirts, fitted when read (None: ``fit``'s)
    tail_phasors: object = None
    #: ``(lo, hi, fits) -> (phasors, unsmoothed phasors)`` of a dwell's revolutions, fitted when
    #: read (None: ``fit``'s and ``raw``'s)
    dwell_fits: object = None
    #: the zeroing corrections made, by (engine order, crossing peak, order index)
    corrections: dict = field(default_factory=dict)


def _nd(ctx: _Context, i: int, eo: int, rows) -> int:
    tw = fit_spectra(ctx.fit.phasor_at(i, rows), eo, ctx.geometry.blade_angles_rad)
    return identify_nd(tw)


def _crossing_entry(ctx: _Context, c: Crossing) -> ResonanceEntry:
    i = ctx.eos.index(c.eo)
    fit, opts = ctx.fit, ctx.options
    freq = ctx.omega * c.eo / TWO_PI
    amp, ph = fit.amp_pkpk_m[..., i], fit.phase_rad[..., i]
    corr = zeroing_correction(ctx, c, i)
    if corr is not None:  # the response the reference held, added back in the crossing's window
        P = fit.phasor_at(i)
        P[c.lo:c.hi + 1] += corr[None, :]
        amp, ph = 2.0 * np.abs(P), angle(P)
    method, sweep = opts.method, math.nan
    if opts.method == "peak" and opts.peak_method not in ("max", "fit"):
        pk = find_peaks(amp[c.lo:c.hi + 1], freq[c.lo:c.hi + 1], method=opts.peak_method)
        pk = replace(pk, revolution=pk.revolution + c.lo, method=f"peak/{opts.peak_method}")
        method = pk.method
    else:
        fitted = opts.method == "peak" and opts.peak_method == "fit"
        raw_p = ctx.raw.phasor[..., i] if corr is None else ctx.raw.phasor[..., i] + corr[None, :]
        raw = ctx.raw.amp_pkpk_m[..., i] if corr is None else 2.0 * np.abs(raw_p)
        pk = peak_method(amp, ph, freq, c.lo, c.hi, amp_raw_m=raw, phasor_raw=raw_p,
                         half_power_width=c.half_power_width if fitted else None)
        if not fitted and ctx.half_width is not None and np.isfinite(ctx.half_width).any():  # the smoother's gain
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
                            tip_radius_m=ctx.geometry.tip_radius_m if opts.sampling_angles else None, offset=corr,
                            half_power_width=c.half_power_width, amp_noise_m=amplitude_noise(raw[c.lo:c.hi + 1]))
        elif opts.method == "sdof":
            pk, sweep = _sdof(ctx, c, i, pk.freq_hz)
    zc = correction_size(corr, fit.phasor_at(i, slice(c.lo, c.hi + 1)))
    check = _zeroing_check(ctx, c, i, pk, corr)
    if pk.method == "sdof" and pk.offset_m is not None:  # its own frame: the responses less its constant
        corr = -np.where(np.isfinite(pk.offset_m), pk.offset_m, 0.0)
        P = ctx.raw.phasor[..., i].copy()
        P[c.lo:c.hi + 1] += corr[None, :]
        amp, ph = 2.0 * np.abs(P), angle(P)
        with quiet():
            check = (_model_misfit(pk.misfit_m, ctx.raw.amp_pkpk_m[c.lo:c.hi + 1, :, i]), None, None)
    pk, crossing_notes = _intervals(ctx, c, i, pk, amp, ph, freq, zc, corr, check)
    pk = _with_bound(ctx, c, pk)
    with quiet():
        damping = float(np.nanmean(pk.damping_ratio)) if np.isfinite(pk.damping_ratio).any() else math.nan
        f_mean = float(np.nanmean(pk.freq_hz)) if np.isfinite(pk.freq_hz).any() else math.nan
    r0 = ctx.revolution0
    entry = ResonanceEntry(
        kind="crossing", eo=c.eo, nd=_nd(ctx, i, c.eo, slice(c.hp_lo, c.hp_hi + 1)), cn=ctx.cns.get(c.eo, fit.cn),
        method=method, rpm=float(ctx.omega[c.peak]) * 60.0 / TWO_PI, freq_hz=f_mean, damping_ratio=damping,
        detection=Detection("prominence_ratio", c.ratio, opts.detect.ratio_threshold, c.snr,
                            opts.detect.snr_threshold),
        first_revolution=r0 + c.lo, last_revolution=r0 + c.hi, peak_revolution=r0 + c.peak, peaks=pk,
        sweep_rate=sweep, zeroing_correction=zc, notes=crossing_notes)
    return entry.with_truth(window_truth(ctx.truth, c.eo, c.lo, c.hi))


def _with_bound(ctx: _Context, c: Crossing, pk: ResonancePeaks) -> ResonancePeaks:
    """The crossing's Cramér-Rao bounds (:mod:`.crb`): the layout and fitted orders, the noise
    of the Eq. 16 fits' residuals over revolutions ``lo .. hi`` (truth-free; without
    redundancy, of the responses' scatter), the SDOF model at
    the estimated amplitude, frequency, phase and damping (the half-power estimate without an
    SDOF fit)."""
    eos_fit = ctx.eos if ctx.joint else (c.eo,)
    angles = ctx.geometry.probe_angles_rad
    sl = slice(c.lo, c.hi + 1)
    try:
        K = crb.phasor_covariance(angles, eos_fit, eos_fit.index(c.eo))
    except ValueError:
        return pk
    sigma = crb.residual_sigma(ctx.d_flat[sl], angles, eos_fit)
    if not np.isfinite(sigma).any():  # no redundancy: the scatter of the unsmoothed responses
        sigma = crb.scatter_sigma(ctx.raw.phasor[sl, :, ctx.eos.index(c.eo)], K)
    zeta = np.where(np.isfinite(pk.damping_ratio), pk.damping_ratio, c.damping_estimate(ctx.omega))
    phase = np.zeros(pk.n_blades) if pk.phase_rad is None else np.nan_to_num(pk.phase_rad)
    with quiet():
        b = crb.resonance_bound(angles, eos_fit, eos_fit.index(c.eo), ctx.omega[sl] * c.eo / TWO_PI,
                                np.broadcast_to(sigma, (c.hi + 1 - c.lo, sigma.size)), pk.amp_pkpk_m, pk.freq_hz,
                                zeta, phase)
    return replace(pk, crb_amp_m=b.amp_pkpk_m, crb_freq_hz=b.freq_hz)


#: A crossing whose half-power band is swept in fewer revolutions than this is fast: the
#: per-revolution fits and the smoothing flatten its peak (checked against the swept SDOF fit).
FAST_SWEEP_REVOLUTIONS = 60


def _zeroing_check(ctx: _Context, c: Crossing, i: int, pk: ResonancePeaks, corr):
    """``(bound, error, swept)``: what the zeroing left in the crossing's responses, per blade,
    for every crossing (a quiet reference too: the prepared baseline can leave a constant of about
    a percent of the peak, whose projection on each blade's response at the peak moves its
    amplitude by up to that much). ``error`` (complex, ``a1 + i a2``, m): the responses' constant
    measured by the swept SDOF fit (whose constant takes it, :func:`~.methods.sdof_method`),
    plus the correction added; ``bound`` (pk-pk, m): the fit's misfit beyond the noise (a
    misfit of that size may sit in the constant, :func:`_model_misfit`) or, where the fit failed (NaN ``error``),
    the reference's estimated response (``contamination``) or twice the correction; ``swept``:
    the SDOF fit's swept peak (pk-pk, m), a second estimate free of the zeroing and of the sweep
    rate. ``None`` each: the SDOF method itself (its constant is in its own model). With a quiet
    reference, no correction and a slow sweep the misfit bound is left out (``bound`` 0): no
    reference response can sit in the constant; the constant and the swept peak still count."""
    ref = ctx.reference
    cont = float(ref.contamination) if ref is not None and ref.start is not None else 0.0
    if pk.method == "sdof":
        return None, None, None
    calm = corr is None and not cont > ctx.options.detect.contamination_limit and \
        not c.half_power_width < FAST_SWEEP_REVOLUTIONS
    sd = _sdof(ctx, c, i, pk.freq_hz, uncertainty=False)[0]  # its constant, misfit and peak
    off = sd.offset_m
    add = np.zeros(off.size, complex) if corr is None else corr
    err = off + add
    with quiet():
        bound = np.maximum(2.0 * np.abs(add), cont * np.asarray(pk.amp_pkpk_m, float))
        misfit = _model_misfit(sd.misfit_m, ctx.raw.amp_pkpk_m[c.lo:c.hi + 1, :, i])
    if calm:
        misfit = np.zeros_like(misfit)
    return np.where(np.isfinite(err), misfit, bound), err, sd.amp_pkpk_m


def _probe_spread(geometry: Geometry) -> float:
    """Variance of the probes' arrival times within a revolution (from the OPR), rev^2."""
    pos = np.mod(np.asarray(geometry.probe_angles_rad, float) - float(geometry.opr_angle_rad), TWO_PI) / TWO_PI
    return float(np.var(pos))


def _joint_spread(ctx: _Context, c: Crossing, i: int, rev: np.ndarray) -> np.ndarray:
    """``|A_joint - A_single|`` per blade at its peak revolution ``rev`` (pk-pk, m): the
    unsmoothed amplitude of the joint fit of every order against that of a fit of this
    crossing's order alone. The joint fit has less redundancy (it amplifies the probes'
    unmodelled content), the single one holds the other orders' response: their spread bounds
    the effect of the other engine orders."""
    radius = ctx.geometry.tip_radius_m if ctx.options.sampling_angles else None
    rows, inv = np.unique(rev, return_inverse=True)
    f = fit_revolutions(ctx.d_flat[rows], ctx.geometry.probe_angles_rad, (c.eo,), omega_rad_s=ctx.omega[rows],
                        tip_radius_m=radius)
    cols = np.arange(rev.size)
    single = f.amp_pkpk_m[inv, cols, 0]
    with quiet():
        d = np.abs(ctx.raw.amp_pkpk_m[rev, cols, i] - single)
    return np.where(np.isfinite(d), d, 0.0)


def _model_misfit(misfit_m, amp_raw: np.ndarray) -> np.ndarray:
    """The SDOF fit's misfit beyond the measurement noise, pk-pk (m): ``2 sqrt(m^2 - s^2 / 2)``,
    ``m`` the rms of its complex residuals, ``s`` the revolution-to-revolution noise of the
    amplitudes (:func:`~.methods.amplitude_noise`; complex noise of rms ``s / sqrt(2)``)."""
    from .methods import amplitude_noise

    with quiet():
        s = amplitude_noise(amp_raw)
        m = np.asarray(misfit_m, float)
        return 2.0 * np.sqrt(np.maximum(m * m - 0.5 * np.where(np.isfinite(s), s, 0.0) ** 2, 0.0))


def _sdof(ctx: _Context, c: Crossing, i: int, fn0_hz: np.ndarray, uncertainty: bool = True):
    """The swept SDOF fit of one crossing (:func:`~.methods.sdof_method`) and its sweep rate."""
    return sdof_method(ctx.raw.phasor[..., i], ctx.t_sample, ctx.opr, rotor_phase_from_opr(ctx.opr), c.eo,
                       c.lo, c.hi, fn0_hz=fn0_hz, zeta0=c.damping_estimate(ctx.omega), uncertainty=uncertainty)


def _intervals(ctx: _Context, c: Crossing, i: int, pk: ResonancePeaks, amp, ph, freq, zc: float, corr, check):
    """The crossing's 95 % intervals and notes (:mod:`.intervals`; the truth is not used).
    ``corr``: the zeroing correction (added to the unsmoothed responses as to the others);
    ``check``: :func:`_zeroing_check`."""
    raw = ctx.raw.amp_pkpk_m[..., i]
    if corr is not None:
        raw = raw.copy()
        raw[c.lo:c.hi + 1] = 2.0 * np.abs(ctx.raw.phasor[c.lo:c.hi + 1, :, i] + corr[None, :])
    eos_fit = ctx.eos if ctx.joint else (c.eo,)
    rev = np.clip(np.nan_to_num(pk.revolution, nan=c.peak).round().astype(np.int64), 0, ctx.fit.coeffs.shape[0] - 1)
    P = ctx.fit.phasor_at(i, rev, np.arange(rev.size))
    gain = layout_gain(ctx.geometry.probe_angles_rad, eos_fit, eos_fit.index(c.eo), P)
    ref = ctx.reference
    contamination = float(ref.contamination) if ref is not None and ref.start is not None else math.nan
    orders = _joint_spread(ctx, c, i, rev) if len(eos_fit) > 1 else None
    with quiet():
        pk, terms = crossing_intervals(
            pk, amp, ph, raw, freq, c.lo, c.hi, gain=gain,
            half_power_width=c.half_power_width, zeroing_m=check[0], zeroing_error=check[1], second_m=check[2],
            orders_m=orders, probe_spread=_probe_spread(ctx.geometry),
            cff_window=cff_window(c.half_power_width) if pk.method == "cff" else None)
    r0 = ctx.revolution0
    nsv = [f"order {n.order:.3f}, ND {n.nd:+d}, {1e3 * n.amp_pkpk_m:.4f} mm, revolutions {n.first_revolution}-"
           f"{n.last_revolution}" for n in ctx.nsv
           if n.first_revolution - r0 <= c.hi and n.last_revolution - r0 >= c.lo]
    others = [k.eo for k in ctx.crossings if k.eo != c.eo and k.hp_lo <= c.hp_hi and k.hp_hi >= c.hp_lo]
    notes = crossing_notes(eo=c.eo, method=pk.method, cn=float(ctx.cns.get(c.eo, ctx.fit.cn)), terms=terms,
                           amp_pkpk_m=pk.amp_pkpk_m, contamination=contamination,
                           contamination_limit=ctx.options.detect.contamination_limit, zeroing_correction=zc,
                           nsv_overlap=nsv, other_crossings=others, half_power_width=float(c.half_power_width),
                           fast_sweep_revolutions=FAST_SWEEP_REVOLUTIONS)
    return pk, notes


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

"""Results of the processing, shared by the pipeline, the streaming processor, the codec and
the views: what one revolution gives (:class:`RevolutionFit`, :class:`RevolutionOutput`) and
what a whole run gives (:class:`ProcessingResult`).

Plain dataclasses: nothing here computes, so the bus and the views can import them without
the processing itself. Arrays are ``(revolution, blade, probe)`` (one revolution:
``(blade, probe)``), SI units.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .travelling_wave import ProbeWave, TravellingWaveSpectra

if TYPE_CHECKING:  # the field types of ProcessingResult (annotations only)
    from .detect import Reference, RunSegments
    from .displacement import Displacements, Geometry
    from .fit import SineFit
    from .nsv import NsvScan
    from .options import ProcessOptions
    from .prep import PreparedData
    from .resonance import ResonanceReport

__all__ = ["RevolutionFit", "RevolutionOutput", "ProcessingResult"]


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
        Raw Eq. 1 displacements (zeroed on :attr:`reference`); its ``toa_s`` None when the
        report alone was asked for (``spectra=False``).
    prepared : PreparedData or None
        Its ``d_m`` and ``region`` None, and its ``offset_m`` the fitted
        :class:`~.prep.Baseline` (or a read-only broadcast zero), when the report alone was
        asked for (``spectra=False``).
    fit : SineFit
        Fits of the prepared displacements (raw when ``prep`` is off); with the report alone
        (``spectra=False``) and one revolution per fit, its ``amp_std_m``, ``residual_rms_m``
        and ``n_samples`` are None and its ``coeffs``, ``amp_pkpk_m``, ``phase_rad`` (and
        ``dc_m``) are :class:`~.spans.SpanRows`: held on the revolutions the report reads
        (the crossings and their margins: a dwell's and a zeroing skirt's are fitted again
        as the report reads them), NaN elsewhere. With the full result in
        scratch files (``process_arrays(..., scratch=True)``, one revolution per fit) its
        run-sized arrays are :class:`~.history.ScratchRows` (read by rows), every revolution's.
    probe_tw : TravellingWaveSpectra or None
        Per revolution and probe, shape (n_rev, n_probes, n_nd), first EO (None when the
        report alone was asked for: ``process_arrays(..., spectra=False)``).
    fit_tw : TravellingWaveSpectra or None
        Per revolution from the fits, shape (n_rev, n_nd), first EO (None likewise). Both
        spectra's magnitudes are :class:`~.history.ScratchRows` with the full result in
        scratch files, as are the displacements' ``d_m`` and ``toa_s``.
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
    probe_tw: TravellingWaveSpectra | None
    fit_tw: TravellingWaveSpectra | None
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

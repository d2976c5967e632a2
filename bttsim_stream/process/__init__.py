"""BTT processing: OPR and TOAs to blade vibration, travelling waves and resonances.

One module per stage (paper equations in brackets):

* :mod:`.displacement` -- speed and expected arrival times from the OPR, blade
  identification, Eq. 1 displacements;
* :mod:`.detect` -- what the run holds: speed segments (ramps, dwells), resonance
  crossings per engine order with their detection statistic, the zeroing reference;
* :mod:`.peak_finding` -- a curve's interior peaks and their prominences (scipy's
  ``find_peaks``, in numpy: scipy.signal is slow to import);
* :mod:`.prep` -- data preparation (Sec. 2.3): offset removal and noise reduction;
* :mod:`.fit` -- windowed multi-EO sine fits (Eq. 16-17);
* :mod:`.methods` -- resonance per blade through a crossing: peak, swept SDOF, CFF;
* :mod:`.resonance` -- entries per crossing and dwell, E_A and E_f (Eq. 18-19), status,
  the summary JSON;
* :mod:`.travelling_wave` -- nodal diameter spectra (Fig. 10);
* :mod:`.nsv` -- non-synchronous vibration (flutter, rotating stall): order alias, ND,
  amplitude per block of revolutions, never a resonance;
* :mod:`.probes` -- condition number of ``B`` and probe layout search (Table 3);
* :mod:`.options` -- :class:`ProcessOptions` and which engine orders are fitted;
* :mod:`.results` -- the result dataclasses (shared with the codec and the views);
* :mod:`.pipeline` -- offline :func:`process_arrays`;
* :mod:`.streaming` -- :class:`StreamingProcessor`, revolution by revolution.

The paper's Table 2 / Table 3 / ND checks on simulated runs are in
:mod:`bttsim_stream.paper.validate_processing` (this package never imports the simulator).

Conventions: arrays ``(revolution, blade, probe)``, SI units (s, m, rad, rad/s; Hz for
frequencies), amplitudes peak-to-peak, blades and probes numbered from 0, NaN for a
missing arrival. Nothing here imports the transport, codec or viewer layers.
"""

import importlib
from typing import TYPE_CHECKING

#: Each public name -> the module that defines it. The submodules load on first use (PEP 562):
#: the codec needs the result dataclasses, not the pipeline, the detector or scipy.
_SOURCES = {
    **dict.fromkeys(('Displacements', 'DoublePulses', 'Geometry', 'assign_extra_edges', 'RotorPhase',
                     'btt_displacement', 'calibrate_arrival_angles', 'compute_displacements',
                     'expected_times', 'identify_blades', 'mean_speed_from_opr', 'rotor_phase_from_opr',),
                    'displacement'),
    **dict.fromkeys(('Crossing', 'DetectOptions', 'Reference', 'RunSegments', 'choose_reference',
                     'detect_crossings', 'predicted_response', 'speed_segments',), 'detect'),
    **dict.fromkeys(('SineFit', 'design_matrix', 'fit_revolutions', 'sine_at_probes',), 'fit'),
    **dict.fromkeys(('METHODS', 'cff_method', 'peak_method', 'sdof_method',), 'methods'),
    **dict.fromkeys(('ProcessOptions', 'engine_orders_of',), 'options'),
    **dict.fromkeys(('process_arrays',), 'pipeline'),
    **dict.fromkeys(('ProcessingResult', 'RevolutionFit', 'RevolutionOutput',), 'results'),
    **dict.fromkeys(('StreamingProcessor',), 'streaming'),
    **dict.fromkeys(('Baseline', 'PreparedData', 'PrepOptions', 'ResonanceRegion', 'fit_baseline', 'locate_resonance',
                     'prepare', 'remove_offset', 'smooth_revolutions', 'speed_adaptive_half_width',), 'prep'),
    **dict.fromkeys(('LayoutCandidate', 'LayoutError', 'check_layout', 'condition_number', 'layout_report',
                     'rank_layouts',), 'probes'),
    **dict.fromkeys(('Detection', 'ResonanceEntry', 'ResonancePeaks', 'ResonanceReport', 'TruthPeaks',
                     'TruthPeakTracker', 'TruthRows', 'find_peaks', 'resonance_errors', 'resonance_report',
                     'summary_table', 'truth_peaks', 'window_truth',), 'resonance'),
    **dict.fromkeys(('TravellingWaveSpectra', 'fit_spectra', 'identify_nd', 'probe_spectra', 'signed_nd',),
                    'travelling_wave'),
    **dict.fromkeys(('NsvDetection', 'NsvOptions', 'NsvScan', 'detect_nsv', 'scan_blocks',), 'nsv'),
}

if TYPE_CHECKING:  # for readers and type checkers: the eager form
    from .displacement import (Displacements, DoublePulses, Geometry, assign_extra_edges, RotorPhase, btt_displacement,
                               calibrate_arrival_angles, compute_displacements, expected_times, identify_blades,
                               mean_speed_from_opr, rotor_phase_from_opr)
    from .detect import (Crossing, DetectOptions, Reference, RunSegments, choose_reference, detect_crossings,
                         predicted_response, speed_segments)
    from .fit import SineFit, design_matrix, fit_revolutions, sine_at_probes
    from .methods import METHODS, cff_method, peak_method, sdof_method
    from .options import ProcessOptions, engine_orders_of
    from .pipeline import process_arrays
    from .results import ProcessingResult, RevolutionFit, RevolutionOutput
    from .streaming import StreamingProcessor
    from .prep import (Baseline, PreparedData, PrepOptions, ResonanceRegion, fit_baseline, locate_resonance, prepare,
                       remove_offset, smooth_revolutions, speed_adaptive_half_width)
    from .probes import LayoutCandidate, LayoutError, check_layout, condition_number, layout_report, rank_layouts
    from .resonance import (Detection, ResonanceEntry, ResonancePeaks, ResonanceReport, TruthPeaks, TruthPeakTracker,
                            TruthRows, find_peaks, resonance_errors, resonance_report, summary_table, truth_peaks,
                            window_truth)
    from .travelling_wave import TravellingWaveSpectra, fit_spectra, identify_nd, probe_spectra, signed_nd
    from .nsv import NsvDetection, NsvOptions, NsvScan, detect_nsv, scan_blocks

__all__ = [
    "Geometry", "RotorPhase", "Displacements", "mean_speed_from_opr", "rotor_phase_from_opr",
    "calibrate_arrival_angles", "expected_times", "btt_displacement", "compute_displacements",
    "identify_blades", "DoublePulses", "assign_extra_edges",
    "PrepOptions", "ResonanceRegion", "PreparedData", "Baseline", "locate_resonance", "fit_baseline", "remove_offset",
    "smooth_revolutions", "speed_adaptive_half_width", "prepare",
    "SineFit", "design_matrix", "fit_revolutions", "sine_at_probes",
    "DetectOptions", "RunSegments", "Crossing", "Reference", "speed_segments", "detect_crossings", "choose_reference",
    "predicted_response", "METHODS", "peak_method", "sdof_method", "cff_method",
    "Detection", "ResonanceEntry", "TruthRows", "window_truth", "LayoutError", "check_layout", "layout_report",
    "ResonancePeaks", "TruthPeaks", "TruthPeakTracker", "ResonanceReport", "find_peaks", "truth_peaks",
    "resonance_errors", "resonance_report", "summary_table",
    "TravellingWaveSpectra", "probe_spectra", "fit_spectra", "identify_nd", "signed_nd",
    "condition_number", "LayoutCandidate", "rank_layouts",
    "ProcessOptions", "ProcessingResult", "RevolutionFit", "RevolutionOutput", "StreamingProcessor", "process_arrays",
    "engine_orders_of",
    "NsvOptions", "NsvScan", "NsvDetection", "detect_nsv", "scan_blocks",
]


def __getattr__(name: str):
    """A public name, imported from its module on first use (then cached here)."""
    mod = _SOURCES.get(name)
    if mod is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{mod}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))

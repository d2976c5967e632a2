"""What the processing computes: its options, and the engine orders it fits.

:class:`ProcessOptions` is shared by the offline pipeline (:mod:`.pipeline`), the streaming
processor (:mod:`.streaming`) and the views; :func:`engine_orders_of`,
:func:`layout_condition_numbers` and :func:`fits_jointly` decide, the same way for both
paths, which engine orders are fitted and whether together.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .detect import DetectOptions
from .displacement import Geometry
from .methods import METHODS
from .nsv import NsvOptions
from .prep import PrepOptions
from .probes import CN_SINGULAR, LayoutError, condition_number
from .resonance import PEAK_METHODS

__all__ = ["EXPECTED_TIMES", "CN_JOINT_MAX", "LIVE_CALIBRATION", "ProcessOptions", "engine_orders_of",
           "layout_condition_numbers", "fits_jointly"]

EXPECTED_TIMES = ("opr", "exact")
#: Joint fits of several engine orders are used when their condition number is below this;
#: above, each order is fitted on its own (and the orders are told apart by their residuals).
CN_JOINT_MAX = 100.0

#: Calibration window (revolutions from the start) of every live consumer of a stream, the
#: streaming processor's per-revolution outputs and the views, when the final report's window
#: is chosen automatically: the live outputs cannot wait for the whole run.
LIVE_CALIBRATION = 64


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
    peak_method : {"fit", "max", "parabolic", "sdof"}
        Refinement of the ``"peak"`` method: ``"fit"`` the vertex of a parabola through the
        unsmoothed amplitudes over a quarter of the half-power width each side
        (:func:`~bttsim_stream.process.methods.quadratic_peak`); ``"max"`` the largest
        prepared amplitude (the paper's definition); ``"parabolic"`` a parabola through 5
        prepared revolutions each side (legacy: ``"sdof"`` here is an amplitude-only
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
    peak_method: str = "fit"
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
        if isinstance(cal, (int, np.integer)) and not isinstance(cal, bool) and cal < 0:
            raise ValueError(f"calibration must be a window of >= 0 revolutions, got {cal}")
        if isinstance(cal, (tuple, list)) and not (
                len(cal) == 2 and all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in cal)
                and 0 <= cal[0] < cal[1]):
            raise ValueError(f"calibration must be (start, stop) revolutions with 0 <= start < stop, got {cal!r}")


def engine_orders_of(info, options: ProcessOptions) -> tuple:
    """The EOs of the per-revolution fits: the options', else the metadata's, else ``(8,)``."""
    if options.engine_orders:
        return tuple(options.engine_orders)
    eos = tuple(int(e) for e in (getattr(info, "engine_orders", None) or ()))
    return tuple(dict.fromkeys(eos)) or (8,)


def layout_condition_numbers(eos, geometry: Geometry, scan: bool) -> tuple[tuple, dict, list]:
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


def fits_jointly(eos: tuple, geometry: Geometry) -> bool:
    """Whether several engine orders are fitted together: enough probes for their unknowns
    and a condition number below :data:`CN_JOINT_MAX` (one order: False)."""
    return (len(eos) > 1 and geometry.n_probes >= 1 + 2 * len(eos)
            and condition_number(eos, np.rad2deg(geometry.probe_angles_rad)) < CN_JOINT_MAX)

"""Rerun entity paths of the views, written once (the views log to them, the blueprint shows them).

The words are those of the bus keys and the library: ``tw``, ``probe``, ``fit``, ``eo``,
``displacement``, ``rotor``, ``campbell``, ``resonance``; display units end the leaf names
(``_mm``, ``_deg``, ``_hz``, ``_rpm``). ``docs/views.md`` lists every entity.
"""

from __future__ import annotations

__all__ = ["tw_path", "tw_map_path", "signal_path", "displacement_path", "fit_path", "fit_rpm_path", "SPEED",
           "TRUTH_AMP", "TW_ND",
           "ROTOR", "CAMPBELL", "RESONANCE_TABLE", "RESONANCE_BARS", "NSV_AMP", "NSV_REV_AMP", "NSV_ND", "NSV_ORDER",
           "NSV_TW", "NSV_TABLE"]

#: Speed of each revolution, rpm (time series).
SPEED = "speed/rpm"
#: The truth's d_eqv peak-to-peak envelope per blade, mm (time series).
TRUTH_AMP = "truth/amp_pkpk_mm"
#: Signed nodal diameter of each revolution, identified by the processor (time series).
TW_ND = "tw/nd"
#: Root of the rotor view (2-D, in units of the tip radius).
ROTOR = "rotor"
#: Root of the Campbell diagram (2-D plot: rpm, Hz).
CAMPBELL = "campbell"
#: The resonance report as markdown.
RESONANCE_TABLE = "resonance/table"
#: Resonant amplitude per blade, mm (bar charts ``btt`` and ``d_eqv`` below it).
RESONANCE_BARS = "resonance/amp_pkpk_mm"

#: Non-synchronous vibration: pk-pk amplitude of each detected block, mm (time series).
NSV_AMP = "nsv/amp_pkpk_mm"
#: Non-synchronous vibration: blade-RMS pk-pk amplitude of every revolution of a detection, mm.
NSV_REV_AMP = "nsv/rev_amp_pkpk_mm"
#: Signed ND of each detected block (time series).
NSV_ND = "nsv/nd"
#: Order f / f_shaft of each detected block (time series).
NSV_ORDER = "nsv/order"
#: The latest NSV block's travelling-wave spectrum by signed ND, mm (bar chart).
NSV_TW = "nsv/tw_mm"
#: The report's NSV detections (markdown).
NSV_TABLE = "nsv/table"


def tw_path(probe: int) -> str:
    """Travelling-wave matrix of one probe: ``tw/probe_<j>``."""
    return f"tw/probe_{int(probe)}"


def tw_map_path(probe: int) -> str:
    """The travelling-wave matrix drawn with ND and revolution ticks and a colour bar (2-D;
    data under ``data/``): ``tw/probe_<j>/map``."""
    return f"{tw_path(probe)}/map"


def signal_path(probe: int) -> str:
    """Raw signal plot of one probe (2-D; data under ``data/``): ``signal/probe_<j>``."""
    return f"signal/probe_{int(probe)}"


def displacement_path(probe: int) -> str:
    """Parent of one probe's raw Eq. 1 displacement (``btt``) and d_eqv (``d_eqv``):
    ``displacement/probe_<j>``."""
    return f"displacement/probe_{int(probe)}"


def fit_path(engine_order: int) -> str:
    """Parent of one engine order's fit series (``amp_pkpk_mm``, ``phase_deg``, ``freq_hz``):
    ``fit/eo_<k>``."""
    return f"fit/eo_{int(engine_order)}"


def fit_rpm_path(engine_order: int) -> str:
    """One engine order's amplitude-against-speed plot (2-D): ``fit/eo_<k>/vs_rpm``."""
    return f"{fit_path(engine_order)}/vs_rpm"

"""The default layout of the views, built in one place (:func:`build_blueprint`)."""

from __future__ import annotations

from collections.abc import Sequence

import rerun.blueprint as rrb

from . import paths
from ._plot2d import plot_bounds

__all__ = ["build_blueprint"]


def _tw_view(probe: int, live: bool) -> rrb.Spatial2DView:
    span = " (rolling window)" if live else ""
    return rrb.Spatial2DView(
        origin=paths.tw_map_path(probe), visual_bounds=rrb.VisualBounds2D(x_range=[-0.12, 1.3], y_range=[-0.72, 0.1]),
        name=f"Travelling wave (mm pk-pk), probe {probe}: signed ND by revolution{span}")


def _series_view(origin: str, name: str, contents=None, legend: bool = True) -> rrb.TimeSeriesView:
    """A time-series view of the whole run (not a window around the time cursor)."""
    whole = rrb.TimeRange(start=rrb.TimeRangeBoundary.infinite(), end=rrb.TimeRangeBoundary.infinite())
    extra = {} if contents is None else {"contents": contents}
    return rrb.TimeSeriesView(origin=origin, name=name, axis_x=rrb.TimeAxis(view_range=whole),
                              plot_legend=rrb.PlotLegend(visible=legend), **extra)


def _amplitude_view(eo: int) -> rrb.TimeSeriesView:
    return _series_view(paths.fit_path(eo), f"Amplitude pk-pk (mm), EO {eo}: fit (colour), d_eqv truth (grey)",
                        ["+ $origin/amp_pkpk_mm", f"+ /{paths.TRUTH_AMP}"], legend=False)


def _amplitude_rpm_view(eo: int) -> rrb.Spatial2DView:
    """Amplitude against speed: every revolution up to the time cursor."""
    upto = [rrb.VisibleTimeRange("revolution", start=rrb.TimeRangeBoundary.infinite(),
                                 end=rrb.TimeRangeBoundary.cursor_relative(seq=0)),
            rrb.VisibleTimeRange("time", start=rrb.TimeRangeBoundary.infinite(),
                                 end=rrb.TimeRangeBoundary.cursor_relative(seconds=0.0))]
    return rrb.Spatial2DView(origin=paths.fit_rpm_path(eo), visual_bounds=plot_bounds(), time_ranges=upto,
                             name=f"Amplitude pk-pk (mm) against speed (rpm) and f_BTT (Hz), EO {eo}")


def _displacement_view(probe: int) -> rrb.TimeSeriesView:
    return _series_view(paths.displacement_path(probe),
                        f"Raw BTT displacement (mm), probe {probe}: Eq. 1 (points), d_eqv (line)")


def _rotor_view() -> rrb.Spatial2DView:
    return rrb.Spatial2DView(origin=paths.ROTOR, name="Rotor at each OPR (tip deflection x exaggeration)",
                             visual_bounds=rrb.VisualBounds2D(x_range=[-1.5, 1.5], y_range=[-1.5, 1.5]))


def _campbell_view() -> rrb.Spatial2DView:
    return rrb.Spatial2DView(origin=paths.CAMPBELL, name="Campbell diagram (x: rpm, y: Hz)",
                             visual_bounds=plot_bounds())


def _signal_view(probe: int) -> rrb.Spatial2DView:
    return rrb.Spatial2DView(origin=paths.signal_path(probe), visual_bounds=plot_bounds(),
                             name=f"Raw signal (V against us), probe {probe}: samples, trigger level, TOA (red)")


def _table_view() -> rrb.TextDocumentView:
    return rrb.TextDocumentView(origin=paths.RESONANCE_TABLE, name="Resonance per blade")


def _fits_tab(eo: int) -> rrb.Vertical:
    return rrb.Vertical(
        rrb.Horizontal(_amplitude_view(eo), _amplitude_rpm_view(eo)),
        _series_view(f"{paths.fit_path(eo)}/phase_deg", f"Fitted phase (deg), EO {eo}", legend=False),
        rrb.Horizontal(_series_view(paths.SPEED, "Speed (rpm, from the OPR)"),
                       _series_view(f"{paths.fit_path(eo)}/freq_hz", f"Frequency f_BTT (Hz), EO {eo}")),
        row_shares=[3, 2, 2], name=f"Fits EO {eo}")


def build_blueprint(n_probes: int, *, n_blades: int | None = None, engine_orders: Sequence[int] = (8,),
                    live: bool = False, active_tab: int = 0, signal_probe: int | None = None,
                    non_synchronous: bool = False) -> rrb.Blueprint:
    """The default layout of the bttsim views.

    Tabs: *Overview* (travelling wave of probe 0, amplitude of the first EO against speed, rotor,
    displacement at probe 0, Campbell diagram, resonance table), one *Fits EO k* per engine
    order (amplitude against revolution and against speed, phase, speed, frequency),
    *Travelling wave* (every probe and the identified ND), *Displacement* (every probe),
    *Rotor & Campbell*, *Resonance* (table and per-blade amplitude bars), *Raw signal*
    when ``signal_probe`` is given (the bus carries raw probe signals), and *Non-synchronous*
    (NSV amplitude growth, its travelling wave by ND, ND, order, detections) when
    ``non_synchronous`` (the processor reported one).

    Parameters
    ----------
    n_probes : int
    n_blades : int, optional
        Not needed any more (the travelling-wave maps draw their ND ticks); accepted for callers.
    engine_orders : sequence of int
        The fitted engine orders (one *Fits* tab each; the first in the overview).
    live : bool
        Names the travelling-wave views as rolling windows.
    active_tab : int
    signal_probe : int, optional
        Probe of the *Raw signal* tab (None: no such tab).
    non_synchronous : bool
        Add the *Non-synchronous* tab.
    """
    eos = list(dict.fromkeys(int(e) for e in engine_orders)) or [8]
    overview = rrb.Grid(_tw_view(0, live), _amplitude_rpm_view(eos[0]), _rotor_view(), _displacement_view(0),
                        _campbell_view(), _table_view(), grid_columns=3, name="Overview")
    tw = rrb.Grid(*[_tw_view(j, live) for j in range(int(n_probes))],
                  _series_view(paths.TW_ND, "Identified ND (backward < 0)"), name="Travelling wave")
    disp = rrb.Grid(*[_displacement_view(j) for j in range(int(n_probes))], name="Displacement")
    rotor = rrb.Horizontal(_rotor_view(), _campbell_view(), name="Rotor & Campbell")
    resonance = rrb.Horizontal(
        _table_view(),
        rrb.BarChartView(origin=paths.RESONANCE_BARS,
                         name="Resonant amplitude pk-pk (mm) per blade: BTT (left), d_eqv (right)"),
        name="Resonance")
    nsv = rrb.Vertical(
        rrb.Horizontal(_series_view("nsv", "Non-synchronous vibration: amplitude pk-pk (mm), per revolution "
                                           "(line) and per block (points)",
                                    contents=[f"/{paths.NSV_AMP}", f"/{paths.NSV_REV_AMP}"]),
                       rrb.BarChartView(origin=paths.NSV_TW, name="NSV travelling wave (mm) by signed ND, "
                                                                 "forward +(n_nd-1) first .. backward last")),
        rrb.Horizontal(_series_view(paths.NSV_ND, "NSV ND (backward < 0)"),
                       _series_view(paths.NSV_ORDER, "NSV order f / f_shaft"),
                       rrb.TextDocumentView(origin=paths.NSV_TABLE, name="NSV detections")),
        name="Non-synchronous")
    return rrb.Blueprint(
        rrb.Tabs(overview, *[_fits_tab(e) for e in eos], tw, disp, rotor, resonance,
                 *([] if signal_probe is None else [rrb.Horizontal(_signal_view(signal_probe), name="Raw signal")]),
                 *([nsv] if non_synchronous else []),
                 active_tab=active_tab),
        rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline="revolution"))

"""Fits view: amplitude, phase and frequency of every engine order, against revolution and speed.

Per engine order ``k`` (one ``BladeFits`` message per EO and revolution, a
:class:`~bttsim_stream.process.results.RevolutionFit`):

* ``fit/eo_<k>/amp_pkpk_mm``, ``fit/eo_<k>/phase_deg``: one series per blade (phase wrapped
  to (-180, 180]); ``fit/eo_<k>/freq_hz``: ``f_BTT = EO Omega / (2 pi)`` (Eq. 17);
* ``fit/eo_<k>/vs_rpm``: the amplitude of every blade against the revolution's speed, a 2-D
  plot (:mod:`._plot2d`) whose x ticks give the speed in rpm and, below, the frequency
  ``EO rpm / 60`` in Hz (which is ``f_BTT``: amplitude against frequency is the same
  plot), with the truth's d_eqv envelope in grey behind the fits.

The truth's d_eqv envelope per blade (``TruthBatch.d_eqv_pkpk_m``) is also a series,
``truth/amp_pkpk_mm``, shown under the fitted amplitudes. The speed series ``speed/rpm``
(from the OPR pulses, :class:`SpeedView`) is shown next to the frequency.
"""

from __future__ import annotations

from collections import deque

import numpy as np
import rerun as rr

from . import paths
from ._common import GREY, LIGHT_GREY, MM, RevIndex, ViewOutput, palette, rpm
from ._plot2d import PlotFrame, ui
from .revolutions import ShownRevolutions

__all__ = ["TRUTH_HISTORY", "FitsView", "SpeedView", "speed_axis_range"]

#: Revolutions of the truth's envelope kept for a plot of an engine order whose first fit
#: comes later (drawn behind its fits from then on): memory bounded whatever the run's length.
TRUTH_HISTORY = 8192


def speed_axis_range(speed_range_rpm) -> tuple[float, float] | None:
    """x range of a plot against speed: the run's speed range with 2 % margins (at least
    10 rpm); None when the range is unknown (``(0, 0)``: the plot takes it from the data)."""
    lo, hi = (float(v) for v in speed_range_rpm)
    if not (np.isfinite(lo) and np.isfinite(hi)) or hi <= 0:
        return None
    pad = max(0.02 * (hi - lo), 10.0)
    return max(lo - pad, 0.0), hi + pad


class _EoPlot:
    """One engine order's amplitude-against-speed plot.

    Live, the frame widens as points come; for a whole recording (logged in batches) it is
    drawn once, by :meth:`settle`, for all the points: the truth's first, then the fits'.
    """

    def __init__(self, out: ViewOutput, engine_order: int, x_range, n_blades: int) -> None:
        eo = int(engine_order)
        self.out = out
        self.frame = PlotFrame(out, paths.fit_rpm_path(eo), x_range, (0.0, 0.0),
                               x_label=lambda x: f"{x:g} rpm\n{eo * x / 60.0:.4g} Hz", y_label=lambda y: f"{y:g} mm")
        self.colors = palette(n_blades)
        out.style(f"{self.frame.data_path}/fit", rr.Points2D.from_fields(radii=ui(1.5), draw_order=10.0))
        out.style(f"{self.frame.data_path}/d_eqv", rr.Points2D.from_fields(radii=ui(1.0), colors=[LIGHT_GREY],
                                                                           draw_order=5.0))
        self._extent: dict[str, tuple[float, float, float]] = {}  # what -> (x lo, x hi, y top), not yet drawn

    def _include(self, what: str, x: np.ndarray, top: float) -> None:
        if self.out.live:
            self.frame.include(x, [top])
            return
        lo, hi = float(x.min()), float(x.max())
        if what in self._extent:
            lo0, hi0, top0 = self._extent[what]
            lo, hi, top = min(lo, lo0), max(hi, hi0), max(top, top0)
        self._extent[what] = (lo, hi, top)

    def settle(self) -> None:
        """Draw the frame for the points logged so far (a whole recording; live: drawn already)."""
        for what in ("d_eqv", "fit"):
            if what in self._extent:
                lo, hi, top = self._extent.pop(what)
                self.frame.include([lo, hi], [top])

    def points(self, what: str, index: RevIndex, speed_rpm: np.ndarray, amp_mm: np.ndarray, colors=None) -> None:
        """Points ``(speed, amplitude)`` of each blade, one row per revolution (NaN left out)."""
        x = np.broadcast_to(np.asarray(speed_rpm, float)[:, None], amp_mm.shape)
        ok = np.isfinite(amp_mm) & np.isfinite(x)
        if not ok.any():
            return
        self._include(what, x[ok], max(float(np.max(amp_mm[ok])), 1e-3))
        columns = {"positions": np.stack([x[ok], amp_mm[ok]], axis=-1)}
        if colors is not None:
            columns["colors"] = np.broadcast_to(colors[None], amp_mm.shape + (3,))[ok]
        self.out.columns(f"{self.frame.data_path}/{what}", index, rr.Points2D.columns(**columns), ok.sum(axis=1))


class FitsView:
    """Per-EO fit series and amplitude-against-speed plots, and the truth's envelope.

    Parameters
    ----------
    out : ViewOutput
    info : RunInfo
        The run metadata (blade count, speed range).

    Attributes
    ----------
    engine_orders : list of int
        The engine orders seen so far, in order of appearance.
    """

    def __init__(self, out: ViewOutput, info) -> None:
        self.out = out
        self.n_blades = int(info.n_blades)
        self.x_range = speed_axis_range(info.speed_range_rpm)
        self.engine_orders: list[int] = []
        self._plots: dict[int, _EoPlot] = {}
        self._fits: list = []
        self._truth: list = []
        # (index, rpm, pk-pk mm) of the last TRUTH_HISTORY revolutions (at least), oldest first
        self._truth_seen: deque[tuple[RevIndex, np.ndarray, np.ndarray]] = deque()
        self._truth_kept = 0
        self.count = {"fits": 0, "truth": 0}

    def add(self, decoded) -> None:
        """A ``fit`` message (:class:`~bttsim_stream.process.results.RevolutionFit` body)."""
        if decoded.body.n_blades == self.n_blades:
            self._fits.append(decoded)

    def add_truth(self, decoded) -> None:
        """A ``truth`` message (one revolution's :class:`~bttsim_stream.sim.core.Truth`)."""
        if decoded.body.d_eqv_pkpk_m.shape == (1, self.n_blades):
            self._truth.append(decoded)

    def _plot(self, eo: int) -> _EoPlot:
        """The plot of ``eo`` (made on first use, with the truth seen so far)."""
        plot = self._plots.get(eo)
        if plot is None:
            plot = self._plots[eo] = _EoPlot(self.out, eo, self.x_range, self.n_blades)
            self.engine_orders.append(eo)
            for index, speed, amp in self._truth_seen:
                plot.points("d_eqv", index, speed, amp)
        return plot

    def flush(self, final: bool = False) -> None:
        """Log what arrived since the last flush."""
        truth, self._truth = self._truth, []
        if truth:
            self._flush_truth(truth)
        fits, self._fits = self._fits, []
        by_eo: dict[int, list] = {}
        for d in fits:
            by_eo.setdefault(int(d.body.engine_order), []).append(d)
        for eo, rows in by_eo.items():
            self._flush_eo(eo, rows)
        if final:
            for plot in self._plots.values():
                plot.settle()

    def _flush_truth(self, rows: list) -> None:
        self.count["truth"] += len(rows)
        index = RevIndex.from_headers([d.header for d in rows])
        amp = np.concatenate([d.body.d_eqv_pkpk_m for d in rows]) * MM  # (n, nb)
        speed = rpm(np.concatenate([d.body.omega_mean for d in rows]))
        nb = self.n_blades
        self.out.style(paths.TRUTH_AMP, rr.SeriesLines(names=[f"blade {b} d_eqv" for b in range(nb)],
                                                       colors=[GREY] * nb, widths=[1.0] * nb))
        self.out.scalars(paths.TRUTH_AMP, index, amp)
        self._truth_seen.append((index, speed, amp))
        self._truth_kept += len(index)
        while self._truth_kept - len(self._truth_seen[0][0]) >= TRUTH_HISTORY:  # the oldest are not needed
            self._truth_kept -= len(self._truth_seen.popleft()[0])
        for plot in self._plots.values():
            plot.points("d_eqv", index, speed, amp)

    def _flush_eo(self, eo: int, rows: list) -> None:
        self.count["fits"] += len(rows)
        plot = self._plot(eo)
        index = RevIndex.from_headers([d.header for d in rows])
        fits = [d.body for d in rows]
        nb, root = self.n_blades, paths.fit_path(eo)
        names = [f"blade {b}" for b in range(nb)]
        amp = np.stack([f.amp_pkpk_m for f in fits]) * MM
        self.out.style(f"{root}/amp_pkpk_mm", rr.SeriesLines(names=names, colors=plot.colors, widths=[1.5] * nb))
        self.out.scalars(f"{root}/amp_pkpk_mm", index, amp)
        self.out.style(f"{root}/phase_deg", rr.SeriesPoints(names=names, colors=plot.colors, marker_sizes=[1.5] * nb))
        phase = np.rad2deg(np.angle(np.exp(1j * np.stack([f.phase_rad for f in fits]))))
        self.out.scalars(f"{root}/phase_deg", index, phase)
        self.out.style(f"{root}/freq_hz", rr.SeriesLines(names=f"f_BTT, EO {eo} (Hz)", colors=[(31, 119, 180)]))
        self.out.scalars(f"{root}/freq_hz", index, np.array([f.freq_hz for f in fits]))
        plot.points("fit", index, rpm([f.omega_rad_s for f in fits]), amp, plot.colors)


class SpeedView:
    """The speed of each revolution, ``speed/rpm`` (mean over the revolution, from the OPR pulses)."""

    def __init__(self, out: ViewOutput) -> None:
        self.out = out
        out.style(paths.SPEED, rr.SeriesLines(names="speed (rpm)", colors=[(40, 40, 40)]))

    def update(self, rows: ShownRevolutions) -> None:
        """Log revolutions ready to be shown."""
        self.out.scalars(paths.SPEED, RevIndex.of(rows.revolution, rows.opr_s), rpm(rows.omega_rad_s))

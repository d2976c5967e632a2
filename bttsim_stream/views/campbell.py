"""Campbell diagram: frequency against speed, from the run metadata alone.

Everything comes from the metadata (:class:`~bttsim_stream.sim.core.RunInfo`): the mode
family frequencies per nodal diameter (``family_freq_hz``: horizontal lines for a model at
zero speed; a speed-dependent model's ``family_freq_hz_at_speed`` at ``family_speed_rad_s``:
curves, interpolated between those speeds as the simulator interpolates the modes,
:func:`~bttsim_stream.model.speed_modes.interpolate_freq_hz`, and drawn up to the model's
last speed, never extrapolated), the run's speed range (``speed_range_rpm``), the excited
engine orders and nodal diameters. The FE model is never rebuilt and the scenario never
parsed here.

A 2-D plot (:mod:`._plot2d`) below ``campbell``: x the speed (rpm, 0 to a round value
above the run's top speed), y the frequency (Hz, up to 1.25 times the largest excited EO
line's value at the right edge). ``campbell/data/engine_orders`` (EO 1..12 lines
``f = EO rpm / 60``, excited EOs red), ``families``, ``run_range`` (the run's speed range),
``resonance`` (each excited EO's crossings with its ND in every family: where the EO line
meets the family's line or curve; the ND is the force's own, set by its travelling-wave
phase, Eq. 5-7, which a legend label "force: EO 8 x ND 1" states), ``labels``, all static;
``speed`` (the current speed, one line per revolution).

Labels are laid out so that they do not overlap (:func:`~._plot2d.place_labels`): an EO
line's label sits just outside the box where the line leaves it (right edge for shallow
lines, top edge for steep ones), or else along the line inside the box; a label with no room
is left out (the line keeps its colour), the excited EOs' first.
"""

from __future__ import annotations

import math

import numpy as np
import rerun as rr

from ..speed_spline import interpolate_freq_hz
from . import paths
from ._common import FAMILY_COLORS, GREEN, RED, TWO_PI, RevIndex, ViewOutput, nice_step, rpm
from ._plot2d import LINE_H, PLOT_HEIGHT, Label, PlotFrame, label_box, place_labels, ui
from .revolutions import ShownRevolutions

__all__ = ["MAX_EO", "CampbellLayout", "CampbellView", "frequency_span_text"]

#: Engine order lines drawn: 1 .. MAX_EO (or more when the run excites a higher EO).
MAX_EO = 12
_EO_GREY = (170, 170, 170)
_GAP = 0.015
#: Points of a speed-dependent family curve across the plot, and of the refinement of an EO
#: crossing inside one interval of them (then linear: the crossing to about 1e-4 rpm).
_CURVE_POINTS = 401
_REFINE_POINTS = 101


def frequency_span_text(lo_hz: float, hi_hz: float) -> str:
    """A family's frequency span as label text: ``"344-347 Hz"`` in whole Hz when that tells
    the ends apart, else to 0.1 Hz (``"817.9-818.3 Hz"``), and one value when they are equal
    to 0.1 Hz (``"817.9 Hz"``, a single line)."""
    for decimals in (0, 1):
        lo, hi = f"{lo_hz:.{decimals}f}", f"{hi_hz:.{decimals}f}"
        if lo != hi:
            return f"{lo}-{hi} Hz"
    return f"{lo} Hz"


def _inside(x: np.ndarray, y: np.ndarray, y_top: float) -> list[np.ndarray]:
    """The pieces of the polyline ``(x, y)`` with ``0 < y < y_top``, as ``(n, 2)`` arrays, each
    ended where it leaves that band (linear between points)."""
    ok = (y > 0) & (y < y_top)
    out = []
    edges = np.flatnonzero(np.diff(np.concatenate([[0], ok.view(np.int8), [0]])))
    for a, b in zip(edges[::2], edges[1::2]):  # ok[a:b] all True
        pts = [np.stack([x[a:b], y[a:b]], axis=-1)]
        for i, j in ((a - 1, a), (b, b - 1)):  # neighbour outside, inside point
            if 0 <= i < y.size:
                edge = y_top if y[i] >= y_top else 0.0
                t = (edge - y[j]) / (y[i] - y[j])
                pt = np.array([[x[j] + t * (x[i] - x[j]), edge]])
                pts.insert(0 if i < j else len(pts), pt)
        line = np.concatenate(pts)
        if line.shape[0] >= 2:
            out.append(line)
    return out


def _signed_nd(nd: int, n_blades: int) -> int:
    """The scenario's ND (0 .. n_blades - 1) as a signed ND (negative: backward)."""
    k = int(nd) % n_blades
    return k if k <= n_blades // 2 else k - n_blades


class CampbellLayout:
    """Geometry and labels of the Campbell diagram of a run (numpy only).

    Parameters
    ----------
    info : RunInfo
    speed_range_rpm : (float, float), optional
        The run's speed range (default the metadata's).
    run_range : bool
        Draw and label the speed range as the run's (False: it is only what was seen so far).

    Attributes
    ----------
    x_top_rpm, f_top_hz : float
        Right and top edges of the plot.
    engine_orders : ndarray of int
        The lines drawn: 1 .. MAX_EO, or up to the largest excited EO.
    excited : tuple of int
        The run's engine orders.
    crossings : list of (rpm, Hz, text)
        Excited EO x ND crossings with each family inside the plot.
    curve_rpm : ndarray, shape (n,), or None
        A speed-dependent model's curves: their speeds, rpm (0 to the plot's right edge or
        the model's last speed, whichever is lower); None: horizontal family lines.
    curve_hz : ndarray, shape (n, n_families, n_blades // 2 + 1), or None
        The family frequencies at ``curve_rpm``, Hz.
    labels : list of (text, (cx, cy), colour)
        The placed labels, box units (see :mod:`._plot2d`).
    """

    def __init__(self, info, speed_range_rpm=None, *, run_range: bool = True) -> None:
        lo, hi = (float(v) for v in (info.speed_range_rpm if speed_range_rpm is None else speed_range_rpm))
        self.speed_range_rpm = (lo, hi)
        self.run_range = bool(run_range) and hi > 0
        top = 1.1 * max(hi, 1.0)
        step = nice_step(top, 5)
        self.x_top_rpm = math.ceil(top / step - 1e-9) * step
        self.excited = tuple(dict.fromkeys(int(e) for e in info.engine_orders))
        self.f_top_hz = 1.25 * max(self.excited or (8,)) * self.x_top_rpm / 60.0
        self.engine_orders = np.arange(1, max(MAX_EO, *self.excited, 1) + 1)
        self.n_blades = int(info.n_blades)
        fam = info.family_freq_hz
        self.families = None if fam is None else np.asarray(fam, float)
        self._speeds = self._table = None
        self.curve_rpm = self.curve_hz = None
        if self.families is not None and info.family_speed_rad_s is not None:
            self._speeds = np.asarray(info.family_speed_rad_s, float)
            self._table = np.asarray(info.family_freq_hz_at_speed, float)
            top = min(self.x_top_rpm, float(rpm(self._speeds[-1])))
            self.curve_rpm = np.linspace(0.0, top, _CURVE_POINTS)
            self.curve_hz = self._freq_hz(self.curve_rpm)
        self.crossings = self._crossings(info)
        #: which ND the run's forces excite: set by the travelling-wave phase (Eq. 5-7), not by
        #: the EO (whose classic aliasing ND = EO mod N, folded, may differ)
        self.legend = "force: " + ", ".join(
            f"EO {int(eo)} x ND {_signed_nd(nd, self.n_blades)}"
            for eo, nd in dict.fromkeys(zip(info.engine_orders, info.nodal_diameters)))
        self.labels: list = []

    def eo_exit(self, eo) -> tuple[np.ndarray, np.ndarray]:
        """Where each EO line leaves the plot: ``(rpm, Hz)``."""
        eo = np.asarray(eo, float)
        x = np.minimum(self.x_top_rpm, 60.0 * self.f_top_hz / eo)
        return x, eo * x / 60.0

    def _freq_hz(self, speed_rpm) -> np.ndarray:
        """Family frequencies (Hz) at speeds (rpm): shape ``speed_rpm.shape + (n_families, n_nd)``."""
        return interpolate_freq_hz(self._speeds, self._table, np.asarray(speed_rpm, float) * (TWO_PI / 60.0))

    def _curve_crossings(self, eo: int, col: int) -> list[tuple[int, float]]:
        """``(family, rpm)`` where the line ``EO rpm / 60`` meets the families' curves at ND
        column ``col``: sign changes on the curve's points, refined on a finer grid in their
        interval, then linear."""
        x = self.curve_rpm
        g = self.curve_hz[:, :, col] - eo * x[:, None] / 60.0  # (n, n_families): > 0 below the crossing
        out = []
        for i, k in zip(*np.nonzero((g[:-1] > 0) != (g[1:] > 0))):
            xf = np.linspace(x[i], x[i + 1], _REFINE_POINTS)
            gf = self._freq_hz(xf)[:, k, col] - eo * xf / 60.0
            flips = np.flatnonzero((gf[:-1] > 0) != (gf[1:] > 0))
            j = int(flips[0]) if flips.size else 0
            t = gf[j] / (gf[j] - gf[j + 1]) if gf[j] != gf[j + 1] else 0.0
            out.append((int(k), float(xf[j] + t * (xf[j + 1] - xf[j]))))
        return sorted(out)

    def _crossings(self, info) -> list:
        out = []
        if self.families is None:
            return out
        for eo, nd in zip(info.engine_orders, info.nodal_diameters):
            signed = _signed_nd(nd, self.n_blades)
            if self.curve_hz is not None:
                for _, speed in self._curve_crossings(int(eo), abs(signed)):
                    f = eo * speed / 60.0
                    if 0 < f < self.f_top_hz:
                        out.append((speed, f, f"EO {eo} x ND {signed}: {speed:.0f} rpm"))
                continue
            for f in self.families[:, abs(signed)]:
                speed = 60.0 * f / eo
                if 0 < f < self.f_top_hz and speed <= self.x_top_rpm:
                    out.append((speed, float(f), f"EO {eo} x ND {signed}: {speed:.0f} rpm"))
        return out

    def family_lines(self) -> list[tuple[int, list[np.ndarray]]]:
        """``(family index, its lines inside the plot)`` of every family with lines shown; a
        line is an ``(n, 2)`` array of ``(rpm, Hz)`` points (horizontal: two points)."""
        if self.families is None:
            return []
        out = []
        for i, row in enumerate(self.families):
            if self.curve_hz is None:
                shown = row[(row > 0) & (row < self.f_top_hz)]
                lines = [np.array([[0.0, f], [self.x_top_rpm, f]]) for f in shown]
            else:
                lines = [ln for col in range(row.size)
                         for ln in _inside(self.curve_rpm, self.curve_hz[:, i, col], self.f_top_hz)]
            if lines:
                out.append((i, lines))
        return out

    def place(self, frame: PlotFrame) -> None:
        """Lay the labels out around ``frame``'s ticks (sets :attr:`labels`)."""
        def box(x, y):
            return frame.to_box(x, y)

        cands: list[tuple[Label, tuple]] = []
        for eo in sorted(self.engine_orders, key=lambda e: (e not in self.excited, e)):
            text = f"EO {eo}"
            bx, by = box(*self.eo_exit(eo))
            x0, y0, x1, y1 = label_box(text, 0.0, 0.0)
            w, h = x1 - x0, y1 - y0
            if bx >= 1.0 - 1e-9:  # leaves through the right edge: beside it, nudged up or down
                spots = [(1.0 + _GAP + w / 2, by + dy) for dy in (0.0, h / 2, -h / 2, h, -h)]
            else:  # through the top edge: above it, in one of two rows
                spots = [(bx + dx, PLOT_HEIGHT + _GAP + h * r) for r in (0.5, 1.5) for dx in (0.0, w / 3, -w / 3)]
            spots += [(t * bx - w / 2 - _GAP, t * by + h / 2 + _GAP) for t in (0.9, 0.78, 0.66, 0.54)]
            cands.append((Label(text, tuple(spots)), RED if eo in self.excited else _EO_GREY))
        run_pos = None
        lo, hi = self.speed_range_rpm
        if self.run_range:
            mid = float(box(0.5 * (lo + hi), 0.0)[0])
            run_pos = [(mid, PLOT_HEIGHT + _GAP + LINE_H * r) for r in (0.5, 1.5)]
        crossing = []
        for speed, f, text in self.crossings:
            bx, by = box(speed, f)
            x0, y0, x1, y1 = label_box(text, 0.0, 0.0)
            w, h = x1 - x0, y1 - y0
            spots = tuple((bx + sx * (w / 2 + _GAP), by + sy * (h / 2 + _GAP)) for sy in (-1, 1) for sx in (1, -1))
            crossing.append((Label(text, spots), RED))
        families = []
        for i, lines in self.family_lines():
            shown = np.concatenate([ln[:, 1] for ln in lines])
            text = f"family {i + 1}: {frequency_span_text(shown.min(), shown.max())}"
            x0, y0, x1, y1 = label_box(text, 0.0, 0.0)
            w, h = x1 - x0, y1 - y0
            top, bottom = float(box(0.0, shown.max())[1]), float(box(0.0, shown.min())[1])
            spots = [(x + w / 2, top + _GAP + h / 2) for x in (0.02, 0.3)]
            spots += [(x + w / 2, bottom - _GAP - h / 2) for x in (0.02, 0.3)]
            families.append((Label(text, tuple(spots)), FAMILY_COLORS[i % len(FAMILY_COLORS)]))
        n_excited = len([e for e in self.engine_orders if e in self.excited])
        x0, y0, x1, y1 = label_box(self.legend, 0.0, 0.0)
        w, h = x1 - x0, y1 - y0
        rows = [PLOT_HEIGHT - _GAP - h * r for r in (0.5, 1.5, 2.5)] + [_GAP + h * r for r in (2.5, 3.5, 4.5)]
        legend = (Label(self.legend, tuple((x + w / 2, y) for y in rows for x in (0.02, 0.25))),
                  RED)  # inside the plot, left: top rows, else low (above the shallow EO lines)
        ordered = cands[:n_excited] + crossing
        if run_pos is not None:
            ordered.append((Label(f"run {lo:g}-{hi:g} rpm", tuple(run_pos)), GREEN))
        ordered += cands[n_excited:] + families + [legend]
        spots = place_labels([lab for lab, _ in ordered], frame.obstacles())
        self.labels = [(lab.text, spot, color) for (lab, color), spot in zip(ordered, spots) if spot is not None]


class CampbellView:
    """The Campbell diagram and the current speed.

    Parameters
    ----------
    out : ViewOutput
    info : RunInfo

    Notes
    -----
    Without a speed range in the metadata (an older recording), the diagram is drawn once
    revolutions come, up to a round speed above the fastest seen, and redrawn larger when
    the speed passes its right edge.
    """

    def __init__(self, out: ViewOutput, info) -> None:
        self.out = out
        self.info = info
        self.layout: CampbellLayout | None = None
        self.frame: PlotFrame | None = None
        self._seen: tuple[float, float] | None = None
        if float(info.speed_range_rpm[1]) > 0:
            self._draw(CampbellLayout(info))

    def _draw(self, lay: CampbellLayout) -> None:
        self.layout = lay
        self.frame = PlotFrame(self.out, paths.CAMPBELL, (0.0, lay.x_top_rpm), (0.0, lay.f_top_hz),
                               x_label=lambda x: f"{x:g} rpm", y_label=lambda f: f"{f:g} Hz", grid=False)
        lay.place(self.frame)
        data = self.frame.data_path
        self.frame.draw()
        eos = lay.engine_orders
        x_end, f_end = lay.eo_exit(eos)
        excited = [e in lay.excited for e in eos]
        self.out.static(f"{data}/engine_orders", rr.LineStrips2D(
            [[[0.0, 0.0], [x, f]] for x, f in zip(x_end, f_end)], colors=[RED if e else _EO_GREY for e in excited],
            radii=[ui(1.2 if e else 0.6) for e in excited]))
        strips, colors = [], []
        for i, lines in lay.family_lines():
            strips += lines
            colors += [FAMILY_COLORS[i % len(FAMILY_COLORS)]] * len(lines)
        if strips:
            self.out.static(f"{data}/families", rr.LineStrips2D(strips, colors=colors, radii=ui(0.7)))
        lo, hi = lay.speed_range_rpm
        if lay.run_range:
            box = rr.Boxes2D(mins=[[lo, 0.0]], sizes=[[max(hi - lo, 1e-9), lay.f_top_hz]], colors=[GREEN],
                             radii=ui(0.8))
            self.out.static(f"{data}/run_range", box)
        if lay.crossings:
            self.out.static(f"{data}/resonance", rr.Points2D([[s, f] for s, f, _ in lay.crossings], colors=[RED],
                                                             radii=ui(4.0)))
        self.frame.log_labels(f"{data}/labels", [(t, c) for t, c, _ in lay.labels], [c for _, _, c in lay.labels])
        self.out.style(f"{data}/speed", rr.LineStrips2D.from_fields(colors=[GREEN], radii=[ui(1.5)]))

    def update(self, rows: ShownRevolutions) -> None:
        """The speed of each revolution as a vertical line (one frame per revolution)."""
        x = rpm(rows.omega_rad_s)
        if float(self.info.speed_range_rpm[1]) <= 0:  # no speed range in the metadata: what was seen
            lo, hi = float(np.nanmin(x)), float(np.nanmax(x))
            if self._seen is not None:
                lo, hi = min(lo, self._seen[0]), max(hi, self._seen[1])
            self._seen = (lo, hi)
            if self.layout is None or hi > self.layout.x_top_rpm:
                self._draw(CampbellLayout(self.info, self._seen, run_range=False))
        f_top = self.layout.f_top_hz
        strips = np.stack([np.stack([x, np.zeros_like(x)], -1), np.stack([x, np.full_like(x, f_top)], -1)], axis=1)
        self.out.columns(f"{self.frame.data_path}/speed", RevIndex.of(rows.revolution, rows.opr_s),
                         rr.LineStrips2D.columns(strips=strips), 1)

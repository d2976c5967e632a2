"""Plots against a quantity other than time, drawn in a 2-D view (Campbell diagram, amplitude
against speed).

Rerun's time-series views plot against the selected timeline only, so a plot whose x axis
is the speed is drawn here: its data are logged under ``<root>/data`` in their own units
(rpm, mm, Hz: hovering a point shows them), and one static ``Transform3D`` on
``<root>/data`` maps them into a box 1 wide and :data:`PLOT_HEIGHT` high, y up (Rerun's 2-D
space has y down: the transform flips it). Re-logging the transform rescales everything
logged before, so a live plot can grow its range. Markers and lines are sized in UI
points, which the scale does not change.

Box coordinates (``bx``, ``by``) run 0..1 and 0..PLOT_HEIGHT, y up. Rerun draws a point's
label centred below the point; :func:`place_labels` lays labels out as boxes of an assumed
text size (:data:`CHAR_W`, :data:`LINE_H`, box units for a view about 500 pixels wide) so
that they do not overlap.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from ._common import DARK, LIGHT_GREY, ViewOutput, nice_step, nice_ticks

__all__ = ["PLOT_HEIGHT", "BOUNDS", "CHAR_W", "LINE_H", "Label", "PlotFrame", "label_box", "place_labels",
           "plot_bounds", "ui"]

#: Height of the plot box (its width is 1).
PLOT_HEIGHT = 1.0 / 1.6
#: Assumed width of one character and height of one line of label text, box units.
CHAR_W = 0.022
LINE_H = 0.055
#: What a view of one plot shows, box units ``(x0, y0, x1, y1)``: the box and room for labels.
BOUNDS = (-0.2, -0.15, 1.17, PLOT_HEIGHT + 0.13)
_GAP = 0.012
_TICK = 0.015


def ui(points: float) -> float:
    """A radius in UI points (independent of the plot's scale)."""
    return float(rr.components.Radius.ui_points(points))


def plot_bounds() -> rrb.VisualBounds2D:
    """Visual bounds of a view showing one plot: the box and room for labels around it."""
    x0, y0, x1, y1 = BOUNDS
    return rrb.VisualBounds2D(x_range=[x0, x1], y_range=[-y1, -y0])  # y down on screen


@dataclass(frozen=True, slots=True)
class Label:
    """A label to place: its text and candidate centres (box units, y up), best first."""

    text: str
    candidates: tuple


def label_box(text: str, cx: float, cy: float) -> tuple[float, float, float, float]:
    """``(x0, y0, x1, y1)`` of a label centred at ``(cx, cy)``, box units."""
    lines = text.split("\n")
    w = CHAR_W * max(len(s) for s in lines) + _GAP
    h = LINE_H * len(lines)
    return cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2


def _overlaps(a, b) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def place_labels(labels: Sequence[Label], obstacles: Sequence = (), within=BOUNDS) -> list:
    """Greedy layout: each label, in order, takes its first candidate centre whose box lies
    ``within`` and overlaps neither an obstacle nor a label placed before it.

    Parameters
    ----------
    labels : sequence of Label
        In priority order.
    obstacles : sequence of (x0, y0, x1, y1)
        Boxes to keep clear (box units).
    within : (x0, y0, x1, y1)
        Where labels may go (default: what a view of the plot shows).

    Returns
    -------
    list
        Per label, its centre ``(cx, cy)`` or None (no room: left out).
    """
    taken = list(obstacles)
    out = []
    for lab in labels:
        spot = None
        for cx, cy in lab.candidates:
            box = label_box(lab.text, cx, cy)
            inside = within[0] <= box[0] and within[1] <= box[1] and box[2] <= within[2] and box[3] <= within[3]
            if inside and not any(_overlaps(box, t) for t in taken):
                spot = (float(cx), float(cy))
                taken.append(box)
                break
        out.append(spot)
    return out


class PlotFrame:
    """Axes, ticks and the data transform of one plot (see the module docstring).

    Parameters
    ----------
    out : ViewOutput
    root : str
        Entity of the view's origin; data go below ``root + "/data"``.
    x_range : (float, float) or None
        Data range mapped onto the box's width; None: from the data (:meth:`include`).
    y_range : (float, float)
        Data range mapped onto its height (the top grows with the data, :meth:`include`).
    x_label, y_label : callable
        Tick value -> label text (may hold a line break).
    grid : bool
        Light grid lines at the ticks.
    y_ticks : sequence of float, optional
        Tick values of the y axis (default: round values over the range).
    """

    def __init__(self, out: ViewOutput, root: str, x_range, y_range, *, x_label: Callable[[float], str],
                 y_label: Callable[[float], str], grid: bool = True, y_ticks: Sequence[float] | None = None) -> None:
        self.out = out
        self.root = root
        self.data_path = f"{root}/data"
        self._x_free = x_range is None
        self.x_range = (0.0, 1.0) if x_range is None else (float(x_range[0]), float(x_range[1]))
        self._x_seen = False
        self.y_range = (float(y_range[0]), float(y_range[1]))
        self.x_label = x_label
        self.y_label = y_label
        self.grid = grid
        self.y_ticks = None if y_ticks is None else np.asarray(y_ticks, float)

    # -- coordinates ---------------------------------------------------------------------
    def _spans(self) -> tuple[float, float]:
        return (max(self.x_range[1] - self.x_range[0], 1e-12), max(self.y_range[1] - self.y_range[0], 1e-12))

    def to_data(self, bx, by) -> np.ndarray:
        """Box coordinates to data coordinates, last axis 2."""
        sx, sy = self._spans()
        x = self.x_range[0] + np.asarray(bx, float) * sx
        y = self.y_range[0] + np.asarray(by, float) / PLOT_HEIGHT * sy
        return np.stack(np.broadcast_arrays(x, y), axis=-1)

    def to_box(self, x, y) -> np.ndarray:
        """Data coordinates to box coordinates, last axis 2."""
        sx, sy = self._spans()
        bx = (np.asarray(x, float) - self.x_range[0]) / sx
        by = (np.asarray(y, float) - self.y_range[0]) / sy * PLOT_HEIGHT
        return np.stack(np.broadcast_arrays(bx, by), axis=-1)

    def label_anchor(self, cx, cy, text: str) -> np.ndarray:
        """Where to put the point of a label centred at box ``(cx, cy)`` (data coordinates)."""
        return self.to_data(cx, label_box(text, cx, cy)[3])

    # -- ticks ---------------------------------------------------------------------------
    def _ticks(self) -> tuple[np.ndarray, np.ndarray]:
        return nice_ticks(*self.x_range), nice_ticks(*self.y_range, n=4) if self.y_ticks is None else self.y_ticks

    def tick_labels(self) -> list[tuple[str, tuple]]:
        """``(text, (cx, cy))`` of every tick label (box units): x below, y left of the axes."""
        xt, yt = self._ticks()
        out = []
        for x in xt:
            text = self.x_label(float(x))
            _, y0, _, y1 = label_box(text, 0.0, 0.0)
            out.append((text, (float(self.to_box(x, self.y_range[0])[0]), -_TICK - _GAP - (y1 - y0) / 2)))
        for y in yt:
            text = self.y_label(float(y))
            x0, y0, x1, y1 = label_box(text, 0.0, 0.0)
            by = float(self.to_box(self.x_range[0], y)[1])
            if by < (y1 - y0) / 2:  # at the corner: above the x tick labels
                by = (y1 - y0) / 2
            out.append((text, (-_TICK - _GAP - (x1 - x0) / 2, by)))
        return out

    def obstacles(self) -> list:
        """Boxes of the tick labels, for :func:`place_labels`."""
        return [label_box(text, *c) for text, c in self.tick_labels()]

    # -- logging -------------------------------------------------------------------------
    def draw(self) -> None:
        """Log the transform, axes, grid and tick labels (static)."""
        sx, sy = self._spans()
        (x0, x1), (y0, y1) = self.x_range, self.y_range
        self.out.static(self.data_path, rr.Transform3D(
            translation=[-x0 / sx, y0 / sy * PLOT_HEIGHT, 0.0], scale=[1.0 / sx, -PLOT_HEIGHT / sy, 1.0]))
        xt, yt = self._ticks()
        dx, dy = self.to_data(_TICK, _TICK) - (x0, y0)  # tick length in data units
        axes = [[[x0, y1], [x0, y0], [x1, y0]]]
        axes += [[[x, y0], [x, y0 - dy]] for x in xt] + [[[x0, y], [x0 - dx, y]] for y in yt]
        self.out.static(f"{self.data_path}/axes", rr.LineStrips2D(axes, colors=[DARK], radii=ui(0.6)))
        if self.grid:
            lines = [[[x, y0], [x, y1]] for x in xt if x > x0] + [[[x0, y], [x1, y]] for y in yt if y > y0]
            self.out.static(f"{self.data_path}/grid", rr.LineStrips2D(lines, colors=[LIGHT_GREY], radii=ui(0.3),
                                                                      draw_order=-10.0))
        self.log_labels(f"{self.data_path}/ticks", self.tick_labels(), DARK)

    def log_labels(self, path: str, placed: Sequence[tuple[str, tuple]], colors) -> None:
        """Log labels ``(text, (cx, cy))`` (box units) as static points with labels."""
        if not placed:
            return
        anchors = np.array([self.label_anchor(cx, cy, text) for text, (cx, cy) in placed])
        self.out.static(path, rr.Points2D(anchors, labels=[t for t, _ in placed], colors=colors, radii=ui(0.0),
                                          show_labels=True))

    def include(self, x=None, y=None) -> bool:
        """Widen the ranges to hold data ``x``, ``y`` and redraw if they changed.

        The top of the y range and, when it was not given, the x range grow to round
        values with some headroom; a given x range stays.

        Returns
        -------
        bool
            True if the ranges changed (and the frame was redrawn).
        """
        changed = False
        x = np.asarray([] if x is None else x, float)
        x = x[np.isfinite(x)]
        if self._x_free and x.size:
            lo, hi = float(x.min()), float(x.max())
            if self._x_seen:
                lo, hi = min(lo, self.x_range[0]), max(hi, self.x_range[1])
            if not self._x_seen or (lo, hi) != self.x_range:
                pad = 0.05 * max(hi - lo, 0.01 * abs(hi), 1e-9)
                step = nice_step(hi - lo + 2 * pad, 5)
                self.x_range = (np.floor((lo - pad) / step) * step, np.ceil((hi + pad) / step) * step)
                self._x_seen = changed = True
        y = np.asarray([] if y is None else y, float)
        y = y[np.isfinite(y)]
        if y.size and (top := float(y.max())) > self.y_range[1]:
            span = 1.1 * top - self.y_range[0]
            step = nice_step(span, 4)
            self.y_range = (self.y_range[0], self.y_range[0] + np.ceil(span / step) * step)
            changed = True
        if changed:
            self.draw()
        return changed

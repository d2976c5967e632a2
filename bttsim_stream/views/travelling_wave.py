"""Travelling-wave view: each probe's nodal-diameter spectrum against revolution (paper Fig. 10).

``tw/probe_<j>``: a tensor ``[nodal_diameter, revolution]`` of magnitudes (mm), rows by
signed ND from ``+(n_nd - 1)`` (forward, top) through 0 to ``-(n_nd - 1)`` (backward,
bottom) (:meth:`~bttsim_stream.process.travelling_wave.ProbeWave.signed_spectrum`);
revolutions without a message are 0. A whole recording logs it once, static (the spectra wait in
scratch files until then, and the probes are drawn one at a time); live it is a
rolling window of the last ``window`` revolutions, re-logged on the ``revolution``
timeline at most every ``period_s`` (re-logging the whole run each time would cost
O(n^2)). ``tw/nd``: the revolution's signed ND as identified by the processor from the fits
of all probes (the same in every probe's message).

``tw/probe_<j>/map``: the same matrix drawn for reading (Rerun's tensor view has no axis
ticks and no colour scale): a 2-D plot (:mod:`._plot2d`) whose ``image`` is the matrix
coloured by :func:`~._common.turbo` of ``(magnitude / top) ** GAMMA``, with ND ticks (y:
``+(n_nd - 1)`` top, 0, ``-(n_nd - 1)`` bottom) and revolution ticks (x: the revolution;
live, revolutions before the latest), and ``colorbar`` beside it, ticked in mm
(``data/colour_ticks``); ``top`` is the largest magnitude seen.
"""

from __future__ import annotations

import math
import time

import numpy as np
import rerun as rr

from ..process.history import SparseRows
from . import paths
from ._common import DARK, MM, RevIndex, ViewOutput, nice_step, nice_ticks, turbo
from ._plot2d import CHAR_W, LINE_H, PLOT_HEIGHT, PlotFrame, ui

__all__ = ["GAMMA", "MAX_SPAN", "TravellingWaveView", "colour_ticks", "nd_ticks"]

#: Colour of a magnitude: ``turbo((magnitude / top) ** GAMMA)`` (below 1: weak waves show).
GAMMA = 0.5
#: The colour bar: x from :data:`_BAR_X` to ``_BAR_X + _BAR_W`` (box units), full plot height.
_BAR_X, _BAR_W = 1.03, 0.04
_BAR_LEVELS = 256
#: Most revolutions a whole recording's map spans (about 7 hours at 10,000 rpm): a message
#: of a revolution further from the first one's is not drawn.
MAX_SPAN = 1 << 22


def nd_ticks(n_nd: int) -> np.ndarray:
    """Signed ND ticks of a map with rows ``+(n_nd - 1) .. -(n_nd - 1)``: round values and
    both ends (a round value too close to an end is left out)."""
    top = max(int(n_nd) - 1, 0)
    step = max(int(nice_step(top, 3)), 1) if top else 1
    inner = [v for v in range(step, top, step) if top - v >= step / 2]
    return np.array(sorted({0, top, -top, *inner, *(-v for v in inner)}), float)


def colour_ticks(top_mm: float) -> list[tuple[float, float]]:
    """``(magnitude mm, height in the bar 0..1)`` of the colour bar's ticks: round values up
    to ``top_mm``, each at least a label's height above the one below."""
    out: list[tuple[float, float]] = []
    for v in nice_ticks(0.0, top_mm, 6):
        h = (v / top_mm) ** GAMMA if top_mm > 0 else 0.0
        if not out or (h - out[-1][1]) * PLOT_HEIGHT >= LINE_H:
            out.append((float(v), float(h)))
    return out


class _WaveMap:
    """One probe's drawn map: frame, image and colour bar (see the module docstring)."""

    def __init__(self, out: ViewOutput, probe: int, n_rows: int, window: int | None) -> None:
        self.out = out
        self.root = paths.tw_map_path(probe)
        top = (n_rows - 1) // 2
        self.window = window
        self.frame = None if window is None else self._frame((-(window - 1) - 0.5, 0.5), top)
        self._top = top
        self._bar_top = None
        bar = turbo(np.linspace(1.0, 0.0, _BAR_LEVELS))[:, None, :]  # top row: the top colour
        out.static(f"{self.root}/colorbar", rr.Transform3D(translation=[_BAR_X, -PLOT_HEIGHT, 0.0],
                                                           scale=[_BAR_W, PLOT_HEIGHT / _BAR_LEVELS, 1.0]))
        out.static(f"{self.root}/colorbar", rr.Image(bar, color_model="RGB"))

    def _frame(self, x_range, top: int) -> PlotFrame:
        frame = PlotFrame(self.out, self.root, x_range, (-top - 0.5, top + 0.5), x_label=lambda x: f"{x:g}",
                          y_label=lambda nd: f"{nd:+g}" if nd else "0", grid=False, y_ticks=nd_ticks(top + 1))
        frame.draw()
        return frame

    def log(self, mat_mm: np.ndarray, first: int, last: int, top_mm: float) -> None:
        """The matrix (rows ND +top..-top, columns revolutions ``first..last``), coloured."""
        if self.frame is None or (self.window is None and self.frame.x_range != (first - 0.5, last + 0.5)):
            self.frame = self._frame((first - 0.5, last + 0.5), self._top)
        n_rows, n_cols = mat_mm.shape
        level = np.clip(mat_mm, 0.0, None)  # (magnitude / top) ** GAMMA, in place: one temporary
        level /= top_mm or 1.0
        rgb = turbo(np.power(level, GAMMA, out=level))
        del level
        self.out.static(f"{self.root}/image", rr.Transform3D(translation=[0.0, -PLOT_HEIGHT, 0.0],
                                                             scale=[1.0 / n_cols, PLOT_HEIGHT / n_rows, 1.0]))
        self.out.latest(f"{self.root}/image", rr.Image(rgb, color_model="RGB", magnification_filter="Nearest"), last)
        if top_mm != self._bar_top:
            self._bar_top = top_mm
            self._log_bar_ticks(top_mm, last)

    def _log_bar_ticks(self, top_mm: float, revolution: int) -> None:
        ticks = colour_ticks(top_mm)
        texts = [f"{v:g} mm" for v, _ in ticks]
        x1 = _BAR_X + _BAR_W
        marks = [[self.frame.to_data(x1, h * PLOT_HEIGHT), self.frame.to_data(x1 + 0.012, h * PLOT_HEIGHT)]
                 for _, h in ticks]
        anchors = [self.frame.label_anchor(x1 + 0.02 + CHAR_W * len(t) / 2 + 0.006, h * PLOT_HEIGHT, t)
                   for t, (_, h) in zip(texts, ticks)]
        data = self.frame.data_path
        self.out.latest(f"{data}/colour_marks", rr.LineStrips2D(marks, colors=[DARK], radii=ui(0.6)), revolution)
        self.out.latest(f"{data}/colour_ticks", rr.Points2D(anchors, labels=texts, colors=[DARK], radii=ui(0.0),
                                                            show_labels=True), revolution)


class _Spectra:
    """One probe's signed spectra (mm) by revolution, dense: a float32 matrix, rows the
    signed NDs, one column per revolution from ``first`` (zeros where no message came),
    grown by doubling. Memory: ``n_rows * 4`` bytes a revolution (live: of the window).

    Parameters
    ----------
    n_rows : int
        Rows of every spectrum stored (a message of another size is not stored).
    """

    def __init__(self, n_rows: int) -> None:
        self.n_rows = int(n_rows)
        self.first = 0  # revolution of column 0
        self._mat = np.zeros((self.n_rows, 0), np.float32)
        self._seen = np.zeros(0, bool)
        self.lo = self.hi = None  # smallest and largest revolution stored

    def put(self, revolution: np.ndarray, spec: np.ndarray) -> None:
        """Store spectra ``spec`` (k, n_rows) of revolutions ``revolution`` (k,) (the later of
        two of one revolution wins, as the messages came)."""
        rev = np.asarray(revolution, np.int64)
        last = rev.size - 1 - np.unique(rev[::-1], return_index=True)[1]  # latest of each revolution
        rev, spec = rev[last], spec[last]
        lo, hi = int(rev.min()), int(rev.max())
        if self.lo is None:
            self.first = lo
        self._span(min(lo, self.first), hi)
        col = rev - self.first
        self._mat[:, col] = spec.T
        self._seen[col] = True
        self.lo = lo if self.lo is None else min(self.lo, lo)
        self.hi = hi if self.hi is None else max(self.hi, hi)

    def _span(self, first: int, last: int) -> None:
        """Make room for columns of revolutions ``first .. last``."""
        shift = self.first - first
        need = last - first + 1
        if shift == 0 and need <= self._seen.size:
            return
        cap = max(need, 2 * self._seen.size if shift == 0 else need, 64)
        mat = np.zeros((self.n_rows, cap), np.float32)
        seen = np.zeros(cap, bool)
        n = self._seen.size
        mat[:, shift:shift + n] = self._mat
        seen[shift:shift + n] = self._seen
        self._mat, self._seen, self.first = mat, seen, first

    def forget_before(self, revolution: int) -> None:
        """Drop the revolutions before ``revolution`` (a live window that moved on)."""
        cut = int(revolution) - self.first
        if self.lo is None or cut <= 0:
            return
        keep = np.flatnonzero(self._seen[cut:])
        self._mat = np.ascontiguousarray(self._mat[:, cut:])
        self._seen = self._seen[cut:].copy()
        self.first = int(revolution)
        self.lo = None if keep.size == 0 else self.first + int(keep[0])
        self.hi = None if keep.size == 0 else self.hi

    def matrix(self, first: int, last: int) -> np.ndarray:
        """Columns of revolutions ``first .. last`` (zeros where none; NaN as 0), float32."""
        mat = np.zeros((self.n_rows, last - first + 1), np.float32)
        a, b = max(first, self.first), min(last, self.first + self._seen.size - 1)
        if a <= b:
            mat[:, a - first:b - first + 1] = self._mat[:, a - self.first:b - self.first + 1]
        return np.nan_to_num(mat, copy=False)


class _RecordedSpectra:
    """A whole recording's :class:`_Spectra` of one probe, held in scratch files
    (:class:`~bttsim_stream.process.history.SparseRows`), not in memory: its matrix is read
    back once, when drawn. ``first`` is ``lo`` (a whole recording forgets nothing)."""

    def __init__(self, n_rows: int) -> None:
        self.n_rows = int(n_rows)
        self.lo = self.hi = None  # smallest and largest revolution stored
        self._rows = SparseRows((self.n_rows,), np.float32)

    @property
    def first(self) -> int | None:
        return self.lo

    def put(self, revolution: np.ndarray, spec: np.ndarray) -> None:
        """As :meth:`_Spectra.put` (the later of two of one revolution wins)."""
        rev = np.asarray(revolution, np.int64)
        self._rows.write(rev, spec)
        lo, hi = int(rev.min()), int(rev.max())
        self.lo = lo if self.lo is None else min(self.lo, lo)
        self.hi = hi if self.hi is None else max(self.hi, hi)

    def matrix(self, first: int, last: int) -> np.ndarray:
        """As :meth:`_Spectra.matrix`, read back by blocks of revolutions."""
        mat = np.empty((self.n_rows, last - first + 1), np.float32)
        for a in range(first, last + 1, _READ_BLOCK):
            b = min(a + _READ_BLOCK, last + 1)
            mat[:, a - first:b - first] = self._rows.read(a, b).T
        return np.nan_to_num(mat, copy=False)

    def close(self) -> None:
        self._rows.close()


#: Revolutions of spectra read back at a time (:meth:`_RecordedSpectra.matrix`).
_READ_BLOCK = 4096


def _by_size(rows: list) -> list[list]:
    """Messages grouped by their number of nodal diameters (all of one run's share it)."""
    n = rows[0].body.forward_m.size
    if all(d.body.forward_m.size == n for d in rows):
        return [rows]
    groups: dict[int, list] = {}
    for d in rows:
        groups.setdefault(d.body.forward_m.size, []).append(d)
    return list(groups.values())


class TravellingWaveView:
    """Travelling-wave matrices of every probe and the identified ND.

    Parameters
    ----------
    out : ViewOutput
    window : int
        Revolutions of the live rolling window.
    period_s : float
        Shortest wall time between two live re-logs of the matrices.
    """

    def __init__(self, out: ViewOutput, *, window: int = 256, period_s: float = 1.0) -> None:
        self.out = out
        self.window = int(window)
        self.period_s = float(period_s)
        self._new: list = []
        self._spectra: dict[int, _Spectra] = {}  # probe -> its signed spectra (mm)
        self._max_mm = 0.0
        self._last_log = -math.inf
        self._nd_until = -1  # last revolution whose ND is logged
        self._maps: dict[int, _WaveMap] = {}
        self.count = 0

    def add(self, decoded) -> None:
        """A ``tw`` message (:class:`~bttsim_stream.process.travelling_wave.ProbeWave` body)."""
        self._new.append(decoded)

    def flush(self, final: bool = False) -> None:
        """Store what arrived; log the ND series, and the matrices when due (``final``: now)."""
        rows, self._new = self._new, []
        if rows:
            self.count += len(rows)
            nd_rows = {}  # one ND per revolution (every probe's message carries it)
            for group in _by_size(rows):
                self._store(group, self._signed_mm(group))
            for d in rows:
                if d.header.revolution > self._nd_until:
                    nd_rows.setdefault(d.header.revolution, d)
            if nd_rows:
                self.out.style(paths.TW_ND, rr.SeriesPoints(names=["ND (backward < 0)"], marker_sizes=[2.0]))
                first = [nd_rows[r] for r in sorted(nd_rows)]
                self._nd_until = first[-1].header.revolution
                self.out.scalars(paths.TW_ND, RevIndex.from_headers([d.header for d in first]),
                                 np.array([d.body.nd for d in first], float))
            if self.out.live:
                self._trim()
        due = time.monotonic() - self._last_log >= self.period_s
        if self._spectra and (final or (self.out.live and rows and due)):
            self._log_matrices()

    def _signed_mm(self, group: list) -> np.ndarray:
        """The signed spectra (:meth:`~bttsim_stream.process.travelling_wave.ProbeWave.signed_spectrum`)
        of messages of one size, mm, as the rows of one float32 matrix; the largest seen updated."""
        fwd = np.array([d.body.forward_m for d in group])
        bwd = np.array([d.body.backward_m for d in group])
        zero = np.fmax(fwd[:, :1], bwd[:, :1])
        # magnitudes beyond float32 (a forged 1e308 m) are drawn at its largest value
        spec = np.clip(np.concatenate([fwd[:, :0:-1], zero, bwd[:, 1:]], axis=1) * MM, 0.0,
                       np.finfo(np.float32).max).astype(np.float32)
        self._max_mm = max(self._max_mm, float(np.nanmax(spec, initial=0.0)))
        return spec

    def _store(self, group: list, spec: np.ndarray) -> None:
        """Spectra of messages of one size, by probe (a probe keeps the size of its first)."""
        probe = np.array([d.body.probe for d in group])
        rev = np.array([d.header.revolution for d in group], np.int64)
        for p in np.unique(probe).tolist():
            store = self._spectra.get(p)
            if store is None:  # live: the window in memory; a whole recording: in scratch files
                store = self._spectra[p] = (_Spectra if self.out.live else _RecordedSpectra)(spec.shape[1])
            mine = probe == p
            top = int(rev[mine].max()) if store.hi is None else max(store.hi, int(rev[mine].max()))
            if self.out.live:  # what is older than the window is never shown
                mine &= rev > top - self.window
                store.forget_before(top - self.window + 1)
            else:  # a revolution number far from the others (forged) would take a matrix of its span
                ref = int(rev[mine][0]) if store.hi is None else store.first
                mine &= np.abs(rev - ref) < MAX_SPAN
            if store.n_rows == spec.shape[1] and mine.any():
                store.put(rev[mine], spec[mine])

    def _trim(self) -> None:
        """Forget revolutions that left the live window (amortised: at twice its size)."""
        for spectra in self._spectra.values():
            if spectra.hi is not None and spectra.hi - spectra.first + 1 > 2 * self.window:
                spectra.forget_before(spectra.hi - self.window + 1)

    def _log_matrices(self) -> None:
        self._last_log = time.monotonic()
        for probe, spectra in sorted(self._spectra.items()):
            if spectra.hi is None:
                continue
            last = spectra.hi
            first = last - self.window + 1 if self.out.live else spectra.lo
            n_rows = spectra.n_rows
            mat = spectra.matrix(first, last)
            self.out.latest(paths.tw_path(probe), rr.Tensor(mat, dim_names=["nodal_diameter", "revolution"],
                                                            value_range=(0.0, self._max_mm or 1.0)), last)
            whole = not self.out.live
            if whole:  # a whole run's matrices go to the sinks one at a time: Rerun holds them until flushed
                self.out.flush()
            wave_map = self._maps.get(probe)
            if wave_map is None:
                wave_map = self._maps[probe] = _WaveMap(self.out, probe, n_rows, None if whole else self.window)
            wave_map.log(mat, first, last, self._max_mm)
            del mat
            if whole:
                self.out.flush()

"""What every view shares: the output stream with its bulk-logging helpers, colours, nice numbers.

Timelines of every temporal entity: ``revolution`` (sequence, the message header's
revolution) and ``time`` (duration, the header's simulated time in s). Values are SI in the
library and converted for display only here and in the views: :data:`MM` (m -> mm),
degrees, rpm, Hz.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass

import numpy as np
import rerun as rr

__all__ = ["MM", "TWO_PI", "GREY", "LIGHT_GREY", "DARK", "RED", "GREEN", "BLUE", "ORANGE", "FAMILY_COLORS",
           "RevIndex", "ViewOutput", "palette", "selection_colors", "nice_step", "nice_ticks", "rpm", "turbo"]

#: Metres to millimetres (display).
MM = 1e3
TWO_PI = 2.0 * math.pi
GREY = (150, 150, 150)
LIGHT_GREY = (190, 190, 190)
DARK = (60, 60, 60)
RED = (214, 39, 40)
GREEN = (44, 160, 44)
BLUE = (31, 119, 180)
ORANGE = (230, 120, 20)
#: Colours of the Campbell diagram's mode families.
FAMILY_COLORS = ((31, 119, 180), (148, 103, 189), (23, 190, 207), (140, 86, 75), (127, 127, 127))
_SELECTION = np.array([BLUE, RED, GREEN, (148, 103, 189), (255, 127, 14), (140, 86, 75)], np.uint8)


def rpm(omega_rad_s):
    """Speed in rpm from rad/s (display)."""
    return np.asarray(omega_rad_s, float) * (60.0 / TWO_PI)


@dataclass(frozen=True, slots=True, eq=False)
class RevIndex:
    """The index of ``n`` rows of per-revolution data.

    Attributes
    ----------
    revolution : ndarray of int64, shape (n,)
    t_s : ndarray, shape (n,)
        Simulated time of each row (header time), s.
    """

    revolution: np.ndarray
    t_s: np.ndarray

    @classmethod
    def of(cls, revolution, t_s) -> "RevIndex":
        return cls(np.asarray(revolution, dtype=np.int64), np.asarray(t_s, dtype=float))

    @classmethod
    def from_headers(cls, headers) -> "RevIndex":
        """From message headers (``revolution``, ``t_s``)."""
        return cls.of([h.revolution for h in headers], [h.t_s for h in headers])

    def __len__(self) -> int:
        return int(self.revolution.size)

    def columns(self) -> list:
        return [rr.TimeColumn("revolution", sequence=self.revolution), rr.TimeColumn("time", duration=self.t_s)]


class ViewOutput:
    """The recording stream the views log to, with the helpers they all use.

    Parameters
    ----------
    rec : rerun.RecordingStream
    live : bool
        Live: data that is re-logged as it changes (travelling-wave windows, resonance
        reports) goes on the ``revolution`` timeline; a whole recording logs it static.
    """

    def __init__(self, rec: rr.RecordingStream, live: bool) -> None:
        self.rec = rec
        self.live = bool(live)
        self._styled: set[str] = set()
        self._index: tuple | None = None  # (RevIndex, its time columns): views log one index to many entities

    def flush(self) -> None:
        """Hand what is logged to the sinks, and wait for it (after a large log: Rerun's
        batcher holds it until then)."""
        self.rec.flush()

    def style(self, path: str, archetype) -> None:
        """Log a static style (series names, colours...) once per entity."""
        if path not in self._styled:
            self._styled.add(path)
            self.rec.log(path, archetype, static=True)

    def static(self, path: str, archetype) -> None:
        """Log static data (replacing any earlier static data of ``path``)."""
        self.rec.log(path, archetype, static=True)

    def latest(self, path: str, archetype, revolution: int) -> None:
        """Data that replaces itself: at ``revolution`` live, static for a whole recording."""
        if not self.live:
            self.static(path, archetype)
            return
        self.rec.set_time("revolution", sequence=max(int(revolution), 0))
        self.rec.log(path, archetype)
        self.rec.reset_time()

    def scalars(self, path: str, index: RevIndex, values) -> None:
        """One row of scalars per revolution: ``values`` shape (n,) or (n, k) (k series)."""
        values = np.asarray(values, dtype=float)
        if values.ndim == 1:
            values = values[:, None]
        if len(index) == 0:
            return
        self.columns(path, index, rr.Scalars.columns(scalars=values.ravel()), values.shape[1])

    def columns(self, path: str, index: RevIndex, columns, per_row) -> None:
        """``send_columns`` of component columns whose instances split into rows of
        ``per_row`` (an int, or one length per row)."""
        lengths = np.full(len(index), per_row) if np.ndim(per_row) == 0 else np.asarray(per_row)
        if self._index is None or self._index[0] is not index:
            self._index = (index, index.columns())
        self.rec.send_columns(path, indexes=self._index[1], columns=columns.partition(lengths))


def palette(n: int) -> np.ndarray:
    """``n`` distinct colours around the hue circle, uint8 (n, 3) (HSV, s = 0.7, v = 0.85)."""
    h = np.arange(n) / max(n, 1)
    k = np.mod(np.array([5.0, 3.0, 1.0])[None, :] + 6.0 * h[:, None], 6.0)
    rgb = 0.85 - 0.6 * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)
    return np.round(255 * rgb).astype(np.uint8)


_TURBO = np.array([[0.13572138, 4.61539260, -42.66032258, 132.13108234, -152.94239396, 59.28637943],
                   [0.09140261, 2.19418839, 4.84296658, -14.18503333, 4.27729857, 2.82956604],
                   [0.10667330, 12.64194608, -60.58204836, 110.36276771, -89.90310912, 27.34824973]])

_TURBO_BLOCK = 1 << 16


def turbo(x) -> np.ndarray:
    """The turbo colour map at ``x`` in [0, 1] (clipped; NaN as 0), uint8 ``x.shape + (3,)``.

    Notes
    -----
    The degree-5 polynomial approximation of Google's turbo (A. Mikhailov, 2019): on average
    6 levels of 255 from matplotlib's table (32 at the dark ends). A map and its colour bar
    drawn with it agree exactly.
    """
    x = np.asarray(x)
    flat = x.reshape(-1)
    out = np.empty((flat.size, 3), np.uint8)
    for lo in range(0, flat.size, _TURBO_BLOCK):  # in blocks: a whole-run map needs no run-sized temporaries
        level = np.clip(np.nan_to_num(flat[lo:lo + _TURBO_BLOCK].astype(float)), 0.0, 1.0)
        powers = level[:, None] ** np.arange(6.0)
        out[lo:lo + _TURBO_BLOCK] = np.round(255.0 * np.clip(powers @ _TURBO.T, 0.0, 1.0))
    return out.reshape(x.shape + (3,))


def selection_colors(n: int, light: bool = False) -> np.ndarray:
    """Colours of ``n`` selected blades, uint8 (n, 3); ``light``: blended halfway to white."""
    c = _SELECTION[np.arange(n) % len(_SELECTION)].astype(float)
    return np.round(c + 0.5 * (255.0 - c) if light else c).astype(np.uint8)


def nice_step(span: float, n: int = 5) -> float:
    """A round step (1, 2, 2.5 or 5 times a power of ten) giving about ``n`` intervals over ``span``."""
    raw = max(abs(float(span)), 1e-12) / max(n, 1)
    if not math.isfinite(raw):  # an infinite (or NaN) span: the largest finite one
        raw = sys.float_info.max / max(n, 1)
    step = 10.0 ** math.floor(math.log10(raw))
    for m in (1.0, 2.0, 2.5, 5.0, 10.0):
        if m * step >= raw:
            return m * step
    return 10.0 * step


def nice_ticks(lo: float, hi: float, n: int = 5) -> np.ndarray:
    """Round tick values in ``[lo, hi]`` (about ``n`` intervals; none for an infinite or NaN end)."""
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return np.zeros(0)
    step = nice_step(hi / 2 - lo / 2, n) if abs(hi - lo) == math.inf else nice_step(hi - lo, n)
    first, last = math.ceil(lo / step - 1e-9), math.floor(hi / step + 1e-9)  # in steps: no overflow
    return np.arange(first, last + 1, dtype=float) * step

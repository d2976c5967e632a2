"""Raw signal view: one probe's digitised window around the selected blade's passage, with the
trigger level and the detected TOA marked, following the run.

Shown only when the bus carries raw signals (``bttsim/<rig>/signal/<probe>``, scenario
``[acquisition.signal] publish = true``); without them nothing is logged. A 2-D plot
(:mod:`._plot2d`) under ``signal/probe_<j>``: x is the time since the window's first sample
in us, y the ADC input in V (``range_lo_v + code * lsb_v``). Per shown revolution
(timelines ``revolution`` and ``time``):

* ``data/window`` -- the samples joined by a line, ``data/samples`` -- the samples;
* ``data/level`` -- the trigger level (threshold; arming level of constant fraction and
  peak) and, for a constant-fraction trigger, the window's own level ``b + f (max - b)``
  (:func:`~bttsim_stream.triggers.constant_fraction_level`);
* ``data/toa`` -- a vertical line at the published TOA (latched on the counter clock), none
  for a missing pulse;
* ``data/note`` -- a label: revolution, blade, and "missing pulse" or the number of edges of
  a double pulse.

At most :data:`MAX_WINDOWS` revolutions of a run are shown (every ``stride``-th,
:func:`signal_stride`), so the cost stays bounded whatever the run's length.
"""

from __future__ import annotations

import math

import numpy as np
import rerun as rr

from ..triggers import constant_fraction_level
from . import paths
from ._common import BLUE, GREEN, ORANGE, RED, DARK, ViewOutput
from ._plot2d import PlotFrame, ui

__all__ = ["MAX_WINDOWS", "signal_stride", "SignalView"]

#: Most windows of one run the view logs.
MAX_WINDOWS = 1000
_US = 1e6


def signal_stride(n_revolutions: int) -> int:
    """Show every ``stride``-th revolution: ``ceil(n_revolutions / MAX_WINDOWS)`` (at least 1)."""
    return max(1, math.ceil(int(n_revolutions) / MAX_WINDOWS))


class SignalView:
    """The raw window of one blade at one probe, per shown revolution.

    Parameters
    ----------
    out : ViewOutput
    info : RunInfo
    probe, blade : int
        What is shown (a blade outside the run: blade 0).
    """

    def __init__(self, out: ViewOutput, info, probe: int = 0, blade: int = 0) -> None:
        self.out = out
        self.probe = int(probe)
        self.blade = int(blade) if 0 <= int(blade) < int(info.n_blades) else 0
        self.stride = signal_stride(info.n_revolutions)
        self.root = paths.signal_path(self.probe)
        self.count = 0
        self._frame: PlotFrame | None = None
        self._pending: list = []

    def wants(self, probe: int, revolution: int) -> bool:
        """Whether a message of ``probe`` for ``revolution`` is shown (decode only those)."""
        return int(probe) == self.probe and int(revolution) % self.stride == 0

    def add(self, decoded) -> None:
        """A ``signal`` message (:class:`~bttsim_stream.bus.codec.SignalBatch`)."""
        body = decoded.body
        if self.wants(body.probe, decoded.header.revolution) and self.blade < body.n_samples.size:
            self._pending.append(decoded)

    def flush(self, final: bool = False) -> None:
        """Log the windows received since the last flush."""
        rows, self._pending = self._pending, []
        for d in rows:
            self._log(d)

    def _log(self, decoded) -> None:
        s, b, h = decoded.body, self.blade, decoded.header
        t_s, volts = s.window(b)
        t0 = float(t_s[0])
        x = (t_s - t0) * _US
        if self._frame is None:
            top = s.range_lo_v + ((1 << s.bits) - 1) * s.lsb_v
            self._frame = PlotFrame(self.out, self.root, None, (s.range_lo_v, top),
                                    x_label=lambda v: f"{v:g} us", y_label=lambda v: f"{v:g} V")
            self._frame.draw()
        self._frame.include(x=x)
        data = self._frame.data_path
        rec = self.out.rec
        rec.set_time("revolution", sequence=max(int(h.revolution), 0))
        rec.set_time("time", duration=float(h.t_s))
        pts = np.stack([x, volts], axis=1)
        rec.log(f"{data}/window", rr.LineStrips2D([pts], colors=[BLUE], radii=ui(0.8)))
        rec.log(f"{data}/samples", rr.Points2D(pts, colors=[BLUE], radii=ui(1.5)))
        x0, x1 = float(x[0]), float(x[-1])
        levels = [[[x0, s.level_v], [x1, s.level_v]]]
        colors = [ORANGE]
        if s.trigger == "constant_fraction":
            cfd = float(constant_fraction_level(volts, s.fraction))
            levels.append([[x0, cfd], [x1, cfd]])
            colors.append(GREEN)
        rec.log(f"{data}/level", rr.LineStrips2D(levels, colors=colors, radii=ui(0.6)))
        toa = float(s.toa_s[b])
        lo, hi = self._frame.y_range
        if math.isfinite(toa):
            xt = (toa - t0) * _US
            rec.log(f"{data}/toa", rr.LineStrips2D([[[xt, lo], [xt, hi]]], colors=[RED], radii=ui(0.8)))
        else:
            rec.log(f"{data}/toa", rr.LineStrips2D([]))
        edges = int(s.n_edges[b])
        what = "missing pulse" if edges == 0 else (f"double pulse ({edges} edges)" if edges > 1 else "TOA")
        rec.log(f"{data}/note", rr.Points2D([[x0, hi]], labels=[f"rev {h.revolution}, blade {b}: {what}"],
                                            colors=[DARK], radii=ui(0.0), show_labels=True))
        rec.reset_time()
        self.count += 1

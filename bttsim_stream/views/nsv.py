"""Non-synchronous vibration view: the NSV's travelling wave by ND and its amplitude growth.

From the processor's ``nsv`` messages (:class:`bttsim.v1.NonSynchronous`, one per detected
block of revolutions) and the final report's ``non_synchronous`` list:

* ``nsv/amp_pkpk_mm`` -- the wave's pk-pk amplitude at its ND, mm, at each detected block's
  last revolution (block-averaged), and ``nsv/rev_amp_pkpk_mm`` the blade-RMS amplitude of
  every revolution of the detections (the growth of a flutter, the level of a stall; on the
  ``revolution`` timeline only);
* ``nsv/nd`` and ``nsv/order`` -- the signed ND and the order ``f / f_shaft`` of each block;
* ``nsv/tw_mm`` -- the latest block's travelling-wave spectrum of the NSV response as a bar
  chart over signed ND ``+(n_nd - 1) .. 0 .. -(n_nd - 1)`` (forward first): the bar at the
  detected ND stands out (the per-revolution ``tw/`` views analyse the engine order and do
  not show an NSV at its ND);
* ``nsv/table`` -- the detections as markdown.
"""

from __future__ import annotations

import numpy as np
import rerun as rr

from . import paths
from ._common import MM, RevIndex, ViewOutput

__all__ = ["NsvView"]


def _signed(fwd: np.ndarray, bwd: np.ndarray) -> np.ndarray:
    zero = np.fmax(fwd[:1], bwd[:1])
    return np.concatenate([fwd[:0:-1], zero, bwd[1:]])


class NsvView:
    """Amplitude growth, ND, order and travelling-wave bars of non-synchronous vibration."""

    def __init__(self, out: ViewOutput) -> None:
        self.out = out
        self._new: list = []
        self._styled = False
        self._rev_styled = False
        self.count = 0

    def add(self, decoded) -> None:
        """An ``nsv`` message (:class:`~bttsim_stream.process.nsv.NsvDetection` body)."""
        self._new.append(decoded)

    def add_report(self, report) -> None:
        """The final report's detections as a table (a report without any: nothing)."""
        dets = getattr(report, "non_synchronous", ())
        if not dets:
            return
        rows = ["| revolutions | order (alternatives) | alias /rev | Hz | ND | pk-pk mm |", "|---|---|---|---|---|---|"]
        for n in dets:
            alts = ", ".join(f"{a:.3f}" for a in n.order_alternatives)
            rows.append(f"| {n.first_revolution}-{n.last_revolution} | {n.order:.3f}{f' ({alts})' if alts else ''} | "
                        f"{n.alias:.3f} | {n.freq_hz:.2f} | {n.nd:+d} | {n.amp_pkpk_m * MM:.4f} |")
        text = "**Non-synchronous vibration (not engine-order resonances)**\n\n" + "\n".join(rows)
        self.out.static(paths.NSV_TABLE, rr.TextDocument(text, media_type="text/markdown"))
        if self.count == 0:  # no live messages (e.g. a run shorter than two blocks): the report's growth
            for n in dets:
                self._rev_amps(n)
        last = dets[-1]
        if np.size(last.forward_m):
            bars = _signed(np.asarray(last.forward_m), np.asarray(last.backward_m)) * MM
            self.out.static(paths.NSV_TW, rr.BarChart(bars))

    def _rev_amps(self, n) -> None:
        amp = np.asarray(n.rev_amp_pkpk_m, float)
        if not amp.size:
            return
        if not self._rev_styled:
            self.out.style(paths.NSV_REV_AMP, rr.SeriesLines(names=["NSV amplitude pk-pk per revolution (mm)"]))
            self._rev_styled = True
        revs = np.arange(int(n.first_revolution), int(n.first_revolution) + amp.size, dtype=np.int64)
        self.out.rec.send_columns(paths.NSV_REV_AMP, indexes=[rr.TimeColumn("revolution", sequence=revs)],
                                  columns=rr.Scalars.columns(scalars=np.nan_to_num(amp) * MM))

    def flush(self, final: bool = False) -> None:
        rows, self._new = self._new, []
        if not rows:
            return
        self.count += len(rows)
        rows.sort(key=lambda d: d.header.revolution)
        if not self._styled:
            self.out.style(paths.NSV_ND, rr.SeriesPoints(names=["NSV ND (backward < 0)"], marker_sizes=[3.0]))
            self.out.style(paths.NSV_ORDER, rr.SeriesPoints(names=["NSV order f / f_shaft"], marker_sizes=[3.0]))
            self.out.style(paths.NSV_AMP, rr.SeriesPoints(names=["NSV amplitude pk-pk (mm)"], marker_sizes=[3.0]))
            self._styled = True
        index = RevIndex.from_headers([d.header for d in rows])
        self.out.scalars(paths.NSV_AMP, index, np.array([d.body.amp_pkpk_m for d in rows]) * MM)
        self.out.scalars(paths.NSV_ND, index, np.array([d.body.nd for d in rows], float))
        self.out.scalars(paths.NSV_ORDER, index, np.array([d.body.order for d in rows]))
        for d in rows:
            self._rev_amps(d.body)
        last = rows[-1]
        self.out.latest(paths.NSV_TW, rr.BarChart(_signed(last.body.forward_m, last.body.backward_m) * MM),
                        last.header.revolution)

"""Resonance view: the processor's resonance report as a table and as bars per blade (Fig. 13).

``resonance/table`` (markdown): the EO, the identified ND, the condition number, the mean
over the blades and, with truth, the mean and largest E_A and E_f; then two narrow tables,
amplitude pk-pk (mm: BTT, d_eqv, E_A %) and frequency (Hz: BTT, d_eqv, E_f %), one row per
blade (one table of amplitude and frequency without truth). ``resonance/amp_pkpk_mm/btt``
and ``.../d_eqv``: bar charts of the resonant amplitude per blade, mm (BTT left of each
blade number, d_eqv right). A whole recording shows its last report (static); live, each
report as it comes, on the ``revolution`` timeline.
"""

from __future__ import annotations

import numpy as np
import rerun as rr

from . import paths
from ._common import BLUE, GREY, MM, ViewOutput

__all__ = ["ResonanceView", "resonance_markdown"]


def _nd_text(nd: int) -> str:
    nd = int(nd)
    return f"ND {nd}" + (" (forward)" if nd > 0 else " (backward)" if nd < 0 else "")


def resonance_markdown(report) -> str:
    """The report (:class:`~bttsim_stream.process.resonance.ResonanceReport`) as markdown:
    amplitudes in mm, frequencies in Hz, tables at most four columns wide."""
    amp = np.asarray(report.peaks.amp_pkpk_m) * MM
    freq = np.asarray(report.peaks.freq_hz)
    lines = [f"### Resonance: EO {report.eo}, {_nd_text(report.nd)}", ""]
    summary = f"CN {report.cn:.3g}"
    if amp.size:
        summary += f"; mean over {amp.size} blades {np.nanmean(amp):.4f} mm pk-pk at {np.nanmean(freq):.3f} Hz"
    lines += [summary, ""]
    if report.truth is None:
        lines += ["| blade | mm pk-pk | Hz |", "|---:|---:|---:|"]
        lines += [f"| {b} | {a:.4f} | {f:.3f} |" for b, (a, f) in enumerate(zip(amp, freq))]
        return "\n".join(lines) + "\n"
    e_a, e_f = np.asarray(report.e_a_pct), np.asarray(report.e_f_pct)
    lines += [f"E_A mean {np.nanmean(e_a):.3f} %, max {np.nanmax(e_a):.3f} %; "
              f"E_f mean {np.nanmean(e_f):.4f} %, max {np.nanmax(e_f):.4f} %", ""]
    truth_amp = np.asarray(report.truth.amp_pkpk_m) * MM
    lines += ["**Amplitude pk-pk (mm)**", "", "| blade | BTT | d_eqv | E_A % |", "|---:|---:|---:|---:|"]
    lines += [f"| {b} | {a:.4f} | {t:.4f} | {e:.3f} |" for b, (a, t, e) in enumerate(zip(amp, truth_amp, e_a))]
    lines += ["", "**Frequency (Hz)**", "", "| blade | BTT | d_eqv | E_f % |", "|---:|---:|---:|---:|"]
    lines += [f"| {b} | {f:.3f} | {t:.3f} | {e:.4f} |"
              for b, (f, t, e) in enumerate(zip(freq, report.truth.freq_hz, e_f))]
    return "\n".join(lines) + "\n"


class ResonanceView:
    """The latest resonance report.

    Parameters
    ----------
    out : ViewOutput
    """

    def __init__(self, out: ViewOutput) -> None:
        self.out = out
        self._pending = None
        self.count = 0

    def add(self, decoded) -> None:
        """A ``resonance`` message (:class:`~bttsim_stream.process.resonance.ResonanceReport` body)."""
        self._pending = decoded
        self.count += 1

    def flush(self, final: bool = False) -> None:
        """Log the latest report (a whole recording: only at the end)."""
        d = self._pending
        if d is None or not (self.out.live or final):
            return
        self._pending = None
        rep, rev = d.body, d.header.revolution
        table = rr.TextDocument(resonance_markdown(rep), media_type=rr.MediaType.MARKDOWN)
        self.out.latest(paths.RESONANCE_TABLE, table, rev)
        amp = np.asarray(rep.peaks.amp_pkpk_m) * MM
        if amp.size == 0:
            return
        blade = np.arange(amp.size, dtype=float)
        self.out.latest(f"{paths.RESONANCE_BARS}/btt", rr.BarChart(amp, abscissa=blade - 0.2, widths=[0.4], color=BLUE),
                        rev)
        if rep.truth is not None:
            truth = np.asarray(rep.truth.amp_pkpk_m) * MM
            self.out.latest(f"{paths.RESONANCE_BARS}/d_eqv",
                            rr.BarChart(truth, abscissa=blade + 0.2, widths=[0.4], color=GREY), rev)

"""Displacement view: the raw Eq. 1 tip displacement of selected blades at every probe, and the truth.

Per probe ``j`` (``displacement/probe_<j>``): ``btt`` -- the raw BTT displacement (Eq. 1,
points) computed by :class:`~bttsim_stream.views.revolutions.RevolutionDisplacements` from
the OPR pulses and TOAs, and ``d_eqv`` -- the truth's ``d_eqv`` at the TOA (lines, lighter),
for the selected blades (default 0 and ``n_blades // 2``), mm.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import rerun as rr

from . import paths
from ._common import MM, RevIndex, ViewOutput, selection_colors
from .revolutions import ShownRevolutions

__all__ = ["DisplacementView", "selected_blades"]


def selected_blades(n_blades: int, blades: Sequence[int] | None = None) -> tuple[int, ...]:
    """The blades shown: ``blades`` within range (default 0 and ``n_blades // 2``), no repeats."""
    req = (0, n_blades // 2) if blades is None else blades
    return tuple(dict.fromkeys(int(b) for b in req if 0 <= int(b) < n_blades))


class DisplacementView:
    """Eq. 1 displacement and d_eqv of some blades at every probe.

    Parameters
    ----------
    out : ViewOutput
    info : RunInfo
    blades : sequence of int, optional
        See :func:`selected_blades`.
    """

    def __init__(self, out: ViewOutput, info, blades: Sequence[int] | None = None) -> None:
        self.out = out
        self.n_blades, self.n_probes = int(info.n_blades), int(info.n_probes)
        self.blades = list(selected_blades(self.n_blades, blades))
        self._truth: list = []
        n = len(self.blades)
        for j in range(self.n_probes):
            root = paths.displacement_path(j)
            out.style(f"{root}/btt", rr.SeriesPoints(names=[f"blade {b} Eq. 1" for b in self.blades],
                                                     colors=selection_colors(n), marker_sizes=[2.0] * n))
            out.style(f"{root}/d_eqv", rr.SeriesLines(names=[f"blade {b} d_eqv" for b in self.blades],
                                                      colors=selection_colors(n, light=True), widths=[1.0] * n))

    def update(self, rows: ShownRevolutions) -> None:
        """Log revolutions ready to be shown (their Eq. 1 displacement)."""
        self._log("btt", RevIndex.of(rows.revolution, rows.opr_s), rows.d_m)

    def add_truth(self, decoded) -> None:
        """A ``truth`` message (one revolution's :class:`~bttsim_stream.sim.core.Truth`)."""
        if decoded.body.d_eqv_m.shape == (1, self.n_blades, self.n_probes):
            self._truth.append(decoded)

    def flush(self, final: bool = False) -> None:
        """Log the truth received since the last flush."""
        rows, self._truth = self._truth, []
        if rows:
            self._log("d_eqv", RevIndex.from_headers([d.header for d in rows]),
                      np.concatenate([d.body.d_eqv_m for d in rows]))

    def _log(self, leaf: str, index: RevIndex, d_m: np.ndarray) -> None:
        """``d_m`` (n, n_blades, n_probes), m: the selected blades of each probe, in mm."""
        for j in range(self.n_probes):
            self.out.scalars(f"{paths.displacement_path(j)}/{leaf}", index, d_m[:, self.blades, j] * MM)

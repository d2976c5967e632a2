"""Travelling-wave view: each probe's nodal-diameter spectrum against revolution (paper Fig. 10).

``tw/probe_<j>``: a tensor ``[nodal_diameter, revolution]`` of magnitudes (mm), rows by
signed ND from ``+(n_nd - 1)`` (forward, top) through 0 to ``-(n_nd - 1)`` (backward,
bottom) (:meth:`~bttsim_stream.process.travelling_wave.ProbeWave.signed_spectrum`);
revolutions without a message are 0. A whole recording logs it once, static; live it is a
rolling window of the last ``window`` revolutions, re-logged on the ``revolution``
timeline at most every ``period_s`` (re-logging the whole run each time would cost
O(n^2)). ``tw/nd``: the revolution's signed ND as identified by the processor from the fits
of all probes (the same in every probe's message).
"""

from __future__ import annotations

import math
import time

import numpy as np
import rerun as rr

from . import paths
from ._common import MM, RevIndex, ViewOutput

__all__ = ["TravellingWaveView"]


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
        self._spectra: dict[int, dict[int, np.ndarray]] = {}  # probe -> revolution -> signed spectrum (mm)
        self._max_mm = 0.0
        self._last_log = -math.inf
        self._nd_until = -1  # last revolution whose ND is logged
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
            for d in rows:
                spec = (d.body.signed_spectrum() * MM).astype(np.float32)
                self._spectra.setdefault(d.body.probe, {})[d.header.revolution] = spec
                self._max_mm = max(self._max_mm, float(np.nanmax(spec, initial=0.0)))
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

    def _trim(self) -> None:
        """Forget revolutions that left the live window (amortised: at twice its size)."""
        for spectra in self._spectra.values():
            if len(spectra) > 2 * self.window:
                last = max(spectra)
                for r in [r for r in spectra if r <= last - self.window]:
                    del spectra[r]

    def _log_matrices(self) -> None:
        self._last_log = time.monotonic()
        for probe, spectra in sorted(self._spectra.items()):
            last = max(spectra)
            first = last - self.window + 1 if self.out.live else min(spectra)
            n_rows = next(iter(spectra.values())).size
            mat = np.zeros((n_rows, last - first + 1), np.float32)
            for r, spec in spectra.items():
                if r >= first and spec.size == n_rows:
                    mat[:, r - first] = spec
            tensor = rr.Tensor(np.nan_to_num(mat), dim_names=["nodal_diameter", "revolution"],
                               value_range=(0.0, self._max_mm or 1.0))
            self.out.latest(paths.tw_path(probe), tensor, last)

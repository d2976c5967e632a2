"""Revolutions for the views: OPR and TOA messages in, speed and raw Eq. 1 displacement out.

Nothing here is new numerics: the messages are regrouped by the bus's
:class:`~bttsim_stream.bus.stream.RevolutionAssembler`, and the rotor phase and Eq. 1 are
those of :mod:`bttsim_stream.process.displacement` (:func:`rotor_phase_from_opr`,
:func:`displacements_from_phase`, :func:`calibrate_arrival_angles`), applied as the
streaming processor applies them:

* revolution ``k`` uses the quadratic rotor phase through OPR pulses ``k-1, k, k+1`` (row
  1 of :func:`rotor_phase_from_opr` on those three), so it is shown once revolution ``k+1``
  has been assembled; a revolution without a predecessor (the first, or after lost ones)
  takes the acceleration of the next one (row 0 of ``k, k+1, k+2``), one without a
  successor (the last) the extrapolated speed (last row of ``k-2, k-1, k``);
* the arrival angles are nominal, from the run metadata's sensing angles (the model's P_nom
  angles), when it carries them; otherwise they are calibrated once, as the median arrival
  angle over the first :data:`CALIBRATION_REVOLUTIONS` revolutions (which are then held back
  until the calibration is done).

Arrays are ``(revolution, blade, probe)``; SI units (s, rad, rad/s, m).
"""

from __future__ import annotations

import math
from collections import deque
from itertools import chain
from dataclasses import dataclass

import numpy as np

from ..bus.stream import Revolution, RevolutionAssembler
from ..process.displacement import (Geometry, RotorPhase, calibrate_arrival_angles,
                                    displacements_from_phase, rotor_phase_from_opr)
from ..process.options import LIVE_CALIBRATION

__all__ = ["CALIBRATION_REVOLUTIONS", "ShownRevolutions", "RevolutionDisplacements"]

#: Revolutions of the arrival-angle calibration when the metadata has no sensing angles: the
#: streaming processor's live window, so that the views and the live fits agree.
CALIBRATION_REVOLUTIONS = LIVE_CALIBRATION


@dataclass(frozen=True, slots=True, eq=False)
class ShownRevolutions:
    """Revolutions ready to be shown.

    Attributes
    ----------
    revolution : ndarray of int64, shape (n,)
    opr_s : ndarray, shape (n,)
        OPR pulse times, s.
    omega_rad_s : ndarray, shape (n,)
        Mean speed of each revolution (Eq. 1's Omega), rad/s.
    d_m : ndarray, shape (n, n_blades, n_probes)
        Raw Eq. 1 displacement, m (NaN where a TOA is missing).
    """

    revolution: np.ndarray
    opr_s: np.ndarray
    omega_rad_s: np.ndarray
    d_m: np.ndarray

    def __len__(self) -> int:
        return int(self.revolution.size)


def _stack(phases: list[RotorPhase]) -> RotorPhase:
    """One :class:`RotorPhase` of the rows of several."""
    return RotorPhase(*(np.concatenate([getattr(p, f) for p in phases])
                        for f in ("opr_s", "omega0_rad_s", "alpha_rad_s2", "omega_mean_rad_s")))


def _phases(ready: list) -> RotorPhase:
    """The rotor phases of ``(revolution, phase)`` pairs, in order, as one :class:`RotorPhase`;
    a phase given as the pulse times ``(prev, t0, next)`` is the middle row of
    :func:`~bttsim_stream.process.displacement.rotor_phase_from_opr` of those three.

    All such windows go through one call: laid end to end, row ``3 i + 1`` of the long
    sequence depends on the pulses ``3 i .. 3 i + 2`` alone, by the same element-wise
    operations, so it is the window's middle row bit for bit (the rows between two windows
    are not used: their errors are ignored).
    """
    windows = [p for _, p in ready if isinstance(p, tuple)]
    if not windows:
        return _stack([p for _, p in ready])
    with np.errstate(all="ignore"):
        batch = rotor_phase_from_opr(np.array(windows, dtype=float).ravel()).rows(slice(1, None, 3))
    if len(windows) == len(ready):
        return batch
    rows, i = [], 0
    for _, p in ready:
        if isinstance(p, tuple):
            rows.append(batch.rows(slice(i, i + 1)))
            i += 1
        else:
            rows.append(p)
    return _stack(rows)


class RevolutionDisplacements:
    """Speed and Eq. 1 displacement of each revolution of a stream, in revolution order.

    Parameters
    ----------
    info : RunInfo
        The run metadata: blade and probe counts, probe and OPR angles, tip radius, and the
        sensing angles when known.
    calibration_revolutions : int
        Calibration window when the metadata carries no sensing angles.

    Attributes
    ----------
    geometry : Geometry
    blade_angles_rad : ndarray, shape (n_blades,)
        Blade angles for drawing: the sensing angles, else ``2 pi b / n_blades``.
    method : str
        ``"nominal"`` (sensing angles) or ``"calibrated"``.
    skipped : int
        Revolutions that could not be shown (an OPR pulse with no neighbour).
    """

    def __init__(self, info, *, calibration_revolutions: int = CALIBRATION_REVOLUTIONS) -> None:
        nb, npr = int(info.n_blades), int(info.n_probes)
        self.geometry = Geometry(n_blades=nb, probe_angles_rad=info.probe_angles_rad,
                                 tip_radius_m=info.tip_radius_m, opr_angle_rad=info.opr_angle_rad,
                                 blade_angles_rad=info.sensing_angles_rad)
        self.blade_angles_rad = self.geometry.blade_angles_rad
        if info.sensing_angles_rad is not None:
            self.method, self._psi = "nominal", self.geometry.nominal_arrival_angles()
        else:
            self.method, self._psi = "calibrated", None
        self._n_cal = max(1, int(calibration_revolutions))
        self._asm = RevolutionAssembler(nb, npr)
        self._queue: deque[Revolution] = deque()   # assembled, not yet shown
        self._before: deque[Revolution] = deque(maxlen=2)  # the last two taken from the queue
        self._last_popped = -1
        self._held: list[tuple[Revolution, RotorPhase]] = []  # waiting for the calibration
        self.skipped = 0

    def add(self, kind: str, decoded) -> None:
        """An ``opr`` or ``toa`` message (:class:`~bttsim_stream.bus.codec.Decoded`)."""
        self._asm.add(kind, decoded)
        if kind == "opr":  # keep the assembler short (its pop scans what it holds)
            self._take(final=False)

    def _take(self, final: bool) -> None:
        for r in self._asm.pop(final):
            self._queue.append(r)
            self._last_popped = r.revolution

    # -- OPR window ----------------------------------------------------------------------
    def _opr(self, k: int) -> float | None:
        """OPR time of revolution ``k``: None while it may still come, NaN if it never will."""
        for r in chain(self._before, self._queue):  # k is near the front: stop there
            if r.revolution == k:
                return r.opr_s
        return math.nan if k <= self._last_popped else None

    def _phase(self, k: int, final: bool):
        """The rotor phase of revolution ``k`` (one row), None to wait for more, False if it
        cannot have one (no neighbouring OPR pulse); with both neighbouring pulses, their
        times and its own ``(prev, t0, next)`` (the row is computed with the others',
        :func:`_phases`)."""
        prev, nxt = self._opr(k - 1), self._opr(k + 1)
        if final:
            prev, nxt = (math.nan if v is None else v for v in (prev, nxt))
        if prev is None or nxt is None:
            return None
        t0 = self._opr(k)
        if not math.isnan(prev) and not math.isnan(nxt):
            return prev, t0, nxt
        if not math.isnan(nxt):  # no predecessor: the acceleration of the next revolution
            nxt2 = self._opr(k + 2)
            if nxt2 is None and not final:
                return None
            window = [t0, nxt] + ([] if nxt2 is None or math.isnan(nxt2) else [nxt2])
            return rotor_phase_from_opr(np.array(window)).rows(slice(0, 1))
        if not math.isnan(prev):  # no successor: the extrapolated speed
            prev2 = self._opr(k - 2)
            window = ([] if prev2 is None or math.isnan(prev2) else [prev2]) + [prev, t0]
            return rotor_phase_from_opr(np.array(window)).rows(slice(-1, None))
        return False

    # -- output --------------------------------------------------------------------------
    def pop(self, final: bool = False) -> ShownRevolutions | None:
        """The revolutions that can be shown now (``final``: all that can be), or None."""
        self._take(final)
        ready: list[tuple[Revolution, RotorPhase]] = []
        while self._queue:
            r = self._queue[0]
            phase = self._phase(r.revolution, final)
            if phase is None:
                break
            self._before.append(self._queue.popleft())
            if phase is False:
                self.skipped += 1
            else:
                ready.append((r, phase))
        if self._psi is None:
            self._held += ready
            if not self._held or (len(self._held) < self._n_cal and not final):
                return None
            ready, self._held = self._held, []
            self._calibrate(ready[: self._n_cal])
        if not ready:
            return None
        phase = _phases(ready)
        toa = np.stack([r.toa_s for r, _ in ready])
        d, _ = displacements_from_phase(phase, toa, self._psi, self.geometry.tip_radius_m)
        return ShownRevolutions(revolution=np.array([r.revolution for r, _ in ready], dtype=np.int64),
                                opr_s=phase.opr_s, omega_rad_s=phase.omega_mean_rad_s, d_m=d)

    def _calibrate(self, rows: list[tuple[Revolution, RotorPhase]]) -> None:
        """Arrival angles from the first revolutions; nominal (``2 pi b / n_blades``) where no
        arrival was seen."""
        psi = calibrate_arrival_angles(_phases(rows), np.stack([r.toa_s for r, _ in rows]),
                                       len(rows))
        self._psi = np.where(np.isfinite(psi), psi, self.geometry.nominal_arrival_angles())


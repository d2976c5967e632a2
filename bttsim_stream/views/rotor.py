"""Rotor view: the blades at each OPR instant, tips moved by their (exaggerated) Eq. 1 displacement.

Drawn in units of the tip radius, +x right and +y up (Rerun's 2-D space has y down: points
are logged as ``(x, -y)``), angles anticlockwise from +x as in the model: ``rotor/casing``
(casing and hub circles), ``rotor/probes`` (``P<j>`` at the probe angles), ``rotor/opr``
(the OPR sensor), static; ``rotor/blades``, one frame per revolution: each blade from hub to
tip at its angle at the OPR pulse (the sensing angle, or ``2 pi b / n_blades`` when the
metadata has none), its tip moved tangentially by ``exaggeration x`` its displacement at
probe 0 along a quadratic bending line; blade 0 in orange.
"""

from __future__ import annotations

import math

import numpy as np
import rerun as rr

from . import paths
from ._common import BLUE, GREY, ORANGE, RED, TWO_PI, RevIndex, ViewOutput
from .revolutions import ShownRevolutions

__all__ = ["DEFAULT_EXAGGERATION", "RotorView"]

#: Default exaggeration of the tip deflection.
DEFAULT_EXAGGERATION = 20.0
_HUB_RATIO = 0.55
_CASING_RATIO = 1.1
_POINTS_PER_BLADE = 6


def _screen(r, a) -> np.ndarray:
    """Polar (radius, angle anticlockwise) to Rerun 2-D coordinates (y down), last axis 2."""
    r, a = np.broadcast_arrays(np.asarray(r, float), np.asarray(a, float))
    return np.stack([r * np.cos(a), -r * np.sin(a)], axis=-1)


class RotorView:
    """The rotor seen along its axis.

    Parameters
    ----------
    out : ViewOutput
    info : RunInfo
    blade_angles_rad : ndarray, shape (n_blades,)
        Angle of each blade in the rotor frame at the OPR pulse, rad.
    exaggeration : float
        Gain on the tip deflection.
    """

    def __init__(self, out: ViewOutput, info, blade_angles_rad: np.ndarray,
                 exaggeration: float = DEFAULT_EXAGGERATION) -> None:
        self.out = out
        self.angles_rad = np.asarray(blade_angles_rad, float) + float(info.opr_angle_rad)  # in space at the OPR
        self.gain = float(exaggeration) / float(info.tip_radius_m)
        self._log_static(info)

    def _log_static(self, info) -> None:
        root, nb = paths.ROTOR, int(info.n_blades)
        circle = np.linspace(0.0, TWO_PI, 181)
        self.out.static(f"{root}/casing", rr.LineStrips2D([_screen(_CASING_RATIO, circle), _screen(_HUB_RATIO, circle)],
                                                          colors=[GREY, GREY], radii=[0.003, 0.003]))
        pa = np.asarray(info.probe_angles_rad, float)
        self.out.static(f"{root}/probes", rr.Arrows2D(origins=_screen(1.3, pa), vectors=_screen(0.17, pa + math.pi),
                                                      labels=[f"P{j}" for j in range(pa.size)],
                                                      colors=[BLUE] * pa.size, radii=0.01))
        opr = float(info.opr_angle_rad)
        self.out.static(f"{root}/opr", rr.Arrows2D(origins=_screen(1.45, [opr]), vectors=_screen(0.3, [opr + math.pi]),
                                                   labels=["OPR"], colors=[RED], radii=0.015))
        colors = np.tile(np.array([[120, 160, 200]], np.uint8), (nb, 1))
        colors[0] = ORANGE
        labels = [""] * nb
        labels[0] = "blade 0"
        self.out.style(f"{root}/blades", rr.LineStrips2D.from_fields(colors=colors, radii=np.full(nb, 0.013),
                                                                     labels=labels))

    def strips(self, d_m: np.ndarray) -> np.ndarray:
        """Blade outlines for displacements ``d_m`` (n, n_blades) in m: shape (n, n_blades, 6, 2)."""
        s = np.linspace(0.0, 1.0, _POINTS_PER_BLADE)
        radius = _HUB_RATIO + (1.0 - _HUB_RATIO) * s
        bend = self.gain * np.nan_to_num(np.asarray(d_m, float))
        a = self.angles_rad[None, :, None] + bend[:, :, None] * (s * s)[None, None, :]
        return _screen(radius[None, None, :], a)

    def update(self, rows: ShownRevolutions) -> None:
        """Log one frame per revolution (the displacement at probe 0)."""
        strips = self.strips(rows.d_m[:, :, 0])
        n, nb = strips.shape[:2]
        self.out.columns(f"{paths.ROTOR}/blades", RevIndex.of(rows.revolution, rows.opr_s),
                         rr.LineStrips2D.columns(strips=strips.reshape(n * nb, *strips.shape[2:])), nb)

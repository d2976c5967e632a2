"""Calibration of the parametric bladed disk to the paper's modal data (Sec. 3.1, Fig. 3).

Four knobs, four targets, solved by Newton's method on log-frequencies with a
finite-difference Jacobian in log-parameters (eigenvalues carry about 1e-9 relative round-off, hence a
finite-difference step of 1e-4 and a tolerance of 1e-8; each evaluation is a 72-DOF blade-alone and
two ~100-DOF cyclic eigensolves, a few milliseconds):

==========================  ============================================  =============
knob                        physical meaning                              drives
==========================  ============================================  =============
``root_thickness_m``        aerofoil thickness at the root                1F: ND 14 first family = 347.5 Hz
``torsion_factor``          effective torsion constant ``J = k_J c t^3``  1T: blade-alone mode 2 = 1148.9 Hz
``thickness_taper``         tip / root thickness                          2F: blade-alone mode 3 = 1717 Hz
``web_thickness_m``         axial thickness of the disk web               ND 1 first family = 343.9 Hz
==========================  ============================================  =============

The calibrated values are stored as the defaults of
:class:`~bttsim_stream.model.bladed_disk.BladedDiskDesign`; ``tests/test_model.py``
checks that the defaults still meet the targets and that this routine reproduces them.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .bladed_disk import BladedDiskDesign, assemble_sector, blade_alone_frequencies, solve_cyclic

__all__ = ["KNOBS", "TARGETS_HZ", "design_frequencies", "calibrate_design"]

KNOBS = ("root_thickness_m", "torsion_factor", "thickness_taper", "web_thickness_m")
#: ND 14 family 1, blade-alone mode 2 and 3, ND 1 family 1 (paper Sec. 3.1, Fig. 3).
TARGETS_HZ = np.array([347.5, 1148.9, 1717.0, 343.9])


def design_frequencies(d: BladedDiskDesign) -> np.ndarray:
    """The four calibrated frequencies (Hz), in the order of :data:`TARGETS_HZ`."""
    fb = blade_alone_frequencies(d, 3)
    sol = solve_cyclic(d, assemble_sector(d), nds=[1, d.n_blades // 2], n_families=1)
    return np.array([sol.freq_hz[1, 0], fb[1], fb[2], sol.freq_hz[0, 0]])


def calibrate_design(d: BladedDiskDesign | None = None, tol: float = 1e-8,
                     max_iter: int = 30) -> BladedDiskDesign:
    """Newton iteration on the four knobs until every target holds to ``tol`` (relative)."""
    d = BladedDiskDesign() if d is None else d
    x = np.log([getattr(d, k) for k in KNOBS])
    target = np.log(TARGETS_HZ)

    def f(xv: np.ndarray) -> np.ndarray:
        dd = replace(d, **{k: float(np.exp(v)) for k, v in zip(KNOBS, xv)})
        return np.log(design_frequencies(dd)) - target

    r = f(x)
    for _ in range(max_iter):
        if np.max(np.abs(r)) < tol:
            break
        h = 1e-4
        J = np.column_stack([(f(x + h * e) - r) / h for e in np.eye(len(x))])
        step = np.linalg.solve(J, -r)
        step = np.clip(step, -0.5, 0.5)
        x = x + step
        r = f(x)
    else:
        raise RuntimeError(f"calibration did not converge: residual {np.max(np.abs(r)):.2e}")
    return replace(d, **{k: float(np.exp(v)) for k, v in zip(KNOBS, x)})

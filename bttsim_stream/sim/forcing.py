"""Blade forcing projected on the modes: per-blade force patterns -> complex modal forces.

A force pattern ``F_b`` (N, complex, one value per blade) along a unit ``direction`` (radial,
tangential, axial) at an edge node of every blade forces mode ``k`` with
``Im(C_k exp(i theta(t)))``, ``C_k = sum_b (phi_force,k,b . d) F_b`` (paper Eq. 5-7).
"""

from __future__ import annotations

import numpy as np

from ..errors import BttsimError

__all__ = ["edge_shapes", "modal_forcing"]


def edge_shapes(model, node: str) -> np.ndarray:
    """Force-node mode shapes (n_modes, n_blades, 3) of the edge ``node`` ("leading_edge" or
    "trailing_edge", the latter from the model file's ``force_shapes_trailing_edge``)."""
    if node == "leading_edge":
        return model.force_shapes
    if "force_shapes_trailing_edge" not in model.extra:
        raise BttsimError("excitation node 'trailing_edge' needs force_shapes_trailing_edge in the model file")
    return model.extra["force_shapes_trailing_edge"]


def modal_forcing(model, excitations) -> tuple[np.ndarray, np.ndarray]:
    """Complex modal force amplitudes (paper Eq. 5-7).

    Parameters
    ----------
    model : ModalModel
    excitations : sequence of scenario ``Excitation``
        Engine order, nodal diameter (travelling-wave phase ``2 pi (b-1) N_ND / N_b``),
        amplitude (N), direction (radial, tangential, axial; normalised here), edge node.

    Returns
    -------
    C : ndarray, shape (n_modes, n_exc), complex
        Modal force of excitation m is ``Im(C[k, m] exp(i EO_m phi(t)))``, N per unit modal
        coordinate.
    eo : ndarray, shape (n_exc,)
    """
    n_b = model.n_blades
    C = np.zeros((model.n_modes, len(excitations)), complex)
    eo = np.zeros(len(excitations))
    b = np.arange(n_b)
    for m, ex in enumerate(excitations):
        shapes = edge_shapes(model, ex.node)
        d = np.asarray(ex.direction, float)
        d = d / np.linalg.norm(d)
        phase = np.exp(2j * np.pi * b * ex.nodal_diameter / n_b)
        C[:, m] = ex.amplitude_n * (shapes @ d) @ phase
        eo[m] = ex.engine_order
    return C, eo

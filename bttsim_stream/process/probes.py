"""Probe layout: condition number of ``B`` (Eq. 16) and a search over candidate angles.

The condition number (CN) is the 2-norm one, ``sigma_max / sigma_min`` of ``B``
(``numpy.linalg.cond``); it measures how much the sine fit amplifies displacement errors
(paper Sec. 3.3.3, Table 3). Angles are in degrees at this module's public surface,
because layouts are written that way on drawings and in the paper; everything else in the
package is in radians.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from .fit import design_matrix

__all__ = ["condition_number", "LayoutCandidate", "rank_layouts", "PAPER_TABLE3", "PAPER_CANDIDATES_DEG"]

#: Table 3 of the paper: probe angles (deg) and the printed CN at EO 8.
PAPER_TABLE3 = (
    ((5.0, 15.15, 23.82, 220.0, 301.5), 1.4),
    ((5.0, 23.82, 148.5, 220.0, 255.6), 1.5),
    ((10.6, 15.15, 23.82, 190.35, 220.0), 2.0),
    ((5.0, 23.82, 148.5, 190.35, 255.6), 2.6),
    ((15.15, 148.5, 190.35, 202.11, 301.5), 3.8),
    ((5.0, 10.6, 148.5, 220.0, 357.0), 5.0),
    ((10.6, 148.5, 190.35, 255.6, 301.5), 7.3),
    ((10.6, 15.15, 23.82, 148.5, 190.35), 10.0),
    ((5.0, 10.6, 15.15, 148.5, 190.35), 16.7),
)
#: The 11 candidate probe angles of Sec. 3.3.3 (deg).
PAPER_CANDIDATES_DEG = (5.0, 10.6, 15.15, 23.82, 148.5, 190.35, 202.11, 220.0, 255.6, 301.5, 357.0)


def condition_number(engine_orders, probe_angles_deg) -> float:
    """2-norm condition number of ``B`` (Eq. 16) for engine order(s) and probe angles.

    Parameters
    ----------
    engine_orders : int or sequence of int
    probe_angles_deg : array_like, shape (n_probes,)
        Probe angles, degrees.

    Returns
    -------
    float
        ``inf`` when the probes cannot separate the unknowns (fewer probes than
        ``1 + 2 n_eo``, or a rank-deficient layout).

    Examples
    --------
    >>> round(condition_number(8, [5, 15.15, 23.82, 220, 301.5]), 4)
    1.4328
    """
    B = design_matrix(np.deg2rad(np.asarray(probe_angles_deg, dtype=float)), engine_orders)
    if B.shape[0] < B.shape[1]:
        return math.inf
    s = np.linalg.svd(B, compute_uv=False)
    return float(s[0] / s[-1]) if s[-1] > s[0] * 1e-14 else math.inf


@dataclass(frozen=True, slots=True)
class LayoutCandidate:
    """One probe layout and its condition number."""

    probe_angles_deg: tuple
    cn: float


def rank_layouts(engine_orders, candidate_angles_deg, n_probes: int) -> list[LayoutCandidate]:
    """Every choice of ``n_probes`` among the candidate angles, best (lowest CN) first.

    Parameters
    ----------
    engine_orders : int or sequence of int
    candidate_angles_deg : sequence of float
    n_probes : int

    Returns
    -------
    list of LayoutCandidate
        ``C(n_candidates, n_probes)`` layouts sorted by CN (ties keep the combination
        order). The condition numbers are computed in one batched SVD.

    Examples
    --------
    >>> ranked = rank_layouts(8, PAPER_CANDIDATES_DEG, 5)
    >>> len(ranked), round(ranked[0].cn, 2), round(ranked[-1].cn, 2)
    (462, 1.43, 16.74)
    """
    angles = tuple(float(a) for a in candidate_angles_deg)
    n_probes = int(n_probes)
    if not 1 <= n_probes <= len(angles):
        raise ValueError(f"n_probes must be in [1, {len(angles)}], got {n_probes}")
    combos = np.array(list(itertools.combinations(range(len(angles)), n_probes)), dtype=np.int64)
    B_all = design_matrix(np.deg2rad(np.asarray(angles)), engine_orders)  # (n_cand, p)
    B = B_all[combos]  # (n_combo, n_probes, p)
    if B.shape[1] < B.shape[2]:
        cn = np.full(len(combos), math.inf)
    else:
        s = np.linalg.svd(B, compute_uv=False)
        with np.errstate(divide="ignore"):
            cn = np.where(s[:, -1] > s[:, 0] * 1e-14, s[:, 0] / s[:, -1], math.inf)
    order = np.argsort(cn, kind="stable")
    return [LayoutCandidate(tuple(angles[i] for i in combos[k]), float(cn[k])) for k in order]

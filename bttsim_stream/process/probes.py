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

from ..defaults import MAX_ENGINE_ORDER
from ..errors import BttsimError
from .fit import design_matrix

__all__ = ["condition_number", "LayoutCandidate", "rank_layouts", "PAPER_TABLE3", "PAPER_CANDIDATES_DEG",
           "LayoutError", "check_engine_orders", "check_angles", "check_layout", "layout_report",
           "CN_WARN", "CN_SINGULAR"]

#: Above this condition number a layout is usable but poor: the paper (Sec. 3.3.3, Fig. 11)
#: finds mean E_A below 4 % only for CN < 10, and the spread of the errors grows with the CN.
CN_WARN = 10.0
#: At or above this condition number the probes cannot separate the unknowns of Eq. 16 in
#: practice (a displacement error of 1 um becomes a metre of amplitude): the layout is singular.
CN_SINGULAR = 1e6


class LayoutError(BttsimError, ValueError):
    """An impossible probe layout or engine order (one line for the user)."""

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


def check_engine_orders(engine_orders) -> tuple:
    """The engine orders as a tuple of int, each in [1, ``MAX_ENGINE_ORDER``].

    Raises
    ------
    LayoutError
        An engine order below 1 (EO 0 is a static deflection, not a vibration; a negative EO
        is the same sine pattern as its opposite) or above 1000, or none at all.
    """
    eos = np.atleast_1d(np.asarray(engine_orders))
    if eos.size == 0:
        raise LayoutError("at least one engine order is needed")
    out = []
    for e in eos.tolist():
        if isinstance(e, float) and not float(e).is_integer():
            raise LayoutError(f"engine orders are whole numbers, got {e:g}")
        if not 1 <= int(e) <= MAX_ENGINE_ORDER:
            raise LayoutError(f"engine order must be in [1, {MAX_ENGINE_ORDER}], got {int(e)}")
        out.append(int(e))
    return tuple(out)


def check_angles(angles_deg, what: str = "probe angles") -> tuple:
    """Probe angles as a tuple of float: finite, distinct, in [0, 360) degrees.

    Raises
    ------
    LayoutError
    """
    vals = [float(a) for a in np.atleast_1d(np.asarray(angles_deg, dtype=float))]
    if not vals:
        raise LayoutError(f"{what}: at least one angle is needed")
    for a in vals:
        if not math.isfinite(a):
            raise LayoutError(f"{what} must be finite, got {a}")
        if not 0.0 <= a < 360.0:
            raise LayoutError(f"{what} must lie in [0, 360) deg, got {a:g}")
    if len(set(vals)) != len(vals):
        dup = sorted({a for a in vals if vals.count(a) > 1})
        raise LayoutError(f"{what} must be distinct, got {', '.join(f'{a:g}' for a in dup)} twice")
    return tuple(vals)


def check_layout(engine_orders, probe_angles_deg) -> float:
    """Validate a layout for fitting Eq. 16 at ``engine_orders`` jointly; return its CN.

    Parameters
    ----------
    engine_orders : int or sequence of int
    probe_angles_deg : array_like, shape (n_probes,)

    Returns
    -------
    float
        The condition number of ``B`` (below :data:`CN_SINGULAR`).

    Raises
    ------
    LayoutError
        EO < 1, angles outside [0, 360) or repeated, fewer probes than unknowns
        (``1 + 2 n_eo``), or a singular layout (CN >= :data:`CN_SINGULAR`): the message
        names the fix.
    """
    eos = check_engine_orders(engine_orders)
    angles = check_angles(probe_angles_deg)
    unknowns = 1 + 2 * len(eos)
    label = "EO " + "+".join(str(e) for e in eos)
    if len(angles) < unknowns:
        raise LayoutError(f"{len(angles)} probe(s) cannot separate the {unknowns} unknowns of the sine fit at "
                          f"{label} (Eq. 16): add probes (at least {unknowns})")
    cn = condition_number(eos, angles)
    if not cn < CN_SINGULAR:
        raise LayoutError(f"the probe layout {', '.join(f'{a:g}' for a in angles)} deg is singular at {label} "
                          f"(condition number {cn:.3g}): the probes see the engine order at (nearly) "
                          f"the same phases; add probes or move them (try `bttsim probes --eo {eos[0]}`)")
    return cn


def layout_report(engine_orders, probe_angles_deg) -> tuple[list[tuple[str, float]], list[str]]:
    """Condition numbers of a layout for each engine order (and all of them jointly).

    Returns
    -------
    rows : list of (label, cn)
        ``("EO 8", 1.43)`` per engine order, then ``("EO 8+9", ...)`` for several.
    warnings : list of str
        One line per CN above :data:`CN_WARN` (and for a singular joint fit, where the
        pipeline falls back to one engine order at a time).

    Raises
    ------
    LayoutError
        As :func:`check_layout`, for any single engine order.
    """
    eos = tuple(dict.fromkeys(check_engine_orders(engine_orders)))
    rows, warns = [], []
    for eo in eos:
        cn = check_layout(eo, probe_angles_deg)
        rows.append((f"EO {eo}", cn))
        if cn > CN_WARN:
            warns.append(f"condition number {cn:.3g} at EO {eo} is above {CN_WARN:g}: expect large amplitude "
                         f"errors (paper Fig. 11); move probes (`bttsim probes --eo {eo}`)")
    if len(eos) > 1:
        label = "EO " + "+".join(str(e) for e in eos)
        try:
            cn = check_layout(eos, probe_angles_deg)
        except LayoutError:
            cn = math.inf
        rows.append((label, cn))
        if not cn < CN_SINGULAR:
            warns.append(f"the probes cannot fit {label} jointly ({len(check_angles(probe_angles_deg))} probes for "
                         f"{1 + 2 * len(eos)} unknowns, or a singular layout): each engine order is fitted "
                         f"on its own, and their responses leak into each other")
        elif cn > CN_WARN:
            warns.append(f"condition number {cn:.3g} for {label} jointly is above {CN_WARN:g}")
    return rows, warns


@dataclass(frozen=True, slots=True)
class LayoutCandidate:
    """One probe layout and its condition number."""

    probe_angles_deg: tuple
    cn: float


#: The most layouts :func:`rank_layouts` ranks (about 8 s and 450 MB of 5 probes at EO 8):
#: choosing among many candidates is combinatorial (64 angles, 10 probes: 1.5e11 layouts).
MAX_LAYOUTS = 1_000_000


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
        raise LayoutError(f"the number of probes must be in [1, {len(angles)}] (the number of candidate "
                          f"angles), got {n_probes}")
    n_layouts = math.comb(len(angles), n_probes)
    if n_layouts > MAX_LAYOUTS:
        raise LayoutError(f"{n_layouts:,} layouts of {n_probes} probes among {len(angles)} candidate angles: more "
                          f"than the {MAX_LAYOUTS:,} ranked at once (fewer candidates, or fix some angles)")
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

"""Cyclic-symmetry sector results and their expansion to the full wheel.

The neutral sector format (``schemas/cyclic_sector.md``, schema ``bttsim.cyclic_sector``
version 1) holds what any FE package's cyclic-symmetry modal analysis gives for one sector
(one blade with its disk segment), at the points BTT needs:

* ``harmonic_index`` (n_sol,) int, 0 .. n_sectors // 2, and ``freq_hz`` (n_sol,);
* the reference sector's tip nodes ``tip_xyz`` (n_tip, 3) and excitation node
  ``force_xyz`` (3,), Cartesian, m, ``+z`` the rotation axis, the rotor turning anticlockwise
  seen from ``+z``; sector ``s`` is the reference sector turned by ``2 pi s / n_sectors``
  about ``+z``;
* complex sector shapes ``tip_shapes`` (n_sol, n_tip, 3) and ``force_shapes`` (n_sol, 3)
  (UX, UY, UZ in the reference sector's Cartesian frame), or their real and imaginary parts
  as ``*_cos`` / ``*_sin`` arrays.

Conventions (written once)
--------------------------
A solution of harmonic index ``k`` with complex sector shape ``u`` moves sector ``s``
(``theta_s = 2 pi s / N``) by ``R(theta_s) u e^{i k theta_s}`` (``R``: rotation about ``+z``):
its real part is the "cosine" standing wave, its imaginary part the "sine" one.

Normalisation ``"sector"`` (the default, what a cyclic eigen-solver returns): ``u^H M_k u = 1``
with ``M_k`` the cyclic-reduced sector mass matrix. The real full-wheel modes are then

* ``k = 0`` (and ``k = N/2``, even N): ``phi_s = R(theta_s) Re(u e^{i k theta_s}) / sqrt(N)``
  (``u`` first turned real: these solutions are standing waves);
* ``0 < k < N/2``: the pair ``sqrt(2/N) R(theta_s) Re(u e^{i k theta_s})`` and
  ``sqrt(2/N) R(theta_s) Im(u e^{i k theta_s})``,

which satisfy ``Phi^T M Phi = I`` on the full wheel (``sum_s e^{2 i k theta_s} = 0`` for
``0 < k < N/2``). Normalisation ``"wheel"``: the shapes are already the full-wheel
mass-normalised cosine / sine modes of sector 0 (factors 1 instead of ``sqrt(2/N)``,
``sqrt(1/N)``).

The numerical functions here never import the bus; the file readers live in
:mod:`bttsim_stream.model.importers`.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field

import numpy as np

from ..defaults import MAX_BLADES
from ..errors import ModelFileError
from .bladed_disk import rotation_z
from .modal_model import SCHEMA_VERSION as MODEL_SCHEMA_VERSION
from .modal_model import MAX_SPEEDS, ModalModel, model_from_cartesian, to_polar
from .npzfile import read_npz

__all__ = ["SECTOR_SCHEMA", "SECTOR_SCHEMA_VERSION", "TIP_RADIUS_RANGE_M", "SHAPE_RANGE", "TIP_SPACING_MIN",
           "CyclicSector", "expand_sector", "expand_sectors_at_speeds", "save_sector", "load_sector", "builtin_sector",
           "tip_geometry", "TipGeometry"]

#: Mean radius of a sector's tip nodes, m: a rotor between 5 mm and 10 m (coordinates in
#: another unit land outside).
TIP_RADIUS_RANGE_M = (0.005, 10.0)
#: Range of the largest component of each solution's tip shape, m per unit mass-normalised
#: modal coordinate (m / sqrt(kg)): below, a mode that does not move the tip (an all-zero,
#: blank export); above, a modal mass under 1e-12 kg (shapes not mass-normalised, or not SI).
#: The force shapes are held to the upper bound.
SHAPE_RANGE = (1e-12, 1e6)
#: Least distance between consecutive tip nodes, as a fraction of the tip radius (0.19 um at
#: 0.19 m): closer nodes are one point, and a chord of one point has no stagger.
TIP_SPACING_MIN = 1e-6

SECTOR_SCHEMA = "bttsim.cyclic_sector"
SECTOR_SCHEMA_VERSION = 1
NORMALISATIONS = ("sector", "wheel")


@dataclass(frozen=True, slots=True, eq=False)
class CyclicSector:
    """One sector's cyclic-symmetry modal solution at the tip and excitation nodes.

    Attributes
    ----------
    n_sectors : int
        Sectors (blades) of the full wheel.
    harmonic_index : ndarray of int, shape (n_sol,)
        Harmonic index (nodal diameter) ``0 <= k <= n_sectors // 2`` of each solution.
    freq_hz : ndarray, shape (n_sol,)
        Natural frequencies, Hz.
    tip_xyz : ndarray, shape (n_tip, 3)
        Reference sector's tip nodes, m, ordered from the trailing edge.
    tip_shapes : ndarray of complex, shape (n_sol, n_tip, 3)
        Complex sector shapes (UX, UY, UZ) at the tip nodes (module conventions).
    force_xyz : ndarray, shape (3,)
    force_shapes : ndarray of complex, shape (n_sol, 3)
    nominal_node : int
        0-based tip node index of the nominal sensing point P_nom.
    stagger_deg : float or None
        Tip stagger; None: measured from the tip nodes (:func:`tip_geometry`).
    normalisation : {"sector", "wheel"}
    provenance : dict
    """

    n_sectors: int
    harmonic_index: np.ndarray
    freq_hz: np.ndarray
    tip_xyz: np.ndarray
    tip_shapes: np.ndarray
    force_xyz: np.ndarray
    force_shapes: np.ndarray
    nominal_node: int = 0
    stagger_deg: float | None = None
    normalisation: str = "sector"
    provenance: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        N = int(self.n_sectors)
        k, f = np.asarray(self.harmonic_index), np.asarray(self.freq_hz)
        n = f.shape[0] if f.ndim == 1 else -1
        problems = []
        if not 2 <= N <= MAX_BLADES:
            problems.append(f"n_sectors must be in [2, {MAX_BLADES}] (the blades of a run), got {N}")
        if f.ndim != 1 or n == 0:
            problems.append(f"freq_hz must be a non-empty 1-D array, got shape {f.shape}")
        elif not np.all(np.isfinite(f)) or np.any(f <= 0):
            problems.append("freq_hz must be finite and > 0")
        if k.shape != (n,) or k.dtype.kind not in "iu":
            problems.append(f"harmonic_index must be ({n},) integers, got {k.shape} {k.dtype}")
        elif k.size and (k.min() < 0 or k.max() > N // 2):
            problems.append(f"harmonic_index must lie in 0..{N // 2} for {N} sectors, got {k.min()}..{k.max()}")
        t = np.asarray(self.tip_xyz)
        if t.ndim != 2 or t.shape[1] != 3 or t.shape[0] < 2:
            problems.append(f"tip_xyz must be (n_tip >= 2, 3), got {t.shape}")
        elif np.asarray(self.tip_shapes).shape != (n, t.shape[0], 3):
            problems.append(f"tip_shapes must be ({n}, {t.shape[0]}, 3), got {np.asarray(self.tip_shapes).shape}")
        if np.asarray(self.force_xyz).shape != (3,):
            problems.append(f"force_xyz must be (3,), got {np.asarray(self.force_xyz).shape}")
        if np.asarray(self.force_shapes).shape != (n, 3):
            problems.append(f"force_shapes must be ({n}, 3), got {np.asarray(self.force_shapes).shape}")
        for name in ("tip_xyz", "tip_shapes", "force_xyz", "force_shapes"):
            if not np.all(np.isfinite(np.asarray(getattr(self, name)))):
                problems.append(f"{name} holds NaN or inf")
        if self.normalisation not in NORMALISATIONS:
            problems.append(f"normalisation must be one of {NORMALISATIONS}, got {self.normalisation!r}")
        if not problems and not 0 <= int(self.nominal_node) < t.shape[0]:
            problems.append(f"nominal_node must be in 0..{t.shape[0] - 1}, got {self.nominal_node}")
        if not problems:
            r_tip = float(np.mean(np.hypot(t[:, 0], t[:, 1])))
            lo, hi = TIP_RADIUS_RANGE_M
            if not lo <= r_tip <= hi:
                problems.append(f"the tip radius is {r_tip:.4g} m, outside [{lo:g}, {hi:g}] m: tip_xyz must be in "
                                f"metres" + (" (this looks like mm)" if r_tip > hi else ""))
            else:
                problems += _implausible(t, np.asarray(self.tip_shapes), np.asarray(self.force_shapes), k, f, r_tip)
        if problems:
            raise ModelFileError("; ".join(problems))

    @property
    def n_tip(self) -> int:
        return int(np.asarray(self.tip_xyz).shape[0])

    def families(self) -> dict[int, np.ndarray]:
        """Harmonic index -> indices of its solutions, by increasing frequency."""
        k = np.asarray(self.harmonic_index)
        return {int(h): np.flatnonzero(k == h)[np.argsort(self.freq_hz[k == h], kind="stable")]
                for h in np.unique(k)}


def _implausible(tip_xyz, tip_shapes, force_shapes, k, f, r_tip: float) -> list:
    """What makes finite, well-shaped sector arrays implausible: tip nodes that coincide, a
    solution that does not move the tip, shapes beyond any mass-normalised SI mode."""
    problems = []
    gap = np.linalg.norm(np.diff(tip_xyz, axis=0), axis=1)
    if gap.min() < TIP_SPACING_MIN * r_tip:
        i = int(np.argmin(gap))
        problems.append(f"tip_xyz: tip nodes {i} and {i + 1} are {gap[i]:.3g} m apart, less than {TIP_SPACING_MIN:g} "
                        f"of the tip radius: the tip nodes must be distinct points along the chord")
    lo, hi = SHAPE_RANGE
    with np.errstate(over="ignore"):
        top = np.abs(tip_shapes).max(axis=(1, 2))
        top_force = float(np.abs(force_shapes).max())
    small = np.flatnonzero(top < lo)
    if small.size:
        i = int(small[0])
        size = "all zero" if top[i] == 0 else f"at most {top[i]:.3g}"
        problems.append(f"tip_shapes: {small.size} of {top.size} solutions do not move the tip nodes (solution {i}, "
                        f"harmonic index {k[i]}, {f[i]:.6g} Hz: {size}; each needs a component of at least {lo:g} "
                        "m per unit modal coordinate)")
    for name, big in (("tip_shapes", float(top.max())), ("force_shapes", top_force)):
        if big > hi:
            problems.append(f"{name}: a component of {big:.3g} m per unit modal coordinate, above {hi:g} (a modal "
                            "mass below 1e-12 kg): not mass-normalised SI shapes")
    return problems


@dataclass(frozen=True, slots=True, eq=False)
class TipGeometry:
    """What the tip nodes say about the blade tip.

    Attributes
    ----------
    chord_m : float
        Distance from the first (trailing-edge) to the last tip node, m.
    stagger_deg : float
        Angle of the chord from the tangential direction (module :mod:`modal_model` convention:
        TE -> LE is ``(tang, axial) = (cos eta, -sin eta)``), deg.
    radius_m : float
        Mean radius of the tip nodes, m.
    axial_m : tuple of float
        Axial extent (min, max) of the tip nodes, m.
    """

    chord_m: float
    stagger_deg: float
    radius_m: float
    axial_m: tuple


def tip_geometry(tip_xyz: np.ndarray) -> TipGeometry:
    """Chord, stagger and radius of a tip node line ordered from the trailing edge.

    Parameters
    ----------
    tip_xyz : ndarray, shape (n_tip, 3)
        Tip nodes of one blade, m, node 0 at the trailing edge.
    """
    p = np.asarray(tip_xyz, float)
    te, le = p[0], p[-1]
    mid = 0.5 * (te + le)
    ang = math.atan2(mid[1], mid[0])
    t_dir = np.array([-math.sin(ang), math.cos(ang), 0.0])
    d = le - te
    stagger = math.degrees(math.atan2(-d[2], float(d @ t_dir)))
    return TipGeometry(chord_m=float(np.linalg.norm(d)), stagger_deg=stagger,
                       radius_m=float(np.mean(np.hypot(p[:, 0], p[:, 1]))),
                       axial_m=(float(p[:, 2].min()), float(p[:, 2].max())))


def _real_standing(u_tip: np.ndarray, u_force: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Turn a standing-wave solution's complex shape real (the phase of its largest entry)."""
    allv = np.concatenate([u_tip.ravel(), u_force.ravel()])
    ph = np.exp(-1j * np.angle(allv[np.argmax(np.abs(allv))]))
    return u_tip * ph, u_force * ph


def _expand_entries(N: int, entries, wheel: bool, fix_phase: bool = True):
    """Full-wheel Cartesian shapes of sector solutions ``(k, family, freq, u_tip, u_force)``
    (module conventions); ``fix_phase`` turns standing-wave solutions real by their largest
    entry (False: they are real already, aligned by the caller)."""
    theta = 2.0 * np.pi * np.arange(N) / N
    R = rotation_z(theta)
    freqs, tips, forces, fam_of, nd_of = [], [], [], [], []
    for k, f, freq, ut, uf in entries:
        standing = k == 0 or 2 * k == N
        if standing and fix_phase:
            ut, uf = _real_standing(ut, uf)
        ph = np.exp(1j * k * theta)                                # (N,)
        wt = np.einsum("sij,spj->spi", R, ph[:, None, None] * ut[None])
        wf = np.einsum("sij,sj->si", R, ph[:, None] * uf[None])
        scale = 1.0 if wheel else math.sqrt((1.0 if standing else 2.0) / N)
        parts = (np.real,) if standing else (np.real, np.imag)
        for part in parts:
            freqs.append(freq); fam_of.append(f); nd_of.append(k)
            tips.append(scale * part(wt)); forces.append(scale * part(wf))
    return freqs, tips, forces, fam_of, nd_of


def expand_sector(sector: CyclicSector, *, damping_ratio=None, damping_beta_s: float | None = 9e-6,
                  n_families: int | None = None) -> tuple[ModalModel, dict]:
    """Expand a cyclic sector solution to the full-wheel modal model.

    Parameters
    ----------
    sector : CyclicSector
    damping_ratio : array_like, shape (n_modes,), optional
        Modal damping ratios of the expanded modes; default stiffness-proportional with
        ``damping_beta_s`` (``zeta = beta omega / 2``).
    n_families : int, optional
        Modes kept per harmonic index (default: the fewest any harmonic index has).

    Returns
    -------
    model : ModalModel
        Mass-normalised full-wheel modes (module conventions), labelled with family and ND,
        with the Campbell table (family x ND) of the sector solution.
    report : dict
        ``families_per_nd`` (harmonic index -> solutions read), ``n_families``, ``tip``
        (:class:`TipGeometry` as a dict), ``dropped`` (solutions left out).

    Raises
    ------
    ModelFileError
        A harmonic index missing, no mode left.
    """
    N = int(sector.n_sectors)
    fams = sector.families()
    missing = [k for k in range(N // 2 + 1) if k not in fams]
    if missing:
        shown = ", ".join(map(str, missing[:8])) + (" ..." if len(missing) > 8 else "")
        raise ModelFileError(f"harmonic indices missing from the sector results: {shown} "
                             f"(a {N}-sector wheel needs 0..{N // 2}; select them all in the FE solution)")
    n_fam = min(len(v) for v in fams.values()) if n_families is None else int(n_families)
    if n_fam < 1:
        raise ModelFileError(f"n_families must be >= 1 (families kept per nodal diameter), got {n_fam}")
    if any(len(v) < n_fam for v in fams.values()):
        raise ModelFileError(f"{n_fam} families requested but some harmonic index has only "
                             f"{min(len(v) for v in fams.values())} solutions")
    theta = 2.0 * np.pi * np.arange(N) / N
    R = rotation_z(theta)                                                     # (N, 3, 3)
    tip_xyz = np.einsum("sij,pj->spi", R, sector.tip_xyz)             # (N, n_tip, 3)
    force_xyz = np.einsum("sij,j->si", R, sector.force_xyz)           # (N, 3)
    entries = [(k, f, float(sector.freq_hz[i]), np.asarray(sector.tip_shapes[i], complex),
                np.asarray(sector.force_shapes[i], complex))
               for k, idx in fams.items() for f, i in enumerate(idx[:n_fam])]
    freqs, tips, forces, fam_of, nd_of = _expand_entries(N, entries, sector.normalisation == "wheel")
    freqs = np.array(freqs)
    fam_of, nd_of = np.array(fam_of, np.int64), np.array(nd_of, np.int64)
    order = np.lexsort((nd_of, freqs, fam_of))
    geo = tip_geometry(sector.tip_xyz)
    stagger = geo.stagger_deg if sector.stagger_deg is None else float(sector.stagger_deg)
    campbell = np.array([[sector.freq_hz[fams[k][f]] for k in range(N // 2 + 1)] for f in range(n_fam)])
    freq_sorted = freqs[order]
    if damping_ratio is None:
        damping_ratio = 0.5 * float(damping_beta_s) * 2.0 * np.pi * freq_sorted
    prov = dict(sector.provenance)
    prov.setdefault("builder", "cyclic sector import")
    prov["method"] = (f"cyclic symmetry ({N} sectors, harmonic indices 0..{N // 2}, {n_fam} families), "
                      f"expanded to the full wheel ({sector.normalisation} normalisation)")
    model = model_from_cartesian(
        freq_sorted, tip_xyz, np.array(tips)[order], force_xyz, np.array(forces)[order],
        nominal_node=int(sector.nominal_node), stagger_deg=stagger, damping_ratio=damping_ratio,
        damping_beta_s=damping_beta_s, provenance=prov, family=fam_of[order], nodal_diameter=nd_of[order])
    model = ModalModel(**{**{f: getattr(model, f) for f in ("freq_hz", "damping_ratio", "tip_ref", "tip_shapes",
                                                            "force_ref", "force_shapes", "meta", "family",
                                                            "nodal_diameter", "extra")},
                          "campbell_freq_hz": campbell})
    report = {"n_sectors": N, "families_per_nd": {k: int(len(v)) for k, v in fams.items()},
              "n_families": n_fam, "n_modes": model.n_modes, "campbell_freq_hz": campbell,
              "tip": {"chord_m": geo.chord_m, "stagger_deg": geo.stagger_deg, "radius_m": geo.radius_m,
                      "axial_m": geo.axial_m, "n_tip": sector.n_tip, "nominal_node": int(sector.nominal_node)},
              "dropped": int(sum(max(0, len(v) - n_fam) for v in fams.values()))}
    return model, report


def _check_speed_sectors(sectors: list, sp: np.ndarray) -> None:
    """Every sector solution is of the speed-0 solution's wheel, with its tip and excitation nodes."""
    s0 = sectors[0]
    N = int(s0.n_sectors)
    size = float(np.abs(s0.tip_xyz).max())
    for i, sec in enumerate(sectors[1:], 1):
        at = f"the solution at {sp[i] * 30 / np.pi:g} rpm"
        if int(sec.n_sectors) != N or sec.normalisation != s0.normalisation:
            raise ModelFileError(f"{at} is for another wheel ({sec.n_sectors} sectors, {sec.normalisation} "
                                 f"normalisation; speed 0: {N}, {s0.normalisation})")
        if (sec.tip_xyz.shape != s0.tip_xyz.shape
                or np.abs(sec.tip_xyz - s0.tip_xyz).max() > 1e-6 * size
                or np.abs(np.asarray(sec.force_xyz) - s0.force_xyz).max() > 1e-6 * size):
            raise ModelFileError(f"{at} has other tip or excitation nodes than the speed-0 solution")


def _track_families(sectors: list, sp: np.ndarray, n_fam: int):
    """Follow each kept (harmonic index, family) of speed 0 through the other speeds.

    Returns, per harmonic index ``k``, the frequencies ``rows_f[k][s][f]``, Hz, and the
    phase-aligned (tip, excitation) sector shapes ``rows_u[k][s][f]`` of family ``f`` at speed
    ``s``, and the poorest MAC between consecutive speeds.
    """
    from scipy.optimize import linear_sum_assignment

    s0 = sectors[0]
    N = int(s0.n_sectors)
    S = len(sectors)
    fams0 = s0.families()

    def vec(sec, i, k):
        ut, uf = np.asarray(sec.tip_shapes[i], complex), np.asarray(sec.force_shapes[i], complex)
        if k == 0 or 2 * k == N:
            ut, uf = _real_standing(ut, uf)
        return ut, uf

    prev = {k: [vec(s0, i, k) for i in idx[:n_fam]] for k, idx in fams0.items()}
    rows_f = {k: [[float(s0.freq_hz[i]) for i in idx[:n_fam]]] for k, idx in fams0.items()}
    rows_u = {k: [prev[k]] for k in fams0}
    min_mac = 1.0
    for s in range(1, S):
        sec = sectors[s]
        fams = sec.families()
        for k in fams0:
            cand = fams.get(k, np.array([], int))
            if cand.size < n_fam:
                raise ModelFileError(f"the solution at {sp[s] * 30 / np.pi:g} rpm has {cand.size} solutions of "
                                     f"harmonic index {k}, fewer than the {n_fam} families kept at speed 0")
            P = np.array([np.concatenate([ut.ravel(), uf]) for ut, uf in prev[k]])          # (n_fam, n)
            C_u = [vec(sec, i, k) for i in cand]
            C = np.array([np.concatenate([ut.ravel(), uf]) for ut, uf in C_u])              # (n_cand, n)
            overlap = P.conj() @ C.T
            mac = np.abs(overlap) ** 2 / np.outer(np.sum(np.abs(P) ** 2, 1), np.sum(np.abs(C) ** 2, 1))
            rows, cols = linear_sum_assignment(-mac)
            worst = float(mac[rows, cols].min())
            min_mac = min(min_mac, worst)
            if worst < 0.5:
                f_bad = int(rows[np.argmin(mac[rows, cols])])
                raise ModelFileError(f"family {f_bad + 1} of harmonic index {k} cannot be followed from "
                                     f"{sp[s - 1] * 30 / np.pi:g} to {sp[s] * 30 / np.pi:g} rpm (MAC {worst:.2f}): "
                                     "add speeds in between")
            ph = overlap[rows, cols]
            ph = np.conj(ph) / np.abs(ph)
            if k == 0 or 2 * k == N:
                ph = np.sign(ph.real)
            prev[k] = [(C_u[j][0] * p, C_u[j][1] * p) for j, p in zip(cols, ph)]
            rows_f[k].append([float(sec.freq_hz[cand[j]]) for j in cols])
            rows_u[k].append(prev[k])
    return rows_f, rows_u, min_mac


def expand_sectors_at_speeds(sectors, speed_rad_s, *, damping_ratio=None, damping_beta_s: float | None = 9e-6,
                             n_families: int | None = None) -> tuple[ModalModel, dict]:
    """A speed-dependent model from cyclic sector solutions at several speeds.

    Speed 0 is expanded by :func:`expand_sector` (the model's zero-speed arrays); at every
    further speed each kept (harmonic index, family) is *tracked*: matched to the previous
    speed's solution of the same harmonic index by the MAC of the complex sector shapes at the
    tip and excitation nodes (optimal assignment over all the solutions of that harmonic
    index), and phase-aligned to it (``u_prev^H u`` real and positive; a standing wave's sign),
    so that mode ``i`` is the same mode at every speed, in the zero-speed model's order.

    Parameters
    ----------
    sectors : sequence of CyclicSector
        One per speed, same wheel and nodes (tip and excitation node positions equal).
    speed_rad_s : array_like, shape (S,)
        Their speeds, rad/s: ``2 <= S <= 64``, strictly ascending from 0.

    Returns
    -------
    model : ModalModel
        With ``speed_rad_s``, ``freq_hz_at_speed``, ``tip_shapes_at_speed``,
        ``force_shapes_at_speed`` and ``campbell_freq_hz_at_speed``.
    report : dict
        :func:`expand_sector`'s report for speed 0, plus ``speed_rad_s`` and ``min_mac`` (the
        poorest match between consecutive speeds).

    Raises
    ------
    ModelFileError
        Speeds not ascending from 0 or not one per sector, sectors of different wheels or
        nodes, a harmonic index with fewer solutions than the families kept at speed 0, or a
        mode that cannot be followed (MAC < 0.5 between two speeds: add speeds in between).
    """

    sectors = list(sectors)
    sp = np.asarray(speed_rad_s, float)
    S = len(sectors)
    if sp.shape != (S,):
        raise ModelFileError(f"{S} sector solutions but {sp.size} speeds: give one speed per solution")
    if not 2 <= S <= MAX_SPEEDS or not np.all(np.isfinite(sp)) or sp[0] != 0.0 or np.any(np.diff(sp) <= 0):
        raise ModelFileError(f"speeds must be 2..{MAX_SPEEDS} values strictly ascending from 0, got "
                             f"{', '.join(f'{v * 30 / np.pi:g}' for v in sp)} rpm")
    _check_speed_sectors(sectors, sp)
    s0 = sectors[0]
    N = int(s0.n_sectors)
    model, report = expand_sector(s0, damping_ratio=damping_ratio, damping_beta_s=damping_beta_s,
                                  n_families=n_families)
    n_fam = report["n_families"]
    fams0 = s0.families()

    rows_f, rows_u, min_mac = _track_families(sectors, sp, n_fam)
    # expand every speed in the zero-speed order
    theta = 2.0 * np.pi * np.arange(N) / N
    R = rotation_z(theta)
    tip_xyz = np.einsum("sij,pj->spi", R, s0.tip_xyz)
    force_xyz = np.einsum("sij,j->si", R, s0.force_xyz)
    wheel = s0.normalisation == "wheel"
    ks = list(fams0)
    freq_at, tip_at, force_at = [], [], []
    order = None
    for s in range(S):
        entries = [(k, f, rows_f[k][s][f], *rows_u[k][s][f]) for k in ks for f in range(n_fam)]
        freqs, tips, forces, fam_of, nd_of = _expand_entries(N, entries, wheel, fix_phase=False)
        freqs = np.array(freqs)
        if order is None:
            order = np.lexsort((np.array(nd_of), freqs, np.array(fam_of)))
        _, tp = to_polar(tip_xyz, np.array(tips)[order])
        _, fp = to_polar(force_xyz, np.array(forces)[order])
        freq_at.append(freqs[order]); tip_at.append(tp); force_at.append(fp)
    campbell = np.array([[[rows_f[k][s][f] for k in range(N // 2 + 1)] for f in range(n_fam)] for s in range(S)])
    arrays = {"speed_rad_s": sp, "freq_hz_at_speed": np.array(freq_at), "tip_shapes_at_speed": np.array(tip_at),
              "force_shapes_at_speed": np.array(force_at), "campbell_freq_hz_at_speed": campbell}
    for key, zero in (("freq_hz_at_speed", model.freq_hz), ("tip_shapes_at_speed", model.tip_shapes),
                      ("force_shapes_at_speed", model.force_shapes),
                      ("campbell_freq_hz_at_speed", model.campbell_freq_hz)):
        arrays[key][0] = zero  # the same numbers, computed by expand_sector: bit-identical row 0
    meta = dict(model.meta)
    meta["provenance"] = {**meta["provenance"], "speeds_rpm": [float(v * 30 / np.pi) for v in sp],
                          "tracking": "MAC of the complex sector shapes at the tip and excitation nodes, "
                                      "optimal assignment per harmonic index; phase-aligned",
                          "tracking_min_mac": min_mac}
    model = ModalModel(**{f: getattr(model, f) for f in ("freq_hz", "damping_ratio", "tip_ref", "tip_shapes",
                                                         "force_ref", "force_shapes", "family", "nodal_diameter",
                                                         "campbell_freq_hz")},
                       meta=meta, extra={**model.extra, **arrays})
    report.update(speed_rad_s=sp, min_mac=min_mac, campbell_freq_hz_at_speed=campbell)
    return model, report


# ---- the neutral file ---------------------------------------------------------------------

_ARRAYS = ("harmonic_index", "freq_hz", "tip_xyz", "force_xyz")


def save_sector(sector: CyclicSector, path) -> None:
    """Write ``sector`` in the neutral format (uncompressed ``.npz``, complex shapes)."""
    meta = {"schema": SECTOR_SCHEMA, "schema_version": SECTOR_SCHEMA_VERSION, "n_sectors": int(sector.n_sectors),
            "nominal_node": int(sector.nominal_node), "normalisation": sector.normalisation,
            "units": "SI: Hz, m; shapes in m per unit modal coordinate",
            "provenance": sector.provenance}
    if sector.stagger_deg is not None:
        meta["stagger_deg"] = float(sector.stagger_deg)
    with open(path, "wb") as fh:
        np.savez(fh, meta=np.array(json.dumps(meta, sort_keys=True)),
                 harmonic_index=np.asarray(sector.harmonic_index, np.int64),
                 freq_hz=np.asarray(sector.freq_hz, float), tip_xyz=np.asarray(sector.tip_xyz, float),
                 force_xyz=np.asarray(sector.force_xyz, float),
                 tip_shapes=np.asarray(sector.tip_shapes, complex),
                 force_shapes=np.asarray(sector.force_shapes, complex))


def _shapes(z: dict, name: str, where: str) -> np.ndarray:
    if name in z:
        return np.asarray(z[name])
    if f"{name}_cos" in z and f"{name}_sin" in z:
        c, s = np.asarray(z[f"{name}_cos"]), np.asarray(z[f"{name}_sin"])
        if c.shape != s.shape or c.dtype.kind != "f" or s.dtype.kind != "f":
            raise ModelFileError(f"{where}: {name}_cos and {name}_sin must be real arrays of one shape")
        return c + 1j * s
    raise ModelFileError(f"{where}: missing {name} (complex) or {name}_cos + {name}_sin")


def load_sector(path) -> CyclicSector:
    """Read a neutral-format sector file (:func:`~bttsim_stream.model.npzfile.read_npz`:
    ``allow_pickle=False``, size checks); any problem is a one-line :class:`ModelFileError`."""
    where = str(path)
    z = read_npz(path, "sector file")
    missing = [k for k in ("meta",) + _ARRAYS if k not in z]
    if missing:
        raise ModelFileError(f"{where}: missing {', '.join(missing)} (schema {SECTOR_SCHEMA})")
    try:
        meta = json.loads(str(z["meta"]))
    except json.JSONDecodeError as exc:
        raise ModelFileError(f"{where}: meta is not JSON ({exc})") from None
    if not isinstance(meta, dict) or meta.get("schema") != SECTOR_SCHEMA:
        raise ModelFileError(f"{where}: meta.schema must be {SECTOR_SCHEMA!r}")
    if meta.get("schema_version") != SECTOR_SCHEMA_VERSION:
        raise ModelFileError(f"{where}: schema_version {meta.get('schema_version')!r} is not supported "
                             f"(this reader knows {SECTOR_SCHEMA_VERSION})")
    n_sectors = meta.get("n_sectors")
    if isinstance(n_sectors, bool) or not isinstance(n_sectors, int) or not 2 <= n_sectors <= MAX_BLADES:
        raise ModelFileError(f"{where}: meta.n_sectors must be an integer in [2, {MAX_BLADES}] (the blades of a "
                             f"run), got {n_sectors!r}")
    nominal, stagger = meta.get("nominal_node", z["tip_xyz"].shape[0] // 2), meta.get("stagger_deg")
    if isinstance(nominal, bool) or not isinstance(nominal, int):
        raise ModelFileError(f"{where}: meta.nominal_node must be a tip node index, got {nominal!r}")
    if stagger is not None and (isinstance(stagger, bool) or not isinstance(stagger, (int, float))
                                or not math.isfinite(stagger)):
        raise ModelFileError(f"{where}: meta.stagger_deg must be a number of degrees, got {stagger!r}")
    if not isinstance(meta.get("provenance", {}), dict):
        raise ModelFileError(f"{where}: meta.provenance must be a JSON object")
    arrays = {k: z[k] for k in _ARRAYS}
    tip, force = _shapes(z, "tip_shapes", where), _shapes(z, "force_shapes", where)
    try:
        return CyclicSector(n_sectors=n_sectors, harmonic_index=arrays["harmonic_index"],
                            freq_hz=arrays["freq_hz"], tip_xyz=arrays["tip_xyz"], tip_shapes=tip,
                            force_xyz=arrays["force_xyz"], force_shapes=force,
                            nominal_node=nominal, stagger_deg=stagger,
                            normalisation=meta.get("normalisation", "sector"), provenance=meta.get("provenance", {}))
    except ModelFileError as exc:
        raise ModelFileError(f"{where}: {exc}") from None


def builtin_sector(scn=None, speed_rad_s: float = 0.0) -> CyclicSector:
    """The built-in parametric model's cyclic solution as a neutral sector (leading-edge
    excitation node), e.g. to try the importer or as a template for one's own export.

    With ``speed_rad_s > 0``, the solution at that speed with the centrifugal effects of
    :mod:`~bttsim_stream.model.centrifugal` (as an FE package's prestressed modal step gives
    it: eigenvectors as solved, not tracked).

    The complex sector vectors of :func:`~bttsim_stream.model.bladed_disk.solve_cyclic`
    (``v^H M_k v = 1``: ``"sector"`` normalisation) are mapped to the tip and force nodes and
    written in the reference sector's Cartesian frame.
    """
    from threadpoolctl import threadpool_limits

    from ..scenario import Scenario
    from .bladed_disk import assemble_sector, solve_cyclic
    from .modal_model import design_from_scenario

    scn = Scenario() if scn is None else scn
    d = design_from_scenario(scn)
    with threadpool_limits(limits=1):
        sec = assemble_sector(d)
        sol = solve_cyclic(d, sec)
        if speed_rad_s:
            import scipy.linalg as sla

            from .centrifugal import centrifugal_sector, cyclic_speed_matrices
            cent = centrifugal_sector(sec, d.n_blades)
            freqs, vecs = [], []
            for nd in range(d.n_blades // 2 + 1):
                K, G, M = cyclic_speed_matrices(sec, cent, d.n_blades, nd)
                w2, v = sla.eigh(K + float(speed_rad_s) ** 2 * G, M, subset_by_index=[0, d.n_families - 1],
                                 driver="gvx")
                freqs.append(np.sqrt(np.maximum(w2, 0.0)) / (2.0 * np.pi))
                vecs.append(v)
            sol = type(sol)(freq_hz=np.array(freqs), vectors=vecs)
    N = d.n_blades

    def cart(ref, maps, v):
        """(n_pts, 3) polar refs, (n_pts, 3, m) maps, (m, n) vectors -> xyz (n_pts, 3), u (n, n_pts, 3)."""
        r, a, zz = ref.T
        xyz = np.stack([r * np.cos(a), r * np.sin(a), zz], -1)
        pol = np.einsum("pcm,mn->npc", maps, v)
        c, s = np.cos(a), np.sin(a)
        u = np.stack([pol[..., 0] * c - pol[..., 1] * s, pol[..., 0] * s + pol[..., 1] * c, pol[..., 2]], -1)
        return xyz, u

    ks, fs, tips, forces = [], [], [], []
    for k, (f_k, v_k) in enumerate(zip(sol.freq_hz, sol.vectors)):
        tip_xyz, ut = cart(sec.tip_ref, sec.tip_map, v_k)
        force_xyz, uf = cart(sec.force_ref[:1], sec.force_map[:1], v_k)
        ks += [k] * len(f_k); fs += list(f_k); tips.append(ut); forces.append(uf[:, 0])
    return CyclicSector(n_sectors=N, harmonic_index=np.array(ks, np.int64), freq_hz=np.array(fs),
                        tip_xyz=tip_xyz, tip_shapes=np.concatenate(tips), force_xyz=force_xyz[0],
                        force_shapes=np.concatenate(forces), nominal_node=d.nominal_node,
                        stagger_deg=float(np.rad2deg(d.stagger_rad)), normalisation="sector",
                        provenance={"builder": "bttsim_stream built-in parametric bladed disk (cyclic sector)",
                                    "model_schema_version": MODEL_SCHEMA_VERSION,
                                    **({"speed_rad_s": float(speed_rad_s)} if speed_rad_s else {})})

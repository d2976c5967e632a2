"""Parametric finite element model of a bladed disk, solved with cyclic symmetry.

The wheel is ``n_blades`` identical sectors. Each sector holds

* a **blade**: a pretwisted, tapered 3D Euler-Bernoulli beam (bending in two planes,
  torsion, axial) from the rim to the tip radius, with an aerofoil-like section whose chord
  turns linearly from the root stagger to the tip stagger ``eta_tip``; a rigid tip chord
  carries the chordwise tip nodes (from the trailing edge) and a rigid arm carries the
  excitation node at the leading (or trailing) edge;
* a **disk sector**: a beam grid -- a radial web strip clamped at the bore, and
  circumferential ring beams at every grid radius joining it to the neighbouring sectors
  (the outermost ring is the rim that the blade roots are fixed to).

Frames and conventions
----------------------
Every sector is assembled in its own *sector frame*: X radial through the blade axis,
Y tangential (direction of rotation), Z axial (trailing edge at larger Z). The sector frame
of blade ``b`` (0-based) is the rotor frame turned by ``2*pi*b/n_blades`` about Z, so all
sectors share the same matrices and a full-wheel DOF vector is the concatenation of sector
vectors, each in its own frame. Tip chord geometry: the unit vector from trailing to leading
edge is ``(Y, Z) = (cos eta, -sin eta)``, so the leading edge is ahead in the direction of
rotation and upstream; with this geometry the BTT displacement is
``d = d_tang + d_z / tan(eta_tip)`` (paper Eq. 2-4).

Cyclic symmetry (Thomas, Int. J. Numer. Meth. Eng. 14, 1979): for harmonic ``n`` the
neighbouring sector's DOF are ``exp(i*2*pi*n/N)`` times the reference sector's, which turns
the ring couplings into a Hermitian per-ND stiffness; each complex eigenvector of ND
``1..floor((N-1)/2)`` expands into a pair of real full-wheel modes, ND 0 into one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .beam import BeamSection, beam_matrices, rigid_offset_matrix, rotation_matrix

__all__ = [
    "BladedDiskDesign",
    "SectorModel",
    "CyclicSolution",
    "WheelModes",
    "assemble_sector",
    "blade_alone_frequencies",
    "solve_cyclic",
    "expand_cyclic",
    "solve_full_wheel",
    "assemble_full_wheel",
    "asymmetry_pattern",
    "nodal_diameter_content",
]

_DOF = 6


@dataclass(frozen=True, slots=True)
class BladedDiskDesign:
    """Every parameter of the parametric bladed disk (SI units, angles in rad).

    Defaults are the calibrated model of the paper's rotor (29 blades; blade-alone
    347.47 / 1148.9 / 1717 Hz; first family ND 1 343.9 Hz rising to ND 14 347.5 Hz). The
    calibrated values come from :func:`bttsim_stream.model.calibrate.calibrate_design`.

    Attributes
    ----------
    n_blades : int
    tip_radius_m : float
        Radius of the tip chord (and of the tip nodes' foot on the blade axis), m.
    stagger_rad : float
        Tip stagger ``eta_tip``: angle of the tip chord from the tangential direction.
    tip_chord_m : float
        Tip chord length; the leading edge is at z = 0, the trailing edge at
        ``tip_chord_m * sin(stagger)``.
    n_tip_nodes : int
        Tip nodes along the chord from the trailing edge.
    tip_node_spacing_m : float
        Spacing of the tip nodes along the chord, m.
    nominal_node : int
        0-based index (from the trailing edge) of the nominal sensing node P_nom.
    rim_radius_m, bore_radius_m : float
        Blade root (rim) radius and disk bore radius, m.
    root_chord_m : float
        Chord at the blade root, m (linear taper to ``tip_chord_m``).
    pretwist_rad : float
        Root stagger minus tip stagger.
    root_thickness_m : float
        Maximum aerofoil thickness at the root, m.
    thickness_taper : float
        Tip thickness / root thickness.
    area_factor, flap_factor, edge_factor, torsion_factor : float
        Section shape factors: ``A = k_A c t``, ``I_flap = k_f c t^3``,
        ``I_edge = k_e c^3 t``, ``J = k_J c t^3`` (c chord, t thickness).
    blade_E_pa, blade_nu, blade_rho : float
        Blade material (the paper: alloy steel, 200 GPa, 0.28, 7640 kg/m^3).
    disk_E_pa, disk_nu, disk_rho : float
        Disk material (the paper: A286, 190 GPa, 0.31, 7920 kg/m^3).
    web_thickness_m : float
        Axial thickness of the disk web, m.
    rim_width_m, rim_length_m : float
        Radial and axial size of the rim ring section, m.
    n_blade_elements, n_disk_elements : int
        Mesh: beam elements along the blade and along the web radius.
    force_span_fraction : float
        Span position of the excitation node (0 root, 1 tip), on the leading edge.
    n_families : int
        Mode families kept per nodal diameter.
    asymmetry : tuple of float
        Relative amplitudes of disk web stiffness harmonics 1, 2 (0 = tuned disk).
    """

    n_blades: int = 29
    tip_radius_m: float = 0.19
    stagger_rad: float = float(np.deg2rad(41.5))
    tip_chord_m: float = 0.0202523
    n_tip_nodes: int = 9
    tip_node_spacing_m: float = 0.0004375
    nominal_node: int = 4
    rim_radius_m: float = 0.115
    bore_radius_m: float = 0.035
    root_chord_m: float = 0.024
    pretwist_rad: float = float(np.deg2rad(15.0))
    root_thickness_m: float = 0.0025860012342059113
    thickness_taper: float = 0.6470455980410424
    area_factor: float = 0.70
    flap_factor: float = 0.040
    edge_factor: float = 0.045
    torsion_factor: float = 0.03659676388094417
    blade_E_pa: float = 200e9
    blade_nu: float = 0.28
    blade_rho: float = 7640.0
    disk_E_pa: float = 190e9
    disk_nu: float = 0.31
    disk_rho: float = 7920.0
    web_thickness_m: float = 0.012327802161169403
    rim_width_m: float = 0.012
    rim_length_m: float = 0.025
    n_blade_elements: int = 12
    n_disk_elements: int = 4
    force_span_fraction: float = 0.3787778121032074
    n_families: int = 5
    asymmetry: tuple[float, float] = (0.0, 0.0)

    @property
    def span_m(self) -> float:
        return self.tip_radius_m - self.rim_radius_m

    @property
    def z_mid_m(self) -> float:
        """Axial position of the blade axis (tip mid-chord) and of the disk mid-plane."""
        return 0.5 * self.tip_chord_m * np.sin(self.stagger_rad)


@dataclass(frozen=True, slots=True, eq=False)
class BeamElement:
    """One beam element of a sector: end points and section orientation in the sector frame,
    its section, and its 12 sector DOF indices (-1: clamped)."""

    p1: np.ndarray
    p2: np.ndarray
    y_hint: np.ndarray
    section: BeamSection
    dofs: np.ndarray


@dataclass(frozen=True, slots=True, eq=False)
class SectorModel:
    """Matrices of one sector in its sector frame (see module notes).

    Attributes
    ----------
    K, M : ndarray, shape (m, m)
        Sector stiffness and mass without the ring couplings, N/m and kg.
    ring_dofs : ndarray, shape (n_rings, 6)
        Sector DOF indices of each ring node.
    ring_K : ndarray, shape (n_rings, 12, 12)
        Ring element stiffness between a sector's ring node (first 6) and the same node of
        the next sector (last 6, in the next sector's frame).
    ring_M : ndarray, shape (n_rings, 12, 12)
        The same for mass.
    tip_map : ndarray, shape (n_tip, 3, m)
        Sector DOF -> tip node displacement in the node's (radial, tangential, axial) frame.
    tip_ref : ndarray, shape (n_tip, 3)
        Undeformed tip nodes as (radius, angle in the sector frame, z).
    force_map, force_ref : ndarray, shapes (n_force, 3, m), (n_force, 3)
        The same for the excitation nodes (leading edge, trailing edge).
    blade_dofs : ndarray, shape (n_blade_dofs,)
        Sector DOF indices that belong to the blade (for blade participation).
    elements : tuple of BeamElement
        The sector's own beam elements (disk web strips, then blade), for the centrifugal
        matrices.
    ring_elements : tuple of BeamElement
        The ring beams, in the order of ``ring_dofs`` (``p2`` in the reference sector frame).
    node_xyz : ndarray, shape (n_nodes, 3)
        Undeformed position of every free node (node ``i`` owns DOF ``6 i .. 6 i + 5``).
    """

    K: np.ndarray
    M: np.ndarray
    ring_dofs: np.ndarray
    ring_K: np.ndarray
    ring_M: np.ndarray
    tip_map: np.ndarray
    tip_ref: np.ndarray
    force_map: np.ndarray
    force_ref: np.ndarray
    blade_dofs: np.ndarray
    elements: tuple = ()
    ring_elements: tuple = ()
    node_xyz: np.ndarray | None = None

    @property
    def n_dof(self) -> int:
        return self.K.shape[0]


def rotation_z(theta) -> np.ndarray:
    """Rotation matrices about +z by ``theta`` (rad), shape ``(..., 3, 3)``."""
    c, s = np.cos(theta), np.sin(theta)
    z, o = np.zeros_like(c), np.ones_like(c)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def _rect_torsion(a: float, b: float) -> float:
    """Saint-Venant constant of an a x b rectangle (Roark, Table 10.7)."""
    a, b = max(a, b), min(a, b)
    return a * b**3 * (1.0 / 3.0 - 0.21 * (b / a) * (1.0 - b**4 / (12.0 * a**4)))


def _chord_dir(stagger: float) -> np.ndarray:
    """Unit vector from trailing to leading edge in the sector frame."""
    return np.array([0.0, np.cos(stagger), -np.sin(stagger)])


def _blade_section(d: BladedDiskDesign, r: float, k_scale: float, m_scale: float) -> tuple[BeamSection, float]:
    """Section at radius ``r`` and its stagger angle."""
    xi = (r - d.rim_radius_m) / d.span_m
    chord = d.root_chord_m + (d.tip_chord_m - d.root_chord_m) * xi
    thick = d.root_thickness_m * (1.0 + (d.thickness_taper - 1.0) * xi)
    stagger = d.stagger_rad + d.pretwist_rad * (1.0 - xi)
    E = d.blade_E_pa * k_scale
    G = E / (2.0 * (1.0 + d.blade_nu))
    I_flap = d.flap_factor * chord * thick**3
    I_edge = d.edge_factor * chord**3 * thick
    sec = BeamSection(E=E, G=G, rho=d.blade_rho * m_scale, A=d.area_factor * chord * thick,
                      I_y=I_flap, I_z=I_edge, J=d.torsion_factor * chord * thick**3,
                      I_p=I_flap + I_edge)
    return sec, stagger


def scatter_add(K: np.ndarray, k: np.ndarray, dofs: np.ndarray) -> None:
    keep = dofs >= 0
    idx = dofs[keep]
    K[np.ix_(idx, idx)] += k[np.ix_(keep, keep)]


def assemble_sector(d: BladedDiskDesign, blade_k: float = 1.0, blade_m: float = 1.0,
                    disk_k: float = 1.0) -> SectorModel:
    """Assemble one sector (blade + disk web + rim and web ring couplings).

    Parameters
    ----------
    d : BladedDiskDesign
    blade_k, blade_m : float
        Blade stiffness and mass factors (mistuning).
    disk_k : float
        Disk stiffness factor of this sector (asymmetry).
    """
    z0 = d.z_mid_m
    nd, nb = d.n_disk_elements, d.n_blade_elements
    r_disk = np.linspace(d.bore_radius_m, d.rim_radius_m, nd + 1)
    r_blade = np.linspace(d.rim_radius_m, d.tip_radius_m, nb + 1)
    # node numbering: disk nodes 1..nd (bore node 0 clamped -> -1), blade nodes follow
    n_nodes = nd + nb
    m = _DOF * n_nodes
    K = np.zeros((m, m))
    M = np.zeros((m, m))

    def dofs(node: int) -> np.ndarray:
        return np.arange(_DOF) + _DOF * (node - 1) if node >= 1 else -np.ones(_DOF, int)

    elements, ring_elements = [], []

    # disk web strips (radial beams), section = sector arc x web thickness
    E_d = d.disk_E_pa * disk_k
    G_d = E_d / (2.0 * (1.0 + d.disk_nu))
    h = d.web_thickness_m
    for e in range(nd):
        r_mid = 0.5 * (r_disk[e] + r_disk[e + 1])
        w = 2.0 * np.pi * r_mid / d.n_blades
        sec = BeamSection(E=E_d, G=G_d, rho=d.disk_rho, A=w * h, I_y=w * h**3 / 12.0,
                          I_z=h * w**3 / 12.0, J=_rect_torsion(w, h), I_p=(w * h**3 + h * w**3) / 12.0)
        p1, p2, yh = np.array([r_disk[e], 0, z0]), np.array([r_disk[e + 1], 0, z0]), np.array([0.0, 1.0, 0.0])
        k, mm = beam_matrices(p1, p2, yh, sec)
        idx = np.concatenate([dofs(e), dofs(e + 1)])
        elements.append(BeamElement(p1, p2, yh, sec, idx))
        scatter_add(K, k, idx)
        scatter_add(M, mm, idx)

    # blade: pretwisted, tapered beam; root node = rim node (index nd)
    blade_nodes = [nd] + [nd + i for i in range(1, nb + 1)]
    for e in range(nb):
        r_mid = 0.5 * (r_blade[e] + r_blade[e + 1])
        sec, stagger = _blade_section(d, r_mid, blade_k, blade_m)
        p1, p2, yh = np.array([r_blade[e], 0, z0]), np.array([r_blade[e + 1], 0, z0]), _chord_dir(stagger)
        k, mm = beam_matrices(p1, p2, yh, sec)
        idx = np.concatenate([dofs(blade_nodes[e]), dofs(blade_nodes[e + 1])])
        elements.append(BeamElement(p1, p2, yh, sec, idx))
        scatter_add(K, k, idx)
        scatter_add(M, mm, idx)
    blade_dofs = np.concatenate([dofs(n) for n in blade_nodes[1:]])

    # ring beams between this sector's grid nodes and the next sector's (rotated frame)
    alpha = 2.0 * np.pi / d.n_blades
    Q = np.eye(12)
    Rn = rotation_z(alpha)
    Q[6:9, 6:9] = Rn
    Q[9:12, 9:12] = Rn
    ring_dofs, ring_K, ring_M = [], [], []
    for j in range(1, nd + 1):
        r = r_disk[j]
        p1 = np.array([r, 0.0, z0])
        p2 = Rn @ p1
        if j == nd:  # rim ring
            b, t, rho = d.rim_width_m, d.rim_length_m, d.disk_rho
        else:  # web ring strip: radial width = grid spacing, massless (web mass is in the strips)
            b, t, rho = r_disk[1] - r_disk[0], h, 0.0
        sec = BeamSection(E=E_d, G=G_d, rho=rho, A=b * t, I_y=b * t**3 / 12.0, I_z=t * b**3 / 12.0,
                          J=_rect_torsion(b, t), I_p=(b * t**3 + t * b**3) / 12.0)
        k, mm = beam_matrices(p1, p2, np.array([1.0, 0.0, 0.0]), sec)
        ring_elements.append(BeamElement(p1, p2, np.array([1.0, 0.0, 0.0]), sec, np.concatenate([dofs(j), dofs(j)])))
        ring_dofs.append(dofs(j))
        ring_K.append(Q.T @ k @ Q)
        ring_M.append(Q.T @ mm @ Q)

    # rigid tip chord on the tip beam node, rigid arm to the excitation nodes
    tip_node_dofs = dofs(blade_nodes[-1])
    foot = np.array([d.tip_radius_m, 0.0, z0])
    chord = _chord_dir(d.stagger_rad)
    te = foot - 0.5 * d.tip_chord_m * chord
    s = d.tip_node_spacing_m * np.arange(d.n_tip_nodes)
    tip_xyz = te[None, :] + s[:, None] * chord[None, :]
    tip_map, tip_ref = _point_maps(tip_xyz, foot, tip_node_dofs, m)

    # excitation nodes: leading and trailing edge of the section at the force span station,
    # carried by the beam's own interpolation inside the element that holds the station
    r_f = d.rim_radius_m + d.force_span_fraction * d.span_m
    e_f = int(np.clip(np.searchsorted(r_blade, r_f, side="right") - 1, 0, nb - 1))
    xi_e = (r_f - r_blade[e_f]) / (r_blade[e_f + 1] - r_blade[e_f])
    _, stg = _blade_section(d, r_f, 1.0, 1.0)
    xi = (r_f - d.rim_radius_m) / d.span_m
    c_f = d.root_chord_m + (d.tip_chord_m - d.root_chord_m) * xi
    foot_f = np.array([r_f, 0.0, z0])
    cd = _chord_dir(stg)
    force_xyz = np.vstack([foot_f + 0.5 * c_f * cd, foot_f - 0.5 * c_f * cd])
    _, stg_e = _blade_section(d, 0.5 * (r_blade[e_f] + r_blade[e_f + 1]), 1.0, 1.0)
    axis_map = _beam_point_map(r_blade[e_f + 1] - r_blade[e_f], xi_e, _chord_dir(stg_e))
    e_dofs = np.concatenate([dofs(blade_nodes[e_f]), dofs(blade_nodes[e_f + 1])])
    force_map, force_ref = _point_maps(force_xyz, foot_f, e_dofs, m, axis_map)

    return SectorModel(K=K, M=M, ring_dofs=np.array(ring_dofs), ring_K=np.array(ring_K),
                       ring_M=np.array(ring_M), tip_map=tip_map, tip_ref=tip_ref,
                       force_map=force_map, force_ref=force_ref, blade_dofs=blade_dofs,
                       elements=tuple(elements), ring_elements=tuple(ring_elements),
                       node_xyz=np.array([[r, 0.0, z0] for r in np.concatenate([r_disk[1:], r_blade[1:]])]))


def _beam_point_map(L: float, xi: float, y_hint: np.ndarray) -> np.ndarray:
    """Element DOF (12, sector frame) -> 6 DOF of the beam axis at ``x = xi L``.

    Cubic Hermite bending, linear axial and torsion: the element's own interpolation, so a
    force there is the element's consistent load.
    """
    R = rotation_matrix(np.array([1.0, 0.0, 0.0]), y_hint)
    T = np.kron(np.eye(4), R)
    N1, N2, N3, N4 = 1 - 3 * xi**2 + 2 * xi**3, L * (xi - 2 * xi**2 + xi**3), 3 * xi**2 - 2 * xi**3, L * (xi**3 - xi**2)
    d1, d2, d3, d4 = (6 * xi**2 - 6 * xi) / L, 1 - 4 * xi + 3 * xi**2, (6 * xi - 6 * xi**2) / L, 3 * xi**2 - 2 * xi
    Nl = np.zeros((6, 12))
    Nl[0, [0, 6]] = [1 - xi, xi]
    Nl[3, [3, 9]] = [1 - xi, xi]
    Nl[1, [1, 5, 7, 11]] = [N1, N2, N3, N4]  # v with rot_z
    Nl[2, [2, 4, 8, 10]] = [N1, -N2, N3, -N4]  # w with -rot_y
    Nl[5, [1, 5, 7, 11]] = [d1, d2, d3, d4]  # rot_z = v'
    Nl[4, [2, 4, 8, 10]] = [-d1, d2, -d3, d4]  # rot_y = -w'
    back = np.kron(np.eye(2), R.T)
    return back @ Nl @ T


def _point_maps(points: np.ndarray, foot: np.ndarray, node_dofs: np.ndarray, m: int,
                axis_map: np.ndarray | None = None):
    """Maps from sector DOF to (radial, tangential, axial) displacement of rigid points.

    ``axis_map`` (6 x len(node_dofs)) gives the foot's 6 DOF from ``node_dofs``; without it
    ``node_dofs`` are the foot's own 6 DOF.
    """
    n = points.shape[0]
    maps = np.zeros((n, 3, m))
    ref = np.zeros((n, 3))
    A = np.eye(6) if axis_map is None else axis_map
    for i, p in enumerate(points):
        ang = np.arctan2(p[1], p[0])
        local = rotation_z(ang).T @ rigid_offset_matrix(p - foot) @ A  # sector xyz -> node (r, t, z)
        maps[i][:, node_dofs] = local
        ref[i] = (np.hypot(p[0], p[1]), ang, p[2])
    return maps, ref


def blade_alone_frequencies(d: BladedDiskDesign, n: int = 3) -> np.ndarray:
    """First ``n`` natural frequencies (Hz) of one blade clamped at its root."""
    import scipy.linalg as sla  # here: the nodes that only read the bus never load it
    sec = assemble_sector(d)
    b = sec.blade_dofs
    w2 = sla.eigh(sec.K[np.ix_(b, b)], sec.M[np.ix_(b, b)], eigvals_only=True,
                  subset_by_index=[0, n - 1])
    return np.sqrt(w2) / (2.0 * np.pi)


def cyclic_matrices(sec: SectorModel, n_blades: int, nd: int) -> tuple[np.ndarray, np.ndarray]:
    phase = np.exp(2j * np.pi * nd / n_blades)
    K = sec.K.astype(complex)
    M = sec.M.astype(complex)
    for dofs, rk, rm in zip(sec.ring_dofs, sec.ring_K, sec.ring_M):
        ix = np.ix_(dofs, dofs)
        for A, B in ((K, rk), (M, rm)):
            A[ix] += B[:6, :6] + B[6:, 6:] + B[:6, 6:] * phase + B[6:, :6] * np.conj(phase)
    if nd == 0 or 2 * nd == n_blades:
        return K.real.copy(), M.real.copy()
    return K, M


@dataclass(frozen=True, slots=True, eq=False)
class CyclicSolution:
    """Per-ND eigen-solution of a tuned wheel.

    Attributes
    ----------
    freq_hz : ndarray, shape (n_nd, n_families)
        Natural frequency of family ``f`` at nodal diameter ``nd`` (Campbell data at zero speed).
    vectors : list of ndarray, each (m, n_families)
        Complex sector eigenvectors, ``v^H M_nd v = 1``.
    """

    freq_hz: np.ndarray
    vectors: list


def solve_cyclic(d: BladedDiskDesign, sec: SectorModel | None = None,
                 nds: list[int] | None = None, n_families: int | None = None) -> CyclicSolution:
    """Solve every nodal diameter 0..floor(N/2) of the tuned wheel."""
    import scipy.linalg as sla  # here: the nodes that only read the bus never load it
    sec = assemble_sector(d) if sec is None else sec
    n_families = d.n_families if n_families is None else n_families
    nds = list(range(d.n_blades // 2 + 1)) if nds is None else nds
    freqs, vecs = [], []
    for nd in nds:
        K, M = cyclic_matrices(sec, d.n_blades, nd)
        w2, v = sla.eigh(K, M, subset_by_index=[0, n_families - 1], driver="gvx")
        freqs.append(np.sqrt(np.maximum(w2, 0.0)) / (2.0 * np.pi))
        vecs.append(v)
    return CyclicSolution(freq_hz=np.array(freqs), vectors=vecs)


@dataclass(frozen=True, slots=True, eq=False)
class WheelModes:
    """Real, mass-normalised full-wheel modes.

    Attributes
    ----------
    freq_hz : ndarray, shape (n_modes,)
    shapes : ndarray, shape (n_modes, n_blades, m)
        Sector DOF of every sector, each in its own sector frame.
    family : ndarray, shape (n_modes,)
    nodal_diameter : ndarray, shape (n_modes,)
        Dominant nodal diameter from the spatial DFT of blade participation.
    """

    freq_hz: np.ndarray
    shapes: np.ndarray
    family: np.ndarray
    nodal_diameter: np.ndarray


def normalise_phase(v: np.ndarray) -> np.ndarray:
    """The complex eigenvector with its largest entry turned real and positive."""
    return v * np.exp(-1j * np.angle(v[np.argmax(np.abs(v))]))


def expand_unsorted(d: BladedDiskDesign, sol: CyclicSolution, fix_phase: bool = True):
    N = d.n_blades
    s = np.arange(N)
    freqs, shapes, fam, nds = [], [], [], []
    for nd, (f_nd, v_nd) in enumerate(zip(sol.freq_hz, sol.vectors)):
        for k in range(v_nd.shape[1]):
            v = v_nd[:, k]
            if nd == 0 or 2 * nd == N:
                v = np.real(normalise_phase(v) if fix_phase else v)
                shapes.append(np.tile(v, (N, 1)) / np.sqrt(N))
                freqs.append(f_nd[k]); fam.append(k); nds.append(nd)
                continue
            # fix the arbitrary complex phase so the expansion is deterministic
            if fix_phase:
                v = normalise_phase(v)
            u = np.exp(1j * 2 * np.pi * nd * s / N)[:, None] * v[None, :]
            for part in (u.real, u.imag):
                shapes.append(part * np.sqrt(2.0 / N))
                freqs.append(f_nd[k]); fam.append(k); nds.append(nd)
    return np.array(freqs), np.array(shapes), np.array(fam), np.array(nds)


def expand_cyclic(d: BladedDiskDesign, sol: CyclicSolution, order: np.ndarray | None = None,
                  fix_phase: bool = True) -> WheelModes:
    """Expand per-ND complex modes to real full-wheel modes (ND 0 single, others pairs).

    Parameters
    ----------
    order : ndarray of int, optional
        Mode order (default: by family, frequency, ND). The speed-dependent model passes the
        zero-speed order so that mode ``i`` is the same mode at every speed.
    fix_phase : bool
        Turn each complex vector's largest entry real (default); False keeps the phase of
        vectors already aligned (:func:`solve_cyclic_speeds`).
    """
    freqs, shapes, fam, nds = expand_unsorted(d, sol, fix_phase)
    if order is None:
        order = np.lexsort((nds, freqs, fam))
    return WheelModes(freq_hz=freqs[order], shapes=shapes[order], family=fam[order], nodal_diameter=nds[order])


def asymmetry_pattern(d: BladedDiskDesign) -> np.ndarray:
    """Deterministic per-sector disk stiffness factors for the asymmetric-disk option.

    Harmonic ``h`` of the disk stiffness splits the pairs of ND ``n`` with ``2n = +-h (mod N)``;
    harmonic 2 splits ND 1 and harmonic 1 splits ND 14 of a 29-sector wheel.
    """
    theta = 2.0 * np.pi * np.arange(d.n_blades) / d.n_blades
    a1, a2 = d.asymmetry
    return 1.0 + a1 * np.cos(theta + 0.4) + a2 * np.cos(2.0 * theta + 1.1)


def assemble_full_wheel(d: BladedDiskDesign, blade_k=None, blade_m=None, disk_k=None):
    """Sparse full-wheel K, M (sector-frame DOF, sector after sector) and the sector models.

    Parameters
    ----------
    blade_k, blade_m, disk_k : array_like, shape (n_blades,), optional
        Per-sector factors (mistuning of blade stiffness and mass; disk asymmetry).
    """
    import scipy.sparse as sp  # only the full-wheel (mistuned) solve needs it
    N = d.n_blades
    ones = np.ones(N)
    blade_k = ones if blade_k is None else np.asarray(blade_k, float)
    blade_m = ones if blade_m is None else np.asarray(blade_m, float)
    disk_k = ones if disk_k is None else np.asarray(disk_k, float)
    sectors = [assemble_sector(d, blade_k[i], blade_m[i], disk_k[i]) for i in range(N)]
    m = sectors[0].n_dof
    rows, cols, kv, mv = [], [], [], []

    def add(r_idx, c_idx, kb, mb):
        rr, cc = np.meshgrid(r_idx, c_idx, indexing="ij")
        rows.append(rr.ravel()); cols.append(cc.ravel()); kv.append(kb.ravel()); mv.append(mb.ravel())

    for i, sec in enumerate(sectors):
        base = i * m
        idx = np.arange(m) + base
        add(idx, idx, sec.K, sec.M)
        nxt = ((i + 1) % N) * m
        for dofs, rk, rm in zip(sec.ring_dofs, sec.ring_K, sec.ring_M):
            both = np.concatenate([dofs + base, dofs + nxt])
            add(both, both, rk, rm)
    r = np.concatenate(rows); c = np.concatenate(cols)
    K = sp.csc_matrix((np.concatenate(kv), (r, c)), shape=(N * m, N * m))
    M = sp.csc_matrix((np.concatenate(mv), (r, c)), shape=(N * m, N * m))
    return K, M, sectors


def nodal_diameter_content(shapes: np.ndarray, blade_dofs: np.ndarray) -> np.ndarray:
    """Energy of each nodal diameter in the blade participation of each mode.

    Parameters
    ----------
    shapes : ndarray, shape (n_modes, n_blades, m)
    blade_dofs : ndarray
        Sector DOF indices of the blade.

    Returns
    -------
    ndarray, shape (n_modes, floor(N/2) + 1)
        Fraction of the blade-DOF energy at each ND (harmonics k and N-k folded).
    """
    X = shapes[:, :, blade_dofs]
    F = np.fft.fft(X, axis=1)
    e = np.sum(np.abs(F) ** 2, axis=2)
    N = shapes.shape[1]
    n_nd = N // 2 + 1
    out = np.zeros((shapes.shape[0], n_nd))
    for k in range(N):
        out[:, min(k, N - k)] += e[:, k]
    return out / np.sum(out, axis=1, keepdims=True)


def solve_full_wheel(d: BladedDiskDesign, n_modes: int, blade_k=None, blade_m=None,
                     disk_k=None) -> tuple[WheelModes, SectorModel]:
    """Exact eigen-solution of the (mistuned or asymmetric) full wheel: lowest ``n_modes``.

    Shift-invert Lanczos on the sparse full-wheel matrices, then a Rayleigh-Ritz step on the
    returned subspace so that the modes are mass-orthonormal to round-off. Families are
    assigned by frequency rank (``rank // n_blades``); the ND by the spatial DFT of blade
    participation.
    """
    import scipy.linalg as sla  # here: the nodes that only read the bus never load it
    import scipy.sparse.linalg as spla  # imported here: the tuned wheel never needs it
    K, M, sectors = assemble_full_wheel(d, blade_k, blade_m, disk_k)
    N = d.n_blades
    m = sectors[0].n_dof
    k_extra = min(n_modes + N, K.shape[0] - 2)
    sigma = -1.0  # below the spectrum: the factorisation is positive definite
    w2, V = spla.eigsh(K, k=k_extra, M=M, sigma=sigma, which="LM", tol=1e-13,
                       v0=np.ones(K.shape[0]))
    Kr = V.T @ (K @ V)
    Mr = V.T @ (M @ V)
    w2, Z = sla.eigh(0.5 * (Kr + Kr.T), 0.5 * (Mr + Mr.T))
    V = (V @ Z)[:, :n_modes]
    w2 = w2[:n_modes]
    # deterministic sign: largest blade-tip component positive
    shapes = V.T.reshape(n_modes, N, m)
    flat = shapes.reshape(n_modes, -1)
    sign = np.sign(flat[np.arange(n_modes), np.argmax(np.abs(flat), axis=1)])
    shapes = shapes * sign[:, None, None]
    content = nodal_diameter_content(shapes, sectors[0].blade_dofs)
    modes = WheelModes(freq_hz=np.sqrt(np.maximum(w2, 0.0)) / (2.0 * np.pi), shapes=shapes,
                       family=np.arange(n_modes) // N, nodal_diameter=np.argmax(content, axis=1))
    return modes, sectors

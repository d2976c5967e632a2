"""3D Euler-Bernoulli beam finite element (12 DOF) with arbitrary section orientation.

Conventions
-----------
Node DOF order: ``(u_x, u_y, u_z, rot_x, rot_y, rot_z)`` in the frame the element is
assembled in. Local element axes: ``x`` along the element, ``y`` and ``z`` the principal
axes of the section. ``EI_y`` resists bending *about* ``y`` (displacement along ``z``),
``EI_z`` bending about ``z`` (displacement along ``y``). SI units.

Notes
-----
Stiffness and consistent mass are the textbook cubic-Hermite / linear-interpolation
matrices (Przemieniecki, *Theory of Matrix Structural Analysis*, 1968, Ch. 5 and 11).
Rotary inertia of the bending rotations is neglected; the torsional inertia uses the
polar mass moment ``rho * I_p`` of the section.

Centrifugal effects (rotation ``Omega`` about the assembly ``Z`` axis) use two more element
matrices: the *geometric* (initial-stress) stiffness of an element carrying the axial force
``N`` (Przemieniecki 1968, Ch. 15; the continuum form ``int N (u'^2 + v'^2 + w'^2) dx`` plus
the torsion term ``N I_p / A``), and the *spin-softening* mass, the consistent mass of the
displacement component in the plane of rotation, ``int rho A (P u)^T (P u) dx`` with
``P = diag(1, 1, 0)`` (Geradin & Rixen, *Mechanical Vibrations*, Sec. 5.7). Coriolis
coupling is not modelled.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["BeamSection", "beam_matrices", "rotation_matrix", "rigid_offset_matrix", "beam_geometric_stiffness",
           "beam_spin_mass", "beam_axial_force", "IN_PLANE"]

#: Projector on the plane of rotation (rotation about the assembly Z axis).
IN_PLANE = np.diag([1.0, 1.0, 0.0])


@dataclass(frozen=True, slots=True)
class BeamSection:
    """Section and material of one element (SI units).

    Attributes
    ----------
    E : float
        Young's modulus, Pa.
    G : float
        Shear modulus, Pa.
    rho : float
        Density, kg/m^3 (0 for a massless stiffness-only element).
    A : float
        Area, m^2.
    I_y, I_z : float
        Second moments about the local y and z axes, m^4.
    J : float
        Saint-Venant torsion constant, m^4.
    I_p : float
        Polar second moment used for the torsional inertia, m^4.
    """

    E: float
    G: float
    rho: float
    A: float
    I_y: float
    I_z: float
    J: float
    I_p: float


def _local_matrices(L: float, s: BeamSection) -> tuple[np.ndarray, np.ndarray]:
    k = np.zeros((12, 12))
    m = np.zeros((12, 12))
    # axial (0, 6) and torsion (3, 9)
    for (i, j), stiff, mass in (
        ((0, 6), s.E * s.A / L, s.rho * s.A * L / 6.0),
        ((3, 9), s.G * s.J / L, s.rho * s.I_p * L / 6.0),
    ):
        k[np.ix_((i, j), (i, j))] = stiff * np.array([[1.0, -1.0], [-1.0, 1.0]])
        m[np.ix_((i, j), (i, j))] = mass * np.array([[2.0, 1.0], [1.0, 2.0]])
    kb = np.array([[12, 6 * L, -12, 6 * L],
                   [6 * L, 4 * L * L, -6 * L, 2 * L * L],
                   [-12, -6 * L, 12, -6 * L],
                   [6 * L, 2 * L * L, -6 * L, 4 * L * L]]) / L**3
    mb = np.array([[156, 22 * L, 54, -13 * L],
                   [22 * L, 4 * L * L, 13 * L, -3 * L * L],
                   [54, 13 * L, 156, -22 * L],
                   [-13 * L, -3 * L * L, -22 * L, 4 * L * L]]) * (s.rho * s.A * L / 420.0)
    # bending in the x-y plane: v with rot_z; in the x-z plane: w with -rot_y
    idx_xy = (1, 5, 7, 11)
    idx_xz = (2, 4, 8, 10)
    flip = np.diag([1.0, -1.0, 1.0, -1.0])
    k[np.ix_(idx_xy, idx_xy)] = s.E * s.I_z * kb
    k[np.ix_(idx_xz, idx_xz)] = s.E * s.I_y * (flip @ kb @ flip)
    m[np.ix_(idx_xy, idx_xy)] = mb
    m[np.ix_(idx_xz, idx_xz)] = flip @ mb @ flip
    return k, m


def rotation_matrix(x_axis: np.ndarray, y_hint: np.ndarray) -> np.ndarray:
    """Rows are the local unit axes (x, y, z) in assembly coordinates.

    ``y_hint`` is orthogonalised against ``x_axis`` (it fixes the section orientation).
    """
    ex = np.asarray(x_axis, float) / np.linalg.norm(x_axis)
    ey = np.asarray(y_hint, float) - np.dot(y_hint, ex) * ex
    ey /= np.linalg.norm(ey)
    ez = np.cross(ex, ey)
    return np.vstack([ex, ey, ez])


def beam_matrices(p1: np.ndarray, p2: np.ndarray, y_hint: np.ndarray,
                  section: BeamSection) -> tuple[np.ndarray, np.ndarray]:
    """Stiffness and mass (12x12) of a beam from ``p1`` to ``p2`` in assembly coordinates.

    Parameters
    ----------
    p1, p2 : ndarray, shape (3,)
        Node positions, m.
    y_hint : ndarray, shape (3,)
        Direction of the section's local ``y`` principal axis (need not be exactly normal).
    section : BeamSection
    """
    d = np.asarray(p2, float) - np.asarray(p1, float)
    L = float(np.linalg.norm(d))
    k, m = _local_matrices(L, section)
    R = rotation_matrix(d, y_hint)
    T = np.kron(np.eye(4), R)
    return T.T @ k @ T, T.T @ m @ T


def rigid_offset_matrix(offset: np.ndarray) -> np.ndarray:
    """Map a node's 6 DOF to the translation of a rigidly attached point (3x6).

    ``u_point = u + rot x offset`` (small rotations).
    """
    r = np.asarray(offset, float)
    skew = np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])
    return np.hstack([np.eye(3), -skew])


def _frame(p1: np.ndarray, p2: np.ndarray, y_hint: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    d = np.asarray(p2, float) - np.asarray(p1, float)
    R = rotation_matrix(d, y_hint)
    return float(np.linalg.norm(d)), R, np.kron(np.eye(4), R)


def _local_geometric(L: float, s: BeamSection, N: float) -> np.ndarray:
    kg = np.zeros((12, 12))
    bar = np.array([[1.0, -1.0], [-1.0, 1.0]]) / L
    kg[np.ix_((0, 6), (0, 6))] = N * bar
    kg[np.ix_((3, 9), (3, 9))] = N * s.I_p / s.A * bar
    kb = np.array([[36, 3 * L, -36, 3 * L],
                   [3 * L, 4 * L * L, -3 * L, -L * L],
                   [-36, -3 * L, 36, -3 * L],
                   [3 * L, -L * L, -3 * L, 4 * L * L]]) * (N / (30.0 * L))
    flip = np.diag([1.0, -1.0, 1.0, -1.0])
    kg[np.ix_((1, 5, 7, 11), (1, 5, 7, 11))] = kb
    kg[np.ix_((2, 4, 8, 10), (2, 4, 8, 10))] = flip @ kb @ flip
    return kg


def beam_geometric_stiffness(p1: np.ndarray, p2: np.ndarray, y_hint: np.ndarray, section: BeamSection,
                             axial_force_n) -> np.ndarray:
    """Geometric (initial-stress) stiffness (12x12, assembly coordinates) for an axial force.

    Parameters
    ----------
    p1, p2, y_hint, section
        As :func:`beam_matrices`.
    axial_force_n : float or array_like, shape (3,)
        Axial force of the element, N (tension positive): a constant, or the coefficients
        ``(c0, c1, c2)`` of ``N(xi) = c0 + c1 xi + c2 xi^2`` along the element
        (``xi = x / L``), e.g. the quadratic force of a radial element under its own
        centrifugal load.

    Notes
    -----
    ``int N(x) (u'^2 + v'^2 + w'^2 + (I_p / A) theta_x'^2) dx`` with the element's own
    interpolation (Wagner's twist term for a doubly symmetric section), integrated exactly
    (4-point Gauss). For a constant ``N`` it is the closed form
    ``N / (30 L) [36, 3L, -36, 3L; 3L, 4L^2, -3L, -L^2; ...]`` in both bending planes and
    ``N / L`` on the axial and ``N I_p / (A L)`` on the twist DOF (Przemieniecki 1968,
    Eq. 15.23; McGuire, Gallagher & Ziemian 2000, Eq. 9.19).
    """
    L, _, T = _frame(p1, p2, y_hint)
    c = np.atleast_1d(np.asarray(axial_force_n, float))
    if c.size == 1:
        return T.T @ _local_geometric(L, section, float(c[0])) @ T
    c = np.concatenate([c, np.zeros(3 - c.size)]) if c.size < 3 else c[:3]
    kg = np.zeros((12, 12))
    ratio = section.I_p / section.A
    for x, w in zip(_GAUSS_X, _GAUSS_W):
        xi = 0.5 * (x + 1.0)
        B = _slope_shapes(L, xi)
        B[3] *= np.sqrt(ratio)
        kg += (0.5 * w * (c[0] + c[1] * xi + c[2] * xi * xi)) * (B.T @ B)
    return T.T @ (kg * L) @ T


def _slope_shapes(L: float, xi: float) -> np.ndarray:
    """d/dx of the local (u, v, w, theta_x) at ``x = xi L`` from the 12 local DOF (4x12)."""
    d1, d2, d3, d4 = (6 * xi**2 - 6 * xi) / L, 1 - 4 * xi + 3 * xi**2, (6 * xi - 6 * xi**2) / L, 3 * xi**2 - 2 * xi
    B = np.zeros((4, 12))
    B[0, [0, 6]] = [-1.0 / L, 1.0 / L]
    B[1, [1, 5, 7, 11]] = [d1, d2, d3, d4]
    B[2, [2, 4, 8, 10]] = [d1, -d2, d3, -d4]
    B[3, [3, 9]] = [-1.0 / L, 1.0 / L]
    return B


_GAUSS_X, _GAUSS_W = np.polynomial.legendre.leggauss(4)


def _translation_shapes(L: float, xi: float) -> np.ndarray:
    """Local translations ``(u, v, w)`` at ``x = xi L`` from the 12 local DOF (3x12)."""
    N1, N2, N3, N4 = 1 - 3 * xi**2 + 2 * xi**3, L * (xi - 2 * xi**2 + xi**3), 3 * xi**2 - 2 * xi**3, L * (xi**3 - xi**2)
    Nl = np.zeros((3, 12))
    Nl[0, [0, 6]] = [1 - xi, xi]
    Nl[1, [1, 5, 7, 11]] = [N1, N2, N3, N4]
    Nl[2, [2, 4, 8, 10]] = [N1, -N2, N3, -N4]
    return Nl


def beam_spin_mass(p1: np.ndarray, p2: np.ndarray, y_hint: np.ndarray, section: BeamSection,
                   projector: np.ndarray = IN_PLANE) -> np.ndarray:
    """Consistent mass of the projected translation, ``int rho A (P u)^T (P u) dx`` (12x12).

    With ``P`` the projector on the plane of rotation this is the element's spin-softening
    matrix ``K_s`` (the rotating frame's centrifugal term ``-Omega^2 K_s``); with ``P = I``
    it is the translational part of :func:`beam_matrices`' mass. Integrated exactly
    (4-point Gauss: the integrand is a degree-6 polynomial). Rotary inertia is left out, as
    in the mass matrix.

    Parameters
    ----------
    p1, p2, y_hint, section
        As :func:`beam_matrices`.
    projector : ndarray, shape (3, 3)
        ``P`` in assembly coordinates.
    """
    L, R, T = _frame(p1, p2, y_hint)
    C = R @ np.asarray(projector, float) @ R.T
    m = np.zeros((12, 12))
    for x, w in zip(_GAUSS_X, _GAUSS_W):
        Nl = _translation_shapes(L, 0.5 * (x + 1.0))
        m += (0.5 * w) * (Nl.T @ C @ Nl)
    m *= section.rho * section.A * L
    return T.T @ m @ T


def beam_axial_force(p1: np.ndarray, p2: np.ndarray, y_hint: np.ndarray, section: BeamSection,
                     u: np.ndarray) -> float:
    """Axial force (N, tension positive) of an element under the nodal displacements ``u``.

    Parameters
    ----------
    u : ndarray, shape (12,)
        Element DOF in assembly coordinates.
    """
    L, R, _ = _frame(p1, p2, y_hint)
    u = np.asarray(u, float)
    return section.E * section.A / L * float(R[0] @ (u[6:9] - u[0:3]))

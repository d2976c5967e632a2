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
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["BeamSection", "beam_matrices", "rotation_matrix", "rigid_offset_matrix"]


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

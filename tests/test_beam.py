"""The beam element against closed-form beam theory."""

import numpy as np
import scipy.linalg as sla

from bttsim_stream.model.beam import BeamSection, beam_matrices, rigid_offset_matrix

SEC = BeamSection(E=200e9, G=78e9, rho=7800.0, A=1e-4, I_y=1e-9, I_z=4e-9, J=1.5e-9, I_p=5e-9)


def _cantilever(direction, y_hint, n=24, L=0.8):
    K = np.zeros((6 * (n + 1),) * 2)
    M = np.zeros_like(K)
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    for e in range(n):
        k, m = beam_matrices(d * e * L / n, d * (e + 1) * L / n, y_hint, SEC)
        K[6 * e:6 * e + 12, 6 * e:6 * e + 12] += k
        M[6 * e:6 * e + 12, 6 * e:6 * e + 12] += m
    return K[6:, 6:], M[6:, 6:], L


def test_cantilever_bending_and_torsion_match_beam_theory():
    K, M, L = _cantilever([1, 0, 0], [0, 1, 0])
    f = np.sqrt(sla.eigh(K, M, eigvals_only=True)) / (2 * np.pi)
    beta = np.array([1.875104069, 4.694091133])
    c = beta**2 / (2 * np.pi * L**2)
    flap = c * np.sqrt(SEC.E * SEC.I_y / (SEC.rho * SEC.A))
    edge = c * np.sqrt(SEC.E * SEC.I_z / (SEC.rho * SEC.A))
    torsion = np.sqrt(SEC.G * SEC.J / (SEC.rho * SEC.I_p)) / (4 * L)
    axial = np.sqrt(SEC.E / SEC.rho) / (4 * L)
    for expected in [*flap, *edge, torsion, axial]:
        assert np.min(np.abs(f - expected)) / expected < 2e-4


def test_frequencies_do_not_depend_on_orientation():
    K1, M1, _ = _cantilever([1, 0, 0], [0, 1, 0])
    K2, M2, _ = _cantilever([0.3, -0.5, 0.8], [1.0, 1.0, 0.2])
    w1 = sla.eigh(K1, M1, eigvals_only=True)
    w2 = sla.eigh(K2, M2, eigvals_only=True)
    # a backward-stable eigensolver (any LAPACK/BLAS) errs by about eps * |w_max| on every
    # eigenvalue: a fixed relative tolerance on the small ones depends on the library
    atol = 100 * np.finfo(float).eps * np.abs(w1).max()
    assert atol < 1e-4 * w1[0]  # an orientation error would move them by far more
    np.testing.assert_allclose(w1[:8], w2[:8], rtol=0, atol=atol)


def test_free_element_has_six_rigid_body_modes():
    k, m = beam_matrices(np.zeros(3), np.array([0.1, 0.05, -0.02]), np.array([0, 0, 1.0]), SEC)
    w = sla.eigh(k, m, eigvals_only=True)
    assert np.sum(np.abs(w) < 1e-6 * w.max()) == 6


def test_rigid_offset_is_small_rotation_kinematics():
    T = rigid_offset_matrix(np.array([0.0, 0.02, 0.0]))
    u = T @ np.array([0, 0, 0, 0, 0, 0.001])  # rotation about z moves a +y point towards -x
    np.testing.assert_allclose(u, [-2e-5, 0, 0], atol=1e-15)

"""The parametric bladed-disk model against the paper's modal data and FE invariants."""

from dataclasses import replace

import numpy as np
import pytest

from bttsim_stream.model import BladedDiskDesign, build_model, localisation
from bttsim_stream.model.bladed_disk import (
    asymmetry_pattern,
    assemble_full_wheel,
    expand_cyclic,
    nodal_diameter_content,
    solve_cyclic,
    solve_full_wheel,
)
from bttsim_stream.model.calibrate import TARGETS_HZ, calibrate_design, design_frequencies
from bttsim_stream.model.modal_model import DISK_ASYMMETRY

N = 29


@pytest.fixture(scope="module")
def design():
    return BladedDiskDesign()


@pytest.fixture(scope="module")
def model():
    return build_model()


@pytest.fixture(scope="module")
def wheel(design):
    modes = expand_cyclic(design, solve_cyclic(design))
    K, M, sectors = assemble_full_wheel(design)
    return modes, K, M, sectors


def test_blade_alone_modes_match_paper(model):
    np.testing.assert_allclose(model.blade_alone_freq_hz, [347.47, 1148.9, 1717.0], rtol=5e-3)


def test_first_family_matches_fig3(model):
    fam1 = model.campbell_freq_hz[0]
    assert fam1[1] == pytest.approx(343.9, rel=1e-3)
    assert fam1[14] == pytest.approx(347.5, rel=1e-3)
    assert np.all(np.diff(fam1[1:]) >= 0), "family 1 must not decrease from ND 1 to ND 14"


def test_mode_count_families_and_pairs(model):
    assert model.n_modes == 145
    assert sorted(set(model.family.tolist())) == [0, 1, 2, 3, 4]
    for fam in range(5):
        sel = model.family == fam
        counts = np.bincount(model.nodal_diameter[sel], minlength=15)
        assert counts[0] == 1 and np.all(counts[1:] == 2)
        for nd in range(1, 15):
            pair = model.freq_hz[sel & (model.nodal_diameter == nd)]
            assert pair[0] == pytest.approx(pair[1], rel=1e-12)
    # the Campbell data are the family frequencies per ND
    for fam in range(5):
        for nd in range(15):
            f = model.freq_hz[(model.family == fam) & (model.nodal_diameter == nd)]
            np.testing.assert_allclose(f, model.campbell_freq_hz[fam, nd], rtol=1e-12)


def test_modes_are_mass_orthonormal_and_exact(wheel):
    modes, K, M, _ = wheel
    Phi = modes.shapes.reshape(len(modes.freq_hz), -1).T
    np.testing.assert_allclose(Phi.T @ (M @ Phi), np.eye(Phi.shape[1]), atol=1e-9)
    w2 = (2 * np.pi * modes.freq_hz) ** 2
    # Rayleigh quotients reproduce the eigenvalues; residuals sit at the round-off floor of
    # matrices whose translational and rotational stiffnesses span ~10 decades
    np.testing.assert_allclose(np.diag(Phi.T @ (K @ Phi)), w2, rtol=1e-7)
    resid = np.linalg.norm(K @ Phi - (M @ Phi) * w2, axis=0) / np.linalg.norm(K @ Phi, axis=0)
    assert resid.max() < 1e-6


def test_nodal_diameter_labels_from_spatial_dft(wheel):
    modes, _, _, sectors = wheel
    content = nodal_diameter_content(modes.shapes, sectors[0].blade_dofs)
    np.testing.assert_array_equal(np.argmax(content, axis=1), modes.nodal_diameter)
    assert content.max(axis=1).min() > 0.999  # a tuned mode is a single spatial harmonic


def test_full_wheel_solve_agrees_with_cyclic_symmetry(design, wheel):
    modes = wheel[0]
    full, _ = solve_full_wheel(design, 2 * N)
    np.testing.assert_allclose(full.freq_hz, modes.freq_hz[:2 * N], rtol=1e-7)
    np.testing.assert_array_equal(np.sort(full.nodal_diameter), np.sort(modes.nodal_diameter[:2 * N]))


def test_tip_shapes_have_three_components(model):
    p = model.tip_shapes[model.family == 0][:, :, model.nominal_node, :]
    peak = np.abs(p).max(axis=(0, 1))
    assert np.all(peak > 0)
    assert peak[0] > 1e-3 * peak[1]  # radial is small but present
    # stagger: the first family moves P_nom along the flap direction, so axial and
    # tangential motions are in phase and of comparable size (docs: schemas/modal_model.md)
    i = np.argmax(np.abs(p[..., 1]).ravel())
    ratio = p[..., 2].ravel()[i] / p[..., 1].ravel()[i]
    assert 0.6 < ratio < 1 / np.tan(np.deg2rad(41.5)) + 1e-9


def test_tip_geometry(model):
    r, ang, z = np.moveaxis(model.tip_ref, -1, 0)
    s = np.hypot(np.diff(r[0] * np.cos(ang[0])), np.diff(r[0] * np.sin(ang[0])))
    spacing = np.hypot(s, np.diff(z[0]))
    np.testing.assert_allclose(spacing, 0.0004375, rtol=1e-12)
    assert z[0, model.nominal_node] == pytest.approx(0.01226, abs=1e-6)
    np.testing.assert_allclose(np.diff(ang[:, 0]), 2 * np.pi / N, rtol=1e-12)
    # the tip chord runs from the TE (larger z) toward the LE, ahead in rotation
    assert np.all(np.diff(z[0]) < 0) and np.all(np.diff(ang[0]) > 0)


def test_damping_is_stiffness_proportional(model):
    np.testing.assert_allclose(model.damping_ratio, 0.5 * 9e-6 * 2 * np.pi * model.freq_hz)


def test_calibration_reproduces_defaults(design):
    np.testing.assert_allclose(design_frequencies(design), TARGETS_HZ, rtol=1e-7)
    start = replace(design, root_thickness_m=design.root_thickness_m * 1.05,
                    web_thickness_m=design.web_thickness_m * 0.9)
    again = calibrate_design(start)
    np.testing.assert_allclose(design_frequencies(again), TARGETS_HZ, rtol=1e-7)
    assert again.root_thickness_m == pytest.approx(design.root_thickness_m, rel=1e-5)


def test_uniform_stiffness_increase_raises_blade_modes_by_half_percent(model):
    stiff = build_model(stiffness_factors=np.full(N, 1.01), mass_factors=np.ones(N))
    rise = stiff.freq_hz[stiff.family == 0] / model.freq_hz[model.family == 0] - 1
    assert np.all((rise > 0.0045) & (rise < np.sqrt(1.01) - 1 + 1e-9))
    blade = stiff.blade_alone_freq_hz  # the blade-alone reference is the nominal design
    assert blade[0] == pytest.approx(model.blade_alone_freq_hz[0])


def test_random_mistuning_localises_first_family(model):
    rng = np.random.default_rng(7)
    k = 1 + 0.02 * rng.standard_normal(N)
    mis = build_model(stiffness_factors=k, mass_factors=np.ones(N))
    assert mis.n_modes == 145
    tuned = localisation(model, 0)
    loc = localisation(mis, 0)
    assert tuned.max() == pytest.approx(1.5, abs=1e-6)
    assert loc.max() > 5.0 and np.median(loc) > 2.0
    # blade-mean frequency shift follows the mean stiffness factor
    assert np.mean(mis.freq_hz[mis.family == 0]) == pytest.approx(
        np.mean(model.freq_hz[model.family == 0]) * np.mean(np.sqrt(k)), rel=1e-3)


def test_mistuned_wheel_is_solved_exactly(design):
    rng = np.random.default_rng(3)
    k = 1 + 0.03 * rng.standard_normal(N)
    m = 1 + 0.01 * rng.standard_normal(N)
    modes, _ = solve_full_wheel(design, 40, k, m)
    K, M, _ = assemble_full_wheel(design, k, m)
    Phi = modes.shapes.reshape(40, -1).T
    np.testing.assert_allclose(Phi.T @ (M @ Phi), np.eye(40), atol=1e-9)
    w2 = (2 * np.pi * modes.freq_hz) ** 2
    # Rayleigh quotients reproduce the eigenvalues; residuals sit at the round-off floor of
    # matrices whose translational and rotational stiffnesses span ~10 decades
    np.testing.assert_allclose(np.diag(Phi.T @ (K @ Phi)), w2, rtol=1e-7)
    resid = np.linalg.norm(K @ Phi - (M @ Phi) * w2, axis=0) / np.linalg.norm(K @ Phi, axis=0)
    assert resid.max() < 1e-6


def test_disk_asymmetry_splits_nd1_pair_like_the_paper(design):
    d = replace(design, asymmetry=DISK_ASYMMETRY)
    modes, _ = solve_full_wheel(d, N, disk_k=asymmetry_pattern(d))
    pair = modes.freq_hz[modes.nodal_diameter == 1]
    assert len(pair) == 2
    assert pair[1] - pair[0] == pytest.approx(0.05, abs=0.01)  # paper: 343.89 / 343.94 Hz
    np.testing.assert_allclose(pair, 343.9, rtol=1e-3)


@pytest.mark.parametrize("k", [3, 7, 12])
def test_force_point_inside_an_element_is_the_beam_interpolation(design, k):
    """At a beam node the element-interpolated force point equals the node's own rigid map."""
    from bttsim_stream.model.bladed_disk import _point_maps, assemble_sector

    d = replace(design, force_span_fraction=k / design.n_blade_elements)
    sec = assemble_sector(d)
    nd = design.n_disk_elements
    node = nd + k  # blade node k (node nd is the root on the rim)
    dofs = np.arange(6) + 6 * (node - 1)
    r = design.rim_radius_m + k / design.n_blade_elements * design.span_m
    foot = np.array([r, 0.0, design.z_mid_m])
    xyz = np.stack([sec.force_ref[:, 0] * np.cos(sec.force_ref[:, 1]),
                    sec.force_ref[:, 0] * np.sin(sec.force_ref[:, 1]), sec.force_ref[:, 2]], axis=1)
    maps, _ = _point_maps(xyz, foot, dofs, sec.n_dof)
    np.testing.assert_allclose(sec.force_map, maps, atol=1e-12)

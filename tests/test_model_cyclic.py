"""Cyclic sector -> full wheel: against a direct full-wheel solve of an exact spring-mass wheel,
and against the built-in model's own cyclic expansion (a sector export re-imported)."""

import json

import numpy as np
import pytest
import scipy.linalg as sla

from bttsim_stream.errors import ModelFileError
from bttsim_stream.model import build_model
from bttsim_stream.model.cyclic import (CyclicSector, builtin_sector, expand_sector, load_sector, save_sector,
                                        tip_geometry)
from bttsim_stream.model.modal_model import to_cartesian

N_NODES = 4  # nodes per sector: the "tip" line of 4 nodes; node 0 is also the force node


def rotation_z(t):
    c, s = np.cos(t), np.sin(t)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def _spring_wheel(N, seed=1):
    """A rotationally periodic spring-mass wheel: full K, M in global Cartesian DOFs, node
    positions of sector 0 and the DOF map of sector s = R(theta_s) applied to sector 0."""
    rng = np.random.default_rng(seed)
    c = 0.004 * np.arange(N_NODES)  # along a 40 deg staggered chord, a little off it
    xyz = np.column_stack([0.18 + 0.0005 * rng.standard_normal(N_NODES), c * np.cos(0.7), 0.012 - c * np.sin(0.7)])
    masses = rng.uniform(0.5, 2.0, N_NODES) * 1e-3
    springs = []  # (node a in sector 0, node b, sector offset of b, 3x3 SPD in sector-0 frame)
    for a in range(N_NODES):
        springs.append((a, a, None, np.diag(rng.uniform(1, 3, 3)) * 1e5))  # to ground
        for b in range(a + 1, N_NODES):
            A = rng.standard_normal((3, 3))
            springs.append((a, b, 0, (A @ A.T + np.eye(3)) * 1e5))
        A = rng.standard_normal((3, 3))
        springs.append((a, (a + 1) % N_NODES, 1, (A @ A.T + np.eye(3)) * 3e4))  # to the next sector
    n = 3 * N_NODES * N
    K, M = np.zeros((n, n)), np.zeros((n, n))
    dof = lambda s, a: slice(3 * (N_NODES * (s % N) + a), 3 * (N_NODES * (s % N) + a) + 3)  # noqa: E731
    for s in range(N):
        R = rotation_z(2 * np.pi * s / N)
        for a in range(N_NODES):
            M[dof(s, a), dof(s, a)] += masses[a] * np.eye(3)
        for a, b, off, k in springs:
            kg = R @ k @ R.T
            if off is None:
                K[dof(s, a), dof(s, a)] += kg
                continue
            for i, j, sign in ((dof(s, a), dof(s, a), 1), (dof(s + off, b), dof(s + off, b), 1),
                               (dof(s, a), dof(s + off, b), -1), (dof(s + off, b), dof(s, a), -1)):
                K[i, j] += sign * kg
    return xyz, K, M


def _sector_solution(N, xyz, K, M, n_fam):
    """Solve every harmonic index on the cyclic-reduced matrices (u^H M_k u = 1)."""
    ks, fs, us = [], [], []
    for k in range(N // 2 + 1):
        T = np.concatenate([np.kron(np.eye(N_NODES), rotation_z(2 * np.pi * s / N)) * np.exp(2j * np.pi * k * s / N)
                            for s in range(N)])
        Kk, Mk = T.conj().T @ K @ T / N, T.conj().T @ M @ T / N
        w2, v = sla.eigh(Kk, Mk, subset_by_index=[0, n_fam - 1])
        ks += [k] * n_fam; fs += list(np.sqrt(w2) / (2 * np.pi)); us.append(v.T.reshape(n_fam, N_NODES, 3))
    u = np.concatenate(us)
    return CyclicSector(n_sectors=N, harmonic_index=np.array(ks), freq_hz=np.array(fs), tip_xyz=xyz,
                        tip_shapes=u, force_xyz=xyz[0], force_shapes=u[:, 0], nominal_node=1)


@pytest.mark.parametrize("N", [7, 8], ids=["odd", "even"])
def test_expansion_is_the_full_wheel_solution(N, tmp_path):
    xyz, K, M = _spring_wheel(N)
    n_fam = 3
    sector = _sector_solution(N, xyz, K, M, n_fam)
    save_sector(sector, tmp_path / "s.npz")
    model, report = expand_sector(load_sector(tmp_path / "s.npz"), damping_beta_s=0.0)
    assert model.n_modes == n_fam * N and report["n_families"] == n_fam
    # the lowest families of the direct solve: each cyclic family spans N full-wheel modes
    w2 = sla.eigh(K, M, eigvals_only=True)
    fam_direct = np.sort(np.concatenate([np.sqrt(w2) / (2 * np.pi)]))
    np.testing.assert_allclose(np.sort(model.freq_hz), np.sort(sector.freq_hz[np.repeat(
        np.arange(sector.freq_hz.size), [1 if k in (0, N / 2) else 2 for k in sector.harmonic_index])]), rtol=0)
    for f in model.freq_hz:  # every expanded frequency is a full-wheel eigenfrequency
        assert np.min(np.abs(fam_direct - f)) < 1e-9 * f
    # Phi^T M Phi = I and Phi^T K Phi = diag(omega^2) on the full wheel's DOFs
    _, u = to_cartesian(model.tip_ref, model.tip_shapes)   # (n_modes, N, n_nodes, 3)
    Phi = u.reshape(model.n_modes, -1).T
    np.testing.assert_allclose(Phi.T @ M @ Phi, np.eye(model.n_modes), atol=1e-10)
    np.testing.assert_allclose(Phi.T @ K @ Phi / np.outer(2 * np.pi * model.freq_hz, 2 * np.pi * model.freq_hz),
                               np.eye(model.n_modes), atol=1e-9)
    # the force node is node 0 of each sector
    np.testing.assert_allclose(model.force_shapes, model.tip_shapes[:, :, 0, :], atol=1e-15)
    assert set(model.nodal_diameter.tolist()) == set(range(N // 2 + 1))


def test_cos_sin_and_wheel_normalisation_give_the_same_model(tmp_path):
    N = 7
    xyz, K, M = _spring_wheel(N)
    s = _sector_solution(N, xyz, K, M, 2)
    ref, _ = expand_sector(s)
    wheel = CyclicSector(**{**{f: getattr(s, f) for f in s.__slots__},
                            "tip_shapes": s.tip_shapes * np.where(s.harmonic_index == 0, 1 / np.sqrt(N),
                                                                  np.sqrt(2 / N))[:, None, None],
                            "force_shapes": s.force_shapes * np.where(s.harmonic_index == 0, 1 / np.sqrt(N),
                                                                      np.sqrt(2 / N))[:, None],
                            "normalisation": "wheel"})
    save_sector(wheel, tmp_path / "w.npz")
    with np.load(tmp_path / "w.npz") as z:  # rewrite with the real cos / sin pairs
        d = {k: z[k] for k in z.files}
    meta = json.loads(str(d["meta"]))
    for name in ("tip_shapes", "force_shapes"):
        c = d.pop(name)
        d[name + "_cos"], d[name + "_sin"] = c.real.copy(), c.imag.copy()
    d["meta"] = np.array(json.dumps(meta))
    np.savez(tmp_path / "cs.npz", **d)
    m2, _ = expand_sector(load_sector(tmp_path / "cs.npz"))
    np.testing.assert_allclose(m2.tip_shapes, ref.tip_shapes, atol=1e-14)
    np.testing.assert_array_equal(m2.freq_hz, ref.freq_hz)


def _frf(model, f_hz):
    w = 2 * np.pi * f_hz
    wr, z = 2 * np.pi * model.freq_hz, model.damping_ratio
    h = 1 / (wr**2 - w**2 + 2j * z * wr * w)
    return np.einsum("k,kbpc,kd->bpcd", h, model.tip_shapes, model.force_shapes[:, 0, :])


def test_builtin_sector_reimported_reproduces_the_builtin_model(tmp_path):
    ref = build_model()
    save_sector(builtin_sector(), tmp_path / "sector.npz")
    model, report = expand_sector(load_sector(tmp_path / "sector.npz"), damping_beta_s=9e-6)
    np.testing.assert_allclose(model.freq_hz, ref.freq_hz, rtol=1e-14)
    np.testing.assert_array_equal(model.family, ref.family)
    np.testing.assert_array_equal(model.nodal_diameter, ref.nodal_diameter)
    np.testing.assert_allclose(model.campbell_freq_hz, ref.campbell_freq_hz, rtol=1e-14)
    np.testing.assert_allclose(model.tip_ref, ref.tip_ref, atol=1e-15)
    np.testing.assert_allclose(model.damping_ratio, ref.damping_ratio, rtol=1e-14)
    # shapes up to the rotation of each degenerate pair: per-ND projectors and the tip FRF
    for fam in range(5):
        for nd in range(15):
            sel = (model.family == fam) & (model.nodal_diameter == nd)
            a = model.tip_shapes[sel].reshape(sel.sum(), -1)
            b = ref.tip_shapes[sel].reshape(sel.sum(), -1)
            np.testing.assert_allclose(a.T @ a, b.T @ b, atol=1e-12 * np.abs(b.T @ b).max())
    for f in (300.0, 343.9, 344.2, 347.45, 1148.9, 1717.0):
        a, b = _frf(model, f), _frf(ref, f)
        np.testing.assert_allclose(a, b, atol=1e-12 * np.abs(b).max())
    assert report["families_per_nd"] == {k: 5 for k in range(15)}
    assert abs(report["tip"]["stagger_deg"] - 41.5) < 0.05 and report["tip"]["n_tip"] == 9


def test_tip_geometry_of_a_straight_chord():
    eta = np.deg2rad(41.5)
    r, c = 0.19, 0.02
    s = np.linspace(0, c, 9)  # TE at larger z; TE -> LE = (tang, axial) (cos eta, -sin eta)
    xyz = np.column_stack([np.full(9, r), s * np.cos(eta), 0.02 - s * np.sin(eta)])
    g = tip_geometry(xyz)
    assert abs(g.stagger_deg - 41.5) < 0.05 and abs(g.chord_m - c) < 1e-12


def test_missing_harmonic_index_and_bad_files(tmp_path):
    N = 7
    xyz, K, M = _spring_wheel(N)
    s = _sector_solution(N, xyz, K, M, 2)
    keep = s.harmonic_index != 2
    cut = CyclicSector(**{**{f: getattr(s, f) for f in s.__slots__}, "harmonic_index": s.harmonic_index[keep],
                          "freq_hz": s.freq_hz[keep], "tip_shapes": s.tip_shapes[keep],
                          "force_shapes": s.force_shapes[keep]})
    with pytest.raises(ModelFileError, match="harmonic indices missing.*2"):
        expand_sector(cut)
    with pytest.raises(ModelFileError, match="harmonic_index must lie in 0..3"):
        CyclicSector(**{**{f: getattr(s, f) for f in s.__slots__}, "harmonic_index": s.harmonic_index + 2})
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(ModelFileError, match="not an .npz archive"):
        load_sector(bad)
    np.savez(tmp_path / "pickled.npz", meta=np.array([{"a": 1}], dtype=object), harmonic_index=np.arange(2),
             freq_hz=np.ones(2), tip_xyz=np.ones((2, 3)), force_xyz=np.ones(3))
    with pytest.raises(ModelFileError):
        load_sector(tmp_path / "pickled.npz")


# ---- several speeds -------------------------------------------------------------------

@pytest.fixture(scope="module")
def speed_sectors():
    from bttsim_stream.scenario import Model, Scenario
    sp = np.linspace(0.0, 4800.0 * np.pi / 30.0, 9)
    built = build_model(Scenario(model=Model(centrifugal=True, centrifugal_speeds=9)))
    return sp, [builtin_sector(None, w) for w in sp], built


def test_import_at_speeds_reproduces_the_builtin_speed_model(speed_sectors):
    """The built-in model's sector solutions at 9 speeds (untracked, raw eigenvector phases, as
    an FE package gives them) imported: the same tracked frequencies, and the same shapes up to
    the zero-speed basis of each (family, ND) space (the tip-node MAC and the mass-weighted MAC
    align phases a little differently: 1e-2)."""
    from bttsim_stream.model.cyclic import expand_sectors_at_speeds
    sp, sectors, built = speed_sectors
    model, report = expand_sectors_at_speeds(sectors, sp)
    assert report["min_mac"] > 0.999
    # (two dense partial eigensolves of the same matrices agree to ~3e-8: the zero-speed model vs
    # the full wheel agree to 1e-7 too)
    np.testing.assert_allclose(model.extra["freq_hz_at_speed"], built.extra["freq_hz_at_speed"], rtol=1e-7)
    np.testing.assert_allclose(model.extra["campbell_freq_hz_at_speed"], built.extra["campbell_freq_hz_at_speed"],
                               rtol=1e-7)
    a, c = model.extra["tip_shapes_at_speed"], built.extra["tip_shapes_at_speed"]
    for f in range(5):
        for nd in range(15):
            sel = np.flatnonzero((built.family == f) & (built.nodal_diameter == nd))
            A0, C0 = a[0, sel].reshape(sel.size, -1), c[0, sel].reshape(sel.size, -1)
            T = np.linalg.lstsq(A0.T, C0.T, rcond=None)[0]
            for s in range(sp.size):
                As, Cs = a[s, sel].reshape(sel.size, -1), c[s, sel].reshape(sel.size, -1)
                tol = 2e-3 if f == 0 else 1.5e-2
                assert np.abs(T.T @ As - Cs).max() < tol * np.abs(Cs).max(), (f, nd, s)


def test_import_at_speeds_cli_and_errors(speed_sectors, tmp_path, capsys):
    from bttsim_stream.cli import main
    sp, sectors, _ = speed_sectors
    paths = []
    for i in (0, 4, 8):
        paths.append(str(tmp_path / f"s{i}.npz"))
        save_sector(sectors[i], paths[-1])
    rpm = ",".join(f"{w * 30 / np.pi:g}" for w in sp[[0, 4, 8]])
    assert main(["model", "import", *paths, "--speeds-rpm", rpm, "--out", str(tmp_path / "m.npz")]) == 0
    out = capsys.readouterr().out
    assert "speeds: 0, 2400, 4800 rpm" in out
    # one line, exit 2: speeds not one per file, not from 0, fewer families at a speed
    few = CyclicSector(**{**{f: getattr(sectors[4], f) for f in CyclicSector.__dataclass_fields__},
                          "harmonic_index": sectors[4].harmonic_index[::5].copy(),
                          "freq_hz": sectors[4].freq_hz[::5].copy(), "tip_shapes": sectors[4].tip_shapes[::5].copy(),
                          "force_shapes": sectors[4].force_shapes[::5].copy()})
    save_sector(few, tmp_path / "few.npz")
    for args, expect in (([*paths, "--speeds-rpm", "0,2400"], "3 results files but 2 speeds"),
                         ([*paths, "--speeds-rpm", "100,2400,4800"], "strictly ascending from 0"),
                         ([paths[0], str(tmp_path / "few.npz"), "--speeds-rpm", "0,2400"],
                          "1 solutions of harmonic index 0, fewer than the 5 families")):
        assert main(["model", "import", *args, "--out", str(tmp_path / "bad.npz")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("bttsim: error:") and expect in err[0], err
        assert not (tmp_path / "bad.npz").exists()


@pytest.mark.parametrize("scale,words", [(1e3, "this looks like mm"), (1e-3, "outside [0.005, 10] m")])
def test_a_sector_in_other_units_than_metres_is_refused(tmp_path, capsys, scale, words):
    """A neutral .npz sector is SI; its tip coordinates in mm (or km) put the tip radius
    outside 5 mm..10 m, the bound the .frd reader holds its units to: one line, exit 2."""
    from bttsim_stream.cli import main

    s = builtin_sector()
    save_sector(s, tmp_path / "si.npz")
    assert main(["model", "import", str(tmp_path / "si.npz"), "--out", str(tmp_path / "ok.npz")]) == 0
    for name in ("tip_xyz", "force_xyz"):
        object.__setattr__(s, name, getattr(s, name) * scale)  # as a file would hold them (unchecked here)
    save_sector(s, tmp_path / "scaled.npz")
    capsys.readouterr()
    assert main(["model", "import", str(tmp_path / "scaled.npz"), "--out", str(tmp_path / "m.npz")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "tip radius" in err[0] and words in err[0], err
    assert not (tmp_path / "m.npz").exists()

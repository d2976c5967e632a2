"""The .frd reader and the importer without CalculiX: a .frd written here in CalculiX's layout
(fixed columns, DISP + DISPI per mode pair, the -z axis and its conjugate phase) from an exact
spring-mass wheel, a deck with node sets (GENERATE, *INCLUDE), and the neutral .npz through
`bttsim model import`."""

import numpy as np
import pytest

from bttsim_stream.cli import main
from bttsim_stream.errors import ModelFileError
from bttsim_stream.model import build_model, load_model
from bttsim_stream.model.cyclic import builtin_sector, expand_sector, save_sector
from bttsim_stream.model.frd import read_frd
from bttsim_stream.model.importers import ImportOptions, import_model, read_deck_sets

from test_model_cyclic import _sector_solution, _spring_wheel

N = 7
IDS = np.array([11, 12, 13, 14])  # the 4 "tip" nodes; node 11 is also the force node


def _e(x):
    return f"{x:12.5E}"


def _write_frd(path, sector, *, axis_dir=-1.0, extra_nodes=((1, (0.05, 0.0, 0.0)),)):
    """A CalculiX-like .frd of ``sector`` (CalculiX's phase: the conjugate about -z)."""
    nodes = [(int(i), tuple(p)) for i, p in zip(IDS, sector.tip_xyz)] + [(i, p) for i, p in extra_nodes]
    out = ["    1C", "    1UPGM               CalculiX",
           f"    2C{'':>24}{len(nodes):>6}{'':>37}1"]
    out += [f" -1{i:>10}" + "".join(_e(v) for v in p) for i, p in nodes] + [" -3"]
    for n, (k, f, u) in enumerate(zip(sector.harmonic_index, sector.freq_hz, sector.tip_shapes)):
        u = np.conj(u) if axis_dir < 0 else u
        for name, part in (("DISP", u.real), ("DISPI", u.imag)):
            out += [f"    1PSTEP{'':>25}{n + 1}{'':>11}1{'':>11}1", "    1PGM                1.000000E+00",
                    f"    1PHID{'':>26}{k}",
                    "    1PAX                 " + "".join(_e(v) for v in (0, 0, 0, 0, 0, axis_dir)),
                    f"    1PMODE{'':>25}{2 * n + 1}",
                    f"  100CL  101{f:12.7f}{len(nodes):>12}{'':>20} 2{2 * n + 1:>5}MODAL      1",
                    f" -4  {name:<8}    4    1", " -5  D1          1    2    1    0",
                    " -5  D2          1    2    2    0", " -5  D3          1    2    3    0",
                    " -5  ALL         1    2    0    0    1ALL"]
            out += [f" -1{i:>10}" + "".join(_e(v) for v in row) for i, row in zip(IDS, part)]
            out += [f" -1{1:>10}" + _e(0) * 3, " -3"]
    out.append(" 9999")
    path.write_text("\n".join(out) + "\n")
    return path


@pytest.fixture(scope="module")
def wheel():
    xyz, K, M = _spring_wheel(N)
    return _sector_solution(N, xyz, K, M, 2)


@pytest.mark.parametrize("axis_dir", [-1.0, 1.0], ids=["minus_z", "plus_z"])
def test_frd_import_reproduces_the_sector_expansion(wheel, tmp_path, axis_dir):
    frd = _write_frd(tmp_path / "s.frd", wheel, axis_dir=axis_dir)
    res = read_frd(frd)
    assert len(res.modes) == wheel.freq_hz.size and res.cyclic_axis[5] == axis_dir
    opts = ImportOptions(n_sectors=N, tip_nodes=tuple(IDS.tolist()), force_node=11, nominal_node=1)
    model, report = import_model(frd, opts)
    ref, _ = expand_sector(wheel)
    np.testing.assert_allclose(model.freq_hz, ref.freq_hz, rtol=1e-7)  # 8 printed digits of the frequency
    np.testing.assert_allclose(model.tip_shapes, ref.tip_shapes, atol=2e-5 * np.abs(ref.tip_shapes).max())
    np.testing.assert_allclose(model.force_shapes, ref.force_shapes, atol=2e-5 * np.abs(ref.tip_shapes).max())
    assert report["notes"]["conjugated"] == (axis_dir < 0)


def test_nodes_by_deck_set_and_by_coordinates(wheel, tmp_path):
    frd = _write_frd(tmp_path / "s.frd", wheel)
    (tmp_path / "mesh.inp").write_text(
        "*NODE, NSET=NALL\n"
        + "".join(f"{i}, {float(p[0])!r}, {float(p[1])!r}, {float(p[2])!r}\n" for i, p in zip(IDS, wheel.tip_xyz))
        + "1, 0.05, 0., 0.\n*NSET, NSET=TIP, GENERATE\n11, 14, 1\n*NSET, NSET=LE\n11,\n")
    (tmp_path / "s.inp").write_text(f"** deck\n*INCLUDE, INPUT=mesh.inp\n*CYCLIC SYMMETRY MODEL, N={N}, NGRAPH=1\n")
    deck = read_deck_sets(tmp_path / "s.inp")
    assert deck.n_sectors == N and deck.node_sets["TIP"].tolist() == IDS.tolist() and len(deck.nodes) == 5
    by_set, _ = import_model(frd, ImportOptions(tip_nset="tip", force_nset="LE", nominal_node=1))  # deck: s.inp
    pts = tuple(tuple(p + 1e-4) for p in wheel.tip_xyz[::-1])  # nearest, given in any order
    by_xyz, rep = import_model(frd, ImportOptions(tip_xyz=pts, force_xyz=tuple(wheel.force_xyz), nominal_node=1))
    np.testing.assert_array_equal(by_set.tip_shapes, by_xyz.tip_shapes)
    np.testing.assert_array_equal(by_set.tip_ref, by_xyz.tip_ref)  # the deck's full-precision coordinates
    assert rep["notes"]["tip"].ids.tolist() == IDS.tolist()  # ordered from the TE again
    with pytest.raises(ModelFileError, match="node set 'ROOT'"):
        import_model(frd, ImportOptions(tip_nset="ROOT", force_node=11))
    with pytest.raises(ModelFileError, match="holds 4 nodes, not 1"):
        import_model(frd, ImportOptions(tip_nset="TIP", force_nset="TIP"))


@pytest.mark.parametrize("cut", [0.5, 0.9, 0.999], ids=["half", "most", "no_end"])
def test_truncated_frd(wheel, tmp_path, cut):
    text = _write_frd(tmp_path / "s.frd", wheel).read_text()
    (tmp_path / "t.frd").write_text(text[: int(len(text) * cut)])
    with pytest.raises(ModelFileError, match="truncated"):
        read_frd(tmp_path / "t.frd")


def test_neutral_sector_through_the_cli(tmp_path, capsys):
    save_sector(builtin_sector(), tmp_path / "sector.npz")
    assert main(["model", "import", str(tmp_path / "sector.npz"), "--out", str(tmp_path / "m.npz")]) == 0
    out = capsys.readouterr().out
    assert "29 sectors" in out and "5 families kept" in out and "stagger 41.52 deg" in out
    m, ref = load_model(tmp_path / "m.npz"), build_model()
    np.testing.assert_allclose(m.freq_hz, ref.freq_hz, rtol=1e-14)
    assert m.meta["provenance"]["builder"].startswith("bttsim_stream built-in")
    # a sector with a harmonic index missing: one line, exit 2, nothing written
    with np.load(tmp_path / "sector.npz") as z:
        d = {k: z[k] for k in z.files}
    keep = d["harmonic_index"] != 7
    for k in ("harmonic_index", "freq_hz", "tip_shapes", "force_shapes"):
        d[k] = d[k][keep]
    np.savez(tmp_path / "cut.npz", **d)
    assert main(["model", "import", str(tmp_path / "cut.npz"), "--out", str(tmp_path / "c.npz")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "harmonic indices missing from the sector results: 7" in err[0]
    assert not (tmp_path / "c.npz").exists()
    assert main(["model", "import", str(tmp_path / "cut.npz"), "--format", "rst",
                 "--out", str(tmp_path / "c.npz")]) == 2
    assert "ANSYS .rst" in capsys.readouterr().err

"""`bttsim model import` of a real CalculiX cyclic-symmetry solution: the worked example in
examples/calculix_sector (gmsh sector, ccx), against a direct 360 deg ccx solve of the same
mesh, then simulated and processed; and bad .frd files, options and nodes (one line, exit 2)."""

import importlib.util
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bttsim_stream.cli import main
from bttsim_stream.model import load_model
from bttsim_stream.model.frd import read_frd
from bttsim_stream.model.modal_model import to_cartesian

REPO = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.integration  # gmsh and two ccx solves: about 15 s


def _example():
    spec = importlib.util.spec_from_file_location("ccx_sector", REPO / "examples" / "calculix_sector" / "sector.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def _need_fe_tools():
    if shutil.which("ccx") is None:
        pytest.skip("CalculiX (ccx) is not installed: apt-get install calculix-ccx (.ci/run does)")
    try:
        import gmsh  # noqa: F401
    except (ImportError, OSError) as exc:  # OSError: the wheel's libGLU / libX* are missing
        pytest.skip(f"gmsh cannot be imported ({exc}): pip install 'bttsim-stream[fe]' and its apt libraries")


@pytest.fixture(scope="module")
def example(tmp_path_factory):
    """The worked example with 6 blades on a coarse mesh, sector and full wheel solved."""
    _need_fe_tools()
    ex = _example()
    d = ex.SectorDesign(n_blades=6, mesh_size=0.014, blade_mesh_size=0.008, n_modes_per_nd=3)
    out = tmp_path_factory.mktemp("ccx")
    files = ex.main(out, d, full=True)
    return out, files, d


def _wheel_tip_shapes(files, model):
    w = read_frd(files["wheel_frd"])
    tip = np.array(model.meta["provenance"]["tip_nodes"])
    rows = np.array([w.index_of(tip + s * files["wheel_stride"]) for s in range(model.n_blades)])
    return np.array([m.freq_hz for m in w.modes]), np.array([m.u[rows] for m in w.modes])


def test_cyclic_expansion_matches_the_direct_full_wheel_solve(example):
    out, files, d = example
    model = load_model(files["model"])
    assert model.n_blades == 6 and model.n_modes == 18 and model.n_tip == 9
    f_wheel, W = _wheel_tip_shapes(files, model)
    # frequencies: every full-wheel mode of the 3 families, to 1e-6 relative
    np.testing.assert_allclose(np.sort(model.freq_hz), np.sort(f_wheel), rtol=1e-6)
    _, U = to_cartesian(model.tip_ref, model.tip_shapes)  # (mode, blade, tip, xyz), rotor frame
    for k in range(model.n_modes):
        same = np.abs(f_wheel - model.freq_hz[k]) < 1e-6 * model.freq_hz[k]
        assert same.sum() == (1 if model.nodal_diameter[k] in (0, 3) else 2)
        basis = W[same].reshape(same.sum(), -1).T
        u = U[k].ravel()
        proj = basis @ np.linalg.lstsq(basis, u, rcond=None)[0]
        mac = (u @ proj) / (u @ u)  # MAC with the wheel's (degenerate) eigenspace
        assert mac >= 0.9999, (k, mac)
    # mass normalisation: ccx's full-wheel modes are mass-normalised (Phi^T M Phi = I); the
    # tip projector of every (family, ND) eigenspace is the same (to the 6-digit print precision)
    for fam in range(3):
        for nd in range(4):
            sel = (model.family == fam) & (model.nodal_diameter == nd)
            same = np.abs(f_wheel - model.freq_hz[sel][0]) < 1e-6 * model.freq_hz[sel][0]
            A, B = U[sel].reshape(sel.sum(), -1), W[same].reshape(same.sum(), -1)
            np.testing.assert_allclose(A.T @ A, B.T @ B, atol=1e-4 * np.abs(B.T @ B).max())
    # the tip line the example meshed (on the plane x = r_tip), from the TE
    pts = _example().tip_points(d)
    np.testing.assert_allclose(model.tip_ref[0, :, 0], np.hypot(pts[:, 0], pts[:, 1]), rtol=1e-5)
    np.testing.assert_allclose(model.tip_ref[0, :, 2], pts[:, 2], atol=1e-8)
    assert abs(model.meta["stagger_deg"] - d.stagger_tip_deg) < 0.01


def test_import_cli_report_and_model_show(example, capsys):
    out, files, d = example
    assert main(["model", "import", str(files["sector_frd"]), "--options", str(files["options"]),
                 "--out", str(out / "cli.npz")]) == 0
    text = capsys.readouterr().out
    assert "6 sectors" in text and "solutions per ND: 0:3, 1:3, 2:3, 3:3" in text
    assert "stagger 41.50 deg" in text and "chord 23.400 mm" in text and "node set TIP" in text
    m = load_model(out / "cli.npz")
    ref = load_model(files["model"])
    np.testing.assert_array_equal(m.freq_hz, ref.freq_hz)
    assert main(["model", "show", str(out / "cli.npz"), "--png", str(out / "cli.png")]) == 0
    assert "family 1" in capsys.readouterr().out
    # tip nodes by number and the force node by number: the same model
    tip = ",".join(map(str, ref.meta["provenance"]["tip_nodes"]))
    assert main(["model", "import", str(files["sector_frd"]), "--tip-nodes", tip, "--force-node",
                 str(ref.meta["provenance"]["force_node"]), "--out", str(out / "ids.npz")]) == 0
    np.testing.assert_array_equal(load_model(out / "ids.npz").tip_shapes, m.tip_shapes)


def _readme_reimport(out: Path, monkeypatch) -> Path:
    """The example README's step, verbatim but for the output name, run in the example's folder."""
    monkeypatch.chdir(out)
    assert main(["model", "import", "sector.frd", "--options", "import.toml", "--out", "readme.npz"]) == 0
    return out / "readme.npz"


def test_readme_reimport_gives_the_model_sector_py_imported(example, monkeypatch, capsys):
    """import.toml holds what sector.py imported with (the damping included): the README's
    `bttsim model import sector.frd --options import.toml` gives the same model."""
    out, files, d = example
    again, ref = load_model(_readme_reimport(out, monkeypatch)), load_model(files["model"])
    np.testing.assert_array_equal(again.freq_hz, ref.freq_hz)
    np.testing.assert_array_equal(again.damping_ratio, ref.damping_ratio)
    np.testing.assert_array_equal(again.tip_shapes, ref.tip_shapes)
    np.testing.assert_array_equal(again.force_shapes, ref.force_shapes)
    # the example's damping: zeta = pi f beta with beta = sector.DAMPING_BETA_S (0.003 on family 1)
    np.testing.assert_allclose(ref.damping_ratio, np.pi * ref.freq_hz * _example().DAMPING_BETA_S, rtol=1e-6)


def test_bttsim_run_finds_the_resonance_at_the_campbell_crossing(example):
    out, files, d = example
    res = subprocess.run([sys.executable, "-m", "bttsim_stream.cli", "run", str(files["scenario"]), "--out",
                          str(out / "run"), "-q"], capture_output=True, text=True, timeout=300,
                         env=dict(os.environ, OMP_NUM_THREADS="1"))
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    s = json.loads((out / "run" / "summary.json").read_text())
    assert s["status"] == "resonance" and s["complete"] and s["eo"] == 8 and abs(s["nd"]) == 2
    model = load_model(files["model"])
    f_cross = model.campbell_freq_hz[0, 2]  # family 1, ND 2 = 8 mod 6
    e = s["resonances"][0]
    # the run-up's peak lags the crossing a little (measured +0.2 %)
    assert abs(e["rpm"] - files["crossing_rpm"]) < 0.005 * files["crossing_rpm"]
    assert abs(e["freq_hz"] - f_cross) < 0.005 * f_cross
    assert s["mean_E_A_pct"] < 2.0  # against the simulator's truth


@pytest.mark.parametrize("case", ["truncated", "binary", "not_frd", "missing_hi", "tip_not_found",
                                  "mm_units", "no_sectors", "bad_toml", "missing"], ids=str)
def test_bad_results_are_one_line_exit_2(example, tmp_path, capsys, case):
    out, files, d = example
    frd = Path(files["sector_frd"])
    args = ["--options", str(files["options"])]
    src = tmp_path / "s.frd"
    if case == "truncated":
        src.write_bytes(frd.read_bytes()[: frd.stat().st_size * 2 // 3])
    elif case == "binary":
        src.write_bytes(b"    1C\n" + bytes(range(256)))
    elif case == "not_frd":
        src.write_text("hello\n")
    elif case == "missing_hi":  # the deck says 6; results for 8 sectors would need ND 4
        src, args = frd, args + ["--n-sectors", "8"]
    elif case == "tip_not_found":
        src, args = frd, ["--deck", str(out / "sector.inp"), "--tip-nodes", "25,999999", "--force-node", "1"]
    elif case == "mm_units":
        (tmp_path / "o.toml").write_text(Path(files["options"]).read_text().replace("deck = \"sector.inp\"",
                                         f"deck = \"{out / 'sector.inp'}\"") + 'units = "mm-t-s"\n')
        src, args = frd, ["--options", str(tmp_path / "o.toml")]
    elif case == "no_sectors":
        shutil.copy(frd, src)
        args = ["--tip-nodes", "25,26,27", "--force-node", "1"]
    elif case == "bad_toml":
        (tmp_path / "o.toml").write_text("tip_nset = \n")
        src, args = frd, ["--options", str(tmp_path / "o.toml")]
    assert main(["model", "import", str(src), *args, "--out", str(tmp_path / "m.npz")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("bttsim: error:"), err
    expect = {"truncated": "truncated", "binary": "not an ASCII", "not_frd": "not a CalculiX",
              "missing_hi": "harmonic indices missing", "tip_not_found": "999999", "mm_units": "tip radius",
              "no_sectors": "number of sectors", "bad_toml": "not valid TOML", "missing": "no such file"}[case]
    assert expect in err[0]
    assert not (tmp_path / "m.npz").exists()


# ---- several speeds: CalculiX centrifugal prestress + perturbation frequency steps ---------

SPEEDS_RPM = (0.0, 10000.0, 20000.0)


@pytest.fixture(scope="module")
def speed_example(tmp_path_factory):
    """The same 6-blade sector solved at 0, 10,000 and 20,000 rpm (one .frd, three frequency steps)."""
    _need_fe_tools()
    ex = _example()
    d = ex.SectorDesign(n_blades=6, mesh_size=0.014, blade_mesh_size=0.008, n_modes_per_nd=3)
    out = tmp_path_factory.mktemp("ccx_speeds")
    files = ex.main(out, d, speeds_rpm=SPEEDS_RPM)
    return out, files, d


def test_readme_reimport_of_the_speed_dependent_example(speed_example, monkeypatch, capsys):
    """With --speeds-rpm, import.toml carries the speeds too: the README's re-import repeats it."""
    out, files, d = speed_example
    again, ref = load_model(_readme_reimport(out, monkeypatch)), load_model(files["model"])
    np.testing.assert_array_equal(again.freq_hz, ref.freq_hz)
    np.testing.assert_array_equal(again.damping_ratio, ref.damping_ratio)
    assert sorted(again.extra) == sorted(ref.extra)
    for key, value in ref.extra.items():
        np.testing.assert_array_equal(again.extra[key], value, err_msg=key)


def test_speed_dependent_import_of_calculix_prestressed_steps(speed_example, capsys):
    out, files, d = speed_example
    model = load_model(files["model"])
    e = model.extra
    np.testing.assert_allclose(e["speed_rad_s"] * 30 / np.pi, SPEEDS_RPM)
    frd = read_frd(files["sector_frd"])
    steps = sorted({m.step for m in frd.modes if m.harmonic_index is not None})
    assert len(steps) == 3
    for s, step in enumerate(steps):
        # every (ND, family) of the step is in the tracked table once: nothing dropped or doubled
        got = np.sort(e["campbell_freq_hz_at_speed"][s].ravel())
        want = np.sort([m.freq_hz for m in frd.modes if m.step == step])
        np.testing.assert_allclose(got, want, rtol=1e-12)
    camp = e["campbell_freq_hz_at_speed"]
    assert np.all(camp[1, 0] > camp[0, 0]) and np.all(camp[2, 0] > camp[1, 0])  # family 1 stiffens
    # tracked shapes move little and keep their sign / phase between speeds
    U = e["tip_shapes_at_speed"].reshape(3, model.n_modes, -1)
    for s in (1, 2):
        dots = np.sum(U[s] * U[s - 1], axis=1) / np.linalg.norm(U[s], axis=1) / np.linalg.norm(U[s - 1], axis=1)
        fam1 = model.family == 0
        assert dots[fam1].min() > 0.99, dots
    # the crossing the written scenario runs through is the stiffened one
    assert files["crossing_rpm"] > 60 * model.campbell_freq_hz[0, 2] / 8 * 1.01
    # model show lists it
    assert main(["model", "show", str(files["model"]), "--png", str(out / "show.png"), "--eo", "8"]) == 0
    text = capsys.readouterr().out
    assert "speed-dependent model: 3 speeds, 0 .. 20000 rpm" in text and "EO  8 x ND  2, family 1" in text


@pytest.mark.parametrize("case", ["count", "order", "one_npz"], ids=str)
def test_bad_speed_imports_are_one_line_exit_2(speed_example, tmp_path, capsys, case):
    out, files, d = speed_example
    frd = str(files["sector_frd"])
    args = {"count": [frd, "--speeds-rpm", "0,10000"], "order": [frd, "--speeds-rpm", "0,20000,10000"],
            "one_npz": [str(tmp_path / "x.npz"), "--speeds-rpm", "0,1"]}[case]
    if case == "one_npz":
        from bttsim_stream.model.cyclic import builtin_sector, save_sector
        save_sector(builtin_sector(), tmp_path / "x.npz")
    assert main(["model", "import", *args, "--options", str(files["options"]),
                 "--out", str(tmp_path / "m.npz")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("bttsim: error:"), err
    expect = {"count": "3 cyclic frequency step(s) in the file but 2 speeds", "order": "strictly ascending from 0",
              "one_npz": "one file per speed"}[case]
    assert expect in err[0]
    assert not (tmp_path / "m.npz").exists()

"""The modal model file: round trip, validation of bad files, and the CLI around it."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bttsim_stream.errors import ModelFileError
from bttsim_stream.model import build_model, load_model, save_model
from bttsim_stream.model.modal_model import model_from_cartesian, to_cartesian

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def model():
    return build_model()


@pytest.fixture(scope="module")
def model_file(model, tmp_path_factory):
    path = tmp_path_factory.mktemp("model") / "m.npz"
    save_model(model, path)
    return path


def _bttsim(*args, cwd=None):
    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.run([sys.executable, "-m", "bttsim_stream.cli", *map(str, args)],
                          capture_output=True, text=True, cwd=cwd or REPO, env=env, timeout=120)


def test_round_trip_is_exact(model, model_file):
    back = load_model(model_file)
    for name, arr in model.as_arrays().items():
        got = back.as_arrays()[name]
        assert got.dtype == np.asarray(arr).dtype
        np.testing.assert_array_equal(got, arr)
    assert back.meta == json.loads(json.dumps(model.meta))


def test_file_is_plain_npz_readable_without_pickle(model_file):
    with np.load(model_file, allow_pickle=False) as z:
        assert {"freq_hz", "damping_ratio", "tip_ref", "tip_shapes", "force_ref",
                "force_shapes", "meta"} <= set(z.files)
        meta = json.loads(str(z["meta"]))
    assert meta["schema"] == "bttsim.modal_model" and meta["schema_version"] == 1
    assert meta["n_blades"] == 29 and meta["nominal_node"] == 4


def _rewrite(src: Path, dst: Path, **changes):
    with np.load(src, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    for k, v in changes.items():
        if v is None:
            arrays.pop(k)
        else:
            arrays[k] = v
    np.savez(dst, **arrays)


def _meta_with(model_file, **kw):
    with np.load(model_file, allow_pickle=False) as z:
        meta = json.loads(str(z["meta"]))
    meta.update(kw)
    return np.array(json.dumps(meta))


BAD = {
    "missing-key": (lambda f: {"tip_shapes": None}, "missing array(s) tip_shapes"),
    "wrong-shape": (lambda f: {"force_shapes": np.zeros((3, 29, 3))}, "force_shapes has shape"),
    "nan": (lambda f: {"freq_hz": np.full(145, np.nan)}, "freq_hz holds non-finite"),
    "int-dtype": (lambda f: {"freq_hz": np.arange(145)}, "freq_hz must be floating point"),
    "schema-version": (lambda f: {"meta": _meta_with(f, schema_version=99)}, "unsupported schema_version 99"),
    "meta-not-json": (lambda f: {"meta": np.array("{not json")}, "meta is not valid JSON"),
    "n-blades-mismatch": (lambda f: {"meta": _meta_with(f, n_blades=30)}, "meta.n_blades = 30"),
    "nominal-out-of-range": (lambda f: {"meta": _meta_with(f, nominal_node=9)}, "meta.nominal_node"),
    "unknown-array": (lambda f: {"surprise": np.zeros(3)}, "unknown array(s) surprise"),
    "negative-frequency": (lambda f: {"freq_hz": -np.ones(145)}, "freq_hz must be in .0, 1e.06. Hz"),
    "absurd-frequency": (lambda f: {"freq_hz": np.full(145, 1e300)}, "freq_hz must be in .0, 1e.06. Hz"),
    "negative-stiffness-factor": (lambda f: {"stiffness_factors": np.r_[-1.0, np.ones(28)]},
                                  "stiffness_factors must be > 0 (a blade's factor on the tuned blade), got -1"),
    "zero-mass-factor": (lambda f: {"mass_factors": np.r_[np.ones(28), 0.0]}, "mass_factors must be > 0"),
}


@pytest.mark.parametrize("case", list(BAD), ids=list(BAD))
def test_inconsistent_files_are_refused(case, model_file, tmp_path):
    make, message = BAD[case]
    bad = tmp_path / "bad.npz"
    _rewrite(model_file, bad, **make(model_file))
    with pytest.raises(ModelFileError, match=message.replace("(", r"\(").replace(")", r"\)")) as exc:
        load_model(bad)
    assert "\n" not in str(exc.value)


def test_truncated_corrupt_pickled_and_missing(model_file, tmp_path):
    data = model_file.read_bytes()
    trunc = tmp_path / "trunc.npz"
    trunc.write_bytes(data[: len(data) // 2])
    text = tmp_path / "text.npz"
    text.write_text("this is not a model\n")
    flipped = tmp_path / "flipped.npz"
    b = bytearray(data)
    b[len(b) // 3: len(b) // 3 + 64] = bytes(64)
    flipped.write_bytes(bytes(b))
    pickled = tmp_path / "pickled.npz"
    with np.load(model_file, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["meta"] = np.array([{"evil": 1}], dtype=object)
    np.savez(pickled, **arrays)
    cases = {trunc: "corrupt", text: "not an .npz archive", flipped: "corrupt", pickled: "pickled",
             tmp_path / "nope.npz": "no such file", tmp_path: "not a file"}
    for path, word in cases.items():
        with pytest.raises(ModelFileError) as exc:
            load_model(path)
        assert word in str(exc.value) and "\n" not in str(exc.value), (path, exc.value)


def test_user_fe_export_loads_like_the_builtin_model(model, tmp_path):
    """A model given as Cartesian FE output (UX, UY, UZ) converts to the same model."""
    tip_xyz, tip_u = to_cartesian(model.tip_ref, model.tip_shapes)
    f_xyz, f_u = to_cartesian(model.force_ref, model.force_shapes)
    user = model_from_cartesian(model.freq_hz, tip_xyz, tip_u, f_xyz, f_u, nominal_node=4,
                                stagger_deg=41.5, damping_beta_s=9e-6)
    path = tmp_path / "user.npz"
    save_model(user, path)
    back = load_model(path)
    np.testing.assert_allclose(back.tip_ref, model.tip_ref, rtol=0, atol=1e-15)
    np.testing.assert_allclose(back.tip_shapes, model.tip_shapes, rtol=0, atol=1e-12)
    np.testing.assert_allclose(back.force_shapes, model.force_shapes, rtol=0, atol=1e-12)
    np.testing.assert_allclose(back.damping_ratio, model.damping_ratio, rtol=1e-14)
    result = _bttsim("model", "show", path, "--png", tmp_path / "user.png")
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "user.png").stat().st_size > 1000


def test_cli_build_then_show(tmp_path):
    out = tmp_path / "m.npz"
    built = _bttsim("model", "build", "--out", out)
    assert built.returncode == 0, built.stderr
    shown = _bttsim("model", "show", out)
    assert shown.returncode == 0, shown.stderr
    assert "343.90 / 343.90" in shown.stdout and "347.50 / 347.50" in shown.stdout
    png = out.with_suffix(".png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cli_build_with_scenario_mistuning(tmp_path):
    scn = tmp_path / "s.toml"
    scn.write_text("[run]\nseed = 4\n[model]\nstiffness_std = 0.01\n")
    out = tmp_path / "m.npz"
    built = _bttsim("model", "build", scn, "--out", out)
    assert built.returncode == 0, built.stderr
    m = load_model(out)
    assert m.n_modes == 145 and np.std(m.extra["stiffness_factors"]) > 0.003
    again = tmp_path / "again.npz"
    assert _bttsim("model", "build", scn, "--out", again).returncode == 0
    np.testing.assert_array_equal(load_model(again).tip_shapes, m.tip_shapes)  # deterministic


def test_cli_show_without_matplotlib_prints_the_table(model_file, tmp_path, capsys, monkeypatch):
    """Without the plot extra: the table and a note (exit 0); with --png the one-line error (exit 2)."""
    from bttsim_stream import cli

    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib -> ImportError
    hint = "the model plot needs matplotlib: pip install 'bttsim-stream[plot]'"
    assert cli.main(["model", "show", str(model_file)]) == 0
    out, err = capsys.readouterr()
    assert "343.90 / 343.90" in out and "wrote" not in out
    assert err.strip().splitlines() == [f"bttsim: note: no plot written: {hint}"]
    assert not model_file.with_suffix(".png").exists()
    png = tmp_path / "asked.png"
    assert cli.main(["model", "show", str(model_file), "--png", str(png)]) == 2
    out, err = capsys.readouterr()
    assert "343.90 / 343.90" in out
    assert err.strip().splitlines() == [f"bttsim: error: {hint}"]
    assert not png.exists()


def test_cli_show_lists_the_crossing_the_scenario_force_excites(model, model_file, tmp_path, capsys, monkeypatch):
    """EO 8 aliases to ND 8 (2606 rpm, listed as such), but the default scenario's force is a
    travelling wave of ND 1 (Eq. 5-7): ``model show`` lists EO 8 x ND 1 of family 1 at the ND 1
    pair's frequency (the run's resonance, about 2580 rpm) and says why; ``--scenario`` takes
    another scenario's ND; a missing scenario is a one-line error (exit 2)."""
    import re

    from bttsim_stream import cli

    monkeypatch.setitem(sys.modules, "matplotlib", None)  # the table only
    assert cli.main(["model", "show", str(model_file)]) == 0
    out = capsys.readouterr().out
    f_nd1 = float(np.mean(model.freq_hz[(model.family == 0) & (model.nodal_diameter == 1)]))
    rpm = 60.0 * f_nd1 / 8.0
    assert abs(rpm - 2580.0) < 3.0
    forced = out[out.index("crossings the forces of the default scenario"):]
    (got,) = re.findall(r"EO  8 x ND  1, family 1:\s+([0-9.]+) rpm", forced)
    assert float(got) == pytest.approx(rpm, abs=0.1)
    assert "EO  8 x ND  8, family 1:   2606.0 rpm" in out[:out.index("crossings the forces")]
    assert "not by its EO" in forced and "ND = EO mod N" in forced
    scn = tmp_path / "nd3.toml"
    scn.write_text("[[excitation]]\nengine_order = 7\nnodal_diameter = 3\n")
    assert cli.main(["model", "show", str(model_file), "--scenario", str(scn)]) == 0
    forced = capsys.readouterr().out.split(f"crossings the forces of scenario {scn}")[1]
    f_nd3 = float(np.mean(model.freq_hz[(model.family == 0) & (model.nodal_diameter == 3)]))
    (got,) = re.findall(r"EO  7 x ND  3, family 1:\s+([0-9.]+) rpm", forced)
    assert float(got) == pytest.approx(60.0 * f_nd3 / 7.0, abs=0.1)
    assert cli.main(["model", "show", str(model_file), "--scenario", str(tmp_path / "none.toml")]) == 2
    assert capsys.readouterr().err.count("\n") == 1


@pytest.mark.parametrize("content", [b"garbage", b"PK\x03\x04broken"], ids=["text", "broken-zip"])
def test_cli_bad_model_exits_2_with_one_line(content, tmp_path):
    bad = tmp_path / "bad.npz"
    bad.write_bytes(content)
    result = _bttsim("model", "show", bad)
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("bttsim: error:") and "Traceback" not in result.stderr


def test_unlabelled_modes_get_family_and_nd_from_the_spatial_dft(model):
    from bttsim_stream.model.modal_model import label_modes
    fam, nd = label_modes(model.freq_hz, model.tip_shapes)
    sel = model.family <= 1  # the first two families are the lowest 58 modes
    np.testing.assert_array_equal(fam[sel], model.family[sel])
    np.testing.assert_array_equal(nd, model.nodal_diameter)

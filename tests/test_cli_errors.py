"""Issue 12: impossible input to ``bttsim cn``, ``probes``, ``process`` and ``scenario --check``
ends in one line and exit status 2 (never a traceback, never ``inf`` with status 0)."""

import os
import stat
from pathlib import Path

import numpy as np
import pytest

from bttsim_stream import cli
from bttsim_stream.scenario import default_toml

REPO = Path(__file__).resolve().parents[1]
SINGULAR = "[probes]\nangles_deg = [0.0, 45.0, 90.0, 135.0]\n"


def _error(capsys, *argv) -> str:
    assert cli.main(list(argv)) == 2
    err = capsys.readouterr().err
    assert err.startswith("bttsim: error:") and err.count("\n") == 1, err
    return err


@pytest.mark.parametrize("argv,words", [
    (["process", "x.mcap", "--eo", "8", "--eo-range", "1-10"], "give --eo (the orders to fit) or --eo-range"),
    (["ingest", "--opr", "o.csv", "--probe", "5=p.csv", "--sample-rate", "1e6", "--out", "x.mcap"],
     "--sample-rate is for raw probe signals"),
    (["cn", "--eo", "0"], "engine order must be in [1, 1000]"),
    (["cn", "--eo", "-8"], "engine order must be in [1, 1000]"),
    (["cn", "--eo", "8.5"], "whole numbers"),
    (["cn", "--eo", ",8"], "--eo must be comma-separated whole numbers, got ',8'"),
    (["cn", "--probes", "5,,15,23"], "must be comma-separated degrees, got '5,,15,23'"),
    (["cn", "--probes", "5,15.15,23.82,220,301.5,"], "comma-separated degrees"),
    (["cn", "--probes", "5,15"], "cannot separate the 3 unknowns"),
    (["cn", "--eo", "8,9", "--probes", "5,15,25,35"], "cannot separate the 5 unknowns"),
    (["cn", "--probes", "0,400,20,30,40"], "[0, 360)"),
    (["cn", "--probes=-5,15,25"], "[0, 360)"),
    (["cn", "--probes", "1,1,2,3"], "distinct"),
    (["cn", "--probes", "5,x,3"], "comma-separated degrees"),
    (["cn", "--probes", "0,45,90,135"], "singular"),
    (["probes", "--n", "2"], "at least 3 probes"),
    (["probes", "--n", "20"], "only 11 candidate angles"),
    (["probes", "--eo", "0"], "engine order must be in [1, 1000]"),
    (["probes", "--top", "0"], "--top must be >= 1"),
    (["cn", "--eo", "100000"], "engine order must be in [1, 1000], got 100000"),
    (["cn", "--eo", "8,8"], "engine order 8 given twice"),
    (["probes", "--candidates", ",".join(str(5 * i) for i in range(64)), "--n", "10"],
     "151,473,214,816 layouts of 10 probes among 64 candidate angles: more than the 1,000,000"),
    (["probes", "--candidates", "0,45,90,135", "--n", "4"], "every layout"),
    (["probes", "--candidates", "10,20,400", "--n", "3"], "[0, 360)"),
], ids=lambda v: " ".join(v) if isinstance(v, list) else None)
def test_layout_commands_refuse_impossible_input(capsys, argv, words):
    assert words in _error(capsys, *argv)


def test_layout_commands_still_answer(capsys):
    assert cli.main(["cn"]) == 0
    assert capsys.readouterr().out.strip() == "1.433"
    assert cli.main(["cn", "--probes", "1,2,3"]) == 0  # computable, but poor: a warning
    out = capsys.readouterr()
    assert float(out.out) > 100 and "warning" in out.err
    assert cli.main(["probes", "--top", "2"]) == 0
    assert "462 layouts" in capsys.readouterr().out


def test_two_excitations_of_one_engine_order_are_a_valid_scenario(capsys, tmp_path):
    """``--eo 8,8`` is refused (a fit of one order twice is singular), but two excitations of
    the same order in a scenario (leading and trailing edge) check out."""
    path = tmp_path / "two.toml"
    path.write_text("[[excitation]]\nengine_order = 8\n[[excitation]]\nengine_order = 8\namplitude_n = 0.5\n")
    assert cli.main(["scenario", "--check", str(path)]) == 0, capsys.readouterr().err


def test_scenario_check_refuses_a_singular_layout_and_warns_on_a_poor_one(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text(SINGULAR)
    err = _error(capsys, "scenario", "--check", str(bad))
    assert "singular at EO 8" in err and "condition number inf" in err and "add probes or move them" in err
    poor = tmp_path / "poor.toml"
    poor.write_text("[probes]\nangles_deg = [5.0, 10.6, 15.15, 148.5, 190.35]\n")  # Table 3's CN 16.7
    assert cli.main(["scenario", "--check", str(poor)]) == 0
    out = capsys.readouterr()
    assert "CN 16.7 at EO 8" in out.out and "warning" in out.err and "above 10" in out.err
    ok = tmp_path / "ok.toml"
    ok.write_text(default_toml())
    assert cli.main(["scenario", "--check", str(ok)]) == 0
    assert "CN 1.43 at EO 8" in capsys.readouterr().out


@pytest.fixture(scope="module")
def singular_mcap(tmp_path_factory):
    from bttsim_stream.acquisition import simulate_to_mcap
    from bttsim_stream.paper.validate_processing import default_model
    from bttsim_stream.scenario import scenario_from_dict

    path = tmp_path_factory.mktemp("singular") / "singular.mcap"
    scn = scenario_from_dict({"probes": {"angles_deg": [0.0, 45.0, 90.0, 135.0]},
                              "speed": {"start_rpm": 2450.0, "end_rpm": 2500.0, "duration_s": 2.0}})
    simulate_to_mcap(scn, path, model=default_model())
    return path


def test_process_error_paths(capsys, singular_mcap, tmp_path):
    err = _error(capsys, "process", str(singular_mcap))
    assert "cannot separate EO 8" in err and "add or move probes" in err
    sample = "recordings/resonance_window.mcap"
    assert "engine order must be in [1, 1000]" in _error(capsys, "process", sample, "--eo", "0")
    assert "--eo-range" in _error(capsys, "process", sample, "--eo-range", "9-3")
    assert "--eo-range" in _error(capsys, "process", sample, "--eo-range", "nine")
    assert "window" in _error(capsys, "process", sample, "--window", "0")
    assert "a sine-fit window of 100000 revolutions is longer than the run's" in _error(
        capsys, "process", sample, "--window", "100000")
    assert "engine order 8 given twice" in _error(capsys, "process", sample, "--eo", "8,8")
    assert "engine order must be in [1, 1000], got 5000" in _error(capsys, "process", sample, "--eo", "5000")
    assert "cannot write" in _error(capsys, "process", sample, "--summary", str(tmp_path / "no" / "dir.json"))
    _error(capsys, "process", str(tmp_path / "missing.mcap"))


def test_nan_or_absurd_amplitudes_in_a_result_are_said():
    """Issue 16: NaN in a claimed result, or an amplitude beyond the linear model, is a warning."""
    from bttsim_stream.offline import result_warnings

    rows = [{"blade": 0, "amp_pkpk_m": 2e-3, "freq_hz": 344.0}, {"blade": 1, "amp_pkpk_m": float("nan"),
                                                                "freq_hz": 344.0},
            {"blade": 2, "amp_pkpk_m": 0.5, "freq_hz": float("nan")}]
    summary = {"resonances": [{"kind": "crossing", "eo": 8, "blades": rows}], "steady": []}
    warnings = result_warnings(summary, 0.19)
    assert len(warnings) == 2
    assert "NaN" in warnings[0] and "2 of 3 blade(s) (1, 2)" in warnings[0]
    assert "above 10% of the tip radius pk-pk" in warnings[1] and "1 blade(s)" in warnings[1]
    assert result_warnings({"resonances": [{"kind": "crossing", "eo": 8, "blades": rows[:1]}]}, 0.19) == []


def test_a_closed_output_pipe_is_not_a_traceback():
    """``bttsim scenario | head -0``: the reader is gone before anything is written."""
    import subprocess
    import sys

    p = subprocess.Popen([sys.executable, "-m", "bttsim_stream.cli", "scenario"], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE)
    p.stdout.close()  # before the command writes (its imports take far longer than this)
    err = p.stderr.read().decode()
    assert p.wait(timeout=120) == 141 and "Traceback" not in err, err


@pytest.mark.parametrize("argv,words", [
    (["replay", "x.mcap", "--wait-for", "-1"], "argument --wait-for: '-1' is below 0"),
    (["replay", "x.mcap", "--wait-for", "two"], "argument --wait-for: 'two' is not a whole number"),
    (["replay", "x.mcap", "--wait-timeout", "-1"], "argument --wait-timeout: '-1' is not a duration"),
    (["replay", "x.mcap", "--wait-timeout", "nan"], "argument --wait-timeout: 'nan' is not a duration"),
    (["replay", "x.mcap", "--duration", "0"], "argument --duration: '0' is not a duration"),
    (["node", "sim", "--wait-for", "-2"], "argument --wait-for: '-2' is below 0"),
    (["node", "processor", "--duration", "-1"], "argument --duration: '-1' is not a duration"),
    (["node", "recorder", "--out", "r.mcap", "--queue", "0"], "argument --queue: '0' is below 1"),
    (["node", "viewer", "--rrd", "v.rrd", "--duration", "nan"], "argument --duration: 'nan' is not a duration"),
    (["node", "router", "--duration", "inf"], "argument --duration: 'inf' is not a duration"),
    (["run", "--out", "o", "--connect-timeout", "-1"], "argument --connect-timeout: '-1' is not a duration"),
    (["replay", "x.mcap", "--wait", "nan"], "argument --wait: 'nan' is not a duration"),
    (["node", "sim", "--linger", "nan"], "argument --linger: 'nan' is not a duration"),
    (["node", "sim", "--revolutions", "0"], "argument --revolutions: '0' is below 1"),
    (["campaign", "c.toml", "--out", "o", "--workers", "0"], "argument --workers: '0' is below 1"),
    (["campaign", "c.toml", "--out", "o", "--connect-timeout", "nan"], "argument --connect-timeout: 'nan'"),
    (["campaign", "c.toml", "--out", "o", "--dashboard", "bogus"], "argument --dashboard: 'bogus' is not HOST:PORT"),
    (["run", "--out", "o", "--web-port", "70000"], "argument --web-port: '70000' is not a port"),
    (["view", "x.mcap", "--rrd", "x.rrd", "--grpc-port", "0"], "argument --grpc-port: '0' is below 1"),
], ids=lambda v: " ".join(v) if isinstance(v, list) else None)
def test_node_options_refuse_impossible_numbers_before_starting(capsys, tmp_path, monkeypatch, argv, words):
    """A negative count of consumers, a queue of none, a duration that is not a finite positive
    time: one line and status 2 before any session is opened or any file written (before, a
    replay with ``--wait-for -1`` published to nobody and a recorder with ``--queue 0`` ran)."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_:  # argparse's own exit, status 2
        cli.main(argv)
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("bttsim: error:") and err.count("\n") == 1 and words in err, err
    assert not any(tmp_path.iterdir())


def test_outputs_that_are_empty_or_the_input_and_files_that_cannot_be_written(capsys, tmp_path, monkeypatch):
    """An empty output path (it would write into the working folder), an output that is the
    command's own input (overwritten before it is read), an ``.rrd`` that is a folder or
    cannot be created, a non-.npz model: one line, status 2, and the input left as it was."""
    monkeypatch.chdir(tmp_path)
    scn = tmp_path / "s.toml"
    scn.write_text(SINGULAR)
    before = scn.read_bytes()
    sample = str(REPO / "recordings" / "resonance_window.mcap")
    assert "--out: an empty path" in _error(capsys, "export", sample, "--out", "")
    assert "DIR: an empty path" in _error(capsys, "certs", "")
    assert "--out: an empty path" in _error(capsys, "model", "build", "--out", "")
    assert f"--out {scn}: that is the input {scn}; it would be overwritten" in _error(
        capsys, "simulate", str(scn), "--out", str(scn))
    assert scn.read_bytes() == before
    (tmp_path / "folder").mkdir()
    assert "folder: is a folder" in _error(capsys, "view", sample, "--rrd", str(tmp_path / "folder"))
    assert "/proc/views.rrd: No such file or directory" in _error(capsys, "view", sample, "--rrd", "/proc/views.rrd")
    np.save(tmp_path / "one.npy", np.zeros(3))
    assert "not an .npz archive" in _error(capsys, "model", "show", str(tmp_path / "one.npy"))
    assert "not an .npz archive" in _error(capsys, "model", "show", str(scn))
    assert "--status-file: cannot write no/s.json: no folder" in _error(
        capsys, "replay", sample, "--status-file", "no/s.json")
    assert "--status-file: cannot write folder: it is a folder" in _error(
        capsys, "replay", sample, "--status-file", "folder")
    assert "invalid node name 'a/b'" in _error(capsys, "record", "--out", "r.mcap", "--until", "a/b")
    assert not any(p.name not in ("s.toml", "folder", "one.npy") for p in tmp_path.iterdir())


def test_outputs_written_through_a_rename_are_files(capsys, tmp_path, monkeypatch):
    """A model or an ingested recording is written to a temporary file, then renamed over its
    ``--out``: a folder, or a pipe (a device alike), would be replaced by a regular file, so
    they are refused; through a symbolic link the link's target is written and the link stays."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "folder").mkdir()
    os.mkfifo(tmp_path / "pipe")
    for out, words in ((".", "names a folder"), ("folder", "is a folder"), ("pipe", "is not a regular file")):
        assert words in _error(capsys, "model", "build", "--out", out)
    assert (tmp_path / "folder").is_dir() and stat.S_ISFIFO(os.stat(tmp_path / "pipe").st_mode)
    (tmp_path / "link.npz").symlink_to("target.npz")
    assert cli.main(["model", "build", "--out", "link.npz"]) == 0
    assert (tmp_path / "link.npz").is_symlink() and (tmp_path / "target.npz").is_file()


def test_certificate_names_and_hosts_are_checked_before_anything_is_written(capsys, tmp_path):
    assert "use 1 to 64 letters" in _error(capsys, "certs", str(tmp_path / "c"), "--names", "x" * 65)
    assert "bad host name '999.1.1.1'" in _error(capsys, "certs", str(tmp_path / "c"), "--host", "999.1.1.1")
    assert "bad host name 'a..b'" in _error(capsys, "certs", str(tmp_path / "c"), "--host", "a..b")
    assert not (tmp_path / "c").exists()
    # a Compose service name and a wildcard are DNS names
    assert cli.main(["certs", str(tmp_path / "ok"), "--names", "sim", "--host", "my_host",
                     "--host", "*.example.com"]) == 0


def test_numbers_beyond_what_the_code_can_hold_are_refused(capsys, tmp_path, monkeypatch):
    """Values that overflowed into a traceback: a certificate valid 10^9 days, a signal file
    starting at -1e300 s or sampled at 1e20 Hz (the scenario's bound), and a run
    that asks for more memory than there is."""
    from bttsim_stream.errors import exit_status

    monkeypatch.chdir(tmp_path)
    assert "--days must be in [1, 36500], got 1000000000" in _error(capsys, "certs", "c", "--days", "1000000000")
    np.savetxt(tmp_path / "opr.csv", np.arange(1, 40) * 0.02)
    np.save(tmp_path / "sig.npy", np.zeros(1000))
    ingest = ["ingest", "--out", "x.mcap", "--opr", "opr.csv", "--blades", "3", "--tip-radius-m", "0.2"]
    assert "the start time after '@' must be a time in s within +-4e+09, got '-1e300'" in _error(
        capsys, *ingest, "--signal", "5=sig.npy@-1e300", "--sample-rate", "1e6")
    assert "--signal-start-s must be a time in s within +-4e+09, got nan" in _error(
        capsys, *ingest, "--signal", "5=sig.npy", "--sample-rate", "1e6", "--signal-start-s", "nan")
    assert "--sample-rate must be at most 1e+09 Hz, got 1e+20" in _error(
        capsys, *ingest, "--signal", "5=sig.npy", "--sample-rate", "1e20")
    assert "--encoder-pulses must be in [1, 100000], got 0" in _error(
        capsys, *ingest, "--probe", "5=opr.csv", "--encoder-pulses", "0")  # 0 was taken as no encoder
    assert not (tmp_path / "x.mcap").exists() and not (tmp_path / "c").exists()

    def too_big():
        np.empty((1 << 40, 1 << 18))  # 2^61 bytes: no machine has them

    assert exit_status(too_big) == 2
    err = capsys.readouterr().err
    assert err.startswith("bttsim: error: out of memory: ") and err.count("\n") == 1, err


# ---- model files and sector files: damaged, forged, implausible ---------------------------

@pytest.fixture(scope="module")
def model_files(tmp_path_factory):
    """A valid sector file (the built-in model's) and a valid model file."""
    from bttsim_stream.model import build_model, save_model
    from bttsim_stream.model.cyclic import builtin_sector, save_sector

    folder = tmp_path_factory.mktemp("model_files")
    save_sector(builtin_sector(), folder / "sector.npz")
    save_model(build_model(), folder / "model.npz")
    return folder / "sector.npz", folder / "model.npz"


def _forged_npy_header() -> bytes:
    """A .npz whose one member's header declares 8 TB of float64 over 64 bytes of data."""
    import io
    import zipfile

    head = io.BytesIO()
    np.lib.format.write_array_header_1_0(head, {"descr": "<f8", "fortran_order": False, "shape": (10**12,)})
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as zf:
        zf.writestr("meta.npy", head.getvalue() + bytes(64))
    return out.getvalue()


def _huge_declared_size(data: bytes) -> bytes:
    """The first member's uncompressed size in the central directory set to 4 GB."""
    import struct

    b = bytearray(data)
    struct.pack_into("<I", b, b.find(b"PK\x01\x02") + 24, 0xFFFFFFF0)
    return bytes(b)


DAMAGED = {
    "truncated": (lambda d: d[: len(d) // 2], "corrupt or truncated"),
    "bad-crc": (lambda d: d[: len(d) // 2] + b"\xff" * 40 + d[len(d) // 2 + 40:], "Bad CRC-32"),
    "zip-magic-only": (lambda d: b"PK\x03\x04" + bytes(100), "corrupt or truncated"),
    "text": (lambda d: b"this is not an archive\n", "not an .npz archive"),
    "forged-npy-header": (lambda d: _forged_npy_header(), "declares (1000000000000,) float64"),
    "huge-declared-size": (_huge_declared_size, "more than 2147483648, refusing to load"),
}


@pytest.mark.parametrize("command", ["import", "import-second-speed", "show", "scenario-source"])
@pytest.mark.parametrize("case", list(DAMAGED), ids=list(DAMAGED))
def test_a_damaged_or_forged_npz_is_one_line_naming_it(capsys, tmp_path, model_files, case, command):
    """Every reader of a user's .npz (model import, model show, a scenario's [model] source):
    one line naming the file and the problem, exit 2, nothing written (never a zipfile
    traceback, nor numpy allocating what a forged header declares)."""
    sector, model = model_files
    src = model if command in ("show", "scenario-source") else sector
    make, words = DAMAGED[case]
    bad = tmp_path / "bad.npz"
    bad.write_bytes(make(src.read_bytes()))
    out = tmp_path / "out.npz"
    if command == "import":
        err = _error(capsys, "model", "import", str(bad), "--out", str(out))
    elif command == "import-second-speed":
        err = _error(capsys, "model", "import", str(sector), str(bad), "--speeds-rpm", "0,1000", "--out", str(out))
    elif command == "show":
        err = _error(capsys, "model", "show", str(bad), "--png", str(tmp_path / "p.png"))
    else:
        scn = tmp_path / "s.toml"
        scn.write_text(f'[model]\nsource = "{bad}"\n')
        err = _error(capsys, "scenario", "--check", str(scn))
    assert f"{bad}: " in err and words in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["bad.npz"] + (["s.toml"] if "scenario" in command
                                                                                 else []))


def _sector_with(src: Path, dst: Path, meta=None, **arrays) -> Path:
    """A copy of the sector file ``src`` with some meta keys and arrays replaced."""
    import json

    with np.load(src, allow_pickle=False) as z:
        a = {k: z[k] for k in z.files}
    a["meta"] = np.array(json.dumps({**json.loads(str(a["meta"])), **(meta or {})}))
    a.update(arrays)
    np.savez(dst, **a)
    return dst


@pytest.mark.parametrize("n", [1_000_000_000, 201, 1])
def test_an_impossible_sector_count_is_refused_up_front(capsys, tmp_path, model_files, n):
    """meta.n_sectors outside the blade count of a run, [2, 200], is refused before anything is
    expanded (10^9 sectors took 93 s to fail), and so is --n-sectors."""
    import time

    sector, _ = model_files
    bad = _sector_with(sector, tmp_path / "bad.npz", {"n_sectors": n})
    t0 = time.perf_counter()
    err = _error(capsys, "model", "import", str(bad), "--out", str(tmp_path / "m.npz"))
    assert time.perf_counter() - t0 < 10.0
    assert f"{bad}: meta.n_sectors must be an integer in [2, 200] (the blades of a run), got {n}" in err, err
    err = _error(capsys, "model", "import", str(sector), "--n-sectors", str(n), "--out", str(tmp_path / "m.npz"))
    assert f"n_sectors must be an integer in [2, 200] (the blades of a run), got {n}" in err, err
    assert not (tmp_path / "m.npz").exists()


IMPLAUSIBLE = {
    "all-zero-shapes": (lambda a: {"tip_shapes": np.zeros_like(a["tip_shapes"])},
                        "tip_shapes: 75 of 75 solutions do not move the tip nodes (solution 0, harmonic index 0, "
                        "344.39 Hz: all zero"),
    "one-zero-mode": (lambda a: {"tip_shapes": a["tip_shapes"] * (np.arange(75) != 3)[:, None, None]},
                      "tip_shapes: 1 of 75 solutions do not move the tip nodes (solution 3, harmonic index 0"),
    "tiny-shapes": (lambda a: {"tip_shapes": a["tip_shapes"] * 1e-200}, "at most 1.3e-199"),
    "absurd-shapes": (lambda a: {"tip_shapes": a["tip_shapes"] * 1e200},
                      "tip_shapes: a component of 1.91e+201 m per unit modal coordinate, above 1e+06"),
    "absurd-force-shapes": (lambda a: {"force_shapes": a["force_shapes"] * 1e200},
                            "force_shapes: a component of 1.44e+201 m per unit modal coordinate, above 1e+06"),
    "tip-at-one-point": (lambda a: {"tip_xyz": np.repeat(a["tip_xyz"][:1], 9, axis=0)},
                         "tip_xyz: tip nodes 0 and 1 are 0 m apart, less than 1e-06 of the tip radius"),
    "two-tip-nodes-coincide": (lambda a: {"tip_xyz": a["tip_xyz"][[0, 1, 2, 3, 3, 5, 6, 7, 8]]},
                               "tip_xyz: tip nodes 3 and 4 are 0 m apart"),
}


@pytest.mark.parametrize("case", list(IMPLAUSIBLE), ids=list(IMPLAUSIBLE))
def test_implausible_sector_shapes_and_tip_geometry_are_refused(capsys, tmp_path, model_files, case):
    """Finite arrays of the right shapes that no FE solution gives (schemas/cyclic_sector.md,
    "Plausibility"): one line naming the array and why, exit 2, no numpy warning, nothing written
    (they were imported with a NaN localisation and a 0 mm chord)."""
    sector, _ = model_files
    with np.load(sector, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    make, words = IMPLAUSIBLE[case]
    bad = _sector_with(sector, tmp_path / "bad.npz", **make(arrays))
    err = _error(capsys, "model", "import", str(bad), "--out", str(tmp_path / "m.npz"))
    assert f"{bad}: " in err and words in err, err
    assert not (tmp_path / "m.npz").exists()


@pytest.mark.parametrize("key", ["stiffness_factors", "mass_factors"])
def test_a_model_with_a_negative_mistuning_factor_is_refused(capsys, tmp_path, model_files, key):
    """A blade factor of -1 (a negative stiffness or mass) passed model show and scenario --check."""
    _, model = model_files
    with np.load(model, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    arrays[key] = np.r_[-1.0, np.ones(28)]
    bad = tmp_path / "bad.npz"
    np.savez(bad, **arrays)
    words = f"{bad}: {key} must be > 0 (a blade's factor on the tuned blade), got -1"
    assert words in _error(capsys, "model", "show", str(bad))
    scn = tmp_path / "s.toml"
    scn.write_text(f'[model]\nsource = "{bad}"\n')
    assert words in _error(capsys, "scenario", "--check", str(scn))


def test_model_show_png_must_be_a_png_file(capsys, tmp_path, model_files):
    """--png afile.txt was a matplotlib traceback, --png DIR (a folder) wrote DIR.png and said
    "wrote DIR": both one line and exit 2 before anything is printed or written."""
    _, model = model_files
    (tmp_path / "DIR").mkdir()
    (tmp_path / "D.png").mkdir()
    (tmp_path / "afile.txt").write_text("kept\n")
    for png, words in (("afile.txt", "--png {}: the plot is a PNG image: give a file name ending in .png"),
                       ("DIR", "--png {}: is a folder, not a file"), ("D.png", "--png {}: is a folder, not a file")):
        path = tmp_path / png
        assert words.format(path) in _error(capsys, "model", "show", str(model), "--png", str(path))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["D.png", "DIR", "afile.txt"]
    assert (tmp_path / "afile.txt").read_text() == "kept\n" and not any((tmp_path / "DIR").iterdir())
    assert cli.main(["model", "show", str(model), "--png", str(tmp_path / "ok.PNG")]) == 0
    assert (tmp_path / "ok.PNG").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not (tmp_path / "ok.PNG.part").exists() and f"wrote {tmp_path / 'ok.PNG'}" in capsys.readouterr().out


@pytest.mark.parametrize("value", ["0", "-2", "true", '"3"'])
def test_n_families_must_be_a_count_of_at_least_one(capsys, tmp_path, model_files, value):
    """n_families = 0 was reported as "0 families requested but some harmonic index has only 5
    solutions"."""
    from bttsim_stream.errors import ModelFileError
    from bttsim_stream.model.cyclic import expand_sector, load_sector

    sector, _ = model_files
    (tmp_path / "o.toml").write_text(f"n_families = {value}\n")
    err = _error(capsys, "model", "import", str(sector), "--options", str(tmp_path / "o.toml"),
                 "--out", str(tmp_path / "m.npz"))
    assert "n_families must be an integer >= 1 (families kept per nodal diameter)" in err, err
    assert not (tmp_path / "m.npz").exists()
    with pytest.raises(ModelFileError, match=r"^n_families must be >= 1 \(families kept per nodal diameter\), got 0$"):
        expand_sector(load_sector(sector), n_families=0)


@pytest.mark.parametrize("key,value,words", [
    ("nominal_node", "x", "meta.nominal_node must be a tip node index, got 'x'"),
    ("nominal_node", None, "meta.nominal_node must be a tip node index, got None"),
    ("stagger_deg", "abc", "meta.stagger_deg must be a number of degrees, got 'abc'"),
    ("provenance", [1], "meta.provenance must be a JSON object"),
], ids=["nominal-text", "nominal-null", "stagger-text", "provenance-list"])
def test_a_forged_sector_meta_is_one_line(capsys, tmp_path, model_files, key, value, words):
    """Meta values of the wrong type ended in int() / float() / dict() tracebacks."""
    sector, _ = model_files
    bad = _sector_with(sector, tmp_path / "bad.npz", {key: value})
    assert f"{bad}: {words}" in _error(capsys, "model", "import", str(bad), "--out", str(tmp_path / "m.npz"))
    assert not (tmp_path / "m.npz").exists()

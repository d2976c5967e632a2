"""bttsim ingest: export folders and unlabelled pulse trains in, against the simulator's own
labelled TOAs (a short run-up through the EO 8 resonance near 2580 rpm)."""

import json
import math
import time
from pathlib import Path

import numpy as np
import pytest

from bttsim_stream.bus.recording import read_recording
from bttsim_stream.cli import main
from bttsim_stream.errors import BttsimError
from bttsim_stream.export import export_run
from bttsim_stream.ingest import ingest_export, ingest_pulses, read_times
from bttsim_stream.offline import load_run
from bttsim_stream.process.displacement import Geometry
from bttsim_stream.process.identify import identify_pulses
from bttsim_stream.process.pipeline import ProcessOptions, process_arrays
from bttsim_stream.acquisition import simulate_to_mcap
from bttsim_stream.scenario import load_scenario

SHORT = """[speed]
start_rpm = 2400.0
end_rpm = 2700.0
duration_s = 6.0
"""


def _process(path):
    run = load_run(path)
    res = process_arrays(run.opr_s, run.toa_s, run.meta, ProcessOptions(), truth=run.truth,
                         revolution0=int(run.revolution[0]))
    return run, res.summary


def _blades(summary, key):
    return np.array([b[key] for b in summary["resonances"][0]["blades"]], dtype=float)


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    d = tmp_path_factory.mktemp("ingest")
    (d / "short.toml").write_text(SHORT)
    simulate_to_mcap(load_scenario(d / "short.toml"), d / "sim.mcap")
    run, summary = _process(d / "sim.mcap")
    return {"dir": d, "mcap": d / "sim.mcap", "run": run, "summary": summary}


def _trains(sim, out: Path, *, drop=0.0, extra=0.0, seed=0, scale=1.0):
    """Pulse trains as a rig gives them: labels dropped, sorted per probe (CSV, header line)."""
    run = sim["run"]
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    np.savetxt(out / "opr.csv", run.opr_s * scale, fmt="%.17g", header="opr_s", comments="")
    args, injected = ["--opr", str(out / "opr.csv")], {"dropped": 0, "extra": 0}
    for j, a in enumerate(np.rad2deg(run.meta.probe_angles_rad)):
        t = run.toa_s[:, :, j].ravel()
        gone = rng.random(t.size) < drop
        fake = rng.uniform(run.opr_s[0], t.max(), int(round(extra * t.size)))
        np.savetxt(out / f"p{j}.csv", np.sort(np.r_[t[~gone], fake]) * scale, fmt="%.17g", header="toa_s",
                   comments="")
        args += ["--probe", f"{float(a)!r}={out / f'p{j}.csv'}"]
        injected["dropped"] += int(gone.sum())
        injected["extra"] += int(fake.size)
    return args, injected


# -- identification ----------------------------------------------------------------------

def test_identify_gives_the_simulator_labels(sim):
    run = sim["run"]
    psi = Geometry.from_info(run.meta).nominal_arrival_angles()  # nominal blade angles, calibrated on the data
    for j in range(run.meta.n_probes):
        got = identify_pulses(run.opr_s, np.sort(run.toa_s[:, :, j].ravel()), psi[:, j])
        np.testing.assert_array_equal(got.toa_s, run.toa_s[:, :, j])
        assert (got.missing, got.extra, got.stray, got.outside) == (0, 0, 0, 0)


def test_identify_counts_every_dropped_and_extra_pulse(sim):
    run = sim["run"]
    psi = Geometry.from_info(run.meta).nominal_arrival_angles()
    rng = np.random.default_rng(7)
    t = run.toa_s[:, :, 2].ravel()  # probe 2: a blade crosses it 0.9 deg after the OPR pulse
    gone = rng.random(t.size) < 0.02
    near = t[~gone][rng.choice((~gone).sum(), 20, replace=False)] + 2e-6  # double triggers
    fake = rng.uniform(run.opr_s[0], t.max(), 30)
    got = identify_pulses(run.opr_s, np.r_[t[~gone], near, fake], psi[:, 2])
    assert got.missing == gone.sum()
    assert got.extra + got.stray == near.size + fake.size
    assert np.isin(near, got.extra_toa_s).all()
    kept = np.isfinite(got.toa_s)
    np.testing.assert_array_equal(got.toa_s[kept], run.toa_s[:, :, 2][kept])


FLUCTUATING = """[speed]
start_rpm = 2400.0
segments = [{duration_s = 0.3, end_rpm = 2500.0}, {duration_s = 0.3, end_rpm = 2380.0},
            {duration_s = 0.3, end_rpm = 2520.0}, {duration_s = 0.3, end_rpm = 2400.0},
            {duration_s = 0.3, end_rpm = 2550.0}, {duration_s = 0.3, end_rpm = 2450.0}]
"""


def test_identify_follows_speed_fluctuation(tmp_path):
    # +-400 rpm/s reversing every 0.3 s: the OPR model's kinks are common to neighbouring blades
    (tmp_path / "f.toml").write_text(FLUCTUATING)
    simulate_to_mcap(load_scenario(tmp_path / "f.toml"), tmp_path / "f.mcap", include_truth=False)
    run = load_run(tmp_path / "f.mcap")
    psi = Geometry.from_info(run.meta).nominal_arrival_angles()
    rng = np.random.default_rng(0)
    for j in range(run.meta.n_probes):
        t = run.toa_s[:, :, j].ravel()
        got = identify_pulses(run.opr_s, np.sort(t), psi[:, j])
        np.testing.assert_array_equal(got.toa_s, run.toa_s[:, :, j])
        gone = rng.random(t.size) < 0.01
        fake = rng.uniform(run.opr_s[0], t.max(), 30)
        got = identify_pulses(run.opr_s, np.r_[t[~gone], fake], psi[:, j])
        assert (got.missing, got.extra + got.stray) == (gone.sum(), fake.size)


# -- from an export --------------------------------------------------------------------

@pytest.mark.parametrize("fmt", ["csv", "parquet"], ids=["csv", "parquet"])
def test_from_export_same_toas_and_results(sim, tmp_path, fmt):
    export_run(sim["mcap"], tmp_path / "exp", fmt)
    out = tmp_path / "in.mcap"
    assert main(["ingest", "--from-export", str(tmp_path / "exp"), "--out", str(out)]) == 0
    run, summary = _process(out)
    orig = sim["run"]
    assert run.meta.has_truth is False and run.truth is None
    np.testing.assert_array_equal(run.toa_s.view(np.int64), orig.toa_s.view(np.int64))  # to the bit
    np.testing.assert_array_equal(run.opr_s, orig.opr_s)
    for key in ("amp_pkpk_m", "freq_hz", "phase_rad"):
        np.testing.assert_array_equal(_blades(summary, key), _blades(sim["summary"], key))
    assert "truth_amp_pkpk_m" not in summary["resonances"][0]["blades"][0]
    rec = read_recording(out).run_metadata
    assert json.loads(rec["source"])["kind"] == "export"
    assert json.loads(rec["ingest"])["toas"] == orig.toa_s.size


# -- from pulse trains -----------------------------------------------------------------

def test_pulse_trains_give_the_original_amplitudes(sim, tmp_path, capsys):
    args, _ = _trains(sim, tmp_path / "t")
    out = tmp_path / "rig.mcap"
    t0 = time.perf_counter()
    assert main(["ingest", *args, "--blades", "29", "--tip-radius-m", "0.19010353787923925", "--eo", "8",
                 "--out", str(out)]) == 0
    rate = sim["run"].toa_s.size / (time.perf_counter() - t0)
    print(f"ingest rate {rate:.3g} TOA/s", file=__import__("sys").stderr)
    run, summary = _process(out)
    np.testing.assert_array_equal(run.toa_s, sim["run"].toa_s)
    err = np.abs(_blades(summary, "amp_pkpk_m") / _blades(sim["summary"], "amp_pkpk_m") - 1)
    assert err.max() < 0.002
    assert "0 missing, 0 extra, 0 stray" in capsys.readouterr().out


def test_pulse_trains_with_dropped_and_extra_pulses(sim, tmp_path):
    args, injected = _trains(sim, tmp_path / "t", drop=0.01, extra=0.001, seed=3)
    out = tmp_path / "rig.mcap"
    res = ingest_pulses(args[1], [(float(a.split("=")[0]), a.split("=", 1)[1]) for a in args[3::2]], out,
                        n_blades=29, tip_radius_m=0.19010353787923925, engine_orders=(8,))
    assert res.missing == injected["dropped"]
    assert res.extra + res.stray == injected["extra"]
    assert res.outside == 0
    run, summary = _process(out)
    err = np.abs(_blades(summary, "amp_pkpk_m") / _blades(sim["summary"], "amp_pkpk_m") - 1)
    assert err.max() < 0.03 and err.mean() < 0.01
    counts = json.loads(read_recording(out).run_metadata["ingest"])
    assert (counts["missing"], counts["extra"] + counts["stray"]) == (injected["dropped"], injected["extra"])


def test_pulse_trains_with_a_scenario(sim, tmp_path):
    args, _ = _trains(sim, tmp_path / "t")
    out = tmp_path / "rig.mcap"
    assert main(["ingest", *args, "--scenario", str(sim["dir"] / "short.toml"), "--out", str(out)]) == 0
    run, summary = _process(out)
    assert run.meta.n_blades == 29 and run.meta.engine_orders == (8,)
    np.testing.assert_allclose(_blades(summary, "amp_pkpk_m"), _blades(sim["summary"], "amp_pkpk_m"), rtol=2e-3)


def test_windows_and_blocks_change_nothing(sim, tmp_path, monkeypatch):
    """Identification in windows of revolutions and reading in small blocks (a CSV block
    boundary inside a line, Parquet batches and windows ending inside revolutions) give the
    recording byte for byte; with a short calibration span the TOAs and counts are those of
    the whole-array :func:`identify_pulses`."""
    import bttsim_stream.ingest as ingest_mod
    import bttsim_stream.process.identify as identify_mod
    import bttsim_stream.timefiles as timefiles_mod

    pa = pytest.importorskip("pyarrow")
    import pyarrow.parquet as pq

    args, _ = _trains(sim, tmp_path / "t", drop=0.01, extra=0.002, seed=11)
    p1 = Path(args[5].split("=", 1)[1])  # one probe as Parquet
    pq.write_table(pa.table({"toa_s": np.loadtxt(p1, skiprows=1)}), tmp_path / "p1.parquet")
    args[5] = args[5].split("=")[0] + f"={tmp_path / 'p1.parquet'}"
    flags = ["--blades", "29", "--tip-radius-m", "0.19010353787923925", "--eo", "8"]

    def ingest(name):
        assert main(["ingest", *args, *flags, "--out", str(tmp_path / name)]) == 0
        return (tmp_path / name).read_bytes()

    whole = ingest("whole.mcap")
    monkeypatch.setattr(ingest_mod, "_CHUNK_REVS", 7)
    monkeypatch.setattr(timefiles_mod, "_BLOCK_BYTES", 997)
    monkeypatch.setattr(timefiles_mod, "_PARQUET_ROWS", 1000)
    assert ingest("small.mcap") == whole
    monkeypatch.setattr(identify_mod, "CALIBRATION_REVOLUTIONS", 40)
    ingest("cal40.mcap")
    got = load_run(tmp_path / "cal40.mcap")
    counts = json.loads(read_recording(tmp_path / "cal40.mcap").run_metadata["ingest"])
    opr = read_times(args[1])
    psi = Geometry.from_info(got.meta).nominal_arrival_angles()
    lo = json.loads(read_recording(tmp_path / "cal40.mcap").run_metadata["source"])["first_opr_pulse"]
    for j in range(got.meta.n_probes):
        ref = identify_pulses(opr, read_times(args[3 + 2 * j].split("=", 1)[1]), psi[:, j])
        np.testing.assert_array_equal(got.toa_s[:, :, j], ref.toa_s[lo:lo + got.toa_s.shape[0]])
        row = counts["per_probe"][j]
        assert (row["missing"], row["extra"], row["stray"]) == (ref.missing, ref.extra, ref.stray)


def test_pulses_beyond_the_opr_file_are_outside(sim, tmp_path):
    """A probe recorded long before and after the OPR file: those pulses count as outside
    and change nothing else (they are counted, not read into the identification)."""
    args, _ = _trains(sim, tmp_path / "t", drop=0.01, extra=0.001, seed=2)
    flags = ["--blades", "29", "--tip-radius-m", "0.19", "--eo", "8"]
    assert main(["ingest", *args, *flags, "--out", str(tmp_path / "a.mcap")]) == 0
    p0 = Path(args[3].split("=", 1)[1])
    t, opr = np.loadtxt(p0, skiprows=1), sim["run"].opr_s
    np.savetxt(p0, np.r_[opr[0] - np.arange(500, 0, -1) * 1e-4, t, opr[-1] + 1.0 + np.arange(2000) * 1e-3],
               fmt="%.17g")
    assert main(["ingest", *args, *flags, "--out", str(tmp_path / "b.mcap")]) == 0
    a, b = (json.loads(read_recording(tmp_path / f).run_metadata["ingest"]) for f in ("a.mcap", "b.mcap"))
    assert b["per_probe"][0]["outside"] == a["per_probe"][0]["outside"] + 2500
    assert {k: v for k, v in a.items() if k not in ("outside", "per_probe")} == \
        {k: v for k, v in b.items() if k not in ("outside", "per_probe")}
    np.testing.assert_array_equal(load_run(tmp_path / "a.mcap").toa_s, load_run(tmp_path / "b.mcap").toa_s)


# -- reading ---------------------------------------------------------------------------

def test_read_times_formats(tmp_path):
    (tmp_path / "a.csv").write_text("# rig 3\nchannel;toa_s\n1;0.5\n2;0.75\n3;1.0\n")
    np.testing.assert_array_equal(read_times(tmp_path / "a.csv", "toa_s"), [0.5, 0.75, 1.0])
    (tmp_path / "b.txt").write_text("0.1\n\n# pause\n0.2\n\n\n")
    np.testing.assert_array_equal(read_times(tmp_path / "b.txt"), [0.1, 0.2])
    (tmp_path / "c.txt").write_text("t\n0.1\n\n0.3\n0.2\n")  # line numbers count every line
    with pytest.raises(BttsimError, match="line 5: time 0.2 s is not after the previous one"):
        read_times(tmp_path / "c.txt")
    (tmp_path / "d.txt").write_text("t\n0.1\n0,2\n")
    with pytest.raises(BttsimError, match="line 3: not a time in s: '0,2'"):
        read_times(tmp_path / "d.txt")
    pa = pytest.importorskip("pyarrow")
    import pyarrow.parquet as pq

    pq.write_table(pa.table({"t": [0.1, 0.2, 0.3], "x": [1, 2, 3]}), tmp_path / "c.parquet")
    np.testing.assert_array_equal(read_times(tmp_path / "c.parquet"), [0.1, 0.2, 0.3])


# -- bad data: one line, exit 2, nothing written ---------------------------------------------

def _bad(sim, tmp_path, case):
    args, _ = _trains(sim, tmp_path / "t", scale=1000.0 if case == "ms" else 1.0)
    blades = "29"
    p0 = Path(args[3].split("=", 1)[1])
    if case == "empty":
        p0.write_text("")
    elif case == "non_monotonic":
        t = np.loadtxt(p0, skiprows=1)
        t[[100, 101]] = t[[101, 100]]
        np.savetxt(p0, t, fmt="%.17g")
    elif case == "no_opr":
        args = args[2:]
    elif case == "one_opr":
        (tmp_path / "t" / "opr.csv").write_text("opr_s\n0.1\n")
    elif case == "blades":
        blades = "31"
    elif case == "nan":
        t = np.loadtxt(p0, skiprows=1)
        t[500] = np.nan
        np.savetxt(p0, t, fmt="%.17g")
    elif case == "garbage":
        p0.write_bytes(np.random.default_rng(0).bytes(20 << 20))
    return [*args, "--blades", blades, "--tip-radius-m", "0.19"]


@pytest.mark.parametrize("case, words", [
    ("empty", "no times"), ("non_monotonic", "must increase"), ("no_opr", "--opr"), ("one_opr", "at least 3"),
    ("blades", "median 29 pulses per revolution"), ("ms", "times in ms"), ("nan", "line 501: nan"),
    ("garbage", "not a text CSV")],
    ids=["empty", "non_monotonic", "no_opr", "one_opr", "blades", "ms", "nan", "garbage"])
def test_bad_input_one_line_exit_2(sim, tmp_path, capsys, case, words):
    out = tmp_path / "out.mcap"
    out.write_bytes(b"keep me")  # an earlier result is not lost
    assert main(["ingest", *_bad(sim, tmp_path, case), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("bttsim: error: ") and err.count("\n") == 1 and words in err, err
    assert "Traceback" not in err
    assert out.read_bytes() == b"keep me"
    assert not list(tmp_path.glob(".out.mcap*"))  # neither the partial recording nor the spilled pulses


@pytest.mark.slow
def test_a_2_gb_garbage_file_in_bounded_memory(sim, tmp_path):
    """A 2 GB file (sparse: NUL bytes, no line end) given as a probe: one line, exit 2, in a
    fresh process whose peak resident memory stays far below the file's size."""
    import subprocess
    import sys

    args, _ = _trains(sim, tmp_path / "t")
    big = tmp_path / "big.csv"
    with open(big, "wb") as fh:
        fh.truncate(2 << 30)
    args[3] = args[3].split("=")[0] + f"={big}"
    # the child's own peak (VmHWM of its address space): ru_maxrss would carry the parent's
    # across fork and exec (a test process of several hundred MB)
    code = ("import sys; from bttsim_stream.cli import main; rc = main(sys.argv[1:]); "
            "print(next(ln.split()[1] for ln in open('/proc/self/status') if ln.startswith('VmHWM:'))); "
            "sys.exit(rc)")
    res = subprocess.run([sys.executable, "-c", code, "ingest", *args, "--blades", "29", "--tip-radius-m", "0.19",
                          "--out", str(tmp_path / "o.mcap")], capture_output=True, text=True, timeout=600)
    assert res.returncode == 2 and res.stderr.count("\n") == 1 and "not a CSV of times" in res.stderr, res.stderr
    assert int(res.stdout) < 300 * 1024, res.stdout  # KiB: the file is 2048 MiB
    assert not (tmp_path / "o.mcap").exists()


def test_export_folder_errors(sim, tmp_path):
    with pytest.raises(BttsimError, match="no run.json"):
        ingest_export(tmp_path, tmp_path / "x.mcap")
    export_run(sim["mcap"], tmp_path / "exp", "csv")
    with open(tmp_path / "exp" / "toa.csv", "wb") as fh:  # 2 GB of NUL bytes, sparse: fails at its first block
        fh.truncate(2 << 30)
    with pytest.raises(BttsimError, match="toa.csv: .*longer than 64 KiB: not a CSV of numbers"):
        ingest_export(tmp_path / "exp", tmp_path / "x.mcap")


def _edit_csv(path: Path, row: int, column: str, value: str | None) -> None:
    """Set ``column`` of data row ``row`` of a CSV table (None: repeat that row)."""
    lines = path.read_text().splitlines()
    if value is None:
        lines.insert(row + 1, lines[row + 1])
    else:
        parts = lines[row + 1].split(",")
        parts[lines[0].split(",").index(column)] = value
        lines[row + 1] = ",".join(parts)
    path.write_text("\n".join(lines) + "\n")


_RUN_JSON_EDITS = {
    "run is a list": (lambda d: d.__setitem__("run", [1, 2]), 'no "run" object'),
    "file is a list": (lambda d: [1, 2, 3], 'no "run" object'),
    "tables is a list": (lambda d: d.__setitem__("tables", ["opr", "toa"]), '"tables" must map'),
    "a table without file": (lambda d: d["tables"].__setitem__("opr", {}), '"tables" must map'),
    "n_blades a string": (lambda d: d["run"].__setitem__("n_blades", "29"), "n_blades must be an integer"),
    "n_blades fractional": (lambda d: d["run"].__setitem__("n_blades", 29.5), "n_blades must be an integer"),
    "angles not numbers": (lambda d: d["run"].__setitem__("probe_angles_rad", "abc"), "could not convert"),
    "engine_orders a number": (lambda d: d["run"].__setitem__("engine_orders", 8), "not iterable"),
    "scenario_toml a number": (lambda d: d["run"].__setitem__("scenario_toml", 5), "must be a string"),
    "tip radius NaN": (lambda d: d["run"].__setitem__("tip_radius_m", math.nan), "tip_radius_m = nan"),
    "negative duration": (lambda d: d["run"].__setitem__("duration_s", -5.0), "duration_s = -5.0"),
    "fewer revolutions than the tables": (lambda d: d["run"].__setitem__("n_revolutions", 10),
                                          "but the run has 10 revolution(s)"),
}
_TABLE_EDITS = {
    "NaN OPR time": ("opr.csv", 4, "opr_s", "nan", "column opr_s must hold finite numbers"),
    "OPR time going back": ("opr.csv", 5, "opr_s", "0.0", "OPR times must increase"),
    "a TOA of 1e300": ("toa.csv", 6, "toa_s", "1e300", "not within a revolution of their OPR pulse"),
    "a TOA row twice": ("toa.csv", 6, "toa_s", None, "repeat a (revolution, blade, probe)"),
    "a fractional blade": ("toa.csv", 6, "blade", "2.5", "column blade must hold integers"),
    "a blade that is text": ("toa.csv", 6, "blade", "x", "line 8: not a number"),
}


@pytest.mark.parametrize("case", list(_RUN_JSON_EDITS) + list(_TABLE_EDITS))
def test_a_hand_edited_export_is_refused_before_anything_is_written(sim, tmp_path, capsys, case):
    """What the readers of a recording refuse (``process``, ``export``, ``view``), ingest
    refuses before writing it; a run.json of other shapes or types is one line too."""
    export_run(sim["mcap"], tmp_path / "exp", "csv")
    if case in _RUN_JSON_EDITS:
        edit, words = _RUN_JSON_EDITS[case]
        doc = json.loads((tmp_path / "exp" / "run.json").read_text())
        got = edit(doc)
        (tmp_path / "exp" / "run.json").write_text(json.dumps(doc if got is None else got))
    else:
        table, row, column, value, words = _TABLE_EDITS[case]
        _edit_csv(tmp_path / "exp" / table, row, column, value)
    capsys.readouterr()
    assert main(["ingest", "--from-export", str(tmp_path / "exp"), "--out", str(tmp_path / "x.mcap")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("bttsim: error:") and words in err[0], err
    assert not (tmp_path / "x.mcap").exists()


def test_cli_flag_and_output_errors(sim, tmp_path, capsys):
    args, _ = _trains(sim, tmp_path / "t")
    cases = [
        ([*args, "--blades", "29", "--tip-radius-m", "0.19", "--out", str(tmp_path / "no" / "x.mcap")], "no folder"),
        ([*args, "--blades", "29", "--out", str(tmp_path / "x.mcap")], "--tip-radius-m R are required"),
        ([*args, "--blades", "29", "--tip-radius-m", "190", "--out", str(tmp_path / "x.mcap")], "radius in m"),
        (["--opr", args[1], "--probe", "5:p.csv", "--blades", "29", "--tip-radius-m", "0.19",
          "--out", str(tmp_path / "x.mcap")], "ANGLE_DEG=FILE"),
        (["--from-export", str(tmp_path), *args, "--out", str(tmp_path / "x.mcap")], "takes no --opr"),
        ([*args, "--blades", "29", "--tip-radius-m", "0.19", "--out", args[3].partition("=")[2]],
         "that is the input"),
        ([*args, "--blades", "29", "--tip-radius-m", "0.19", "--out", args[1]], "that is the input"),
    ]
    export_run(sim["mcap"], tmp_path / "exp", "csv")
    cases.append((["--from-export", str(tmp_path / "exp"), "--out", str(tmp_path / "exp" / "toa.csv")],
                  "that is the input"))
    inputs = {p: p.read_bytes() for p in [*(tmp_path / "t").iterdir(), tmp_path / "exp" / "toa.csv"]}
    for argv, words in cases:
        assert main(["ingest", *argv]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and words in err, err
    assert not (tmp_path / "x.mcap").exists()
    assert all(p.read_bytes() == data for p, data in inputs.items())  # no input overwritten
    for _ in range(2):  # a file of its own beside the export's: written, and written again
        assert main(["ingest", "--from-export", str(tmp_path / "exp"), "--out", str(tmp_path / "exp" / "in.mcap")]) == 0


# -- raw probe signals -------------------------------------------------------------------

def _signal_traces(mcap: Path, out: Path, fill=np.nan):
    """Each probe's voltage trace rebuilt from the recording's SignalBatch windows
    (``range_lo_v + code * lsb_v`` at samples ``first_sample ..``), from one common first
    sample; ``fill`` where no window was recorded. Returns the files, the first sample's
    index, the sample rate and the published (missing, double) counts."""
    from bttsim_stream.bus import codec

    per = {}
    for m in read_recording(mcap).messages:
        if "/signal/" in m.key:
            b = codec.decode_message(m.key, m.payload).body
            per.setdefault(b.probe, []).append(b)
    k0 = min(int(b.first_sample.min()) for bs in per.values() for b in bs)
    files, missing, double = [], 0, 0
    for j, bs in sorted(per.items()):
        first = np.concatenate([b.first_sample for b in bs])
        n = np.concatenate([b.n_samples for b in bs])
        edges = np.concatenate([b.n_edges for b in bs])
        missing += int((edges == 0).sum())
        double += int(np.maximum(edges - 1, 0).sum())
        y = np.full(int((first + n).max()) - k0, fill)
        idx = np.repeat(first - k0, n) + np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)
        assert np.unique(idx).size == idx.size  # the windows do not overlap
        y[idx] = bs[0].range_lo_v + np.concatenate([b.codes for b in bs]) * bs[0].lsb_v
        np.save(out / f"signal{j}.npy", y)
        files.append(out / f"signal{j}.npy")
    return files, k0, bs[0].sample_rate_hz, missing, double


SIGNAL_CASES = {
    # the example itself (constant fraction, ~1 % of the pulses do not arm it), shortened
    "constant_fraction": "",
    # a noisy threshold trigger: double pulses and missing ones
    "threshold": 'hysteresis_v = 0.01\n',
}
_THRESHOLD = {'trigger = "constant_fraction"': 'trigger = "threshold"', "noise_v = 0.01": "noise_v = 0.015"}


@pytest.fixture(scope="module", params=list(SIGNAL_CASES), ids=list(SIGNAL_CASES))
def signal_run(request, tmp_path_factory):
    d = tmp_path_factory.mktemp(f"signal_{request.param}")
    text = Path(__file__).resolve().parents[1].joinpath("examples", "signal_chain.toml").read_text()
    text = text.replace("[acquisition]\n", "[speed]\nstart_rpm = 2400.0\nend_rpm = 2700.0\nduration_s = 3.0\n\n"
                        "[acquisition]\n") + SIGNAL_CASES[request.param] + "publish = true\n"
    for a, b in (_THRESHOLD.items() if request.param == "threshold" else ()):
        text = text.replace(a, b)
    (d / "s.toml").write_text(text)
    simulate_to_mcap(load_scenario(d / "s.toml"), d / "sim.mcap", include_truth=False)
    files, k0, fs, missing, double = _signal_traces(d / "sim.mcap", d)
    run = load_run(d / "sim.mcap")
    np.savetxt(d / "opr.csv", run.opr_s, fmt="%.17g")
    return {"dir": d, "run": run, "files": files, "k0": k0, "fs": fs, "missing": missing, "double": double}


def test_raw_signals_give_the_published_toas(signal_run, capsys):
    """The simulator's windows, ingested as raw signals with the scenario's trigger and
    clock: the published TOAs to the bit, the same missing and double pulses."""
    s, d = signal_run, signal_run["dir"]
    args = ["ingest", "--opr", str(d / "opr.csv"), "--scenario", str(d / "s.toml"), "--out", str(d / "ing.mcap"),
            f"--signal-start-s={s['k0'] / s['fs']!r}"]
    files = list(s["files"])
    early = 54_321  # probe 1's digitiser started earlier (at 0 V): its own start time after '@'
    np.save(d / "early.npy", np.r_[np.zeros(early), np.load(files[1])])
    files[1] = f"{d / 'early.npy'}@{(s['k0'] - early) / s['fs']!r}"
    for a, f in zip(np.rad2deg(s["run"].meta.probe_angles_rad), files):
        args += ["--signal", f"{float(a)!r}={f}"]
    main(args)
    counts = json.loads(read_recording(d / "ing.mcap").metadata["bttsim.run"]["ingest"])
    got = load_run(d / "ing.mcap")
    np.testing.assert_array_equal(got.toa_s, s["run"].toa_s)
    np.testing.assert_array_equal(got.opr_s, s["run"].opr_s)
    assert s["missing"] > 0 and (counts["missing"], counts["double"]) == (s["missing"], s["double"])
    assert (counts["extra"], counts["stray"], counts["outside"]) == (0, 0, 0)
    assert got.extra_edges["toa_s"].size == s["double"]
    np.testing.assert_array_equal(np.sort(got.extra_edges["toa_s"]), np.sort(s["run"].extra_edges["toa_s"]))
    assert "double edges" in capsys.readouterr().out


def test_raw_signals_in_blocks_and_continuous(signal_run, monkeypatch):
    """Reading in small blocks changes nothing; a continuous trace (the gaps at 0 V) gives
    the threshold trigger's TOAs too (its state needs no window)."""
    import bttsim_stream.timefiles as timefiles_mod
    from bttsim_stream.ingest import SignalOptions, read_signal_pulses

    s = signal_run
    scn = load_scenario(s["dir"] / "s.toml")
    opt = SignalOptions(start_s=s["k0"] / s["fs"]).resolve(s["dir"] / "s.toml")
    hold = 0.25 * 60.0 / 2400.0 / 29
    whole = read_signal_pulses(s["files"][2], opt.trigger_of(2), opt, hold)
    monkeypatch.setattr(timefiles_mod, "_SIGNAL_BLOCK", 4099)
    small = read_signal_pulses(s["files"][2], opt.trigger_of(2), opt, hold)
    for a, b in zip(whole, small):
        np.testing.assert_array_equal(a, b)
    y = np.load(s["files"][2])[:300_000]  # volts as a one-column CSV: the same pulses as the .npy
    np.save(s["dir"] / "part.npy", y)
    np.savetxt(s["dir"] / "part.csv", y, fmt="%.17g", header="volts", comments="")
    for a, b in zip(read_signal_pulses(s["dir"] / "part.npy", opt.trigger_of(2), opt, hold),
                    read_signal_pulses(s["dir"] / "part.csv", opt.trigger_of(2), opt, hold)):
        np.testing.assert_array_equal(a, b)
    if scn.acquisition.signal.trigger == "threshold":
        y = np.load(s["files"][2])
        np.save(s["dir"] / "cont.npy", np.where(np.isnan(y), 0.0, y))
        cont = read_signal_pulses(s["dir"] / "cont.npy", opt.trigger_of(2), opt, hold)
        for a, b in zip(whole[:3], cont[:3]):
            np.testing.assert_array_equal(a, b)


def test_raw_signal_errors(sim, tmp_path, capsys):
    np.savetxt(tmp_path / "opr.csv", sim["run"].opr_s)
    np.save(tmp_path / "flat.npy", np.zeros(1000))
    np.save(tmp_path / "two.npy", np.zeros((10, 3)))
    (tmp_path / "two.csv").write_text("t,v\n0,0.1\n1e-6,0.2\n")
    base = ["ingest", "--opr", str(tmp_path / "opr.csv"), "--blades", "29", "--tip-radius-m", "0.19",
            "--sample-rate", "2e6", "--out", str(tmp_path / "o.mcap")]
    for extra, words in [(["--signal", f"5={tmp_path / 'flat.npy'}"], "no pulse reaches"),
                         (["--signal", f"5={tmp_path / 'two.npy'}"], "1-D array"),
                         (["--signal", f"5={tmp_path / 'none.npy'}"], "no such file"),
                         (["--signal", f"5={tmp_path / 'flat.npy'}", "--trigger", "edge"], "--trigger"),
                         (["--signal", "five"], "--signal must be"),
                         (["--signal", f"5={tmp_path / 'flat.npy'}@soon"], "must be a time in s"),
                         (["--signal", f"5={tmp_path / 'two.csv'}"], "holds one column")]:
        assert main(base + extra) == 2
        err = capsys.readouterr().err.strip()
        assert words in err and "\n" not in err, err
    assert not (tmp_path / "o.mcap").exists()


# -- shaft encoder -------------------------------------------------------------------------

@pytest.mark.parametrize("wheel", ["missing_tooth", "index"], ids=["missing-tooth", "index"])
def test_encoder_train_gives_the_opr_and_a_better_angle(tmp_path, wheel):
    """A 36-pulse encoder from the shaft angle of a run with speed fluctuation: the OPR
    recovered, the blade labels unchanged, the rotor angle at the TOAs 10x closer to the
    truth than the OPR-only model's."""
    from bttsim_stream.process.identify import encoder_revolutions, shaft_angle
    from bttsim_stream.sim.speed import speed_profile_from_scenario

    (tmp_path / "f.toml").write_text(FLUCTUATING)
    scn = load_scenario(tmp_path / "f.toml")
    simulate_to_mcap(scn, tmp_path / "f.mcap", include_truth=False)
    run = load_run(tmp_path / "f.mcap")
    prof = speed_profile_from_scenario(scn)
    k = 36
    base = prof.angle(run.opr_s[0])
    tooth = np.arange(-5, k * run.opr_s.size)
    enc = prof.time_at_angle(base + 2 * np.pi * tooth / k)
    enc = enc[enc < prof.duration_s]
    if wheel == "missing_tooth":
        enc_file, index = enc[(tooth[:enc.size] % k) != k - 1], None
    else:
        enc_file, index = enc, 5
    er = encoder_revolutions(enc_file, k, index)
    n = min(er.opr_s.size, run.opr_s.size)
    np.testing.assert_allclose(er.opr_s[:n], run.opr_s[:n], rtol=0, atol=1e-12)
    t = run.toa_s[1:-2].ravel()
    truth = prof.angle(t) - base
    err_opr = np.abs(shaft_angle(run.opr_s, t) - truth).max()
    err_enc = np.abs(shaft_angle(er.opr_s, t, er) - truth).max()
    assert err_enc < 0.1 * err_opr, (err_enc, err_opr)
    psi = Geometry.from_info(run.meta).nominal_arrival_angles()
    got = identify_pulses(er.opr_s, np.sort(run.toa_s[:n - 1, :, 1].ravel()), psi[:, 1], encoder=er)
    np.testing.assert_array_equal(got.toa_s[:n - 1], run.toa_s[:n - 1, :, 1])
    np.savetxt(tmp_path / "enc.csv", enc_file, fmt="%.17g")
    np.savetxt(tmp_path / "p1.csv", np.sort(run.toa_s[:, :, 1].ravel()), fmt="%.17g")
    res = ingest_pulses(tmp_path / "enc.csv", [(np.rad2deg(run.meta.probe_angles_rad[1]), tmp_path / "p1.csv")],
                        tmp_path / "e.mcap", scenario_path=tmp_path / "f.toml", encoder_pulses=k,
                        encoder_index=index)
    assert res.missing == 0 and res.extra + res.stray == 0 and "encoder" in res.notes[-1]


def test_encoder_errors():
    from bttsim_stream.process.identify import encoder_revolutions

    even = np.arange(200) * 1e-3
    with pytest.raises(ValueError, match="no missing-tooth gap"):
        encoder_revolutions(even, 10)
    with pytest.raises(ValueError, match="encoder pulses missing"):
        encoder_revolutions(np.delete(even, 50), 10, index=0)
    gappy = np.delete(even, np.arange(9, 200, 10))
    with pytest.raises(ValueError, match="tooth positions"):
        encoder_revolutions(gappy, 12)
    assert encoder_revolutions(gappy, 10).opr_s.size == 19  # pulse 0: the first after a gap


# -- replay onto Zenoh -------------------------------------------------------------------

@pytest.mark.integration
def test_replay_of_an_ingested_run_to_the_live_processor(sim, tmp_path):
    """``bttsim replay`` of an ingested recording, the processor node subscribing on
    loopback: the same per-blade results as ``bttsim process`` of the file."""
    import subprocess
    import sys

    sys.path.insert(0, str(Path(__file__).parent))
    from _procs import start, stop
    from bttsim_stream.testing import free_port

    args, _ = _trains(sim, tmp_path / "t", drop=0.01, extra=0.001, seed=5)
    rig = tmp_path / "rig.mcap"
    assert main(["ingest", *args, "--blades", "29", "--tip-radius-m", "0.190104", "--eo", "8", "--out", str(rig)]) == 0
    assert main(["process", str(rig), "--summary", str(tmp_path / "offline.json")]) == 0
    port = free_port()
    live_path = tmp_path / "live.json"
    proc = start("bttsim_stream.nodes.processor_node", "--rig", "rig1", "--no-score", "--summary", live_path,
                 "-l", f"tcp/127.0.0.1:{port}")
    try:  # the replay waits for the processor's subscriptions, then for its done token
        rep = subprocess.run([sys.executable, "-m", "bttsim_stream.cli", "replay", str(rig), "--rate", "max",
                              "--wait", "120", "-e", f"tcp/127.0.0.1:{port}"], cwd=Path(__file__).parents[1],
                             capture_output=True, text=True, timeout=300)
        assert rep.returncode == 0, rep.stderr
        _, err = proc.communicate(timeout=120)
        assert proc.returncode == 0, err
    finally:
        stop(proc)
    live, offline = json.loads(live_path.read_text()), json.loads((tmp_path / "offline.json").read_text())
    assert live["status"] == offline["status"] == "resonance"
    for key in ("amp_pkpk_m", "freq_hz"):
        np.testing.assert_allclose(_blades(live, key), _blades(offline, key), rtol=1e-9)
    assert live["revolutions_processed"] == offline["revolutions_processed"]

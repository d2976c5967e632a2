"""`bttsim export`: tidy CSV / Parquet tables read back with no project code, against the
recording (read with the project's reader), the simulator's own ground truth and `bttsim process`."""

import csv
import json
import sys

import numpy as np
import pytest

from bttsim_stream.cli import main
from bttsim_stream.export import read_tables
from bttsim_stream.offline import load_run
from bttsim_stream.process.pipeline import ProcessOptions, process_arrays
from bttsim_stream.scenario import load_scenario
from bttsim_stream.sim.core import RunUpSimulator, collect

# 4 s through the default rotor's EO 8 resonance, a 125 MHz clock and trigger jitter: the TOAs
# differ from the truth's, so a column swap would show
SCENARIO = """
[speed]
start_rpm = 2450.0
end_rpm = 2700.0
duration_s = 4.0
[acquisition]
clock_hz = 125e6
trigger_jitter_s = 2e-8
"""


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    d = tmp_path_factory.mktemp("export")
    (d / "s.toml").write_text(SCENARIO)
    assert main(["simulate", str(d / "s.toml"), "--out", str(d / "run.mcap"), "-q"]) == 0
    return d


def _csv(path):
    """A CSV table with the standard library only: column -> list of str."""
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    return {name: [r[i] for r in rows[1:]] for i, name in enumerate(rows[0])}


def _num(col, dtype=float):
    return np.array([float("nan") if v == "NaN" else v for v in col], dtype=dtype)


@pytest.fixture(scope="module")
def exported_csv(recording):
    out = recording / "csv"
    assert main(["export", str(recording / "run.mcap"), "--out", str(out)]) == 0
    return out


def test_csv_round_trip_against_the_recording_and_the_simulator(recording, exported_csv):
    run = load_run(recording / "run.mcap")
    n_rev, n_b, n_p = run.toa_s.shape
    opr = _csv(exported_csv / "opr.csv")
    np.testing.assert_array_equal(_num(opr["revolution"], np.int64), run.revolution)
    np.testing.assert_array_equal(_num(opr["opr_s"]), run.opr_s)  # 17 digits: bit for bit
    toa = _csv(exported_csv / "toa.csv")
    assert len(toa["toa_s"]) == n_rev * n_b * n_p
    rev, blade, probe = (_num(toa[k], np.int64) for k in ("revolution", "blade", "probe"))
    grid = np.full((n_rev, n_b, n_p), np.nan)
    grid[rev - run.revolution[0], blade, probe] = _num(toa["toa_s"])
    np.testing.assert_array_equal(grid, run.toa_s)
    # the simulator itself, run again in this process: the recorded truth is its truth
    sim = collect(RunUpSimulator(load_scenario(recording / "s.toml")))
    truth = _csv(exported_csv / "truth.csv")
    for col, ref in (("truth_toa_s", sim.truth.toa_s), ("t_exp_s", sim.truth.t_exp_s),
                     ("d_eqv_m", sim.truth.d_eqv_m), ("d_z_m", sim.truth.d_z_m)):
        np.testing.assert_array_equal(_num(truth[col]).reshape(n_rev, n_b, n_p), ref, err_msg=col)
    np.testing.assert_array_equal(grid, sim.toa_s)  # acquisition TOAs (clock, jitter) as simulated
    assert np.max(np.abs(sim.toa_s - sim.truth.toa_s)) > 1e-9  # ... which are not the truth's
    tr = _csv(exported_csv / "truth_revolution.csv")
    np.testing.assert_array_equal(_num(tr["d_eqv_pkpk_m"]).reshape(n_rev, n_b), sim.truth.d_eqv_pkpk_m)


def test_csv_processing_tables_match_bttsim_process(recording, exported_csv):
    run = load_run(recording / "run.mcap")
    res = process_arrays(run.opr_s, run.toa_s, run.meta, ProcessOptions(), truth=run.truth)
    n_rev, n_b, n_p = run.toa_s.shape
    disp = _csv(exported_csv / "displacement.csv")
    np.testing.assert_array_equal(_num(disp["d_m"]).reshape(n_rev, n_b, n_p), res.displacements.d_m)
    fit = _csv(exported_csv / "fit.csv")
    assert set(fit["engine_order"]) == {"8"}
    np.testing.assert_array_equal(_num(fit["amp_pkpk_m"]).reshape(n_rev, n_b), res.fit.amp_pkpk_m[..., 0])
    tw = _csv(exported_csv / "tw.csv")
    np.testing.assert_array_equal(_num(tw["forward_m"]).reshape(res.fit_tw.forward_m.shape), res.fit_tw.forward_m)
    # the resonance table holds what `bttsim process --summary` reports
    assert main(["process", str(recording / "run.mcap"), "--summary", str(recording / "s.json")]) == 0
    summary = json.loads((recording / "s.json").read_text())
    rt = _csv(exported_csv / "resonance.csv")
    first = [i for i, e in enumerate(rt["entry"]) if e == "0"]
    assert len(first) == n_b and summary["status"] == "resonance"
    for i, row in zip(first, summary["resonances"][0]["blades"]):
        assert float(rt["amp_pkpk_m"][i]) == row["amp_pkpk_m"] and float(rt["E_A_pct"][i]) == row["E_A_pct"]
    assert rt["kind"][0] == "crossing" and int(rt["eo"][0]) == summary["resonances"][0]["eo"]
    doc = json.loads((exported_csv / "run.json").read_text())
    assert doc["summary"]["blades"] == summary["blades"]
    assert doc["run"]["n_blades"] == n_b and doc["tables"]["toa"]["columns"]["toa_s"]["unit"] == "s"
    for name, d in doc["tables"].items():  # every column documented
        assert all(c["description"] for c in d["columns"].values()), name


def test_parquet_round_trip_bit_for_bit(recording, exported_csv):
    pq = pytest.importorskip("pyarrow.parquet", reason="the parquet extra (pyarrow) is not installed")
    out = recording / "pq"
    assert main(["export", str(recording / "run.mcap"), "--format", "parquet", "--out", str(out)]) == 0
    doc = json.loads((out / "run.json").read_text())
    for name in doc["tables"]:
        tab = pq.read_table(out / f"{name}.parquet")
        ref = _csv(exported_csv / f"{name}.csv")
        assert tab.column_names == list(ref), name
        for col in tab.column_names:
            v = tab.column(col).to_numpy(zero_copy_only=False)
            dtype = {"f": float, "i": np.int64}.get(v.dtype.kind, str)
            np.testing.assert_array_equal(v, _num(ref[col], dtype) if dtype is not str else ref[col], err_msg=col)
    run = load_run(recording / "run.mcap")
    toa = pq.read_table(out / "toa.parquet").column("toa_s").to_numpy()
    assert toa.dtype == np.float64 and np.array_equal(toa, run.toa_s.ravel(), equal_nan=True)
    # the library's reader gives the same columns from either format
    a, b = read_tables(out), read_tables(exported_csv)
    assert a.keys() == b.keys()
    for name in a:
        for col in a[name]:
            if a[name][col].dtype.kind == "f":
                np.testing.assert_array_equal(a[name][col], b[name][col], err_msg=f"{name}.{col}")
            else:
                assert a[name][col].tolist() == b[name][col].tolist(), f"{name}.{col}"


def test_double_pulses_export_one_row_per_extra_edge_against_the_simulator(exported_csv, tmp_path):
    """The probe signal chain without hysteresis on a noisy pulse gives double pulses: the
    ``extra_edge`` table holds every later edge the simulator's trigger published (its count
    per window from ``RevolutionBatch.n_edges``, at most 8 a passage), each in its own blade's
    window and after that blade's TOA; a run without double pulses has no such table."""
    scn_text = SCENARIO.replace("trigger_jitter_s = 2e-8\n", "") + (
        "[acquisition.signal]\nenabled = true\nhysteresis_v = 0.0\nnoise_v = 0.02\n")
    (tmp_path / "s.toml").write_text(scn_text)
    run_file = tmp_path / "run.mcap"
    assert main(["simulate", str(tmp_path / "s.toml"), "--out", str(run_file), "-q"]) == 0
    assert main(["export", str(run_file), "--out", str(tmp_path / "csv")]) == 0
    t = _csv(tmp_path / "csv" / "extra_edge.csv")
    rev, probe, blade = (_num(t[k], np.int64) for k in ("revolution", "probe", "blade"))
    edge = _num(t["toa_s"])
    batches = collect(RunUpSimulator(load_scenario(tmp_path / "s.toml")))
    n_extra = np.minimum(batches.n_edges - 1, 8).clip(0)  # (revolution, blade, probe)
    assert edge.size == n_extra.sum() > 0
    assert np.all(blade >= 0)  # every edge in a blade's window
    counts = np.zeros_like(n_extra)
    np.add.at(counts, (rev, blade, probe), 1)
    np.testing.assert_array_equal(counts, n_extra)
    toa = load_run(run_file).toa_s
    later = edge - toa[rev, blade, probe]
    assert np.all((later > 0) & (later < 100e-6))  # microseconds after the blade's own TOA
    assert not (exported_csv / "extra_edge.csv").exists()  # no double pulses, no table


def test_a_recording_without_truth_exports_no_truth(recording, exported_csv, tmp_path):
    assert main(["simulate", str(recording / "s.toml"), "--out", str(tmp_path / "blind.mcap"), "-q",
                 "--no-truth"]) == 0
    assert main(["export", str(tmp_path / "blind.mcap"), "--out", str(tmp_path / "o")]) == 0
    doc = json.loads((tmp_path / "o" / "run.json").read_text())
    assert "truth" not in doc["tables"] and not (tmp_path / "o" / "truth.csv").exists()
    rt = _csv(tmp_path / "o" / "resonance.csv")
    assert rt["E_A_pct"] and set(rt["E_A_pct"]) == {"NaN"} and set(rt["truth_amp_pkpk_m"]) == {"NaN"}
    # the same acquisition as the recording with truth
    assert _csv(tmp_path / "o" / "toa.csv") == _csv(exported_csv / "toa.csv")


def test_a_recording_cut_short_exports_and_views_what_it_holds_and_says_so(recording, exported_csv, tmp_path, capsys):
    """A recording holding the first half of its run exports (and views) that half, and says
    the tables are not the whole run (a warning line; the whole recording gives none)."""
    from bttsim_stream.bus.recording import McapRecorder, read_recording

    msgs = read_recording(recording / "run.mcap").messages
    n = load_run(recording / "run.mcap").meta.n_revolutions
    with McapRecorder(tmp_path / "half.mcap") as rec:
        for m in msgs:
            if not (m.key.split("/")[2] in ("opr", "toa", "truth") and m.seq >= n // 2):
                rec.write(m.key, m.payload, m.log_time_ns, seq=m.seq)
    capsys.readouterr()
    assert main(["export", str(tmp_path / "half.mcap"), "--out", str(tmp_path / "o")]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"bttsim: warning: {tmp_path / 'half.mcap'}: INCOMPLETE: {n // 2} of {n} revolutions: the tables "
                   "are not the whole run"], err
    assert len(_csv(tmp_path / "o" / "opr.csv")["revolution"]) == n // 2
    assert main(["export", str(recording / "run.mcap"), "--out", str(tmp_path / "whole")]) == 0
    assert "INCOMPLETE" not in capsys.readouterr().err
    # the views of it say so too
    assert main(["view", str(tmp_path / "half.mcap"), "--rrd", str(tmp_path / "half.rrd")]) == 0
    assert capsys.readouterr().err.strip().splitlines() == [
        f"bttsim: warning: {tmp_path / 'half.mcap'}: INCOMPLETE: {n // 2} of {n} revolutions: the views are not "
        "the whole run"]


def test_a_recording_of_two_rigs_is_read_one_rig_at_a_time(recording, exported_csv, tmp_path, capsys):
    """One file of two rigs' runs (as a recorder of every rig writes it): ``process``,
    ``export`` and ``view`` refuse to choose between them (one line naming both, exit 2);
    with ``--rig`` each gives what the rig's own recording gives; a rig it does not hold, and
    run metadata on another rig's key, are one-line errors."""
    from bttsim_stream.bus.recording import McapRecorder, read_recording

    (tmp_path / "rig2.toml").write_text(SCENARIO + '[run]\nrig = "rig2"\n')
    assert main(["simulate", str(tmp_path / "rig2.toml"), "--out", str(tmp_path / "rig2.mcap"), "-q"]) == 0
    own = {"rig1": recording / "run.mcap", "rig2": tmp_path / "rig2.mcap"}
    both = tmp_path / "both.mcap"
    msgs = sorted([m for f in own.values() for m in read_recording(f).messages], key=lambda m: m.log_time_ns)
    with McapRecorder(both) as rec:
        rec.write_all(msgs)
    capsys.readouterr()
    for cmd in (["process", str(both)], ["export", str(both), "--out", str(tmp_path / "x")],
                ["view", str(both), "--rrd", str(tmp_path / "x.rrd")], ["process", str(both), "--rig", "rig3"]):
        assert main(cmd) == 2, cmd
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "rig1, rig2" in err[0] and str(both) in err[0], err
        assert ("choose one with --rig" if "rig3" not in cmd else "no run metadata of rig 'rig3'") in err[0]
    assert not (tmp_path / "x").exists() and not (tmp_path / "x.rrd").exists()
    for rig, alone in own.items():
        assert main(["process", str(both), "--rig", rig, "--summary", str(tmp_path / f"{rig}.json")]) == 0
        assert main(["process", str(alone), "--summary", str(tmp_path / f"{rig}-alone.json")]) == 0
        assert (tmp_path / f"{rig}.json").read_bytes() == (tmp_path / f"{rig}-alone.json").read_bytes(), rig
    assert main(["export", str(both), "--rig", "rig2", "--out", str(tmp_path / "e2")]) == 0
    assert main(["export", str(own["rig2"]), "--out", str(tmp_path / "e2-alone")]) == 0
    for table in ("opr", "toa", "fit", "resonance", "truth"):
        assert _csv(tmp_path / "e2" / f"{table}.csv") == _csv(tmp_path / "e2-alone" / f"{table}.csv"), table
    assert json.loads((tmp_path / "e2" / "run.json").read_text())["run"]["rig"] == "rig2"
    capsys.readouterr()
    assert main(["view", str(both), "--rig", "rig1", "--rrd", str(tmp_path / "v1.rrd")]) == 0
    err = capsys.readouterr().err
    assert "rejected" not in err and "ignoring run" not in err, err  # the other rig's messages are not read
    assert (tmp_path / "v1.rrd").stat().st_size > 0
    # run metadata of rig1 on rig2's key
    meta = next(m for m in read_recording(own["rig1"]).messages if m.key == "bttsim/rig1/meta")
    with McapRecorder(tmp_path / "forged.mcap") as rec:
        rec.write_all(read_recording(own["rig1"]).messages)
        rec.write("bttsim/rig2/meta", meta.payload, meta.log_time_ns, seq=0)
    assert main(["process", str(tmp_path / "forged.mcap"), "--rig", "rig2"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "the run metadata of rig 'rig1' on another rig's key" in err[0], err


def test_parquet_without_pyarrow_names_the_extra(recording, monkeypatch, capsys, tmp_path):
    monkeypatch.setitem(sys.modules, "pyarrow", None)  # import pyarrow -> ImportError
    monkeypatch.setitem(sys.modules, "pyarrow.parquet", None)
    assert main(["export", str(recording / "run.mcap"), "--format", "parquet", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "bttsim-stream[parquet]" in err[0]
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("what", ["missing", "not_mcap", "truncated"], ids=str)
def test_bad_input_is_one_line_exit_2(recording, tmp_path, capsys, what):
    src = tmp_path / "bad.mcap"
    if what == "not_mcap":
        src.write_text("hello\n")
    elif what == "truncated":
        src.write_bytes((recording / "run.mcap").read_bytes()[:20000])
    assert main(["export", str(src), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("bttsim: error:"), err


def test_a_truth_copy_of_another_shape_conflicts_and_keeps_the_first():
    """Truth rows: a second copy of a revolution that differs, in a value or in its shape, is a
    conflict and the first holds (before: a copy of another shape marked the revolution bad
    and the whole run's truth was dropped without a word)."""
    from dataclasses import fields

    from bttsim_stream.offline import _TruthTable
    from bttsim_stream.sim.core import Truth

    def truth(value, n_probes=2):
        return Truth(*[np.full((1, 3, n_probes), value) if f in ("toa_s", "t_exp_s") else
                       (np.full((1, 3), value) if f == "d_eqv_pkpk_m" else None)
                       for f in ("opr_s", "toa_s", "t_exp_s", "d_eqv_m", "d_tang_m", "d_z_m", "d_eq1_m",
                                 "d_eqv_pkpk_m", "omega_mean")])

    def add(table, revolution, tr):  # as load_run adds a decoded row (codec.truth_row)
        table.add(revolution, tr.toa_s.shape[1:], {n: getattr(tr, n) for n in table.names})

    for copy, conflicts in ((truth(1.0), 0), (truth(2.0), 1), (truth(1.0, n_probes=3), 1)):
        t = _TruthTable(("d_eqv_pkpk_m",), 4, (3, 2))
        add(t, 0, truth(1.0))
        add(t, 0, copy)
        add(t, 1, truth(5.0))
        assert t.conflicts == conflicts
        rows = t.rows([0, 1], tuple(f.name for f in fields(Truth)))
        assert rows is not None and rows.d_eqv_pkpk_m[0, 0] == 1.0 and rows.d_eqv_pkpk_m[1, 0] == 5.0

"""``bttsim campaign`` on Dask: a tiny study on a two-worker LocalCluster, scored the same as
``bttsim simulate`` + ``bttsim process``, deterministic, resumable, surviving a killed worker;
on a real ``dask scheduler`` + two ``dask worker`` processes (one of them killed mid-campaign),
and across network namespaces with TLS; bad specs and an unreachable scheduler are one line
and exit 2."""

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

distributed = pytest.importorskip("distributed")
pq = pytest.importorskip("pyarrow.parquet")

from _procs import LineWatch  # noqa: E402
from bttsim_stream.bus.certs import generate_certificates  # noqa: E402
from bttsim_stream.campaign import expand, load_spec, run_campaign  # noqa: E402
from bttsim_stream.campaign.run import ROW_COLUMNS, TIMING_COLUMNS  # noqa: E402
from bttsim_stream.cli import main  # noqa: E402

pytestmark = pytest.mark.integration

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
N_BLADES = 29
#: A short run-up through the EO 8 x ND 1 resonance (~2580 rpm): about 1 s to simulate.
SPEC = """
[campaign]
name = "tiny"
seed = 7
seeds = 2
processors = ["peak", "sdof"]

[scenario.speed]
start_rpm = 2400.0
end_rpm = 2700.0
duration_s = 6.0

[axes]
"acquisition.trigger_jitter_s" = [0.0, 1e-6]
"""


@pytest.fixture(scope="module")
def cluster():
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address="127.0.0.1:0") as c:
        yield c


@pytest.fixture(scope="module")
def tiny(cluster, tmp_path_factory):
    d = tmp_path_factory.mktemp("campaign")
    (d / "spec.toml").write_text(SPEC)
    spec = load_spec(d / "spec.toml")
    t0 = time.perf_counter()
    res = run_campaign(spec, d / "out", scheduler=cluster.scheduler_address)
    print(f"tiny campaign: {res.executed} runs in {time.perf_counter() - t0:.1f} s ({res.runs_per_s:.2f} runs/s)")
    return spec, res, d


def _values(path, drop=TIMING_COLUMNS) -> dict:
    t = pq.read_table(path)
    return {c: t.column(c).to_pylist() for c in t.column_names if c not in drop}


def test_tiny_campaign_rows_and_columns(tiny):
    spec, res, d = tiny
    t = pq.read_table(d / "out" / "results.parquet")
    assert set(ROW_COLUMNS) | {"acquisition.trigger_jitter_s"} <= set(t.column_names)
    rows = t.to_pylist()
    # 2 seeds x 2 jitter levels = 4 runs; each: 1 crossing x 29 blades x 2 methods
    assert res.runs == res.executed == 4 and res.failed == 0
    assert len(rows) == 4 * N_BLADES * 2 == res.rows
    assert {r["status"] for r in rows} == {"ok"}
    assert len({(r["run_id"], r["method"], r["crossing"], r["blade"]) for r in rows}) == len(rows)
    assert {r["method"] for r in rows} == {"peak", "sdof"}
    assert {r["acquisition.trigger_jitter_s"] for r in rows} == {0.0, 1e-6}
    assert {r["worker"] for r in rows} <= {"0", "1"}
    assert all(r["eo"] == 8 and np.isfinite(r["E_A_pct"]) for r in rows)
    assert all(r["amp_ci95_lo_m"] <= r["amp_pkpk_m"] <= r["amp_ci95_hi_m"] for r in rows)
    report = (d / "out" / "report.md").read_text()
    assert "## By `acquisition.trigger_jitter_s`" in report and "| peak |" in report


def test_matches_bttsim_process(tiny, tmp_path, capsys):
    """A run's E_A in results.parquet is `bttsim process`'s on the same scenario (through MCAP)."""
    spec, _, d = tiny
    run = [r for r in expand(spec) if r.point["acquisition.trigger_jitter_s"] == 1e-6][0]
    (tmp_path / "s.toml").write_text(run.scenario_toml)
    rows = [r for r in pq.read_table(d / "out" / "results.parquet").to_pylist() if r["run_id"] == run.run_id]
    assert main(["simulate", str(tmp_path / "s.toml"), "--out", str(tmp_path / "r.mcap"), "-q"]) == 0
    for method in ("peak", "sdof"):
        assert main(["process", str(tmp_path / "r.mcap"), "--method", method,
                     "--summary", str(tmp_path / f"{method}.json")]) == 0
        blades = json.loads((tmp_path / f"{method}.json").read_text())["resonances"][0]["blades"]
        mine = sorted((r for r in rows if r["method"] == method), key=lambda r: r["blade"])
        np.testing.assert_allclose([r["E_A_pct"] for r in mine], [b["E_A_pct"] for b in blades], rtol=1e-9, atol=0)
        np.testing.assert_allclose([r["amp_pkpk_m"] for r in mine], [b["amp_pkpk_m"] for b in blades], rtol=1e-12)
    capsys.readouterr()


def test_deterministic_and_resume(tiny, cluster, tmp_path):
    """The same spec twice gives the same values; --resume reruns only what is missing."""
    spec, _, d = tiny
    first = _values(d / "out" / "results.parquet")
    again = run_campaign(spec, tmp_path / "again", scheduler=cluster.scheduler_address)
    assert again.executed == 4
    assert _values(tmp_path / "again" / "results.parquet") == first
    part = sorted((tmp_path / "again" / "runs").glob("*.parquet"))[1]
    part.unlink()
    (tmp_path / "again" / "results.parquet").unlink()
    resumed = run_campaign(spec, tmp_path / "again", scheduler=cluster.scheduler_address, resume=True)
    assert (resumed.executed, resumed.skipped) == (1, 3)
    assert _values(tmp_path / "again" / "results.parquet") == first
    summary = json.loads((tmp_path / "again" / "campaign.json").read_text())
    assert [c["executed"] for c in summary["calls"]] == [4, 1] and summary["executed"] == 5
    assert summary["wall_s"] == pytest.approx(again.wall_s + resumed.wall_s, rel=1e-12)
    assert summary["compute_s"] == pytest.approx(again.compute_s + resumed.compute_s, rel=1e-12)
    # resuming a finished campaign runs nothing and keeps the timings of the calls that did
    idle = run_campaign(spec, tmp_path / "again", scheduler=cluster.scheduler_address, resume=True)
    assert (idle.executed, idle.skipped, idle.compute_s) == (0, 4, 0.0)
    after = json.loads((tmp_path / "again" / "campaign.json").read_text())
    assert after["calls"][:2] == summary["calls"] and after["calls"][2]["executed"] == 0
    for k in ("executed", "wall_s", "compute_s", "runs_per_s", "workers", "runs", "rows"):
        assert after[k] == summary[k], k
    assert summary["runs_per_s"] > 0 and summary["workers"] == 2
    assert _values(tmp_path / "again" / "results.parquet") == first
    with pytest.raises(Exception, match="already holds a campaign"):
        run_campaign(spec, tmp_path / "again", scheduler=cluster.scheduler_address)


def test_worker_killed_mid_campaign(tmp_path):
    """SIGKILL of a worker running a task: its nanny restarts it, Dask reruns the task, no row
    is lost or duplicated."""
    (tmp_path / "spec.toml").write_text(SPEC.replace('["peak", "sdof"]', '["peak"]'))
    spec = load_spec(tmp_path / "spec.toml")
    killed = {}
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address="127.0.0.1:0") as cl, distributed.Client(cl) as client:
        pids = client.run(os.getpid)

        def killer():
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline and not killed:
                busy = {w: ks for w, ks in client.processing().items() if ks}
                if busy:
                    time.sleep(0.3)  # inside the run (simulating), not at its very start
                    w = next(iter(busy))
                    os.kill(pids[w], signal.SIGKILL)
                    killed[w] = list(busy[w])
                time.sleep(0.05)

        th = threading.Thread(target=killer, daemon=True)
        th.start()
        res = run_campaign(spec, tmp_path / "out", scheduler=cl.scheduler_address)
        th.join(5)
    assert killed, "no worker was killed"
    rows = pq.read_table(tmp_path / "out" / "results.parquet").to_pylist()
    assert res.executed == 4 and res.failed == 0
    assert {r["status"] for r in rows} == {"ok"}
    assert len(rows) == 4 * N_BLADES
    assert len({(r["run_id"], r["blade"]) for r in rows}) == len(rows)


#: User processors that fail, each in its own way, and one that leaves blades out (written
#: into the test's folder, which the workers put on their path).
BAD_PROCESSORS = """
import numpy as np
import pyarrow as pa

def raises(tables, run):
    raise ZeroDivisionError("no\\nthis spans\\n   three lines")

def exits(tables, run):
    raise SystemExit(3)

def array(tables, run):
    return np.zeros(run["n_blades"])  # not a table

def no_amp(tables, run):
    return {"blade": np.arange(run["n_blades"])}

def typo(tables, run):
    return {"blade": [0], "amp_pk_m": [1e-3]}

def bad_blade(tables, run):
    return {"blade": [0, run["n_blades"]], "amp_pkpk_m": [1e-3, 1e-3]}

def twice(tables, run):
    return {"blade": [3, 3], "amp_pkpk_m": [1e-3, 2e-3]}

def ragged(tables, run):
    return {"blade": [0, 1, 2], "amp_pkpk_m": [1e-3, 2e-3]}

def text(tables, run):
    return {"blade": [0], "amp_pkpk_m": ["big"]}

def inverted(tables, run):
    return {"blade": [0], "amp_pkpk_m": [1e-3], "amp_ci95_lo_m": [2e-3], "amp_ci95_hi_m": [1e-3]}

def two_blades(tables, run):
    # a pyarrow Table, two blades only, the engine order the metadata announces
    toa = tables["toa"].to_pydict()
    assert set(toa) == {"revolution", "blade", "probe", "toa_s"} and set(tables) == {"opr", "toa"}
    assert not any(k.startswith("truth") for k in run)
    return pa.table({"blade": [5, 0], "amp_pkpk_m": [2e-3, 1e-3]})
"""
BAD = {"raises": "ZeroDivisionError: no this spans three lines", "exits": "SystemExit: 3",
       "array": "returned ndarray, not a table", "no_amp": "no column amp_pkpk_m", "typo": "unknown column(s) amp_pk_m",
       "bad_blade": "blade 29, not in 0..28", "twice": "two rows for one blade", "ragged": "column amp_pkpk_m of shape",
       "text": "column amp_pkpk_m of shape (1,) and dtype <U3", "inverted": "amp_ci95_lo_m above amp_ci95_hi_m"}


def test_user_processor_tables_are_the_export(tmp_path, capsys):
    """A user's processor gets the opr and toa tables that `bttsim export --format parquet`
    writes of the same run (columns, dtypes, values) and run.json's run object; in memory."""
    from bttsim_stream.campaign import user_tables
    from bttsim_stream.campaign.run import _simulate
    from bttsim_stream.scenario import scenario_from_dict
    import tomllib

    (tmp_path / "spec.toml").write_text(SPEC.replace("seeds = 2", "seeds = 1").replace("[0.0, 1e-6]", "[1e-6]"))
    run = expand(load_spec(tmp_path / "spec.toml"))[0]
    opr_s, toa_s, revolution, info, truth, path = _simulate(run, scenario_from_dict(tomllib.loads(run.scenario_toml)))
    assert path is None and truth is not None  # in memory
    tables, meta = user_tables(revolution, opr_s, toa_s, info)
    (tmp_path / "s.toml").write_text(run.scenario_toml)
    assert main(["simulate", str(tmp_path / "s.toml"), "--out", str(tmp_path / "r.mcap"), "-q"]) == 0
    assert main(["export", str(tmp_path / "r.mcap"), "--format", "parquet", "--out", str(tmp_path / "x")]) == 0
    capsys.readouterr()
    assert set(tables) == {"opr", "toa"}
    for name in ("opr", "toa"):
        exported = pq.read_table(tmp_path / "x" / f"{name}.parquet")
        assert tables[name].schema.equals(exported.schema), name
        assert tables[name].equals(exported), name
    assert tables["toa"].num_rows == toa_s.size and np.isnan(tables["toa"].column("toa_s").to_numpy()).sum() == \
        np.isnan(toa_s).sum()
    assert meta == json.loads((tmp_path / "x" / "run.json").read_text())["run"]


def test_user_processor_and_failures(cluster, tmp_path, monkeypatch):
    """The example processor (tables in, per-blade table out) is scored against the truth,
    with the coverage of its intervals; a processor that raises, exits or returns a malformed
    table is one error row with its reason on one line, and the campaign goes on."""
    (tmp_path / "userproc_bad.py").write_text(BAD_PROCESSORS)
    for p in (EXAMPLES, tmp_path):
        monkeypatch.syspath_prepend(str(p))
    client = distributed.Client(cluster.scheduler_address)
    client.run(lambda ps=[str(EXAMPLES), str(tmp_path)]: __import__("sys").path.__setitem__(slice(0, 0), ps))
    client.close()
    procs = ["peak", "campaign_processor:peak_fit", "nosuch:fn", "userproc_bad:two_blades"] + \
        [f"userproc_bad:{k}" for k in BAD]
    (tmp_path / "spec.toml").write_text(SPEC.replace("seeds = 2", "seeds = 1")
                                        .replace('["peak", "sdof"]', json.dumps(procs))
                                        .replace("[0.0, 1e-6]", "[1e-6]"))
    res = run_campaign(load_spec(tmp_path / "spec.toml"), tmp_path / "out", scheduler=cluster.scheduler_address)
    rows = pq.read_table(tmp_path / "out" / "results.parquet").to_pylist()
    by = {m: sorted((r for r in rows if r["method"] == m), key=lambda r: r["blade"]) for m in procs}
    user, peak = by["campaign_processor:peak_fit"], by["peak"]
    assert len(user) == N_BLADES and all(r["status"] == "ok" and r["eo"] == 8 for r in user)
    # scored against the truth: the same per-blade truth as the built-in method's, E_A by Eq. 18
    np.testing.assert_allclose([r["truth_amp_pkpk_m"] for r in user], [r["truth_amp_pkpk_m"] for r in peak],
                               rtol=1e-12)
    e_a = [100 * abs(r["amp_pkpk_m"] - r["truth_amp_pkpk_m"]) / r["truth_amp_pkpk_m"] for r in user]
    assert np.all(np.isfinite(e_a)) and np.allclose([r["E_A_pct"] for r in user], e_a, rtol=1e-12)
    assert np.median(e_a) < 20 and np.all(np.isfinite([r["E_f_pct"] for r in user]))
    assert all(0 <= r["amp_ci95_lo_m"] < r["amp_pkpk_m"] < r["amp_ci95_hi_m"] for r in user)
    covered = np.mean([r["amp_ci95_lo_m"] <= r["truth_amp_pkpk_m"] <= r["amp_ci95_hi_m"] for r in user])
    report = (tmp_path / "out" / "report.md").read_text()
    line = next(x for x in report.splitlines() if x.startswith("| campaign_processor:peak_fit | 1 | 29 | 0 |"))
    assert f"| {100 * covered:.1f} % of 29" in line  # the coverage of its intervals
    two = by["userproc_bad:two_blades"]  # blades left out are NaN rows
    assert len(two) == N_BLADES and [b["blade"] for b in two if np.isfinite(b["amp_pkpk_m"])] == [0, 5]
    assert two[5]["E_A_pct"] == pytest.approx(100 * abs(2e-3 - two[5]["truth_amp_pkpk_m"]) / two[5]["truth_amp_pkpk_m"])
    assert np.isnan(two[5]["amp_ci95_lo_m"]) and np.isnan(two[1]["E_A_pct"])
    for name, needle in [("nosuch:fn", "nosuch")] + [(f"userproc_bad:{k}", v) for k, v in BAD.items()]:
        bad = by[name]
        assert len(bad) == 1 and bad[0]["status"] == "error", name
        assert needle in bad[0]["error"] and "\n" not in bad[0]["error"], (name, bad[0]["error"])
    assert res.failed == 1 and res.executed == 1
    assert "nosuch:fn | error | 1 |" in report


@pytest.mark.parametrize("text, needle", [
    ("[campaign]\nseeds = 0\n", "seeds"),
    ("[campaign]\nprocessors = [\"peek\"]\n", "did you mean 'peak'"),
    ("[axes]\n\"acquisition.trigger_jiter_s\" = [0.0]\n", "trigger_jitter_s"),
    ("[axes]\n\"acquisition.trigger_jitter_s\" = [-1.0]\n", "trigger_jitter_s = -1.0"),
    ("[axes]\n\"speed.duration_s\" = {start = 1.0, stop = 2.0}\n", "range"),
    ("[campagn]\n", "did you mean 'campaign'"),
    ("[campaign\n", "malformed TOML"),
    ("[campaign]\nseeds = 1000\n[axes]\n\"acquisition.trigger_jitter_s\" = {start = 0.0, stop = 1e-6, num = 101}\n",
     "expands to 101000 runs (at most 100000)"),
], ids=["seeds", "method", "axis-name", "axis-value", "range", "table", "toml", "too-many-runs"])
def test_bad_spec_exit_2(tmp_path, capsys, text, needle):
    (tmp_path / "bad.toml").write_text(text)
    assert main(["campaign", str(tmp_path / "bad.toml"), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("bttsim: error: ") and needle in err
    assert not (tmp_path / "out").exists()


def test_scheduler_unreachable_exit_2(tmp_path, capsys):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    (tmp_path / "spec.toml").write_text(SPEC)
    assert main(["campaign", str(tmp_path / "spec.toml"), "--out", str(tmp_path / "out"), "-q",
                 "--scheduler", f"tcp://127.0.0.1:{port}", "--connect-timeout", "2"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "cannot reach the Dask scheduler" in err
    assert not (tmp_path / "out").exists()  # a failed start leaves no folder
    (tmp_path / "empty").mkdir()
    assert main(["campaign", str(tmp_path / "spec.toml"), "--out", str(tmp_path / "empty"), "-q",
                 "--scheduler", f"tcp://127.0.0.1:{port}", "--connect-timeout", "1"]) == 2
    assert list((tmp_path / "empty").iterdir()) == []  # nor anything in an existing one
    capsys.readouterr()


#: One short run (128 revolutions), for the checks of the output folder and the options.
SHORT = """
[campaign]
seeds = 1
processors = ["peak"]

[scenario.speed]
start_rpm = 2450.0
end_rpm = 2700.0
duration_s = 3.0

[axes]
"acquisition.trigger_jitter_s" = [0.0]
"""


def _snapshot(d: Path) -> dict:
    return {str(p.relative_to(d)): (p.read_bytes() if p.is_file() else None) for p in sorted(d.rglob("*"))}


def test_window_longer_than_the_run_is_an_error_row(cluster, tmp_path):
    """A processor whose sine-fit window is longer than the run is refused as `bttsim process
    --window` refuses it: an error row with the reason, never a scored result."""
    (tmp_path / "spec.toml").write_text(SHORT.replace('["peak"]', '["peak", {name = "w1000", method = "peak", '
                                                                    'window = 1000}]'))
    spec = load_spec(tmp_path / "spec.toml")
    res = run_campaign(spec, tmp_path / "out", scheduler=cluster.scheduler_address)
    rows = pq.read_table(tmp_path / "out" / "results.parquet").to_pylist()
    from bttsim_stream.campaign.run import _simulate
    from bttsim_stream.scenario import scenario_from_dict
    import tomllib

    run = expand(spec)[0]
    n_rev = _simulate(run, scenario_from_dict(tomllib.loads(run.scenario_toml)))[2].size  # the run's revolutions
    assert {r["status"] for r in rows if r["method"] == "peak"} == {"ok"}
    (bad,) = [r for r in rows if r["method"] == "w1000"]
    assert bad["status"] == "error" and np.isnan(bad["E_A_pct"]) and bad["blade"] == -1
    assert f"a sine-fit window of 1000 revolutions is longer than the run's {n_rev}" in bad["error"], bad["error"]
    assert res.failed == 1 and 100 < n_rev < 1000
    assert "| w1000 | error | 1 |" in (tmp_path / "out" / "report.md").read_text()


def test_resume_reruns_a_damaged_or_foreign_part(cluster, tmp_path):
    """--resume trusts only a part file that is a readable Parquet file of the campaign's
    columns holding its own run's rows: a truncated one, one of other columns, or another
    run's, is run again, and results.parquet is the same as the first call's."""
    (tmp_path / "spec.toml").write_text(SHORT.replace("[0.0]", "[0.0, 1e-6]"))
    spec = load_spec(tmp_path / "spec.toml")
    out = tmp_path / "out"
    run_campaign(spec, out, scheduler=cluster.scheduler_address)
    first = _values(out / "results.parquet")
    a, b = (out / "runs" / f"{r.run_id}.parquet" for r in expand(spec))
    import pyarrow as pa

    for damage in (lambda: a.write_bytes(a.read_bytes()[:100]),  # truncated
                   lambda: pq.write_table(pa.table({"index": [0]}), a),  # a Parquet file of other columns
                   lambda: shutil.copyfile(b, a)):  # the other run's rows
        damage()
        resumed = run_campaign(spec, out, scheduler=cluster.scheduler_address, resume=True)
        assert (resumed.executed, resumed.skipped) == (1, 1)
        assert _values(out / "results.parquet") == first and _values(a) == _values(b.with_name(a.name))


def test_resume_refuses_another_study(tmp_path, capsys):
    """--resume on a folder of another spec, or of campaign outputs without spec.json, is one
    line and exit 2 before anything starts, and the folder is left as it was."""
    from bttsim_stream.campaign.driver import spec_record

    (tmp_path / "a.toml").write_text(SHORT)
    (tmp_path / "b.toml").write_text(SHORT.replace("[0.0]", "[1e-6]"))
    (tmp_path / "c.toml").write_text(SHORT.replace('["peak"]', '[{name = "peak", method = "peak", window = 3}]'))
    other, foreign = tmp_path / "other", tmp_path / "foreign"
    (other / "runs").mkdir(parents=True)
    (other / "spec.json").write_text(json.dumps(spec_record(load_spec(tmp_path / "a.toml"))))
    (other / "results.parquet").write_bytes(b"the earlier study's results")
    (other / "report.md").write_text("# the earlier study\n")
    foreign.mkdir()
    (foreign / "report.md").write_text("# someone's report\n")
    (foreign / "results.parquet").write_bytes(b"someone's table")
    unreachable = ["--scheduler", "tcp://127.0.0.1:9", "--connect-timeout", "1", "-q", "--resume"]
    for spec, out, needle in (("b", other, "other/spec.json: the folder holds another study (its spec differs)"),
                              ("c", other, "another study"),
                              ("a", foreign, "holds results.parquet, report.md but no spec.json")):
        before = _snapshot(out)
        assert main(["campaign", str(tmp_path / f"{spec}.toml"), "--out", str(out), *unreachable]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and needle in err, err
        assert _snapshot(out) == before


def test_results_path_not_a_file(tmp_path, capsys):
    """A results.parquet that is a folder is named (not a temporary file) and nothing is left."""
    from bttsim_stream.campaign.driver import spec_record
    from bttsim_stream.campaign.results import write_rows
    from bttsim_stream.errors import BttsimError

    (tmp_path / "spec.toml").write_text(SHORT)
    spec = load_spec(tmp_path / "spec.toml")
    out = tmp_path / "out"
    (out / "results.parquet").mkdir(parents=True)
    (out / "spec.json").write_text(json.dumps(spec_record(spec)))
    before = _snapshot(out)
    assert main(["campaign", str(tmp_path / "spec.toml"), "--out", str(out), "-q", "--resume",
                 "--scheduler", "tcp://127.0.0.1:9", "--connect-timeout", "1"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{out / 'results.parquet'}: not a file" in err and ".tmp" not in err, err
    assert _snapshot(out) == before
    with pytest.raises(BttsimError, match=r"results\.parquet: cannot write") as info:
        write_rows(out / "results.parquet", [], spec)
    assert ".tmp" not in str(info.value) and _snapshot(out) == before


def test_bad_workers_or_dashboard_exit_2(tmp_path):
    """--workers beyond the maximum is an argument error; a dashboard address not on this
    machine is one line: both exit 2 at once and leave no folder."""
    (tmp_path / "spec.toml").write_text(SHORT)
    for opt, needle in ((["--workers", "1000000"], "argument --workers: '1000000' is above 256"),
                        (["--dashboard", "192.0.2.1:8787"], "cannot start the embedded Dask cluster with --dashboard "
                                                            "192.0.2.1:8787")):
        p = subprocess.Popen([sys.executable, "-m", "bttsim_stream.cli", "campaign", tmp_path / "spec.toml", "--out",
                              tmp_path / "out", "-q", *opt], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True, start_new_session=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
        try:
            _, err = p.communicate(timeout=120)
        finally:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()
        assert p.returncode == 2 and err.count("\n") == 1 and needle in err, err
        assert not (tmp_path / "out").exists()


@pytest.mark.unit
def test_expansion_validates_each_axis_point_once(tmp_path, monkeypatch):
    """Each axis point's scenario is built once whatever the seed count, and every run's TOML
    is the scenario writer's own text of that run (seed included)."""
    import tomllib

    from bttsim_stream.campaign import spec as spec_mod
    from bttsim_stream.scenario import dumps_toml, scenario_from_dict

    (tmp_path / "spec.toml").write_text(SHORT.replace("seeds = 1", "seeds = 7").replace("[0.0]", "[0.0, 1e-6, 2e-6]")
                                        + '"excitation.amplitude_n" = [1.0, 2.25]\n')
    spec = load_spec(tmp_path / "spec.toml")
    calls = []
    monkeypatch.setattr(spec_mod, "scenario_from_dict", lambda *a, **k: calls.append(1) or scenario_from_dict(*a, **k))
    runs = expand(spec)
    assert len(runs) == 42 and len(calls) == 6 and len({r.run_id for r in runs}) == 42
    for r in runs:
        d = tomllib.loads(r.scenario_toml)
        assert d["run"]["seed"] == r.seed and r.scenario_toml == dumps_toml(scenario_from_dict(d))
        assert d["acquisition"]["trigger_jitter_s"] == r.point["acquisition.trigger_jitter_s"]


@pytest.mark.unit
def test_quick_example_expands():
    runs = expand(load_spec(EXAMPLES / "campaign_quick.toml"))
    assert len(runs) == 12 and len({r.run_id for r in runs}) == 12
    assert len({r.seed for r in runs}) == 3  # paired: one seed per replicate at every point


# --- a real Dask cluster: `dask scheduler` and `dask worker` processes ---------------------

REPO = Path(__file__).resolve().parents[1]


class DaskProcs:
    """``dask scheduler`` / ``dask worker`` processes (optionally in a network namespace),
    each in its own process group, stopped by it; readiness from their log lines."""

    def __init__(self):
        self.procs: list[tuple[subprocess.Popen, LineWatch]] = []

    def start(self, cli: str, *args, ns: str | None = None) -> tuple[subprocess.Popen, LineWatch]:
        cmd = [sys.executable, "-m", f"distributed.cli.dask_{cli}", *map(str, args)]
        if ns:
            cmd = ["ip", "netns", "exec", ns, *cmd]  # exec: the PID is the scheduler's / worker's
        p = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                             start_new_session=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
        watch = LineWatch(p.stderr)
        self.procs.append((p, watch))
        return p, watch

    def scheduler(self, *args, ns=None) -> str:
        """Start a scheduler; its address once it listens."""
        _, watch = self.start("scheduler", "--no-dashboard", *args, ns=ns)
        line = watch.wait_for(lambda ln: "Scheduler at:" in ln, timeout=120)
        return line.split("Scheduler at:")[1].strip()

    def worker(self, address: str, name: str, *args, ns=None) -> subprocess.Popen:
        """Start a single-threaded worker; returned once it has registered with the scheduler."""
        p, watch = self.start("worker", address, "--name", name, "--nthreads", "1", "--no-dashboard", *args, ns=ns)
        watch.wait_for(lambda ln: "Registered to:" in ln, timeout=120)
        return p

    def stop(self) -> None:
        for p, _ in reversed(self.procs):
            if p.poll() is None:
                try:
                    os.killpg(p.pid, signal.SIGTERM)
                    p.wait(30)
                except subprocess.TimeoutExpired:
                    os.killpg(p.pid, signal.SIGKILL)
                    p.wait()
                except ProcessLookupError:
                    pass


@pytest.fixture
def dask_procs():
    procs = DaskProcs()
    try:
        yield procs
    finally:
        procs.stop()


def _check_rows(out: Path, n_runs: int, methods: int) -> list[dict]:
    rows = pq.read_table(out / "results.parquet").to_pylist()
    assert {r["status"] for r in rows} == {"ok"}
    assert len(rows) == n_runs * N_BLADES * methods
    assert len({(r["run_id"], r["method"], r["blade"]) for r in rows}) == len(rows)  # none twice
    assert len({r["run_id"] for r in rows}) == n_runs  # none lost
    return rows


def test_real_scheduler_and_two_worker_processes(dask_procs, tmp_path, capsys):
    """`dask scheduler` + two `dask worker` processes (with nannies) on loopback, the campaign
    through `bttsim campaign --scheduler`: every run once, both workers named in the rows, the
    same values as on a LocalCluster."""
    address = dask_procs.scheduler("--host", "127.0.0.1", "--port", "0")
    for name in ("wa", "wb"):
        dask_procs.worker(address, name, "--host", "127.0.0.1")
    (tmp_path / "spec.toml").write_text(SPEC.replace('["peak", "sdof"]', '["peak"]'))
    assert main(["campaign", str(tmp_path / "spec.toml"), "--out", str(tmp_path / "out"), "-q",
                 "--scheduler", address]) == 0
    assert "on 2 worker(s)" in capsys.readouterr().out
    rows = _check_rows(tmp_path / "out", 4, 1)
    assert {r["worker"] for r in rows} == {"wa", "wb"}
    assert json.loads((tmp_path / "out" / "campaign.json").read_text())["scheduler"] == address


def test_worker_process_killed_mid_campaign(dask_procs, tmp_path):
    """SIGKILL of a `dask worker` process (no nanny: nothing restarts it) while it runs a
    task: the scheduler reruns its tasks on the other worker; no row lost or duplicated."""
    address = dask_procs.scheduler("--host", "127.0.0.1", "--port", "0")
    workers = {name: dask_procs.worker(address, name, "--host", "127.0.0.1", "--no-nanny") for name in ("wa", "wb")}
    (tmp_path / "spec.toml").write_text(SPEC.replace('["peak", "sdof"]', '["peak"]'))
    spec = load_spec(tmp_path / "spec.toml")
    killed = {}
    with distributed.Client(address) as client:
        names = {a: w["name"] for a, w in client.scheduler_info()["workers"].items()}

        def killer():
            deadline = time.monotonic() + 120
            while time.monotonic() < deadline and not killed:
                executing = {a: ks for a, ks in client.processing().items() if ks}
                if executing:
                    time.sleep(0.3)  # inside the run, not at its very start
                    name = names[next(iter(executing))]
                    os.kill(workers[name].pid, signal.SIGKILL)
                    killed[name] = list(next(iter(executing.values())))
                time.sleep(0.05)

        th = threading.Thread(target=killer, daemon=True)
        th.start()
        res = run_campaign(spec, tmp_path / "out", scheduler=address)
        th.join(5)
    assert killed, "no worker was killed"
    (dead,) = killed
    assert workers[dead].wait(10) == -signal.SIGKILL
    assert res.executed == 4 and res.failed == 0 and res.workers == 2
    rows = _check_rows(tmp_path / "out", 4, 1)
    alive = ({"wa", "wb"} - {dead}).pop()
    # the killed worker's tasks ran again on the other one
    assert alive in {r["worker"] for r in rows}
    assert {r["worker"] for r in rows if f"bttsim-run-{r['run_id']}" in killed[dead]} == {alive}


# --- several hosts: network namespaces, TLS ---------------------------------------------------

NET = "10.78.0"


def _ip(*args, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=30, check=check)


@pytest.fixture
def lan():
    """Three namespaces on one LAN: the scheduler host (a bridge, 10.78.0.1) and two worker
    hosts (10.78.0.11, 10.78.0.12), each linked to the bridge by a veth pair; deleted after."""
    if os.geteuid() != 0 or shutil.which("ip") is None:
        pytest.skip("network namespaces need root and iproute2 (ip netns)")
    probe = f"bttsim-probe-{os.getpid()}"
    res = _ip("netns", "add", probe, check=False)
    if res.returncode != 0:
        pytest.skip(f"ip netns add is not permitted here: {res.stderr.strip()}")
    _ip("netns", "del", probe, check=False)
    ns = {k: f"bc{os.getpid()}{k}" for k in ("s", "a", "b")}
    try:
        for name in ns.values():
            _ip("netns", "add", name)
            _ip("-n", name, "link", "set", "lo", "up")
        res = _ip("-n", ns["s"], "link", "add", "br0", "type", "bridge", check=False)
        if res.returncode != 0:
            pytest.skip(f"no Linux bridge here: {res.stderr.strip()}")
        _ip("-n", ns["s"], "addr", "add", f"{NET}.1/24", "dev", "br0")
        _ip("-n", ns["s"], "link", "set", "br0", "up")
        for host, last in (("a", 11), ("b", 12)):
            _ip("-n", ns[host], "link", "add", "eth0", "type", "veth", "peer", "name", f"p{host}", "netns", ns["s"])
            _ip("-n", ns["s"], "link", "set", f"p{host}", "master", "br0")
            _ip("-n", ns["s"], "link", "set", f"p{host}", "up")
            _ip("-n", ns[host], "addr", "add", f"{NET}.{last}/24", "dev", "eth0")
            _ip("-n", ns[host], "link", "set", "eth0", "up")
        yield ns
    finally:
        for name in ns.values():
            _ip("netns", "del", name, check=False)


def _campaign_in(ns: str, *args) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", "netns", "exec", ns, sys.executable, "-m", "bttsim_stream.cli", "campaign",
                           *map(str, args)], cwd=REPO, capture_output=True, text=True, timeout=600,
                          env={**os.environ, "OMP_NUM_THREADS": "1"})


def test_multi_host_with_tls_in_network_namespaces(lan, dask_procs, tmp_path):
    """Scheduler | worker host A | worker host B, each its own network stack, mutual TLS with
    `bttsim certs` certificates (Dask's Security, tls:// addresses): the campaign, run on the
    scheduler host, gets every run from both remote workers; no certificate, or one of another
    CA, is one line and exit 2."""
    certs = tmp_path / "certs"
    generate_certificates(certs, ["scheduler", "worker", "campaign"], hosts=[f"{NET}.1", f"{NET}.11", f"{NET}.12"])

    def tls(name, d=certs):
        return ["--tls-ca-file", d / "ca.pem", "--tls-cert", d / f"{name}.pem", "--tls-key", d / f"{name}-key.pem"]

    address = dask_procs.scheduler("--host", f"tls://{NET}.1", "--port", "8786", *tls("scheduler"), ns=lan["s"])
    assert address == f"tls://{NET}.1:8786"
    for host, last in (("a", 11), ("b", 12)):
        dask_procs.worker(address, f"host-{host}", "--host", f"{NET}.{last}", "--no-nanny", *tls("worker"),
                          ns=lan[host])
    (tmp_path / "spec.toml").write_text(SPEC.replace('["peak", "sdof"]', '["peak"]'))
    res = _campaign_in(lan["s"], tmp_path / "spec.toml", "--out", tmp_path / "out", "-q", "--scheduler", address,
                       "--tls-dir", certs)
    assert res.returncode == 0, res.stderr
    assert "on 2 worker(s)" in res.stdout
    rows = _check_rows(tmp_path / "out", 4, 1)
    assert {r["worker"] for r in rows} == {"host-a", "host-b"}
    # the same values as the LocalCluster campaign of the same spec (worker and timings apart)
    local = run_campaign(load_spec(tmp_path / "spec.toml"), tmp_path / "local", n_workers=1)
    assert local.failed == 0 and _values(tmp_path / "out" / "results.parquet") == _values(local.results)

    other = tmp_path / "other"
    generate_certificates(other, ["campaign"])  # a certificate of another CA
    for extra in ([], ["--tls-dir", other]):
        res = _campaign_in(lan["s"], tmp_path / "spec.toml", "--out", tmp_path / f"refused{len(extra)}", "-q",
                           "--scheduler", address, "--connect-timeout", "3", *extra)
        assert res.returncode == 2, res.stderr
        assert res.stderr.count("\n") == 1 and "cannot reach the Dask scheduler" in res.stderr, res.stderr


def test_quick_example_end_to_end(tmp_path):
    """`examples/campaign_quick.toml` through the CLI on a 2-worker LocalCluster (what the docs
    promise in under 2 minutes on 2 cores): every run scored, and the errors respond to the
    noise as they must: more trigger jitter, larger amplitude errors for every processor."""
    t0 = time.perf_counter()
    res = subprocess.run([sys.executable, "-m", "bttsim_stream.cli", "campaign", EXAMPLES / "campaign_quick.toml",
                          "--out", tmp_path / "quick", "--workers", "2", "-q"], cwd=REPO, capture_output=True,
                         text=True, timeout=600, env={**os.environ, "OMP_NUM_THREADS": "1"})
    print(f"campaign_quick.toml: {time.perf_counter() - t0:.1f} s wall")
    assert res.returncode == 0, res.stderr
    assert "12 run(s)" in res.stdout and "0 failed" in res.stdout
    rows = _check_rows(tmp_path / "quick", 12, 3)
    assert {r["worker"] for r in rows} <= {"0", "1"}
    for method in ("peak", "sdof", "peak_raw"):
        mean = {j: np.mean([r["E_A_pct"] for r in rows if r["method"] == method
                            and r["acquisition.trigger_jitter_s"] == j]) for j in (5e-7, 2e-6)}
        assert mean[2e-6] > 1.5 * mean[5e-7], (method, mean)
    report = (tmp_path / "quick" / "report.md").read_text()
    assert "## By `speed.duration_s`" in report and "| peak_raw | 12 |" in report


def test_ctrl_c_keeps_every_finished_run(tmp_path):
    """Ctrl-C (SIGINT to the campaign's process group, as a terminal sends it) once runs have
    finished: exit status 130, a valid results.parquet holding exactly the finished runs, a
    report saying so; --resume then runs only the rest."""
    (tmp_path / "spec.toml").write_text(SPEC.replace("seeds = 2", "seeds = 3").replace('["peak", "sdof"]', '["peak"]'))
    cmd = [sys.executable, "-m", "bttsim_stream.cli", "campaign", tmp_path / "spec.toml", "--out", tmp_path / "out",
           "--workers", "1", "-q"]
    # SIGINT as a terminal's foreground job has it: a CI shell's background job inherits it ignored
    p = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         start_new_session=True, env={**os.environ, "OMP_NUM_THREADS": "1"},
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.monotonic() + 300
        while not list((tmp_path / "out" / "runs").glob("*.parquet")) and p.poll() is None:
            assert time.monotonic() < deadline, "no run finished"
            time.sleep(0.1)  # waiting for the first part file
        os.killpg(p.pid, signal.SIGINT)
        _, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
    assert p.returncode == 130, err
    finished = {f.stem for f in (tmp_path / "out" / "runs").glob("*.parquet")}
    rows = pq.read_table(tmp_path / "out" / "results.parquet").to_pylist()
    assert {r["run_id"] for r in rows} == finished and 1 <= len(finished) < 6
    assert len(rows) == len(finished) * N_BLADES and {r["status"] for r in rows} == {"ok"}
    assert "(interrupted: the rest did not run)" in (tmp_path / "out" / "report.md").read_text()
    resumed = run_campaign(load_spec(tmp_path / "spec.toml"), tmp_path / "out", n_workers=1, resume=True)
    assert (resumed.executed, resumed.skipped) == (6 - len(finished), len(finished))
    _check_rows(tmp_path / "out", 6, 1)

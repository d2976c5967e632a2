"""Every consumer node run on its own says whether what it received or wrote is complete.

A real simulator node and the three consumers (recorder, processor, viewer) as separate
processes on loopback (multicast scouting off). A whole run: each exits 0 and counts nothing
missing. The simulator killed mid-run (SIGKILL, once a watcher of this test has seen OPR
pulses flow): each exits 3 and counts what it misses per key -- the recorder exactly the
numbers absent from its file, the processor and the viewer the tails their logs and final
statistics name -- with no traceback anywhere.
"""

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zenoh

from _procs import REPO, stop
from bttsim_stream.bus.recording import read_recording
from bttsim_stream.bus.session import free_port, make_config

pytestmark = pytest.mark.integration

# 6 s of run-up at real speed: about 260 revolutions
SCENARIO = "[speed]\nstart_rpm = 2400.0\nend_rpm = 2800.0\nduration_s = 6.0\n"
RIG = "rig1"
ACQUISITION = [f"bttsim/{RIG}/opr", f"bttsim/{RIG}/truth"] + [f"bttsim/{RIG}/toa/{j}" for j in range(5)]
SEEN_BEFORE_KILL = 40  # OPR pulses the watcher sees before the simulator is killed


def _start(tmp_path: Path, name: str, *args) -> subprocess.Popen:
    """Node ``name``, its stdout and stderr to ``NAME.out`` and ``NAME.log`` (no pipe to fill)."""
    with open(tmp_path / f"{name}.out", "w") as out, open(tmp_path / f"{name}.log", "w") as err:
        return subprocess.Popen([sys.executable, "-m", "bttsim_stream.nodes", name, *map(str, args)], cwd=REPO,
                                stdout=out, stderr=err)


def _run(tmp_path: Path, kill_sim: bool) -> dict:
    scn = tmp_path / "scn.toml"
    scn.write_text(SCENARIO)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    via = ("-e", endpoint, "--drain-timeout", "3")
    files = {"mcap": tmp_path / "run.mcap", "summary": tmp_path / "summary.json",
             **{n: tmp_path / f"{n}.json" for n in ("recorder", "processor", "viewer")}}
    opr: list[int] = []
    procs = {}
    session = None
    # the simulator listens, every consumer (and this test's watcher) connects to it: killing it cuts them all off
    try:
        procs["recorder"] = _start(tmp_path, "recorder", "--rig", RIG, "--out", files["mcap"],
                                   "--status-file", files["recorder"], *via)
        procs["processor"] = _start(tmp_path, "processor", "--rig", RIG, "--summary", files["summary"],
                                    "--status-file", files["processor"], *via)
        procs["viewer"] = _start(tmp_path, "viewer", "--rig", RIG, "--rrd", tmp_path / "v.rrd",
                                 "--status-file", files["viewer"], *via)
        procs["sim"] = _start(tmp_path, "sim", scn, "-l", endpoint, "--wait-for", "3", "--wait-timeout", "120",
                              "--rate", "realtime")
        if kill_sim:
            deadline = time.monotonic() + 240
            while session is None:  # the watcher: once the simulator listens
                try:
                    session = zenoh.open(make_config(connect=[endpoint]))
                except zenoh.ZError:
                    assert time.monotonic() < deadline and procs["sim"].poll() is None, \
                        (tmp_path / "sim.log").read_text()
            session.declare_subscriber(f"bttsim/{RIG}/opr", lambda s: opr.append(1))
            while len(opr) < SEEN_BEFORE_KILL:  # readiness: data flow
                assert time.monotonic() < deadline and procs["sim"].poll() is None, (tmp_path / "sim.log").read_text()
                time.sleep(0.02)
            procs["sim"].send_signal(signal.SIGKILL)
        results = {}
        for name, p in procs.items():
            p.wait(timeout=300)
            results[name] = (p.returncode, (tmp_path / f"{name}.out").read_text(),
                             (tmp_path / f"{name}.log").read_text())
    finally:
        for p in procs.values():
            stop(p)
        if session is not None:
            session.close()
    for name, (_, _, err) in results.items():
        assert "Traceback" not in err, (name, err)
    return {"results": results, "files": files}


def _status(path: Path) -> dict:
    status = json.loads(path.read_text())
    assert status["state"] == "done", status
    return status["stats"]


def _absent(mcap: Path, n: int) -> dict:
    run = read_recording(mcap)
    assert not run.truncated
    seqs: dict[str, set] = {}
    for m in run.messages:
        seqs.setdefault(m.key, set()).add(m.seq)
    return {k: n - len(seqs.get(k, ())) for k in ACQUISITION}


def _n_revolutions(mcap: Path) -> int:
    from bttsim_stream.bus import codec

    meta = next(m for m in read_recording(mcap).messages if m.key.endswith("/meta"))
    return codec.decode_run_metadata(meta.payload, meta.key).body.n_revolutions


def test_a_whole_run_exits_0_on_every_consumer(tmp_path):
    r = _run(tmp_path, kill_sim=False)
    for name, (rc, _, err) in r["results"].items():
        assert rc == 0, (name, err)
    f = r["files"]
    n = _n_revolutions(f["mcap"])
    assert _absent(f["mcap"], n) == dict.fromkeys(ACQUISITION, 0)
    for name in ("recorder", "processor", "viewer"):
        stats = _status(f[name])
        assert stats["complete"] is True and stats["missing"] == 0 and stats["missing_by_key"] == {}, (name, stats)
    summary = json.loads(f["summary"].read_text())
    assert summary["complete"] and summary["revolutions_processed"] == summary["revolutions_expected"] == n


def test_a_simulator_killed_mid_run_makes_every_consumer_exit_3_and_count_per_key(tmp_path):
    r = _run(tmp_path, kill_sim=True)
    res, f = r["results"], r["files"]
    assert res["sim"][0] == -signal.SIGKILL
    for name in ("recorder", "processor", "viewer"):
        rc, _, err = res[name]
        assert rc == 3, (name, rc, err)
        assert "INCOMPLETE" in err, (name, err)
    n = _n_revolutions(f["mcap"])
    absent = _absent(f["mcap"], n)
    rec = _status(f["recorder"])
    assert rec["complete"] is False
    # the recorder: exactly the numbers absent from its file, per key
    assert {k: sum(rec["missing_by_key"].get(k, {"": 0}).values()) for k in ACQUISITION} == absent
    assert 0 < absent[f"bttsim/{RIG}/opr"] <= n - SEEN_BEFORE_KILL
    for name in ("processor", "viewer"):
        stats = _status(f[name])
        by_key = stats["missing_by_key"]
        assert stats["complete"] is False and stats["missing"] == sum(sum(m.values()) for m in by_key.values())
        for key in ACQUISITION:  # a reliable link cut: what is missing is each key's tail
            # (a consumer may be a revolution or two behind the watcher that saw SEEN_BEFORE_KILL
            # pulses on a loaded machine: it has a part of the run, not necessarily as much)
            m = by_key[key]
            assert m["head"] == m["gaps"] == 0 and 0 < m["tail"] < n, (name, key, m)
        # its log names the keys and their counts
        assert f"opr {by_key[f'bttsim/{RIG}/opr']['tail']}" in res[name][2], (name, res[name][2])
    summary = json.loads(f["summary"].read_text())
    tail = _status(f["processor"])["missing_by_key"][f"bttsim/{RIG}/opr"]["tail"]
    assert summary["complete"] is False and summary["revolutions_processed"] <= n - tail < n

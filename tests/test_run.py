"""The main job, end to end: ``bttsim run`` as a new user runs it (separate node processes)."""

import json
import signal
import subprocess
import sys
import time
from pathlib import Path


import pytest

from _procs import LineWatch
from bttsim_stream.bus.recording import read_recording

pytestmark = pytest.mark.integration

REPO = Path(__file__).resolve().parents[1]
SHORT = "[speed]\nstart_rpm = 2400.0\nend_rpm = 2800.0\nduration_s = 12.0\n"


def _rrd_verify(path: Path) -> None:
    res = subprocess.run([sys.executable, "-m", "rerun", "rrd", "verify", str(path)], capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr


def _node_pids(out: Path) -> list[int]:
    """PIDs of node processes whose command line names this output folder."""
    pids = []
    for proc in Path("/proc").iterdir():
        if proc.name.isdigit():
            try:
                cmd = (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            except OSError:
                continue
            if "bttsim_stream.nodes" in cmd and str(out) in cmd:
                pids.append(int(proc.name))
    return pids


def test_run_writes_the_three_files(tmp_path):
    scn = tmp_path / "short.toml"
    scn.write_text(SHORT)
    out = tmp_path / "out"
    res = subprocess.run([sys.executable, "-m", "bttsim_stream.cli", "run", scn, "--out", out],
                         cwd=REPO, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "revolution" in res.stderr and "rpm" in res.stderr and "remaining" in res.stderr  # progress
    summary = json.loads((out / "summary.json").read_text())
    assert summary["nd"] == 1 and summary["eo"] == 8 and len(summary["blades"]) == 29
    assert summary["mean_E_A_pct"] < 5.0 and summary["mean_E_f_pct"] < 0.5
    assert summary["complete"] is True and summary["lost"] == summary["duplicates"] == summary["rejected"] == 0
    assert summary["revolutions_processed"] == summary["revolutions_expected"] > 400
    assert "E_A" in res.stdout  # the per-blade table is printed
    rec = read_recording(out / "run.mcap")
    assert not rec.truncated
    kinds = {m.key.split("/")[2] for m in rec.messages}
    assert {"meta", "opr", "toa", "truth", "fit", "tw", "resonance"} <= kinds
    assert '"gaps": 0' in (out / "recorder.log").read_text()
    _rrd_verify(out / "views.rrd")
    assert _node_pids(out) == []


def test_ctrl_c_stops_every_node_and_leaves_valid_files(tmp_path):
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "bttsim_stream.cli", "run", "--realtime", "--out", out],
                            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        err = LineWatch(proc.stderr)
        # a few seconds of the real-time run: the progress line (plain lines when not on a
        # terminal) shows it past revolution 20
        err.wait_for(lambda line: line.startswith("revolution") and int(line.split()[1].split("/")[0]) >= 20,
                     timeout=180)
        assert len(_node_pids(out)) == 4
        proc.send_signal(signal.SIGINT)
        stdout = proc.stdout.read()  # stderr is read by the LineWatch thread
        proc.wait(timeout=120)
        stderr = err.text()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, stderr  # Ctrl-C: the partial files are valid, and marked
    assert "interrupted" in stdout
    summary = json.loads((out / "summary.json").read_text())
    assert summary["complete"] is False and summary["revolutions_processed"] < summary["revolutions_expected"]
    assert "INCOMPLETE" in stdout
    assert _node_pids(out) == []
    rec = read_recording(out / "run.mcap")
    assert not rec.truncated and len(rec.messages) > 100
    _rrd_verify(out / "views.rrd")


def test_run_through_a_zenoh_router_in_client_mode(tmp_path):
    """`bttsim router` routes between client-mode nodes: the same complete result as the
    embedded peer network."""
    from _procs import start, stop
    from bttsim_stream.bus.session import free_port

    scn = tmp_path / "short.toml"
    scn.write_text(SHORT)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = start("bttsim_stream.nodes", "router", "-l", endpoint)
    try:
        LineWatch(router.stdout).wait_for(lambda line: "router ready" in line)
        out = tmp_path / "out"
        res = subprocess.run([sys.executable, "-m", "bttsim_stream.cli", "run", scn, "--out", out, "-q",
                              "-m", "client", "-e", endpoint], cwd=REPO, capture_output=True, text=True, timeout=600)
    finally:
        assert stop(router) == 0
    assert res.returncode == 0, res.stdout + res.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["complete"] is True and summary["lost"] == 0 and summary["mean_E_A_pct"] < 5.0
    assert '"gaps": 0' in (out / "recorder.log").read_text()

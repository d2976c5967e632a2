"""The main job, end to end: ``bttsim run`` as a new user runs it (separate node processes)."""

import json
import os
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
    assert "revolution" in res.stderr and "rpm" in res.stderr  # progress
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
    recorder_log = (out / "recorder.log").read_text()
    assert '"gaps": 0' in recorder_log
    # nothing was missed, so nothing was asked again of the publishers' caches (the report,
    # which comes after the acquisition, is no gap before it came)
    assert "a gap opened" not in recorder_log and '"duplicates_skipped": 0' in recorder_log, recorder_log
    assert summary["recording"]["complete"] is True and summary["recording"]["missing"] == 0
    assert summary["recording"]["missing_by_key"] == {} and '"complete": true' in (out / "recorder.log").read_text()
    _rrd_verify(out / "views.rrd")
    from test_views import rrd_entities  # the views got the processor's final report too
    from bttsim_stream.views import paths
    assert rrd_entities(out / "views.rrd")[f"/{paths.RESONANCE_TABLE}"]["rows"] == 1
    assert _node_pids(out) == []


def test_progress_gives_the_total_then_names_each_phase_in_order(tmp_path):
    """A short run's progress on a pipe: the nodes starting, revolutions of the run's count
    (never "0/0"), the last one N/N, then each phase after it, in order."""
    import re

    scn = tmp_path / "short.toml"
    scn.write_text("[speed]\nstart_rpm = 2400.0\nend_rpm = 2500.0\nduration_s = 3.0\n")
    out = tmp_path / "out"
    res = subprocess.run([sys.executable, "-m", "bttsim_stream.cli", "run", scn, "--out", out],
                         cwd=REPO, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stdout + res.stderr
    n = json.loads((out / "summary.json").read_text())["revolutions_expected"]
    lines = res.stderr.splitlines()
    revs = [i for i, line in enumerate(lines) if line.startswith("revolution")]
    assert revs, res.stderr
    assert all(re.match(rf"revolution +\d+/{n} ", lines[i]) for i in revs), res.stderr  # the total, from the first
    assert re.match(rf"revolution +{n}/{n} ", lines[revs[-1]]) and "remaining" not in lines[revs[-1]]
    phases = ["starting the 4 nodes ...", lines[revs[0]], lines[revs[-1]], "making the report ...",
              "finishing the recording ...", "finishing the views ..."]
    where = [lines.index(p) for p in phases]
    assert where == sorted(where), res.stderr
    assert "RESONANCE" in res.stdout  # the table, after all that


def test_ctrl_c_says_stopping_at_once_and_ends_in_seconds_with_valid_files(tmp_path):
    """Ctrl-C on a run (its own process group, as a terminal's foreground job): "stopping"
    on stderr at once, every node stopped and the run over within seconds, with the
    recording, the views and the summary of what was done valid."""
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "bttsim_stream.cli", "run", "--realtime", "--out", out],
                            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        err = LineWatch(proc.stderr)
        # a few seconds of the real-time run: the progress line (plain lines when not on a
        # terminal) shows it past revolution 20
        err.wait_for(lambda line: line.startswith("revolution") and int(line.split()[1].split("/")[0]) >= 20,
                     timeout=180)
        assert len(_node_pids(out)) == 4
        t0 = time.monotonic()
        os.killpg(proc.pid, signal.SIGINT)  # what the terminal does: the whole foreground group
        err.wait_for(lambda line: "stopping" in line, timeout=30)
        t_said = time.monotonic() - t0
        stdout = proc.stdout.read()  # stderr is read by the LineWatch thread
        proc.wait(timeout=120)
        t_ended = time.monotonic() - t0
        stderr = err.text()
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert t_said < 2.0, (t_said, stderr)
    assert t_ended < 15.0, (t_ended, stderr)  # 3-5 s measured on 2 loaded cores; the bound has margin
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


# --------------------------------------------------------------------------------------
# bttsim run --web: loopback only, no orphan, Ctrl-C at once, ports checked first
# --------------------------------------------------------------------------------------


def _start_web_run(tmp_path: Path, name: str, *extra: str):
    """`bttsim run SHORT --web` on free ports; (process, stderr watch, out dir, web port, gRPC port)."""
    from bttsim_stream.bus.session import free_port

    scn = tmp_path / "short.toml"
    scn.write_text(SHORT)
    out = tmp_path / name
    web_port, grpc_port = free_port(), free_port()
    proc = subprocess.Popen([sys.executable, "-m", "bttsim_stream.cli", "run", scn, "--out", out, "--web",
                             "--web-port", str(web_port), "--grpc-port", str(grpc_port), *extra],
                            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    return proc, LineWatch(proc.stderr), out, web_port, grpc_port


def _kill(proc) -> None:
    if proc.poll() is None:
        proc.kill()
        proc.wait()


def _wait_gone(pids, timeout_s: float) -> list[int]:
    """Wait until none of ``pids`` runs (zombies count as gone); those still running."""
    from _net import alive

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        left = [p for p in pids if alive(p)]
        if not left:
            return []
        time.sleep(0.1)
    return [p for p in pids if alive(p)]


def test_web_run_listens_on_loopback_only_and_ctrl_c_ends_the_serving_at_once(tmp_path):
    """What `ss -ltnp` shows for the run's processes, during the run and while it serves
    afterwards: loopback only; the web page and its data server answer; Ctrl-C then ends it in
    seconds, with the run's own exit status."""
    from _net import children, is_loopback, listening_of

    proc, err, out, web_port, grpc_port = _start_web_run(tmp_path, "out", "--realtime")
    try:
        url = err.wait_for(lambda line: line.startswith("web viewer:"), timeout=180)
        assert f"http://127.0.0.1:{web_port}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A{grpc_port}" in url
        nodes = children(proc.pid)
        assert len(nodes) == 4
        during = listening_of([proc.pid, *nodes])
        assert ("127.0.0.1", web_port) in during and ("127.0.0.1", grpc_port) in during
        assert len(during) >= 6 and all(is_loopback(addr) for addr, _ in during), during  # + 4 zenoh
        err.wait_for(lambda line: "keeps serving until Ctrl-C" in line, timeout=300)
        after = listening_of([proc.pid, *children(proc.pid)])
        assert ("127.0.0.1", web_port) in after and all(is_loopback(addr) for addr, _ in after), after
        import urllib.request

        with urllib.request.urlopen(f"http://127.0.0.1:{web_port}/re_viewer_bg.wasm", timeout=60) as r:
            assert r.status == 200 and r.headers["Content-Type"] == "application/wasm"
        _rrd_verify(out / "views.rrd")  # complete while it serves
        t0 = time.monotonic()
        proc.send_signal(signal.SIGINT)
        stdout = proc.stdout.read()
        proc.wait(timeout=60)
        assert time.monotonic() - t0 < 20
    finally:
        _kill(proc)
    assert proc.returncode == 0, err.text()  # a complete run; the Ctrl-C only ended the serving
    assert "E_A" in stdout and "interrupted" not in stdout
    assert _wait_gone(nodes, 30) == [] and _node_pids(out) == []
    from _net import can_connect

    assert not can_connect("127.0.0.1", web_port) and not can_connect("127.0.0.1", grpc_port)


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGHUP, signal.SIGTERM], ids=["SIGKILL", "SIGHUP", "SIGTERM"])
def test_killing_a_web_run_leaves_no_node_behind(tmp_path, sig):
    """SIGKILL of the orchestrator: every node gets its parent-death SIGTERM and ends (the web
    viewer stops serving). SIGHUP and SIGTERM: handled like Ctrl-C (exit 130)."""
    from _net import can_connect, children

    proc, err, out, web_port, _ = _start_web_run(tmp_path, "out", "--realtime")
    nodes: list[int] = []
    try:
        err.wait_for(lambda line: line.startswith("revolution") and int(line.split()[1].split("/")[0]) >= 10,
                     timeout=180)
        nodes = children(proc.pid)
        assert len(nodes) == 4 and can_connect("127.0.0.1", web_port)
        proc.send_signal(sig)
        proc.wait(timeout=120)
        left = _wait_gone(nodes, 60)
        assert left == [], [Path(f"/proc/{p}/cmdline").read_bytes()[:120] for p in left]
    finally:
        _kill(proc)
        for pid in _wait_gone(nodes, 0):  # a failed test leaves no orphan either
            os.kill(pid, signal.SIGKILL)
    assert proc.returncode == (-signal.SIGKILL if sig == signal.SIGKILL else 130)
    assert _node_pids(out) == [] and not can_connect("127.0.0.1", web_port)
    rec = read_recording(out / "run.mcap")  # finalised by the recorder, even after a SIGKILL of the run
    assert not rec.truncated and len(rec.messages) > 10


def test_two_web_runs_with_their_own_ports_do_not_clash(tmp_path):
    runs = [_start_web_run(tmp_path, f"out{i}") for i in range(2)]
    try:
        for _proc, err, *_ in runs:
            err.wait_for(lambda line: "keeps serving until Ctrl-C" in line, timeout=400)
        for proc, *_ in runs:
            proc.send_signal(signal.SIGINT)
        for proc, *_ in runs:
            proc.wait(timeout=60)
    finally:
        for proc, *_ in runs:
            _kill(proc)
    for proc, err, out, *_ in runs:
        assert proc.returncode == 0, err.text()
        summary = json.loads((out / "summary.json").read_text())
        assert summary["complete"] is True and summary["lost"] == 0
        _rrd_verify(out / "views.rrd")


@pytest.mark.parametrize("which", ["--web-port", "--grpc-port"])
def test_a_busy_web_port_is_a_one_line_error_before_the_run(tmp_path, which):
    import socket

    from bttsim_stream.bus.session import free_port

    ports = {"--web-port": free_port(), "--grpc-port": free_port()}
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", ports[which]))
        busy.listen()
        t0 = time.monotonic()
        res = subprocess.run([sys.executable, "-m", "bttsim_stream.cli", "run", "--out", tmp_path / "out", "--web",
                              "--web-port", str(ports["--web-port"]), "--grpc-port", str(ports["--grpc-port"])],
                             cwd=REPO, capture_output=True, text=True, timeout=120)
    assert res.returncode == 2, res.stdout + res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("bttsim: error:") and which in lines[0]
    assert f"127.0.0.1:{ports[which]}" in lines[0] and "in use" in lines[0]
    assert time.monotonic() - t0 < 30 and not (tmp_path / "out").exists()  # nothing started


def test_signal_chain_example_reports_its_missing_pulses_and_keeps_the_amplitude(tmp_path):
    """examples/signal_chain.toml (capacitive probes, constant-fraction trigger armed just above
    the pulse peak) on a short run-up through the resonance: about 1 % of the TOAs do not
    trigger; the processor counts exactly the NaN TOAs the recording holds, prints them, and its
    resonance amplitude stays within 3 % of the truth."""
    import tomllib

    import numpy as np

    from bttsim_stream.bus import codec
    from bttsim_stream.scenario import dumps_toml, scenario_from_dict

    table = tomllib.loads((REPO / "examples" / "signal_chain.toml").read_text())
    table["speed"] = {"start_rpm": 2400.0, "end_rpm": 2800.0, "duration_s": 12.0}
    scn = tmp_path / "signal.toml"
    scn.write_text(dumps_toml(scenario_from_dict(table)))
    out = tmp_path / "out"
    res = subprocess.run([sys.executable, "-m", "bttsim_stream.cli", "run", scn, "--out", out],
                         cwd=REPO, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stdout + res.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["complete"] is True and summary["status"] == "resonance"
    rec = read_recording(out / "run.mcap")
    toa = {(m.key, d.header.revolution): d.body for m in rec.messages if "/toa/" in m.key
           for d in [codec.decode_toa_batch(m.payload, m.key)]}
    truth = [codec.decode_truth(m.payload, m.key) for m in rec.messages if m.key.endswith("/truth")]
    toa_s = np.array([b.toa_s for b in toa.values()])
    ticks = np.array([b.toa_ticks for b in toa.values()])
    missing = np.isnan(toa_s)
    assert toa_s.size == summary["revolutions_processed"] * 29 * 5
    assert 0.005 < missing.mean() < 0.02, missing.mean()
    assert np.all(ticks[missing] == -1) and np.all(ticks[~missing] >= 0)
    assert summary["missing_toas"] == int(missing.sum())
    assert f"missing pulses: {int(missing.sum())} TOAs did not trigger" in res.stdout
    # the published TOAs are the trigger's, not the exact ones: they differ from the truth
    # by the constant-fraction crossing (microseconds), never by a blade pitch
    assert truth, "the recording holds the truth stream"
    by_rev = {d.header.revolution: d.body.toa_s[0] for d in truth}
    err = np.concatenate([toa[(k, r)].toa_s - by_rev[r][:, toa[(k, r)].probe] for (k, r) in toa])
    err = err[np.isfinite(err)]
    assert 1e-6 < np.median(np.abs(err)) < 50e-6 and np.max(np.abs(err)) < 200e-6
    assert summary["mean_E_A_pct"] < 3.0
    assert _node_pids(out) == []


def test_drain_timeout_reaches_every_consumer_and_a_bad_one_is_refused(tmp_path):
    """``bttsim run --drain-timeout S`` is the recorder's, the processor's and the viewer's
    own flag (not the simulator's); a negative or infinite one is a one-line error, exit 2."""
    from bttsim_stream.orchestrate import plan_run

    plan = plan_run(None, str(tmp_path / "out"), drain_timeout_s=4.5)
    try:
        for node in ("recorder", "processor", "viewer"):
            cmd = plan.commands[node]
            assert cmd[cmd.index("--drain-timeout") + 1] == "4.5", cmd
        assert "--drain-timeout" not in plan.commands["sim"]
    finally:
        import shutil
        shutil.rmtree(plan.status_dir, ignore_errors=True)
    for bad in ("-1", "inf", "nan", "soon"):
        res = subprocess.run([sys.executable, "-m", "bttsim_stream.cli", "run", "--out", tmp_path / "o2",
                              "--drain-timeout", bad], cwd=REPO, capture_output=True, text=True, timeout=60)
        lines = res.stderr.strip().splitlines()
        assert res.returncode == 2 and len(lines) == 1 and "--drain-timeout" in lines[0], res.stderr
        assert not (tmp_path / "o2").exists()

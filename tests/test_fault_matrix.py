"""The fault matrix of ``bttsim run --realtime``: every fault ends in one of two honest ways.

Either the recording is complete, identical to a clean run's message by message (key,
sequence number, payload, log time), and the exit status is 0; or the exit status is non-zero
and what is missing is counted: per key in the recording -- exactly the numbers absent from
``run.mcap`` -- or, with the acquisition recorded whole (the recorder catches up from the
simulator's caches), in the processor's result (``lost``); or the recorder itself failed, and
the run says so. Never exit 0 with
anything missing; never a traceback in any log.

Faults: SIGSTOP of each node for 5 s, 15 s and 40 s (beyond the 30 s Zenoh lease), SIGKILL of
each node, a router killed and restarted in the three-namespace layout of
``docs/deployment.md`` (root and ``ip netns``), 20 % packet loss (nftables, iptables or
``tc netem``, the first the kernel allows; skipped where none does). Each fault starts
mid-run: once the recorder's first chunk is on disk. The long cases are marked ``slow``; a
stalled and a killed recorder are the quick ones.
"""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from _procs import LineWatch, stop
from bttsim_stream.bus.recording import read_recording
from test_deployment import ROUTER_ADDR, _node, namespaces  # noqa: F401 (a fixture)
from test_faults import _finish, _node_pid, _wait_mid_run

pytestmark = pytest.mark.integration

REPO = Path(__file__).resolve().parents[1]
# about 260 revolutions, 6 s at real speed: long enough for a fault mid-run
SCENARIO = "[speed]\nstart_rpm = 2400.0\nend_rpm = 2800.0\nduration_s = 6.0\n"
NODES = ("sim", "processor", "recorder", "viewer")
RIG = "rig1"


def _start(tmp_path: Path, tag: str):
    scn = tmp_path / "scn.toml"
    scn.write_text(SCENARIO)
    out = tmp_path / tag
    proc = subprocess.Popen([sys.executable, "-m", "bttsim_stream.cli", "run", str(scn), "--out", str(out), "--quiet",
                             "--realtime"], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)
    return proc, out


def _data(run) -> list:
    return sorted((m.key, m.seq, m.payload, m.log_time_ns) for m in run.messages)


#: ``bttsim run``'s recorder follows the processor: its resonance report is one expected message
REPORT = {"resonance": 1}


def _absent(run, key: str, n: int | None) -> int:
    seqs = {m.seq for m in run.messages if m.key == key}
    return (n if n is not None else (max(seqs) + 1 if seqs else 0)) - len(seqs)


def check_honest(rc: int, text: str, out: Path, clean: list, logs=NODES) -> str:
    """The matrix's invariant; returns which way the run ended ("complete" or "incomplete")."""
    for name in logs:
        log = out / f"{name}.log"
        assert "Traceback" not in (log.read_text() if log.exists() else ""), (name, log.read_text())
    assert "Traceback" not in text, text
    run = read_recording(out / "run.mcap")
    if rc == 0:
        assert not run.truncated and _data(run) == clean, "exit 0 with a recording other than the clean run's"
        return "complete"
    rec = json.loads((out / "summary.json").read_text())["recording"] if (out / "summary.json").exists() else None
    if rec is None or rec["missing"] is None:  # the recorder gave no statistics: it failed, and the run says so
        assert "the recorder node failed" in text, text
        return "incomplete"
    summary = json.loads((out / "summary.json").read_text())
    if rec["complete"] and summary["complete"]:  # the record and the result whole: the views are not, and say so
        assert ("the viewer node failed" in text or "the views miss" in text) and _data(run) == clean, text
        return "node failed" if "node failed" in text else "views incomplete"
    if rec["complete"]:  # then the result is what is incomplete: the processor lost data, and says how much
        short = summary["revolutions_processed"] < summary["revolutions_expected"]
        assert summary["complete"] is False and (summary["lost"] or short or summary["status"] == "none"), summary
        acq = ("/meta", "/opr", "/truth", "/toa/")  # the acquisition is whole: the clean run's

        def acquisition(msgs):
            return [m for m in msgs if any(a in m[0] for a in acq)]

        assert acquisition(_data(run)) == acquisition(clean)
        return "incomplete result"
    meta = json.loads(run.metadata["bttsim.recorder"]["missing_by_key"]) if "bttsim.recorder" in run.metadata \
        else rec["missing_by_key"]
    assert meta == rec["missing_by_key"]
    n = summary["revolutions_expected"]
    acquisition = [f"bttsim/{RIG}/opr", f"bttsim/{RIG}/truth"] + [f"bttsim/{RIG}/toa/{j}" for j in range(5)]
    for key in acquisition:  # every acquisition key counted to its last number
        got = rec["missing_by_key"].get(key, {"head": 0, "gaps": 0, "tail": 0})
        assert sum(got.values()) == _absent(run, key, n), (key, got)
    for key, got in rec["missing_by_key"].items():
        count = n if key in acquisition else REPORT.get(key.rsplit("/", 1)[-1])
        assert sum(got.values()) == _absent(run, key, count), (key, got)
    assert rec["missing"] > 0 or "conflict" in rec["incomplete"], rec
    return "incomplete"


@pytest.fixture(scope="module")
def clean(tmp_path_factory) -> list:
    proc, out = _start(tmp_path_factory.mktemp("clean"), "clean")
    rc, text = _finish(proc)
    assert rc == 0, text
    run = read_recording(out / "run.mcap")
    assert not run.truncated
    return _data(run)


def _stop_case(node: str, seconds: float, marks=()):
    return pytest.param(node, seconds, marks=marks, id=f"{node}-{seconds:g}s")


STOPS = [_stop_case("recorder", 5)] + [
    _stop_case(n, s, marks=pytest.mark.slow) for s in (5, 15, 40) for n in NODES if (n, s) != ("recorder", 5)]


@pytest.mark.parametrize("node,seconds", STOPS)
def test_a_stopped_node(tmp_path, clean, node, seconds):
    proc, out = _start(tmp_path, f"stop-{node}")
    try:
        _wait_mid_run(proc, out)
        pid = _node_pid(out, node)
        assert pid is not None
        os.kill(pid, signal.SIGSTOP)
        try:
            time.sleep(seconds)  # the fault itself
        finally:
            os.kill(pid, signal.SIGCONT)
    finally:
        rc, text = _finish(proc)
    way = check_honest(rc, text, out, clean)
    print(f"SIGSTOP {node} {seconds:g} s: exit {rc}, {way}; recording: {_recording_line(out)}")


@pytest.mark.parametrize("node", [pytest.param(n, marks=() if n == "recorder" else pytest.mark.slow) for n in NODES])
def test_a_killed_node(tmp_path, clean, node):
    proc, out = _start(tmp_path, f"kill-{node}")
    try:
        _wait_mid_run(proc, out)
        pid = _node_pid(out, node)
        assert pid is not None
        os.kill(pid, signal.SIGKILL)
    finally:
        rc, text = _finish(proc)
    assert rc != 0 and f"the {node} node failed (killed by SIGKILL" in text, text
    way = check_honest(rc, text, out, clean, logs=[n for n in NODES if n != node])
    print(f"SIGKILL {node}: exit {rc}, {way}; recording: {_recording_line(out)}")


# -- the three-namespace layout --------------------------------------------------------------

def _wait_file(path: Path, predicate, timeout_s: float = 120.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if path.exists():
            try:
                if predicate(json.loads(path.read_text())):
                    return
            except ValueError:
                pass
        time.sleep(0.05)
    pytest.fail(f"{path} never said so")


def _router(ns: dict):
    router = _node(ns["router"], "router", "-l", f"tcp/{ROUTER_ADDR['sim']}:7447",
                   "-l", f"tcp/{ROUTER_ADDR['proc']}:7447")
    LineWatch(router.stdout).wait_for(lambda line: "router ready" in line)
    return router


@pytest.mark.slow
def test_a_router_killed_and_restarted_mid_run(namespaces, clean, tmp_path):  # noqa: F811
    """Router, recorder + processor behind it, a real-time simulator: the router is killed
    (SIGKILL) once the run is publishing, and started again on the same addresses. The
    consumers must outlive it (they reconnect and wait for the simulator's end), and the
    recorder's verdict must be honest."""
    ns = namespaces
    scn = tmp_path / "scn.toml"
    scn.write_text(SCENARIO)
    out = tmp_path / "out"
    out.mkdir()
    procs = []
    try:
        router = _router(ns)
        procs.append(router)
        via = ["-m", "client", "-e", f"tcp/{ROUTER_ADDR['proc']}:7447"]
        recorder = _node(ns["proc"], "recorder", "--rig", RIG, "--out", out / "run.mcap", "--until", "sim,processor",
                         "--status-file", out / "recorder.json", *via)
        processor = _node(ns["proc"], "processor", "--rig", RIG, "--summary", out / "processor.json", *via)
        sim = _node(ns["sim"], "sim", scn, "--wait-for", "2", "--rate", "realtime", "-m", "client",
                    "-e", f"tcp/{ROUTER_ADDR['sim']}:7447")
        procs += [recorder, processor, sim]
        _wait_file(out / "recorder.json", lambda s: s["state"] == "ready")  # the run is about to publish
        time.sleep(2.0)  # the fault's moment: a third of the way into the run
        router.kill()
        router.wait()
        procs.append(_router(ns))
        results = {}
        for name, p in (("sim", sim), ("processor", processor), ("recorder", recorder)):
            stdout, err = p.communicate(timeout=300)
            (out / f"{name}.log").write_text(err)
            results[name] = (p.returncode, stdout, err)
    finally:
        for p in reversed(procs):
            stop(p)
    for name, (rc, _, err) in results.items():
        assert "Traceback" not in err, (name, err)
        assert rc in (0, 3), (name, rc, err)
    rc, stdout, err = results["recorder"]
    stats = json.loads(stdout.strip().splitlines()[-1])
    run = read_recording(out / "run.mcap")
    assert not run.truncated
    processed = json.loads((out / "processor.json").read_text())
    if rc == 0:
        assert stats["complete"]
        if processed["complete"]:
            assert _data(run) == clean
        else:  # the acquisition is whole; the results are those of a processor that says what it lost
            assert processed["lost"] > 0
            acq = ("/meta", "/opr", "/truth", "/toa/")
            assert [m for m in _data(run) if any(a in m[0] for a in acq)] == \
                [m for m in clean if any(a in m[0] for a in acq)]
    else:
        assert not stats["complete"] and stats["missing"] > 0
        for key, got in stats["missing_by_key"].items():
            assert sum(got.values()) == _absent(run, key, _expected(run, key)), (key, got)


@pytest.mark.slow
def test_a_run_through_a_router_killed_and_restarted_mid_run(namespaces, clean, tmp_path):  # noqa: F811
    """``bttsim run -m client -e tcp/ROUTER``: every node of the run (and the run's own session)
    in one namespace, a client of a ``bttsim router`` in another, the only way between them.
    The router is killed (SIGKILL) once the recorder has written data, and started again on the
    same addresses: the run either records the whole clean run and exits 0, or exits non-zero
    and counts per key what it misses; no traceback in any log."""
    ns = namespaces
    scn = tmp_path / "scn.toml"
    scn.write_text(SCENARIO)
    out = tmp_path / "out"
    router = _router(ns)
    procs = [router]
    try:
        proc = subprocess.Popen(["ip", "netns", "exec", ns["proc"], sys.executable, "-m", "bttsim_stream.cli", "run",
                                 str(scn), "--out", str(out), "--quiet", "--realtime", "-m", "client",
                                 "-e", f"tcp/{ROUTER_ADDR['proc']}:7447"], cwd=REPO, stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True, start_new_session=True)
        try:
            _wait_mid_run(proc, out)
            router.kill()  # the fault
            router.wait()
            procs.append(_router(ns))
        finally:
            rc, text = _finish(proc)
    finally:
        for p in reversed(procs):
            stop(p)
    way = check_honest(rc, text, out, clean)
    print(f"router restart under bttsim run: exit {rc}, {way}; recording: {_recording_line(out)}")


def _expected(run, key: str) -> int | None:
    """The run's message count of an acquisition key (from the OPR count the metadata fixes)."""
    from bttsim_stream.bus import codec

    meta = next(m for m in run.messages if m.key.endswith("/meta"))
    n = codec.decode_run_metadata(meta.payload, meta.key).body.n_revolutions
    return n if key.rsplit("/", 2)[-1] in ("opr", "truth") or "/toa/" in key else None


#: Ways to drop 20 % of the packets that reach a namespace's loopback, tried in turn (the
#: kernel may lack netem; nftables' numgen and iptables' statistic match need no qdisc). Each
#: leaves a counter of the packets it dropped, printed by LOSS_COUNT.
LOSS_RULES = {
    "nftables": ("nft add table inet loss && nft add chain inet loss in '{ type filter hook input priority 0; }' "
                 "&& nft add rule inet loss in numgen random mod 100 '<' 20 counter drop",
                 "nft list chain inet loss in"),
    "iptables": ("iptables -A INPUT -m statistic --mode random --probability 0.2 -j DROP",
                 "iptables -L INPUT -v -n -x"),
    "tc netem": ("tc qdisc add dev lo root netem loss 20%", "tc -s qdisc show dev lo"),
}


def _loss_rule() -> tuple[str, str, str]:
    """``(name, install, count)`` of the first way to drop packets that works here, in a network
    namespace of this test's own (``unshare -rn``); skips with what each one said."""
    tried = []
    for name, (install, count) in LOSS_RULES.items():
        res = subprocess.run(["unshare", "-rn", "sh", "-c", f"ip link set lo up && {install}"], capture_output=True,
                             text=True, timeout=30)
        if res.returncode == 0:
            return name, install, count
        tried.append(f"{name}: {(res.stderr.strip() or res.stdout.strip()).splitlines()[-1:] or res.returncode}")
    pytest.skip("no way to drop packets in a network namespace here: " + "; ".join(map(str, tried)))


def _dropped(name: str, text: str) -> int:
    """Packets the rule dropped, from its counter's listing."""
    import re

    pattern = {"nftables": r"counter packets (\d+)", "iptables": r"^\s*(\d+)\s+\d+\s+DROP",
               "tc netem": r"dropped (\d+)"}[name]
    return sum(int(n) for n in re.findall(pattern, text, flags=re.MULTILINE))


@pytest.mark.slow
def test_packet_loss(tmp_path, clean):
    """20 % of the packets dropped at random on loopback inside a network namespace of the
    test's own (every node of the run in it): TCP retransmits, and the run either records the
    whole clean run and exits 0 or says, per key, what it misses."""
    name, install, count = _loss_rule()
    scn = tmp_path / "scn.toml"
    scn.write_text(SCENARIO)
    out = tmp_path / "loss"
    script = f'ip link set lo up && {install} && "$@"; rc=$?; echo "--- dropped"; {count}; exit $rc'
    res = subprocess.run(["unshare", "-rn", "sh", "-c", script, "sh", sys.executable, "-m", "bttsim_stream.cli", "run",
                          str(scn), "--out", str(out), "-q", "--realtime"], cwd=REPO, capture_output=True, text=True,
                         timeout=900)
    text, listing = (res.stdout + res.stderr).split("--- dropped", 1) if "--- dropped" in res.stdout else \
        (res.stdout + res.stderr, "")
    assert _dropped(name, listing) > 100, (name, listing)  # the loss happened
    way = check_honest(res.returncode, text, out, clean)
    print(f"packet loss ({name}): exit {res.returncode}, {way}; {_dropped(name, listing)} packets dropped; "
          f"recording: {_recording_line(out)}")


def _recording_line(out: Path) -> str:
    try:
        return json.loads((out / "summary.json").read_text())["recording"].get("incomplete") or "complete"
    except (OSError, ValueError, KeyError, AttributeError):
        return "no summary"

"""A multi-host deployment, for real: three network namespaces joined through a `bttsim router`.

Layout (``docs/deployment.md``), each namespace with its own network stack and no route to
the others but the router's links::

    [ns sim]  sim  --10.77.1.1 ---- 10.77.1.2--+
                                                [ns router]  bttsim router
    [ns proc] processor, recorder --10.77.2.1 ---- 10.77.2.2--+

Every node is a Zenoh client of the router (the only way across), multicast scouting off.
The result (summary and every recorded message) must equal a loopback run's, with 0 lost,
without security and with mutual TLS + access control (certificates made here, valid for the
router's addresses). Needs root and ``ip netns``; skipped with the reason otherwise.
"""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from _procs import LineWatch, stop
from bttsim_stream.bus.certs import IDENTITIES, generate_certificates
from bttsim_stream.bus.recording import read_recording

pytestmark = pytest.mark.integration

REPO = Path(__file__).resolve().parents[1]
SHORT = "[speed]\nstart_rpm = 2400.0\nend_rpm = 2800.0\nduration_s = 12.0\n"
ROUTER_ADDR = {"sim": "10.77.1.2", "proc": "10.77.2.2"}


def _ip(*args, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=30, check=check)


def _netns_or_skip() -> None:
    if os.geteuid() != 0 or shutil.which("ip") is None:
        pytest.skip("network namespaces need root and iproute2 (ip netns)")
    probe = f"bttsim-probe-{os.getpid()}"
    res = _ip("netns", "add", probe, check=False)
    if res.returncode != 0:
        pytest.skip(f"ip netns add is not permitted here: {res.stderr.strip()}")
    _ip("netns", "del", probe, check=False)


@pytest.fixture
def namespaces():
    """Three namespaces ``sim``, ``router``, ``proc`` and two veth links; deleted afterwards."""
    _netns_or_skip()
    ns = {k: f"bt{os.getpid()}{k}" for k in ("sim", "router", "proc")}
    try:
        for name in ns.values():
            _ip("netns", "add", name)
            _ip("-n", name, "link", "set", "lo", "up")
        for side, net in (("sim", 1), ("proc", 2)):
            a, b = f"v{side}", f"vr{side}"  # interface names are per namespace
            _ip("-n", ns[side], "link", "add", a, "type", "veth", "peer", "name", b, "netns", ns["router"])
            _ip("-n", ns[side], "addr", "add", f"10.77.{net}.1/24", "dev", a)
            _ip("-n", ns["router"], "addr", "add", f"10.77.{net}.2/24", "dev", b)
            _ip("-n", ns[side], "link", "set", a, "up")
            _ip("-n", ns["router"], "link", "set", b, "up")
        # no route between the outer namespaces: only the router's links cross
        assert _ip("netns", "exec", ns["sim"], "ping", "-c", "1", "-W", "1", "10.77.2.1", check=False).returncode != 0
        yield ns
    finally:
        for name in ns.values():
            _ip("netns", "del", name, check=False)


def _node(ns: str, *args) -> subprocess.Popen:
    """A node in namespace ``ns`` (``ip netns exec`` execs it: the PID is the node's)."""
    return subprocess.Popen(["ip", "netns", "exec", ns, sys.executable, "-m", "bttsim_stream.nodes",
                             *map(str, args)], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _result(out: Path) -> tuple[dict, list]:
    rec = read_recording(out / "run.mcap")
    assert not rec.truncated
    summary = json.loads((out / "summary.json").read_text())
    # `bttsim run` adds what its recorder saw; a processor node alone writes the rest
    recording = summary.pop("recording", None)
    assert recording is None or (recording["complete"] and recording["missing"] == 0), recording
    return summary, sorted((m.key, m.seq, m.payload, m.log_time_ns) for m in rec.messages)


@pytest.fixture(scope="module")
def loopback(tmp_path_factory) -> tuple[Path, tuple[dict, list]]:
    """The scenario and a loopback ``bttsim run`` of it (no router, no namespaces)."""
    d = tmp_path_factory.mktemp("loopback")
    scn = d / "short.toml"
    scn.write_text(SHORT)
    res = subprocess.run([sys.executable, "-m", "bttsim_stream.cli", "run", scn, "--out", d / "out", "-q"],
                         cwd=REPO, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stdout + res.stderr
    return scn, _result(d / "out")


def _deploy(ns: dict, scn: Path, out: Path, security: list, scheme: str) -> None:
    """Router, then processor + recorder, then the simulator; every process stopped by PID."""
    out.mkdir()
    procs = []
    try:
        router = _node(ns["router"], "router", *security,
                       "-l", f"{scheme}/{ROUTER_ADDR['sim']}:7447", "-l", f"{scheme}/{ROUTER_ADDR['proc']}:7447")
        procs.append(router)
        LineWatch(router.stdout).wait_for(lambda line: "router ready" in line)
        via_proc = ["-m", "client", "-e", f"{scheme}/{ROUTER_ADDR['proc']}:7447", *security]
        recorder = _node(ns["proc"], "recorder", "--rig", "rig1", "--out", out / "run.mcap", "--until",
                         "sim,processor", *via_proc)
        processor = _node(ns["proc"], "processor", "--rig", "rig1", "--summary", out / "summary.json", *via_proc)
        procs += [recorder, processor]
        # the simulator starts publishing once both consumers' tokens have crossed the router
        sim = _node(ns["sim"], "sim", scn, "--wait-for", "2", "-m", "client",
                    "-e", f"{scheme}/{ROUTER_ADDR['sim']}:7447", *security)
        procs.append(sim)
        for name, p in (("sim", sim), ("processor", processor), ("recorder", recorder)):
            stdout, err = p.communicate(timeout=300)
            (out / f"{name}.log").write_text(err)
            assert p.returncode == 0, f"{name}: {err}"
    finally:
        for p in reversed(procs):
            stop(p)
    stats = json.loads(stdout.strip().splitlines()[-1])  # the recorder's statistics
    assert stats["gaps"] == 0 and stats["complete"] and stats["missing"] == 0, stats


def test_three_namespaces_through_a_router_equal_the_loopback_run(namespaces, loopback, tmp_path):
    scn, clean = loopback
    _deploy(namespaces, scn, tmp_path / "out", [], "tcp")
    summary, messages = _result(tmp_path / "out")
    assert summary["complete"] is True and summary["lost"] == 0
    assert (summary, messages) == clean


def test_three_namespaces_with_mtls_and_access_control_equal_the_loopback_run(namespaces, loopback, tmp_path):
    scn, clean = loopback
    certs = tmp_path / "certs"
    generate_certificates(certs, IDENTITIES, hosts=tuple(ROUTER_ADDR.values()))
    _deploy(namespaces, scn, tmp_path / "out", ["--tls-dir", certs], "tls")
    summary, messages = _result(tmp_path / "out")
    assert summary["complete"] is True and summary["lost"] == 0
    assert (summary, messages) == clean

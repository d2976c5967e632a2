"""Security switched on: mutual TLS and access control (certificates made here), forgers refused.

Every run is a real ``bttsim run`` (separate node processes, real Zenoh sessions on
127.0.0.1, multicast scouting off) of a 12 s run-up; results are compared with one clean
loopback run without security: the summary and every recorded message (key, sequence number,
payload, log time) must be identical.
"""

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

from _procs import LineWatch, start, stop
from bttsim_stream.bus.certs import IDENTITIES, generate_certificates
from bttsim_stream.bus.recording import read_recording
from bttsim_stream.bus.session import free_port

pytestmark = pytest.mark.integration

REPO = Path(__file__).resolve().parents[1]
FORGER = Path(__file__).resolve().parent / "_forger.py"
SHORT = "[speed]\nstart_rpm = 2400.0\nend_rpm = 2800.0\nduration_s = 12.0\n"


@pytest.fixture(scope="module")
def scenario(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("scn") / "short.toml"
    path.write_text(SHORT)
    return path


@pytest.fixture(scope="module")
def certs(tmp_path_factory) -> Path:
    """Certificates of every identity and of an ``intruder`` (valid, signed by the same CA)."""
    d = tmp_path_factory.mktemp("certs")
    generate_certificates(d, IDENTITIES + ("intruder",))
    return d


@pytest.fixture(scope="module")
def foreign_certs(tmp_path_factory) -> Path:
    """The same names, signed by another CA."""
    d = tmp_path_factory.mktemp("foreign")
    generate_certificates(d, IDENTITIES)
    return d


def bttsim(*args, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "bttsim_stream.cli", *map(str, args)], cwd=REPO,
                          capture_output=True, text=True, timeout=timeout)


def result(out: Path) -> tuple[dict, list]:
    """The summary and every recorded message of a run."""
    summary = json.loads((out / "summary.json").read_text())
    rec = read_recording(out / "run.mcap")
    assert not rec.truncated
    return summary, sorted((m.key, m.seq, m.payload, m.log_time_ns) for m in rec.messages)


@pytest.fixture(scope="module")
def clean(scenario, tmp_path_factory) -> tuple[dict, list]:
    """A loopback run without security."""
    out = tmp_path_factory.mktemp("clean") / "out"
    res = bttsim("run", scenario, "--out", out, "-q")
    assert res.returncode == 0, res.stdout + res.stderr
    summary, messages = result(out)
    assert summary["complete"] is True and summary["lost"] == 0 and len(messages) > 5000
    return summary, messages


def start_forger(scenario, endpoint, *flags):
    return subprocess.Popen([sys.executable, str(FORGER), str(scenario), "-e", endpoint, *map(str, flags)],
                            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def start_router(endpoint, *flags):
    router = start("bttsim_stream.nodes", "router", "-l", endpoint, *flags)
    LineWatch(router.stdout).wait_for(lambda line: "router ready" in line)
    return router


def test_certs_command_and_bad_security_flags_are_one_line_errors(tmp_path):
    res = bttsim("certs", tmp_path / "c", "--host", "10.0.0.1", "--host", "bttsim-router")
    assert res.returncode == 0, res.stderr
    assert {p.name for p in (tmp_path / "c").iterdir()} == {"ca.pem", "ca-key.pem"} | {
        f"{n}{s}" for n in IDENTITIES for s in (".pem", "-key.pem", ".json5")}
    assert (tmp_path / "c" / "ca-key.pem").stat().st_mode & 0o077 == 0  # private
    cases = [
        (("certs", tmp_path / "c"), "exists"),  # a new CA would invalidate the old certificates
        (("certs", tmp_path / "d", "--names", "sim,a/b"), "bad certificate name"),
        (("node", "recorder", "--out", tmp_path / "x.mcap", "--tls-dir", tmp_path / "nothing"), "no such"),
        (("node", "recorder", "--out", tmp_path / "x.mcap", "--tls-dir", tmp_path / "c", "-l", "tcp/127.0.0.1:1"),
         "must be tls/"),
        (("node", "recorder", "--out", tmp_path / "x.mcap", "--tls-ca", tmp_path / "c" / "ca.pem"), "go together"),
        (("run", "--out", tmp_path / "o", "--tls-dir", tmp_path / "nothing"), "no such"),
    ]
    for args, words in cases:
        res = bttsim(*args, timeout=60)
        assert res.returncode == 2 and words in res.stderr, (args, res.stderr)
        assert len(res.stderr.strip().splitlines()) == 1, res.stderr


def test_run_with_mtls_and_access_control_equals_the_clean_run(scenario, certs, clean, tmp_path):
    out = tmp_path / "out"
    res = bttsim("run", scenario, "--out", out, "-q", "--tls-dir", certs)
    assert res.returncode == 0, res.stdout + res.stderr
    assert result(out) == clean
    assert '"gaps": 0' in (out / "recorder.log").read_text()


def test_forgers_are_refused_and_a_secured_run_is_bit_identical_to_a_clean_one(scenario, certs, foreign_certs,
                                                                              clean, tmp_path):
    """Through a secured router: forgers without a certificate, or with one of another CA,
    cannot connect (exit 2, one line); forgers with valid certificates of other identities
    (the viewer's, an unknown ``intruder``) connect, their publishers even match the run's
    subscribers, yet nothing they put (TOA, truth, OPR, metadata, results, a liveliness token
    posing as the simulator) reaches the run."""
    endpoint = f"tls/127.0.0.1:{free_port()}"
    router = start_router(endpoint, "--tls-dir", certs)
    forgers = {}
    try:
        refused = {"no certificate": start_forger(scenario, endpoint, "--connect-timeout", 3),
                   "another CA": start_forger(scenario, endpoint, "--connect-timeout", 3, "--tls-dir", foreign_certs,
                                              "--tls-name", "sim")}
        forgers = {"viewer": start_forger(scenario, endpoint, "--tls-dir", certs, "--tls-name", "viewer",
                                          "--pose-as-sim"),
                   "intruder": start_forger(scenario, endpoint, "--tls-dir", certs, "--tls-name", "intruder",
                                            "--pose-as-sim")}
        for name, f in forgers.items():
            assert "forger connected" in f.stdout.readline(), (name, f.stderr.read() if f.poll() is not None else "")
        out = tmp_path / "out"
        res = bttsim("run", scenario, "--out", out, "-q", "-m", "client", "-e", endpoint, "--tls-dir", certs)
        for name, f in refused.items():
            _, err = f.communicate(timeout=60)
            assert f.returncode == 2, (name, err)
            assert err.startswith("bttsim: error: cannot reach") and len(err.strip().splitlines()) == 1, (name, err)
        stats = {}
        for name, f in forgers.items():
            assert stop(f) == 0, f.stderr.read()
            stats[name] = json.loads(f.stdout.read().strip().splitlines()[-1])
    finally:
        for f in [*forgers.values(), *locals().get("refused", {}).values()]:
            stop(f)
        assert stop(router) == 0
    assert res.returncode == 0, res.stdout + res.stderr
    assert stats["viewer"]["put"] > 200 and stats["viewer"]["matched"] > 100, stats  # they would have arrived
    assert stats["intruder"]["put"] > 200 and stats["intruder"]["matched"] == 0, stats  # sees nobody
    assert result(out) == clean


def test_without_security_the_same_forger_reaches_the_run_and_the_recorder_refuses_it(scenario, clean, tmp_path):
    """The control experiment: the forger of the test above, against the same layout without
    security, gets its messages to the recorder (only its batches of a probe that does not
    exist: the rest is the forgery tests' business), which refuses them: counted, kept on
    ``rejected/`` channels, the data channels the clean run's."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = start_router(endpoint)
    forger = start_forger(scenario, endpoint, "--only", "toa/7", "--once")
    try:
        assert "forger connected" in forger.stdout.readline()
        out = tmp_path / "out"
        res = bttsim("run", scenario, "--out", out, "-q", "-m", "client", "-e", endpoint)
        assert stop(forger) == 0
        stats = json.loads(forger.stdout.read().strip().splitlines()[-1])
    finally:
        stop(forger)
        assert stop(router) == 0
    _, messages = result(out)
    assert res.returncode == 0, res.stdout + res.stderr
    assert stats["put"] == stats["matched"] == 100, stats
    assert messages == clean[1]
    refused = [m for m in read_recording(out / "run.mcap", "rejected/**").messages]
    # every forgery the recorder received is refused, counted and kept apart; the forger puts
    # its first message once any subscriber matches, which may be before the recorder's (the
    # processor's or the viewer's): a few may never reach the recorder at all
    counted = json.loads((out / "summary.json").read_text())["recording"]["rejected"]
    assert {m.key for m in refused} == {"rejected/bttsim/rig1/toa/7"}
    assert len(refused) == counted and 90 <= counted <= 100, (len(refused), counted)


def test_a_node_refused_by_an_mtls_peer_fails_instead_of_recording_nothing(scenario, certs, foreign_certs, tmp_path):
    """A recorder without a certificate, or with one of another CA, against an mTLS simulator
    (configured with the file ``bttsim certs`` writes): exit 2 with one line within the connect
    timeout (it used to record 0 messages and exit 0); the simulator, which finds nobody, fails too."""
    endpoint = f"tls/127.0.0.1:{free_port()}"
    from bttsim_stream.bus.security import write_config_files

    template = write_config_files(certs, ["sim"])[0]  # as bttsim certs writes it: -c, not --tls-dir
    sim = start("bttsim_stream.nodes", "sim", scenario, "-l", endpoint, "-c", template, "--wait-for", "1",
                "--wait-timeout", "15")
    try:
        for flags in ([], ["--tls-dir", foreign_certs]):
            t0 = time.monotonic()
            res = subprocess.run([sys.executable, "-m", "bttsim_stream.nodes", "recorder", "--out",
                                  tmp_path / "x.mcap", "-e", endpoint, "--connect-timeout", "3", *flags],
                                 cwd=REPO, capture_output=True, text=True, timeout=60)
            assert res.returncode == 2, res.stderr
            lines = [l for l in res.stderr.splitlines() if l.startswith("bttsim: error")]
            assert lines and "cannot reach" in lines[0] and endpoint in lines[0], res.stderr
            assert time.monotonic() - t0 < 30
        _, err = sim.communicate(timeout=60)
    finally:
        stop(sim)
    assert sim.returncode == 2 and "found 0 of the 1 node(s)" in err, err


def _listen_endpoint(out: Path, node: str, timeout_s: float = 120) -> str:
    """The ``-l`` endpoint of a node process of the run writing into ``out`` (from /proc)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for proc in Path("/proc").iterdir():
            if not proc.name.isdigit():
                continue
            try:
                argv = (proc / "cmdline").read_bytes().decode(errors="replace").split("\0")
            except OSError:
                continue
            if "bttsim_stream.nodes" in argv and node in argv and any(str(out) in a for a in argv) and "-l" in argv:
                return argv[argv.index("-l") + 1]
        time.sleep(0.05)
    raise AssertionError(f"no {node} process of {out}")


def test_forgers_on_a_nodes_own_port_change_nothing_in_a_secured_run(scenario, certs, clean, tmp_path):
    """The attack of issue 16 (any local process connects to a node's loopback port), against
    ``bttsim run --tls-dir`` (a mesh of peers, no router): each node enforces the policy on its
    own links, so forgers with valid certificates of other identities, connected to the
    processor's and the recorder's own ports while the run goes on (real time, 12 s), change
    nothing, and one without a certificate is refused."""
    out = tmp_path / "out"
    run = subprocess.Popen([sys.executable, "-m", "bttsim_stream.cli", "run", str(scenario), "--out", str(out), "-q",
                            "--realtime", "--tls-dir", str(certs)], cwd=REPO, stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE, text=True)
    forgers = {}
    try:
        ends = {n: _listen_endpoint(out, n) for n in ("processor", "recorder")}
        forgers = {"viewer": start_forger(scenario, ends["processor"], "--tls-dir", certs, "--tls-name", "viewer",
                                          "--pose-as-sim"),
                   "intruder": start_forger(scenario, ends["recorder"], "--tls-dir", certs, "--tls-name", "intruder"),
                   "no certificate": start_forger(scenario, ends["processor"], "--connect-timeout", 3)}
        stdout, stderr = run.communicate(timeout=600)
        stats = {}
        for name, f in forgers.items():
            if name == "no certificate":
                _, err = f.communicate(timeout=60)
                assert f.returncode == 2 and "cannot reach" in err, err
            else:
                assert stop(f) == 0, f.stderr.read()
                stats[name] = json.loads(f.stdout.read().strip().splitlines()[-1])
    finally:
        for f in forgers.values():
            stop(f)
        stop(run)
    assert run.returncode == 0, stdout + stderr
    assert stats["viewer"]["matched"] > 100 and stats["intruder"]["put"] > 100, stats
    assert result(out) == clean


def test_only_named_consumers_receive_truth(scenario, certs):
    """From a secured simulator's late-joiner cache (replies, as live samples are puts under
    the same rules): the viewer's identity gets OPR and truth, ``run`` (bttsim run's own
    session) OPR only, an unknown identity of the same CA nothing."""
    import zenoh
    import zenoh.ext as zx

    from bttsim_stream.bus.security import TlsFiles
    from bttsim_stream.bus.session import make_config

    endpoint = f"tls/127.0.0.1:{free_port()}"
    sim = start("bttsim_stream.nodes", "sim", scenario, "--revolutions", "30", "--linger", "60", "-l", endpoint,
                "--tls-dir", certs)
    got = {}
    try:
        LineWatch(sim.stderr).wait_for(lambda line: "published" in line)  # the run is over: its cache remains
        for who in ("viewer", "run", "intruder"):
            tls = TlsFiles(certs / "ca.pem", certs / f"{who}.pem", certs / f"{who}-key.pem")
            with zenoh.open(make_config("client", connect=[endpoint], tls=tls)) as session:
                subs = {k: zx.declare_advanced_subscriber(
                    session, f"bttsim/rig1/{k}", handler=zenoh.handlers.FifoChannel(1000),
                    history=zx.HistoryConfig(detect_late_publishers=True, max_samples=None, max_age=None),
                    recovery=None, subscriber_detection=False, allowed_origin=None) for k in ("opr", "truth")}
                counts = dict.fromkeys(subs, 0)
                deadline = time.monotonic() + 5  # what is allowed comes at once; wait for the rest
                while time.monotonic() < deadline and (who != "viewer" or min(counts.values()) < 30):
                    idle = True
                    for k, sub in subs.items():
                        if sub.try_recv() is not None:
                            counts[k] += 1
                            idle = False
                    if idle:
                        time.sleep(0.01)
                got[who] = counts
    finally:
        stop(sim)
    assert got == {"viewer": {"opr": 30, "truth": 30}, "run": {"opr": 30, "truth": 0},
                   "intruder": {"opr": 0, "truth": 0}}, got

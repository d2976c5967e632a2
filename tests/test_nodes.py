"""Integration tests: real node processes talking over Zenoh on loopback."""

import json
import os
import queue
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zenoh
import zenoh.ext as zx

from _procs import LineWatch, start as _start, stop as _stop
from bttsim_stream.bus import codec
from bttsim_stream.bus.recording import McapRecorder, read_recording
from bttsim_stream.testing import free_port, virtual_acquisition
from bttsim_stream.bus.session import declare_subscriber, make_config, unpack_attachment

pytestmark = pytest.mark.integration

REPO = Path(__file__).resolve().parents[1]
SHORT = "[speed]\nstart_rpm = 2500.0\nend_rpm = 2600.0\nduration_s = 2.0\n"


def _messages(path):
    return sorted((m.key, m.seq, m.payload, m.log_time_ns) for m in read_recording(path).messages)


def _record_a_replay(recording: Path, out: Path, said: list | None = None) -> Path:
    """``bttsim replay`` of ``recording`` into a recorder node writing ``out`` (stopped by PID);
    the replay's stdout appended to ``said``."""
    port = free_port()
    rec = _start("bttsim_stream.nodes.recorder_node", "--rig", "rig1", "--out", out, "-l", f"tcp/127.0.0.1:{port}")
    try:  # the replay waits (up to --wait s) until the recorder subscribes to every key
        rep = subprocess.run([sys.executable, "-m", "bttsim_stream.cli", "replay", recording, "--wait", "120",
                              "-e", f"tcp/127.0.0.1:{port}"], cwd=REPO, capture_output=True, text=True, timeout=180)
        assert rep.returncode == 0, rep.stderr
        rec.communicate(timeout=60)
    finally:
        _stop(rec)
    if said is not None:
        said.append(rep.stdout)
    return out


@pytest.fixture
def scenario(tmp_path):
    path = tmp_path / "short.toml"
    path.write_text(SHORT)
    return path


@pytest.fixture
def direct(scenario, tmp_path):
    out = tmp_path / "direct.mcap"
    res = subprocess.run([sys.executable, "-m", "bttsim_stream.cli", "simulate", scenario, "--out", out, "-q"],
                         cwd=REPO, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    return out


def _wait_matched(pubs: dict) -> None:
    """Until every publisher matches a subscriber (a publisher drops samples until then)."""
    deadline = time.monotonic() + 120
    while not all(p.matching_status.matching for p in pubs.values()) and time.monotonic() < deadline:
        time.sleep(0.02)


def _publish_run(session, msgs: list, node: str = "processor") -> None:
    """As the simulator does: once ``node`` is alive, publish ``msgs`` (blocking congestion
    control) and wait until the node has the whole stream (its ``done`` token)."""
    from bttsim_stream.bus.session import StopFlag, pack_attachment, wait_for_liveliness

    assert wait_for_liveliness(session, f"bttsim/rig1/alive/{node}", 1, 120, StopFlag(install=False))
    pubs = {k: session.declare_publisher(k, congestion_control=zenoh.CongestionControl.BLOCK)
            for k in {m.key for m in msgs}}
    _wait_matched(pubs)
    for m in msgs:
        pubs[m.key].put(m.payload, attachment=pack_attachment(m.seq, m.log_time_ns))
    assert wait_for_liveliness(session, f"bttsim/rig1/done/{node}", 1, 120, StopFlag(install=False))


def test_sim_node_and_recorder_give_the_simulate_bytes_with_no_gaps(scenario, direct, tmp_path):
    port = free_port()
    rec_out = tmp_path / "live.mcap"
    rec = _start("bttsim_stream.nodes.recorder_node", "--rig", "rig1", "--out", rec_out,
                 "-l", f"tcp/127.0.0.1:{port}")
    sim = _start("bttsim_stream.nodes.sim_node", scenario, "-e", f"tcp/127.0.0.1:{port}", "--wait-for", "1")
    try:
        assert sim.wait(timeout=120) == 0, sim.stderr.read()
        out, err = rec.communicate(timeout=60)  # the recorder stops when the simulator is gone
        assert rec.returncode == 0, err
    finally:
        _stop(sim), _stop(rec)
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["gaps"] == 0 and summary["messages"] == 85 * 7 + 1
    assert _messages(rec_out) == _messages(direct)


def _replay_into_a_subscriber(path, count: int, *options) -> tuple[list, subprocess.CompletedProcess]:
    """``bttsim replay PATH --rate max OPTIONS`` into a plain subscriber of this process,
    listening first: what it received, ``(key, payload, seq, log time)`` sorted (the replay's
    own status left out), once the replay has ended and ``count`` messages came in (the last
    samples may still be in flight: at most 30 s more), and the replay's result."""
    port = free_port()
    got = []
    conf = make_config(listen=[f"tcp/127.0.0.1:{port}"])
    with zenoh.open(conf) as session:
        sub = session.declare_subscriber("bttsim/**", lambda s: "/status/" in str(s.key_expr) or got.append(
            (str(s.key_expr), s.payload.to_bytes(), *unpack_attachment(s.attachment))))
        rep = subprocess.run([sys.executable, "-m", "bttsim_stream.cli", "replay", path, "--rate", "max",
                              "-e", f"tcp/127.0.0.1:{port}", *options], cwd=REPO, capture_output=True, text=True,
                             timeout=120)
        deadline = time.monotonic() + 30
        while rep.returncode == 0 and len(got) < count and time.monotonic() < deadline:
            time.sleep(0.05)
        sub.undeclare()
    return sorted(got), rep


def _sorted(messages) -> list:
    return sorted((m.key, m.payload, m.seq, m.log_time_ns) for m in messages)


def test_replay_delivers_every_message_and_a_recorder_reproduces_the_file(direct, tmp_path):
    file_msgs = read_recording(direct).messages
    got, rep = _replay_into_a_subscriber(direct, len(file_msgs))
    assert rep.returncode == 0, rep.stderr
    assert got == _sorted(file_msgs)
    # and a recorder fed by the replay writes the same messages as the file
    assert _messages(_record_a_replay(direct, tmp_path / "replayed.mcap")) == _messages(direct)


def test_status_messages_in_a_recording_are_not_data(direct, tmp_path):
    """A node's status recorded beside the data (a file written by another tool): the replay
    does not put it back on the live status key, and ``view`` and ``process`` read the data
    as if it were not there."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    path = tmp_path / "with-status.mcap"
    with open(direct, "rb") as f, open(path, "wb") as g:
        w = Writer(g)
        w.start()
        schemas, chans = {}, {}
        status = w.register_channel("bttsim/rig1/status/sim", "json", 0)
        for i, (sch, ch, m) in enumerate(make_reader(f).iter_messages()):
            schemas.setdefault(sch.id, w.register_schema(sch.name, sch.encoding, sch.data))
            chans.setdefault(ch.id, w.register_channel(ch.topic, ch.message_encoding, schemas[sch.id], ch.metadata))
            w.add_message(chans[ch.id], m.log_time, m.data, m.publish_time, m.sequence)
            if i == 3:
                w.add_message(status, m.log_time, b'{"state": "running"}', m.log_time, 0)
        w.finish()
    said: list = []
    assert _messages(_record_a_replay(path, tmp_path / "r.mcap", said)) == _messages(direct)
    n = len(read_recording(direct).messages)
    assert f"replayed {n} of {n + 1} messages" in said[0] and "1 status message(s)" in said[0], said
    for argv in (["view", path, "--rrd", tmp_path / "v.rrd"], ["process", path]):
        res = subprocess.run([sys.executable, "-m", "bttsim_stream.cli", *map(str, argv)], cwd=REPO,
                             capture_output=True, text=True, timeout=180)
        assert res.returncode == 0, res.stderr


def _replay_error(path, *options) -> list:
    """The stderr lines of ``bttsim replay PATH --wait 0 OPTIONS``, which must fail with status 2."""
    res = subprocess.run([sys.executable, "-m", "bttsim_stream.cli", "replay", path, "--wait", "0", *options],
                         cwd=REPO, capture_output=True, text=True, timeout=120)
    assert res.returncode == 2, res.stderr
    return res.stderr.splitlines()


def test_replay_of_a_cut_or_incomplete_recording_says_so_or_replays_what_is_there(direct, tmp_path):
    """The replay reads the file as a stream, twice (what it holds, then to publish it): a file
    cut short (no footer) is one error line that counts the readable messages, exit 2; with
    ``--allow-truncated`` exactly those go out; a file of metadata alone is an error, and so is
    ``--wait-for`` on a rig without metadata (its consumers would refuse its data)."""
    msgs = read_recording(direct).messages
    whole = tmp_path / "small-chunks.mcap"
    with McapRecorder(whole, chunk_size=16 * 1024) as rec:
        rec.write_all(msgs)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(whole.read_bytes()[:int(0.6 * whole.stat().st_size)])
    readable = read_recording(cut)
    assert readable.truncated and 0 < len(readable.messages) < len(msgs)
    assert _replay_error(cut) == [f"bttsim: error: {cut}: truncated MCAP (no footer; {len(readable.messages)} "
                                  "messages readable); use --allow-truncated to replay what is there"]
    got, rep = _replay_into_a_subscriber(cut, len(readable.messages), "--allow-truncated")
    assert rep.returncode == 0, rep.stderr
    assert f"replayed {len(readable.messages)} of {len(readable.messages)} " in rep.stdout
    assert got == _sorted(readable.messages)
    meta_only, no_meta = tmp_path / "meta-only.mcap", tmp_path / "no-meta.mcap"
    with McapRecorder(meta_only) as a, McapRecorder(no_meta) as b:
        a.write_all([m for m in msgs if m.key.endswith("/meta")])
        b.write_all([m for m in msgs if not m.key.endswith("/meta")])
    assert _replay_error(meta_only) == [f"bttsim: error: {meta_only}: no messages to replay"]
    assert _replay_error(no_meta, "--wait-for", "1") == [
        f"bttsim: error: {no_meta}: no run metadata for rig1: its consumers would refuse its data and never "
        "confirm it (--wait-for); replay it without --wait-for"]


@pytest.mark.parametrize("change", ["a key more", "messages fewer"])
def test_a_recording_changed_between_the_replays_two_readings_is_a_one_line_error(change, direct, tmp_path,
                                                                                 monkeypatch, capsys):
    """The replay reads the file twice (what it holds, then each message to publish): a file
    rewritten in between, with a key the first reading did not see or fewer messages, ends in
    one line naming the change, status 2 (in this process: the second reading is made to see
    the rewritten file)."""
    from bttsim_stream import cli
    from bttsim_stream.bus import recording
    from bttsim_stream.bus.recording import RecordingScan

    msgs = read_recording(direct).messages
    changed = tmp_path / "changed.mcap"
    with McapRecorder(changed) as rec:
        if change == "a key more":
            extra = next(m for m in msgs if m.key == "bttsim/rig1/toa/0")
            rec.write_all([*msgs[:-1], type(extra)("bttsim/rig1/toa/99", extra.payload, extra.log_time_ns, extra.seq)])
        else:
            rec.write_all(msgs[:len(msgs) // 2])
    readings = []  # the first (the survey) reads the original, the second the rewritten file

    def scan(path):
        readings.append(path)
        return RecordingScan(path if len(readings) == 1 else changed)

    monkeypatch.setattr(recording, "RecordingScan", scan)  # the replay imports it from there when it runs
    assert cli.main(["replay", str(direct), "--wait", "0", "-l", f"tcp/127.0.0.1:{free_port()}"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(readings) == 2 and len(err) == 1, err
    want = "a message of bttsim/rig1/toa/99 the first reading did not hold" if change == "a key more" else \
        f"{len(msgs) // 2} of its {len(msgs)} messages read the second time"
    assert err[0].startswith(f"bttsim: error: {direct}: the file changed while it was replayed") and want in err[0]


def _wait_status(path: Path, proc: subprocess.Popen, timeout_s: float = 120.0) -> None:
    """Until the node ``proc`` has written its status file ``path`` (it is on the bus)."""
    deadline = time.monotonic() + timeout_s
    while not path.exists():
        assert proc.poll() is None, proc.stderr.read()
        assert time.monotonic() < deadline, f"{path} never written"
        time.sleep(0.02)


def _counts(path, keys=None) -> dict:
    """Messages per channel of a recording (only ``keys``, if given)."""
    counts: dict = {}
    for m in read_recording(path).messages:
        if keys is None or m.key in keys:
            counts[m.key] = counts.get(m.key, 0) + 1
    return counts


def _replay_to_consumers(direct, tmp_path, nodes: dict, per_rig: int | None = None) -> str:
    """``bttsim replay DIRECT --wait-for N`` listening on loopback (N = ``per_rig``, else every
    node), and the consumer nodes ``{label: (module, args)}`` connected to it one after the
    other, each once the one before is on the bus (its status file written) and once the
    replay waits on its rig (``--rig`` in its args, else rig1); every one must end with status
    0. Returns the replay's stderr."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    n = per_rig or len(nodes)
    rep = _start("bttsim_stream.cli", "replay", direct, "--wait-for", str(n), "--wait-timeout", "120",
                 "-l", endpoint)
    rep_err = LineWatch(rep.stderr)
    procs = {}
    try:
        for label, (module, args) in nodes.items():
            rig = args[args.index("--rig") + 1] if "--rig" in args else "rig1"
            rep_err.wait_for(lambda line, rig=rig: f"waiting for {n} node(s) on {rig}" in line)
            status = tmp_path / f"{label}-status.json"
            procs[label] = _start(module, *([] if "--rig" in args else ["--rig", "rig1"]), *args, "-e", endpoint,
                                  "--status-file", status)
            _wait_status(status, procs[label])
            name = args[args.index("--name") + 1] if "--name" in args else label.split("@")[0]
            assert json.loads(status.read_text())["node"] == name
        assert rep.wait(timeout=180) == 0, rep_err.text()
        for label, proc in procs.items():
            _, err = proc.communicate(timeout=120)  # a consumer stops when the replay is gone
            assert proc.returncode == 0, (label, err)
    finally:
        for proc in [*procs.values(), rep]:
            _stop(proc)
    original = read_recording(direct).messages
    assert f"replayed {len(original)} of {len(original)} " in rep.stdout.read()
    return rep_err.text()


def test_replay_waits_for_every_consumer_and_each_gets_the_whole_run(direct, tmp_path):
    """``bttsim replay --wait-for 2`` with two consumers, a processor and a recorder, the recorder
    started only once the processor is on the bus: the replay starts once both have the run
    metadata, the processor's result rests on every revolution and the recording holds every
    message of the original (85 revolutions: more than the publishers' caches keep, so a
    consumer that came in late could not make up for the head of the run)."""
    _replay_to_consumers(direct, tmp_path, {
        "processor": ("bttsim_stream.nodes.processor_node", ["--summary", tmp_path / "summary.json"]),
        "recorder": ("bttsim_stream.nodes.recorder_node", ["--out", tmp_path / "replayed.mcap"])})
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["complete"] and summary["revolutions_processed"] == summary["revolutions_expected"] == 85
    assert summary["lost"] == 0
    acquisition = {m.key for m in read_recording(direct).messages}  # the recording also holds the results
    assert _counts(tmp_path / "replayed.mcap", acquisition) == _counts(direct)
    assert [m for m in _messages(tmp_path / "replayed.mcap") if m[0] in acquisition] == _messages(direct)


def test_two_recorders_of_one_rig_under_their_own_names_each_get_the_whole_run(direct, tmp_path):
    """Two recorders of one rig, the second with ``--name recorder-2``: the replay's
    ``--wait-for 2`` counts both (under one name they count once: its liveliness key is one)
    and waits for each one's ``done``; both recordings hold the whole acquisition."""
    names = ("recorder", "recorder-2")
    err = _replay_to_consumers(direct, tmp_path, {
        name: ("bttsim_stream.nodes.recorder_node", ["--name", name, "--out", tmp_path / f"{name}.mcap"])
        for name in names})
    assert "2 other node(s) alive on rig1" in err
    for name in names:
        assert _messages(tmp_path / f"{name}.mcap") == _messages(direct), name


def test_a_replay_of_two_rigs_waits_on_each_and_each_rig_gets_its_whole_run(scenario, direct, tmp_path):
    """One recording of two rigs (rig1 and a second run on rig2, as a recorder of every rig
    writes them) replayed with ``--wait-for 1``: the replay waits for a consumer on rig1, then
    on rig2, and each rig's processor gets every revolution of its own run."""
    toml = tmp_path / "rig2.toml"
    toml.write_text(scenario.read_text() + '[run]\nrig = "rig2"\n')
    other = tmp_path / "rig2.mcap"
    res = subprocess.run([sys.executable, "-m", "bttsim_stream.cli", "simulate", toml, "--out", other, "-q"],
                         cwd=REPO, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    both = tmp_path / "two-rigs.mcap"
    with McapRecorder(both) as rec:
        rec.write_all(sorted([*read_recording(direct).messages, *read_recording(other).messages],
                             key=lambda m: m.log_time_ns))
    err = _replay_to_consumers(both, tmp_path, {
        f"processor@{rig}": ("bttsim_stream.nodes.processor_node",
                             ["--rig", rig, "--summary", tmp_path / f"{rig}.json"]) for rig in ("rig1", "rig2")},
                               per_rig=1)
    assert err.index("waiting for 1 node(s) on rig1") < err.index("waiting for 1 node(s) on rig2")
    for rig in ("rig1", "rig2"):
        summary = json.loads((tmp_path / f"{rig}.json").read_text())
        assert summary["complete"] and summary["lost"] == 0, (rig, summary)
        assert summary["revolutions_processed"] == summary["revolutions_expected"] == 85, (rig, summary)


@pytest.mark.parametrize("name, why", [("rec/2", "invalid node name 'rec/2'"),
                                       ("processor", "'processor' is another node's name")])
def test_a_node_name_that_cannot_be_a_key_or_is_taken_is_a_one_line_error(name, why, tmp_path):
    res = subprocess.run([sys.executable, "-m", "bttsim_stream.nodes.recorder_node", "--name", name, "--out",
                          tmp_path / "r.mcap"], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert res.returncode == 2 and why in res.stderr and "Traceback" not in res.stderr, res.stderr
    assert len(res.stderr.splitlines()) <= 2 and not (tmp_path / "r.mcap").exists()


@pytest.mark.parametrize("program", ["replay", "sim-node"])
def test_a_signal_while_waiting_for_consumers_is_a_clean_stop(program, direct, tmp_path):
    """SIGINT to a replay or a simulator still waiting for its ``--wait-for`` consumers (none
    comes): it stops at once with status 0, publishes nothing, and says so in its status."""
    status = tmp_path / "status.json"
    what = [direct] if program == "replay" else []
    proc = _start("bttsim_stream.cli", program, *what, "--wait-for", "1", "--wait-timeout", "120",
                  "-l", f"tcp/127.0.0.1:{free_port()}", "--status-file", status)
    err = LineWatch(proc.stderr)
    try:
        err.wait_for(lambda line: "waiting for 1 node(s) on rig1" in line)
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=60) == 0, err.text()
    finally:
        _stop(proc)
    assert "error" not in err.text()
    done = json.loads(status.read_text())
    assert done["state"] == "done" and done["stats"]["messages"] == 0, done
    assert done["stats"]["stopped_by_signal"] == signal.SIGINT


def test_raw_signal_channels_are_recorded_and_replayed_bit_identically(tmp_path):
    """With [acquisition.signal] publish, the signal/<probe> channels go into the MCAP like
    every other channel, and a recorder fed by the replay writes the same messages."""
    scenario = tmp_path / "signal.toml"
    scenario.write_text(SHORT + "[acquisition.signal]\nenabled = true\npublish = true\n")
    direct = tmp_path / "direct.mcap"
    res = subprocess.run([sys.executable, "-m", "bttsim_stream.cli", "simulate", scenario, "--out", direct, "-q"],
                         cwd=REPO, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    signals = [m for m in read_recording(direct).messages if "/signal/" in m.key]
    assert len(signals) == 85 * 5 and {m.key for m in signals} == {f"bttsim/rig1/signal/{j}" for j in range(5)}
    assert _messages(_record_a_replay(direct, tmp_path / "replayed.mcap")) == _messages(direct)


def test_late_joiner_receives_recent_history(scenario):
    with virtual_acquisition(scenario, revolutions=30, linger_s=60) as daq:
        LineWatch(daq.process.stderr).wait_for(lambda line: "published" in line)  # the run is over
        got = []
        with zenoh.open(daq.client_config()) as session:
            sub = zx.declare_advanced_subscriber(
                session, "bttsim/rig1/opr", handler=zenoh.handlers.FifoChannel(1000),
                history=zx.HistoryConfig(detect_late_publishers=True, max_samples=None, max_age=None),
                recovery=None, subscriber_detection=False, allowed_origin=None)
            deadline = time.monotonic() + 5
            while time.monotonic() < deadline and len(got) < 30:
                s = sub.try_recv()
                if s is None:
                    time.sleep(0.01)
                    continue
                got.append(codec.decode_opr(s.payload.to_bytes()).header.revolution)
            # our nodes' subscriber: a plain one plus one query of the publishers' caches
            ours = queue.Queue()
            own = declare_subscriber(session, "bttsim/rig1/**", ours.put, history=True)
            mine = []
            while sum(k == "bttsim/rig1/opr" for k, _ in mine) < 30 or ("bttsim/rig1/meta", 0) not in mine:
                s = ours.get(timeout=10)  # the history comes at once: Empty here is a failure
                mine.append((str(s.key_expr), unpack_attachment(s.attachment)[0]))
            own.undeclare()
        assert daq.metadata.n_blades == 29 and daq.metadata.n_probes == 5
    assert got == list(range(30))  # all 30 OPR pulses from the publisher cache, in order
    assert [seq for key, seq in mine if key == "bttsim/rig1/opr"] == list(range(30))
    assert ("bttsim/rig1/meta", 0) in mine


def test_recorder_killed_mid_run_leaves_a_readable_file(tmp_path):
    port = free_port()
    out = tmp_path / "killed.mcap"
    rec = _start("bttsim_stream.nodes.recorder_node", "--rig", "rig1", "--out", out, "-l", f"tcp/127.0.0.1:{port}")
    sim = _start("bttsim_stream.nodes.sim_node", "-e", f"tcp/127.0.0.1:{port}", "--wait-for", "1",
                 "--rate", "20", stdout=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and (not out.exists() or out.stat().st_size < 3_000_000):
            time.sleep(0.2)
        os.kill(rec.pid, signal.SIGKILL)
        rec.wait(timeout=10)
    finally:
        _stop(sim), _stop(rec)
    recording = read_recording(out)
    assert recording.truncated and len(recording.messages) > 1000
    by_key = {}
    for m in recording.messages:
        by_key.setdefault(m.key, []).append(m.seq)
        codec.decode_message(m.key, m.payload)  # every message decodes
    for key, seqs in by_key.items():
        if not key.endswith("/meta"):
            assert seqs == list(range(seqs[0], seqs[0] + len(seqs))), key
    # a truncated file given to replay is a one-line error, exit 2
    res = subprocess.run([sys.executable, "-m", "bttsim_stream.cli", "replay", out, "--wait", "0"], cwd=REPO,
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 2 and res.stderr.count("\n") == 1 and "truncated" in res.stderr


SAMPLE = REPO / "recordings" / "resonance_window.mcap"


@pytest.mark.parametrize("command", [["replay", "--wait", "0"], ["process"], ["view", "--rrd", "x.rrd"]],
                         ids=["replay", "process", "view"])
@pytest.mark.parametrize("content", [b"not an mcap at all", b"\x89MCAP0\r\n" + b"\x00" * 40, "cut"],
                         ids=["garbage", "corrupt", "truncated"])
def test_corrupt_or_truncated_mcap_is_one_line_exit_2(command, content, tmp_path):
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(SAMPLE.read_bytes()[:1_500_000] if content == "cut" else content)
    res = subprocess.run([sys.executable, "-m", "bttsim_stream.cli", command[0], bad, *command[1:]], cwd=tmp_path,
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 2 and res.stderr.startswith("bttsim: error:") and res.stderr.count("\n") == 1


def test_nodes_stop_cleanly_on_sigterm_and_sigint(tmp_path):
    port = free_port()
    out = tmp_path / "stopped.mcap"
    # --until '': only the signal stops the recorder (it would otherwise end with the
    # simulator, and a signal during its exit is not the case under test)
    rec = _start("bttsim_stream.nodes.recorder_node", "--rig", "rig1", "--out", out, "--until", "",
                 "-l", f"tcp/127.0.0.1:{port}")
    sim_port = free_port()
    sim = _start("bttsim_stream.nodes.sim_node", "-e", f"tcp/127.0.0.1:{port}", "-l", f"tcp/127.0.0.1:{sim_port}",
                 "--wait-for", "1", "--rate", "realtime", stdout=subprocess.DEVNULL)
    try:  # a few revolutions in (peers do not route: listen to the simulator itself)
        with zenoh.open(make_config(connect=[f"tcp/127.0.0.1:{sim_port}"])) as session:
            oprs = []
            sub = session.declare_subscriber("bttsim/rig1/opr", oprs.append)
            deadline = time.monotonic() + 120
            while len(oprs) < 20 and time.monotonic() < deadline:
                time.sleep(0.05)
            sub.undeclare()
        assert len(oprs) >= 20
        t0 = time.monotonic()
        assert _stop(sim, signal.SIGTERM) == 0
        assert _stop(rec, signal.SIGINT) == 3  # finalised; the run was cut short: not complete, and it says so
        assert time.monotonic() - t0 < 10
    finally:
        _stop(sim), _stop(rec)
    recording = read_recording(out)
    assert not recording.truncated and len(recording.messages) > 50  # finalised, with a footer
    assert recording.metadata["bttsim.run"]["rig"] == "rig1"


def test_readme_subscriber_decodes_live_toas():
    """The README's 15-line subscriber, run as a program against a real-time virtual DAQ."""
    with virtual_acquisition(revolutions=200, rate="realtime") as daq:
        ex = subprocess.run([sys.executable, str(REPO / "examples" / "subscribe_toas.py"), daq.endpoint, "25"],
                            capture_output=True, text=True, timeout=60)
    assert ex.returncode == 0, ex.stderr
    rows = [line.split(maxsplit=2) for line in ex.stdout.strip().splitlines()]
    assert len(rows) == 25
    assert {int(r[1]) for r in rows} == {0, 1, 2, 3, 4}  # every probe
    revs = [int(r[0]) for r in rows]
    assert revs == sorted(revs) and revs[-1] - revs[0] <= 6


def test_readme_subscriber_listens_to_a_replay():
    """The README's second example: the subscriber listens, the replay connects and waits for it."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    sub = subprocess.Popen([sys.executable, str(REPO / "examples" / "subscribe_toas.py"), endpoint, "25", "--listen"],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        rep = subprocess.run([sys.executable, "-m", "bttsim_stream.cli", "replay", SAMPLE, "--wait", "120",
                              "-e", endpoint], cwd=REPO, capture_output=True, text=True, timeout=180)
        assert rep.returncode == 0, rep.stderr
        assert "replayed 3004 of 3004" in rep.stdout and "no subscriber" not in rep.stderr
        out, err = sub.communicate(timeout=60)
    finally:
        _stop(sub)
    assert sub.returncode == 0, err
    rows = [line.split(maxsplit=2) for line in out.strip().splitlines()]
    assert len(rows) == 25 and {int(r[1]) for r in rows} == {0, 1, 2, 3, 4}


@pytest.mark.parametrize("node", ["recorder", "viewer"])
def test_a_late_recorder_or_viewer_asks_the_metadata_queryable(tmp_path, node):
    """A node whose data came before its run's metadata (it joined late: the metadata sample
    went by before its subscription reached the publisher) asks the ``meta`` queryable, as
    the processor does, and then takes the run whole; here the metadata is never published
    as a sample at all, only answered."""
    from bttsim_stream.bus.session import pack_attachment
    from bttsim_stream.bus.stream import MessageStream
    from _io_helpers import NR, make_batch, make_info

    port = free_port()
    out = tmp_path / "late.mcap"
    args = ["--out", out] if node == "recorder" else ["--rrd", tmp_path / "late.rrd"]
    proc = _start(f"bttsim_stream.nodes.{node}_node", "--rig", "rig1", *args, "-l", f"tcp/127.0.0.1:{port}")
    stream = MessageStream("run-a", "rig1")
    meta, *data = [stream.run_metadata(make_info(n_revolutions=NR))] + stream.acquisition(make_batch())
    asked: list = []

    try:
        with zenoh.open(make_config(connect=[f"tcp/127.0.0.1:{port}"])) as session:
            def answer(query) -> None:  # as the simulator answers: stamped, it names the publishing session
                asked.append(time.monotonic())
                query.reply(meta.key, meta.payload, attachment=pack_attachment(meta.seq, meta.log_time_ns),
                            timestamp=session.new_timestamp())

            queryable = session.declare_queryable(meta.key, answer)
            token = session.liveliness().declare_token("bttsim/rig1/alive/sim")  # the node stops when it goes
            _publish_run(session, data, node)
            token.undeclare()
            out_text, err = proc.communicate(timeout=120)
            queryable.undeclare()
    finally:
        _stop(proc)
    assert proc.returncode == 0, err
    assert asked, "the metadata queryable was never asked"
    stats = json.loads(out_text.strip().splitlines()[-1])
    assert stats["complete"] is True and stats["rejected"] == 0 and stats["messages"] == len(data) + 1, stats
    if node == "recorder":
        assert read_recording(out).messages == [meta, *data]


def test_recorder_refuses_a_sample_mcap_cannot_hold_and_keeps_the_file_readable(tmp_path):
    """A forged attachment (sequence 2^62) used to crash the recorder and leave no readable file."""
    from bttsim_stream.bus.session import pack_attachment, wait_for_liveliness, wait_for_subscribers, StopFlag
    from bttsim_stream.bus.stream import MessageStream
    from _io_helpers import NR, make_batch, make_info

    port = free_port()
    out = tmp_path / "forged.mcap"
    rec = _start("bttsim_stream.nodes.recorder_node", "--rig", "rig1", "--out", out, "-l", f"tcp/127.0.0.1:{port}")
    stream = MessageStream("run-a", "rig1")
    msgs = [stream.run_metadata(make_info(n_revolutions=NR))] + stream.acquisition(make_batch())
    try:
        with zenoh.open(make_config(connect=[f"tcp/127.0.0.1:{port}"])) as session:
            token = session.liveliness().declare_token("bttsim/rig1/alive/sim")  # the recorder stops when it goes
            assert wait_for_subscribers(session, ["bttsim/rig1/opr"], 120, StopFlag(install=False))
            pubs = {m.key: session.declare_publisher(m.key) for m in msgs}
            _wait_matched(pubs)
            pubs[msgs[1].key].put(msgs[1].payload, attachment=pack_attachment(1 << 62, 10))  # forged
            for m in msgs:
                pubs[m.key].put(m.payload, attachment=pack_attachment(m.seq, m.log_time_ns))
            assert wait_for_liveliness(session, "bttsim/rig1/done/recorder", 1, 120, StopFlag(install=False))
            token.undeclare()
        out_text, err = rec.communicate(timeout=120)
    finally:
        _stop(rec)
    assert rec.returncode == 0, err
    assert json.loads(out_text.strip().splitlines()[-1])["rejected"] == 1
    recording = read_recording(out)
    assert not recording.truncated and recording.messages == msgs


def test_processor_counts_and_skips_forged_samples_and_gives_the_clean_result(scenario, tmp_path):
    """Garbage, a probe that does not exist, a revolution far ahead, a duplicate batch shifted
    by 1 us: the processor neither crashes nor changes its result, and counts them."""
    from bttsim_stream.acquisition import AcquisitionStream
    from bttsim_stream.bus.session import pack_attachment, wait_for_liveliness, StopFlag
    from bttsim_stream.bus.codec import Header, OprPulse, encode_opr, encode_toa_batch
    from bttsim_stream.process.pipeline import process_arrays
    from bttsim_stream.scenario import load_scenario
    from bttsim_stream.sim.core import collect

    acq = AcquisitionStream(load_scenario(scenario), include_truth=False)
    pairs = list(acq.batches())
    msgs = [acq.meta] + [m for _, ms in pairs for m in ms]
    batch = collect(b for b, _ in pairs)
    bad = [("bttsim/rig1/toa/0", b"\x08\x96\x01garbage", (1 << 40, 0)),
           ("bttsim/rig1/toa/99", encode_toa_batch(Header(acq.run_id, 0, 3, 0.1), 99, [0.1] * 29), (0, 0)),
           ("bttsim/rig1/opr", encode_opr(Header(acq.run_id, 10**6, 100_000, 1e3), OprPulse(1e3)), (10**6, 0)),
           ("bttsim/rig1/toa/0", encode_toa_batch(Header(acq.run_id, 0, 0, 0.0), 0,
                                                  (batch.toa_s[0, :, 0] + 1e-6).tolist()), (0, 0))]
    port = free_port()
    summary_path = tmp_path / "summary.json"
    proc = _start("bttsim_stream.nodes.processor_node", "--rig", "rig1", "--no-score", "--summary", summary_path,
                  "-l", f"tcp/127.0.0.1:{port}")
    try:
        with zenoh.open(make_config(connect=[f"tcp/127.0.0.1:{port}"])) as session:
            token = session.liveliness().declare_token("bttsim/rig1/alive/sim")
            assert wait_for_liveliness(session, "bttsim/rig1/alive/processor", 1, 120, StopFlag(install=False))
            pubs = {k: session.declare_publisher(k, congestion_control=zenoh.CongestionControl.BLOCK)
                    for k in {m.key for m in msgs} | {k for k, _, _ in bad}}
            _wait_matched(pubs)
            for i, m in enumerate(msgs):
                pubs[m.key].put(m.payload, attachment=pack_attachment(m.seq, m.log_time_ns))
                if i == 40:  # in the middle of the run, after revolution 0 is in
                    for key, payload, (seq, t_ns) in bad:
                        pubs[key].put(payload, attachment=pack_attachment(seq, t_ns))
            # as the simulator does: leave once the processor has the whole stream
            assert wait_for_liveliness(session, "bttsim/rig1/done/processor", 1, 120, StopFlag(install=False))
            token.undeclare()
        out, err = proc.communicate(timeout=120)
    finally:
        _stop(proc)
    assert proc.returncode == 0, err
    got = json.loads(summary_path.read_text())
    clean = process_arrays(batch.opr_s, batch.toa_s, acq.info).summary
    assert {k: v for k, v in got.items() if k in clean} == json.loads(json.dumps(clean))
    # the garbage and the far-ahead revolution (its sequence number too) are rejected; the
    # wrong probe is ignored; the repeated batch is a duplicate (its sequence number is old)
    assert got["complete"] is True and got["revolutions_processed"] == got["revolutions_expected"] == 85
    assert (got["rejected"], got["duplicates"], got["lost"]) == (2, 1, 0), err
    assert "ignored 1" in err, err


@pytest.mark.parametrize("confirm", [True, False], ids=["confirmed", "never-confirmed"])
def test_processor_stays_until_the_nodes_awaiting_its_report_have_it(scenario, confirm):
    """Closing a session drops what is still queued (on a slow or lossy link: the last fits
    and the report). After its report the processor stays while a node that declared an
    ``awaiting`` token has no ``reported`` token, and leaves once it has one; a node that
    never confirms is waited for ``--drain-timeout`` seconds, and the processor says so."""
    from bttsim_stream.acquisition import AcquisitionStream
    from bttsim_stream.scenario import load_scenario

    acq = AcquisitionStream(load_scenario(scenario), include_truth=False)
    msgs = [acq.meta] + [m for _, ms in acq.batches() for m in ms]
    port, drain_s = free_port(), 2.0
    proc = _start("bttsim_stream.nodes.processor_node", "--rig", "rig1", "--no-score", "--drain-timeout", drain_s,
                  "-l", f"tcp/127.0.0.1:{port}")
    try:
        with zenoh.open(make_config(connect=[f"tcp/127.0.0.1:{port}"])) as session:
            reports: queue.Queue = queue.Queue()
            sub = session.declare_subscriber("bttsim/rig1/resonance", lambda s: reports.put(time.monotonic()))
            token = session.liveliness().declare_token("bttsim/rig1/alive/sim")
            awaiting = session.liveliness().declare_token("bttsim/rig1/awaiting/probe")
            _publish_run(session, msgs)
            token.undeclare()
            t_report = reports.get(timeout=120)
            assert proc.poll() is None  # the report is in, not confirmed: the processor stays
            if confirm:
                reported = session.liveliness().declare_token("bttsim/rig1/reported/probe")
            out, err = proc.communicate(timeout=120)
            t_end = time.monotonic()
            if confirm:
                reported.undeclare()
            awaiting.undeclare()
            sub.undeclare()
    finally:
        _stop(proc)
    assert proc.returncode == 0, err
    assert ("leaving before probe confirmed the report (2 s)" in err) is not confirm, err
    if not confirm:
        assert t_end - t_report >= drain_s - 1.0, (t_end - t_report, err)


def test_processor_node_publishes_non_synchronous_vibration(tmp_path):
    """A flutter recording (analytic response, tests/_nsv_truth.py) published to the processor
    node: NonSynchronous messages arrive on ``bttsim/rig1/nsv`` during the run (one per detected
    block from the second on) with the flutter's ND, and the node's summary reports the NSV and
    no resonance, as ``bttsim process`` does."""
    from _nsv_truth import logistic, synthesize, write_recording
    from bttsim_stream.offline import load_run, processing_messages

    run = synthesize(n_rev=256, rpm0=2500.0, rpm1=2540.0, freq_hz=344.0, nd=5,
                     amp_pk_m=logistic(1e-6, 0.2e-3, 3.0), noise_s=3e-8, seed=21)
    rec = tmp_path / "flutter.mcap"
    write_recording(rec, run)
    msgs = read_recording(rec).messages
    port = free_port()
    summary_path = tmp_path / "summary.json"
    proc = _start("bttsim_stream.nodes.processor_node", "--rig", "rig1", "--no-score", "--summary", summary_path,
                  "-l", f"tcp/127.0.0.1:{port}")
    got: "queue.Queue" = queue.Queue()
    try:
        with zenoh.open(make_config(connect=[f"tcp/127.0.0.1:{port}"])) as session:
            sub = declare_subscriber(session, "bttsim/rig1/nsv", lambda s: got.put(s.payload.to_bytes()),
                                     history=False)
            token = session.liveliness().declare_token("bttsim/rig1/alive/sim")
            _publish_run(session, msgs)
            token.undeclare()
            out, err = proc.communicate(timeout=120)
            sub.undeclare()
    finally:
        _stop(proc)
    assert proc.returncode == 0, err
    live = []
    while not got.empty():
        live.append(codec.decode_nsv(got.get()).body)
    expected = [m for m in processing_messages(load_run(rec))[0] if m.key == "bttsim/rig1/nsv"]
    assert len(live) == len(expected) >= 3
    assert all(d.nd == 5 and abs(d.freq_hz - 344.0) < 1.0 for d in live)
    summary = json.loads(summary_path.read_text())
    assert summary["status"] == "none" and summary["non_synchronous"][0]["nd"] == 5


@pytest.mark.parametrize("command", [["node", "recorder", "--out", "r.mcap"], ["record", "--out", "r.mcap"],
                                     ["node", "processor"]])
def test_bttsim_node_exits_3_when_its_result_is_not_whole(command, tmp_path, monkeypatch):
    """``bttsim node NAME`` (and ``bttsim record``) exit as the node's own script does: 3 when
    nothing of a run came in before ``--duration`` (it used to drop the node's status: 0)."""
    from bttsim_stream import cli

    monkeypatch.chdir(tmp_path)
    assert cli.main([*command, "-l", f"tcp/127.0.0.1:{free_port()}", "--duration", "0.5"]) == 3

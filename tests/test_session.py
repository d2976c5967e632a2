"""Zenoh session configuration: loopback defaults, and a -c file merged with them."""

import hashlib
import json
import os
import signal
import subprocess
import sys
import time

import pytest

from bttsim_stream.bus.session import GONE_SIGNAL, StopFlag, declare_publisher, free_port, make_config, opened, \
    wait_for_subscribers
from bttsim_stream.errors import BttsimError

import _procs


def _get(conf, key):
    return json.loads(conf.get_json(key))


def test_defaults_listen_only_where_asked_and_do_not_scout():
    conf = make_config(connect=["tcp/127.0.0.1:7447"])
    assert _get(conf, "listen/endpoints") == [] and _get(conf, "connect/endpoints") == ["tcp/127.0.0.1:7447"]
    assert _get(conf, "scouting/multicast/enabled") is False and _get(conf, "mode") == "peer"


def test_a_config_file_is_merged_with_the_loopback_defaults(tmp_path):
    bare = tmp_path / "bare.json5"
    bare.write_text('{ transport: { unicast: { max_sessions: 100 } } }')
    conf = make_config(config_file=str(bare), listen=["tcp/127.0.0.1:7001"])
    # zenoh's own default would listen on every interface and scout by multicast
    assert _get(conf, "listen/endpoints") == ["tcp/127.0.0.1:7001"]
    assert _get(conf, "scouting/multicast/enabled") is False and _get(conf, "mode") == "peer"
    assert _get(conf, "transport/unicast/max_sessions") == 100
    assert _get(make_config(config_file=str(bare)), "listen/endpoints") == []


def test_what_the_file_sets_wins_and_command_line_endpoints_are_added(tmp_path):
    full = tmp_path / "full.json5"
    full.write_text('{ mode: "client", listen: { endpoints: ["tcp/127.0.0.1:7002"] }, '
                    'scouting: { multicast: { enabled: true } } }')
    conf = make_config(config_file=str(full), connect=["tcp/127.0.0.1:7003"])
    assert _get(conf, "mode") == "client" and _get(conf, "scouting/multicast/enabled") is True
    assert _get(conf, "listen/endpoints") == ["tcp/127.0.0.1:7002"]
    assert _get(conf, "connect/endpoints") == ["tcp/127.0.0.1:7003"]
    assert _get(make_config(config_file=str(full), listen=["tcp/127.0.0.1:7004"]),
                "listen/endpoints") == ["tcp/127.0.0.1:7004"]  # bttsim run gives each node its own


def test_payloads_never_pass_through_shared_memory(tmp_path):
    """Not even when a file asks for it (see the stalled-receiver test below for why)."""
    shm = tmp_path / "shm.json5"
    shm.write_text('{ transport: { shared_memory: { enabled: true } } }')
    for conf in (make_config(), make_config(config_file=str(shm))):
        assert _get(conf, "transport/shared_memory/enabled") is False


@pytest.mark.parametrize("kwargs, match", [
    (dict(config_file="/nonexistent.json5"), "no such Zenoh configuration file"),
    (dict(connect=["localhost"]), "bad zenoh endpoint"),
    (dict(mode="client"), "client mode needs"),
], ids=["missing-file", "bad-endpoint", "client-without-endpoint"])
def test_bad_configuration_is_a_one_line_error(kwargs, match):
    with pytest.raises(BttsimError, match=match) as exc:
        make_config(**kwargs)
    assert "\n" not in str(exc.value)


# --------------------------------------------------------------------------------------
# StopFlag: signals, nested signals, waiters in threads
# --------------------------------------------------------------------------------------

_WAITER = """
import sys, time
from bttsim_stream.bus.session import StopFlag
stop = StopFlag()
print("ready", flush=True)
n = 0
while not stop.wait(float(sys.argv[1])):
    n += 1
import signal
signal.signal(stop.signal, signal.SIG_IGN)  # the rest of a burst must not end the interpreter's exit
print("stopped by", stop.signal, flush=True)
"""


@pytest.mark.parametrize("sig_name, flood_s, wait_s", [("SIGTERM", 0, 30.0), ("SIGHUP", 0, 30.0),
                                                       ("SIGINT", 0, 30.0), ("SIGTERM", 1.0, 0.0005)],
                         ids=["SIGTERM", "SIGHUP", "SIGINT", "a flood of SIGTERMs for 1 s while it polls"])
def test_stop_flag_wakes_at_once_on_a_signal_and_survives_a_flood(sig_name, flood_s, wait_s):
    """The handler takes no lock: signals in quick succession (handlers nested in the main
    thread) cannot deadlock it (a threading.Event did), and a long wait ends at once."""
    import os
    import signal
    import subprocess
    import sys
    import time

    sig = getattr(signal, sig_name)
    proc = subprocess.Popen([sys.executable, "-c", _WAITER, str(wait_s)], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "ready"
        t0 = time.monotonic()
        os.kill(proc.pid, sig)
        while time.monotonic() - t0 < flood_s and proc.poll() is None:
            os.kill(proc.pid, sig)
        out, _ = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0 and f"stopped by {int(sig)}" in out
    assert time.monotonic() - t0 < 10


def test_stop_flag_wakes_every_waiting_thread_and_keeps_its_deadline():
    import threading
    import time

    from bttsim_stream.bus.session import StopFlag

    stop = StopFlag(install=False)
    woke = []
    threads = [threading.Thread(target=lambda: woke.append(stop.wait(60.0))) for _ in range(3)]
    for t in threads:
        t.start()
    t0 = time.monotonic()
    stop.set()
    for t in threads:
        t.join(10)
    assert woke == [True, True, True] and time.monotonic() - t0 < 5
    assert stop.wait(60.0) is True  # stays set

    timed = StopFlag(0.2, install=False)
    assert not timed
    t0 = time.monotonic()
    assert timed.wait(60.0) is True
    assert 0.15 < time.monotonic() - t0 < 5


# --------------------------------------------------------------------------------------
# A receiver stalled with samples waiting in its FIFO reads them intact afterwards
# --------------------------------------------------------------------------------------

_PAYLOAD = 16384  # above Zenoh's 3 kB threshold for passing payloads through shared memory
_HELD_THEN_STALLED, _AFTER = 350, 1200  # the second: more than Zenoh's 16 MB pool holds

_STALLED_RECEIVER = """
import hashlib, json, sys
import zenoh
from bttsim_stream.bus.session import StopFlag, make_config
from bttsim_stream.runtime import node_session

total = int(sys.argv[2])
held = [0]
def count(_sample):
    held[0] += 1
    print("held", held[0], flush=True)
with node_session(make_config(listen=[sys.argv[1]]), "rig1", "viewer") as ctx:
    ctx.subscribe("stall/**")  # the nodes' receive path: a FIFO inside Zenoh, drained in batches
    ctx.declare(ctx.session.declare_subscriber("stall/**", zenoh.handlers.Callback(count, indirect=False)))
    print("ready", flush=True)
    sys.stdin.readline()  # drain only when told (the samples wait in the FIFO meanwhile)
    bad, n = [], 0
    for r in ctx.samples(StopFlag(install=False)):
        if r is None:
            continue
        body = r.payload[32:]
        if hashlib.sha256(body).digest() != r.payload[:32] or int.from_bytes(body[:8], "little") != n:
            bad.append(n)
        n += 1
        if n == total:
            break
    print(json.dumps({"n": n, "bad": bad}), flush=True)
"""


def _numbered(i: int) -> bytes:
    body = i.to_bytes(8, "little") * (_PAYLOAD // 8 - 4)
    return hashlib.sha256(body).digest() + body


@pytest.mark.integration
def test_a_receiver_stalled_with_samples_in_its_fifo_reads_them_intact():
    """A node stopped (SIGSTOP) for a second while large samples wait in its FIFO reads every
    one intact afterwards, even though the publisher sent enough meanwhile to fill a Zenoh
    shared-memory pool twice over (a pool lends its buffers to the receiver only while the
    receiver keeps confirming it holds them: a stopped one would read them overwritten)."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    total = 50 + _HELD_THEN_STALLED + _AFTER
    proc = subprocess.Popen([sys.executable, "-c", _STALLED_RECEIVER, ep, str(total)], cwd=_procs.REPO,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines = _procs.LineWatch(proc.stdout)
    try:
        lines.wait_for(lambda ln: ln.strip() == "ready", timeout=60)
        with opened(make_config(connect=[ep])) as session:
            assert wait_for_subscribers(session, ["stall/x"], 30.0, StopFlag(install=False))
            pub = declare_publisher(session, "stall/x", cache_samples=1)
            sent = 0
            for stage in (50, _HELD_THEN_STALLED):  # the first 50: Zenoh sets up its pool meanwhile
                for _ in range(stage):
                    pub.put(_numbered(sent))
                    sent += 1
                lines.wait_for(lambda ln, k=sent: ln.strip() == f"held {k}", timeout=60)
            os.kill(proc.pid, signal.SIGSTOP)
            try:
                time.sleep(1.0)  # the fault itself (Zenoh's watchdogs: 50 ms confirm, 100 ms check)
            finally:
                os.kill(proc.pid, signal.SIGCONT)
            for _ in range(_AFTER):
                pub.put(_numbered(sent))
                sent += 1
            lines.wait_for(lambda ln: ln.strip() == f"held {total}", timeout=60)
            proc.stdin.write("drain\n")
            proc.stdin.flush()
            result = json.loads(lines.wait_for(lambda ln: ln.startswith("{"), timeout=60))
            pub.undeclare()
        rc = proc.wait(timeout=60)  # it ends by itself once it has read them all
    finally:
        _procs.stop(proc)
    assert result["n"] == total and result["bad"] == [], (result["bad"][:10], len(result["bad"]))
    assert rc == 0, proc.stderr.read()


# --------------------------------------------------------------------------------------
# A consumer told that the node it follows is gone for good ends once drained
# --------------------------------------------------------------------------------------

_CONSUMER = """
import json, sys, time
from bttsim_stream.bus.session import StopFlag, make_config
from bttsim_stream.runtime import node_session

# argv: endpoint, samples to announce ("all in"), samples that make it done (-1: never), patience
n_sent, n_all, patience = int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4])
with node_session(make_config(listen=[sys.argv[1]]), "rig1", "recorder") as ctx:
    ctx.subscribe("bttsim/rig1/data")
    ctx.watch_nodes(("sim",))
    ctx.announce()
    print("ready", flush=True)
    n = 0
    for r in ctx.samples(StopFlag(install=False), done=lambda: n_all >= 0 and n >= n_all, patience_s=patience):
        n += r is not None
        if r is not None and n == n_sent:
            print("all in", flush=True)
    print(json.dumps({"n": n, "final": ctx.watch.final, "sent": sorted(ctx.watch.sent), "t": time.monotonic()}),
          flush=True)
"""

_PUBLISHER = """
import sys, time
from bttsim_stream.bus.session import make_config
from bttsim_stream.runtime import node_session

with node_session(make_config(connect=[sys.argv[1]]), "rig1", "sim") as ctx:
    ctx.announce()
    pub = ctx.publisher("bttsim/rig1/data")
    for i in range(int(sys.argv[2])):
        pub.put(i.to_bytes(8, "little"))
    if sys.argv[3:] == ["declare"]:
        print("declaring", time.monotonic(), flush=True)  # one clock for every process (Linux)
        ctx.sent()  # all published; now it would wait for its consumers' confirmations
    print("sent", flush=True)
    sys.stdin.readline()  # until killed (or told)
"""


@pytest.mark.integration
def test_a_consumer_told_its_publisher_is_gone_for_good_ends_once_drained():
    """A consumer whose publisher died mid-run would wait its whole patience (``--drain-timeout``)
    of silence for the rest: the publisher might come back. Told by the gone signal (what
    ``bttsim run`` sends once it has reaped the failed node), it ends as soon as what came is
    handed out -- every sample the publisher sent before it died."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    n = 500
    # never done, and an hour of patience: only the gone signal ends it before the test's timeout
    consumer = subprocess.Popen([sys.executable, "-c", _CONSUMER, ep, str(n), "-1", "3600"], cwd=_procs.REPO,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    publisher = None
    try:
        out = _procs.LineWatch(consumer.stdout)
        out.wait_for(lambda ln: ln.strip() == "ready", timeout=60)
        publisher = subprocess.Popen([sys.executable, "-c", _PUBLISHER, ep, str(n)], cwd=_procs.REPO,
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        _procs.LineWatch(publisher.stdout).wait_for(lambda ln: ln.strip() == "sent", timeout=60)
        out.wait_for(lambda ln: ln.strip() == "all in", timeout=60)
        publisher.kill()
        publisher.wait(30)
        consumer.send_signal(GONE_SIGNAL)
        line = out.wait_for(lambda ln: ln.startswith("{"), timeout=60)
        got = json.loads(line)
        assert (got["n"], got["final"]) == (n, True)
        assert consumer.wait(30) == 0
    finally:
        for p in (publisher, consumer):
            if p is not None and p.poll() is None:
                p.kill()
                p.wait()


_EXITING_CONSUMER = """
import signal
from bttsim_stream.bus.session import GONE_SIGNAL, make_config
from bttsim_stream.runtime import node_session

with node_session(make_config(), "rig1", "viewer") as ctx:
    ctx.watch_nodes(("sim", "processor"))
    assert signal.getsignal(GONE_SIGNAL) not in (signal.SIG_IGN, signal.SIG_DFL)  # handled while it runs
status = dict(line.split(":", 1) for line in open("/proc/self/status") if line.startswith("SigIgn"))
print(int(status["SigIgn"], 16) >> (int(GONE_SIGNAL) - 1) & 1, flush=True)
"""


@pytest.mark.integration
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/status")
def test_a_closed_node_ignores_the_gone_signal_while_it_exits():
    """``bttsim run`` sends the gone signal once the last node a consumer follows is reaped,
    which may be while that consumer is exiting, its work done. Python resets its own signal
    handlers to the default action (terminate) at interpreter exit, and a viewer died so of a
    late signal (the run then said it had failed). Once its session is closed, a node ignores
    the signal in the kernel, where the interpreter's exit does not undo it."""
    out = subprocess.run([sys.executable, "-c", _EXITING_CONSUMER], cwd=_procs.REPO, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "1"


@pytest.mark.integration
@pytest.mark.parametrize("lost_tail", [False, True])
def test_a_consumer_that_lost_the_tail_ends_while_its_publisher_waits(lost_tail):
    """The simulator stays after its last sample until its consumers confirm the whole stream;
    a consumer that waited for the simulator to leave would wait for ever when it lacks the
    tail (lost to a link cut). Once the publisher declares that it has sent all, a consumer
    lacking part of the run ends after its patience of silence, while the publisher still
    waits; one with everything still ends only once the publisher has left (the processor's
    last results may still be on their way)."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    n = 300
    patience = 2.0
    consumer = subprocess.Popen([sys.executable, "-c", _CONSUMER, ep, str(n), str(n + 1 if lost_tail else n),
                                 str(patience)], cwd=_procs.REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                text=True)
    publisher = None
    try:
        out = _procs.LineWatch(consumer.stdout)
        out.wait_for(lambda ln: ln.strip() == "ready", timeout=60)
        publisher = subprocess.Popen([sys.executable, "-c", _PUBLISHER, ep, str(n), "declare"], cwd=_procs.REPO,
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        said = _procs.LineWatch(publisher.stdout)
        t_sent = float(said.wait_for(lambda ln: ln.startswith("declaring"), timeout=60).split()[1])
        said.wait_for(lambda ln: ln.strip() == "sent", timeout=60)
        if not lost_tail:  # it has everything: it waits for the publisher to leave, as before
            out.wait_for(lambda ln: ln.strip() == "all in", timeout=60)
            with pytest.raises(subprocess.TimeoutExpired):
                consumer.wait(timeout=3 * 0.5)  # three times its idle time: still there
            publisher.stdin.write("\n")
            publisher.stdin.flush()
        got = json.loads(out.wait_for(lambda ln: ln.startswith("{"), timeout=60))
        assert got["n"] == n and got["sent"] == (["sim"] if lost_tail else [])  # left: its token went
        if lost_tail:  # it ended while the publisher still waited, after its patience of silence
            assert publisher.poll() is None
            assert got["t"] - t_sent >= patience
        assert consumer.wait(30) == 0
    finally:
        for p in (publisher, consumer):
            if p is not None:
                _procs.stop(p, signal.SIGKILL)

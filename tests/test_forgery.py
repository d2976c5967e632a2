"""Forged data on a run without security stays out of the record.

A real ``bttsim run`` through a ``bttsim router`` (loopback, multicast scouting off), with
forgers connected to the same router: garbage on the TOA keys, a forger that answers every
real ``toa/0`` batch at once with garbage and a well-formed batch for the next number
(racing the real one), and a flood on ``fit``. The recording's data channels must equal a
clean run's message by message (key, sequence number, payload, log time), every forgery
counted by the recorder, and the refused copies (bounded) only on ``rejected/...`` channels.
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from _procs import LineWatch, start, stop
from bttsim_stream.bus.admission import KEEP_REJECTED
from bttsim_stream.bus.recording import read_messages, read_recording
from bttsim_stream.bus.session import free_port

pytestmark = pytest.mark.integration

REPO = Path(__file__).resolve().parents[1]
FORGER = Path(__file__).resolve().parent / "_forger.py"
SHORT = "[speed]\nstart_rpm = 2400.0\nend_rpm = 2800.0\nduration_s = 6.0\n"
# the acceptance case floods for 20 s (BTTSIM_FLOOD_S=20): the same rate, shorter by default
FLOOD_RATE, FLOOD_S = 10000, float(os.environ.get("BTTSIM_FLOOD_S", "2"))
N_GARBAGE = 1000


def bttsim(*args, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "bttsim_stream.cli", *map(str, args)], cwd=REPO,
                          capture_output=True, text=True, timeout=timeout)


def data(out: Path) -> list:
    rec = read_recording(out / "run.mcap")
    assert not rec.truncated and not any(k.startswith("rejected/") for k in rec.keys())
    return sorted((m.key, m.seq, m.payload, m.log_time_ns) for m in rec.messages)


def node_stats(out: Path, name: str = "recorder") -> dict:
    """A node's final statistics: the JSON line it printed last (its log holds its stdout)."""
    text = (out / f"{name}.log").read_text()
    return json.loads([ln for ln in text.splitlines() if ln.startswith("{")][-1])


recorder_stats = node_stats


@pytest.fixture(scope="module")
def router():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    proc = start("bttsim_stream.nodes", "router", "-l", endpoint)
    LineWatch(proc.stdout).wait_for(lambda line: "router ready" in line)
    yield endpoint
    assert stop(proc) == 0


@pytest.fixture(scope="module")
def scenario(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("scn") / "short.toml"
    path.write_text(SHORT)
    return path


def test_forgeries_stay_out_of_the_record(scenario, router, tmp_path):
    clean = tmp_path / "clean"
    res = bttsim("run", scenario, "--out", clean, "-q", "-m", "client", "-e", router)
    assert res.returncode == 0, res.stdout + res.stderr
    forgers = {
        "garbage": ("--garbage", N_GARBAGE, "--once", "--period", 0.001),
        "next": ("--next", "bttsim/rig1/toa/0"),
        "flood": ("--flood", "bttsim/rig1/fit", "--rate", FLOOD_RATE, "--seconds", FLOOD_S),
    }
    procs = {name: subprocess.Popen([sys.executable, str(FORGER), str(scenario), "-e", router, *map(str, flags)],
                                    cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for name, flags in forgers.items()}
    stats = {}
    try:
        for name, f in procs.items():
            assert "forger connected" in f.stdout.readline(), (name, f.stderr.read() if f.poll() is not None else "")
        out = tmp_path / "forged"
        res = bttsim("run", scenario, "--out", out, "-q", "-m", "client", "-e", router)
        for name, f in procs.items():
            assert stop(f) == 0, f.stderr.read()
            stats[name] = json.loads(f.stdout.read().strip().splitlines()[-1])
    finally:
        for f in procs.values():
            stop(f)
    text = res.stdout + res.stderr
    # the record, the result and the views are whole: every node admits as the recorder does
    assert res.returncode == 0, res.stderr[-3000:]
    assert "Traceback" not in text + "".join((out / f"{n}.log").read_text()
                                             for n in ("recorder", "processor", "sim", "viewer"))
    assert data(out) == data(clean)  # the record is the clean run's, message by message
    rec = recorder_stats(out)
    assert rec["complete"] and rec["conflicts"] == 0 and rec["missing"] == 0, rec
    by_key = rec["rejected_by_key"]
    toa = sum(n for k, n in by_key.items() if "/toa/" in k)
    assert stats["garbage"]["put"] == N_GARBAGE and stats["next"]["put"] > 100 and stats["flood"]["put"] > 0.9 * \
        FLOOD_RATE * FLOOD_S, stats
    # every forgery that reached the recorder is counted: all the batches racing the real toa/0
    # ones (put while the run publishes), and the garbage put once its keys had a first
    # subscriber -- which may be the processor, before the recorder subscribed (the flood drops)
    assert stats["next"]["put"] <= toa <= N_GARBAGE + stats["next"]["put"], (by_key, stats)
    assert by_key["bttsim/rig1/toa/0"] >= stats["next"]["put"], (by_key, stats)
    assert 0.5 * stats["flood"]["put"] <= by_key.get("bttsim/rig1/fit", 0) <= stats["flood"]["put"], (by_key, stats)
    assert rec["rejected_reasons"].get("not from the session that published the run", 0) > 0, rec["rejected_reasons"]
    assert rec["rejected"] == sum(by_key.values()) == sum(rec["rejected_reasons"].values())
    # the views: the same checks (bus/admission.py), nothing missed, the forgeries counted, not shown
    view = node_stats(out, "viewer")
    assert view["complete"] and view["missing"] == 0 and view["conflicts"] == 0 and view["gaps"] == 0, view
    # the batches racing the real toa/0 ones come while the run publishes, the viewer subscribed:
    # every one refused (the garbage and the flood start at the first subscriber, the recorder:
    # they may be over before the viewer, slower to start, subscribes)
    view_toa = sum(n for k, n in view["rejected_by_key"].items() if "/toa/" in k)
    assert stats["next"]["put"] <= view_toa <= N_GARBAGE + stats["next"]["put"], (view, stats)
    assert view["rejected_by_key"]["bttsim/rig1/toa/0"] >= stats["next"]["put"], (view, stats)
    assert view["rejected_reasons"].get("not from the session that published the run", 0) > 0, view
    assert view["rejected_by_key"].get("bttsim/rig1/fit", 0) <= stats["flood"]["put"]
    assert view["rejected"] == sum(view["rejected_by_key"].values()) == sum(view["rejected_reasons"].values())
    assert view["messages"] == rec["messages"], (view["messages"], rec["messages"])  # what was shown: the record
    kept = {}
    for m in read_messages(out / "run.mcap", "rejected/**"):
        kept[m.key] = kept.get(m.key, 0) + 1
    assert kept and max(kept.values()) <= KEEP_REJECTED and sum(kept.values()) == rec["rejected_kept"], kept
    assert kept.get("rejected/bttsim/rig1/fit") == KEEP_REJECTED  # a flood: bounded
    res = bttsim("process", out / "run.mcap", "--summary", tmp_path / "s.json")
    assert res.returncode == 0, res.stderr

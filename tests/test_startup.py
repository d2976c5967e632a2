"""What the command line and the bus's consumers import at start-up, and how the live loop
batches its work.

Every node is a process of its own that pays its imports: a recorder, a processor or a viewer
decodes the bus without the modal model, the scenario parser or the simulator; only the
processor's final report loads scipy. Every ``bttsim`` command builds the parsers of every
command and node: that loads none of their machinery (each command and each node's ``main``
imports its own).
"""
import ast
import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

from bttsim_stream import process
from bttsim_stream.acquisition import AcquisitionStream
from bttsim_stream.bus import keys
from bttsim_stream.runtime import WAKE_AT, Inbox
from bttsim_stream.scenario import scenario_from_dict

pytestmark = pytest.mark.unit

#: Modules no consumer of the bus needs before it has work for them.
HEAVY = ("bttsim_stream.model", "bttsim_stream.scenario", "bttsim_stream.sim.core", "bttsim_stream.process.pipeline",
         "bttsim_stream.process.streaming", "scipy")


#: What building the parsers must not load besides: the recordings, the live run and the
#: package metadata (read only by a command that writes the version).
MACHINERY = HEAVY + ("bttsim_stream.bus.codec", "bttsim_stream.bus.recording", "bttsim_stream.bus.stream",
                     "bttsim_stream.acquisition", "bttsim_stream.offline", "bttsim_stream.processor",
                     "bttsim_stream.orchestrate", "bttsim_stream.views", "mcap", "google.protobuf", "rerun",
                     "importlib.metadata")
NODES = Path(__file__).resolve().parents[1] / "nodes"


def _loaded(code: str) -> set[str]:
    out = subprocess.run([sys.executable, "-c", code + "\nimport sys, json; print(json.dumps(sorted(sys.modules)))"],
                         capture_output=True, text=True, check=True, timeout=120)
    return set(json.loads(out.stdout.splitlines()[-1]))


def _node_imports(node: str) -> str:
    """Every import statement of the node's module, those inside its ``main`` and helpers too
    (read from its source): what the node has loaded once it runs."""
    tree = ast.parse((NODES / f"{node}.py").read_text())
    return "\n".join(ast.unparse(n) for n in ast.walk(tree)
                     if isinstance(n, (ast.Import, ast.ImportFrom)) and getattr(n, "module", "") != "__future__")


@pytest.mark.parametrize("node", ["recorder_node", "viewer_node"])
def test_a_recorder_and_a_viewer_start_without_the_simulator_or_the_processing(node):
    mods = _loaded(_node_imports(node))
    assert "bttsim_stream.bus.codec" in mods and "bttsim_stream.sim.records" in mods
    assert not sorted(m for m in mods if m in HEAVY)


def test_the_processor_starts_without_the_simulator_and_scipy():
    mods = _loaded(_node_imports("processor_node"))
    assert "bttsim_stream.processor" in mods and "bttsim_stream.process.streaming" in mods
    assert not sorted(m for m in mods if m in HEAVY[:3] + ("scipy",))


def test_the_parsers_of_every_command_and_node_load_none_of_their_machinery():
    mods = _loaded("import bttsim_stream.cli; bttsim_stream.cli.build_parser()")
    assert {f"bttsim_stream.nodes.{m}" for m in ("sim_node", "recorder_node", "processor_node")} <= mods
    assert not sorted(m for m in mods if m in MACHINERY or m.split(".")[0] in MACHINERY)


def test_the_processing_package_gives_every_public_name_from_its_module():
    import importlib

    for name in process.__all__:
        value = getattr(process, name)
        home = getattr(value, "__module__", None)
        if isinstance(home, str):  # a class or a function: the very object of its module
            assert home.startswith("bttsim_stream.process.") and getattr(importlib.import_module(home), name) is value
    assert set(dir(process)) >= set(process.__all__)
    with pytest.raises(AttributeError):
        process.no_such_name  # noqa: B018
    from bttsim_stream.sim import core, records  # the simulator re-exports its records
    assert core.RunInfo is records.RunInfo and core.Truth is records.Truth
    assert core.RevolutionBatch is records.RevolutionBatch


def test_the_inbox_hands_out_everything_in_order_and_wakes_its_consumer_for_a_batch():
    import threading

    box = Inbox(1 << 16)
    assert box.take(0.0) == []
    woke = []

    def consumer():
        t0 = time.monotonic()
        box.wait(60.0)  # no timeout in practice: only a batch ends this sleep
        woke.append(time.monotonic() - t0)

    th = threading.Thread(target=consumer)
    th.start()
    while not box._sleeping:
        time.sleep(0.001)
    for i in range(WAKE_AT - 1):
        box.put(i)
    assert not woke and th.is_alive()  # fewer than a batch: still asleep
    box.put(WAKE_AT - 1)
    th.join(30.0)
    assert woke and not th.is_alive()
    assert box.take(0.0) == list(range(WAKE_AT)) and box.qsize() == 0


def test_live_views_flush_less_often_while_messages_keep_coming(tmp_path):
    from bttsim_stream import views

    stream = AcquisitionStream(scenario_from_dict({"speed": {"start_rpm": 2400.0, "end_rpm": 2500.0,
                                                             "duration_s": 1.0}}), include_truth=False)
    rec, _ = views.open_recording(rrd_path=tmp_path / "live.rrd")
    live = views.LiveViews(rec, live=True, flush_period_s=100.0)
    assert live.busy_flush_period_s == 500.0
    live.feed(stream.meta.key, stream.meta.payload)
    msgs = [m for _, batch in stream.batches() for m in batch]
    live._last_flush = time.monotonic() - 200.0  # the quiet period has passed, not the busy one
    for m in msgs[:3]:
        live.feed(m.key, m.payload)
    assert live.stats["revolutions"] == 0  # nothing flushed while messages keep coming
    assert live.poll()  # a quiet bus: flushed
    live._last_flush = time.monotonic() - 600.0
    live.feed(msgs[3].key, msgs[3].payload)  # the busy period has passed too: flushed on feed
    assert time.monotonic() - live._last_flush < 100.0
    for m in msgs[4:]:
        live.feed(m.key, m.payload)
    live.close()
    rec.disconnect()
    n = stream.info.n_revolutions
    assert live.stats["revolutions"] == n and live.stats["messages"] == len(msgs) + 1
    assert all(keys.parse_key(m.key).rig == stream.rig for m in msgs)

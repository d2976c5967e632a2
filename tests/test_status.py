"""Node status (``bttsim/<rig>/status/<node>``): the JSON message, its strict decoding, the
atomic status file, the board that keeps each expected node's latest status, and its rule in
the access-control policy."""

import json
import time

import pytest
import zenoh

from bttsim_stream.bus import keys
from bttsim_stream.bus.security import access_control_policy
from bttsim_stream.bus.session import free_port, make_config
from bttsim_stream.bus.status import (MAX_STATUS_BYTES, SCHEMA, NodeStatus, StatusBoard, decode_status,
                                      encode_status, read_status_file, write_status_file)
from bttsim_stream.errors import BttsimError
from bttsim_stream.summary import build_summary, recording_block, with_recording

pytestmark = pytest.mark.unit

KEY = "bttsim/rig1/status/recorder"
STATS = {"messages": 12, "complete": True, "missing_by_key": {"bttsim/rig1/opr": {"head": 0, "gaps": 1, "tail": 0}}}


def _raw(**change) -> bytes:
    msg = {"schema": SCHEMA, "node": "recorder", "state": "done", "seq": 2, "url": "", "stats": STATS}
    msg.update(change)
    return json.dumps({k: v for k, v in msg.items() if v is not ...}).encode()


def test_a_status_round_trips_and_names_its_node_in_its_key():
    s = NodeStatus("recorder", "done", 2, "", STATS)
    back = decode_status(encode_status(s), KEY, nodes=("recorder", "viewer"))
    assert back == s and back.final
    assert keys.status_key("rig1", "recorder") == KEY and keys.parse_key(KEY).node == "recorder"
    assert keys.is_status_key(KEY) and not keys.is_status_key("bttsim/rig1/opr")
    assert not NodeStatus("viewer", "starting", 0, "http://x").final


@pytest.mark.parametrize("payload, where", [
    (b"\xff\xfe", "not UTF-8 JSON"),
    (b"[1, 2]", "not a bttsim.status.v1"),
    (b"[" * 100_000 + b"]" * 100_000, "bttsim.status.v1|JSON"),  # deep nesting: refused, no crash
    (_raw(schema="bttsim.status.v2"), "not a bttsim.status.v1"),
    (_raw(extra=1), "not a bttsim.status.v1"),
    (_raw(url=...), "not a bttsim.status.v1"),
    (_raw(state="finished"), "state"),
    (_raw(seq=-1), "seq"),
    (_raw(seq=True), "seq"),
    (_raw(seq=1.5), "seq"),
    (_raw(url="x" * 5000), "url"),
    (_raw(stats=[1]), "stats"),
    (_raw(node="rec/order"), "node name"),
    (_raw(node="viewer"), "on bttsim/rig1/status/recorder"),  # posing as another node
], ids=["utf8", "array", "deep", "schema", "extra", "missing", "state", "seq-neg", "seq-bool", "seq-float",
        "url-long", "stats-list", "node-bad", "node-not-key"])
def test_a_malformed_status_is_a_one_line_error(payload, where):
    with pytest.raises(BttsimError, match=where):
        decode_status(payload, KEY)


def test_size_and_node_names_are_checked():
    with pytest.raises(BttsimError, match="bytes"):
        decode_status(b" " * (MAX_STATUS_BYTES + 1), KEY)
    with pytest.raises(BttsimError, match="bytes"):
        encode_status(NodeStatus("recorder", "done", 0, "", {"x": "y" * MAX_STATUS_BYTES}))
    with pytest.raises(BttsimError, match="unexpected node"):
        decode_status(_raw(), KEY, nodes=("viewer",))


def test_the_status_file_is_replaced_whole_and_read_back_only_for_its_node(tmp_path):
    path = tmp_path / "recorder.json"
    assert read_status_file(path, "recorder") is None  # no file yet
    write_status_file(path, NodeStatus("recorder", "ready", 1))
    write_status_file(path, NodeStatus("recorder", "done", 2, "", STATS))
    assert [p.name for p in tmp_path.iterdir()] == ["recorder.json"]  # no temporary file left
    assert read_status_file(path, "recorder") == NodeStatus("recorder", "done", 2, "", STATS)
    assert read_status_file(path, "viewer") is None
    path.write_bytes(b'{"schema": "bttsim.status.v1", "node": "recorder", "sta')  # half a file
    assert read_status_file(path, "recorder") is None


def test_the_board_keeps_the_latest_status_of_the_expected_nodes_only(tmp_path):
    port = free_port()
    listen = make_config(listen=[f"tcp/127.0.0.1:{port}"])
    join = make_config(connect=[f"tcp/127.0.0.1:{port}"])
    with zenoh.open(listen) as a, zenoh.open(join) as b:
        board = StatusBoard(a, "rig1", ("recorder", "viewer"), files={"viewer": tmp_path / "viewer.json"})
        try:
            pubs = {k: b.declare_publisher(k) for k in
                    (KEY, "bttsim/rig1/status/viewer", "bttsim/rig1/status/intruder", "bttsim/rig1/status/sim")}
            deadline = time.monotonic() + 30  # ready once the board's subscription has reached b
            while not all(p.matching_status.matching for p in pubs.values()) and time.monotonic() < deadline:
                time.sleep(0.02)
            assert all(p.matching_status.matching for p in pubs.values()), "the board never subscribed"
            pubs[KEY].put(encode_status(NodeStatus("recorder", "ready", 1)))
            pubs[KEY].put(encode_status(NodeStatus("recorder", "done", 3, "", STATS)))
            pubs[KEY].put(encode_status(NodeStatus("recorder", "ready", 2)))  # older: kept out
            pubs["bttsim/rig1/status/intruder"].put(encode_status(NodeStatus("intruder", "done", 9)))
            pubs["bttsim/rig1/status/sim"].put(encode_status(NodeStatus("recorder", "done", 9)))  # wrong key
            pubs["bttsim/rig1/status/viewer"].put(b"{not json")
            got = board.final("recorder", wait_s=5.0)
            deadline = time.monotonic() + 5
            while board.rejected < 3 and time.monotonic() < deadline:
                time.sleep(0.05)
            assert got == NodeStatus("recorder", "done", 3, "", STATS)
            assert board.get("recorder").seq == 3 and board.get("intruder") is None and board.rejected == 3
            # nothing final on the bus for the viewer: its status file answers
            assert board.final("viewer") is None
            write_status_file(tmp_path / "viewer.json", NodeStatus("viewer", "serving", 4, "http://v", {"gaps": 0}))
            assert board.final("viewer").stats == {"gaps": 0} and board.get("viewer").url == "http://v"
            for p in pubs.values():
                p.undeclare()
        finally:
            board.close()


def test_each_identity_may_put_only_its_own_status_and_every_member_receives_status():
    acl = access_control_policy()
    by_id = {r["id"]: r for r in acl["rules"]}

    def who(rule_id):
        return {s for p in acl["policies"] if rule_id in p["rules"] for s in p["subjects"]}

    for n in ("sim", "processor", "recorder", "viewer", "run"):
        assert by_id[f"status of {n}"]["key_exprs"] == [f"bttsim/*/status/{n}"] and who(f"status of {n}") == {n}
        assert by_id[f"status of {n}"]["flows"] == ["ingress"]
    assert "bttsim/*/status/*" in by_id["receive data"]["key_exprs"]
    assert who("relay status") == {"router"}


def test_one_summary_builder_keeps_the_key_order_and_the_recording_verdict():
    from bttsim_stream.bus.stream import Completeness

    c = Completeness(revolutions_expected=10, revolutions_processed=10, lost=0, duplicates=0, rejected=0)
    s = build_summary({"nd": 1, "complete": "overwritten"}, c, missing_toas=3, doubles={"double_pulses": 0})
    assert list(s)[:2] == ["nd", "complete"] and s["missing_toas"] == 3 and s["double_pulses"] == 0
    assert s["complete"] is True
    assert with_recording(s, {"complete": True, "missing": 0})["complete"] is True
    bad = with_recording(s, {})  # the recorder gave no statistics: the run is not known complete
    assert bad["complete"] is False and bad["recording"] == recording_block({})
    assert "no completeness statistics" in bad["recording"]["incomplete"]


def test_a_status_put_never_waits_on_the_nodes_own_full_subscription():
    """A recorder or viewer subscribes to every key of its rig through a bounded FIFO, which
    only its main thread drains. With the FIFO full (a publisher flooding the rig), its own
    status put must return: delivered to its own subscription it would wait for ever on the
    thread that is putting (seen with a replay at full rate and a slow recorder)."""
    import threading

    from bttsim_stream.runtime import node_session

    port = free_port()
    with node_session(make_config(listen=[f"tcp/127.0.0.1:{port}"]), "rig1", "recorder", fifo_size=4,
                      linger_s=0.0) as node, zenoh.open(make_config(connect=[f"tcp/127.0.0.1:{port}"])) as other:
        node.subscribe(keys.all_key("rig1"))  # never drained below: the FIFO fills
        pub = other.declare_publisher("bttsim/rig1/opr", congestion_control=zenoh.CongestionControl.DROP)
        deadline = time.monotonic() + 60
        while not pub.matching_status.matching and time.monotonic() < deadline:
            time.sleep(0.02)
        for _ in range(64):
            pub.put(b"x")
        sent = threading.Event()

        def report() -> None:
            for state in ("ready", "done"):
                node.status(state)
            sent.set()

        threading.Thread(target=report, daemon=True).start()
        assert sent.wait(30), "the status put waited on the node's own full subscription"
        while node._live[0].try_recv() is not None:  # let Zenoh's receiving thread go before closing
            pass

"""Recorder node: writes every ``bttsim/<rig>/**`` sample to an MCAP file, as received.

Inputs: every key of the rig (run metadata, OPR, TOA batches, truth, fits, travelling waves,
resonance reports); the run metadata sample is also written as the ``bttsim.run`` metadata
record. Output: ``OUT.mcap`` with zstd chunks, one channel per key, the protobuf schemas
embedded, log time = simulated time (from the sample attachment; payloads are not decoded).
Completeness: the run metadata fixes the count of the metadata, OPR, TOA and truth keys
(``n_revolutions`` each, numbered from 0); the recording is complete when every one of them
is whole to its last number and nothing is missing on the other keys (result keys: fits,
travelling waves, resonance reports -- checked before their first and between their numbers
received; their count is not known). A run with no metadata received is incomplete. A key of
no run (another rig, a probe the run does not have) cannot make it incomplete: it is listed
in ``foreign_keys``. The statistics -- ``complete``, ``missing`` and ``missing_by_key`` (head,
gaps, tail per key), ``foreign_keys``, sequence gaps, duplicates, rejected -- are logged, printed
as one JSON line on stdout, written as the ``bttsim.recorder`` metadata record and sent as the ``stats`` of the node's
final status (``bttsim/<rig>/status/recorder``, state ``done``; also to ``--status-file``).
Status keys themselves are not recorded. Liveliness: ``bttsim/<rig>/alive/recorder``.

Stops when the liveliness tokens of the nodes named by ``--until`` (default: the simulator,
``alive/sim``) have gone, after ``--duration`` seconds, or on SIGINT / SIGTERM; the file is
finalised in every case. After SIGKILL the file reads back up to its last complete chunk.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time

from bttsim_stream.bus import codec, keys
from bttsim_stream.bus.recording import MAX_SEQ, McapRecorder
from bttsim_stream.bus.session import StopFlag
from bttsim_stream.bus.stream import SequenceTracker, StreamEnd, acquisition_counts
from bttsim_stream.runtime import NodeProgram, add_status_argument, node_session, run_node

log = logging.getLogger("bttsim.recorder")


def main(conf, args: argparse.Namespace) -> dict:
    """Record until stopped; returns (and prints as JSON) the gap statistics."""
    rig = args.rig if args.rig == "*" else keys.validate_rig(args.rig)
    until = tuple(n for n in args.until.split(",") if n)
    stop = StopFlag(args.duration)
    stats = SequenceTracker()
    rejected = 0
    meta_done: set[str] = set()
    ends: dict[str, StreamEnd] = {}  # per rig: has the whole acquisition stream come in?
    with McapRecorder(args.out) as rec, \
            node_session(conf, rig if rig != "*" else "any", "recorder", inbox_size=args.queue,
                         status_file=args.status_file) as node:
        node.subscribe(keys.all_key(rig), history=True)
        if until:
            node.watch_nodes(until)
        node.announce()
        for sample in node.samples(stop):
            if sample is None:
                continue
            key, att = sample.key, sample.att
            if keys.is_status_key(key):  # the nodes' own state: not part of the run's record
                continue
            seq, t_ns = att if att is not None else (None, time.time_ns())
            if (seq is not None and seq >= MAX_SEQ) or t_ns < 0:  # untrusted: MCAP cannot hold it
                rejected += 1
                if rejected <= 3:
                    log.warning("rejected a sample on %s (sequence %s, time %s ns)", key, seq, t_ns)
                continue
            if not stats.accept(key, seq):
                continue
            payload = sample.payload
            if key.endswith("/meta") and key not in meta_done:
                info = codec.decode_run_metadata(payload, key).body
                rec.write_run_metadata(info.run_id, info.rig, info.scenario_toml, info.software_version)
                meta_done.add(key)
                ends[info.rig] = StreamEnd(info)
                stats.expect(acquisition_counts(info))
                node.ready()
            rec.write(key, payload, t_ns, seq=seq or 0)
            key_rig = key.split("/", 2)[1]
            end = ends.get(key_rig)
            if end is not None and not end.done:
                end.note(key, seq)
                if end.done:
                    node.done(key_rig)
        summary = dict(stats.summary(), rejected=rejected + stats.implausible,
                       **_completeness(stats, ends, None if rig == "*" else rig))
        rec.write_metadata("bttsim.recorder", {k: json.dumps(v) for k, v in summary.items()})
        node.status("done", summary)
    if summary["complete"]:
        log.info("recorded %d messages on %d keys to %s; complete", summary["messages"], summary["keys"], args.out)
    else:
        log.warning("recorded %d messages on %d keys to %s; INCOMPLETE: %s", summary["messages"], summary["keys"],
                    args.out, summary["incomplete"])
    print(json.dumps(summary), flush=True)
    return summary


def _completeness(stats: SequenceTracker, ends: dict[str, StreamEnd], rig: str | None) -> dict:
    """The statistics' completeness keys: ``complete``, ``missing``, ``missing_by_key``
    (``{key: {"head", "gaps", "tail"}}``), ``run_metadata`` (the rigs whose metadata came)
    and ``incomplete`` (one line saying why, "" if complete)."""
    expected: dict[str, int] = {}
    for end in ends.values():
        expected.update(end.counts)
    missing, foreign = {}, {}
    for key, m in stats.missing(expected).items():
        (missing if _of_the_run(key, expected, ends) else foreign)[key] = m
    why = []
    if not ends or (rig is not None and rig not in ends):
        why.append(f"no run metadata received{f' for {rig}' if rig else ''}")
    if missing:
        total = sum(m.total for m in missing.values())
        why.append(f"{total} messages missing (" + ", ".join(
            f"{k.split('/', 2)[-1]} {m.total}" for k, m in missing.items()) + ")")
    return {"complete": not why, "missing": sum(m.total for m in missing.values()),
            "missing_by_key": {k: m.to_dict() for k, m in missing.items()}, "run_metadata": sorted(ends),
            "foreign_keys": sorted(foreign), "incomplete": "; ".join(why)}


def _of_the_run(key: str, expected: dict[str, int], ends: dict[str, StreamEnd]) -> bool:
    """Does ``key`` belong to a run whose metadata came (its rig; a probe's key only for a probe
    the run has)? A key of no run (a forger's ``toa/7`` of a 5-probe run) cannot make the
    recording incomplete: its numbers are counted under ``foreign_keys``, not as missing."""
    parts = key.split("/")
    if len(parts) < 3 or parts[1] not in ends:
        return False
    if len(parts) == 4 and parts[2] in ("toa", "tw", "signal"):
        return f"{parts[0]}/{parts[1]}/toa/{parts[3]}" in expected
    return True


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", required=True, metavar="FILE.mcap", help="output MCAP file")
    p.add_argument("--rig", default="*", help="rig to record (default: every rig)")
    p.add_argument("--duration", type=float, metavar="S", help="stop after S seconds")
    p.add_argument("--until", default="sim", metavar="NODES",
                   help="comma-separated nodes whose end ends the recording ('sim'; '' = only a signal "
                        "or --duration)")
    p.add_argument("--queue", type=int, default=1 << 20, metavar="N",
                   help="samples buffered before the network is slowed down (1048576)")
    add_status_argument(p)


PROGRAM = NodeProgram("recorder", __doc__, add_arguments, main)


def run(argv=None) -> int:
    return run_node(PROGRAM, argv)


if __name__ == "__main__":
    sys.exit(run())

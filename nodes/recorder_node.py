"""Recorder node: writes every valid ``bttsim/<rig>/**`` message to an MCAP file.

Inputs: every key of the rig (run metadata, OPR, TOA batches, truth, fits, travelling waves,
resonance reports); the run metadata sample is also written as the ``bttsim.run`` metadata
record. Output: ``OUT.mcap`` with zstd chunks, one channel per key, the protobuf schemas
embedded, log time = simulated time (from the sample attachment), payloads as received.

Only valid messages go into a key's channel: each one is decoded and checked against the run
as the processor checks it (:class:`~bttsim_stream.bus.admission.RecordGate`: run id,
sequence number and time against the header, probe, blade count, revolution, the publishing
session); the rest are refused, counted per key and reason, and the first ones kept on
``rejected/<key>`` channels that no reader of the data reads. A second, different payload for
a number already written is a conflict (the first one stays), counted.

Completeness: the run metadata fixes the count of the metadata, OPR, TOA and truth keys
(``n_revolutions`` each, numbered from 0); the recording is complete when every one of them
is whole to its last number, nothing is missing on the other keys (result keys: fits,
travelling waves, resonance reports -- checked before their first and between their numbers
received; their count is not known; when ``--until`` names the processor, its resonance
report must have come: one message, numbered 0) and nothing conflicted. A number that fills a gap late (a
publisher's cache replayed after the recorder stalled) closes it. A run with no metadata
received is incomplete. Keys of no run (another rig, a probe the run does not have) are
refused and listed in ``foreign_keys``. Data of a run whose metadata has not come waits
(bounded) while the recorder asks the run's ``bttsim/<rig>/meta`` queryable (at most once a
second). The statistics -- ``complete``, ``missing`` and
``missing_by_key`` (head, gaps, tail per key), ``foreign_keys``, sequence gaps, duplicates,
``rejected`` (``rejected_by_key``, ``rejected_reasons``), ``conflicts`` -- are logged, printed
as one JSON line on stdout, written as the ``bttsim.recorder`` metadata record and sent as
the ``stats`` of the node's final status (``bttsim/<rig>/status/recorder``, state ``done``;
also to ``--status-file``). Status keys themselves are not recorded. Liveliness:
``bttsim/<rig>/alive/recorder``. ``recorder`` in these keys (and in those below) is the
node's name, ``--name``: a second recorder of one rig takes another, so that a simulator's
``--wait-for`` counts it.

Following the processor, the recorder declares ``bttsim/<rig>/awaiting/recorder`` with the run
metadata and ``bttsim/<rig>/reported/recorder`` once it has the report: the processor stays
until then. Stops when the liveliness tokens of the nodes named by ``--until`` (default: the
simulator, ``alive/sim``) have gone -- at once if the whole acquisition stream came in, else after
``--drain-timeout`` seconds of silence (they may come back: a router restart; so also once they
have declared that they sent all, ``bttsim/<rig>/sent/<node>``, while they wait for it) -- after
``--duration`` seconds, or on SIGINT / SIGTERM; the file is finalised in every case. After
SIGKILL the file reads back up to its last complete chunk. A recorder that misses numbers (a
stall, a lost link) asks the publishers' caches for them again -- the simulator's keep its
last 1024 messages a key -- and counts the rest as missing. Exit status 3 when the recording
is not complete.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from typing import TYPE_CHECKING

from bttsim_stream.bus import keys
from bttsim_stream.bus.session import StopFlag
from bttsim_stream.runtime import EXIT_INCOMPLETE, SINK_FIFO_SIZE, NodeProgram, add_drain_argument, \
    add_duration_argument, add_name_argument, add_status_argument, node_session, positive_count, run_node

if TYPE_CHECKING:
    from bttsim_stream.bus.admission import RecordGate
    from bttsim_stream.bus.recording import McapRecorder
    from bttsim_stream.bus.stream import StreamEnd

log = logging.getLogger("bttsim.recorder")
#: After a gap opened, the publishers' caches are asked again at most this often (s) ...
CATCH_UP_EVERY_S = 1.0
#: ... and their answers awaited this long (s).
CATCH_UP_TIMEOUT_S = 2.0
#: Counts of refused messages at which the recorder logs one more line.
_LOG_AT = frozenset(10 ** k for k in range(1, 13))
#: Samples the inbox holds: late-joiner history and the caches' answers to a catch-up (at most
#: their size, 1024 a key, for each key), never the live stream (its FIFO holds ``--queue``).
INBOX_SIZE = 1 << 20
#: Admitted messages handed to the MCAP writer together (:meth:`McapRecorder.write_all`: the
#: same file as one call each, at a fraction of the CPU); fewer when the bus goes quiet.
WRITE_BATCH = 256


def main(conf, args: argparse.Namespace) -> dict:
    """Record until stopped; returns (and prints as JSON) the statistics."""
    # the codec and the MCAP writer: imported when the node runs, not whenever `bttsim` builds
    # its parsers
    from bttsim_stream.bus.admission import RecordGate
    from bttsim_stream.bus.recording import McapRecorder

    rig = args.rig if args.rig == "*" else keys.validate_rig(args.rig)
    until = tuple(keys.validate_node(n) for n in args.until.split(",") if n)
    stop = StopFlag(args.duration)
    # the whole run: every rig's acquisition and, when the processor is followed, its report
    # (its last output: a link that lags may deliver it after the processor's token has gone)
    report = "processor" in until
    gate = RecordGate(None if rig == "*" else rig, report=report)
    ends: dict[str, StreamEnd] = {}  # per rig: has the whole run (acquisition, report) come in?
    with McapRecorder(args.out) as rec, \
            node_session(conf, rig if rig != "*" else "any", args.name, inbox_size=INBOX_SIZE,
                         fifo_size=args.queue,
                         status_file=args.status_file) as node:
        node.subscribe(keys.all_key(rig), history=True)
        if until:
            node.watch_nodes(until)
        node.announce()
        act = _Actions(rec, node, gate, ends)

        def whole() -> bool:
            return bool(ends) and all(e.whole for e in ends.values())

        for sample in node.samples(stop, done=whole, patience_s=args.drain_timeout):
            act.take(sample)
        if gate.missing() and not stop.signal:  # a last look in the publishers' caches
            act.catch_up(force=True)
            drained = StopFlag(install=False)
            drained.set()
            for sample in node.samples(drained):
                act.take(sample)
        for verdict in gate.finish():
            act(verdict)
        act.write_pending()
        summary = dict(gate.summary(), **gate.completeness(None if rig == "*" else rig))
        rec.write_metadata("bttsim.recorder", {k: json.dumps(v) for k, v in summary.items()})
        node.status("done", summary)
    if summary["complete"]:
        log.info("recorded %d messages on %d keys to %s; complete", summary["messages"], summary["keys"], args.out)
    else:
        log.warning("recorded %d messages on %d keys to %s; INCOMPLETE: %s", summary["messages"], summary["keys"],
                    args.out, summary["incomplete"])
    if summary["rejected"]:
        log.warning("refused %d message(s) (%s); %d kept on rejected/ channels", summary["rejected"],
                    ", ".join(f"{n} {why}" for why, n in summary["rejected_reasons"].items()), summary["rejected_kept"])
    print(json.dumps(summary), flush=True)
    return summary


class _Actions:
    """Carry out the gate's verdicts: write, keep a refused copy, note the stream's end."""

    def __init__(self, rec: McapRecorder, node, gate: RecordGate, ends: dict) -> None:
        self.rec, self.node, self.gate, self.ends = rec, node, gate, ends
        self._jumps = 0
        self._asked = 0.0
        self.recovered = 0
        self._pending: list = []  # verdicts to write, in order (see WRITE_BATCH)

    def take(self, sample) -> None:
        """Judge a received sample and act on the verdicts; after a gap opened, ask the
        publishers' caches for what was missed (at most every :data:`CATCH_UP_EVERY_S`)."""
        if sample is None:  # the bus is quiet: what waits goes to the writer
            self.write_pending()
        elif not keys.is_status_key(sample.key):  # status: not part of the run's record
            for verdict in self.gate.admit(sample.key, sample.payload, sample.att, sample.source):
                self(verdict)
        if self.gate.jumps > self._jumps:
            self.catch_up()
        if self.gate.waiting_rigs:  # data before its metadata: joined late, ask the queryable
            self.node.ask_metadata(self.gate.waiting_rigs)

    def catch_up(self, force: bool = False) -> None:
        now = time.monotonic()
        if not force and now - self._asked < CATCH_UP_EVERY_S:
            return
        self._jumps, self._asked = self.gate.jumps, now
        n = self.node.catch_up(CATCH_UP_TIMEOUT_S)
        log.info("a gap opened: asked the publishers' caches, %d message(s) came back", n)

    def write_pending(self) -> None:
        """Write the admitted messages not written yet (a verdict has a message's key,
        payload, log time and sequence number)."""
        if self._pending:
            batch, self._pending = self._pending, []
            self.rec.write_all(batch)

    def __call__(self, v) -> None:
        if v.action == "write":
            if v.meta is not None:
                from bttsim_stream.bus.stream import StreamEnd  # loaded with the gate by main

                info = v.meta
                self.write_pending()  # the file keeps the order of the verdicts
                self.rec.write_run_metadata(info.run_id, info.rig, info.scenario_toml, info.software_version)
                self.ends[info.rig] = StreamEnd(info, report=self.gate.report)
                self.node.ready()
                if self.gate.report:  # the processor stays until we have its report
                    self.node.confirm(keys.awaiting_key, info.rig)
            self._pending.append(v)
            if len(self._pending) >= WRITE_BATCH:
                self.write_pending()
            key_rig = v.key.split("/", 2)[1]
            end = self.ends.get(key_rig)
            if end is not None and not end.whole:
                done, reported = end.done, end.reported
                end.note(v.key, v.seq)
                if end.done and not done:
                    # the last numbers are in, not all before: ask before saying so (the report
                    # comes after the acquisition: not yet in is not missed)
                    if self.gate.missing(report=False):
                        self.catch_up(force=True)
                    self.node.done(key_rig)
                if end.reported and not reported:  # the processor may leave now
                    self.node.confirm(keys.reported_key, key_rig)
        elif v.action == "reject":
            n = self.gate.rejected
            if n <= 3 or n in _LOG_AT:  # a flood is logged a few times, counted whole
                log.warning("refused %d message(s); latest on %s (sequence %d): %s", n, v.key[:200], v.seq, v.reason)
            if v.keep:
                self.write_pending()
                self.rec.write_rejected(v.key, v.payload, v.log_time_ns, seq=v.seq)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", required=True, metavar="FILE.mcap", help="output MCAP file")
    p.add_argument("--rig", default="*", help="rig to record (default: every rig)")
    add_duration_argument(p)
    p.add_argument("--until", default="sim", metavar="NODES",
                   help="comma-separated nodes whose end ends the recording ('sim'; '' = only a signal "
                        "or --duration)")
    add_drain_argument(p)
    p.add_argument("--queue", type=positive_count, default=SINK_FIFO_SIZE, metavar="N",
                   help=f"live samples buffered before the network is slowed down ({SINK_FIFO_SIZE})")
    add_name_argument(p, "recorder")
    add_status_argument(p)


def _main(conf, args: argparse.Namespace) -> int:
    """:func:`main` as a program: exit status 3 when the recording is not complete."""
    return 0 if main(conf, args)["complete"] else EXIT_INCOMPLETE


PROGRAM = NodeProgram("recorder", __doc__, add_arguments, _main)


def run(argv=None) -> int:
    return run_node(PROGRAM, argv)


if __name__ == "__main__":
    sys.exit(run())

"""Replay node: republishes an MCAP recording on Zenoh, indistinguishable from the live run.

Every recorded message goes back on its key with the same payload bytes and the same
attachment (sequence number, log time); the recorded run metadata answers the
``bttsim/<rig>/meta`` queryable and an ``alive/sim`` liveliness token is held while
replaying, as the simulator node does. Pacing: the original (``--rate realtime``), a
speed-up factor, or as fast as possible (``--rate max``, the default). The file is read as a
stream, twice (what it holds, then each message as it goes out): memory does not grow with
the recording.

Before publishing it waits for its consumers. With ``--wait-for N`` it does as the simulator
node, on each rig of the recording in turn: it waits for N other nodes' liveliness tokens
(``bttsim/<rig>/alive/*``; nodes are counted by name) and for a subscriber on every OPR and
TOA key (an error after ``--wait-timeout`` seconds), publishes the rig's metadata, and waits
for N ``bttsim/<rig>/ready/*`` tokens before the first revolution: every consumer gets the
whole run. Without it, it waits (``--wait``, default 5 s) for a subscriber on its keys, then
up to 0.5 s for one on every key: a consumer that comes later gets only what the publishers' caches still
hold (the last messages of each key). Give the consumers a listen endpoint (``-l``) and the
replay a connect endpoint (``-e``), or the other way round.
"""

from __future__ import annotations

import argparse
import itertools
import logging
import sys
import time

from bttsim_stream.bus import keys
from bttsim_stream.bus.session import StopFlag, pack_attachment, wait_for_consumers, wait_for_done, \
    wait_for_subscribers
from bttsim_stream.errors import BttsimError
from bttsim_stream.runtime import RATE_HELP, NodeProgram, add_duration_argument, add_status_argument, \
    add_wait_arguments, node_session, parse_rate, run_node, seconds

log = logging.getLogger("bttsim.replay")


def main(conf, args: argparse.Namespace) -> dict:
    """Replay the recording; returns ``{"messages": sent, "of": total, "stopped_by_signal": signal or None}``
    (also the ``done`` status)."""
    # the codec and the MCAP reader: imported when the node runs, not whenever `bttsim` builds
    # its parsers
    from bttsim_stream.bus import codec
    from bttsim_stream.bus.recording import RecordingScan
    from bttsim_stream.bus.stream import StreamEnd

    rate = parse_rate(args.rate)
    head = _Survey(args.mcap)  # the first pass: what the file holds, no message kept but the metadata
    if head.truncated and not args.allow_truncated:
        raise BttsimError(f"{args.mcap}: truncated MCAP (no footer; {head.count} messages readable); "
                          "use --allow-truncated to replay what is there")
    if not head.data:
        raise BttsimError(f"{args.mcap}: no messages to replay")
    metas, rigs = head.metas, head.rigs
    stop = StopFlag(args.duration)
    sent = 0
    # a consumer confirms (done token) only a whole stream: wait for that only if it is whole
    ends = [StreamEnd(codec.decode_run_metadata(meta.payload, meta.key).body) for meta in metas]
    bare = sorted(set(rigs) - {keys.parse_key(m.key).rig for m in metas})
    if args.wait_for and bare:
        raise BttsimError(f"{args.mcap}: no run metadata for {', '.join(bare)}: its consumers would refuse its data "
                          "and never confirm it (--wait-for); replay it without --wait-for")
    with node_session(conf, rigs[0], "sim", status_file=args.status_file) as node:
        node.status("starting")
        for r in rigs:
            node.declare(node.session.liveliness().declare_token(keys.alive_key(r, "sim")))
        for m in metas:
            node.declare(node.session.declare_queryable(
                m.key, lambda q, p=m.payload, s=m.seq: q.reply(q.key_expr, p, attachment=pack_attachment(s, 0),
                                                               timestamp=node.session.new_timestamp())))
        for k in head.keys:  # metadata first, then data, as live
            node.publisher(k)
        data_keys = head.keys

        def put(*messages) -> None:
            nonlocal sent
            for m in messages:
                node.publisher(m.key).put(m.payload, attachment=pack_attachment(m.seq, m.log_time_ns))
                sent += 1

        if args.wait_for:
            parsed = [(k, keys.parse_key(k)) for k in data_keys]
            for r in rigs:  # the rig's consumers, then its metadata, then their confirmation
                own = [m for m in metas if keys.parse_key(m.key).rig == r]
                acquisition = [k for k, pk in parsed if pk.rig == r and pk.kind in ("opr", "toa")]
                wait_for_consumers(node.session, r, args.wait_for, args.wait_timeout, stop, data_keys=acquisition,
                                   publish_metadata=lambda own=own: put(*own))
        elif args.wait > 0:
            # a first subscriber, then a moment for the others of the same node to match too
            if not wait_for_subscribers(node.session, data_keys, args.wait, stop, every=False):
                log.warning("no subscriber after %.1f s; replaying anyway", args.wait)
            wait_for_subscribers(node.session, data_keys, 0.5, stop)
        t0_log = head.t0_log_ns
        t0_wall = time.monotonic()
        known, read = set(head.keys), 0
        for m in itertools.islice(RecordingScan(args.mcap), head.count):  # the second pass, as a stream
            if stop:
                break
            read += 1
            if keys.is_status_key(m.key):
                continue
            if m.key not in known:
                raise BttsimError(f"{args.mcap}: the file changed while it was replayed (a message of {m.key} "
                                  "the first reading did not hold)")
            for end in ends:
                end.note(m.key, m.seq)
            if args.wait_for and m.key.endswith("/meta"):  # already out, ahead of the rest
                continue
            if rate and stop.wait(max(0.0, t0_wall + (m.log_time_ns - t0_log) * 1e-9 / rate - time.monotonic())):
                break
            put(m)
        if not stop and read < head.count:
            raise BttsimError(f"{args.mcap}: the file changed while it was replayed: {read} of its "
                              f"{head.count} messages read the second time")
        whole = bool(ends) and all(end.done for end in ends)
        if not stop and whole:  # what went out may still be on its way: stay until it is in
            for r in rigs:
                node.sent(r)
            for r in rigs:
                waiting = wait_for_done(node.session, r, args.drain_timeout, stop)
                if waiting:
                    log.warning("leaving before %s confirmed the whole stream of %s (%g s)",
                                ", ".join(sorted(waiting)), r, args.drain_timeout)
        result = {"messages": sent, "of": head.count, "stopped_by_signal": stop.signal}
        node.status("done", result)
    print(f"replayed {sent} of {head.count} messages from {args.mcap}"
          + (f" ({head.status} status message(s) of the recorded run's nodes not replayed)" if head.status else ""),
          flush=True)
    return result


class _Survey:
    """A first pass over the recording (:class:`~bttsim_stream.bus.recording.RecordingScan`):
    its run metadata messages (kept), its keys in the order of their first message, its rigs,
    how many messages (and whether any is not metadata), the earliest log time and whether the
    file was cut. Memory does not grow with the file: the replay reads it a second time to
    publish it."""

    def __init__(self, path) -> None:
        from bttsim_stream.bus.recording import RecordingScan  # loaded by main

        scan = RecordingScan(path)
        first: dict[str, None] = {}
        self.metas: list = []
        self.count, self.data, self.t0_log_ns = 0, False, None
        self.status = 0  # messages of status keys: a node's state then, not data (never replayed)
        for m in scan:
            self.count += 1
            if keys.is_status_key(m.key):
                self.status += 1
                continue
            first.setdefault(m.key)
            if m.key.endswith("/meta"):
                self.metas.append(m)
            else:
                self.data = True
            if self.t0_log_ns is None or m.log_time_ns < self.t0_log_ns:
                self.t0_log_ns = m.log_time_ns
        self.keys = list(first)
        self.rigs = sorted({keys.parse_key(k).rig for k in self.keys})
        self.truncated = scan.truncated


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("mcap", help="recording to replay (MCAP)")
    p.add_argument("--rate", default="max", help=RATE_HELP)
    p.add_argument("--wait", type=seconds, default=5.0, metavar="S",
                   help="without --wait-for: seconds to wait for a subscriber before replaying (5)")
    add_wait_arguments(p)
    p.add_argument("--drain-timeout", type=seconds, default=120.0, metavar="S",
                   help="after a whole run, wait up to S seconds for the nodes that took it to confirm it (120)")
    p.add_argument("--allow-truncated", action="store_true", help="replay a file without its footer")
    add_duration_argument(p)
    add_status_argument(p)


PROGRAM = NodeProgram("replay", __doc__, add_arguments, main)


def run(argv=None) -> int:
    return run_node(PROGRAM, argv)


if __name__ == "__main__":
    sys.exit(run())

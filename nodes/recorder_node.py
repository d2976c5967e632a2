"""Recorder node: writes every ``bttsim/<rig>/**`` sample to an MCAP file, as received.

Inputs: every key of the rig (run metadata, OPR, TOA batches, truth, fits, travelling waves,
resonance reports); the run metadata sample is also written as the ``bttsim.run`` metadata
record. Output: ``OUT.mcap`` with
zstd chunks, one channel per key, the protobuf schemas embedded, log time = simulated time
(from the sample attachment; payloads are not decoded). Sequence gaps are counted per key
and reported (log line, JSON on stdout, and a ``bttsim.recorder`` metadata record).

Stops when the liveliness tokens of the nodes named by ``--until`` (default: the simulator,
``alive/sim``) have gone, after ``--duration`` seconds, or on SIGINT / SIGTERM; the file is finalised in every
case. After SIGKILL the file reads back up to its last complete chunk.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time

import zenoh
import zenoh.ext as zx

from bttsim_stream.io import codec, keys
from bttsim_stream.io.mcap_io import McapRecorder
from bttsim_stream.transport import (NodeWatch, StopFlag, run_program, add_session_args, config_from_args,
                                     open_session, unpack_attachment)

log = logging.getLogger("bttsim.recorder")


class _SeqStats:
    """Per-key counts, first sequence number and gaps (missing sequence numbers)."""

    def __init__(self) -> None:
        self.count: dict[str, int] = {}
        self.first: dict[str, int] = {}
        self.next: dict[str, int] = {}
        self.gaps: dict[str, int] = {}
        self.duplicates = 0

    def accept(self, key: str, seq: int | None) -> bool:
        self.count[key] = self.count.get(key, 0) + 1
        if seq is None:
            return True
        if key not in self.next:
            self.first[key] = seq
        elif seq < self.next[key]:
            self.duplicates += 1  # history replayed after a live sample: already written
            self.count[key] -= 1
            return False
        elif seq > self.next[key]:
            self.gaps[key] = self.gaps.get(key, 0) + seq - self.next[key]
        self.next[key] = seq + 1
        return True

    def summary(self) -> dict:
        return {"messages": sum(self.count.values()), "keys": len(self.count),
                "gaps": sum(self.gaps.values()), "gaps_by_key": dict(self.gaps),
                "duplicates_skipped": self.duplicates,
                "late_start_keys": {k: v for k, v in self.first.items() if v > 0}}


def main(conf: "zenoh.Config", out: str, rig: str = "*", *, duration_s: float | None = None,
         until: tuple[str, ...] | None = ("sim",), queue: int = 1 << 20) -> dict:
    """Record until stopped; returns the gap statistics.

    ``until``: node names (liveliness tokens) whose end ends the recording (None: only a
    signal or ``duration_s`` stops it).
    """
    if rig != "*":
        keys.validate_rig(rig)
    stop = StopFlag(duration_s)
    stats = _SeqStats()
    meta_done: set[str] = set()
    with open_session(conf) as session, McapRecorder(out) as rec:
        # subscriber first: a simulator that waits for our token then finds our subscription
        sub = zx.declare_advanced_subscriber(
            session, keys.all_key(rig), handler=zenoh.handlers.FifoChannel(queue),
            history=zx.HistoryConfig(detect_late_publishers=True, max_samples=None, max_age=None),
            recovery=None, subscriber_detection=False, allowed_origin=None)
        watch = NodeWatch(session, rig, until) if until else None
        token = session.liveliness().declare_token(keys.alive_key(rig if rig != "*" else "any", "recorder"))
        idle_since = None
        while True:
            sample = sub.try_recv()
            now = time.monotonic()
            if sample is None:
                if stop:
                    break
                if watch is not None and watch.ended():
                    idle_since = idle_since or now
                    if now - idle_since > 0.5:  # drained
                        break
                time.sleep(0.001)
                continue
            idle_since = None
            key = str(sample.key_expr)
            att = unpack_attachment(sample.attachment)
            seq, t_ns = (att if att is not None else (None, time.time_ns()))
            if not stats.accept(key, seq):
                continue
            payload = sample.payload.to_bytes()
            if key.endswith("/meta") and key not in meta_done:
                m = codec.decode_run_metadata(payload, key)
                rec.write_run_metadata(m.run_id, m.rig, m.scenario_toml, m.software_version)
                meta_done.add(key)
            rec.write(key, payload, t_ns, sequence=seq or 0)
        summary = stats.summary()
        rec.write_metadata("bttsim.recorder", {k: json.dumps(v) for k, v in summary.items()})
        sub.undeclare()
        if watch is not None:
            watch.undeclare()
        token.undeclare()
    level = logging.WARNING if summary["gaps"] else logging.INFO
    log.log(level, "recorded %d messages on %d keys to %s; %d sequence gaps", summary["messages"],
            summary["keys"], out, summary["gaps"])
    return summary


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="bttsim-recorder", description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True, help="output MCAP file")
    p.add_argument("--rig", default="*", help="rig to record (default: every rig)")
    p.add_argument("--duration", type=float, help="stop after this many seconds")
    p.add_argument("--until", default="sim", help="comma-separated nodes whose end ends the recording "
                   "('sim'; '' = only a signal or --duration)")
    add_session_args(p)
    return p


def run(argv=None) -> int:
    def body(args):
        summary = main(config_from_args(args), args.out, args.rig, duration_s=args.duration,
                       until=tuple(n for n in args.until.split(",") if n) or None)
        print(json.dumps(summary), flush=True)

    return run_program(_parser(), body, argv)


if __name__ == "__main__":
    sys.exit(run())

"""Replay node: republishes an MCAP recording on Zenoh, indistinguishable from the live run.

Every recorded message goes back on its key with the same payload bytes and the same
attachment (sequence number, log time); the recorded run metadata answers the
``bttsim/<rig>/meta`` queryable and an ``alive/sim`` liveliness token is held while
replaying, as the simulator node does. Pacing: the original (``--rate realtime``), a
speed-up factor, or as fast as possible (``--rate max``, the default). Before publishing it
waits (``--wait``, default 5 s) for subscribers on the data keys.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time

import zenoh
import zenoh.ext as zx

from bttsim_stream.errors import BttsimError
from bttsim_stream.io import keys
from bttsim_stream.io.mcap_io import read_recording
from bttsim_stream.transport import (StopFlag, run_program, add_session_args, config_from_args, open_session,
                                     pack_attachment, wait_for_subscribers)

log = logging.getLogger("bttsim.replay")


def main(conf: "zenoh.Config", path: str, *, rate: float | None = None, wait_s: float = 5.0,
         allow_truncated: bool = False, duration_s: float | None = None) -> dict:
    rec = read_recording(path)
    if rec.truncated and not allow_truncated:
        raise BttsimError(f"{path}: truncated MCAP (no footer; {len(rec.messages)} messages readable); "
                          "use --allow-truncated to replay what is there")
    metas = [m for m in rec.messages if m.key.endswith("/meta")]
    data = rec.messages
    if not any(not m.key.endswith("/meta") for m in data):
        raise BttsimError(f"{path}: no messages to replay")
    stop = StopFlag(duration_s)
    sent = 0
    with open_session(conf) as session:
        rigs = sorted({keys.parse_key(m.key).rig for m in data})
        tokens = [session.liveliness().declare_token(keys.alive_key(r, "sim")) for r in rigs]
        queryables = [session.declare_queryable(
            m.key, lambda q, p=m.payload: q.reply(q.key_expr, p, attachment=pack_attachment(0, 0)))
            for m in metas]
        pubs = {}
        for k in dict.fromkeys(m.key for m in data):  # metadata first, then data, as live
            pubs[k] = zx.declare_advanced_publisher(
                session, k, cache=zx.CacheConfig(max_samples=64, replies_config=None),
                publisher_detection=True, sample_miss_detection=None,
                congestion_control=zenoh.CongestionControl.BLOCK, reliability=zenoh.Reliability.RELIABLE,
                encoding=None, priority=None, express=None, allowed_destination=None)
        if wait_s > 0 and not wait_for_subscribers(session, list(pubs), wait_s, stop):
            log.warning("not every key has a subscriber after %.1f s; replaying anyway", wait_s)
        t0_log = min(m.log_time_ns for m in data)
        t0_wall = time.monotonic()
        for m in data:
            if stop:
                break
            if rate:
                due = t0_wall + (m.log_time_ns - t0_log) * 1e-9 / rate
                if stop.wait(max(0.0, due - time.monotonic())):
                    break
            pubs[m.key].put(m.payload, attachment=pack_attachment(m.sequence, m.log_time_ns))
            sent += 1
        time.sleep(0.2)  # let the last samples leave before the token goes
        for p in pubs.values():
            p.undeclare()
        for q in queryables:
            q.undeclare()
        for t in tokens:
            t.undeclare()
    log.info("replayed %d of %d messages from %s", sent, len(data), path)
    return {"messages": sent, "of": len(data)}


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="bttsim-replay", description=__doc__.splitlines()[0])
    p.add_argument("mcap", help="recording to replay")
    p.add_argument("--rate", default="max", help="'max' (default), 'realtime', or a speed-up factor")
    p.add_argument("--wait", type=float, default=5.0, help="seconds to wait for subscribers (5)")
    p.add_argument("--allow-truncated", action="store_true", help="replay a file without its footer")
    p.add_argument("--duration", type=float, help="stop after this many seconds")
    add_session_args(p)
    return p


def run(argv=None) -> int:
    from .sim_node import parse_rate

    return run_program(_parser(), lambda args: main(
        config_from_args(args), args.mcap, rate=parse_rate(args.rate), wait_s=args.wait,
        allow_truncated=args.allow_truncated, duration_s=args.duration), argv)


if __name__ == "__main__":
    sys.exit(run())

"""Simulator node: a virtual BTT acquisition system publishing a scenario's run-up on Zenoh.

Keys (``schemas/bus.md``):

* ``bttsim/<rig>/opr`` -- ``bttsim.v1.Opr``, one per revolution
* ``bttsim/<rig>/toa/<probe>`` -- ``bttsim.v1.ToaBatch``, one per probe per revolution
* ``bttsim/<rig>/truth`` -- ``bttsim.v1.TruthBatch``, one per revolution (``--no-truth`` drops it)
* ``bttsim/<rig>/meta`` -- ``bttsim.v1.RunMetadata``: published once first, and a queryable
* ``bttsim/<rig>/alive/sim`` -- liveliness token while the node runs

Publishers keep a cache for late joiners (zenoh-ext advanced publishers) and block rather
than drop under congestion (``--lossy`` drops instead). Stops at the end of the run, after
``--duration`` seconds, on SIGINT or SIGTERM.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time

import zenoh
import zenoh.ext as zx

from bttsim_stream.acquisition import AcquisitionStream
from bttsim_stream.errors import BttsimError
from bttsim_stream.io import keys
from bttsim_stream.transport import (StopFlag, run_program, add_session_args, config_from_args, open_session,
                                     pack_attachment, wait_for_liveliness)

log = logging.getLogger("bttsim.sim_node")
CACHE_SAMPLES = 64


def main(conf: "zenoh.Config", scenario, *, rate: float | None = None, lossy: bool = False,
         truth: bool = True, wait_for: int = 0, wait_timeout_s: float = 30.0,
         duration_s: float | None = None, revolutions: int | None = None, linger_s: float = 0.0,
         progress: bool = False) -> dict:
    """Publish the scenario's acquisition stream.

    Parameters
    ----------
    rate : float or None
        None: as fast as possible; 1.0: real time; otherwise a speed-up factor.
    wait_for : int
        Wait (up to ``wait_timeout_s``) for this many ``alive/*`` tokens of other nodes on the
        rig (e.g. recorder, processor) before publishing, so nothing is published unheard.
    linger_s : float
        Keep serving the metadata and cache this long after the last revolution.
    """
    stop = StopFlag(duration_s)
    stream = AcquisitionStream(scenario, include_truth=truth, n_revolutions=revolutions,
                               chunk_revolutions=1 if rate else 16)
    rig = stream.rig
    cc = zenoh.CongestionControl.DROP if lossy else zenoh.CongestionControl.BLOCK
    sent = 0
    with open_session(conf) as session:
        token = session.liveliness().declare_token(keys.alive_key(rig, "sim"))
        meta = session.declare_queryable(
            stream.meta_key, lambda q: q.reply(q.key_expr, stream.meta_payload,
                                               attachment=pack_attachment(0, 0)))
        pubs: dict[str, object] = {}

        def publisher(key: str):
            if key not in pubs:
                pubs[key] = zx.declare_advanced_publisher(
                    session, key, cache=zx.CacheConfig(max_samples=CACHE_SAMPLES, replies_config=None),
                    publisher_detection=True, sample_miss_detection=None, congestion_control=cc,
                    reliability=zenoh.Reliability.RELIABLE, encoding=None, priority=None,
                    express=None, allowed_destination=None)
            return pubs[key]

        if wait_for:
            seen = wait_for_liveliness(session, keys.alive_all_key(rig), wait_for + 1, wait_timeout_s, stop)
            log.info("%d other node(s) alive on %s", seen - 1, rig)
        # the metadata also goes out once as a sample (cached for late joiners), so that a
        # recorder stores it in stream order; the queryable answers on demand
        publisher(stream.meta_key).put(stream.meta_payload, attachment=pack_attachment(0, 0))
        sent += 1
        t_wall0 = time.monotonic()
        for batch, msgs in stream.batches():
            if stop:
                break
            if rate:
                due = t_wall0 + float(batch.opr_s[-1]) / rate
                if stop.wait(max(0.0, due - time.monotonic())):
                    break
            for m in msgs:
                publisher(m.key).put(m.payload, attachment=pack_attachment(m.seq, m.log_time_ns))
            sent += len(msgs)
            if progress:
                n = int(batch.revolution[-1]) + 1
                print(f"\rrevolution {n}/{stream.info.n_revolutions}", end="", file=sys.stderr, flush=True)
        if progress:
            print(file=sys.stderr)
        if linger_s and not stop:
            stop.wait(linger_s)
        for p in pubs.values():
            p.undeclare()
        meta.undeclare()
        token.undeclare()
    log.info("published %d messages (run %s)", sent, stream.run_id)
    return {"run_id": stream.run_id, "messages": sent, "stopped_by_signal": stop.signal}


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="bttsim-sim-node", description=__doc__.splitlines()[0])
    p.add_argument("scenario", nargs="?", help="scenario TOML (default: the paper's Table 1)")
    p.add_argument("--rate", default="max", help="'max' (default), 'realtime', or a speed-up factor")
    p.add_argument("--lossy", action="store_true", help="drop samples under congestion instead of blocking")
    p.add_argument("--no-truth", action="store_true", help="do not publish truth")
    p.add_argument("--wait-for", type=int, default=0, metavar="N", help="wait for N other nodes' liveliness")
    p.add_argument("--duration", type=float, help="stop after this many seconds")
    p.add_argument("--revolutions", type=int, help="stop after this many revolutions")
    p.add_argument("--linger", type=float, default=0.0, help="seconds to stay up after the run")
    p.add_argument("--progress", action="store_true")
    add_session_args(p)
    return p


def parse_rate(text: str) -> float | None:
    if text == "max":
        return None
    if text == "realtime":
        return 1.0
    try:
        value = float(text)
    except ValueError:
        raise BttsimError(f"--rate must be 'max', 'realtime' or a positive factor, got {text!r}") from None
    if not value > 0:
        raise BttsimError(f"--rate must be positive, got {text!r}")
    return value


def run(argv=None) -> int:
    from bttsim_stream.scenario import Scenario, load_scenario

    return run_program(_parser(), lambda args: main(
        config_from_args(args), load_scenario(args.scenario) if args.scenario else Scenario(),
        rate=parse_rate(args.rate), lossy=args.lossy, truth=not args.no_truth, wait_for=args.wait_for,
        duration_s=args.duration, revolutions=args.revolutions, linger_s=args.linger,
        progress=args.progress), argv)


if __name__ == "__main__":
    sys.exit(run())

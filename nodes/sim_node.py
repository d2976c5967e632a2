"""Simulator node: a virtual BTT acquisition system publishing a scenario's run-up on Zenoh.

Keys (``schemas/bus.md``):

* ``bttsim/<rig>/opr`` -- ``bttsim.v1.Opr``, one per revolution
* ``bttsim/<rig>/toa/<probe>`` -- ``bttsim.v1.ToaBatch``, one per probe per revolution
* ``bttsim/<rig>/truth`` -- ``bttsim.v1.TruthBatch``, one per revolution (``--no-truth`` drops it)
* ``bttsim/<rig>/signal/<probe>`` -- ``bttsim.v1.SignalBatch``, one per probe per revolution, only
  with ``[acquisition.signal] publish = true``
* ``bttsim/<rig>/meta`` -- ``bttsim.v1.RunMetadata``: published once first, and a queryable
* ``bttsim/<rig>/alive/sim`` -- liveliness token while the node runs
* ``bttsim/<rig>/status/sim`` -- its status (JSON, ``schemas/bus.md``): ``starting``, ``done``

Publishers keep a cache for late joiners and block rather than drop under congestion
(``--lossy`` drops instead). Stops at the end of the run, after ``--duration`` seconds, on
SIGINT or SIGTERM.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time

from bttsim_stream.bus import keys
from bttsim_stream.bus.session import StopFlag, pack_attachment, wait_for_consumers, wait_for_done
from bttsim_stream.runtime import RATE_HELP, NodeProgram, Progress, add_duration_argument, add_status_argument, \
    add_wait_arguments, node_session, parse_rate, positive_count, run_node, seconds

log = logging.getLogger("bttsim.sim")
#: Messages each acquisition key keeps for late joiners and for consumers catching up after a
#: stall or a lost link (a recorder asks for them again): about 40 s of a 1500 rpm run.
CACHE_SAMPLES = 1024
#: With ``--lossy``, the longest wait for the consumers' ``done`` tokens after the run (s).
LOSSY_DRAIN_S = 5.0


def main(conf, args: argparse.Namespace) -> dict:
    """Publish the scenario's acquisition stream (options: see :func:`add_arguments`)."""
    # the simulator: imported when the node runs, not whenever `bttsim` builds its parsers
    from bttsim_stream.acquisition import AcquisitionStream
    from bttsim_stream.scenario import Scenario, load_scenario

    scenario = load_scenario(args.scenario) if args.scenario else Scenario()
    rate = parse_rate(args.rate)
    stop = StopFlag(args.duration)
    stream = AcquisitionStream(scenario, include_truth=not args.no_truth, n_revolutions=args.revolutions,
                               chunk_revolutions=1 if rate else 16)
    meta = stream.meta
    sent = 0
    progress = Progress(args.progress)
    with node_session(conf, stream.rig, "sim", linger_s=0.0, status_file=args.status_file) as node:
        node.announce()
        node.declare(node.session.declare_queryable(
            meta.key, lambda q: q.reply(q.key_expr, meta.payload, attachment=pack_attachment(meta.seq, 0),
                                        timestamp=node.session.new_timestamp())))  # stamped: it names this session
        data_keys = [keys.opr_key(stream.rig)] + [keys.toa_key(stream.rig, j) for j in range(stream.info.n_probes)]

        def publish_metadata() -> None:
            # also once as a sample (cached for late joiners), so that a recorder stores it in
            # stream order; the queryable answers on demand
            nonlocal sent
            node.publisher(meta.key, lossy=args.lossy).put(meta.payload, attachment=pack_attachment(meta.seq, 0))
            sent += 1

        wait_for_consumers(node.session, stream.rig, args.wait_for, args.wait_timeout, stop, data_keys=data_keys,
                           publish_metadata=publish_metadata)
        t_wall0 = time.monotonic()
        for batch, msgs in stream.batches():
            if stop:
                break
            if rate and stop.wait(max(0.0, t_wall0 + float(batch.opr_s[-1]) / rate - time.monotonic())):
                break
            for m in msgs:
                node.publisher(m.key, cache_samples=CACHE_SAMPLES, lossy=args.lossy).put(
                    m.payload, attachment=pack_attachment(m.seq, m.log_time_ns))
            sent += len(msgs)
            progress.update(f"revolution {int(batch.revolution[-1]) + 1}/{stream.info.n_revolutions}")
        progress.close()
        log.info("published %d messages (run %s)", sent, stream.run_id)
        if args.wait_for and not stop:  # what went out may still be on its way: stay until it is in
            node.sent()  # ... and say so: a consumer that lost the tail need not wait for us to leave
            # --lossy may have dropped a key's last message, and then no "done" ever comes
            drain_s = min(args.drain_timeout, LOSSY_DRAIN_S) if args.lossy else args.drain_timeout
            waiting = wait_for_done(node.session, stream.rig, drain_s, stop)
            if waiting:
                log.warning("leaving before %s confirmed the whole stream (%g s)", ", ".join(sorted(waiting)),
                            drain_s)
        if args.linger and not stop:
            stop.wait(args.linger)
        result = {"run_id": stream.run_id, "messages": sent, "stopped_by_signal": stop.signal}
        node.status("done", result)
    return result


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scenario", nargs="?", help="scenario TOML (default: the paper's Table 1)")
    p.add_argument("--rate", default="max", help=RATE_HELP)
    p.add_argument("--lossy", action="store_true", help="drop samples under congestion instead of blocking")
    p.add_argument("--no-truth", action="store_true", help="do not publish truth (a blind acquisition)")
    add_wait_arguments(p)
    add_duration_argument(p)
    p.add_argument("--revolutions", type=positive_count, metavar="N", help="stop after N revolutions")
    p.add_argument("--drain-timeout", type=seconds, default=120.0, metavar="S",
                   help="after the run, wait up to S seconds for the --wait-for nodes to confirm the whole stream "
                        "(120; with --lossy at most 5)")
    p.add_argument("--linger", type=seconds, default=0.0, metavar="S",
                   help="keep serving the metadata and the late-joiner cache S seconds after the run")
    p.add_argument("--progress", action="store_true", help="show a progress line on stderr")
    add_status_argument(p)


PROGRAM = NodeProgram("sim", __doc__, add_arguments, main)


def run(argv=None) -> int:
    return run_node(PROGRAM, argv)


if __name__ == "__main__":
    sys.exit(run())

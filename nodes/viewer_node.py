"""Viewer node: streams a rig's bus to Rerun views (an .rrd file, a native viewer, the web viewer).

Inputs: every key of the rig, ``bttsim/<rig>/**`` (run metadata, OPR, TOA batches, truth,
blade fits, travelling waves, resonance reports, raw probe signals when published), fed to
:class:`bttsim_stream.views.LiveViews` (batched, flushed every 0.2 s). Outputs: Rerun only
(``--rrd OUT.rrd``, ``--rerun-url URL``, ``--web``); its liveliness token
``bttsim/<rig>/alive/viewer`` (a simulator started with ``--wait-for`` counts it); its status
``bttsim/<rig>/status/viewer`` (the web viewer's URL from ``starting`` on; ``done`` with its
counts of what it showed and lost; ``serving``), also to ``--status-file``.

Stops when the nodes named by ``--until`` (default: the simulator) have gone and the bus is
drained (with ``--web`` it then finalises the .rrd, says so in its status, ``serving``, and
keeps serving), after ``--duration`` seconds, or on SIGINT / SIGTERM / SIGHUP;
the .rrd is finalised in every case. The web viewer (page and data server) listens on
``--bind`` (127.0.0.1) only.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys

from bttsim_stream.bus import keys
from bttsim_stream.defaults import DEFAULT_RIG
from bttsim_stream.bus.session import StopFlag
from bttsim_stream.bus.stream import SequenceTracker, StreamEnd
from bttsim_stream.runtime import NodeProgram, add_status_argument, add_web_arguments, node_session, run_node

log = logging.getLogger("bttsim.viewer")


def main(conf, args: argparse.Namespace) -> None:
    """Show the rig's bus until stopped (options: see :func:`add_arguments`)."""
    from bttsim_stream import views  # rerun takes 0.5 s to import: not for every ``bttsim --help``

    rig = keys.validate_rig(args.rig)
    stop = StopFlag(args.duration)
    rec, sinks = views.open_recording(rrd_path=args.rrd, grpc_url=args.rerun_url, serve_web=args.web,
                                      web_port=args.web_port, grpc_port=args.grpc_port, bind=args.bind)
    if sinks.web_url:
        print(f"web viewer: {sinks.web_url}", flush=True)
    live = views.LiveViews(rec, live=True)
    seqs = SequenceTracker()  # what was lost on the way, per key (duplicates are not shown twice)
    try:
        with node_session(conf, rig, "viewer", status_file=args.status_file) as node:
            node.url = sinks.web_url or ""
            # subscriber before the token: a simulator waiting for our token finds our subscription
            node.subscribe(keys.all_key(rig), history=True)
            node.watch_nodes(tuple(n for n in args.until.split(",") if n) or ("sim",))
            node.announce()
            _show(node, live, seqs, stop)
            live.close()
            counts = _report(live.stats, seqs)
            node.status("done", counts)
            if args.web and not stop:
                views.finish_files(rec)  # the .rrd is complete while we serve
                log.info("run ended; serving the web viewer until stopped (Ctrl-C)")
                node.status("serving", counts)
                while not stop.wait(0.2):
                    pass
    finally:
        rec.flush()
        rec.disconnect()
        sinks.close()


def _show(node, live, seqs: SequenceTracker, stop: StopFlag) -> None:
    """Feed the rig's samples (status keys aside) to the views until the watched nodes end."""
    end = None  # has the whole acquisition stream come in?
    for sample in node.samples(stop, poll_s=0.02):
        if sample is None:
            live.poll()
        elif not keys.is_status_key(sample.key) and seqs.accept(sample.key, sample.att[0] if sample.att else None):
            live.feed(sample.key, sample.payload)
            if live.meta is not None:
                node.ready()
                end = end or StreamEnd(live.meta)
                end.note(sample.key, sample.att[0] if sample.att else None)
                if end.done:
                    node.done()


def _report(st: dict, seqs: SequenceTracker) -> dict:
    """Log what was shown and lost; the counts (also printed as one JSON line on stdout)."""
    counts = dict(seqs.summary(), rejected=st["bad"] + st["ignored"] + seqs.implausible)
    log.log(logging.WARNING if counts["gaps"] else logging.INFO,
            "showed %d messages (%d revolutions, %d fits, %d travelling waves); %d sequence gaps, "
            "%d duplicates, %d rejected", st["messages"], st["revolutions"], st["fits"], st["tw"],
            counts["gaps"], counts["duplicates_skipped"], counts["rejected"])
    print(json.dumps(counts), flush=True)
    return counts


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--rig", default=DEFAULT_RIG, help=f"rig to show ({DEFAULT_RIG})")
    p.add_argument("--rrd", metavar="OUT.rrd", help="write an .rrd file (open it with: rerun OUT.rrd)")
    p.add_argument("--rerun-url", metavar="URL",
                   help="stream to a running viewer, e.g. rerun+http://127.0.0.1:9876/proxy")
    p.add_argument("--web", action="store_true", help="serve the web viewer (prints its URL)")
    add_web_arguments(p)
    p.add_argument("--until", default="sim", metavar="NODES",
                   help="comma-separated nodes whose end ends the views ('sim'; bttsim run: 'sim,processor')")
    p.add_argument("--duration", type=float, metavar="S", help="stop after S seconds")
    add_status_argument(p)


PROGRAM = NodeProgram("viewer", __doc__, add_arguments, main)


def run(argv=None) -> int:
    return run_node(PROGRAM, argv)


if __name__ == "__main__":
    sys.exit(run())

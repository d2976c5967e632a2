"""Viewer node: streams a rig's bus to Rerun views (an .rrd file, a native viewer, the web viewer).

Inputs: every key of the rig, ``bttsim/<rig>/**`` (run metadata, OPR, TOA batches, truth,
blade fits, travelling waves, resonance reports, raw probe signals when published), fed to
:class:`bttsim_stream.views.LiveViews` (batched, flushed every 0.2 s). Outputs: Rerun only
(``--rrd OUT.rrd``, ``--rerun-url URL``, ``--web``); its liveliness token
``bttsim/<rig>/alive/viewer`` (a simulator started with ``--wait-for`` counts it); its status
``bttsim/<rig>/status/viewer`` (the web viewer's URL from ``starting`` on; ``done`` with its
counts of what it showed and lost; ``serving``), also to ``--status-file``. ``viewer`` in
these keys (and in its ``ready``, ``done``, ``awaiting`` and ``reported`` tokens) is the
node's name, ``--name``: a second viewer of one rig takes another.

Every sample is admitted as the recorder admits what it writes
(:class:`~bttsim_stream.bus.admission.RecordGate`: decoded, checked against the run and the
session that published it, duplicates and conflicts told apart); what is refused is counted
per key and reason, never shown. Completeness is the recorder's too: per key, the numbers not
received (head, gaps, tail against the run's counts); exit status 3 when anything is missing.

Stops when the nodes named by ``--until`` (default: the simulator) have gone and the bus is
drained -- if the run is not whole (its acquisition stream and, when ``--until`` names the
processor, the processor's resonance report), after ``--drain-timeout`` seconds of
silence, also counted from when they declared that they sent all (``bttsim/<rig>/sent/<node>``;
with ``--web`` it then finalises the .rrd, says so in its status, ``serving``, and keeps
serving) -- after ``--duration`` seconds, or on SIGINT / SIGTERM / SIGHUP;
the .rrd is finalised in every case. The web viewer (page and data server) listens on
``--bind`` (127.0.0.1) only.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from typing import TYPE_CHECKING

from bttsim_stream.bus import keys
from bttsim_stream.defaults import DEFAULT_RIG
from bttsim_stream.bus.session import StopFlag
from bttsim_stream.runtime import EXIT_INCOMPLETE, SINK_FIFO_SIZE, NodeProgram, add_drain_argument, \
    add_duration_argument, add_name_argument, add_status_argument, add_web_arguments, node_session, run_node

if TYPE_CHECKING:
    from bttsim_stream.bus.admission import RecordGate

log = logging.getLogger("bttsim.viewer")



def main(conf, args: argparse.Namespace) -> dict:
    """Show the rig's bus until stopped (options: see :func:`add_arguments`); returns the
    counts of what was shown, refused and missed."""
    # imported when the node runs, not whenever `bttsim` builds its parsers (rerun takes 0.5 s)
    from bttsim_stream import views
    from bttsim_stream.bus.admission import RecordGate

    rig = keys.validate_rig(args.rig)
    until = tuple(keys.validate_node(n) for n in args.until.split(",") if n) or ("sim",)
    stop = StopFlag(args.duration)
    rec, sinks = views.open_recording(rrd_path=args.rrd, grpc_url=args.rerun_url, serve_web=args.web,
                                      web_port=args.web_port, grpc_port=args.grpc_port, bind=args.bind)
    if sinks.web_url:
        print(f"web viewer: {sinks.web_url}", flush=True)
    live = views.LiveViews(rec, live=True)
    # what is shown is admitted as the recorder admits what it writes (following the processor:
    # its report expected too)
    gate = RecordGate(rig, decode=True, report="processor" in until)
    try:
        with node_session(conf, rig, args.name, fifo_size=SINK_FIFO_SIZE, status_file=args.status_file) as node:
            node.url = sinks.web_url or ""
            # subscriber before the token: a simulator waiting for our token finds our subscription
            node.subscribe(keys.all_key(rig), history=True)
            node.watch_nodes(until)
            node.announce()
            _show(node, live, gate, stop, args.drain_timeout)
            live.close()
            counts = _report(live.stats, gate, rig)
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
    return counts


def _show(node, live, gate: RecordGate, stop: StopFlag, drain_s: float) -> None:
    """Feed the rig's admitted samples (status keys aside) to the views until the watched
    nodes end (and, if the run is not whole, ``drain_s`` of silence after). The run is whole
    once its acquisition stream came in and, when the gate expects it (the processor is
    followed), the processor's resonance report: its last output, which a link that lags may
    deliver after the processor's token has gone (the processor waits for our ``reported``
    token, up to its ``--drain-timeout``)."""
    from bttsim_stream.bus.stream import StreamEnd
    from bttsim_stream.views.live import Incoming

    ends: list = []  # has the whole run (acquisition, report) come in?

    def whole() -> bool:
        return bool(ends) and ends[0].whole

    for sample in node.samples(stop, poll_s=0.02, done=whole, patience_s=drain_s):
        if gate.waiting_rigs:  # data before its metadata: joined late, ask the queryable
            node.ask_metadata(gate.waiting_rigs)
        if sample is None:
            live.poll()
            continue
        if keys.is_status_key(sample.key):
            continue
        for v in gate.admit(sample.key, sample.payload, sample.att, sample.source):
            if v.action != "write":  # a duplicate, a refusal: counted by the gate
                continue
            parts = v.key.split("/")
            live.feed_decoded(Incoming(parts[2], parts[1], v.decoded))
            if v.meta is not None:
                node.ready()
                if gate.report:  # the processor stays until we have its report
                    node.confirm(keys.awaiting_key)
                ends.append(StreamEnd(v.meta, report=gate.report))
            elif ends and not ends[0].whole:
                end = ends[0]
                done, reported = end.done, end.reported
                end.note(v.key, v.seq)
                if end.done and not done:
                    node.done()
                if end.reported and not reported:  # the processor may leave now
                    node.confirm(keys.reported_key)


def _report(st: dict, gate: RecordGate, rig: str) -> dict:
    """Log what was shown, refused and missed; the counts (also printed as one JSON line on
    stdout): the gate's (:meth:`RecordGate.summary`, :meth:`RecordGate.completeness`)."""
    gate.finish()  # samples still waiting for a metadata that never came: refused, counted
    counts = dict(gate.summary(), **gate.completeness(rig), shown=st["messages"], ignored=st["ignored"])
    log.log(logging.INFO if counts["complete"] else logging.WARNING,
            "showed %d messages (%d revolutions, %d fits, %d travelling waves); %d duplicates, %d refused; %s",
            st["messages"], st["revolutions"], st["fits"], st["tw"], counts["duplicates_skipped"], counts["rejected"],
            "complete" if counts["complete"] else f"INCOMPLETE: {counts['incomplete']}")
    if counts["rejected"]:
        log.warning("refused %d message(s) (%s)", counts["rejected"],
                    ", ".join(f"{n} {why}" for why, n in counts["rejected_reasons"].items()))
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
    add_duration_argument(p)
    add_drain_argument(p)
    add_name_argument(p, "viewer")
    add_status_argument(p)


def _main(conf, args: argparse.Namespace) -> int:
    """:func:`main` as a program: exit status 3 when the views miss anything of the run."""
    return 0 if main(conf, args)["complete"] else EXIT_INCOMPLETE


PROGRAM = NodeProgram("viewer", __doc__, add_arguments, _main)


def run(argv=None) -> int:
    return run_node(PROGRAM, argv)


if __name__ == "__main__":
    sys.exit(run())

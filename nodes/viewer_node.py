"""Viewer node: streams a rig's bus to Rerun views (an .rrd file, a native viewer, the web viewer).

Inputs: every key of the rig, ``bttsim/<rig>/**`` (run metadata, OPR, TOA batches, truth,
blade fits, travelling waves, resonance reports), pulled from a FIFO on the main thread and
fed to :class:`bttsim_stream.views.LiveViews` (batched, flushed every 0.2 s).
Outputs: Rerun only (``--rrd OUT.rrd``, ``--rerun-url URL``, ``--web``); its liveliness token
``bttsim/<rig>/alive/viewer`` (a simulator started with ``--wait-for`` counts it).

Stops when the simulator's token (``alive/sim``) goes away after having been seen (with
``--web`` it keeps serving until stopped), after ``--duration`` seconds, or on SIGINT /
SIGTERM; the .rrd is finalised in every case.
"""

from __future__ import annotations

import argparse
import logging
import sys
import threading
import time

import zenoh
import zenoh.ext as zx

from bttsim_stream import views
from bttsim_stream.io import keys
from bttsim_stream.transport import StopFlag, add_session_args, config_from_args, open_session, run_program

log = logging.getLogger("bttsim.viewer")


def main(conf: "zenoh.Config", options) -> None:
    """Show the rig's bus until stopped.

    ``options`` has ``rig``, ``rrd``, ``web``, ``web_port``, ``grpc_port``, ``rerun_url`` and
    ``duration`` (an :class:`argparse.Namespace` from :func:`run`, or any such object).
    """
    rig = keys.validate_rig(options.rig)
    stop = StopFlag(options.duration)
    rec, sinks = views.open_recording(rrd_path=options.rrd, grpc_url=options.rerun_url, serve_web=options.web,
                                      web_port=options.web_port, grpc_port=options.grpc_port)
    if sinks.web_url:
        print(f"web viewer: {sinks.web_url}", flush=True)
    live = views.LiveViews(rec, live=True)
    sim_seen, sim_gone = threading.Event(), threading.Event()

    def on_alive(sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            sim_seen.set()
        elif sim_seen.is_set():
            sim_gone.set()

    try:
        with open_session(conf) as session:
            # subscriber before the token: a simulator waiting for our token finds our subscription
            sub = zx.declare_advanced_subscriber(
                session, keys.all_key(rig), handler=zenoh.handlers.FifoChannel(1 << 16),
                history=zx.HistoryConfig(detect_late_publishers=True, max_samples=None, max_age=None),
                recovery=None, subscriber_detection=False, allowed_origin=None)
            watch = session.liveliness().declare_subscriber(keys.alive_key(rig, "sim"), on_alive, history=True)
            token = session.liveliness().declare_token(keys.alive_key(rig, "viewer"))
            idle_since = None
            while not stop:
                sample = sub.try_recv()
                if sample is not None:
                    idle_since = None
                    live.feed(str(sample.key_expr), sample.payload.to_bytes())
                    continue
                live.poll()
                if sim_gone.is_set():
                    idle_since = idle_since or time.monotonic()
                    if time.monotonic() - idle_since > 0.5:  # drained
                        break
                time.sleep(0.002)
            token.undeclare()
            watch.undeclare()
            sub.undeclare()
        live.close()
        log.info("showed %d messages (%d revolutions, %d fits, %d travelling waves)", live.stats["messages"],
                 live.stats["revolutions"], live.stats["fits"], live.stats["tw"])
        if options.web and not stop:
            log.info("run ended; serving the web viewer until stopped (Ctrl-C)")
            while not stop.wait(0.2):
                pass
    finally:
        rec.flush()
        rec.disconnect()


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="bttsim-viewer", description=__doc__.splitlines()[0])
    p.add_argument("--rig", default="rig1", help="rig to show (default rig1)")
    p.add_argument("--rrd", metavar="OUT.rrd", help="write an .rrd file (open it with: rerun OUT.rrd)")
    p.add_argument("--rerun-url", metavar="URL",
                   help="stream to a running viewer, e.g. rerun+http://127.0.0.1:9876/proxy")
    p.add_argument("--web", action="store_true", help="serve the web viewer (prints its URL)")
    p.add_argument("--web-port", type=int, default=9090, help="web viewer HTTP port (9090)")
    p.add_argument("--grpc-port", type=int, default=9876, help="port of the web viewer's data server (9876)")
    p.add_argument("--duration", type=float, help="stop after this many seconds")
    add_session_args(p)
    return p


def run(argv=None) -> int:
    return run_program(_parser(), lambda args: main(config_from_args(args), args), argv)


if __name__ == "__main__":
    sys.exit(run())

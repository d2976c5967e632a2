"""Processor node: turns the live OPR and TOA stream into blade vibration, blind to truth.

Inputs: ``bttsim/<rig>/meta`` (``RunMetadata``: geometry), ``bttsim/<rig>/opr`` (``Opr``),
``bttsim/<rig>/toa/<probe>`` (``ToaBatch``). Unless ``--no-score`` it also reads
``bttsim/<rig>/truth`` (``TruthBatch``), used only to score the final report (E_A, E_f).
Outputs, per revolution once the next OPR is in: ``bttsim/<rig>/fit`` (``BladeFits``, one per
engine order, Eq. 16-17) and ``bttsim/<rig>/tw/<probe>`` (``TravellingWave``); per detected
block of revolutions ``bttsim/<rig>/nsv`` (``NonSynchronous``: non-synchronous vibration); at
the end ``bttsim/<rig>/resonance`` (``ResonanceReport``) and, with ``--summary``, the summary JSON.
Liveliness: ``bttsim/<rig>/alive/processor``; status ``bttsim/<rig>/status/processor`` (``done``
with the report's completeness counts and the acquisition numbers not received, per key).
Ends when the simulator's token goes (at once if the whole acquisition stream came in, else
after ``--drain-timeout`` seconds of silence: it may come back, a router restart; so also once
the simulator has declared that it sent all, ``bttsim/<rig>/sent/sim``, while it waits for it), on
``--duration``, SIGINT or SIGTERM. After its report it stays until every node that awaits
it (token ``bttsim/<rig>/awaiting/<node>``: a recorder or viewer that follows the processor)
has it (``bttsim/<rig>/reported/<node>``), at most ``--drain-timeout`` seconds: closing the
session drops what is still queued. Exit status 3 when the result does not rest on the whole
run (no report, revolutions missing or lost; the log says what is missing per key).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from bttsim_stream.bus import keys
from bttsim_stream.defaults import DEFAULT_RIG
from bttsim_stream.bus.session import StopFlag, pack_attachment, wait_for_done
from bttsim_stream.errors import BttsimError
from bttsim_stream.processing_flags import add_processing_arguments, processing_options
from bttsim_stream.runtime import EXIT_INCOMPLETE, FIFO_SIZE, NodeProgram, add_drain_argument, add_duration_argument, \
    add_status_argument, node_session, run_node

if TYPE_CHECKING:
    from bttsim_stream.processor import ProcessorSession

log = logging.getLogger("bttsim.processor")



def main(conf, args: argparse.Namespace) -> dict | None:
    """Process until the simulator ends; returns the summary dict."""
    # the processing: imported when the node runs, not whenever `bttsim` builds its parsers
    from bttsim_stream.process.resonance import summary_table
    from bttsim_stream.processor import ProcessorSession

    rig = keys.validate_rig(args.rig)
    options = processing_options(args)  # a bad value: one line, exit 2
    stop = StopFlag(args.duration)
    summary = None
    # its live samples wait in the inbox (arrival order across the keys), as many as a FIFO
    # subscription holds: a processor behind the simulator slows it instead of holding more
    with node_session(conf, rig, "processor", inbox_size=FIFO_SIZE, status_file=args.status_file) as node:
        for k in (keys.meta_key(rig), keys.opr_key(rig), keys.toa_all_key(rig)) + (
                () if args.no_score else (keys.truth_key(rig),)):
            node.subscribe(k, fifo=False)  # in arrival order across the keys: revolutions complete as they come
        node.watch_nodes(("sim",))
        node.announce()

        def publish(messages) -> None:
            for m in messages:
                node.publisher(m.key).put(m.payload, attachment=pack_attachment(m.seq, m.log_time_ns))

        run = None
        early: list = []  # data that came before the metadata (callbacks of different keys race)
        bad = 0
        kinds: dict[str, str] = {}
        meta_payload, sources = None, set()  # the run's metadata, and the sessions that sent it
        for sample in node.samples(stop, done=lambda: run is not None and run.received_all,
                                   patience_s=args.drain_timeout):
            if sample is None:
                if run is None:  # missed the sample? ask
                    node.ask_metadata({rig})
                continue
            key, payload, att = sample.key, sample.payload, sample.att
            try:  # every sample is untrusted: a bad one is counted and skipped
                kind = kinds.get(key) or _kind(kinds, key)
                item = (kind, key, ProcessorSession.decode(kind, key, payload), att[0] if att else None)
            except BttsimError as exc:
                if run is not None:
                    run.reject(exc)
                else:
                    bad += 1
                continue
            if kind == "meta":
                if meta_payload in (None, payload):  # a session that sent the run's metadata published the run
                    meta_payload = payload
                    sources.add(sample.source)
                if run is None:
                    try:
                        run = ProcessorSession(item[2].body, options, score=not args.no_score)
                    except ValueError as exc:  # the layout cannot separate an engine order: say so, once
                        raise BttsimError(f"cannot process rig {rig}: {exc}") from None
                    run.rejected += bad
                    node.ready()
                    for e, source in early:
                        publish(_from_the_run(run, e, source, sources))
                    early.clear()
            elif run is not None:
                publish(_from_the_run(run, item, sample.source, sources))
                if run.received_all:
                    node.done()
            elif len(early) < MAX_EARLY:
                early.append((item, sample.source))
                node.ask_metadata({rig})  # joined late: ask the queryable
            else:
                bad += 1
        missing = {} if run is None else run.missing()
        if run is not None:
            msgs, summary = run.finish()
            publish(msgs)
            if args.summary:
                Path(args.summary).write_text(json.dumps(summary, indent=2) + "\n")
            print(summary_table(summary), flush=True)
            if not stop:  # the report may still be queued, and closing the session drops it
                node.sent(rig)
                waiting = wait_for_done(node.session, rig, args.drain_timeout, stop, asked="awaiting",
                                        given="reported")
                if waiting:
                    log.warning("leaving before %s confirmed the report (%g s)", ", ".join(sorted(waiting)),
                                args.drain_timeout)
        node.status("done", _final_stats(summary, args.summary, missing))
    _log_verdict(summary, missing)
    return summary


def _log_verdict(summary: dict | None, missing: dict) -> None:
    """Say whether the result rests on the whole run, and what is missing per key."""
    from bttsim_stream.bus.stream import missing_line  # loaded with the processor by main

    if summary is None:
        log.warning("INCOMPLETE: no run metadata received, no report")
    elif summary.get("complete"):
        log.info("complete: %d of %d revolutions processed", summary["revolutions_processed"],
                 summary["revolutions_expected"])
    else:
        log.warning("INCOMPLETE: %d of %d revolutions processed; %s", summary["revolutions_processed"],
                    summary["revolutions_expected"], missing_line(missing) or "nothing missing on the bus")


def _from_the_run(run: ProcessorSession, item: tuple, source: str | None, sources: set) -> list:
    """Add a decoded message to the run, unless it is acquisition data of a Zenoh session that
    did not publish the run (its samples' timestamps name the session): refused, counted."""
    if item[0] in ("opr", "toa", "truth") and source not in sources:
        run.reject(BttsimError(f"{item[1]}: not from the session that published the run"))
        return []
    return run.add(*item)


def _final_stats(summary: dict | None, path: str | None, missing: dict) -> dict:
    """The processor's final status statistics: whether it made a report, where it wrote the
    summary, the summary's completeness keys, and the acquisition numbers it did not receive
    (``missing``, ``missing_by_key``: head, gaps and tail per key)."""
    lost = {"missing": sum(m.total for m in missing.values()),
            "missing_by_key": {k: m.to_dict() for k, m in missing.items()}}
    if summary is None:
        return {"report": False, "summary": "", "complete": False, **lost}
    return {"report": True, "summary": path or "", **lost,
            **{k: summary.get(k) for k in ("status", "complete", "revolutions_expected", "revolutions_processed",
                                           "lost", "duplicates", "rejected")}}


def _kind(kinds: dict, key: str) -> str:
    """The key's kind, parsed once per key (at most ``MAX_KEYS`` kept: keys are untrusted)."""
    kind = keys.parse_key(key).kind
    if len(kinds) < MAX_KEYS:
        kinds[key] = kind
    return kind


#: Keys whose kind is remembered (a run has a few dozen).
MAX_KEYS = 1024
#: Samples kept while the run metadata has not arrived.
MAX_EARLY = 100_000


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--rig", default=DEFAULT_RIG, help=f"rig to process ({DEFAULT_RIG})")
    p.add_argument("--summary", metavar="FILE.json", help="write the summary JSON here at the end")
    p.add_argument("--no-score", action="store_true", help="do not read truth (no E_A / E_f)")
    add_processing_arguments(p)  # --method, --eo, --eo-range, --no-prep, --window
    add_duration_argument(p)
    add_drain_argument(p)
    add_status_argument(p)


def _main(conf, args: argparse.Namespace) -> int:
    """:func:`main` as a program: exit status 3 when the result does not rest on the whole run
    (no report, revolutions missing or lost)."""
    summary = main(conf, args)
    return 0 if summary is not None and summary.get("complete") else EXIT_INCOMPLETE


PROGRAM = NodeProgram("processor", __doc__, add_arguments, _main)


def run(argv=None) -> int:
    return run_node(PROGRAM, argv)


if __name__ == "__main__":
    sys.exit(run())

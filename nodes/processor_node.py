"""Processor node: turns the live OPR and TOA stream into blade vibration, blind to truth.

Inputs: ``bttsim/<rig>/meta`` (``RunMetadata``: geometry), ``bttsim/<rig>/opr`` (``Opr``),
``bttsim/<rig>/toa/<probe>`` (``ToaBatch``). Unless ``--no-score`` it also reads
``bttsim/<rig>/truth`` (``TruthBatch``), used only to score the final report (E_A, E_f).
Outputs, per revolution once the next OPR is in: ``bttsim/<rig>/fit`` (``BladeFits``, one per
engine order, Eq. 16-17) and ``bttsim/<rig>/tw/<probe>`` (``TravellingWave``); at the end
``bttsim/<rig>/resonance`` (``ResonanceReport``) and, with ``--summary``, the summary JSON.
Liveliness: ``bttsim/<rig>/alive/processor``. Ends when the simulator's token goes (after the
final report), on ``--duration``, SIGINT or SIGTERM.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

from bttsim_stream.bus import codec, keys
from bttsim_stream.bus.session import StopFlag, pack_attachment, unpack_attachment
from bttsim_stream.bus.stream import Completeness, MessageStream, RevolutionAssembler, SequenceTracker
from bttsim_stream.errors import BttsimError
from bttsim_stream.offline import add_processing_arguments, processing_options
from bttsim_stream.process.pipeline import StreamingProcessor
from bttsim_stream.process.resonance import TruthPeakTracker, summary_table
from bttsim_stream.runtime import NodeProgram, node_session, run_node

log = logging.getLogger("bttsim.processor")


def main(conf, args: argparse.Namespace) -> dict | None:
    """Process until the simulator ends; returns the summary dict."""
    rig = keys.validate_rig(args.rig)
    options = processing_options(args)  # a bad value: one line, exit 2
    score = not args.no_score
    stop = StopFlag(args.duration)
    summary = None
    with node_session(conf, rig, "processor") as node:
        for k in (keys.meta_key(rig), keys.opr_key(rig), keys.toa_all_key(rig)) + ((keys.truth_key(rig),) if score else ()):
            node.subscribe(k)
        node.watch_nodes(("sim",))
        node.announce()

        def publish(messages) -> None:
            for m in messages:
                node.publisher(m.key).put(m.payload, attachment=pack_attachment(m.seq, m.log_time_ns))

        proc = tracker = asm = out = None
        asked_meta = 0.0
        rejected = 0
        seqs = SequenceTracker()
        for sample in node.samples(stop):
            if sample is None:
                continue
            key, payload = str(sample.key_expr), sample.payload.to_bytes()
            try:  # every sample is untrusted: a bad one is counted and skipped
                kind = keys.parse_key(key).kind
                d = codec.decode_message(key, payload)
                if kind in ("opr", "toa", "truth") and proc is not None:
                    _check_shape(d, kind, proc.geometry)
            except BttsimError as exc:
                rejected += 1
                if rejected <= 3 or rejected % 1000 == 0:
                    log.warning("rejected %d sample(s); latest: %s", rejected, exc)
                continue
            att = unpack_attachment(sample.attachment)
            if kind in ("opr", "toa") and not seqs.accept(key, att[0] if att else None):
                continue  # already received, or an implausible sequence number (counted)
            if kind == "meta":
                if proc is None:
                    meta = d.body
                    try:
                        proc = StreamingProcessor(meta, options)
                    except ValueError as exc:  # the layout cannot separate an engine order: say so, once
                        raise BttsimError(f"cannot process rig {rig}: {exc}") from None
                    tracker = TruthPeakTracker(proc.engine_orders[0])
                    asm = RevolutionAssembler(meta.n_blades, meta.n_probes, n_revolutions=meta.n_revolutions)
                    out = MessageStream(meta.run_id, rig)
                continue
            if proc is None:  # joined late: ask the queryable (once a second), data before it is lost
                if time.monotonic() - asked_meta > 1.0:
                    asked_meta = time.monotonic()
                    node.query(keys.meta_key(rig))
                continue
            if kind == "truth":
                tracker.update(d.header.revolution, d.body.d_eqv_pkpk_m[0], float(d.body.omega_mean[0]))
                continue
            asm.add(kind, d)
            for rev in asm.pop():
                for o in proc.push(rev.revolution, rev.opr_s, rev.toa_s):
                    publish(out.processing(o))
        if proc is not None:
            for rev in asm.pop(final=True):
                for o in proc.push(rev.revolution, rev.opr_s, rev.toa_s):
                    publish(out.processing(o))
            try:
                for o in proc.flush():
                    publish(out.processing(o))
                summary = proc.finish(tracker if score else None)
            except (ValueError, np.linalg.LinAlgError) as exc:  # fewer than three revolutions, ...
                raise BttsimError(f"no resonance report: {exc}") from None
            summary.update(Completeness(
                revolutions_expected=meta.n_revolutions, revolutions_processed=asm.given_complete,
                lost=seqs.lost, duplicates=seqs.duplicates + asm.duplicates,
                rejected=rejected + seqs.implausible).to_summary())
            publish([out.resonance(proc.result.report)])
            if args.summary:
                Path(args.summary).write_text(json.dumps(summary, indent=2) + "\n")
            print(summary_table(summary), flush=True)
            log.info("revolutions: %d given out, %d dropped; fragments ignored %d, duplicates %d; "
                     "samples rejected %d", asm.given, asm.dropped, asm.ignored, asm.duplicates, rejected)
    return summary


def _check_shape(d, kind: str, geometry) -> None:
    """Refuse a decoded OPR / TOA / truth message that does not fit the run's geometry."""
    if kind == "toa" and d.body.toa_s.size != geometry.n_blades:
        raise BttsimError(f"TOA batch of {d.body.toa_s.size} blades in a run of {geometry.n_blades}")
    if kind == "truth" and d.body.d_eqv_pkpk_m.shape != (1, geometry.n_blades):
        raise BttsimError(f"truth of {d.body.d_eqv_pkpk_m.shape[1]} blades in a run of {geometry.n_blades}")
    if kind == "opr" and not np.isfinite(d.body.opr_s):
        raise BttsimError("OPR time is not finite")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--rig", default="rig1", help="rig to process (rig1)")
    p.add_argument("--summary", metavar="FILE.json", help="write the summary JSON here at the end")
    p.add_argument("--no-score", action="store_true", help="do not read truth (no E_A / E_f)")
    add_processing_arguments(p)  # --method, --eo, --eo-range, --no-prep, --window
    p.add_argument("--duration", type=float, metavar="S", help="stop after S seconds")


PROGRAM = NodeProgram("processor", __doc__, add_arguments, main)


def run(argv=None) -> int:
    return run_node(PROGRAM, argv)


if __name__ == "__main__":
    sys.exit(run())

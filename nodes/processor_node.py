"""Processor node: turns the live OPR and TOA stream into blade vibration, blind to truth.

Inputs: ``bttsim/<rig>/meta`` (``RunMetadata``: geometry), ``bttsim/<rig>/opr`` (``Opr``),
``bttsim/<rig>/toa/<probe>`` (``ToaBatch``). With ``--score`` it also reads
``bttsim/<rig>/truth`` (``TruthBatch``), used only to score the final report (E_A, E_f).
Outputs, per revolution once the next OPR is in: ``bttsim/<rig>/fit`` (``BladeFits``,
Eq. 16-17) and ``bttsim/<rig>/tw/<probe>`` (``TravellingWave``); at the end
``bttsim/<rig>/resonance`` (``ResonanceReport``) and, with ``--summary``, the summary JSON.
Liveliness: ``bttsim/<rig>/alive/processor``. Ends when the simulator's token goes (after the
final report), on ``--duration``, SIGINT or SIGTERM.
"""

from __future__ import annotations

import argparse
import json
import logging
import queue
import sys
import time
from pathlib import Path

import numpy as np
import zenoh

from bttsim_stream.io import codec, keys
from bttsim_stream.process.pipeline import ProcessOptions, StreamingProcessor
from bttsim_stream.process.resonance import TruthPeakTracker, summary_table
from bttsim_stream.transport import (NodeWatch, StopFlag, run_program, add_session_args, config_from_args,
                                     open_session, pack_attachment)

log = logging.getLogger("bttsim.processor")


def main(conf: "zenoh.Config", rig: str = "rig1", *, summary_path: str | None = None, score: bool = True,
         options: ProcessOptions = ProcessOptions(), duration_s: float | None = None) -> dict | None:
    """Process until the simulator ends; returns the summary dict."""
    keys.validate_rig(rig)
    stop = StopFlag(duration_s)
    with open_session(conf) as session:
        inbox: queue.SimpleQueue = queue.SimpleQueue()  # one queue for all keys keeps the stream order
        subs = [session.declare_subscriber(k, inbox.put) for k in
                (keys.meta_key(rig), keys.opr_key(rig), f"{keys.PREFIX}/{rig}/toa/*")
                + ((keys.truth_key(rig),) if score else ())]
        watch = NodeWatch(session, rig, ("sim",))
        token = session.liveliness().declare_token(keys.alive_key(rig, "processor"))
        pubs: dict[str, object] = {}
        seqs: dict[str, int] = {}

        def put(enc) -> None:
            if enc.key not in pubs:
                pubs[enc.key] = session.declare_publisher(enc.key, congestion_control=zenoh.CongestionControl.BLOCK)
            pubs[enc.key].put(enc.payload, attachment=pack_attachment(seqs[enc.key] - 1, enc.log_time_ns))

        meta = proc = tracker = None
        pending: dict[int, dict] = {}
        n_probes = 0

        def publish(outputs) -> None:
            for o in outputs:
                for i, eo in enumerate(o.engine_orders):  # one BladeFits per engine order
                    put(codec.encode_blade_fits(
                        run_id=meta.run_id, rig=rig, seqs=seqs, revolution=o.revolution, t_s=o.opr_s,
                        engine_order=eo, omega_mean_rad_s=o.omega_rad_s, cn=o.cn,
                        amp_pkpk_m=o.amp_pkpk_m[:, i], phase_rad=o.phase_rad[:, i], dc_m=o.dc_m,
                        residual_m=o.residual_rms_m, amp_std_m=o.amp_std_m[:, i], freq_hz=float(o.freq_hz[i])))
                # the ND identified from the fits (all probes): a single probe cannot tell a
                # wave from its image 2 EO - ND
                nd = int(o.fit_tw.dominant_nd)
                for p in range(o.probe_tw.forward_m.shape[0]):
                    put(codec.encode_travelling_wave(
                        run_id=meta.run_id, rig=rig, seqs=seqs, revolution=o.revolution, t_s=o.opr_s,
                        probe=p, forward_m=o.probe_tw.forward_m[p], backward_m=o.probe_tw.backward_m[p],
                        dominant_nd=nd))

        idle_since = None
        while not stop:
            try:
                sample = inbox.get(timeout=0.05)
            except queue.Empty:
                sample = None
            if sample is None:
                if watch.ended():
                    idle_since = idle_since or time.monotonic()
                    if time.monotonic() - idle_since > 0.5:
                        break
                continue
            idle_since = None
            key, payload = str(sample.key_expr), sample.payload.to_bytes()
            kind = keys.parse_key(key).kind
            if kind == "meta":
                if meta is None:
                    meta = codec.decode_run_metadata(payload, key)
                    proc = StreamingProcessor(meta, options)
                    tracker = TruthPeakTracker(proc.engine_orders[0])
                    n_probes = meta.n_probes
                continue
            if meta is None:  # joined late: ask the queryable
                for reply in session.get(keys.meta_key(rig), timeout=1.0):
                    if reply.ok is not None:
                        inbox.put(reply.ok)
                continue
            if kind == "truth":
                t = codec.decode_truth_batch(payload, key)
                tracker.update(t.header.revolution, t.d_eqv_pkpk_m, t.omega_mean_rad_s)
                continue
            if kind == "opr":
                m = codec.decode_opr(payload, key)
                pending.setdefault(m.header.revolution, {})["opr"] = m.opr_s
            elif kind == "toa":
                m = codec.decode_toa_batch(payload, key)
                pending.setdefault(m.header.revolution, {})[m.probe] = m.toa_s
            for rev in sorted(r for r, v in pending.items() if len(v) == n_probes + 1):
                v = pending.pop(rev)
                toa = np.stack([v[p] for p in range(n_probes)], axis=1)
                publish(proc.push(rev, v["opr"], toa))
        summary = None
        if proc is not None and proc._opr.n >= 3:
            publish(proc.flush())
            summary = proc.finish(tracker if score else None)
            put(codec.encode_resonance_report(summary, run_id=meta.run_id, rig=rig, seqs=seqs))
            if summary_path:
                Path(summary_path).write_text(json.dumps(summary, indent=2) + "\n")
            print(summary_table(summary), flush=True)
        time.sleep(0.2)  # let the last samples leave before the token goes
        for p in pubs.values():
            p.undeclare()
        for s in subs:
            s.undeclare()
        watch.undeclare()
        token.undeclare()
    return summary


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="bttsim-processor", description=__doc__.splitlines()[0])
    p.add_argument("--rig", default="rig1")
    p.add_argument("--summary", help="write the summary JSON here at the end")
    p.add_argument("--no-score", action="store_true", help="do not read truth (no E_A / E_f)")
    p.add_argument("--no-prep", action="store_true", help="no data preparation in the final report")
    p.add_argument("--window", type=int, default=1, help="revolutions per sine fit (1)")
    p.add_argument("--duration", type=float)
    add_session_args(p)
    return p


def run(argv=None) -> int:
    return run_program(_parser(), lambda args: main(
        config_from_args(args), args.rig, summary_path=args.summary, score=not args.no_score,
        options=ProcessOptions(prep=not args.no_prep, window=args.window), duration_s=args.duration), argv)


if __name__ == "__main__":
    sys.exit(run())

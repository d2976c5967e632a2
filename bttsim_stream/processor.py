"""The processor's work without the transport: decoded bus messages in, numbered result
messages and the summary out.

:class:`ProcessorSession` is the one path from acquisition messages to results, used live
by the processor node (``nodes/processor_node.py``) and on recordings by
:func:`bttsim_stream.offline.processing_messages` (``bttsim view`` of a raw recording), so
both publish the same messages and the same summary. Revolutions are regrouped by the bus's
:class:`~bttsim_stream.bus.stream.RevolutionAssembler`, processed by the streaming
processor (Eq. 1, Eq. 16-17 per revolution; the offline pipeline for the final report) and
numbered by a :class:`~bttsim_stream.bus.stream.MessageStream`. Every message is untrusted:
sequence numbers are checked (:class:`~bttsim_stream.bus.stream.SequenceTracker`), shapes
against the run, and what does not fit is counted, never fatal.
"""

from __future__ import annotations

import logging

import numpy as np

from .bus import codec, keys
from .bus.codec import Decoded
from .bus.stream import Completeness, KeyMissing, Message, MessageStream, RevolutionAssembler, SequenceTracker, \
    StreamEnd, acquisition_counts
from .errors import BttsimError
from .process.displacement import DoublePulses
from .process.options import ProcessOptions
from .process.streaming import StreamingProcessor
from .process.resonance import TruthPeakTracker
from .sim.records import RunInfo
from .summary import build_summary

__all__ = ["ProcessorSession"]

log = logging.getLogger("bttsim.processor")


class ProcessorSession:
    """Process one run's messages as they come.

    Parameters
    ----------
    meta : RunInfo
        The run metadata (geometry, revolution count, engine orders).
    options : ProcessOptions
    score : bool
        Use truth messages for E_A / E_f in the final report.

    Attributes
    ----------
    rejected : int
        Messages refused (malformed, not fitting the run, implausible sequence numbers). A TOA
        batch holding a TOA not within a revolution of its OPR pulse is refused when the next
        pulse comes (:attr:`StreamingProcessor.refused_batches`), after it took its number: the
        completeness counts it as rejected and lost.
    missing_toas : int
        TOAs received as NaN (no pulse triggered: the signal chain's missing pulses); they
        stay NaN through the processing, which fits the probes present.
    doubles : DoublePulses
        Extra trigger edges received (double pulses), each assigned to the blade whose window
        it falls in; the first edge stays the TOA.
    """

    def __init__(self, meta: RunInfo, options: ProcessOptions = ProcessOptions(), *, score: bool = True) -> None:
        self.meta = meta
        self.score = score
        self.proc = StreamingProcessor(meta, options)
        self.tracker = TruthPeakTracker(self.proc.engine_orders[0])
        self.asm = RevolutionAssembler(meta.n_blades, meta.n_probes, n_revolutions=meta.n_revolutions)
        self.seqs = SequenceTracker()
        self.seqs.expect(self.expected())  # a number at or beyond a key's count is not believed
        self.out = MessageStream(meta.run_id, meta.rig)
        self.rejected = 0
        self.missing_toas = 0
        self.doubles = DoublePulses()
        self.end = StreamEnd(meta)

    @property
    def received_all(self) -> bool:
        """Has the whole acquisition stream come in (:class:`StreamEnd`)?"""
        return self.end.done

    def expected(self) -> dict[str, int]:
        """``{key: n}``: the acquisition keys the processor reads and their message counts (the
        run metadata's; truth only when scoring)."""
        counts = acquisition_counts(self.meta)
        counts.pop(keys.meta_key(self.meta.rig), None)
        if not self.score:
            counts.pop(keys.truth_key(self.meta.rig), None)
        return counts

    def missing(self) -> dict[str, KeyMissing]:
        """Per acquisition key that misses anything: the numbers not received (head, gaps and
        tail against the run's count)."""
        return self.seqs.missing(self.expected())

    def reject(self, exc: Exception) -> None:
        """Count a refused message (logged: the first three, then every 1000th)."""
        self.rejected += 1
        if self.rejected <= 3 or self.rejected % 1000 == 0:
            log.warning("rejected %d message(s); latest: %s", self.rejected, exc)

    @staticmethod
    def decode(kind: str, key: str, payload: bytes) -> Decoded:
        """Decode a message of ``key`` (of kind ``kind``) for :meth:`add`: a truth message
        without its per-probe fields, which the scoring does not use (checked all the same).

        Raises
        ------
        BttsimError
            A payload its decoder refuses.
        """
        if kind == "truth":
            return codec.decode_truth(payload, key, fields=())
        return codec.decode_message(key, payload)

    def add(self, kind: str, key: str, decoded: Decoded, seq: int | None = None) -> list[Message]:
        """Add a decoded ``opr``, ``toa`` or ``truth`` message (``seq``: its sequence number, if
        known); returns the result messages that became ready."""
        try:  # what does not fit the run is refused before it can take a sequence number
            self._check(kind, decoded)
        except BttsimError as exc:
            self.reject(exc)
            return []
        if kind in ("opr", "toa", "truth") and not self.seqs.accept(key, seq):
            return []  # already received, or an implausible sequence number (counted)
        self.end.note(key, seq)
        if kind == "truth":
            t = decoded.body
            nsv = None
            if getattr(t, "nsv_kind", None) is not None:  # the non-synchronous components (issue 13)
                nsv = (t.nsv_kind[0], t.nsv_freq_hz[0], t.nsv_nd[0], t.nsv_amp_pkpk_m[0])
            eo = None if t.eo_pkpk_m is None else (t.eo_engine_order[0], t.eo_pkpk_m[0])
            self.tracker.update(decoded.header.revolution, t.d_eqv_pkpk_m[0], float(t.omega_mean[0]), nsv=nsv, eo=eo)
            return []
        if kind == "toa":
            self.missing_toas += int(np.count_nonzero(np.isnan(decoded.body.toa_s)))
            self.doubles.add(decoded.body.toa_s, decoded.body.extra_toa_s)
        self.asm.add(kind, decoded)
        out = self._push(self.asm.pop())
        if kind == "opr":  # the previous revolution's outputs need no more than this pulse
            out += self._advance(int(decoded.header.revolution))
        return out

    def _advance(self, revolution: int) -> list[Message]:
        """The outputs that ``revolution``'s OPR pulse completes, before its TOAs come: the
        live fit of a revolution goes out as soon as the pulse that ends it is in."""
        opr = self.asm.next_opr(revolution)
        if opr is None:
            return []
        out: list[Message] = []
        for o in self.proc.advance(revolution, opr):
            out += self.out.processing(o)
        return out + self._nsv() if out else out

    def _check(self, kind: str, d: Decoded) -> None:
        g = self.proc.geometry
        if d.header.run_id != self.meta.run_id:  # (run, key, seq) names a message: another run's is foreign
            raise BttsimError(f"a {kind} message of run {d.header.run_id!r} in run {self.meta.run_id!r}")
        if kind == "toa" and d.body.toa_s.size != g.n_blades:
            raise BttsimError(f"TOA batch of {d.body.toa_s.size} blades in a run of {g.n_blades}")
        if kind == "truth" and d.body.d_eqv_pkpk_m.shape != (1, g.n_blades):
            raise BttsimError(f"truth of {d.body.d_eqv_pkpk_m.shape[1]} blades in a run of {g.n_blades}")
        if kind == "opr" and not np.isfinite(d.body.opr_s):
            raise BttsimError("OPR time is not finite")

    def _push(self, revolutions) -> list[Message]:
        out: list[Message] = []
        for rev in revolutions:
            for o in self.proc.push(rev.revolution, rev.opr_s, rev.toa_s):
                out += self.out.processing(o)
        return out + self._nsv()

    def _nsv(self) -> list[Message]:
        """One ``NonSynchronous`` message per detected block of revolutions completed (the
        live view of non-synchronous vibration; the final report holds the run's grouping)."""
        msgs = []
        for det in self.proc.nsv_ready():
            k = det.last_revolution - (self.proc._first_rev or 0)
            msgs.append(self.out.nsv(det, t_s=float(self.proc._opr[k])))
        return msgs

    def completeness(self) -> Completeness:
        """What the result rests on so far."""
        refused = self.proc.refused_batches  # numbered, then dropped: their numbers are missing too
        return Completeness(revolutions_expected=self.meta.n_revolutions,
                            revolutions_processed=self.asm.given_complete,
                            lost=self.seqs.lost + self.seqs.missed_at_start + refused,
                            duplicates=self.seqs.duplicates + self.asm.duplicates,
                            rejected=self.rejected + self.seqs.implausible + refused)

    def finish(self) -> tuple[list[Message], dict]:
        """The rest of the stream, the last outputs and the resonance report message, and the
        summary dict (the brief's form, with the completeness keys).

        Raises
        ------
        BttsimError
            Fewer than three revolutions: no report.
        """
        msgs = self._push(self.asm.pop(final=True))
        try:
            for o in self.proc.flush():
                msgs += self.out.processing(o)
            msgs += self._nsv()
            result = self.proc.finish(self.tracker if self.score else None)
        except (ValueError, np.linalg.LinAlgError) as exc:  # fewer than three revolutions, ...
            raise BttsimError(f"no resonance report: {exc}") from None
        summary = build_summary(result, self.completeness(), missing_toas=self.missing_toas,
                                doubles=self.doubles.to_summary())
        msgs.append(self.out.resonance(self.proc.result.report))
        if self.proc.refused_batches:
            log.warning("%d TOA batch(es) refused: a TOA not within a revolution of its OPR pulse",
                        self.proc.refused_batches)
        a = self.asm
        log.info("revolutions: %d given out, %d dropped; fragments ignored %d, duplicates %d; "
                 "messages rejected %d", a.given, a.dropped, a.ignored, a.duplicates, self.rejected)
        return msgs, summary

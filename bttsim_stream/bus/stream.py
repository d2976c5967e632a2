"""The message stream: one record type, one place that numbers messages, one revolution
assembler, one "results -> messages".

* :class:`Message` is the one record of a message wherever it is -- about to be published,
  received with its attachment, or read from an MCAP file: key, payload bytes, log time (ns)
  and the publisher's per-key sequence number.
* :class:`Sequencer` is the only place where sequence numbers are assigned (0, 1, 2, ... per
  key). :class:`MessageStream` owns one and turns the library's dataclasses into numbered
  messages: the run metadata, the acquisition (:class:`~bttsim_stream.sim.core.RevolutionBatch`)
  and the processing results (:class:`~bttsim_stream.process.results.RevolutionOutput`,
  :class:`~bttsim_stream.process.resonance.ResonanceReport`). The simulator node, ``bttsim
  simulate``, the processor node and the offline processing all publish through it, so a
  live run and a file hold the same bytes.
* :class:`RevolutionAssembler` regroups OPR pulses and per-probe TOA batches into
  revolutions (the processor node, offline processing and the views all use it).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..sim.records import RevolutionBatch, RunInfo
from . import codec, keys

__all__ = ["Message", "Sequencer", "SequenceTracker", "KeyMissing", "missing_line", "acquisition_counts",
           "MessageStream", "Revolution", "RevolutionAssembler", "StreamEnd", "Completeness"]


@dataclass(frozen=True, slots=True)
class Message:
    """One message of the bus or of a recording.

    Attributes
    ----------
    key : str
        Key expression it travels on (the MCAP channel topic).
    payload : bytes
        Serialized protobuf.
    log_time_ns : int
        Simulated time, ns (the MCAP log time).
    seq : int
        The publisher's per-key sequence number (the MCAP ``sequence`` field and the
        sample attachment).
    """

    key: str
    payload: bytes
    log_time_ns: int
    seq: int = 0


class Sequencer:
    """Per-key sequence numbers: 0, 1, 2, ... (the only place they are assigned)."""

    __slots__ = ("_next",)

    def __init__(self) -> None:
        self._next: dict[str, int] = {}

    def next(self, key: str) -> int:
        """Take the next number of ``key``."""
        seq = self._next.get(key, 0)
        self._next[key] = seq + 1
        return seq

    def take(self, key: str, count: int) -> np.ndarray:
        """Take the next ``count`` numbers of ``key`` (int64 array)."""
        seq = self._next.get(key, 0)
        self._next[key] = seq + int(count)
        return np.arange(seq, seq + int(count), dtype=np.int64)

    def count(self, key: str) -> int:
        """How many numbers ``key`` has taken."""
        return self._next.get(key, 0)


class SequenceTracker:
    """The receiving side of :class:`Sequencer`: per key, what arrived against the numbers.

    :meth:`accept` says whether a message is new (its number is beyond the last one seen on
    its key); a number at or below it is a duplicate (e.g. late-joiner history replayed
    after live samples) and is counted, not accepted; a jump counts the numbers skipped as
    lost. A jump of more than ``max_jump`` is not believed (a forged or corrupt number that
    would make every later message look like a duplicate): counted in :attr:`implausible`,
    not accepted. Messages without a number (``seq=None``) are always accepted.
    """

    def __init__(self, max_jump: int = 1 << 16) -> None:
        self.max_jump = int(max_jump)
        self.implausible = 0
        self.count: dict[str, int] = {}
        self.first: dict[str, int] = {}
        self.next: dict[str, int] = {}
        self.gaps: dict[str, int] = {}
        self.limit: dict[str, int] = {}
        self.duplicates = 0

    def expect(self, counts: dict[str, int]) -> None:
        """Keys whose message count is known (``{key: n}``, e.g. :func:`acquisition_counts`):
        their numbers run 0..n-1, and a number at or beyond ``n`` is not believed."""
        self.limit.update({k: int(n) for k, n in counts.items()})

    def accept(self, key: str, seq: int | None) -> bool:
        """Count one message; False for a duplicate or a number not believed."""
        if seq is None:
            self.count[key] = self.count.get(key, 0) + 1
            return True
        expected = self.next.get(key)
        if seq != expected:  # the rare cases: the first message of a key, a gap, a duplicate
            start = 0 if expected is None else expected
            if seq < start:
                self.duplicates += 1
                return False
            # a jump (from 0 for a key's first message) beyond the key's known count, or
            # beyond max_jump, is not believed: a forged number must neither make every later
            # message a duplicate nor make the missing counts absurd
            if seq >= self.limit.get(key, start + self.max_jump + 1):
                self.implausible += 1
                return False
            if expected is None:
                self.first[key] = seq
            else:
                self.gaps[key] = self.gaps.get(key, 0) + seq - expected
        elif seq >= self.limit.get(key, seq + 1):  # one past a key's known end
            self.implausible += 1
            return False
        self.count[key] = self.count.get(key, 0) + 1
        self.next[key] = seq + 1
        return True

    def missing(self, expected: dict[str, int] | None = None) -> dict[str, "KeyMissing"]:
        """What is missing, per key that misses anything: numbers before the first one received
        (``head``; publishers count from 0), between received ones (``gaps``) and, for a key
        whose count is known (``expected``, ``{key: n}``), after the last one received up to
        ``n - 1`` (``tail``; a key with nothing received misses all ``n`` as its head).
        Computed from per-key counters at the end: nothing is done per message."""
        expected = expected or {}
        out: dict[str, KeyMissing] = {}
        for key in sorted(set(self.next) | set(expected)):
            n = expected.get(key)
            nxt = self.next.get(key)
            if nxt is None:  # nothing numbered received
                m = KeyMissing(head=int(n or 0), gaps=0, tail=0)
            else:
                head, gaps = self.first.get(key, 0), self.gaps.get(key, 0)
                tail = 0 if n is None else max(0, int(n) - nxt)
                if n is not None:  # numbers accepted before the count was known: stay within n
                    head, gaps = min(head, int(n)), min(gaps, int(n))
                m = KeyMissing(head=int(head), gaps=int(gaps), tail=int(tail))
            if m.total:
                out[key] = m
        return out

    @property
    def lost(self) -> int:
        """Numbers skipped on every key."""
        return sum(self.gaps.values())

    @property
    def missed_at_start(self) -> int:
        """Numbers before the first one received, on every key (publishers count from 0: a
        subscriber that joined late, or the first messages lost)."""
        return sum(self.first.values())

    def summary(self) -> dict:
        """Counts for a report: messages, keys, gaps (by key), duplicates, late-start keys."""
        return {"messages": sum(self.count.values()), "keys": len(self.count),
                "gaps": self.lost, "gaps_by_key": dict(self.gaps),
                "duplicates_skipped": self.duplicates,
                "late_start_keys": {k: v for k, v in self.first.items() if v > 0}}


@dataclass(frozen=True, slots=True)
class KeyMissing:
    """Numbers missing on one key (:meth:`SequenceTracker.missing`).

    Attributes
    ----------
    head : int
        Before the first number received (all of a known count if nothing came).
    gaps : int
        Between numbers received.
    tail : int
        After the last number received, up to the key's known count (0 if unknown).
    """

    head: int
    gaps: int
    tail: int

    @property
    def total(self) -> int:
        return self.head + self.gaps + self.tail

    def to_dict(self) -> dict:
        return {"head": self.head, "gaps": self.gaps, "tail": self.tail}


def missing_line(missing: dict) -> str:
    """``"12 messages missing (opr 2, toa/0 10)"``: a ``{key: KeyMissing}`` in one line, the rig
    prefix left out ("" when nothing is missing)."""
    if not missing:
        return ""
    total = sum(m.total for m in missing.values())
    by_key = ", ".join(f"{k.split('/', 2)[-1]} {m.total}" for k, m in missing.items())
    return f"{total} messages missing ({by_key})"


def acquisition_counts(meta) -> dict[str, int]:
    """The message count of every key whose count the run metadata (:class:`RunInfo`) fixes:
    the metadata key (one message), the OPR key, each probe's TOA key and, if the run has
    it, the truth key (``n_revolutions`` each, numbered 0..n_revolutions-1)."""
    rig, n = meta.rig, int(meta.n_revolutions)
    counts = {keys.meta_key(rig): 1, keys.opr_key(rig): n}
    counts.update({keys.toa_key(rig, j): n for j in range(int(meta.n_probes))})
    if meta.has_truth:
        counts[keys.truth_key(rig)] = n
    return counts


@dataclass(frozen=True, slots=True)
class Completeness:
    """What a result rests on, against what the run holds (the summary's completeness keys).

    Attributes
    ----------
    revolutions_expected : int
        The run's revolution count (run metadata).
    revolutions_processed : int
        Revolutions processed with every probe's batch.
    lost : int
        Acquisition messages missing by their sequence numbers.
    duplicates : int
        Messages (or fragments) received twice; the first one is used.
    rejected : int
        Messages refused as malformed or not fitting the run.
    """

    revolutions_expected: int
    revolutions_processed: int
    lost: int = 0
    duplicates: int = 0
    rejected: int = 0

    @property
    def complete(self) -> bool:
        """Every revolution of the run processed and nothing lost."""
        return self.lost == 0 and self.revolutions_processed >= self.revolutions_expected

    def to_summary(self) -> dict:
        """The summary JSON keys: ``complete``, ``revolutions_expected``, ``revolutions_processed``,
        ``lost``, ``duplicates``, ``rejected``."""
        return {"complete": self.complete, "revolutions_expected": int(self.revolutions_expected),
                "revolutions_processed": int(self.revolutions_processed), "lost": int(self.lost),
                "duplicates": int(self.duplicates), "rejected": int(self.rejected)}


class MessageStream:
    """A publisher's outgoing messages, numbered per key.

    Parameters
    ----------
    run_id, rig : str
    """

    def __init__(self, run_id: str, rig: str) -> None:
        self.run_id = run_id
        self.rig = keys.validate_rig(rig)
        self.sequencer = Sequencer()
        self._k_opr = keys.opr_key(self.rig)
        self._k_truth = keys.truth_key(self.rig)
        self._k_fit = keys.fits_key(self.rig)
        self._k_toa: list[str] = []
        self._k_signal: list[str] = []
        self._k_tw: list[str] = []

    def _message(self, key: str, revolution: int, t_s: float, encode, *args) -> Message:
        seq = self.sequencer.next(key)
        payload = encode(codec.Header(self.run_id, seq, revolution, t_s), *args)
        return Message(key, payload, codec.log_time_ns(t_s), seq)

    # -- metadata ------------------------------------------------------------------------
    def run_metadata(self, info: RunInfo) -> Message:
        """The run metadata message (log time 0); ``info.run_id`` is set to the stream's."""
        info = replace(info, run_id=self.run_id, rig=self.rig)
        return self._message(keys.meta_key(self.rig), -1, 0.0, codec.encode_run_metadata, info)

    # -- acquisition ---------------------------------------------------------------------
    def acquisition(self, batch: RevolutionBatch, *, include_truth: bool = True) -> list[Message]:
        """Messages of a batch of revolutions, in publication order.

        Per revolution: one ``Opr`` (header time: the OPR as acquired), with raw signals
        (``batch.signal``) one ``SignalBatch`` per probe, one ``ToaBatch`` per probe
        0..n_probes-1 (header time, also the ``SignalBatch``'s: its latest TOA or extra edge of a
        double pulse, the OPR time if all are missing; the extra edges in the batch's
        ``extra_toa_s``), then one ``TruthBatch`` (header time: the acquired OPR; if
        ``include_truth``). The raw windows go before the TOAs, so a consumer that has a
        run's last TOAs (:class:`StreamEnd`) has its signals too.
        """
        toa = np.asarray(batch.toa_s, dtype=np.float64)
        if toa.ndim != 3:
            raise ValueError(f"toa_s: expected shape (n_rev, n_blades, n_probes), got {toa.shape}")
        nr, nb, npr = toa.shape
        revs = np.asarray(batch.revolution, dtype=np.int64).tolist()
        opr = np.asarray(batch.opr_s, dtype=np.float64)
        if len(revs) != nr or opr.shape != (nr,):
            raise ValueError(f"revolution and opr_s must have shape ({nr},)")
        ticked = batch.toa_ticks is not None
        if ticked != (batch.opr_ticks is not None):
            raise ValueError("opr_ticks and toa_ticks must both be given or both be None")
        if ticked:
            toa_ticks = np.asarray(batch.toa_ticks, dtype=np.int64)
            if toa_ticks.shape != toa.shape:
                raise ValueError(f"toa_ticks: expected shape {toa.shape}, got {toa_ticks.shape}")
        if include_truth and np.shape(batch.truth.toa_s) != toa.shape:
            raise ValueError(f"truth: expected shape {toa.shape}, got {np.shape(batch.truth.toa_s)}")
        while len(self._k_toa) < npr:
            self._k_toa.append(keys.toa_key(self.rig, len(self._k_toa)))
        if nr == 0:
            return []
        latest = np.fmax.reduce(toa, axis=1)  # (nr, np), ignores NaN
        latest = np.where(np.isnan(latest), opr[:, None], latest)
        extra = None
        if batch.extra_passage is not None and batch.extra_passage.size:
            p = np.asarray(batch.extra_passage, dtype=np.int64)
            t_extra = np.asarray(batch.extra_toa_s, dtype=np.float64)
            # a passage's first MAX_EXTRA_EDGES_PER_BLADE extra edges (a latch FIFO of that
            # depth): a chattering trigger must not publish batches every decoder refuses
            k = np.lexsort((t_extra, p))
            start = np.r_[0, np.flatnonzero(np.diff(p[k])) + 1]
            rank = np.arange(k.size) - np.repeat(start, np.diff(np.r_[start, k.size]))
            keep = np.sort(k[rank < codec.MAX_EXTRA_EDGES_PER_BLADE])
            p, t_extra = p[keep], t_extra[keep]
            msg = (p // (nb * npr)) * npr + p % npr  # (revolution, probe) message of each edge
            order = np.lexsort((t_extra, msg))
            ticks = None if batch.extra_toa_ticks is None else np.asarray(batch.extra_toa_ticks)[keep][order]
            extra = (msg[order], t_extra[order], ticks)
            flat = latest.reshape(-1)  # a batch goes out after its last edge
            np.fmax.at(flat, msg, t_extra)
        revs_a = np.asarray(revs, dtype=np.int64)
        # every message of the batch encoded at once (codec's batch encoders: the same bytes
        # as one message at a time); numbers taken per key in publication order
        seq_opr = self.sequencer.take(self._k_opr, nr)
        seq_toa = np.stack([self.sequencer.take(self._k_toa[j], nr) for j in range(npr)], axis=1)  # (nr, np)
        opr_pl = codec.encode_opr_batch(self.run_id, seq_opr, revs_a, opr, opr,
                                        np.asarray(batch.opr_ticks, dtype=np.int64) if ticked else None)
        toa_pl = codec.encode_toa_batches(
            self.run_id, seq_toa.ravel(), np.repeat(revs_a, npr), latest.ravel(), np.tile(np.arange(npr), nr),
            toa.transpose(0, 2, 1).reshape(nr * npr, nb),
            toa_ticks.transpose(0, 2, 1).reshape(nr * npr, nb) if ticked else None,
            extra)
        t_opr = codec.log_times_ns(opr).tolist()
        t_toa = codec.log_times_ns(latest).tolist()
        seq_opr_l, seq_toa_l = seq_opr.tolist(), seq_toa.tolist()
        k_opr, k_toa = self._k_opr, self._k_toa
        raw = batch.signal
        if raw is not None:
            while len(self._k_signal) < npr:
                self._k_signal.append(keys.signal_key(self.rig, len(self._k_signal)))
            seq_sig = np.stack([self.sequencer.take(self._k_signal[j], nr) for j in range(npr)], axis=1)
            sig_pl = codec.encode_signal_batches(self.run_id, seq_sig.ravel(), np.repeat(revs_a, npr), latest.ravel(),
                                                 raw, toa, batch.n_edges)
            seq_sig_l, k_sig = seq_sig.tolist(), self._k_signal
        if include_truth:
            seq_tr = self.sequencer.take(self._k_truth, nr)
            tr_pl = codec.encode_truth_batch(self.run_id, seq_tr, revs_a, opr, batch.truth)
            seq_tr_l, k_tr = seq_tr.tolist(), self._k_truth
        out: list[Message] = []
        for i in range(nr):
            out.append(Message(k_opr, opr_pl[i], t_opr[i], seq_opr_l[i]))
            row = seq_toa_l[i]
            t_row = t_toa[i]
            if raw is not None:
                for j in range(npr):
                    out.append(Message(k_sig[j], sig_pl[i * npr + j], t_row[j], seq_sig_l[i][j]))
            for j in range(npr):
                out.append(Message(k_toa[j], toa_pl[i * npr + j], t_row[j], row[j]))
            if include_truth:
                out.append(Message(k_tr, tr_pl[i], t_opr[i], seq_tr_l[i]))
        return out

    # -- processing results --------------------------------------------------------------
    def processing(self, output) -> list[Message]:
        """Messages of one processed revolution
        (:class:`~bttsim_stream.process.results.RevolutionOutput`): one ``BladeFits`` per
        engine order, then one ``TravellingWave`` per probe; header time: the OPR."""
        rev, t = int(output.revolution), float(output.opr_s)
        log_ns = codec.log_time_ns(t)
        # the fits (output.fits()) and the probes' waves (output.probe_waves()) written at
        # once, each kind: the same bytes
        eos = output.engine_orders
        seqs = [self.sequencer.next(self._k_fit) for _ in eos]
        payloads = codec.encode_fits(self.run_id, seqs, rev, t, eos, output.omega_rad_s, output.freq_hz, output.cn,
                                     output.amp_pkpk_m, output.phase_rad, output.amp_std_m, output.dc_m,
                                     output.residual_rms_m)
        out = [Message(self._k_fit, payload, log_ns, seq) for payload, seq in zip(payloads, seqs)]
        tw = output.probe_tw
        n_probes = tw.forward_m.shape[0]
        while len(self._k_tw) < n_probes:
            self._k_tw.append(keys.tw_key(self.rig, len(self._k_tw)))
        k_tw = self._k_tw[:n_probes]
        seqs = [self.sequencer.next(k) for k in k_tw]
        payloads = codec.encode_probe_waves(self.run_id, seqs, rev, t, tw.forward_m, tw.backward_m,
                                            int(output.fit_tw.dominant_nd))
        out += [Message(k, payload, log_ns, seq) for k, payload, seq in zip(k_tw, payloads, seqs)]
        return out

    def nsv(self, detection, *, t_s: float = 0.0) -> Message:
        """A non-synchronous vibration message (:class:`~bttsim_stream.process.nsv.NsvDetection`),
        numbered at its last revolution; header time ``t_s`` (the OPR of that revolution)."""
        return self._message(keys.nsv_key(self.rig), int(detection.last_revolution), t_s, codec.encode_nsv,
                             detection)

    def resonance(self, report, *, revolution: int = -1, t_s: float = 0.0) -> Message:
        """The resonance report message (:class:`~bttsim_stream.process.resonance.ResonanceReport`);
        ``revolution`` -1: the whole run."""
        return self._message(keys.resonance_key(self.rig), revolution, t_s, codec.encode_resonance_report,
                             report)


@dataclass(frozen=True, slots=True, eq=False)
class Revolution:
    """One assembled revolution.

    Attributes
    ----------
    revolution : int
    opr_s : float
        OPR pulse time, s.
    toa_s : ndarray, shape (n_blades, n_probes)
        TOAs, s; NaN for a probe whose batch did not arrive.
    complete : bool
        True when every probe's batch arrived.
    """

    revolution: int
    opr_s: float
    toa_s: np.ndarray
    complete: bool


class StreamEnd:
    """Has a consumer received the whole acquisition stream of a run (and the processor's report)?

    The simulator numbers each acquisition key 0, 1, ... one message per revolution
    (:class:`Sequencer`): the stream is whole once the OPR key, every probe's TOA key and
    (if the run has it) the truth key have delivered number ``n_revolutions - 1``. Feed it
    the sequence numbers a :class:`SequenceTracker` accepted.

    Parameters
    ----------
    meta : RunInfo
    report : bool
        The consumer follows the processor: the run is :attr:`whole` only once the
        processor's resonance report (its last output) came in too.
    """

    def __init__(self, meta, report: bool = False) -> None:
        self.counts = acquisition_counts(meta)
        self._last = int(meta.n_revolutions) - 1
        self._waiting = set(self.counts) - {keys.meta_key(meta.rig)}
        self._report_key = keys.resonance_key(meta.rig)
        self.reported = not report

    def note(self, key: str, seq: int | None) -> None:
        """A message of ``key`` numbered ``seq`` came in."""
        if seq == self._last:
            self._waiting.discard(key)
        if key == self._report_key:
            self.reported = True

    @property
    def done(self) -> bool:
        """The whole acquisition stream came in."""
        return not self._waiting

    @property
    def whole(self) -> bool:
        """The whole acquisition stream came in, and the report if it is awaited."""
        return self.reported and not self._waiting


class RevolutionAssembler:
    """Regroup OPR pulses and per-probe TOA batches (decoded, in any order) into revolutions.

    Revolutions come out in increasing order from :meth:`pop`: a revolution as soon as its
    OPR and every probe's batch are in. An incomplete one (probe batches or its OPR pulse
    lost) comes out once nothing more can come for it: each missing source (the OPR stream,
    each probe's stream) has already delivered a later revolution (one source's messages
    arrive in order: one publisher, one reliable link), or a revolution ``reorder`` or more
    ahead is complete, or more than ``reorder`` revolutions are waiting (a source that went
    silent), or at the end (``final``). Different sources may be far apart (hundreds of
    revolutions on a loaded machine), so nothing is decided from the distance between them
    alone. A revolution without an OPR pulse cannot be placed and is dropped (counted in
    :attr:`dropped`).

    Every fragment is untrusted: one for a revolution already given out, outside
    ``[0, n_revolutions)``, more than ``max_ahead`` revolutions beyond the last one given out,
    for a probe that does not exist or with the wrong blade count is ignored (counted in
    :attr:`ignored`); a second batch for the same (revolution, probe) or a second OPR pulse
    for a revolution is a duplicate (counted in :attr:`duplicates`; the first one stays). So a
    forged far-ahead revolution neither flushes the revolutions in progress nor makes memory
    grow beyond ``max_ahead`` revolutions.

    Parameters
    ----------
    n_blades, n_probes : int
    n_revolutions : int, optional
        The run's revolution count (from the run metadata), if known.
    max_ahead : int
        Largest accepted distance beyond the last revolution given out.
    reorder : int
        How far (revolutions) a complete revolution, or the number of revolutions waiting, may
        run ahead of an incomplete one before it is given out.
    """

    def __init__(self, n_blades: int, n_probes: int, *, n_revolutions: int | None = None,
                 max_ahead: int = 2048, reorder: int = 1024) -> None:
        self.n_blades = int(n_blades)
        self.n_probes = int(n_probes)
        self.n_revolutions = None if not n_revolutions else int(n_revolutions)
        self.max_ahead = int(max_ahead)
        self.reorder = max(1, int(reorder))
        self.max_ahead = max(self.max_ahead, self.reorder + 1)
        self._newest = [-1] * (self.n_probes + 1)  # per source; [-1]: OPR (a list: a few sources)
        self.duplicates = 0
        self._opr: dict[int, float] = {}
        self._toa: dict[int, np.ndarray] = {}
        self._seen: dict[int, set] = {}
        self._max_complete = -1
        self._last_out: int | None = None
        self.dropped = 0
        self.ignored = 0
        self.given = 0
        self.given_complete = 0

    def add_opr(self, revolution: int, opr_s: float) -> None:
        """An OPR pulse (``opr_s`` finite)."""
        revolution = int(revolution)
        if not self._acceptable(revolution) or not np.isfinite(opr_s):
            self.ignored += 1
            return
        if revolution in self._opr:
            self.duplicates += 1
            return
        self._opr[revolution] = float(opr_s)
        self._newest[-1] = max(self._newest[-1], revolution)
        self._note_complete(revolution)

    def add_toa(self, revolution: int, probe: int, toa_s: np.ndarray) -> None:
        """One probe's TOAs (n_blades,); out-of-range probes and wrong sizes are ignored."""
        revolution, probe = int(revolution), int(probe)
        toa = np.asarray(toa_s, dtype=float)
        if not self._acceptable(revolution) or not 0 <= probe < self.n_probes or toa.shape != (self.n_blades,):
            self.ignored += 1
            return
        if probe in self._seen.get(revolution, ()):
            self.duplicates += 1
            return
        row = self._toa.get(revolution)
        if row is None:
            row = self._toa[revolution] = np.full((self.n_blades, self.n_probes), np.nan)
        self._seen.setdefault(revolution, set()).add(probe)
        row[:, probe] = toa
        self._newest[probe] = max(self._newest[probe], revolution)
        self._note_complete(revolution)

    def add(self, kind: str, decoded: codec.Decoded) -> None:
        """Add a decoded ``opr`` or ``toa`` message (other kinds are ignored)."""
        if kind == "opr":
            self.add_opr(decoded.header.revolution, decoded.body.opr_s)
        elif kind == "toa":
            self.add_toa(decoded.header.revolution, decoded.body.probe, decoded.body.toa_s)

    def _complete(self, revolution: int) -> bool:
        return revolution in self._opr and len(self._seen.get(revolution, ())) >= self.n_probes

    def _note_complete(self, revolution: int) -> None:
        if self._complete(revolution):
            self._max_complete = max(self._max_complete, revolution)

    def _passed(self, revolution: int) -> bool:
        """Has every source missing from ``revolution`` delivered a later revolution?"""
        # equivalently: every source not yet beyond it has delivered its part (the sources
        # behind are few, often the ones still sending it: the first such one decides)
        seen = self._seen.get(revolution, ())
        for src, newest in enumerate(self._newest):
            if newest <= revolution and not (revolution in self._opr if src == self.n_probes else src in seen):
                return False
        return True

    def _acceptable(self, revolution: int) -> bool:
        if revolution < 0 or (self.n_revolutions is not None and revolution >= self.n_revolutions):
            return False
        if self._last_out is None:
            return True
        return self._last_out < revolution <= self._last_out + self.max_ahead

    def next_opr(self, revolution: int) -> float | None:
        """The OPR time of ``revolution`` if it is the next one to be given out and its pulse
        is in (its TOAs may not be), else None."""
        nxt = 0 if self._last_out is None else self._last_out + 1
        return self._opr.get(int(revolution)) if int(revolution) == nxt else None

    @property
    def finished(self) -> bool:
        """Has the run's last revolution been given out (``n_revolutions`` known)?"""
        return self.n_revolutions is not None and self._last_out == self.n_revolutions - 1

    @property
    def pending(self) -> int:
        """Revolutions waiting (with an OPR pulse or TOAs)."""
        return len(set(self._opr) | set(self._toa))

    def pop(self, final: bool = False) -> list[Revolution]:
        """Revolutions ready now, in increasing order (``final``: everything left)."""
        out: list[Revolution] = []
        waiting = sorted(set(self._opr) | set(self._toa))  # nothing is added while popping
        for i, k in enumerate(waiting):
            has_opr = k in self._opr
            complete = self._complete(k)
            if not (complete or final or self._max_complete >= k + self.reorder
                    or len(waiting) - i > self.reorder or self._passed(k)):
                break
            toa = self._toa.pop(k, None)
            self._seen.pop(k, None)
            opr = self._opr.pop(k, None)
            self._last_out = k
            if not has_opr:
                self.dropped += 1
                continue
            if toa is None:
                toa = np.full((self.n_blades, self.n_probes), np.nan)
            out.append(Revolution(k, opr, toa, complete))
            self.given += 1
            self.given_complete += int(complete)
        return out

"""What a recorder may write: every bus message checked as the processor checks it, before it
goes into a recording's data channels.

The bus is untrusted (with security off anyone on the network may publish on a run's keys), and
a recording is the run's record: :class:`RecordGate` decides, message by message, whether a
received sample is written to its key's channel, is a duplicate, or is refused:

* it must decode (:func:`~bttsim_stream.bus.codec.decode_message`: sizes, shapes, finite
  values), carry the 16-byte attachment, and its header must agree with it (sequence number,
  log time);
* it must belong to the run whose metadata came (``run_id``, a probe the run has, a sequence
  number below the run's count on the acquisition keys, revolution = sequence number there,
  times not going back on a key);
* it must come from the session that published the run (the acquisition keys: a Zenoh session
  that sent the run's metadata; a result key: the session of its first valid message), known
  from the sample's timestamp, which carries the publishing session's id;
* a second payload for a sequence number already written is a *conflict* (the first one stays;
  compared over the last :data:`WINDOW` numbers of a key, older ones are duplicates); the
  same payload again is a duplicate.

Refused messages are counted per key and reason; the first :data:`KEEP_REJECTED` of each key
(at most :data:`KEEP_REJECTED_BYTES` in all) may be kept on a ``rejected/<key>`` channel, which
the readers of the data (``process``, ``export``, ``view``) never read. Samples that come before
their run's metadata wait (at most :data:`MAX_EARLY` of them, :data:`MAX_EARLY_BYTES` in all) and
are judged when it comes.

Completeness (:meth:`RecordGate.missing`): per key, the numbers written, kept as a bitmap (a
number filling a gap -- from a publisher's cache after a stall -- is written late, and the gap
closes); head, gaps and tail are counted against the run's known counts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


from ..errors import BttsimError
from . import codec
from . import keys as _keys
from .recording import REJECTED_PREFIX
from .stream import KeyMissing, acquisition_counts, missing_line

__all__ = ["RecordGate", "Verdict", "REJECTED_PREFIX", "WINDOW", "KEEP_REJECTED", "KEEP_REJECTED_BYTES",
           "MAX_EARLY"]

#: Sequence numbers per key whose payload digest is kept, to tell a conflict from a duplicate.
WINDOW = 4096
#: Refused messages kept per key on its ``rejected/`` channel (the rest only counted).
KEEP_REJECTED = 1000
#: Bytes of refused messages kept in all.
KEEP_REJECTED_BYTES = 16 << 20
#: Samples (and bytes) held while their run's metadata has not come.
MAX_EARLY = 100_000
MAX_EARLY_BYTES = 64 << 20
#: Largest jump of a result key's numbers believed (its count is not known).
MAX_JUMP = 1 << 16

_ACQUISITION = frozenset(("opr", "toa", "truth", "signal"))
_RESULTS = frozenset(("fit", "tw", "nsv", "resonance"))
_PROBE_KINDS = frozenset(("toa", "signal", "tw"))


@dataclass(frozen=True, slots=True)
class Verdict:
    """What to do with one sample.

    Attributes
    ----------
    action : str
        ``"write"`` (to its key's channel), ``"duplicate"`` (already written, same payload),
        ``"reject"`` (refused: ``reason``), ``"wait"`` (held until its run's metadata comes).
    key : str
    payload : bytes
    seq : int
        The message's sequence number (0 if unknown).
    log_time_ns : int
    reason : str
        Why it was refused ("" otherwise).
    meta : RunInfo or None
        For a run's first metadata: the decoded run metadata.
    keep : bool
        For a refused message: whether to keep a copy on its ``rejected/`` channel.
    decoded : Decoded or None
        For a message to write: the decoded message when the gate decodes (``decode=True``:
        a viewer shows it without decoding it again; else only for the types
        :func:`~bttsim_stream.bus.codec.check_message` decodes whole, None for the others).
    """

    action: str
    key: str
    payload: bytes = b""
    seq: int = 0
    log_time_ns: int = 0
    reason: str = ""
    meta: object = None
    keep: bool = False
    decoded: object = None


class _KeyState:
    """Per key: the numbers written (bitmap), their count and span, the last number's time
    and the digests of the last :data:`WINDOW` payloads."""

    __slots__ = ("bits", "count", "first", "last", "last_t", "win_seq", "win_hash", "source")

    def __init__(self) -> None:
        self.bits = bytearray()
        self.count = 0
        self.first = -1
        self.last = -1
        self.last_t = -1
        self.win_seq = [-1] * WINDOW  # lists: read and written an element at a time, from Python
        self.win_hash = [0] * WINDOW
        self.source: str | None = None

    def has(self, seq: int) -> bool:
        i = seq >> 3
        return i < len(self.bits) and bool(self.bits[i] & (1 << (seq & 7)))

    def add(self, seq: int, digest: int, t_ns: int) -> None:
        i = seq >> 3
        if i >= len(self.bits):
            self.bits.extend(bytes(max(i + 1 - len(self.bits), len(self.bits))))
        self.bits[i] |= 1 << (seq & 7)
        self.count += 1
        self.first = seq if self.first < 0 else min(self.first, seq)
        if seq > self.last:
            self.last, self.last_t = seq, t_ns
        self.win_seq[seq % WINDOW] = seq
        self.win_hash[seq % WINDOW] = digest

    def same(self, seq: int, digest: int) -> bool | None:
        """Is ``digest`` the written payload's (None: no longer known)?"""
        if self.win_seq[seq % WINDOW] != seq:
            return None
        return self.win_hash[seq % WINDOW] == digest


class _Run:
    """One rig's run: its metadata and the sessions that published it."""

    def __init__(self, info, payload_digest: int, source: str | None) -> None:
        self.info = info
        self.digest = payload_digest
        self.sources = {source}
        self.counts = acquisition_counts(info)


class RecordGate:
    """Judge every received sample before it is recorded (see the module docstring).

    Parameters
    ----------
    rig : str or None
        The rig recorded (None: any); another rig's messages are refused.
    decode : bool
        True: every message written is decoded whole, and its verdict carries it (a viewer
        shows it). False (a recorder, which writes payloads as they came): checked by
        :func:`~bttsim_stream.bus.codec.check_message` -- every check of the decoder, the
        same messages refused, without building the bodies it does not need.
    report : bool
        True (a receiver that follows the processor): each run's resonance report is
        expected too, one message numbered 0 on ``bttsim/<rig>/resonance``; a run without it
        is incomplete (the processor's last output never came).

    Attributes
    ----------
    rejected_by_key : dict
        ``{key: count}`` of refused messages.
    reasons : dict
        ``{reason: count}``.
    conflicts_by_key : dict
        ``{key: count}`` of second, different payloads for a number already written.
    duplicates : int
    kept_rejected : int
        Refused messages kept on ``rejected/`` channels.
    """

    def __init__(self, rig: str | None = None, *, decode: bool = False, report: bool = False) -> None:
        self.rig = rig
        self.decode = bool(decode)
        self.report = bool(report)
        self.runs: dict[str, _Run] = {}
        self._keys: dict[str, _KeyState] = {}
        self._early: list = []
        self._early_bytes = 0
        self._early_rigs: set[str] = set()
        self.rejected_by_key: dict[str, int] = {}
        self.reasons: dict[str, int] = {}
        self.conflicts_by_key: dict[str, int] = {}
        self.duplicates = 0
        #: Times a key's numbers jumped (a gap opened): the time to ask the publishers' caches.
        self.jumps = 0
        self.kept_rejected = 0
        self._kept_bytes = 0
        self._kept_by_key: dict[str, int] = {}
        self._last_log_ns = 0

    # -- judging -------------------------------------------------------------------------
    def admit(self, key: str, payload: bytes, att: tuple[int, int] | None, source: str | None = None) -> list:
        """Judge one sample; returns the verdicts to act on, in order (the sample's own, and
        for a run's metadata, those of the samples that waited for it)."""
        verdict = self._judge(key, payload, att, source)
        if verdict.action == "wait":
            if len(self._early) < MAX_EARLY and self._early_bytes + len(payload) <= MAX_EARLY_BYTES:
                self._early.append((key, payload, att, source))
                self._early_bytes += len(payload)
                self._early_rigs.add(key.split("/", 2)[1])
                return []
            verdict = self._reject(key, payload, att, "received before its run's metadata (too many waiting)")
        out = [verdict]
        if verdict.meta is not None and self._early:
            waiting, self._early, self._early_bytes = self._early, [], 0
            for item in waiting:
                out += self.admit(*item)
        return out

    @property
    def waiting_rigs(self) -> set[str]:
        """The rigs whose samples wait for their run's metadata (a receiver asks for it)."""
        return self._early_rigs - set(self.runs) if self._early else set()

    def finish(self) -> list:
        """Verdicts of the samples still waiting for a metadata that never came (refused)."""
        waiting, self._early, self._early_bytes = self._early, [], 0
        return [self._reject(k, p, a, "no run metadata received for its rig") for k, p, a, _ in waiting]

    def _judge(self, key: str, payload: bytes, att, source) -> Verdict:
        if att is None:
            return self._reject(key, payload, att, "no sequence-number attachment")
        try:
            info = _keys.parse_key(key)
        except BttsimError:
            return self._reject(key, payload, att, "not a key of the bus")
        if self.rig is not None and info.rig != self.rig:
            return self._reject(key, payload, att, "another rig")
        if info.message_type is None:
            return self._reject(key, payload, att, "not a data key")
        try:
            checked = codec.Checked.of(codec.decode_message(key, payload)) if self.decode or info.kind == "meta" \
                else codec.check_message(key, payload)
        except BttsimError:
            return self._reject(key, payload, att, "does not decode")
        seq, t_ns = int(att[0]), int(att[1])
        h = checked.header
        if h.seq != seq:
            return self._reject(key, payload, att, "header and attachment numbers differ")
        if codec.log_time_ns(h.t_s) != t_ns:
            return self._reject(key, payload, att, "header and attachment times differ")
        if info.kind == "meta":
            return self._meta(key, payload, att, checked.decoded, source)
        run = self.runs.get(info.rig)
        if run is None:
            return Verdict("wait", key)
        problem = self._problem(key, info, checked, seq, t_ns, run, source)
        if problem:
            return self._reject(key, payload, att, problem)
        return self._number(key, payload, att, seq, t_ns, source, checked.decoded, info.kind)

    def _problem(self, key: str, info, checked, seq: int, t_ns: int, run: _Run, source) -> str:
        """Why a checked message (:class:`~bttsim_stream.bus.codec.Checked`) does not fit its
        run ("" if it does)."""
        meta, h = run.info, checked.header
        if h.run_id != meta.run_id:
            return "another run"
        if info.kind in _PROBE_KINDS and not info.probe < meta.n_probes:
            return "a probe the run does not have"
        if info.kind in _ACQUISITION:
            if source not in run.sources:
                return "not from the session that published the run"
            if not (0 <= seq < meta.n_revolutions and h.revolution == seq):
                return "a revolution number outside the run"
            st = self._keys.get(key)
            if st is not None and seq > st.last and t_ns < st.last_t:
                return "time goes back"
        elif not -1 <= h.revolution < meta.n_revolutions:
            return "a revolution number outside the run"
        if info.kind in ("toa", "truth") and checked.n_blades != meta.n_blades:
            return "a blade count other than the run's"
        if info.kind == "opr" and not math.isfinite(checked.opr_s):
            return "an OPR time that is not finite"
        return ""

    def _meta(self, key: str, payload: bytes, att, decoded, source) -> Verdict:
        rig = decoded.body.rig
        if f"{_keys.PREFIX}/{rig}/meta" != key or att[0] != 0:
            return self._reject(key, payload, att, "metadata of another key")
        digest = hash(payload)
        run = self.runs.get(rig)
        if run is None:
            self.runs[rig] = _Run(decoded.body, digest, source)
            v = self._number(key, payload, att, 0, int(att[1]), source, decoded, "meta")
            return Verdict(v.action, key, payload, 0, v.log_time_ns, meta=decoded.body, decoded=decoded)
        if digest != run.digest:
            self.conflicts_by_key[key] = self.conflicts_by_key.get(key, 0) + 1
            return self._reject(key, payload, att, "a second, different run metadata")
        run.sources.add(source)  # the same metadata from another session: that one published it too
        self.duplicates += 1
        return Verdict("duplicate", key, payload, 0)

    def _number(self, key: str, payload: bytes, att, seq: int, t_ns: int, source, decoded, kind: str) -> Verdict:
        st = self._keys.get(key)
        if st is None:
            st = self._keys[key] = _KeyState()
        if kind in _RESULTS:
            if st.source is None and st.count == 0:
                st.source = source
            elif source != st.source:
                return self._reject(key, payload, att, "not from the session that published the key")
            if seq > max(st.last, 0) + MAX_JUMP:
                return self._reject(key, payload, att, "an implausible sequence number")
        digest = hash(payload)
        if st.has(seq):
            same = st.same(seq, digest)
            if same is False:
                self.conflicts_by_key[key] = self.conflicts_by_key.get(key, 0) + 1
                return self._reject(key, payload, att, "a second, different payload for a number")
            self.duplicates += 1
            return Verdict("duplicate", key, payload, seq)
        if seq > st.last + 1:
            self.jumps += 1  # numbers skipped (for now): a publisher's cache may still hold them
        st.add(seq, digest, t_ns)
        self._last_log_ns = max(self._last_log_ns, t_ns)
        return Verdict("write", key, payload, seq, t_ns, decoded=decoded)

    def _reject(self, key: str, payload: bytes, att, reason: str) -> Verdict:
        self.rejected_by_key[key] = self.rejected_by_key.get(key, 0) + 1
        self.reasons[reason] = self.reasons.get(reason, 0) + 1
        n = self._kept_by_key.get(key, 0)
        keep = n < KEEP_REJECTED and self._kept_bytes + len(payload) <= KEEP_REJECTED_BYTES and len(key) < 1024
        if keep:
            self._kept_by_key[key] = n + 1
            self._kept_bytes += len(payload)
            self.kept_rejected += 1
        seq = int(att[0]) if att is not None and 0 <= att[0] < 1 << 32 else 0
        # a refused message's own time is not believed: it is filed at the recording's latest time
        return Verdict("reject", key, payload, seq, self._last_log_ns, reason=reason, keep=keep)

    # -- results -------------------------------------------------------------------------
    @property
    def rejected(self) -> int:
        return sum(self.rejected_by_key.values())

    @property
    def conflicts(self) -> int:
        return sum(self.conflicts_by_key.values())

    def expected(self, report: bool = True) -> dict[str, int]:
        """``{key: n}`` of every key whose count a run's metadata fixes (and, with ``report``
        and the gate's :attr:`report`, the resonance report's: at least one)."""
        out: dict[str, int] = {}
        for rig, run in self.runs.items():
            out.update(run.counts)
            if self.report and report:
                out[_keys.resonance_key(rig)] = 1
        return out

    def missing(self, report: bool = True) -> dict[str, KeyMissing]:
        """Per key of a run that misses anything: numbers missing before the first one
        written (head), between (gaps) and after the last one, up to the key's known count
        (tail; a key with nothing written misses its whole count as head). ``report`` False:
        the processor's report is not counted before it came (it comes last, after the
        acquisition: while the run goes, its absence is no gap)."""
        expected = self.expected(report)
        out: dict[str, KeyMissing] = {}
        for key in sorted(set(self._keys) | set(expected)):
            if key.split("/")[1] not in self.runs:
                continue
            st, n = self._keys.get(key), expected.get(key)
            if st is None or st.count == 0:
                m = KeyMissing(head=int(n or 0), gaps=0, tail=0)
            else:
                tail = 0 if n is None else max(0, n - 1 - st.last)
                m = KeyMissing(head=st.first, gaps=st.last - st.first + 1 - st.count, tail=tail)
            if m.total:
                out[key] = m
        return out

    def completeness(self, rig: str | None = None) -> dict:
        """The completeness keys of a receiver's statistics: ``complete``, ``missing``,
        ``missing_by_key`` (``{key: {"head", "gaps", "tail"}}``), ``run_metadata`` (the rigs
        whose metadata came), ``foreign_keys`` (keys refused as of no run) and ``incomplete``
        (one line saying why, "" if complete). ``rig``: the rig whose metadata must have come
        (None: any one). Conflicts (a second, different payload for a number) make it
        incomplete: a forged message may have come first, in place of the real one."""
        missing = self.missing()
        why = []
        if not self.runs or (rig is not None and rig not in self.runs):
            why.append(f"no run metadata received{f' for {rig}' if rig else ''}")
        if missing:
            why.append(missing_line(missing))
        unreported = sorted(k.split("/")[1] for k in missing
                            if k.endswith("/resonance") and not getattr(self._keys.get(k), "count", 0))
        if unreported:
            why.append(f"no resonance report from the processor ({', '.join(unreported)})")
        if self.conflicts:
            why.append(f"{self.conflicts} conflicting message(s) (" + ", ".join(
                f"{k.split('/', 2)[-1]} {n}" for k, n in self.conflicts_by_key.items()) + ")")
        expected = self.expected()
        foreign = sorted(k for k in self.rejected_by_key if not self._of_a_run(k, expected))
        return {"complete": not why, "missing": sum(m.total for m in missing.values()),
                "missing_by_key": {k: m.to_dict() for k, m in missing.items()}, "run_metadata": sorted(self.runs),
                "foreign_keys": foreign[:100], "incomplete": "; ".join(why)}

    def _of_a_run(self, key: str, expected: dict[str, int]) -> bool:
        """Does ``key`` belong to a run whose metadata came (its rig; a probe's key only for a
        probe the run has)? A key of no run (a forger's ``toa/7`` of a 5-probe run) cannot make
        a recording incomplete: its numbers are counted under ``foreign_keys``, not as missing."""
        parts = key.split("/")
        if len(parts) < 3 or parts[1] not in self.runs:
            return False
        if len(parts) == 4 and parts[2] in _PROBE_KINDS:
            return f"{parts[0]}/{parts[1]}/toa/{parts[3]}" in expected
        return True

    def summary(self) -> dict:
        """Counts for the recorder's statistics (``messages``, ``keys``, ``gaps``,
        ``gaps_by_key``, ``duplicates_skipped``, ``late_start_keys``, ``rejected``,
        ``rejected_by_key``, ``rejected_reasons``, ``rejected_kept``, ``conflicts``,
        ``conflicts_by_key``)."""
        gaps = {k: st.last - st.first + 1 - st.count for k, st in self._keys.items()
                if st.count and st.last - st.first + 1 != st.count}
        return {"messages": sum(st.count for st in self._keys.values()),
                "keys": sum(1 for st in self._keys.values() if st.count),
                "gaps": sum(gaps.values()), "gaps_by_key": gaps, "duplicates_skipped": self.duplicates,
                "late_start_keys": {k: st.first for k, st in self._keys.items() if st.first > 0},
                "rejected": self.rejected, "rejected_by_key": dict(self.rejected_by_key),
                "rejected_reasons": dict(self.reasons), "rejected_kept": self.kept_rejected,
                "conflicts": self.conflicts, "conflicts_by_key": dict(self.conflicts_by_key)}

    def last_numbers(self) -> dict[str, int]:
        """``{key: last number written}``."""
        return {k: st.last for k, st in self._keys.items() if st.count}

"""Recordings as arrays, and the processor's messages for a recording that has none.

:func:`load_run` reads an MCAP run back into ``(revolution, blade, probe)`` arrays (used by
``bttsim process`` and ``bttsim view``): revolutions are regrouped as the bus's
:class:`~bttsim_stream.bus.stream.RevolutionAssembler` does at the end of a stream, straight
into preallocated arrays, and only complete revolutions (OPR and every probe's batch) are kept; truth comes back as a
:class:`~bttsim_stream.sim.core.Truth` when recorded.

:func:`processing_messages` feeds a recording to the processor node's own
:class:`~bttsim_stream.processor.ProcessorSession`, so ``bttsim view`` of a raw recording
shows what a live run would have shown.
"""

from __future__ import annotations

import math
from pathlib import Path
from dataclasses import dataclass, field, fields, replace

import numpy as np

from .bus import codec, keys
from .bus.recording import McapRecorder, RecordingScan
from .bus.stream import Completeness, Message, SequenceTracker
from .defaults import MAX_TIP_AMPLITUDE_FRACTION
from .errors import BttsimError
from .process.displacement import DoublePulses, assign_extra_edges, outside_revolution
from .process.history import ScratchRows
from .process.pipeline import ProcessOptions
from .processor import ProcessorSession
from .sim.records import RunInfo, Truth

__all__ = ["RecordedRun", "PROCESS_TRUTH_FIELDS", "load_run", "messages_of", "completeness", "result_warnings",
           "processing_messages", "with_processing", "check_times", "check_probes"]


@dataclass(frozen=True, slots=True, eq=False)
class RecordedRun:
    """A recorded run.

    Attributes
    ----------
    meta : RunInfo
        The run metadata.
    revolution : ndarray of int64, shape (n_rev,)
    opr_s : ndarray, shape (n_rev,)
    toa_s : ndarray or ScratchRows, shape (n_rev, n_blades, n_probes)
        (a :class:`~.process.history.ScratchRows` when read with ``scratch=True``)
    truth : Truth or None
        The simulator's truth of these revolutions, from the truth channel (the fields not
        asked for by :func:`load_run`'s ``truth_fields`` are None).
    messages : list of Message or None
        Every recorded message of the run's rig, in file order (None unless :func:`load_run` was asked to keep
        them: :func:`messages_of` streams them from ``path`` again).
    doubles : dict
        Double pulses of the recorded TOA batches (``double_pulses``, ``extra_edges``,
        ``stray_edges``; :class:`~bttsim_stream.process.displacement.DoublePulses`).
    extra_edges : dict of ndarray
        Every extra trigger edge of those batches, one row each: ``revolution``, ``probe``,
        ``blade`` (the window it falls in,
        :func:`~bttsim_stream.process.displacement.assign_extra_edges`; -1: in none) and
        ``toa_s``, sorted by revolution, probe and time.
    path : str
        The file read.
    lost, duplicates : int
        Acquisition messages missing or repeated by their sequence numbers.
    """

    meta: RunInfo
    revolution: np.ndarray
    opr_s: np.ndarray
    toa_s: np.ndarray
    truth: Truth | None
    messages: list | None
    doubles: dict = field(default_factory=lambda: DoublePulses().to_summary())
    extra_edges: dict = field(default_factory=lambda: _edge_rows([]))
    path: str = ""
    lost: int = 0
    duplicates: int = 0


#: The truth fields that ``bttsim process`` reads (E_A / E_f, the NSV scores, exact times).
PROCESS_TRUTH_FIELDS = ("opr_s", "t_exp_s", "d_eqv_pkpk_m", "omega_mean", "eo_engine_order", "eo_pkpk_m", "nsv_kind",
                        "nsv_freq_hz", "nsv_nd", "nsv_amp_pkpk_m", "nsv_rms_m", "nsv_band_hz")


class _TruthTable:
    """Per-revolution truth rows in preallocated arrays (the first message of a revolution
    holds, as in the recorder; a later one that differs in a kept field is counted in
    ``conflicts``); memory: the kept fields' arrays, no Python object per revolution."""

    def __init__(self, names, capacity: int, toa_tail: tuple) -> None:
        self.names = tuple(names)
        self.capacity = max(int(capacity), 16)
        self.toa_tail = tuple(toa_tail)
        self.index: dict[int, int] = {}
        self.n = 0
        self.tables: dict[str, np.ndarray] = {}
        self.tails: dict[str, tuple | None] = {}  # per field: (tail shape, dtype kind), None: absent
        self.bad: set[int] = set()  # revolutions whose latest truth is of another rotor or layout
        self.str_size: dict[str, int] = {}
        self.conflicts = 0
        self.first_conflict: int | None = None  # its revolution

    def _fits(self, tail: tuple, row: dict) -> bool:
        if tail != self.toa_tail:
            return False
        for name in self.names:
            a, spec = row[name], self.tails[name]
            if (a is None) != (spec is None) or (spec is not None and (a.shape != (1,) + spec[0]
                                                                     or a.dtype.kind != spec[1])):
                return False
        return True

    def add(self, revolution: int, tail: tuple, row: dict) -> None:
        """One revolution's truth: ``tail`` its ``(n_blades, n_probes)``, ``row`` the kept
        fields' arrays of shape ``(1, ...)`` (:func:`~bttsim_stream.bus.codec.truth_row`)."""
        if not self.tails and tail == self.toa_tail:
            for name in self.names:
                a = row[name]
                self.tails[name] = None if a is None else (a.shape[1:], a.dtype.kind)
                if a is not None:
                    self.tables[name] = np.empty((self.capacity,) + a.shape[1:],
                                                 dtype=object if a.dtype.kind == "U" else a.dtype)
                    self.str_size[name] = 0
        fits = bool(self.tails) and self._fits(tail, row)
        i = self.index.get(revolution)
        if i is not None:  # a copy: the first holds; one that differs (or is of another shape) conflicts
            if not fits or not all(np.array_equal(a[i], row[name][0], equal_nan=a.dtype.kind in "fc")
                                   for name, a in self.tables.items()):
                self.conflicts += 1
                self.first_conflict = revolution if self.first_conflict is None else self.first_conflict
            return
        if not fits:
            self.bad.add(revolution)
            return
        self.bad.discard(revolution)
        i = self.index[revolution] = self.n
        self.n += 1
        if self.n > self.capacity:
            self.capacity *= 2
            for name, a in self.tables.items():
                grown = np.empty((self.capacity,) + a.shape[1:], dtype=a.dtype)
                grown[: a.shape[0]] = a
                self.tables[name] = grown
        for name, a in self.tables.items():
            row_ = row[name]
            a[i] = row_[0]
            if row_.dtype.kind == "U":
                self.str_size[name] = max(self.str_size[name], row_.dtype.itemsize // 4)

    def rows(self, numbers: list, all_names) -> Truth | None:
        """The truth of revolutions ``numbers`` (None if one is missing or of another rotor)."""
        if any(r not in self.index or r in self.bad for r in numbers):
            return None
        idx = np.fromiter((self.index[r] for r in numbers), dtype=np.int64, count=len(numbers))
        contiguous = idx.size and idx[-1] - idx[0] == idx.size - 1 and bool(np.all(np.diff(idx) == 1))
        out = {}
        for name in all_names:
            a = self.tables.get(name)
            if a is None:
                out[name] = None
                continue
            a = a[idx[0]:idx[-1] + 1] if contiguous else a[idx]
            if a.dtype == object:
                a = a.astype(f"<U{max(self.str_size[name], 1)}")
            out[name] = a
        return Truth(**out)


#: Revolutions of TOAs a recording read into scratch files keeps in memory (the latest ones:
#: a revolution's batches come together; a late one is written into the file).
_WINDOW = 4096


class _Acquisition:
    """A recording's OPR pulses and TOA batches regrouped into revolutions, in preallocated
    arrays: the complete revolutions that ``RevolutionAssembler(n_blades, n_probes)``'s
    ``pop(final=True)`` gives (the same checks; the first of duplicates stays), with no Python
    object per revolution. Memory: one ``(n_rev, n_blades, n_probes)`` array, the OPR times
    and a dict of revolution numbers."""

    def __init__(self, n_blades: int, n_probes: int, capacity: int, scratch: bool = False) -> None:
        self.nb, self.npr = int(n_blades), int(n_probes)
        cap = max(int(capacity), 16)
        self.index: dict[int, int] = {}
        self.numbers = np.empty(cap, np.int64)
        self.opr = np.full(cap, np.nan)
        self.has_opr = np.zeros(cap, bool)
        # scratch: the TOAs of the latest rows in memory (rows _base ..), the older ones in a scratch file
        self.store = ScratchRows((self.nb, self.npr)) if scratch else None
        self._base = 0
        self.toa = np.full((min(cap, _WINDOW) if scratch else cap, self.nb, self.npr), np.nan)
        self.seen = np.zeros((cap, self.npr), bool)
        self.n = 0
        self.ignored = 0
        self.duplicates = 0
        #: Duplicates whose content differs from the first's, and the first of them (a description).
        self.conflicts = 0
        self.first_conflict = ""

    def _row(self, revolution: int) -> int:
        i = self.index.get(revolution)
        if i is None:
            if self.n == self.numbers.size:  # more revolutions than the metadata said: grow
                for name, fill in (("numbers", 0), ("opr", np.nan), ("has_opr", False), ("toa", np.nan),
                                   ("seen", False)):
                    if name == "toa" and self.store is not None:
                        continue
                    a = getattr(self, name)
                    grown = np.full((2 * a.shape[0],) + a.shape[1:], fill, dtype=a.dtype)
                    grown[: a.shape[0]] = a
                    setattr(self, name, grown)
            if self.store is not None and self.n - self._base == self.toa.shape[0]:
                self._spill(self.toa.shape[0] // 2)
            i = self.index[revolution] = self.n
            self.numbers[i] = revolution
            self.n += 1
        return i

    def add(self, kind: str, d) -> None:
        """A decoded ``opr`` or ``toa`` message (a :class:`~bttsim_stream.bus.codec.Decoded`;
        others are ignored): :meth:`add_opr` or :meth:`add_toa`."""
        if kind == "opr":
            self.add_opr(int(d.header.revolution), float(d.body.opr_s))
        elif kind == "toa":
            self.add_toa(int(d.header.revolution), int(d.body.probe), np.asarray(d.body.toa_s, dtype=float))

    def add_opr(self, rev: int, opr: float) -> None:
        """A decoded ``opr`` message: its revolution and pulse time
        (:func:`~bttsim_stream.bus.codec.opr_row`)."""
        if rev < 0 or not math.isfinite(opr):
            self.ignored += 1
            return
        i = self._row(rev)
        if self.has_opr[i]:
            self.duplicates += 1
            if self.opr[i] != opr:
                self._conflict(f"the OPR pulse of revolution {rev}")
            return
        self.opr[i], self.has_opr[i] = opr, True

    def add_toa(self, rev: int, probe: int, toa: np.ndarray) -> None:
        """A decoded ``toa`` message: its revolution, probe and TOAs
        (:func:`~bttsim_stream.bus.codec.toa_row`)."""
        if rev < 0 or not 0 <= probe < self.npr or toa.shape != (self.nb,):
            self.ignored += 1
            return
        i = self._row(rev)
        spilled = i < self._base  # a late batch of a row in the scratch file: read, changed, written back
        row = self.store[i] if spilled else self.toa[i - self._base]
        if self.seen[i, probe]:
            self.duplicates += 1
            if not np.array_equal(row[:, probe], toa, equal_nan=True):
                self._conflict(f"the TOAs of revolution {rev}, probe {probe}")
            return
        row[:, probe] = toa
        self.seen[i, probe] = True
        if spilled:
            self.store.patch(i, row)

    def _spill(self, m: int) -> None:
        """The oldest ``m`` rows in memory to the scratch file."""
        if m <= 0:
            return
        self.store.write(self.toa[:m])
        self.toa[:-m] = self.toa[m:]
        self.toa[-m:] = np.nan
        self._base += m

    def _conflict(self, what: str) -> None:
        self.conflicts += 1
        self.first_conflict = self.first_conflict or what

    def complete(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Revolution numbers, OPR times and TOAs of the complete revolutions, in order (the
        tables are handed over: call once). With ``scratch``, the TOAs are a
        :class:`~.process.history.ScratchRows`."""
        n = self.n
        rows = np.flatnonzero(self.has_opr[:n] & self.seen[:n].all(axis=1))
        rows = rows[np.argsort(self.numbers[rows], kind="stable")]
        if self.store is not None:
            self._spill(n - self._base)
            store, self.store, self.toa = self.store, None, None
            if rows.size < n or not np.array_equal(rows, np.arange(n)):  # a copy of the rows kept, in order
                kept = ScratchRows(store.tail)
                for a in range(0, rows.size, _WINDOW):
                    kept.write(store[rows[a:a + _WINDOW]])
                store.close()
                store = kept
            return self.numbers[rows], self.opr[rows], store
        if rows.size == n and np.array_equal(rows, np.arange(n)):  # as usual: in order, whole
            toa, self.toa = self.toa, None
            toa.resize((n, self.nb, self.npr), refcheck=False)  # in place: no second copy
            return self.numbers[:n].copy(), self.opr[:n].copy(), toa
        return self.numbers[rows], self.opr[rows], self.toa[rows]


def _capacity(path, meta) -> int:
    """Revolutions to preallocate for: the metadata's count, but no more than the file can
    hold (an untrusted count must not allocate beyond it: each revolution takes at least an
    OPR message and one per probe, some tens of bytes each)."""
    try:
        size = Path(path).stat().st_size
    except (OSError, TypeError, ValueError):
        size = 0
    return min(int(meta.n_revolutions or 0) + 1, size // (24 * (1 + int(meta.n_probes))) + 16)


def load_run(path, *, allow_truncated: bool = False, keep_messages: bool = False,
             truth_fields=None, rig: str | None = None, scratch: bool = False) -> RecordedRun:
    """Read and decode a recording; a corrupt, truncated, foreign or impossible file is a
    one-line error (:class:`BttsimError` naming the file).

    The file is read as a stream into arrays: memory is the run's arrays (TOAs, OPR times and
    the truth fields kept), not its messages.

    Parameters
    ----------
    path : str or Path
    allow_truncated : bool
        Read a recording without a footer up to its cut.
    keep_messages : bool
        Keep every message (:attr:`RecordedRun.messages`); else None.
    truth_fields : iterable of str, optional
        The :class:`~bttsim_stream.sim.core.Truth` fields to keep (default all; the others are
        None), e.g. :data:`PROCESS_TRUTH_FIELDS`.
    rig : str, optional
        The rig whose run is read (its ``bttsim/<rig>/...`` keys; the other rigs' messages are
        not decoded). Default: the recording's only rig; a recording of several rigs is then
        an error that names them.
    scratch : bool
        The TOAs and the truth's envelopes (``d_eqv_pkpk_m``, ``eo_pkpk_m``) in scratch files,
        not in memory (:class:`~.process.history.ScratchRows`, read by blocks of revolutions;
        ``close()`` deletes one): only the latest revolutions are held while reading.

    Notes
    -----
    Beyond the decoders' checks, the acquisition must make sense as a run: OPR times strictly
    increasing, and every TOA either NaN (no pulse) or a finite time within a revolution of
    its own OPR pulse (``[OPR_n - T_n, OPR_n + 2 T_n]``, ``T_n`` the revolution's period).
    """
    scan = RecordingScan(path)
    all_truth = tuple(f.name for f in fields(Truth))
    kept_truth = all_truth if truth_fields is None else tuple(n for n in all_truth if n in set(truth_fields))
    messages: list | None = [] if keep_messages else None
    n_messages = 0
    error: BttsimError | None = None  # a decoding error, raised after the truncation check
    meta = meta_key = meta_payload = None
    early: list = []  # acquisition before the run metadata (kept until it comes)
    asm = truth = None
    seqs = SequenceTracker()
    extras: dict = {}  # (revolution, probe) -> (toa_s, extra_toa_s) of the latest batch, when it has extras

    def take(kind: str, row: tuple) -> None:
        nonlocal truth
        if row[0] != meta.run_id:  # another run's message (the live receivers refuse it too)
            asm.ignored += 1
            return
        if kind == "truth":
            if truth is None:
                truth = _TruthTable(kept_truth, _capacity(path, meta), (meta.n_blades, meta.n_probes))
            truth.add(row[1], row[2], row[3])
        elif kind == "opr":
            asm.add_opr(row[1], row[2])
        else:
            _, rev, probe, toa, extra = row
            asm.add_toa(rev, probe, toa)
            if extra.size:  # once each: the latest batch of a (revolution, probe) holds
                extras[(rev, probe)] = (toa, extra)
            else:
                extras.pop((rev, probe), None)

    rigs: dict[str, None] = {}  # the rigs with run metadata, in file order
    want = rig  # the rig read: the one asked for, else the first with run metadata
    for m in scan:
        n_messages += 1
        if messages is not None:
            messages.append(m)
        try:
            info = keys.parse_key(m.key)
        except BttsimError as exc:
            error = error or exc
            continue
        if info.kind == "meta":
            rigs.setdefault(info.rig, None)
        if error is not None or (want is not None and info.rig != want):  # another rig's: not read
            continue
        kind = info.kind
        try:
            if kind in ("opr", "toa"):
                seqs.accept(m.key, m.seq)
            if kind == "meta" and meta is not None and m.key == meta_key and bytes(m.payload) != meta_payload:
                raise BttsimError(f"{m.key}: a second, different run metadata message (which run is it?)")
            if kind == "meta" and meta is None:
                meta = codec.decode_run_metadata(m.payload, m.key).body
                if meta.rig != info.rig:
                    raise BttsimError(f"{m.key}: the run metadata of rig {meta.rig!r} on another rig's key")
                want, meta_key, meta_payload = info.rig, m.key, bytes(m.payload)
                asm = _Acquisition(meta.n_blades, meta.n_probes, _capacity(path, meta), scratch=scratch)
                for r, *item in early:
                    if r == want:
                        take(*item)
                early = []
            elif kind in ("opr", "toa", "truth"):
                if kind == "toa":
                    row = codec.toa_row(m.payload, m.key)
                elif kind == "opr":
                    row = codec.opr_row(m.payload, m.key)
                else:
                    row = codec.truth_row(m.payload, m.key, fields=kept_truth)
                if meta is None:
                    early.append((info.rig, kind, row))
                else:
                    take(kind, row)
        except BttsimError as exc:
            error = exc
    _refuse_scan(path, scan.truncated and not allow_truncated, n_messages, rig, list(rigs), error, meta)
    _refuse_conflicts(path, asm, truth)
    numbers, opr_s, toa_s = _complete_revolutions(path, meta, asm)
    asm = None  # its tables are handed over
    tr = None if truth is None else _truth_of(truth.rows(numbers.tolist(), all_truth), scratch)
    truth = None  # its tables are handed over
    doubles, edges = _extra_edges(extras, numbers)
    if messages is not None:
        messages = list(keys.of_rig(messages, want))
    return RecordedRun(meta=meta, revolution=numbers, opr_s=opr_s, toa_s=toa_s, truth=tr, messages=messages,
                       doubles=doubles, extra_edges=edges, path=str(path),
                       lost=seqs.lost + seqs.missed_at_start, duplicates=seqs.duplicates)


def _refuse_conflicts(path, asm: _Acquisition, truth: _TruthTable | None) -> None:
    """A recording whose copies of a message differ: which one is the run? (A recorder writes
    the first of a number's payloads and refuses the others.)"""
    if asm.conflicts:
        raise BttsimError(f"{path}: {asm.conflicts} OPR/TOA message(s) differ from an earlier one of the same "
                          f"revolution (first: {asm.first_conflict}); which one is the acquisition?")
    if truth is not None and truth.conflicts:
        raise BttsimError(f"{path}: {truth.conflicts} truth message(s) differ from an earlier one of the same "
                          f"revolution (first: revolution {truth.first_conflict}); which one is the truth?")


def _truth_of(truth: Truth | None, scratch: bool) -> Truth | None:
    """The truth read, its run-sized envelopes in scratch files when ``scratch``."""
    if not scratch or truth is None:
        return truth
    return replace(truth, **{f: ScratchRows.of(getattr(truth, f)) for f in ("d_eqv_pkpk_m", "eo_pkpk_m")
                             if getattr(truth, f) is not None})


def _refuse_scan(path, truncated: bool, n_messages: int, rig: str | None, rigs: list, error, meta) -> None:
    """The one-line errors of a recording's scan, in this order: cut short (no footer), the
    runs of several rigs and none asked for, a message that did not decode, no run metadata
    (of the rig asked for)."""
    if truncated:
        raise BttsimError(f"{path}: truncated MCAP (no footer; {n_messages} messages readable)")
    if rig is None and len(rigs) > 1:
        raise BttsimError(f"{path}: the recording holds the runs of {len(rigs)} rigs ({', '.join(rigs)}): "
                          f"choose one with --rig")
    if error is not None:
        raise BttsimError(f"{path}: {error}") from None
    if meta is None and rig is not None:
        raise BttsimError(f"{path}: no run metadata of rig {rig!r} in the recording"
                          + (f" (its rigs: {', '.join(rigs)})" if rigs else ""))
    if meta is None:
        raise BttsimError(f"{path}: no run metadata ({keys.PREFIX}/<rig>/meta) in the recording")


def _complete_revolutions(path, meta: RunInfo, asm: _Acquisition) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The numbers, OPR times and TOAs of the acquisition's complete revolutions (its tables
    handed over), checked as a run: three at least, within the metadata's count, none
    missing between them, times that make sense (:func:`check_times`)."""
    ignored = asm.ignored
    numbers, opr_s, toa_s = asm.complete()
    if numbers.size < 3:
        why = (f" ({ignored} OPR/TOA message(s) ignored: a blade count other than the metadata's "
               f"{meta.n_blades}, a probe index beyond {meta.n_probes - 1}, a revolution out of range, a "
               f"non-finite OPR time or another run's id)" if ignored else "")
        raise BttsimError(f"{path}: fewer than 3 complete revolutions recorded{why}")
    if meta.n_revolutions and numbers[-1] >= meta.n_revolutions:
        raise BttsimError(f"{path}: revolution {int(numbers[-1])} recorded, but the run metadata says the run has "
                          f"{meta.n_revolutions} revolution(s)")
    if np.any(np.diff(numbers) != 1):
        missing = int(numbers[-1] - numbers[0] + 1 - numbers.size)
        raise BttsimError(f"{path}: {missing} revolution(s) missing in the recording")
    check_times(path, numbers, opr_s, toa_s)
    return numbers, opr_s, toa_s


def _extra_edges(extras: dict, numbers: np.ndarray) -> tuple[dict, dict]:
    """The double-pulse summary and the extra-edge rows of the latest TOA batches with extra
    edges (``(revolution, probe) -> (toa_s, extra_toa_s)``) of revolutions ``numbers``."""
    doubles = DoublePulses()
    rows = []
    for (rev, probe), (toa, extra) in sorted(extras.items()):
        if numbers[0] <= rev <= numbers[-1]:
            doubles.add(toa, extra)
            rows.append((rev, probe, assign_extra_edges(toa, extra), extra))
    return doubles.to_summary(), _edge_rows(rows)


def messages_of(run: RecordedRun):
    """The messages of the run's rig in file order: :attr:`RecordedRun.messages` if kept, else
    streamed from the file again (a truncated file up to its cut)."""
    if run.messages is not None:
        return iter(run.messages)
    return keys.of_rig(RecordingScan(run.path), run.meta.rig)


def _edge_rows(rows: list) -> dict:
    """The columns of :attr:`RecordedRun.extra_edges` from ``(revolution, probe, blade, toa_s)``
    groups (one per TOA batch)."""
    n = [r[3].size for r in rows]
    return {"revolution": np.repeat(np.array([r[0] for r in rows], np.int64), n),
            "probe": np.repeat(np.array([r[1] for r in rows], np.int64), n),
            "blade": np.concatenate([np.asarray(r[2], np.int64) for r in rows] or [np.zeros(0, np.int64)]),
            "toa_s": np.concatenate([np.asarray(r[3], float) for r in rows] or [np.zeros(0)])}


_CHECK_BLOCK = 4096  # revolutions per block of the time checks


def toa_blocks(toa_s):
    """The TOAs (an array or a :class:`~.process.history.ScratchRows`) by blocks of
    :data:`_CHECK_BLOCK` revolutions, each an array."""
    for lo in range(0, toa_s.shape[0], _CHECK_BLOCK):
        yield toa_s[lo:lo + _CHECK_BLOCK]


def missing_toas(toa_s) -> int:
    """NaN TOAs (pulses that did not trigger), counted by blocks."""
    return sum(int(np.count_nonzero(np.isnan(block))) for block in toa_blocks(toa_s))


def check_times(path, revolution: np.ndarray, opr_s: np.ndarray, toa_s) -> None:
    """OPR times strictly increasing; TOAs NaN or finite within a revolution of their OPR
    (:func:`~.process.displacement.outside_revolution`). ``toa_s``: shape (n_rev, n_blades,
    n_probes), or anything whose ``shape[0]`` is that and whose slices of revolutions are
    such arrays (a recording's tables read in blocks).

    Raises
    ------
    BttsimError
        Naming ``path``, the first offending revolution and the count.
    """
    period = np.diff(opr_s)
    bad = np.flatnonzero(~(period > 0))
    if bad.size:
        i = int(bad[0])
        raise BttsimError(f"{path}: OPR times must increase: revolution {int(revolution[i + 1])} at "
                          f"{float(opr_s[i + 1])!r} s after revolution {int(revolution[i])} at {float(opr_s[i])!r} s")
    if not np.isfinite(opr_s).all():
        raise BttsimError(f"{path}: OPR times must be finite")
    period = np.append(period, period[-1])[:, None, None]
    first, count = None, 0
    for lo, block in zip(range(0, toa_s.shape[0], _CHECK_BLOCK), toa_blocks(toa_s)):  # no run-sized temporaries
        hi = lo + block.shape[0]
        wrong = outside_revolution(block, opr_s[lo:hi, None, None], period[lo:hi])
        if wrong.any():
            count += int(wrong.sum())
            if first is None:
                n, b, p = (int(x[0]) for x in np.nonzero(wrong))
                first = (n + lo, b, p, float(block[n, b, p]))
    if first is not None:
        n, b, p, t = first
        raise BttsimError(f"{path}: {count} TOA(s) not within a revolution of their OPR pulse (first: "
                          f"revolution {int(revolution[n])}, blade {b}, probe {p}: {t!r} s, OPR at "
                          f"{float(opr_s[n])!r} s)")


def check_probes(path, run: RecordedRun, options: ProcessOptions) -> list[str]:
    """A probe that holds no TOA in the whole recording leaves the others to separate the
    engine orders (each, and jointly when several are fitted together): if they cannot, the
    run cannot be processed (a :class:`BttsimError` naming the file and the empty probes),
    rather than fitted to NaN and reported as showing no resonance. Returns the notes (which
    probes are empty) when the others can."""
    from .process.displacement import Geometry
    from .process.options import engine_orders_of, fits_jointly, layout_condition_numbers

    present = np.zeros(run.toa_s.shape[2], bool)
    for block in toa_blocks(run.toa_s):  # by blocks: the TOAs may be a scratch file's
        present |= np.isfinite(block).any(axis=(0, 1))
    if present.all():
        return []
    if not present.any():
        raise BttsimError(f"{path}: no probe holds a TOA in the whole recording")
    empty = ", ".join(str(j) for j in np.flatnonzero(~present))
    geometry = Geometry.from_info(run.meta)
    left = replace(geometry, probe_angles_rad=geometry.probe_angles_rad[present])
    scan = options.eo_range is not None
    eos = tuple(range(options.eo_range[0], options.eo_range[1] + 1)) if scan else engine_orders_of(run.meta, options)
    try:
        kept, _, _ = layout_condition_numbers(eos, left, scan)
    except ValueError as exc:  # LayoutError
        raise BttsimError(f"{path}: probe(s) {empty} hold no TOA in the whole recording; {exc}") from None
    if not scan and len(eos) > 1 and fits_jointly(eos, geometry) and not fits_jointly(eos, left):
        raise BttsimError(f"{path}: probe(s) {empty} hold no TOA in the whole recording: the probes left cannot fit "
                          f"EO {'+'.join(map(str, eos))} jointly; give one engine order (--eo)")
    if scan and len(kept) < len(eos):
        raise BttsimError(f"{path}: probe(s) {empty} hold no TOA in the whole recording: the probes left cannot "
                          f"separate EO {', '.join(str(e) for e in eos if e not in kept)}; narrow --eo-range")
    return [f"probe(s) {empty} hold no TOA in the whole recording: the others are fitted"]


def completeness(run: RecordedRun) -> Completeness:
    """What of the run the recording holds: complete revolutions against the run metadata's
    count, acquisition messages missing or repeated by their sequence numbers."""
    return Completeness(revolutions_expected=run.meta.n_revolutions, revolutions_processed=int(run.revolution.size),
                        lost=run.lost, duplicates=run.duplicates)


_OTHER_COLUMNS = ("amp_std_m", "truth_amp_pkpk_m", "truth_freq_hz", "E_A_pct", "E_f_pct")
_MEAN_COLUMNS = ("mean_E_A_pct", "max_E_A_pct", "mean_E_f_pct", "max_E_f_pct")


def result_warnings(summary: dict, tip_radius_m: float) -> list[str]:
    """What a reader of the summary must not miss: a NaN where a resonance or dwell claims an
    amplitude or a frequency (or in its uncertainty, truth and errors), and an amplitude beyond
    the linear model's reach
    (:data:`~bttsim_stream.defaults.MAX_TIP_AMPLITUDE_FRACTION` of the tip radius)."""
    out = []
    limit = 2.0 * MAX_TIP_AMPLITUDE_FRACTION * float(tip_radius_m)  # pk-pk
    for e in [*summary.get("resonances", []), *summary.get("steady", [])]:
        label = f"the {'dwell' if e.get('kind') == 'dwell' else 'resonance'} at EO {e.get('eo')}"
        rows = e.get("blades", [])
        nan = [r["blade"] for r in rows
               if not (np.isfinite(r.get("amp_pkpk_m", np.nan)) and np.isfinite(r.get("freq_hz", np.nan)))]
        if nan:
            out.append(f"{label}: no estimate (NaN) for {len(nan)} of {len(rows)} blade(s) "
                       f"({', '.join(map(str, nan[:10]))}{' ...' if len(nan) > 10 else ''}): treat them as unmeasured")
        other = sorted({k for r in rows if r["blade"] not in nan for k in _OTHER_COLUMNS
                        if k in r and not np.isfinite(r[k])}
                       | {k for k in _MEAN_COLUMNS if k in e and not np.isfinite(e[k])})
        if other:
            out.append(f"{label}: NaN in {', '.join(other)} (an uncertainty, or the recording's truth, unusable there)")
        big = [r["blade"] for r in rows if np.isfinite(r.get("amp_pkpk_m", np.nan)) and r["amp_pkpk_m"] > limit]
        if big:
            out.append(f"{label}: amplitude above {2 * MAX_TIP_AMPLITUDE_FRACTION:.0%} of the tip radius pk-pk "
                       f"({limit * 1e3:.3g} mm) for {len(big)} blade(s): physically absurd for this linear model")
    return out


def processing_messages(run: RecordedRun, options: ProcessOptions = ProcessOptions()) -> tuple[list[Message], dict]:
    """The processor node's messages for a recorded run, and the summary dict.

    The recording's acquisition (and truth) messages go through the processor node's own
    :class:`~bttsim_stream.processor.ProcessorSession`, in file order with their sequence
    numbers, so the result is what the processor would have published live.
    """
    session = ProcessorSession(run.meta, options)
    msgs: list[Message] = []
    for m in messages_of(run):
        kind = keys.parse_key(m.key).kind
        if kind in ("opr", "toa", "truth"):
            msgs += session.add(kind, m.key, session.decode(kind, m.key, m.payload), m.seq)
    tail, summary = session.finish()
    return msgs + tail, summary


def with_processing(path, out_path, *, allow_truncated: bool = False, meta: RunInfo | None = None) -> str:
    """``path`` if the recording holds the processor's messages of the run's rig, else a copy
    of that rig's messages at ``out_path`` with them added, each message of the processor node's own
    :class:`~bttsim_stream.processor.ProcessorSession` (the messages of
    :func:`processing_messages`) right after the one that made it, as a live run records them.

    Read and written as a stream: memory does not grow with the recording (beyond the
    processor session's own state). ``meta``: the run metadata of the recording already read
    (:func:`load_run`), else it is read (and checked as a run) here."""
    if meta is None:
        meta = load_run(path, allow_truncated=allow_truncated, truth_fields=()).meta
    if any(keys.parse_key(m.key).kind == "fit" for m in keys.of_rig(RecordingScan(path), meta.rig)):
        return str(path)
    session = ProcessorSession(meta, ProcessOptions())
    with McapRecorder(out_path) as rec:
        batch: list[Message] = []
        for m in keys.of_rig(RecordingScan(path), meta.rig):  # the run's rig only
            if keys.is_status_key(m.key):  # a node's state then, not data: nothing shows it
                continue
            batch.append(m)
            kind = keys.parse_key(m.key).kind
            if kind in ("opr", "toa", "truth"):
                batch += session.add(kind, m.key, session.decode(kind, m.key, m.payload), m.seq)
            if len(batch) >= 4096:
                rec.write_all(batch)
                batch = []
        rec.write_all(batch + session.finish()[0])
    return str(out_path)

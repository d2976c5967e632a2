"""Recordings as arrays, and the processor's messages for a recording that has none.

:func:`load_run` reads an MCAP run back into ``(revolution, blade, probe)`` arrays (used by
``bttsim process`` and ``bttsim view``): revolutions are regrouped by the bus's
:class:`~bttsim_stream.bus.stream.RevolutionAssembler`, and only complete revolutions (OPR
and every probe's batch) are kept; truth comes back as a
:class:`~bttsim_stream.sim.core.Truth` when recorded.

:func:`processing_messages` feeds a recording to the processor node's own
:class:`~bttsim_stream.processor.ProcessorSession`, so ``bttsim view`` of a raw recording
shows what a live run would have shown.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field, fields

import numpy as np

from .bus import codec, keys
from .bus.recording import McapRecorder, read_recording
from .bus.stream import Completeness, Message, RevolutionAssembler, SequenceTracker
from .defaults import MAX_TIP_AMPLITUDE_FRACTION
from .errors import BttsimError
from .process.displacement import DoublePulses, assign_extra_edges
from .process.pipeline import METHODS, ProcessOptions
from .process.probes import check_engine_orders
from .processor import ProcessorSession
from .sim.core import RunInfo, Truth

__all__ = ["RecordedRun", "load_run", "completeness", "result_warnings", "processing_messages", "with_processing",
           "add_processing_arguments", "processing_options", "parse_engine_orders"]


def add_processing_arguments(p: argparse.ArgumentParser) -> None:
    """The processing flags shared by ``bttsim process`` and the processor node."""
    p.add_argument("--method", choices=METHODS, default="peak",
                   help="resonance method: peak (per-revolution sine-fit peak, the paper's), sdof (swept "
                        "single-degree-of-freedom fit of amplitude and phase: frequency, damping, amplitude, "
                        "sweep-corrected) or cff (circumferential Fourier fit over a few revolutions)")
    p.add_argument("--eo", metavar="EO[,EO...]", help="engine orders to fit (default: the run metadata's)")
    p.add_argument("--eo-range", metavar="LO-HI",
                   help="engine order unknown: scan LO..HI for resonance crossings (each order fitted on its own)")
    p.add_argument("--no-prep", action="store_true", help="no data preparation")
    p.add_argument("--window", type=int, default=1, metavar="N", help="revolutions per sine fit (1)")


def processing_options(args: argparse.Namespace, **extra) -> ProcessOptions:
    """:class:`ProcessOptions` from the flags of :func:`add_processing_arguments` (``extra``:
    further options); a bad value is a :class:`BttsimError`."""
    eos = parse_engine_orders(args.eo) if getattr(args, "eo", None) else None
    eo_range = _eo_range(args.eo_range) if getattr(args, "eo_range", None) else None
    try:
        return ProcessOptions(prep=not args.no_prep, window=args.window, method=args.method, engine_orders=eos,
                              eo_range=eo_range, **extra)
    except ValueError as exc:
        raise BttsimError(str(exc)) from None


def _eo_range(text: str) -> tuple:
    parts = str(text).replace(":", "-").split("-")
    try:
        lo, hi = (int(x) for x in parts)
    except ValueError:
        raise BttsimError(f"--eo-range must be LO-HI (whole numbers), got {text!r}") from None
    if lo < 1 or hi < lo:
        raise BttsimError(f"--eo-range must satisfy 1 <= LO <= HI, got {text!r}")
    return lo, hi


def parse_engine_orders(text: str) -> tuple:
    """``--eo 8`` or ``--eo 8,9``: the engine orders, checked (:class:`BttsimError` otherwise)."""
    try:
        vals = [int(x) for x in str(text).split(",") if x.strip()]
    except ValueError:
        raise BttsimError(f"--eo must be comma-separated whole numbers, got {text!r}") from None
    return check_engine_orders(vals)


@dataclass(frozen=True, slots=True, eq=False)
class RecordedRun:
    """A recorded run.

    Attributes
    ----------
    meta : RunInfo
        The run metadata.
    revolution : ndarray of int64, shape (n_rev,)
    opr_s : ndarray, shape (n_rev,)
    toa_s : ndarray, shape (n_rev, n_blades, n_probes)
    truth : Truth or None
        The simulator's truth of these revolutions, from the truth channel.
    messages : list of Message
        Every recorded message, in file order.
    doubles : dict
        Double pulses of the recorded TOA batches (``double_pulses``, ``extra_edges``,
        ``stray_edges``; :class:`~bttsim_stream.process.displacement.DoublePulses`).
    extra_edges : dict of ndarray
        Every extra trigger edge of those batches, one row each: ``revolution``, ``probe``,
        ``blade`` (the window it falls in,
        :func:`~bttsim_stream.process.displacement.assign_extra_edges`; -1: in none) and
        ``toa_s``, sorted by revolution, probe and time.
    """

    meta: RunInfo
    revolution: np.ndarray
    opr_s: np.ndarray
    toa_s: np.ndarray
    truth: Truth | None
    messages: list
    doubles: dict = field(default_factory=lambda: DoublePulses().to_summary())
    extra_edges: dict = field(default_factory=lambda: _edge_rows([]))


def load_run(path, *, allow_truncated: bool = False) -> RecordedRun:
    """Read and decode a recording; a corrupt, truncated, foreign or impossible file is a
    one-line error (:class:`BttsimError` naming the file).

    Beyond the decoders' checks, the acquisition must make sense as a run: OPR times strictly
    increasing, and every TOA either NaN (no pulse) or a finite time within a revolution of
    its own OPR pulse (``[OPR_n - T_n, OPR_n + 2 T_n]``, ``T_n`` the revolution's period).
    """
    rec = read_recording(path)
    if rec.truncated and not allow_truncated:
        raise BttsimError(f"{path}: truncated MCAP (no footer; {len(rec.messages)} messages readable)")
    meta = None
    decoded: list[tuple[str, codec.Decoded]] = []
    truth: dict[int, Truth] = {}
    try:
        for m in rec.messages:
            kind = keys.parse_key(m.key).kind
            if kind == "meta" and meta is None:
                meta = codec.decode_run_metadata(m.payload, m.key).body
            elif kind in ("opr", "toa"):
                decoded.append((kind, codec.decode_message(m.key, m.payload)))
            elif kind == "truth":
                t = codec.decode_truth(m.payload, m.key)
                truth[t.header.revolution] = t.body
    except BttsimError as exc:
        raise BttsimError(f"{path}: {exc}") from None
    if meta is None:
        raise BttsimError(f"{path}: no run metadata ({keys.PREFIX}/<rig>/meta) in the recording")
    asm = RevolutionAssembler(meta.n_blades, meta.n_probes)
    for kind, d in decoded:
        asm.add(kind, d)
    revs = [r for r in asm.pop(final=True) if r.complete]
    if len(revs) < 3:
        why = (f" ({asm.ignored} OPR/TOA message(s) ignored: a blade count other than the metadata's "
               f"{meta.n_blades}, a probe index beyond {meta.n_probes - 1}, a revolution out of range or a "
               f"non-finite OPR time)" if asm.ignored else "")
        raise BttsimError(f"{path}: fewer than 3 complete revolutions recorded{why}")
    numbers = np.array([r.revolution for r in revs], dtype=np.int64)
    if meta.n_revolutions and numbers[-1] >= meta.n_revolutions:
        raise BttsimError(f"{path}: revolution {int(numbers[-1])} recorded, but the run metadata says the run has "
                          f"{meta.n_revolutions} revolution(s)")
    if np.any(np.diff(numbers) != 1):
        missing = int(numbers[-1] - numbers[0] + 1 - numbers.size)
        raise BttsimError(f"{path}: {missing} revolution(s) missing in the recording")
    opr_s = np.array([r.opr_s for r in revs])
    toa_s = np.stack([r.toa_s for r in revs])
    _check_times(path, numbers, opr_s, toa_s)
    tr = None
    if truth and all(r in truth for r in numbers.tolist()):
        rows = [truth[r] for r in numbers.tolist()]
        if all(t.toa_s.shape[1:] == toa_s.shape[1:] for t in rows):  # truth of another rotor: left out
            tr = Truth(**{f.name: np.concatenate([getattr(t, f.name) for t in rows]) for f in fields(Truth)})
    doubles = DoublePulses()
    rows = []
    batches = {(d.header.revolution, d.body.probe): d.body for kind, d in decoded if kind == "toa"}  # once each
    for (rev, probe), b in sorted(batches.items()):
        if b.extra_toa_s.size and numbers[0] <= rev <= numbers[-1]:
            doubles.add(b.toa_s, b.extra_toa_s)
            rows.append((rev, probe, assign_extra_edges(b.toa_s, b.extra_toa_s), b.extra_toa_s))
    return RecordedRun(meta=meta, revolution=numbers, opr_s=opr_s, toa_s=toa_s, truth=tr, messages=rec.messages,
                       doubles=doubles.to_summary(), extra_edges=_edge_rows(rows))


def _edge_rows(rows: list) -> dict:
    """The columns of :attr:`RecordedRun.extra_edges` from ``(revolution, probe, blade, toa_s)``
    groups (one per TOA batch)."""
    n = [r[3].size for r in rows]
    return {"revolution": np.repeat(np.array([r[0] for r in rows], np.int64), n),
            "probe": np.repeat(np.array([r[1] for r in rows], np.int64), n),
            "blade": np.concatenate([np.asarray(r[2], np.int64) for r in rows] or [np.zeros(0, np.int64)]),
            "toa_s": np.concatenate([np.asarray(r[3], float) for r in rows] or [np.zeros(0)])}


def _check_times(path, revolution: np.ndarray, opr_s: np.ndarray, toa_s: np.ndarray) -> None:
    """OPR times strictly increasing; TOAs NaN or finite within a revolution of their OPR."""
    period = np.diff(opr_s)
    bad = np.flatnonzero(~(period > 0))
    if bad.size:
        i = int(bad[0])
        raise BttsimError(f"{path}: OPR times must increase: revolution {int(revolution[i + 1])} at "
                          f"{float(opr_s[i + 1])!r} s after revolution {int(revolution[i])} at {float(opr_s[i])!r} s")
    if not np.isfinite(period).all():
        raise BttsimError(f"{path}: OPR times must be finite")
    period = np.append(period, period[-1])[:, None, None]
    rel = toa_s - opr_s[:, None, None]
    with np.errstate(invalid="ignore"):
        wrong = ~np.isnan(toa_s) & ~((rel >= -period) & (rel <= 2.0 * period))
    if wrong.any():
        n, b, p = (int(x[0]) for x in np.nonzero(wrong))
        raise BttsimError(f"{path}: {int(wrong.sum())} TOA(s) not within a revolution of their OPR pulse (first: "
                          f"revolution {int(revolution[n])}, blade {b}, probe {p}: {float(toa_s[n, b, p])!r} s, OPR at "
                          f"{float(opr_s[n])!r} s)")


def completeness(run: RecordedRun) -> Completeness:
    """What of the run the recording holds: complete revolutions against the run metadata's
    count, acquisition messages missing or repeated by their sequence numbers."""
    seqs = SequenceTracker()
    for m in run.messages:
        if keys.parse_key(m.key).kind in ("opr", "toa"):
            seqs.accept(m.key, m.seq)
    return Completeness(revolutions_expected=run.meta.n_revolutions, revolutions_processed=int(run.revolution.size),
                        lost=seqs.lost + seqs.missed_at_start, duplicates=seqs.duplicates)


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
    for m in run.messages:
        kind = keys.parse_key(m.key).kind
        if kind in ("opr", "toa", "truth"):
            msgs += session.add(kind, m.key, codec.decode_message(m.key, m.payload), m.seq)
    tail, summary = session.finish()
    return msgs + tail, summary


def with_processing(path, out_path, *, allow_truncated: bool = False) -> str:
    """``path`` if the recording holds the processor's messages, else a copy at ``out_path``
    with them added (:func:`processing_messages`)."""
    run = load_run(path, allow_truncated=allow_truncated)
    if any(keys.parse_key(m.key).kind == "fit" for m in run.messages):
        return str(path)
    msgs, _ = processing_messages(run)
    with McapRecorder(out_path) as rec:
        rec.write_all(run.messages)
        rec.write_all(msgs)
    return str(out_path)

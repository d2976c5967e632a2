"""Protobuf encoding and decoding of the processing's outputs: per-revolution blade fits
(``bttsim.v1.BladeFits``), travelling waves (``bttsim.v1.TravellingWave``), resonance
reports (``bttsim.v1.ResonanceReport``) and non-synchronous vibration
(``bttsim.v1.NonSynchronous``). Conventions as in :mod:`.codec` (which re-exports these).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from ..defaults import MAX_BLADES, MAX_REVOLUTIONS
from ..process.results import RevolutionFit
from ..process.resonance import (STATUSES, Detection, ResonanceEntry, ResonancePeaks, ResonanceReport,
                                TruthPeaks)
from ..process.nsv import NsvDetection
from ..process.travelling_wave import ProbeWave
from ._gen.bttsim.v1 import bttsim_pb2 as _pb
from .codec_base import (Decoded, Header, as_array, check_len, check_probe_key, corrupt_error,
                         fill_header, header_of, parse_payload, serialize, as_vector)


__all__ = ["encode_fit", "check_fit", "decode_fit", "encode_probe_wave", "check_probe_wave", "decode_probe_wave",
           "encode_resonance_report", "decode_resonance_report", "encode_nsv", "decode_nsv"]

_FIT_ARRAYS = (("amp_pkpk_m", "amp_pkpk_m"), ("phase_rad", "phase_rad"), ("dc_m", "dc_m"),
               ("residual_m", "residual_rms_m"), ("amp_std_m", "amp_std_m"))  # (proto, dataclass)


# --------------------------------------------------------------------------------------
# Processing outputs
# --------------------------------------------------------------------------------------


def encode_fit(header: Header, fit: RevolutionFit) -> bytes:
    """Encode one revolution's fits at one EO (:class:`bttsim.v1.BladeFits`, key ``fit``)."""
    amp = as_vector(fit.amp_pkpk_m, "amp_pkpk_m")
    nb = amp.size
    m = _pb.BladeFits()
    fill_header(m.header, header.run_id, header.seq, header.revolution, header.t_s)
    m.n_blades = nb
    m.engine_order = int(fit.engine_order)
    m.omega_mean_rad_s = float(fit.omega_rad_s)
    m.freq_hz = float(fit.freq_hz)
    m.cn = float(fit.cn)
    for proto_name, name in _FIT_ARRAYS:
        getattr(m, proto_name).extend(as_vector(getattr(fit, name), name, nb).tolist())
    return serialize(m)


def check_fit(payload: bytes, key: str | None = None):
    """Every check of :func:`decode_fit` (the same :class:`~bttsim_stream.errors.BttsimError`
    for the same payloads), without building the fit: returns the parsed ``BladeFits``."""
    m, where = parse_payload(_pb.BladeFits, payload, key)
    nb = int(m.n_blades)
    for proto_name, _ in _FIT_ARRAYS:
        check_len(where, m, proto_name, nb, f"({nb},)")
    return m


def decode_fit(payload: bytes, key: str | None = None) -> Decoded:
    """Decode a :class:`bttsim.v1.BladeFits` payload into ``(Header, RevolutionFit)``.

    Raises
    ------
    BttsimError
        Unparsable or oversized payload, missing header, or inconsistent array lengths.
    """
    m = check_fit(payload, key)
    fit = RevolutionFit(engine_order=int(m.engine_order), omega_rad_s=m.omega_mean_rad_s, freq_hz=m.freq_hz,
                        cn=m.cn, **{name: as_array(getattr(m, proto_name)) for proto_name, name in _FIT_ARRAYS})
    return Decoded(header_of(m.header), fit)


def encode_probe_wave(header: Header, wave: ProbeWave) -> bytes:
    """Encode one probe's travelling-wave spectrum (:class:`bttsim.v1.TravellingWave`, key ``tw/<probe>``)."""
    fwd = as_vector(wave.forward_m, "forward_m")
    bwd = as_vector(wave.backward_m, "backward_m", fwd.size)
    if fwd.size == 0:
        raise ValueError("forward_m: at least one nodal diameter is needed")
    m = _pb.TravellingWave()
    fill_header(m.header, header.run_id, header.seq, header.revolution, header.t_s)
    m.probe = int(wave.probe)
    m.n_nd = fwd.size
    m.forward_m.extend(fwd.tolist())
    m.backward_m.extend(bwd.tolist())
    m.dominant_nd = int(wave.nd)
    return serialize(m)


_NEGATIVE = (0.0).__gt__


def _bad_magnitude(values) -> bool:
    """Is one of a repeated field's values negative or infinite (NaN, not measured, is
    neither)? Iterated in C over the field, no array made."""
    return any(map(_NEGATIVE, values)) or math.inf in values


def _check_magnitudes(where: str, msg, *fields: str) -> None:
    """Magnitudes: >= 0 or NaN (not measured); never infinite or negative."""
    for field in fields:
        if _bad_magnitude(getattr(msg, field)):
            raise corrupt_error(where, msg, f"{field} must be >= 0 and finite (NaN: missing)")


def check_probe_wave(payload: bytes, key: str | None = None):
    """Every check of :func:`decode_probe_wave` (the same
    :class:`~bttsim_stream.errors.BttsimError` for the same payloads), without building the
    wave: returns the parsed ``TravellingWave``."""
    m, where = parse_payload(_pb.TravellingWave, payload, key)
    n = int(m.n_nd)
    if n > MAX_BLADES // 2 + 1:
        raise corrupt_error(where, m, f"n_nd = {n} (at most {MAX_BLADES // 2 + 1}, for {MAX_BLADES} blades)")
    check_len(where, m, "forward_m", n, f"({n},)")
    check_len(where, m, "backward_m", n, f"({n},)")
    _check_magnitudes(where, m, "forward_m", "backward_m")
    if abs(m.dominant_nd) >= max(n, 1):
        raise corrupt_error(where, m, f"dominant_nd = {m.dominant_nd} with n_nd = {n}")
    check_probe_key(where, m, key, "tw")
    return m


def decode_probe_wave(payload: bytes, key: str | None = None) -> Decoded:
    """Decode a :class:`bttsim.v1.TravellingWave` payload into ``(Header, ProbeWave)``.

    Raises
    ------
    BttsimError
        Unparsable or oversized payload, missing header, inconsistent array lengths, a
        magnitude below 0 or infinite, a dominant ND beyond ``n_nd`` or another probe's key.
    """
    m = check_probe_wave(payload, key)
    return Decoded(header_of(m.header), ProbeWave(probe=int(m.probe), forward_m=as_array(m.forward_m),
                                                backward_m=as_array(m.backward_m),
                                                nd=int(m.dominant_nd)))


_EXTENDED = ("phase_rad", "amp_std_m", "freq_std_hz", "damping_ratio", "steady_amp_pkpk_m", "natural_freq_hz")


#: (dataclass field, (proto lo, proto hi)) of the 95 % intervals.
_CI95 = (("amp_ci95_m", ("amp_ci95_lo_m", "amp_ci95_hi_m")), ("freq_ci95_hz", ("freq_ci95_lo_hz", "freq_ci95_hi_hz")),
         ("phase_ci95_rad", ("phase_ci95_lo_rad", "phase_ci95_hi_rad")))


def _fill_blades(rows, peaks: ResonancePeaks, truth: TruthPeaks | None, e_a, e_f, *, extended: bool) -> None:
    nan = np.full(peaks.n_blades, np.nan)
    for b in range(peaks.n_blades):
        row = rows.add()
        row.blade = b
        row.amp_pkpk_m = float(peaks.amp_pkpk_m[b])
        row.freq_hz = float(peaks.freq_hz[b])
        if truth is not None:
            row.truth_amp_pkpk_m = float(truth.amp_pkpk_m[b])
            row.truth_freq_hz = float(truth.freq_hz[b])
            row.e_a_pct = float(e_a[b])
            row.e_f_pct = float(e_f[b])
            row.has_truth = True
        if extended:
            for name in _EXTENDED:
                arr = getattr(peaks, name)
                setattr(row, name, float((nan if arr is None or np.size(arr) != peaks.n_blades else arr)[b]))
            row.revolution = float(peaks.revolution[b])
            row.has_extended = True
        cis = [getattr(peaks, name) for name, _ in _CI95]
        if all(c is not None and np.shape(c) == (peaks.n_blades, 2) for c in cis):
            for (_name, (lo, hi)), c in zip(_CI95, cis):
                setattr(row, lo, float(c[b, 0]))
                setattr(row, hi, float(c[b, 1]))
            row.has_ci95 = True
        if peaks.crb_amp_m is not None and np.size(peaks.crb_amp_m) == peaks.n_blades:
            row.crb_amp_m = float(peaks.crb_amp_m[b])
            crb_f = peaks.crb_freq_hz
            row.crb_freq_hz = float((nan if crb_f is None or np.size(crb_f) != peaks.n_blades else crb_f)[b])
            row.has_crb = True


def _fill_stats(m, e_a, e_f) -> None:
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        m.mean_e_a_pct, m.max_e_a_pct = float(np.nanmean(e_a)), float(np.nanmax(e_a))
        m.mean_e_f_pct, m.max_e_f_pct = float(np.nanmean(e_f)), float(np.nanmax(e_f))


def _fill_entry(m, e: ResonanceEntry) -> None:
    m.kind, m.eo, m.nd, m.cn, m.method = e.kind, int(e.eo), int(e.nd), float(e.cn), e.method
    m.rpm, m.freq_hz, m.damping_ratio = float(e.rpm), float(e.freq_hz), float(e.damping_ratio)
    d = e.detection
    m.detection_statistic, m.detection_value, m.detection_threshold = d.statistic, float(d.value), float(d.threshold)
    m.detection_snr, m.detection_snr_threshold = float(d.snr), float(d.snr_threshold)
    m.first_revolution, m.last_revolution = int(e.first_revolution), int(e.last_revolution)
    m.peak_revolution, m.sweep_rate = int(e.peak_revolution), float(e.sweep_rate)
    m.zeroing_correction_pct = 100.0 * float(e.zeroing_correction)
    m.notes.extend(str(n) for n in e.notes)
    _fill_blades(m.blades, e.peaks, e.truth, e.e_a_pct, e.e_f_pct, extended=True)
    if e.truth is not None and e.peaks.n_blades:
        _fill_stats(m, e.e_a_pct, e.e_f_pct)


def encode_resonance_report(header: Header, report: ResonanceReport) -> bytes:
    """Encode a resonance report (:class:`bttsim.v1.ResonanceReport`, key ``resonance``).

    Blades are numbered 0..n_blades-1; truth fields (and the error statistics) are set when
    the report carries the truth. The status, every resonance and dwell entry (with its own
    blade table, detection statistic and revolutions), the zeroing reference and the notes
    travel too (fields 10-18).
    """
    m = _pb.ResonanceReport()
    fill_header(m.header, header.run_id, header.seq, header.revolution, header.t_s)
    m.nd = int(report.nd)
    m.eo = int(report.eo)
    m.cn = float(report.cn)
    _fill_blades(m.blades, report.peaks, report.truth, report.e_a_pct, report.e_f_pct, extended=False)
    if report.truth is not None and report.peaks.n_blades:
        _fill_stats(m, report.e_a_pct, report.e_f_pct)
    m.status = report.status
    for e in report.resonances:
        _fill_entry(m.resonances.add(), e)
    for e in report.steady:
        _fill_entry(m.steady.add(), e)
    ref = report.reference
    if ref is not None:
        m.reference_method = str(ref.get("method") or "")
        m.reference_first = -1 if ref.get("first") is None else int(ref["first"])
        m.reference_last = -1 if ref.get("last") is None else int(ref["last"])
        c = ref.get("contamination_pct")
        m.reference_contamination_pct = math.nan if c is None else float(c)
        m.reference_reason = str(ref.get("reason") or "")
    m.notes.extend(str(n) for n in report.notes)
    for n in report.non_synchronous:
        _fill_nsv_detection(m.non_synchronous.add(), n)
    return serialize(m)


def _fill_nsv_detection(m, n: NsvDetection) -> None:
    m.first_revolution, m.last_revolution = int(n.first_revolution), int(n.last_revolution)
    m.order, m.alias_per_rev, m.nd = float(n.order), float(n.alias), int(n.nd)
    m.order_alternatives.extend(float(a) for a in n.order_alternatives)
    m.nd_alternatives.extend(int(a) for a in n.nd_alternatives)
    m.freq_hz, m.freq_min_hz, m.freq_max_hz = float(n.freq_hz), float(n.freq_min_hz), float(n.freq_max_hz)
    m.amp_pkpk_m, m.amp_first_pkpk_m = float(n.amp_pkpk_m), float(n.amp_first_pkpk_m)
    m.amp_last_pkpk_m = float(n.amp_last_pkpk_m)
    m.ratio, m.ratio_threshold, m.coherence = float(n.ratio), float(n.ratio_threshold), float(n.coherence)
    m.blocks = int(n.blocks)
    m.forward_m.extend(np.asarray(n.forward_m, float).tolist())
    m.backward_m.extend(np.asarray(n.backward_m, float).tolist())
    rev_amp = np.asarray(n.rev_amp_pkpk_m, float)
    if rev_amp.size == int(n.last_revolution) - int(n.first_revolution) + 1:
        m.rev_amp_pkpk_m.extend(rev_amp.tolist())
    if n.truth is not None:
        m.has_truth = True
        if n.truth.get("kind") is not None:
            t = n.truth
            m.truth_kind, m.truth_freq_hz, m.truth_nd = str(t["kind"]), float(t["freq_hz"]), int(t["nd"])
            m.truth_amp_pkpk_m, m.truth_amp_last_pkpk_m = float(t["amp_pkpk_m"]), float(t["amp_last_pkpk_m"])


def encode_nsv(header: Header, nsv: NsvDetection) -> bytes:
    """Encode a non-synchronous vibration (:class:`bttsim.v1.NonSynchronous`, key ``nsv``)."""
    m = _pb.NonSynchronous()
    fill_header(m.header, header.run_id, header.seq, header.revolution, header.t_s)
    _fill_nsv_detection(m, nsv)
    return serialize(m)


def _decode_nsv_body(where: str, m, n) -> NsvDetection:
    """One ``NonSynchronous`` body, checked: sizes against the blade limit, values in range."""
    n_nd = len(n.forward_m)
    if len(n.backward_m) != n_nd or n_nd > MAX_BLADES // 2 + 1:
        raise corrupt_error(where, m,
                            f"non-synchronous spectrum of {n_nd} forward and {len(n.backward_m)} backward NDs")
    if len(n.order_alternatives) != len(n.nd_alternatives) or len(n.order_alternatives) > 2 * MAX_BLADES + 4:
        raise corrupt_error(where, m, "non-synchronous order alternatives and their NDs differ in number (or too many)")
    if not (0 <= n.first_revolution <= n.last_revolution <= MAX_REVOLUTIONS):
        raise corrupt_error(where, m, f"non-synchronous revolutions {n.first_revolution}-{n.last_revolution}")
    if not (math.isfinite(n.order) and 0.0 < n.order <= MAX_BLADES + 1 and 0.0 <= n.alias_per_rev <= 0.5):
        raise corrupt_error(where, m, f"non-synchronous order {n.order!r} / alias {n.alias_per_rev!r}")
    if abs(n.nd) > MAX_BLADES // 2 or any(abs(a) > MAX_BLADES // 2 for a in n.nd_alternatives):
        raise corrupt_error(where, m, f"non-synchronous ND {n.nd}")
    if not (math.isfinite(n.amp_pkpk_m) and n.amp_pkpk_m >= 0.0):
        raise corrupt_error(where, m, f"non-synchronous amplitude {n.amp_pkpk_m!r}")
    n_rev = int(n.last_revolution) - int(n.first_revolution) + 1
    if len(n.rev_amp_pkpk_m) not in (0, n_rev):
        raise corrupt_error(where, m, f"{len(n.rev_amp_pkpk_m)} per-revolution amplitudes for revolutions "
                                 f"{n.first_revolution}-{n.last_revolution}")
    rev_amp = as_array(n.rev_amp_pkpk_m)
    truth = None
    if n.has_truth:
        if n.truth_kind not in ("", "rotating_stall", "flutter", "broadband") or abs(n.truth_nd) > MAX_BLADES // 2:
            raise corrupt_error(where, m, f"non-synchronous truth {n.truth_kind[:40]!r}, ND {n.truth_nd}")
        truth = {"kind": None} if not n.truth_kind else {
            "kind": n.truth_kind, "freq_hz": float(n.truth_freq_hz), "nd": int(n.truth_nd),
            "amp_pkpk_m": float(n.truth_amp_pkpk_m), "amp_last_pkpk_m": float(n.truth_amp_last_pkpk_m)}
    return NsvDetection(
        first_revolution=int(n.first_revolution), last_revolution=int(n.last_revolution), order=float(n.order),
        order_alternatives=tuple(float(a) for a in n.order_alternatives),
        nd_alternatives=tuple(int(a) for a in n.nd_alternatives), alias=float(n.alias_per_rev),
        freq_hz=float(n.freq_hz), freq_min_hz=float(n.freq_min_hz), freq_max_hz=float(n.freq_max_hz), nd=int(n.nd),
        amp_pkpk_m=float(n.amp_pkpk_m), amp_first_pkpk_m=float(n.amp_first_pkpk_m),
        amp_last_pkpk_m=float(n.amp_last_pkpk_m), ratio=float(n.ratio),
        ratio_threshold=float(n.ratio_threshold), coherence=float(n.coherence), blocks=int(n.blocks),
        forward_m=as_array(n.forward_m), backward_m=as_array(n.backward_m), rev_amp_pkpk_m=rev_amp,
        revolutions=np.arange(n.first_revolution, n.first_revolution + rev_amp.size, dtype=np.int64), truth=truth)


def decode_nsv(payload: bytes, key: str | None = None) -> Decoded:
    """Decode a :class:`bttsim.v1.NonSynchronous` payload into ``(Header, NsvDetection)``.

    Raises
    ------
    BttsimError
        Unparsable or oversized payload, missing header, spectra longer than the largest
        wheel's ND count, order / alias / ND / revolutions out of range.
    """
    m, where = parse_payload(_pb.NonSynchronous, payload, key)
    return Decoded(header_of(m.header), _decode_nsv_body(where, m, m))


def _decode_blades(where: str, m, rows, *, extended: bool):
    nb = len(rows)
    if [b.blade for b in rows] != list(range(nb)):
        raise corrupt_error(where, m, "blades must be numbered 0..n_blades-1 in order")
    has_truth = [bool(b.has_truth) for b in rows]
    if any(has_truth) and not all(has_truth):
        raise corrupt_error(where, m, "truth on some blades only")
    nan = np.full(nb, np.nan)
    kw = {}
    rev = nan
    method = "reported"
    if extended and nb:
        if not all(b.has_extended for b in rows):
            raise corrupt_error(where, m, "an entry's blade rows lack their extended fields")
        kw = {name: as_array([getattr(b, name) for b in rows]) for name in _EXTENDED}
        rev = as_array([b.revolution for b in rows])
    if nb and all(b.has_ci95 for b in rows):  # older writers: no intervals (None)
        for name, (lo, hi) in _CI95:
            kw[name] = np.stack([as_array([getattr(b, lo) for b in rows]), as_array([getattr(b, hi) for b in rows])], 1)
    if nb and all(b.has_crb for b in rows):  # older writers: no bounds (None)
        kw["crb_amp_m"] = as_array([b.crb_amp_m for b in rows])
        kw["crb_freq_hz"] = as_array([b.crb_freq_hz for b in rows])
    peaks = ResonancePeaks(revolution=rev, amp_pkpk_m=as_array([b.amp_pkpk_m for b in rows]),
                           freq_hz=as_array([b.freq_hz for b in rows]),
                           damping_ratio=kw.pop("damping_ratio", nan.copy()), method=method, **kw)
    truth = e_a = e_f = None
    if nb and all(has_truth):
        truth = TruthPeaks(revolution=np.full(nb, -1, np.int64),
                           amp_pkpk_m=as_array([b.truth_amp_pkpk_m for b in rows]),
                           freq_hz=as_array([b.truth_freq_hz for b in rows]))
        e_a = as_array([b.e_a_pct for b in rows])
        e_f = as_array([b.e_f_pct for b in rows])
    return peaks, truth, e_a, e_f


def _decode_entry(where: str, m, e) -> ResonanceEntry:
    if e.kind not in ("crossing", "dwell"):
        raise corrupt_error(where, m, f"entry kind {e.kind!r}")
    peaks, truth, e_a, e_f = _decode_blades(where, m, e.blades, extended=True)
    peaks = replace(peaks, method=e.method)
    return ResonanceEntry(
        kind=e.kind, eo=int(e.eo), nd=int(e.nd), cn=float(e.cn), method=e.method, rpm=float(e.rpm),
        freq_hz=float(e.freq_hz), damping_ratio=float(e.damping_ratio),
        detection=Detection(e.detection_statistic, float(e.detection_value), float(e.detection_threshold),
                            float(e.detection_snr), float(e.detection_snr_threshold)),
        first_revolution=int(e.first_revolution), last_revolution=int(e.last_revolution),
        peak_revolution=int(e.peak_revolution), peaks=peaks, truth=truth, e_a_pct=e_a, e_f_pct=e_f,
        sweep_rate=float(e.sweep_rate), zeroing_correction=float(e.zeroing_correction_pct) / 100.0,
        notes=tuple(e.notes))


def decode_resonance_report(payload: bytes, key: str | None = None) -> Decoded:
    """Decode a :class:`bttsim.v1.ResonanceReport` payload into ``(Header, ResonanceReport)``.

    The legacy per-blade peak revolutions and damping ratios do not travel: they come back
    NaN (truth peak revolutions -1), with ``peaks.method == "reported"``; the entries'
    blade rows carry theirs. A report from an older writer has ``status == ""`` and no
    entries.

    Raises
    ------
    BttsimError
        Unparsable or oversized payload, missing header, blades out of order, truth on
        only some blades, an unknown status or entry kind.
    """
    m, where = parse_payload(_pb.ResonanceReport, payload, key)
    if m.status not in ("",) + STATUSES:
        raise corrupt_error(where, m, f"status {m.status!r}")
    peaks, truth, e_a, e_f = _decode_blades(where, m, m.blades, extended=False)
    ref = None
    if m.reference_method:
        c = float(m.reference_contamination_pct)
        ref = {"method": m.reference_method, "first": None if m.reference_first < 0 else int(m.reference_first),
               "last": None if m.reference_last < 0 else int(m.reference_last),
               "contamination_pct": c if math.isfinite(c) else None, "reason": m.reference_reason}
    report = ResonanceReport(nd=int(m.nd), eo=int(m.eo), cn=m.cn, peaks=peaks, truth=truth,
                             e_a_pct=e_a, e_f_pct=e_f, status=m.status,
                             resonances=tuple(_decode_entry(where, m, e) for e in m.resonances),
                             steady=tuple(_decode_entry(where, m, e) for e in m.steady),
                             reference=ref, notes=tuple(m.notes),
                             non_synchronous=tuple(_decode_nsv_body(where, m, n) for n in m.non_synchronous))
    return Decoded(header_of(m.header), report)

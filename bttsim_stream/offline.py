"""Recordings as arrays: an MCAP run back into (revolution, blade, probe) arrays.

Used by ``bttsim process`` and ``bttsim view``. Only complete revolutions (OPR and every
probe's batch) are kept; truth comes back as a ``Truth``-like object when recorded.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import BttsimError
from .io import codec, keys
from .io.mcap_io import read_recording
from .sim.core import Truth

__all__ = ["RecordedRun", "load_run", "processed_messages", "with_processing"]


@dataclass(frozen=True, slots=True, eq=False)
class RecordedRun:
    """A recorded run.

    Attributes
    ----------
    meta : RunMetadataMsg
    revolution : ndarray of int64, shape (n_rev,)
    opr_s : ndarray, shape (n_rev,)
    toa_s : ndarray, shape (n_rev, n_blades, n_probes)
    truth : Truth or None
        The simulator's :class:`~bttsim_stream.sim.core.Truth`, rebuilt from the truth channel.
    messages : list
        Every recorded message (key, payload, log_time_ns, sequence).
    """

    meta: object
    revolution: np.ndarray
    opr_s: np.ndarray
    toa_s: np.ndarray
    truth: Truth | None
    messages: list


def load_run(path, *, allow_truncated: bool = False) -> RecordedRun:
    """Read and decode a recording; a corrupt, truncated or foreign file is a one-line error."""
    rec = read_recording(path)
    if rec.truncated and not allow_truncated:
        raise BttsimError(f"{path}: truncated MCAP (no footer; {len(rec.messages)} messages readable)")
    meta = None
    opr: dict[int, float] = {}
    toa: dict[int, dict[int, np.ndarray]] = {}
    truth: dict[int, object] = {}
    for m in rec.messages:
        kind = keys.parse_key(m.key).kind
        if kind == "meta" and meta is None:
            meta = codec.decode_run_metadata(m.payload, m.key)
        elif kind == "opr":
            o = codec.decode_opr(m.payload, m.key)
            opr[o.header.revolution] = o.opr_s
        elif kind == "toa":
            t = codec.decode_toa_batch(m.payload, m.key)
            toa.setdefault(t.header.revolution, {})[t.probe] = t.toa_s
        elif kind == "truth":
            tb = codec.decode_truth_batch(m.payload, m.key)
            truth[tb.header.revolution] = tb
    if meta is None:
        raise BttsimError(f"{path}: no run metadata ({keys.PREFIX}/<rig>/meta) in the recording")
    n_p = meta.n_probes
    revs = np.array(sorted(r for r in opr if r in toa and len(toa[r]) == n_p), dtype=np.int64)
    if revs.size < 3:
        raise BttsimError(f"{path}: fewer than 3 complete revolutions recorded")
    if np.any(np.diff(revs) != 1):
        missing = int(revs[-1] - revs[0] + 1 - revs.size)
        raise BttsimError(f"{path}: {missing} revolution(s) missing in the recording")
    toa_arr = np.stack([np.stack([toa[r][p] for p in range(n_p)], axis=1) for r in revs])
    tr = None
    if truth and all(r in truth for r in revs):
        rows = [truth[r] for r in revs]
        tr = Truth(
            opr_s=np.array([t.opr_s for t in rows]), omega_mean=np.array([t.omega_mean_rad_s for t in rows]),
            **{f: np.stack([getattr(t, f) for t in rows]) for f in
               ("toa_s", "t_exp_s", "d_eqv_m", "d_tang_m", "d_z_m", "d_eq1_m", "d_eqv_pkpk_m")})
    return RecordedRun(meta=meta, revolution=revs, opr_s=np.array([opr[r] for r in revs]),
                       toa_s=toa_arr, truth=tr, messages=rec.messages)


def processed_messages(run: RecordedRun, result) -> list:
    """Encode an offline :class:`~bttsim_stream.process.pipeline.ProcessingResult` as the
    processor node would publish it (fits and travelling waves per revolution, the report)."""
    meta = run.meta
    rig, run_id, seqs = meta.rig, meta.run_id, {}
    fit, tw = result.fit, result.probe_tw
    eo = int(result.engine_orders[0])
    omega = result.displacements.omega_rad_s
    out = []
    for i, rev in enumerate(run.revolution.tolist()):
        t = float(run.opr_s[i])
        out.append(codec.encode_blade_fits(
            run_id=run_id, rig=rig, seqs=seqs, revolution=rev, t_s=t, engine_order=eo,
            omega_mean_rad_s=float(omega[i]), cn=fit.cn, amp_pkpk_m=fit.amp_pkpk_m[i, :, 0],
            phase_rad=fit.phase_rad[i, :, 0], dc_m=fit.dc_m[i], residual_m=fit.residual_rms_m[i],
            amp_std_m=fit.amp_std_m[i, :, 0]))
        nd = int(result.fit_tw.dominant_nd[i])  # from the fits: no per-probe image ambiguity
        for p in range(tw.forward_m.shape[1]):
            out.append(codec.encode_travelling_wave(
                run_id=run_id, rig=rig, seqs=seqs, revolution=rev, t_s=t, probe=p,
                forward_m=tw.forward_m[i, p], backward_m=tw.backward_m[i, p], dominant_nd=nd))
    out.append(codec.encode_resonance_report(result.summary, run_id=run_id, rig=rig, seqs=seqs))
    return out


def with_processing(path, out_path, *, allow_truncated: bool = False) -> str:
    """Copy a recording to ``out_path``, adding the processor's messages if it has none."""
    from .io.mcap_io import McapRecorder
    from .process.pipeline import ProcessOptions, process_arrays

    run = load_run(path, allow_truncated=allow_truncated)
    kinds = {keys.parse_key(m.key).kind for m in run.messages}
    if "fit" in kinds:
        return str(path)
    result = process_arrays(run.opr_s, run.toa_s, run.meta, ProcessOptions(), truth=run.truth)
    with McapRecorder(out_path) as rec:
        for m in run.messages:
            rec.write(m.key, m.payload, m.log_time_ns, sequence=m.sequence)
        seq: dict[str, int] = {}
        for e in processed_messages(run, result):
            rec.write(e.key, e.payload, e.log_time_ns, sequence=seq.get(e.key, 0))
            seq[e.key] = seq.get(e.key, 0) + 1
    return str(out_path)

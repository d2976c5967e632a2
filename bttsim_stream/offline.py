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

__all__ = ["RecordedRun", "RecordedTruth", "load_run"]


@dataclass(frozen=True, slots=True, eq=False)
class RecordedTruth:
    """Truth arrays of a recording (same fields as the simulator's ``Truth``)."""

    opr_s: np.ndarray
    omega_mean: np.ndarray
    toa_s: np.ndarray
    t_exp_s: np.ndarray
    d_eqv_m: np.ndarray
    d_tang_m: np.ndarray
    d_z_m: np.ndarray
    d_eq1_m: np.ndarray
    d_eqv_pkpk_m: np.ndarray


@dataclass(frozen=True, slots=True, eq=False)
class RecordedRun:
    """A recorded run.

    Attributes
    ----------
    meta : RunMetadataMsg
    revolution : ndarray of int64, shape (n_rev,)
    opr_s : ndarray, shape (n_rev,)
    toa_s : ndarray, shape (n_rev, n_blades, n_probes)
    truth : RecordedTruth or None
    messages : list
        Every recorded message (key, payload, log_time_ns, sequence).
    """

    meta: object
    revolution: np.ndarray
    opr_s: np.ndarray
    toa_s: np.ndarray
    truth: RecordedTruth | None
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
        tr = RecordedTruth(
            opr_s=np.array([t.opr_s for t in rows]), omega_mean=np.array([t.omega_mean_rad_s for t in rows]),
            **{f: np.stack([getattr(t, f) for t in rows]) for f in
               ("toa_s", "t_exp_s", "d_eqv_m", "d_tang_m", "d_z_m", "d_eq1_m", "d_eqv_pkpk_m")})
    return RecordedRun(meta=meta, revolution=revs, opr_s=np.array([opr[r] for r in revs]),
                       toa_s=toa_arr, truth=tr, messages=rec.messages)

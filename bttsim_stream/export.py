"""Tidy tables of a recorded run (``bttsim export``): CSV or Parquet, readable with no project code.

One file per table, one row per observation, one column per variable; units in the column
names (``_s``, ``_m``, ``_rad``, ``_hz``, ``_rad_s``, ``_pct``), revolutions numbered as in the
run, blades and probes 0-based. The tables (documented in ``schemas/export.md``):

========================  ================================================================
``opr``                   revolution, opr_s
``toa``                   revolution, blade, probe, toa_s (the acquisition's TOAs)
``extra_edge``            revolution, probe, blade, toa_s (double pulses' later edges; when any)
``displacement``          revolution, blade, probe, d_m, t_exp_s (Eq. 1, offline processing)
``fit``                   revolution, blade, engine_order, amp_pkpk_m, phase_rad, ... (Eq. 16-17)
``tw``                    revolution, nd, forward_m, backward_m (from the fits, first EO)
``tw_probe``              revolution, probe, nd, forward_m, backward_m (per probe, first EO)
``resonance``             entry, kind, eo, nd, rpm, ..., blade, amp_pkpk_m, freq_hz, E_A_pct, ...
``truth``                 revolution, blade, probe, toa_s, t_exp_s, d_eqv_m, ... (when recorded)
``truth_revolution``      revolution, blade, opr_s, omega_mean_rad_s, d_eqv_pkpk_m (when recorded)
``truth_eo``              revolution, blade, eo, eo_pkpk_m (each engine order's own response;
                          when recorded)
``truth_nsv``             revolution, component, nsv_kind, nsv_freq_hz, nsv_nd, ... (non-synchronous
                          vibration in the truth; when any)
========================  ================================================================

plus ``run.json``: the run metadata, the processing summary (the brief's summary JSON), and
for every table its file, row count and per-column unit, dtype and meaning.

Displacements, fits, spectra and the resonance table come from the offline processing of the
recording (exactly ``bttsim process`` with its defaults), so a raw ``bttsim simulate``
recording exports the same tables as a ``bttsim run`` one.

CSV: a header line, comma separated, floats written with 17 significant digits (they read
back to the same float64), ``NaN`` for a missing value. Parquet: one file per table, float64 /
int64 / string columns, written with pyarrow (the ``parquet`` extra).
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np

from . import __version__
from .errors import BttsimError
from .sim.records import Truth  # not from sim.core: the export never loads the simulator

__all__ = ["FORMATS", "COLUMNS", "BLOCK_ROWS", "TOA_TRUTH_FIELDS", "Unstreamable", "RunTables",
           "run_tables", "export_run", "read_tables", "ExportCounts"]

FORMATS = ("csv", "parquet")
_NAN = re.compile(r"(?<![^,\n])nan(?![^,\n])")  # a whole CSV field "nan"

#: Column -> (unit, meaning), shared by every table; units "" for counts and labels.
COLUMNS: dict[str, tuple[str, str]] = {
    "revolution": ("", "revolution number of the run (OPR pulse n starts revolution n)"),
    "blade": ("", "blade index, 0-based, anticlockwise from the OPR"),
    "probe": ("", "probe index, 0-based, in the run metadata's probe order"),
    "opr_s": ("s", "once-per-revolution pulse time"),
    "toa_s": ("s", "time of arrival of the blade at the probe"),
    "d_m": ("m", "BTT displacement of Eq. 1 (tangential, at the tip radius)"),
    "t_exp_s": ("s", "expected arrival time of the undeflected blade"),
    "engine_order": ("", "engine order of the sine fit"),
    "amp_pkpk_m": ("m", "peak-to-peak amplitude"),
    "phase_rad": ("rad", "phase psi of the sine fit (Eq. 16)"),
    "amp_std_m": ("m", "standard uncertainty of the pk-pk amplitude (NaN without redundancy)"),
    "dc_m": ("m", "offset a0 of the sine fit"),
    "residual_rms_m": ("m", "RMS residual of the sine fit"),
    "n_samples": ("", "samples in the fit"),
    "omega_rad_s": ("rad/s", "mean rotor speed of the revolution (from the OPR times)"),
    "freq_hz": ("Hz", "vibration frequency EO * Omega / (2 pi) (Eq. 17)"),
    "nd": ("", "nodal diameter (signed in `resonance`: negative for a backward wave)"),
    "forward_m": ("m", "forward travelling-wave magnitude (pk-pk) at this ND"),
    "backward_m": ("m", "backward travelling-wave magnitude (pk-pk) at this ND"),
    "entry": ("", "resonance entry index (crossings first, then steady dwells)"),
    "kind": ("", "'crossing' or 'dwell'"),
    "eo": ("", "engine order"),
    "rpm": ("rpm", "speed at the crossing's peak (or the dwell's mean speed)"),
    "entry_freq_hz": ("Hz", "blade mean of the resonant frequency of the entry"),
    "method": ("", "resonance method: peak, sdof, cff (crossings) or mean (dwells)"),
    "cn": ("", "condition number of B (Eq. 16)"),
    "first_revolution": ("", "first revolution used by the entry"),
    "last_revolution": ("", "last revolution used by the entry (inclusive)"),
    "peak_revolution": ("", "revolution of the blade's peak (fractional for refined methods)"),
    "damping_ratio": ("", "damping ratio from the SDOF method (NaN otherwise)"),
    "freq_std_hz": ("Hz", "standard uncertainty of the frequency"),
    "amp_ci95_lo_m": ("m", "lower end of the 95 % interval of the pk-pk amplitude (NaN: none)"),
    "amp_ci95_hi_m": ("m", "upper end of the 95 % interval of the pk-pk amplitude"),
    "freq_ci95_lo_hz": ("Hz", "lower end of the 95 % interval of the frequency"),
    "freq_ci95_hi_hz": ("Hz", "upper end of the 95 % interval of the frequency"),
    "phase_ci95_lo_rad": ("rad", "lower end of the 95 % interval of the phase"),
    "phase_ci95_hi_rad": ("rad", "upper end of the 95 % interval of the phase"),
    "crb_amp_m": ("m", "Cramér-Rao lower bound (standard deviation) of the pk-pk amplitude (NaN: none)"),
    "crb_freq_hz": ("Hz", "Cramér-Rao lower bound (standard deviation) of the frequency (NaN: none)"),
    "truth_amp_pkpk_m": ("m", "true resonant pk-pk amplitude of d_eqv (Eq. 3-4)"),
    "truth_freq_hz": ("Hz", "true resonant frequency"),
    "E_A_pct": ("%", "amplitude error (Eq. 18)"),
    "E_f_pct": ("%", "frequency error (Eq. 19)"),
    "truth_toa_s": ("s", "simulated TOA before acquisition errors (clock, noise)"),
    "d_eqv_m": ("m", "true d_eqv(t_TOA) = d_tang + d_z / tan(eta_tip) at P_nom (Eq. 3-4)"),
    "d_tang_m": ("m", "true tangential displacement of P_nom at the TOA"),
    "d_z_m": ("m", "true axial displacement of P_nom at the TOA"),
    "d_eq1_m": ("m", "Eq. 1 displacement from the simulated TOA and the exact expected time"),
    "omega_mean_rad_s": ("rad/s", "true mean speed over the revolution"),
    "d_eqv_pkpk_m": ("m", "true pk-pk envelope of d_eqv(t) over the revolution (engine orders)"),
    "eo_pkpk_m": ("m", "true pk-pk envelope of this engine order's own part of d_eqv(t) over the revolution"),
    "component": ("", "non-synchronous vibration component index (scenario order: stalls, broadband, flutter)"),
    "nsv_kind": ("", "'rotating_stall', 'flutter' or 'broadband'"),
    "nsv_freq_hz": ("Hz", "true frequency in the rotor frame at the revolution's mean speed (broadband: band centre)"),
    "nsv_nd": ("", "true signed nodal diameter (+ forward, - backward; broadband 0)"),
    "nsv_amp_pkpk_m": ("m", "true pk-pk d_eqv at P_nom, largest blade (0 when absent)"),
    "nsv_rms_m": ("m", "true rms of the component's d_eqv at P_nom over the revolution"),
    "band_lo_hz": ("Hz", "broadband force band, low end (else 0)"),
    "band_hi_hz": ("Hz", "broadband force band, high end (else 0)"),
}


@dataclass(frozen=True, slots=True, eq=False)
class RunTables:
    """The tidy tables of one run.

    Attributes
    ----------
    tables : dict of str -> callable
        Table name -> a function of no argument that gives the table as an iterator of row
        blocks (at least one), each a dict column name -> 1-D array (int64, float64 or str),
        all columns of a block the same length; the table is the blocks one after the
        other. Built when asked for, a block at a time: a writer holds one block
        (:meth:`table` builds a whole table).
    meta : dict
        JSON-serialisable: ``run`` (metadata), ``summary`` (processing report), ``processing``.
    """

    tables: dict
    meta: dict

    def blocks(self, name: str):
        """Table ``name`` as an iterator of row blocks (built as iterated)."""
        return self.tables[name]()

    def table(self, name: str) -> dict:
        """Table ``name`` (built now, whole)."""
        blocks = list(self.blocks(name))
        return {k: np.concatenate([b[k] for b in blocks]) for k in blocks[0]}


#: Rows of a block of a table (about; whole revolutions).
BLOCK_ROWS = 100_000
#: Rows of a block a CSV writer formats at once (their Python floats and text lines: about 0.8 kB
#: a row of the widest tables while formatted).
CSV_ROWS = 20_000
#: The truth fields with one value per TOA: the ``truth`` table, read from the recording as
#: it is written (not held for the whole run).
TOA_TRUTH_FIELDS = ("toa_s", "t_exp_s", "d_eqv_m", "d_tang_m", "d_z_m", "d_eq1_m")


class Unstreamable(Exception):
    """The recording's truth is not one message per revolution in order: the ``truth`` table
    is made from the whole run's arrays instead."""


def _blocks(n_rev: int, per_rev: int, make):
    """``make(a, b)`` (the rows of revolutions ``a .. b-1``) over blocks of about
    :data:`BLOCK_ROWS` rows; one (empty) block for no revolution."""
    step = max(1, BLOCK_ROWS // max(int(per_rev), 1))
    for a in range(0, max(int(n_rev), 1), step):
        yield make(a, min(a + step, int(n_rev)))


def long_cols(shape: tuple, names: tuple, first: np.ndarray) -> dict:
    """Index columns of a C-order flattening of an array of ``shape``; axis 0 numbered by ``first``."""
    idx = np.indices(shape).reshape(len(shape), -1)
    cols = {names[0]: np.asarray(first, dtype=np.int64)[idx[0]]}
    for name, i in zip(names[1:], idx[1:]):
        cols[name] = i.astype(np.int64)
    return cols


def f64(a) -> np.ndarray:
    """A contiguous float64 column of ``a`` (flattened in C order)."""
    return np.ascontiguousarray(np.asarray(a, dtype=np.float64).ravel())


def _opt(arr, n: int) -> np.ndarray:
    return np.full(n, np.nan) if arr is None or np.size(arr) != n else np.asarray(arr, dtype=np.float64)


def _ci(arr, n: int, k: int) -> np.ndarray:
    return np.full(n, np.nan) if arr is None or np.shape(arr) != (n, 2) else np.asarray(arr, np.float64)[:, k]


def _resonance_table(report, revolution0: int) -> dict:
    cols: dict[str, list] = {k: [] for k in (
        "entry", "kind", "eo", "nd", "rpm", "entry_freq_hz", "method", "cn", "first_revolution", "last_revolution",
        "blade", "peak_revolution", "amp_pkpk_m", "freq_hz", "phase_rad", "amp_std_m", "freq_std_hz",
        "amp_ci95_lo_m", "amp_ci95_hi_m", "freq_ci95_lo_hz", "freq_ci95_hi_hz", "phase_ci95_lo_rad",
        "phase_ci95_hi_rad", "crb_amp_m", "crb_freq_hz", "damping_ratio", "truth_amp_pkpk_m", "truth_freq_hz",
        "E_A_pct", "E_f_pct")}
    for i, e in enumerate(tuple(report.resonances) + tuple(report.steady)):
        p = e.peaks
        n = p.n_blades
        t = e.truth
        per_blade = {
            "blade": np.arange(n), "peak_revolution": _opt(p.revolution, n) + revolution0,
            "amp_pkpk_m": _opt(p.amp_pkpk_m, n), "freq_hz": _opt(p.freq_hz, n), "phase_rad": _opt(p.phase_rad, n),
            "amp_std_m": _opt(p.amp_std_m, n), "freq_std_hz": _opt(p.freq_std_hz, n),
            "amp_ci95_lo_m": _ci(p.amp_ci95_m, n, 0), "amp_ci95_hi_m": _ci(p.amp_ci95_m, n, 1),
            "freq_ci95_lo_hz": _ci(p.freq_ci95_hz, n, 0), "freq_ci95_hi_hz": _ci(p.freq_ci95_hz, n, 1),
            "phase_ci95_lo_rad": _ci(p.phase_ci95_rad, n, 0), "phase_ci95_hi_rad": _ci(p.phase_ci95_rad, n, 1),
            "crb_amp_m": _opt(p.crb_amp_m, n), "crb_freq_hz": _opt(p.crb_freq_hz, n),
            "damping_ratio": _opt(p.damping_ratio, n),
            "truth_amp_pkpk_m": _opt(None if t is None else t.amp_pkpk_m, n),
            "truth_freq_hz": _opt(None if t is None else t.freq_hz, n),
            "E_A_pct": _opt(e.e_a_pct, n), "E_f_pct": _opt(e.e_f_pct, n)}
        per_entry = {"entry": i, "kind": e.kind, "eo": int(e.eo), "nd": int(e.nd), "rpm": float(e.rpm),
                     "entry_freq_hz": float(e.freq_hz), "method": e.method, "cn": float(e.cn),
                     "first_revolution": int(e.first_revolution), "last_revolution": int(e.last_revolution)}
        for k, v in per_entry.items():
            cols[k].extend([v] * n)
        for k, v in per_blade.items():
            cols[k].extend(np.asarray(v).tolist())
    out = {}
    for k, v in cols.items():
        if k in ("kind", "method"):
            out[k] = np.array(v, dtype=str) if v else np.zeros(0, dtype="<U1")
        elif k in ("entry", "eo", "nd", "first_revolution", "last_revolution", "blade"):
            out[k] = np.array(v, dtype=np.int64)
        else:
            out[k] = np.array(v, dtype=np.float64)
    return out


def jsonable(x):
    """``x`` with numpy arrays and scalars turned into JSON's lists and numbers."""
    if isinstance(x, np.ndarray):
        return [jsonable(v) for v in x.tolist()] if x.ndim else jsonable(x.item())
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, dict):
        return {k: jsonable(v) for k, v in x.items()}
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(x) else None
    return x


def run_tables(run, result=None) -> RunTables:
    """The tidy tables of a recorded run.

    Parameters
    ----------
    run : RecordedRun
        From :func:`bttsim_stream.offline.load_run`.
    result : ProcessingResult, optional
        Its offline processing (default: :func:`~bttsim_stream.process.pipeline.process_arrays`
        with the default options, the truth when recorded).

    Returns
    -------
    RunTables
    """
    from .process.pipeline import ProcessOptions, process_arrays

    rev = np.asarray(run.revolution, dtype=np.int64)
    r0 = int(rev[0])
    n_rev, n_b, n_p = run.toa_s.shape
    if result is None:
        try:
            # the run-sized arrays in scratch files, read by blocks as the tables are written
            result = process_arrays(run.opr_s, run.toa_s, run.meta, ProcessOptions(), truth=run.truth, revolution0=r0,
                                    scratch=True)
        except (ValueError, np.linalg.LinAlgError, FloatingPointError) as exc:
            raise BttsimError(f"the processing of the recording failed ({exc})") from None
    t: dict = {}  # name -> block iterator: the tables are built a block at a time, when written
    one = lambda cols: lambda: iter([cols()])  # noqa: E731  (a table of one block)
    toa_idx = lambda a, b: long_cols((b - a, n_b, n_p), ("revolution", "blade", "probe"), rev[a:b])  # noqa: E731
    t["opr"] = one(lambda: {"revolution": rev.copy(), "opr_s": f64(run.opr_s)})
    t["toa"] = lambda: _blocks(n_rev, n_b * n_p, lambda a, b: dict(toa_idx(a, b), toa_s=f64(run.toa_s[a:b])))
    if run.extra_edges["toa_s"].size:  # double pulses (the probe signal chain)
        t["extra_edge"] = one(lambda: {k: np.array(v) for k, v in run.extra_edges.items()})
    disp = result.displacements
    t["displacement"] = lambda: _blocks(n_rev, n_b * n_p, lambda a, b: dict(
        toa_idx(a, b), d_m=f64(disp.d_m[a:b]), t_exp_s=f64(disp.t_exp_at(slice(a, b)))))
    fit = result.fit
    t["fit"] = lambda: _blocks(n_rev, n_b * len(fit.engine_orders), lambda a, b: _fit_table(fit, disp, rev, a, b))
    ftw = result.fit_tw
    t["tw"] = lambda: _blocks(n_rev, ftw.forward_m.shape[1], lambda a, b: dict(
        long_cols((b - a,) + ftw.forward_m.shape[1:], ("revolution", "nd"), rev[a:b]),
        forward_m=f64(ftw.forward_m[a:b]), backward_m=f64(ftw.backward_m[a:b])))
    ptw = result.probe_tw
    t["tw_probe"] = lambda: _blocks(n_rev, int(np.prod(ptw.forward_m.shape[1:])), lambda a, b: dict(
        long_cols((b - a,) + ptw.forward_m.shape[1:], ("revolution", "probe", "nd"), rev[a:b]),
        forward_m=f64(ptw.forward_m[a:b]), backward_m=f64(ptw.backward_m[a:b])))
    t["resonance"] = one(lambda: _resonance_table(result.report, r0))
    if run.truth is not None:
        tr = run.truth
        if tr.toa_s is None:  # the per-TOA truth not kept: read from the recording
            t["truth"] = lambda: _truth_stream(run.path, rev, n_b, n_p, run.meta.rig)
        else:
            t["truth"] = lambda: _blocks(n_rev, n_b * n_p, lambda a, b: _truth_table(tr, toa_idx(a, b), a, b))
        t["truth_revolution"] = lambda: _blocks(n_rev, n_b, lambda a, b: dict(
            long_cols((b - a, n_b), ("revolution", "blade"), rev[a:b]),
            opr_s=f64(np.repeat(tr.opr_s[a:b], n_b)), omega_mean_rad_s=f64(np.repeat(tr.omega_mean[a:b], n_b)),
            d_eqv_pkpk_m=f64(tr.d_eqv_pkpk_m[a:b])))
        if tr.eo_pkpk_m is not None and np.prod(tr.eo_pkpk_m.shape):  # (an array or scratch rows)
            t["truth_eo"] = lambda: _blocks(n_rev, int(np.prod(tr.eo_pkpk_m.shape[1:])),
                                            lambda a, b: _truth_eo_table(tr, rev, a, b))
        if tr.nsv_kind is not None and tr.nsv_kind.size:
            t["truth_nsv"] = lambda: _blocks(n_rev, int(np.prod(tr.nsv_kind.shape[1:])),
                                             lambda a, b: _truth_nsv_table(tr, rev, a, b))
    info = {f.name: getattr(run.meta, f.name) for f in fields(run.meta)}
    meta = {"run": jsonable(info), "summary": jsonable(result.summary),
            "processing": {"by": "bttsim process (default options)", "options": jsonable(asdict(result.options)),
                           "engine_orders": list(result.engine_orders),
                           "displacement_method": disp.method}}
    return RunTables(tables=t, meta=meta)


def _truth_table(tr, idx: dict, a: int, b: int) -> dict:
    """Rows of revolutions ``a .. b-1`` of the ``truth`` table from the run's truth arrays."""
    return dict(idx, truth_toa_s=f64(tr.toa_s[a:b]), t_exp_s=f64(tr.t_exp_s[a:b]), d_eqv_m=f64(tr.d_eqv_m[a:b]),
                d_tang_m=f64(tr.d_tang_m[a:b]), d_z_m=f64(tr.d_z_m[a:b]), d_eq1_m=f64(tr.d_eq1_m[a:b]))


def _truth_stream(path, rev: np.ndarray, n_b: int, n_p: int, rig: str):
    """The ``truth`` table read from the recording's truth messages as it is written, in
    blocks: one message per revolution of ``rev``, in order.

    Raises
    ------
    Unstreamable
        A revolution's truth repeated, out of order, missing or of another shape (the
        table is then made from the whole run's arrays, whose rules say which holds).
    """
    from .bus import codec, keys
    from .bus.recording import RecordingScan

    r0, r1 = int(rev[0]), int(rev[-1])
    step = max(1, BLOCK_ROWS // (n_b * n_p))
    names = ("revolution", "blade", "probe")
    rows: list = []
    expect = r0

    def block():
        a = expect - len(rows) - r0
        tr = Truth(*[np.concatenate([getattr(d, f) for d in rows]) if f in TOA_TRUTH_FIELDS else None
                     for f in ("opr_s",) + TOA_TRUTH_FIELDS + ("d_eqv_pkpk_m", "omega_mean")])
        return _truth_table(tr, long_cols((len(rows), n_b, n_p), names, rev[a:a + len(rows)]), 0, len(rows))

    for m in keys.of_rig(RecordingScan(path), rig):
        if "/truth" not in m.key or keys.parse_key(m.key).kind != "truth":
            continue
        d = codec.decode_truth(m.payload, m.key)
        r = int(d.header.revolution)
        if r < r0 or r > r1:
            continue
        if r != expect or any(getattr(d.body, f).shape != (1, n_b, n_p) for f in TOA_TRUTH_FIELDS):
            raise Unstreamable(f"truth of revolution {r}")
        rows.append(d.body)
        expect += 1
        if len(rows) == step:
            yield block()
            rows = []
    if expect != r1 + 1:
        raise Unstreamable("truth missing")
    if rows or r1 < r0:
        yield block()


def _truth_eo_table(tr, rev: np.ndarray, a: int, b: int) -> dict:
    """The ``truth_eo`` table (revolutions ``a .. b-1``): each engine order's own response, per
    revolution and blade."""
    cols = long_cols((b - a,) + tr.eo_pkpk_m.shape[1:], ("revolution", "blade", "eo"), rev[a:b])
    cols["eo"] = np.asarray(tr.eo_engine_order[0], np.int64)[cols["eo"]]
    return dict(cols, eo_pkpk_m=f64(tr.eo_pkpk_m[a:b]))


def _truth_nsv_table(tr, rev: np.ndarray, a: int, b: int) -> dict:
    """The ``truth_nsv`` table (revolutions ``a .. b-1``): each non-synchronous component."""
    return dict(long_cols((b - a,) + tr.nsv_kind.shape[1:], ("revolution", "component"), rev[a:b]),
                nsv_kind=np.asarray(tr.nsv_kind[a:b], str).ravel(), nsv_freq_hz=f64(tr.nsv_freq_hz[a:b]),
                nsv_nd=np.asarray(tr.nsv_nd[a:b], np.int64).ravel(), nsv_amp_pkpk_m=f64(tr.nsv_amp_pkpk_m[a:b]),
                nsv_rms_m=f64(tr.nsv_rms_m[a:b]), band_lo_hz=f64(tr.nsv_band_hz[a:b, ..., 0]),
                band_hi_hz=f64(tr.nsv_band_hz[a:b, ..., 1]))


def _fit_table(fit, disp, rev: np.ndarray, a: int, b: int) -> dict:
    """The ``fit`` table (revolutions ``a .. b-1``): one row per revolution, blade and engine order."""
    n_b = fit.amp_pkpk_m.shape[1]
    n_rev = b - a
    n_eo = len(fit.engine_orders)
    fit_cols = long_cols((n_rev, n_b, n_eo), ("revolution", "blade", "engine_order"), rev[a:b])
    fit_cols["engine_order"] = np.asarray(fit.engine_orders, dtype=np.int64)[fit_cols["engine_order"]]
    # rows a .. b-1 read first: the fit's arrays may be scratch rows
    per_rev_blade = lambda x: f64(np.broadcast_to(np.asarray(x[a:b], float)[:, :, None], (n_rev, n_b, n_eo)))  # noqa: E731
    omega = np.asarray(fit.omega_rad_s if fit.omega_rad_s is not None else disp.omega_rad_s, float)[a:b]
    freq = (np.asarray(fit.freq_hz, float)[a:b] if fit.freq_hz is not None
            else np.outer(omega, fit.engine_orders) / (2 * np.pi))
    fit_cols.update(amp_pkpk_m=f64(fit.amp_pkpk_m[a:b]), phase_rad=f64(fit.phase_rad[a:b]),
                    amp_std_m=f64(fit.amp_std_m[a:b]), dc_m=per_rev_blade(fit.dc_m),
                    residual_rms_m=per_rev_blade(fit.residual_rms_m),
                    n_samples=np.broadcast_to(np.asarray(fit.n_samples[a:b], np.int64)[:, :, None],
                                              (n_rev, n_b, n_eo)).ravel().copy(),
                    omega_rad_s=f64(np.broadcast_to(omega[:, None, None], (n_rev, n_b, n_eo))),
                    freq_hz=f64(np.broadcast_to(freq[:, None, :], (n_rev, n_b, n_eo))))
    return fit_cols


def _write_csv(path: Path, blocks) -> tuple[int, dict]:
    """One table as CSV, a block at a time: ints as integers, floats with 17 significant
    digits (``repr`` exact), ``NaN`` for missing values; rows formatted in C by one ``%``
    format per row, :data:`CSV_ROWS` at a time. Returns the row count and the first block
    (its columns' dtypes)."""
    n, first = 0, None
    with open(path, "w", newline="") as fh:
        for cols in blocks:
            names = list(cols)
            arrays = [np.asarray(cols[k]) for k in names]
            if first is None:
                first = cols
                fh.write(",".join(names) + "\n")
            fmt = ",".join("%d" if a.dtype.kind in "iub" else "%.17g" if a.dtype.kind == "f" else "%s" for a in arrays)
            rows_in = arrays[0].shape[0] if arrays else 0
            int_first = bool(arrays) and arrays[0].dtype.kind in "iu"
            for lo in range(0, rows_in, CSV_ROWS):
                rows = zip(*(a[lo:lo + CSV_ROWS].tolist() for a in arrays))
                text = "\n".join(fmt % r for r in rows)
                # a whole field "nan" -> "NaN"; with an integer first column (every table here) it
                # always follows a comma, which str.replace finds 3x faster than the regex
                text = text.replace(",nan", ",NaN") if int_first else _NAN.sub("NaN", text)
                fh.write(text + "\n")
            n += rows_in
    return n, first


def _write_parquet(path: Path, blocks, pa, pq) -> tuple[int, dict]:
    """One table as Parquet, a row group per block (the schema of the first)."""
    n, first, writer = 0, None, None
    try:
        for cols in blocks:
            table = pa.table({k: pa.array(v) for k, v in cols.items()})
            if writer is None:
                first = cols
                writer = pq.ParquetWriter(path, table.schema)
            else:
                table = table.cast(writer.schema)
            writer.write_table(table)
            n += table.num_rows
    finally:
        if writer is not None:
            writer.close()
    return n, first


def _pyarrow():
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        raise BttsimError("--format parquet needs pyarrow: pip install 'bttsim-stream[parquet]' "
                          "(or use --format csv)") from None
    return pa, pq


def _column_meta(name: str, a: np.ndarray) -> dict:
    unit, meaning = COLUMNS.get(name, ("", ""))
    kind = {"i": "int64", "u": "int64", "f": "float64"}.get(a.dtype.kind, "string")
    return {"unit": unit, "dtype": kind, "description": meaning}


def export_run(path, out_dir, fmt: str = "csv", rig: str | None = None) -> "ExportCounts":
    """Export a recording to tidy tables in ``out_dir`` (created if missing).

    Parameters
    ----------
    path : path-like
        The recording (MCAP).
    out_dir : path-like
        Output folder: one ``<table>.csv`` or ``<table>.parquet`` per table and ``run.json``.
    fmt : {"csv", "parquet"}
    rig : str, optional
        The rig whose run is exported (:func:`~bttsim_stream.offline.load_run`; default: the
        recording's only one).

    Returns
    -------
    ExportCounts
        Table name -> number of rows (a dict); its ``incomplete`` says what the recording
        lacks of its run ("" when it holds the whole run).

    Raises
    ------
    BttsimError
        An unreadable recording, an unknown format, pyarrow missing for Parquet, an output
        folder that cannot be written.
    """
    from .offline import load_run

    if fmt not in FORMATS:
        raise BttsimError(f"--format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    if fmt == "parquet":
        _pyarrow()  # before the (long) read: a missing extra fails at once
    if not Path(path).is_file():
        raise BttsimError(f"{path}: no such file")
    out = Path(out_dir)
    kept = tuple(f.name for f in fields(Truth) if f.name not in TOA_TRUTH_FIELDS)
    try:  # the per-TOA truth read from the file as its table is written
        return _export(load_run(path, truth_fields=kept, rig=rig, scratch=True), path, out, fmt)
    except Unstreamable:  # an odd truth stream: the whole run's arrays say what it holds
        return _export(load_run(path, rig=rig, scratch=True), path, out, fmt)


class ExportCounts(dict):
    """Rows per table written; ``incomplete``: what the recording lacks of its run, one line
    ("" when whole: every revolution, nothing lost)."""

    incomplete: str = ""


def _export(run, path, out: Path, fmt: str) -> ExportCounts:
    """Write the tables and ``run.json`` of a loaded run (see :func:`export_run`)."""
    from .offline import completeness

    rt = run_tables(run)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise BttsimError(f"{out}: cannot create the output folder ({exc.strerror or exc})") from None
    if not out.is_dir():
        raise BttsimError(f"{out}: not a folder")
    counts, described = ExportCounts(), {}
    c = completeness(run)
    if not c.complete:
        counts.incomplete = (f"{c.revolutions_processed} of {c.revolutions_expected} revolutions"
                             + (f", {c.lost} messages lost" if c.lost else ""))
    try:
        for name in rt.tables:  # one table at a time, a block at a time: built, written, dropped
            file = out / f"{name}.{fmt}"
            if fmt == "csv":
                n, cols = _write_csv(file, rt.blocks(name))
            else:
                n, cols = _write_parquet(file, rt.blocks(name), *_pyarrow())
            counts[name] = n
            described[name] = {"file": file.name, "rows": n,
                               "columns": {k: _column_meta(k, np.asarray(v)) for k, v in cols.items()}}
            del cols
        doc = dict(rt.meta, format=fmt, source=str(path), software_version=__version__, tables=described)
        (out / "run.json").write_text(json.dumps(doc, indent=2, allow_nan=False) + "\n")
    except OSError as exc:
        raise BttsimError(f"{out}: cannot write ({exc.strerror or exc})") from None
    return counts


def read_tables(out_dir) -> dict:
    """Read an export folder back: table name -> column name -> ndarray (int64, float64, str),
    dtypes from ``run.json``."""
    out = Path(out_dir)
    doc = json.loads((out / "run.json").read_text())
    tables = {}
    for name, d in doc["tables"].items():
        file = out / d["file"]
        if doc["format"] == "parquet":
            _, pq = _pyarrow()
            tab = pq.read_table(file)
            tables[name] = {k: tab.column(k).to_numpy(zero_copy_only=False) for k in tab.column_names}
            continue
        cols = d["columns"]
        raw = np.loadtxt(file, delimiter=",", skiprows=1, dtype=str, ndmin=2) if d["rows"] else None
        tables[name] = {}
        for i, (k, c) in enumerate(cols.items()):
            v = raw[:, i] if raw is not None else np.zeros(0, dtype=str)
            tables[name][k] = (v.astype(np.int64) if c["dtype"] == "int64"
                               else v.astype(np.float64) if c["dtype"] == "float64" else v)
    return tables

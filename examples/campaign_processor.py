"""A user's own BTT processor for ``bttsim campaign`` (``processors = ["campaign_processor:peak_fit"]``).

The campaign calls ``peak_fit(tables, run)`` with the run's acquisition as the tidy tables of
``bttsim export`` (``schemas/export.md``): ``tables["opr"]`` (revolution, opr_s) and
``tables["toa"]`` (revolution, blade, probe, toa_s) as pyarrow Tables, and ``run``, the run
metadata of ``run.json`` (probe angles, blade count, tip radius, engine orders, ...); never
the truth. It returns one row per blade: the estimated peak-to-peak resonance amplitude with
its 95 % interval and the frequency there, which the campaign scores against the truth.

The method is deliberately plain (no data preparation, no resonance model):

1. rotor angle at any time from a cubic spline through the OPR pulses (2 pi per revolution);
2. Eq. 1-like tip displacements: the tip radius times the blade's angle at each arrival,
   zeroed on its median over the run per blade and probe;
3. per revolution and blade, a least-squares sine fit at the engine order over the probes
   that saw the blade (Eq. 16: ``d_k = A cos(EO theta_k) + B sin(EO theta_k) + C``), with the
   covariance of (A, B) from the fit's residual (``n_probes - 3`` degrees of freedom);
4. per blade, the revolution of the largest amplitude ``2 sqrt(A^2 + B^2)`` (Eq. 17): its
   amplitude, its 95 % interval (Student's t times the amplitude's standard uncertainty by
   the delta method) and ``EO * Omega / 2 pi`` there.

The interval covers the noise of that one fit, not the bias of picking the largest of many
noisy fits, so expect its coverage to fall short of 95 %: what the campaign's report measures.

The same function runs on an export folder (``bttsim export RUN.mcap --format parquet --out
out/``) without the campaign::

    import json, pyarrow.parquet as pq
    tables = {name: pq.read_table(f"out/{name}.parquet") for name in ("opr", "toa")}
    peak_fit(tables, json.load(open("out/run.json"))["run"])

The module must be importable on every Dask worker (``PYTHONPATH`` or an installed package).
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.stats import t as student_t

EDGE = 2  # revolutions left out at each end: the spline is unreliable there


def _toa_cube(tables: dict, run: dict):
    """``(opr_s (n_rev,), toa_s (n_rev, n_blades, n_probes))`` from the tidy tables, NaN where
    a TOA is missing (the tables say where each row goes; no ordering is assumed)."""
    opr, toa = tables["opr"], tables["toa"]
    rev = opr.column("revolution").to_numpy()
    order = np.argsort(rev)
    rev, opr_s = rev[order], opr.column("opr_s").to_numpy()[order]
    cube = np.full((rev.size, int(run["n_blades"]), int(run["n_probes"])), np.nan)
    row = np.searchsorted(rev, toa.column("revolution").to_numpy())
    cube[row, toa.column("blade").to_numpy(), toa.column("probe").to_numpy()] = toa.column("toa_s").to_numpy()
    return opr_s, cube


def peak_fit(tables: dict, run: dict) -> dict:
    """Per-blade peak-to-peak resonance amplitude with its 95 % interval.

    Parameters
    ----------
    tables : dict of str -> pyarrow.Table
        ``"opr"`` and ``"toa"``, as ``bttsim export`` writes them.
    run : dict
        ``run.json``'s ``run`` object.

    Returns
    -------
    dict of columns
        ``blade``, ``eo``, ``amp_pkpk_m``, ``amp_std_m``, ``amp_ci95_lo_m``, ``amp_ci95_hi_m``
        (m) and ``freq_hz``, one entry per blade.
    """
    eo = int(run["engine_orders"][0])
    opr_s, toa_s = _toa_cube(tables, run)
    n_rev, n_b, n_p = toa_s.shape
    turns = 2 * np.pi * np.arange(n_rev)
    rotor = CubicSpline(opr_s, turns)  # rotor angle at time t, rad
    angle = rotor(toa_s) - turns[:, None, None]  # blade angle within its revolution, (rev, blade, probe)
    d = float(run["tip_radius_m"]) * (angle - np.nanmedian(angle, axis=0))  # m

    theta = np.asarray(run["probe_angles_rad"], float)
    basis = np.column_stack([np.cos(eo * theta), np.sin(eo * theta), np.ones_like(theta)])  # (probe, 3)
    w = np.isfinite(d)  # the probes that saw the blade in that revolution
    dw = np.where(w, d, 0.0)
    normal = np.einsum("rbp,pi,pj->rbij", w.astype(float), basis, basis)  # B^T W B, (rev, blade, 3, 3)
    dof = w.sum(axis=-1) - 3
    ok = dof > 0  # a residual to estimate the noise from
    normal[~ok] = np.eye(3)
    cov = np.linalg.inv(normal)
    coef = np.einsum("rbij,pj,rbp->rbi", cov, basis, dw)  # (rev, blade, 3)
    resid = np.where(w, d - coef @ basis.T, 0.0)
    s2 = np.where(ok, (resid**2).sum(axis=-1) / np.maximum(dof, 1), np.nan)  # noise variance, m^2
    a, b = coef[..., 0], coef[..., 1]
    amp = np.where(ok, 2.0 * np.hypot(a, b), np.nan)  # pk-pk, Eq. 17
    with np.errstate(invalid="ignore", divide="ignore"):
        grad = np.stack([a, b], axis=-1) * (2.0 / np.hypot(a, b))[..., None]  # d amp / d (A, B)
    amp_std = np.sqrt(s2 * np.einsum("rbi,rbij,rbj->rb", grad, cov[..., :2, :2], grad))

    inner = amp[EDGE:n_rev - EDGE]
    filled = np.where(np.isfinite(inner), inner, -np.inf)
    peak = np.argmax(filled, axis=0) + EDGE  # per blade
    blades = np.arange(n_b)
    found = np.isfinite(filled).any(axis=0)
    est = np.where(found, amp[peak, blades], np.nan)
    std = np.where(found, amp_std[peak, blades], np.nan)
    half = student_t.ppf(0.975, np.maximum(dof[peak, blades], 1)) * std
    omega = 2 * np.pi / np.gradient(opr_s)  # rad/s per revolution
    return {"blade": blades, "eo": np.full(n_b, eo), "amp_pkpk_m": est, "amp_std_m": std,
            "amp_ci95_lo_m": np.maximum(est - half, 0.0), "amp_ci95_hi_m": est + half,
            "freq_hz": np.where(found, eo * omega[peak] / (2 * np.pi), np.nan)}

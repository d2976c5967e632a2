"""A user's own BTT processor for ``bttsim campaign`` (``processors = ["campaign_processor:peak_fit"]``).

The campaign calls ``peak_fit(run)`` with a :class:`bttsim_stream.campaign.RunData` (OPR and
TOA arrays, probe angles, blade count, tip radius, engine orders; never the truth) and scores
what it returns against the truth. This one is deliberately plain: rotor angle from a cubic
spline through the OPR pulses, Eq. 1-like tip displacements zeroed on their median, one
least-squares sine fit at the engine order per revolution and blade (Eq. 16, no data
preparation), and the largest amplitude over the run per blade.

The module must be importable on every Dask worker (``PYTHONPATH`` or an installed package).
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import CubicSpline


def peak_fit(run) -> dict:
    """Per-blade peak-to-peak resonance amplitude, m.

    Parameters
    ----------
    run : bttsim_stream.campaign.RunData

    Returns
    -------
    dict
        ``amp_pkpk_m`` (n_blades,) and the engine order ``eo`` it was fitted at.
    """
    eo = run.engine_orders[0] if run.engine_orders else 8
    n_rev = run.opr_s.size
    rotor = CubicSpline(run.opr_s, 2 * np.pi * np.arange(n_rev))  # rotor angle at time t, rad
    angle = rotor(run.toa_s) - 2 * np.pi * np.arange(n_rev)[:, None, None]  # (revolution, blade, probe)
    d = run.tip_radius_m * (angle - np.nanmedian(angle, axis=0))  # m, zeroed per blade and probe
    theta = np.asarray(run.probe_angles_rad, float)
    basis = np.column_stack([np.cos(eo * theta), np.sin(eo * theta), np.ones_like(theta)])  # (probe, 3)
    coef = np.nan_to_num(d) @ np.linalg.pinv(basis).T  # (revolution, blade, 3)
    amp = 2.0 * np.hypot(coef[..., 0], coef[..., 1])  # pk-pk
    # the edges of the spline are unreliable: leave the first and last revolutions out
    return {"amp_pkpk_m": np.nanmax(amp[2:-2], axis=0), "eo": int(eo)}

"""Shared fixtures of the bus tests: synthetic revolution batches and numbered message streams."""

import numpy as np

from bttsim_stream.bus.stream import MessageStream
from bttsim_stream.sim.core import RevolutionBatch, RunInfo, Truth

NR, NB, NP = 3, 29, 5
TRUTH_2D = ("toa_s", "t_exp_s", "d_eqv_m", "d_tang_m", "d_z_m", "d_eq1_m")


def make_batch(seed=0, ticks=False, rev0=0, nr=NR, nb=NB, npr=NP) -> RevolutionBatch:
    """A random but seeded batch with the simulator's shapes (values need not be physical)."""
    rng = np.random.default_rng(seed)
    shape = (nr, nb, npr)
    opr = 0.05 * np.arange(rev0, rev0 + nr) + 1e-4 * rng.random(nr)
    toa = opr[:, None, None] + 0.05 * rng.random(shape)
    truth = Truth(opr_s=opr + 1e-7 * rng.standard_normal(nr),
                  **{name: rng.standard_normal(shape) for name in TRUTH_2D},
                  d_eqv_pkpk_m=rng.random((nr, nb)) * 1e-3, omega_mean=100 + rng.random(nr))
    opr_ticks = toa_ticks = None
    if ticks:
        clock = 80e6
        opr_ticks = np.floor(opr * clock).astype(np.int64)
        toa_ticks = np.floor(toa * clock).astype(np.int64)
        opr, toa = opr_ticks / clock, toa_ticks / clock
    return RevolutionBatch(revolution=np.arange(rev0, rev0 + nr, dtype=np.int64), opr_s=opr,
                           toa_s=toa, opr_ticks=opr_ticks, toa_ticks=toa_ticks, truth=truth,
                           residual_s=0.0, bracketed=np.ones(shape, bool))


def make_info(**changes) -> RunInfo:
    base = dict(n_blades=NB, n_probes=NP, n_revolutions=5000,
                probe_angles_rad=np.deg2rad([5, 15.15, 23.82, 220, 301.5]), probe_axial_m=12.26e-3,
                tip_radius_m=0.19, opr_angle_rad=0.1, clock_hz=80e6, stagger_deg=41.5,
                engine_orders=(8,), nodal_diameters=(1,), toa_method="PAD", duration_s=130.0,
                seed=12345, rig="rig1", scenario_toml="[run]\nrig = \"rig1\"\n", software_version="0.1.0",
                has_truth=True)
    base.update(changes)
    return RunInfo(**base)


RUN_META = {"run_id": "run-a", "rig": "rig1", "scenario_toml": "[run]\nrig = \"rig1\"\n",
            "software_version": "0.1.0"}


def recorded_messages(n_batches=4, ticks=False):
    """The metadata and ``n_batches`` batches of 3 revolutions as one publisher numbers them."""
    stream = MessageStream("run-a", "rig1")
    out = [stream.run_metadata(make_info())]
    for k in range(n_batches):
        out += stream.acquisition(make_batch(seed=k, ticks=ticks, rev0=3 * k))
    return out

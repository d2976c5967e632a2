"""Streaming run-up simulation: OPR pulses, per-probe TOAs and ground truth per revolution.

Axis order of every batch array: ``(revolution, blade, probe)``. Times in s, angles in rad,
displacements in m. Revolution ``n`` starts at OPR pulse ``n`` (the rotor's reference mark,
at rotor angle 0, passing the OPR sensor: ``phi(t) = theta_opr + 2 pi n``) and holds, for every
blade and probe, the arrival whose rigid P_nom crossing falls in ``[OPR_n, OPR_n+1)``.

Memory does not grow with the run: the modal envelopes are integrated chunk by chunk and
only a short tail of the grid is kept between chunks.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Iterator

import numpy as np

from ..errors import BttsimError
from ..model import build_model, load_model
from .modal import EnvelopeIntegrator, EnvelopeGrid, build_grid, modal_forcing, tip_basis
from .speed import SpeedProfile, speed_profile_from_scenario
from .toa import CrossingSet, eval_compressed, eval_nodes, prepare_crossings, stage_a_grid, stage_a_hp, stage_b

__all__ = ["RunInfo", "Truth", "RevolutionBatch", "RunUpSimulator", "load_scenario_model",
           "collect"]

TWO_PI = 2.0 * np.pi
_BLOCK = 64  # envelope grid steps per integration block


@dataclass(frozen=True, slots=True, eq=False)
class RunInfo:
    """The run's acquisition metadata (what a real BTT system would publish).

    Attributes
    ----------
    n_blades, n_probes, n_revolutions : int
    probe_angles_rad : ndarray, shape (n_probes,)
        Nominal probe angles (the positions the acquisition believes in).
    probe_axial_m : float
    tip_radius_m : float
        Mean radius of P_nom, m (``R_Pnom`` in Eq. 1).
    opr_angle_rad : float
    clock_hz : float
        TOA clock (0: not quantised); tick period ``1 / clock_hz``.
    stagger_deg : float
    engine_orders, nodal_diameters : tuple of int
    toa_method : str
    duration_s : float
    seed : int
    rig : str
    sensing_angles_rad : ndarray, shape (n_blades,), or None
        Angle of each blade's nominal sensing point P_nom in the rotor frame at rotor angle 0
        (the model's ``tip_ref[:, nominal_node, 1]``), rad; None: unknown.
    family_freq_hz : ndarray, shape (n_families, n_blades // 2 + 1), or None
        The model's mode family frequencies per nodal diameter (Campbell diagram), Hz.
    speed_range_rpm : tuple of float
        Slowest and fastest speed of the run's speed profile, rpm ((0, 0): unknown).
    run_id : str
        Identifies the run on the bus ("" until published).
    scenario_toml : str
        The run's full scenario file ("" when not known).
    software_version : str
    has_truth : bool
        Whether the run publishes ground truth on its own key.

    Notes
    -----
    This is what travels as ``bttsim.v1.RunMetadata`` (:mod:`bttsim_stream.bus.codec`): the
    simulator fills the acquisition fields, the publisher adds ``run_id``, ``scenario_toml``,
    ``software_version`` and ``has_truth`` (:func:`dataclasses.replace`).
    """

    n_blades: int
    n_probes: int
    n_revolutions: int
    probe_angles_rad: np.ndarray
    probe_axial_m: float
    tip_radius_m: float
    opr_angle_rad: float
    clock_hz: float
    stagger_deg: float
    engine_orders: tuple
    nodal_diameters: tuple
    toa_method: str
    duration_s: float
    seed: int
    rig: str = "rig1"
    sensing_angles_rad: np.ndarray | None = None
    family_freq_hz: np.ndarray | None = None
    speed_range_rpm: tuple = (0.0, 0.0)
    run_id: str = ""
    scenario_toml: str = ""
    software_version: str = ""
    has_truth: bool = False

    @property
    def tick_s(self) -> float:
        """TOA clock period, s (0 when not quantised)."""
        return 1.0 / self.clock_hz if self.clock_hz > 0 else 0.0


@dataclass(frozen=True, slots=True, eq=False)
class Truth:
    """Ground truth, kept apart from the acquisition data.

    Attributes
    ----------
    opr_s : ndarray, shape (n_rev,)
        Exact OPR times.
    toa_s : ndarray, shape (n_rev, n_blades, n_probes)
        TOAs from the simulator before acquisition errors.
    t_exp_s : ndarray, shape (n_rev, n_blades, n_probes)
        Exact arrival times of the rigid P_nom at the (actual) probe positions.
    d_eqv_m, d_tang_m, d_z_m : ndarray, shape (n_rev, n_blades, n_probes)
        ``d_eqv(t_TOA)`` (Eq. 3-4) and its tangential and axial parts at P_nom.
    d_eq1_m : ndarray, shape (n_rev, n_blades, n_probes)
        Eq. 1 displacement from ``toa_s`` and the exact expected times.
    d_eqv_pkpk_m : ndarray, shape (n_rev, n_blades)
        Peak-to-peak envelope of ``d_eqv(t)`` in the revolution (largest over the
        revolution's arrivals of ``2 sum_m |G_eqv,m|``; exact for one engine order).
    omega_mean : ndarray, shape (n_rev,)
        Mean speed over the revolution, rad/s.
    """

    opr_s: np.ndarray
    toa_s: np.ndarray
    t_exp_s: np.ndarray
    d_eqv_m: np.ndarray
    d_tang_m: np.ndarray
    d_z_m: np.ndarray
    d_eq1_m: np.ndarray
    d_eqv_pkpk_m: np.ndarray
    omega_mean: np.ndarray


@dataclass(frozen=True, slots=True, eq=False)
class RevolutionBatch:
    """Consecutive revolutions of acquisition data and truth.

    Attributes
    ----------
    revolution : ndarray of int64, shape (n_rev,)
    opr_s : ndarray, shape (n_rev,)
        OPR pulse times as acquired (jitter, clock).
    toa_s : ndarray, shape (n_rev, n_blades, n_probes)
        TOAs as acquired (probe errors, jitter, clock).
    opr_ticks, toa_ticks : ndarray of int64 or None
        The same as integer clock ticks when the clock is quantised.
    truth : Truth
    residual_s : float
        Largest final HP Newton step in the batch, s.
    bracketed : ndarray of bool, shape (n_rev, n_blades, n_probes)
        False where no tip-node pair straddled the probe (extrapolated).
    """

    revolution: np.ndarray
    opr_s: np.ndarray
    toa_s: np.ndarray
    opr_ticks: np.ndarray | None
    toa_ticks: np.ndarray | None
    truth: Truth
    residual_s: float
    bracketed: np.ndarray


def load_scenario_model(scn):
    """The scenario's modal model: built-in (built now) or a user's file."""
    if scn.model.source == "builtin":
        return build_model(scn)
    return load_model(scn.model.source)


class RunUpSimulator:
    """Simulate the scenario's run-up and yield :class:`RevolutionBatch` chunks.

    Parameters
    ----------
    scn : Scenario
    model : ModalModel, optional
        Defaults to the scenario's model.
    chunk_revolutions : int
        Revolutions per yielded batch.
    envelope_step_s : float
        Grid step of the modal envelopes (exact integration; the step only sets the Hermite
        interpolation error of the envelopes, below 1e-9 relative at 2 ms).
    initial : {"steady", "rest"}
        Initial modal state (see :class:`~bttsim_stream.sim.modal.EnvelopeIntegrator`).
    n_revolutions : int, optional
        Stop after this many revolutions.
    """

    def __init__(self, scn, model=None, *, chunk_revolutions: int = 32, envelope_step_s: float = 2e-3,
                 initial: str = "steady", n_revolutions: int | None = None) -> None:
        self.scn = scn
        self.model = load_scenario_model(scn) if model is None else model
        m = self.model
        if m.n_blades != scn.rotor.n_blades and scn.model.source != "builtin":
            pass  # a user's model defines the blade count
        if np.any(m.damping_ratio >= 1.0):
            raise BttsimError("model: damping ratios must be < 1 (underdamped modes)")
        self.chunk = int(chunk_revolutions)
        self.speed: SpeedProfile = speed_profile_from_scenario(scn)
        seed = scn.run.seed
        self._rng = {name: np.random.default_rng(np.random.SeedSequence([seed, i]))
                     for i, name in enumerate(("probe", "jitter", "opr"))}
        nb = m.n_blades
        p = m.nominal_node
        self.p = p
        self.stagger = np.deg2rad(float(m.meta["stagger_deg"]))
        probes = np.deg2rad(np.asarray(scn.probes.angles_deg, float))
        err = np.deg2rad(scn.acquisition.probe_angle_error_deg) * self._rng["probe"].standard_normal(probes.size)
        self.probe_actual = probes + err
        self.theta_opr = np.deg2rad(scn.probes.opr_angle_deg)
        self.z_probe = scn.probes.axial_position_m
        self.tip_ref = m.tip_ref
        z_nodes = m.tip_ref[..., 2]
        if np.any(self.z_probe > z_nodes.max(axis=1)) or np.any(self.z_probe < z_nodes.min(axis=1)):
            raise BttsimError(
                f"[probes] axial_position_m = {self.z_probe * 1e3:.3f} mm lies outside the model's tip "
                f"nodes (z {z_nodes.min() * 1e3:.3f} .. {z_nodes.max() * 1e3:.3f} mm)")
        order = np.argsort(-z_nodes, axis=1)
        if not np.all(order == np.arange(m.n_tip)):
            raise BttsimError("model: tip nodes must be ordered from the trailing edge (z decreasing)")
        self.theta_p = m.tip_ref[:, p, 1]
        self.psi = np.mod(self.probe_actual[None, :] - self.theta_p[:, None] - self.theta_opr, TWO_PI)
        C, eo = modal_forcing(m, scn.excitation)
        self.eo = eo
        self.basis = tip_basis(m.tip_shapes)
        self.integrator = EnvelopeIntegrator(m.freq_hz, m.damping_ratio, C, eo, self.basis,
                                             self.speed, initial=initial)
        self.grid = build_grid(self.speed, envelope_step_s)
        self.h_env = envelope_step_s
        self._i_grid = 0
        self._env: EnvelopeGrid | None = None
        #: wall time spent integrating envelopes (per simulated second, scales with the
        #: responding modes) and on the crossings (per TOA, independent of the modes)
        self.timing = {"envelopes_s": 0.0, "crossings_s": 0.0}
        total = int(np.floor((self.speed.angle(self.speed.duration_s) - self.theta_opr) / TWO_PI))
        self.n_revolutions = max(0, total if n_revolutions is None else min(total, n_revolutions))
        v = self.basis.nodes[:, p, :]  # (r, 3)
        self._v_eqv = v[:, 1] + v[:, 2] / np.tan(self.stagger)  # (r,)
        acq = scn.acquisition
        self.info = RunInfo(
            n_blades=nb, n_probes=probes.size, n_revolutions=self.n_revolutions,
            probe_angles_rad=probes, probe_axial_m=self.z_probe,
            tip_radius_m=float(np.mean(m.tip_ref[:, p, 0])), opr_angle_rad=float(self.theta_opr),
            clock_hz=acq.clock_hz, stagger_deg=float(m.meta["stagger_deg"]),
            engine_orders=tuple(int(e.engine_order) for e in scn.excitation),
            nodal_diameters=tuple(int(e.nodal_diameter) for e in scn.excitation),
            toa_method=scn.toa.method, duration_s=self.speed.duration_s, seed=seed, rig=scn.run.rig,
            sensing_angles_rad=self.theta_p.copy(),
            family_freq_hz=None if m.campbell_freq_hz is None else np.array(m.campbell_freq_hz, float),
            speed_range_rpm=self.speed.rpm_range())

    # -- envelopes -------------------------------------------------------------------------
    def _envelopes(self, t_start: float, t_end: float) -> EnvelopeGrid:
        """Envelopes covering ``[t_start, t_end]``; earlier grid points are dropped.

        The integration advances in whole blocks of the global grid, so that the arithmetic
        (and so every bit of the output) does not depend on how revolutions are chunked.
        """
        i_end = min(int(np.searchsorted(self.grid, t_end)) + 1, self.grid.size - 1)
        parts = [] if self._env is None else [self._env]
        while self._i_grid < i_end or not parts:
            stop = min((self._i_grid // _BLOCK + 1) * _BLOCK, self.grid.size - 1)
            new = self.integrator.advance(self.grid[self._i_grid:stop + 1])
            parts.append(new if not parts else EnvelopeGrid(t=new.t[1:], G=new.G[1:], dG=new.dG[1:]))
            self._i_grid = stop
            if stop == self.grid.size - 1:
                break
        env = parts[0] if len(parts) == 1 else EnvelopeGrid(
            t=np.concatenate([q.t for q in parts]), G=np.concatenate([q.G for q in parts]),
            dG=np.concatenate([q.dG for q in parts]))
        first = max(0, int(np.searchsorted(env.t, t_start, side="right")) - 2)
        self._env = EnvelopeGrid(t=env.t[first:], G=env.G[first:], dG=env.dG[first:])
        return self._env

    # -- one chunk -------------------------------------------------------------------------
    def _chunk(self, revs: np.ndarray) -> RevolutionBatch:
        m, scn = self.model, self.scn
        nb, npr, nt, p = m.n_blades, self.psi.shape[1], m.n_tip, self.p
        nr = revs.size
        opr_edges = self.speed.time_at_angle(self.theta_opr + TWO_PI * np.arange(revs[0], revs[-1] + 2))
        phi_c = self.theta_opr + TWO_PI * revs[:, None, None] + self.psi[None]  # (nr, nb, np)
        t_r = self.speed.time_at_angle(phi_c).ravel()
        blade = np.broadcast_to(np.arange(nb)[None, :, None], phi_c.shape).ravel()
        phi_c = phi_c.ravel()
        margin = 2 * self.h_env + 2e-3
        t_clock = time.perf_counter()
        env = self._envelopes(float(t_r.min()) - margin, float(t_r.max()) + margin)
        self.timing["envelopes_s"] += time.perf_counter() - t_clock
        t_clock = time.perf_counter()
        cs = prepare_crossings(env, blade, t_r, self.basis.nodes)
        theta_n = self.tip_ref[blade][:, :, 1]  # (n_c, nt)
        radius = self.tip_ref[blade][:, :, 0]
        z_ref = self.tip_ref[blade][:, :, 2]
        w_r, dw_r = eval_compressed(cs, self.speed, self.eo, t_r[:, None])
        flat = self.basis.nodes.reshape(self.basis.nodes.shape[0], -1)
        u_all = (w_r[:, 0, :] @ flat).reshape(-1, nt, 3)
        du_all = (dw_r[:, 0, :] @ flat).reshape(-1, nt, 3)
        target_all = phi_c[:, None] + self.theta_p[blade][:, None] - theta_n
        # the two nodes predicted to straddle the probe's z (Eq. 10); checked after stage A
        dz_est = z_ref + u_all[..., 2] - self.z_probe
        k = np.clip(np.sum(dz_est >= 0, axis=1) - 1, 0, nt - 2)  # dz >= 0 for nodes <= k
        cand = k[:, None] + np.arange(2)[None, :]
        t_det, u, dz, residual = self._stage_a(cs, cand, t_r, target_all, radius, z_ref,
                                                u_all, du_all)
        toa, _, bracketed = stage_b(t_det, dz, scn.toa.axial_interpolation)
        bad = ~bracketed
        if np.any(bad):  # the deflection moved the straddling pair: take every node there
            sub = np.flatnonzero(bad)
            cs_b = CrossingSet(blade=cs.blade[sub], t0=cs.t0[sub], P=cs.P[:, sub], nodes=cs.nodes)
            cand_b = np.ascontiguousarray(np.broadcast_to(np.arange(nt), (sub.size, nt)))
            t_b, _, dz_b, res_b = self._stage_a(cs_b, cand_b, t_r[sub], target_all[sub], radius[sub],
                                                z_ref[sub], u_all[sub], du_all[sub])
            residual = max(residual, res_b)
            toa[sub], _, bracketed[sub] = stage_b(t_b, dz_b, scn.toa.axial_interpolation)
        # truth at the TOA: P_nom displacements, d_eqv (Eq. 3-4), Eq. 1 with exact t_exp
        up, _ = eval_nodes(cs, self.speed, self.eo, toa[:, None], np.full((toa.size, 1), p),
                           derivative=False)
        d_tang, d_z = up[:, 0, 1], up[:, 0, 2]
        d_eqv = d_tang + d_z / np.tan(self.stagger)
        omega_mean = TWO_PI / np.diff(opr_edges)
        shape = (nr, nb, npr)
        r_p = self.tip_ref[:, p, 0][None, :, None]
        d_eq1 = omega_mean[:, None, None] * r_p * (t_r.reshape(shape) - toa.reshape(shape))
        tau = (toa - cs.t0)[:, None, None]
        G = cs.P[0] + tau * (cs.P[1] + tau * (cs.P[2] + tau * cs.P[3]))  # (n_c, n_exc, r)
        amp = 2.0 * np.sum(np.abs(G @ self._v_eqv), axis=1)
        pkpk = amp.reshape(shape).max(axis=2)
        truth = Truth(opr_s=opr_edges[:-1], toa_s=toa.reshape(shape), t_exp_s=t_r.reshape(shape),
                      d_eqv_m=d_eqv.reshape(shape), d_tang_m=d_tang.reshape(shape),
                      d_z_m=d_z.reshape(shape), d_eq1_m=d_eq1, d_eqv_pkpk_m=pkpk,
                      omega_mean=omega_mean)
        out = self._acquire(revs, truth, float(residual), bracketed.reshape(shape))
        self.timing["crossings_s"] += time.perf_counter() - t_clock
        return out

    def _stage_a(self, cs, cand, t_r, target_all, radius, z_ref, u_all, du_all):
        """Stage A for the candidate nodes: HP Newton, then AD/PAD on the grid if asked."""
        rows = np.arange(cand.shape[0])[:, None]
        target = target_all[rows, cand]
        rad = radius[rows, cand]
        ur, ut = u_all[rows, cand, 0], u_all[rows, cand, 1]
        dur, dut = du_all[rows, cand, 0], du_all[rows, cand, 1]
        x = rad + ur
        delta = np.arctan2(ut, x)
        ddelta = (x * dut - ut * dur) / (x * x + ut * ut)
        phi_r, om_r, _ = self.speed.state(t_r)
        # first-order start: rigid node time corrected by the deflection and its rate at t_r
        g0 = phi_r[:, None] + delta - target
        t0 = t_r[:, None] - g0 / (om_r[:, None] + ddelta)
        t_det, u, residual = stage_a_hp(cs, self.speed, self.eo, cand, target, rad, t0)
        method = self.scn.toa.method
        if method in ("AD", "PAD"):
            t_det = stage_a_grid(cs, self.speed, self.eo, cand, target, rad, t_det,
                                 self.scn.toa.grid_step_s, method)
            u, _ = eval_nodes(cs, self.speed, self.eo, t_det, cand, derivative=False)
        dz = z_ref[rows, cand] + u[..., 2] - self.z_probe
        return t_det, u, dz, residual

    def _acquire(self, revs, truth: Truth, residual: float, bracketed) -> RevolutionBatch:
        acq = self.scn.acquisition
        toa = truth.toa_s.copy()
        opr = truth.opr_s.copy()
        if acq.trigger_jitter_s > 0:
            toa += acq.trigger_jitter_s * self._rng["jitter"].standard_normal(toa.shape)
        if acq.opr_jitter_s > 0:
            opr += acq.opr_jitter_s * self._rng["opr"].standard_normal(opr.shape)
        toa_ticks = opr_ticks = None
        if acq.clock_hz > 0:
            toa_ticks = np.floor(toa * acq.clock_hz).astype(np.int64)
            opr_ticks = np.floor(opr * acq.clock_hz).astype(np.int64)
            toa = toa_ticks / acq.clock_hz
            opr = opr_ticks / acq.clock_hz
        return RevolutionBatch(revolution=revs.astype(np.int64), opr_s=opr, toa_s=toa,
                               opr_ticks=opr_ticks, toa_ticks=toa_ticks, truth=truth,
                               residual_s=residual, bracketed=bracketed)

    def __iter__(self) -> Iterator[RevolutionBatch]:
        for n0 in range(0, self.n_revolutions, self.chunk):
            yield self._chunk(np.arange(n0, min(n0 + self.chunk, self.n_revolutions)))


def collect(batches) -> RevolutionBatch:
    """Concatenate batches along the revolution axis (for tests and offline studies)."""
    batches = list(batches)

    def cat(get):
        vals = [get(b) for b in batches]
        return None if vals[0] is None else np.concatenate(vals)

    truth = Truth(**{f: cat(lambda b, f=f: getattr(b.truth, f)) for f in Truth.__dataclass_fields__})
    return RevolutionBatch(revolution=cat(lambda b: b.revolution), opr_s=cat(lambda b: b.opr_s),
                           toa_s=cat(lambda b: b.toa_s), opr_ticks=cat(lambda b: b.opr_ticks),
                           toa_ticks=cat(lambda b: b.toa_ticks), truth=truth,
                           residual_s=max(b.residual_s for b in batches),
                           bracketed=cat(lambda b: b.bracketed))

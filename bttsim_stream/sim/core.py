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

from ..errors import BttsimError, ScenarioError
from ..model import build_model, load_model
from ..model.speed_modes import is_speed_dependent
from .bounds import check_tip_amplitude, check_tip_nodes
from .modal import FixedModes, GridPoints
from .records import RevolutionBatch, RunInfo, Truth
from .signal import RawSignals
from .sources import Carriers, NonSynchronous, excitation_sources
from .speed import SpeedProfile, speed_profile_from_scenario
from .speed_modal import SpeedDependentModes
from .stages import Acquired, Passages, acquisition_stages, stream, toa_method
from .toa import crossing_frame, eval_planes, hermite_in_place, hp_crossings, project_planes, stage_b

__all__ = ["CROSSINGS_PER_CHUNK", "RunInfo", "Truth", "RevolutionBatch", "RunUpSimulator", "load_scenario_model",
           "collect"]

TWO_PI = 2.0 * np.pi

#: Crossings per batch by default: large enough that per-batch costs vanish, small enough
#: that a batch's crossing arrays (tens of values per crossing) stay in a core's cache
#: (measured best between about 2,000 and 4,000 for 1 to 16 probes).
CROSSINGS_PER_CHUNK = 2320




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
    chunk_revolutions : int, optional
        Revolutions per yielded batch (the results do not depend on it). Default: about
        :data:`CROSSINGS_PER_CHUNK` crossings per batch (16 revolutions of 29 blades and 5
        probes), at most 64 revolutions.
    envelope_step_s : float
        Grid step of the modal envelopes (exact integration; the step only sets the Hermite
        interpolation error of the envelopes, below 1e-9 relative at 2 ms).
    initial : {"steady", "rest"}, optional
        Initial modal state (see :class:`~bttsim_stream.sim.modal.EnvelopeIntegrator`);
        default the scenario's ``[speed] initial``.
    n_revolutions : int, optional
        Stop after this many revolutions.
    """

    def __init__(self, scn, model=None, *, chunk_revolutions: int | None = None, envelope_step_s: float = 2e-3,
                 initial: str | None = None, n_revolutions: int | None = None) -> None:
        self.scn = scn
        self.model = load_scenario_model(scn) if model is None else model
        m = self.model
        if np.any(m.damping_ratio >= 1.0):
            raise BttsimError("model: damping ratios must be < 1 (underdamped modes)")
        self.speed: SpeedProfile = speed_profile_from_scenario(scn)
        self.p = p = m.nominal_node
        self.stagger = np.deg2rad(float(m.meta["stagger_deg"]))
        probes = np.deg2rad(np.asarray(scn.probes.angles_deg, float))
        err = np.deg2rad(scn.acquisition.probe_angle_error_deg) * stream(scn.run.seed, 0).standard_normal(probes.size)
        self.probe_actual = probes + err
        self.theta_opr = np.deg2rad(scn.probes.opr_angle_deg)
        self.z_probe = scn.probes.axial_position_m
        self.tip_ref = m.tip_ref
        check_tip_nodes(m, self.z_probe)
        self.theta_p = m.tip_ref[:, p, 1]
        self.chunk = (int(chunk_revolutions) if chunk_revolutions is not None else
                      max(1, min(64, round(CROSSINGS_PER_CHUNK / (m.n_blades * probes.size)))))
        self.psi = np.mod(self.probe_actual[None, :] - self.theta_p[:, None] - self.theta_opr, TWO_PI)
        modes = SpeedDependentModes(m) if is_speed_dependent(m) else FixedModes(m)
        self.basis = modes.basis
        v = self.basis.nodes[:, p, :]  # (r, 3)
        self._v_eqv = v[:, 1] + v[:, 2] / np.tan(self.stagger)  # (r,): d_eqv at P_nom (Eq. 3-4)
        # a force near the float limit overflows the forcing to inf and the bound with it, which
        # is refused below in one line: the overflow warnings would only repeat it
        with np.errstate(over="ignore", invalid="ignore"):
            self.sources = excitation_sources(scn, m, self.speed, modes, self._v_eqv)
            #: the scenario's non-synchronous vibration (:class:`~bttsim_stream.sim.nsv.NsvSetup`) or None
            self.nsv = next((s.nsv for s in self.sources if isinstance(s, NonSynchronous)), None)
            check_tip_amplitude(scn, m, self.sources)  # refuses non-synchronous options with speed-dependent modes
        forced = self._lay_out_carriers()
        initial = scn.speed.initial if initial is None else initial
        self.integrator = modes.integrator(forced, scn.excitation, self.speed, initial)
        self._build_grid(envelope_step_s)
        self._i_grid = 0
        self._buf_t: np.ndarray | None = None  # envelope grid points kept: [_lo, _hi)
        self._buf: np.ndarray | None = None
        self._lo = self._hi = 0
        #: CPU time spent integrating envelopes (per simulated second, scales with the
        #: responding modes) and on the crossings (per TOA, independent of the modes)
        self.timing = {"envelopes_s": 0.0, "crossings_s": 0.0}
        total = int(np.floor((self.speed.angle(self.speed.duration_s) - self.theta_opr) / TWO_PI))
        self.n_revolutions = max(0, total if n_revolutions is None else min(total, n_revolutions))
        if self.n_revolutions < 1:  # the scenario's check leaves a rounding's width: no run without one
            raise ScenarioError("the speed profile makes no whole revolution between two OPR pulses: raise the "
                                "speed or duration_s")
        r = self.basis.nodes.shape[0]
        self._VT = np.ascontiguousarray(self.basis.nodes.reshape(r, -1).T)  # (nt * 3, r)
        # P_nom tangential, axial and d_eqv direction (Eq. 3-4)
        self._V_truth = np.stack([v[:, 1], v[:, 2], self._v_eqv], axis=1)[:, None, :]  # (r, 1, 3)
        self._radius = np.ascontiguousarray(m.tip_ref[..., 0])  # (nb, nt)
        self._z_ref = np.ascontiguousarray(m.tip_ref[..., 2])
        self._dtheta = self.theta_p[:, None] - m.tip_ref[..., 1]  # theta_Pnom - theta_node
        self._pattern: dict = {}
        # offsets of a crossing's envelope values in the buffer (see _envelopes), in the order
        # (grid point i / i + 1, G / dG, excitation, r, re / im), for a buffer of cap points
        n_exc, nb = self.eo.size, m.n_blades
        pt, g, mm, j, c = np.ix_(np.arange(2), np.arange(2), np.arange(n_exc), np.arange(r), np.arange(2))
        self._gather_plane = (((g * n_exc + mm) * 2 + c) + 0 * pt + 0 * j)[..., None]
        self._gather_rest = (pt * (nb * r) + j + 0 * (g + mm + c))[..., None]
        self._gather_off = None
        # envelope integration block (global grid steps): longer for fewer responding modes
        n_act = max(int(self.integrator.active.size), 1)
        self._block = int(np.clip(2 ** int(np.log2(max(32768 // n_act, 1))), 64, 512))
        self.toa_method = toa_method(scn.toa)
        self.stages = acquisition_stages(scn, self.speed, m.tip_ref[:, p, 0])
        self.info = self._run_info(probes)

    def _lay_out_carriers(self) -> Carriers:
        """Every source's forced carriers, then every source's closed-form ones: sets the carrier
        phases ``eo``, ``omega`` (None: all 0) and each source's carrier indices; returns the
        forced carriers (the envelope recursion's)."""
        forced = [s.forced for s in self.sources]
        closed = [s.closed for s in self.sources]
        every = forced + closed
        #: carrier phases ``EO_m phi(t) + omega_m t`` of every carrier (None: all omega 0)
        self.eo = np.concatenate([c.eo for c in every])
        self.omega = None
        if any(c.omega is not None for c in every):
            self.omega = np.concatenate([np.zeros(c.size) if c.omega is None else c.omega for c in every])
        n_forced = sum(c.size for c in forced)
        self._n_forced = n_forced  # carriers of the envelope recursion
        starts_f = np.cumsum([0] + [c.size for c in forced])
        starts_c = n_forced + np.cumsum([0] + [c.size for c in closed])
        self._rows = [_rows(np.r_[starts_f[k]:starts_f[k + 1], starts_c[k]:starts_c[k + 1]])
                      for k in range(len(self.sources))]
        C = np.concatenate([c.C for c in forced], axis=1)
        omega = None if self.omega is None else self.omega[:n_forced]
        return Carriers(self.eo[:n_forced], omega, C)

    def _build_grid(self, step_s: float) -> None:
        """The envelope grid: shorter steps where a free response is present (a start from
        rest, a speed knot); the sources' warnings about the step join the integrator's."""
        m = self.model
        radius = float(np.mean(m.tip_ref[:, self.p, 0]))
        near = np.argsort(np.abs(m.tip_ref[..., 2] - self.z_probe), axis=1)[:, :4]  # candidate nodes
        reach = radius * float(np.max(np.abs(self.theta_p[:, None] - np.take_along_axis(m.tip_ref[..., 1], near, 1))))
        self.grid = GridPoints(self.speed, step_s, self.integrator.transient_grid(step_s, radius, reach))
        self.h_env = step_s
        for s in self.sources:
            self.integrator.warnings.extend(s.warnings(step_s, radius, self.speed))

    def _run_info(self, probes: np.ndarray) -> RunInfo:
        m, scn, p = self.model, self.scn, self.p
        return RunInfo(
            n_blades=m.n_blades, n_probes=probes.size, n_revolutions=self.n_revolutions,
            probe_angles_rad=probes, probe_axial_m=self.z_probe,
            tip_radius_m=float(np.mean(m.tip_ref[:, p, 0])), opr_angle_rad=float(self.theta_opr),
            clock_hz=scn.acquisition.clock_hz, stagger_deg=float(m.meta["stagger_deg"]),
            engine_orders=tuple(int(e.engine_order) for e in scn.excitation),
            nodal_diameters=tuple(int(e.nodal_diameter) for e in scn.excitation),
            toa_method=scn.toa.method, duration_s=self.speed.duration_s, seed=scn.run.seed, rig=scn.run.rig,
            sensing_angles_rad=self.theta_p.copy(),
            family_freq_hz=None if m.campbell_freq_hz is None else np.array(m.campbell_freq_hz, float),
            **_family_curves(m), speed_range_rpm=self.speed.rpm_range())

    # -- envelopes -------------------------------------------------------------------------
    def _envelopes(self, t_start: float, t_end: float) -> tuple[np.ndarray, np.ndarray]:
        """Envelopes covering ``[t_start, t_end]``; earlier grid points are dropped.

        The integration advances in whole blocks of the global grid, so that the arithmetic
        (and so every bit of the output) does not depend on how revolutions are chunked. The
        grid points are kept in a buffer that is reused (memory does not grow with the run).

        Returns
        -------
        t : ndarray, shape (n,)
            Grid times.
        GD : ndarray, shape (4 * n_exc, cap, n_blades * r)
            The buffer: planes of envelopes ``G`` then derivatives ``dG``, per excitation,
            real then imaginary parts, each holding ``(n_blades, r)`` values per grid point
            (so that the integrator's matrix products write contiguous blocks); grid point
            ``k`` of ``t`` is at index ``lo + k`` of a plane.
        lo : int
        """
        i_end = min(self.grid.searchsorted(t_end) + 1, self.grid.size - 1)
        while self._i_grid < i_end or self._hi == 0:
            stop = min((self._i_grid // self._block + 1) * self._block, self.grid.size - 1)
            t_blk = self.grid.points(self._i_grid, stop + 1)
            first = 0 if self._hi == 0 else 1  # the block's first point is the last one kept
            n_new = t_blk.size - first
            self._reserve(n_new, t_start)
            hi = self._hi
            n_exc = self.eo.size
            # (G, dG) x excitation x (re, im) planes of (grid point, blade, r), written by the
            # integrator's matrix products straight into the buffer, one contiguous block each
            planes = self._buf[:, hi:hi + n_new].reshape(2, n_exc, 2, n_new, -1)
            self.integrator.advance(t_blk, out=planes[:, :self._n_forced], first=first)
            if self._n_forced < n_exc:  # closed-form carriers (flutter): the sources' own envelopes
                self._closed_envelopes(t_blk[first:], planes)
            self._buf_t[hi:hi + n_new] = t_blk[first:]
            self._hi = hi + n_new
            self._i_grid = stop
            if stop == self.grid.size - 1:
                break
        lo, hi = self._lo, self._hi
        self._lo = max(lo, lo + int(np.searchsorted(self._buf_t[lo:hi], t_start, side="right")) - 2)
        return self._buf_t[self._lo:hi], self._buf, self._lo

    def _closed_envelopes(self, t: np.ndarray, planes: np.ndarray) -> None:
        """Write the closed-form carriers' envelopes at ``t`` into ``planes`` (see :meth:`_envelopes`)."""
        j = self._n_forced
        for s in self.sources:
            for G, dG in s.closed_envelopes(t):
                for g, X in enumerate((G, dG)):
                    X = X.reshape(X.shape[0], -1)
                    planes[g, j, 0] = X.real
                    planes[g, j, 1] = X.imag
                j += 1

    def _reserve(self, n: int, t_start: float) -> None:
        """Room for ``n`` more grid points: when the buffer is full, the points still needed
        (from ``t_start`` on) move to its front (it grows only if they do not fit)."""
        if self._buf is not None and self._hi + n <= self._buf_t.size:
            return
        lo, hi = self._lo, self._hi
        if self._buf is not None:
            lo = max(lo, lo + int(np.searchsorted(self._buf_t[lo:hi], t_start, side="right")) - 2)
        keep = hi - lo
        cap = max(2 * (keep + n), 4 * self._block + 8)
        n_exc, r, nb = self.eo.size, self.basis.nodes.shape[0], self.model.n_blades
        if self._buf is None or cap > self._buf_t.size:
            buf_t, buf = np.empty(cap), np.empty((4 * n_exc, cap, nb * r))
            self._gather_off = self._gather_plane * (cap * nb * r) + self._gather_rest
        else:
            buf_t, buf = self._buf_t, self._buf
        if keep:
            buf_t[:keep] = self._buf_t[lo:hi]
            buf[:, :keep] = self._buf[:, lo:hi]
        self._buf_t, self._buf, self._lo, self._hi = buf_t, buf, 0, keep

    # -- one chunk -------------------------------------------------------------------------
    def _chunk(self, revs: np.ndarray) -> RevolutionBatch:
        """One batch of revolutions, every blade and probe at once (crossings on the last axis).

        1. Rigid crossing time ``t_r`` of P_nom at each probe (exact inverse of Eq. 6).
        2. The blade's compressed envelope around ``t_r``: cubic Hermite coefficients,
           evaluated at ``t_r`` and projected onto every tip node (axial: which two nodes
           straddle the probe's z, Eq. 10; radial and tangential: first-order start).
        3. Once per batch, the Hermite coefficients are projected onto the (radial,
           tangential, axial) components of the two candidate nodes and of P_nom
           (:func:`~bttsim_stream.sim.toa.local_motion`); stage A (HP Newton, Eq. 8; AD / PAD,
           Eq. 12-14) and the truth then evaluate short complex cubics only.
        4. Stage B (Eq. 9-11); crossings whose pair did not straddle the probe are redone
           with every node.
        5. The truth at the TOAs (every excitation source its own part), then the acquisition
           stages.
        """
        nb, npr = self.model.n_blades, self.psi.shape[1]
        nr = revs.size
        shape = (nr, nb, npr)
        opr_edges = self.speed.time_at_angle(self.theta_opr + TWO_PI * np.arange(revs[0], revs[-1] + 2))
        phi_c = (self.theta_opr + TWO_PI * revs[:, None, None] + self.psi[None]).ravel()  # (n,)
        t_r = self.speed.time_at_angle(phi_c)
        blade, z_ref_t = self._chunk_pattern(nr)
        margin = 2 * self.h_env + 2e-3
        t_clock = time.process_time()
        env_t, GD, lo = self._envelopes(float(t_r.min()) - margin, float(t_r.max()) + margin)
        self.timing["envelopes_s"] += time.process_time() - t_clock
        t_clock = time.process_time()
        cx = self._at_rigid_times(env_t, GD, lo, t_r, blade)
        toa, bracketed, residual = self._toas(cx, phi_c, t_r, blade, z_ref_t)
        X, cr, ci = self._truth_envelopes(cx, toa, t_r)
        d_tang = np.sum(X[:, 0, 1] * cr + X[:, 0, 0] * ci, axis=0)
        d_z = np.sum(X[:, 1, 1] * cr + X[:, 1, 0] * ci, axis=0)
        d_eqv = d_tang + d_z / np.tan(self.stagger)
        omega_mean = TWO_PI / np.diff(opr_edges)
        fields = {}
        for s, rows in zip(self.sources, self._rows):
            fields.update(s.truth(X[rows, 2], omega_mean, shape))
        r_p = self.tip_ref[:, self.p, 0][None, :, None]
        d_eq1 = omega_mean[:, None, None] * r_p * (t_r.reshape(shape) - toa.reshape(shape))
        truth = Truth(opr_s=opr_edges[:-1], toa_s=toa.reshape(shape), t_exp_s=t_r.reshape(shape),
                      d_eqv_m=d_eqv.reshape(shape), d_tang_m=d_tang.reshape(shape),
                      d_z_m=d_z.reshape(shape), d_eq1_m=d_eq1, omega_mean=omega_mean, **fields)
        out = self._acquire(revs, truth, float(residual), bracketed.reshape(shape),
                            Passages(toa, blade, lambda: self._radial_at_toa(cx, toa, cr, ci)))
        self.timing["crossings_s"] += time.process_time() - t_clock
        return out

    def _at_rigid_times(self, env_t, GD, lo, t_r, blade) -> _Crossings:
        """Each crossing's blade envelope as cubic Hermite coefficients, and the tip-node
        displacements and velocities at its rigid time ``t_r`` (step 2 of :meth:`_chunk`)."""
        nb, nt = self.model.n_blades, self.model.n_tip
        # 2. Hermite coefficients of each crossing's blade envelope, crossings last
        i = _clip_index(np.searchsorted(env_t, t_r, side="right") - 1, env_t.size - 2)
        t0 = env_t[i]
        n_exc, r = self.eo.size, self.basis.nodes.shape[0]
        # (2 [i, i + 1], 2 [G, dG], n_exc, r, 2 [re, im], n): envelope data, crossings last
        # [G0, dG0, G1, dG1] x (n_exc, r, re/im), crossings last, gathered element by element
        # straight into the layout of the Hermite coefficients (4, n_exc, r, 2, n)
        idx = ((lo + i) * (nb * r) + blade * r) + self._gather_off  # (2, 2, n_exc, r, 2, n)
        CPr = hermite_in_place(np.take(GD.reshape(-1), idx).reshape(4, n_exc, r, 2, -1), env_t[i + 1] - t0)
        frame = crossing_frame(self.speed, t0, t_r, self.eo, self.omega)
        om_r = frame.om_ref
        tau = t_r - t0
        c0, s0 = frame.rot[:, 0, None, :], frame.rot[:, 1, None, :]  # (n_exc, 1, n)
        Gr = eval_planes(CPr, tau)  # (n_exc, r, 2, n) at t_r, no carrier
        dGr = np.multiply(CPr[3], 3.0)
        dGr *= tau
        tmp = np.multiply(CPr[2], 2.0)
        dGr += tmp
        dGr *= tau
        dGr += CPr[1]
        # Im(G e^{i th}) and Im((G' + i EO Omega G) e^{i th}) at t_r (in place, the same
        # operations in the same order)
        tmp = tmp[:, :, 0]  # (n_exc, r, n) scratch
        w_r = Gr[:, :, 1] * c0
        w_r += np.multiply(Gr[:, :, 0], s0, out=tmp)
        dw_r = dGr[:, :, 1] * c0
        dw_r += np.multiply(dGr[:, :, 0], s0, out=tmp)
        rate = self.eo[:, None] * om_r if self.omega is None else self.eo[:, None] * om_r + self.omega[:, None]
        d = np.multiply(Gr[:, :, 0], c0, out=dGr[:, :, 0])  # dGr no longer needed
        d -= np.multiply(Gr[:, :, 1], s0, out=tmp)
        d *= rate[:, None, :]
        dw_r += d
        if n_exc > 1:
            w_r, dw_r = w_r.sum(axis=0), dw_r.sum(axis=0)
        else:
            w_r, dw_r = w_r[0], dw_r[0]
        u_r = (self._VT @ w_r).reshape(nt, 3, -1)  # (nt, 3, n) at t_r
        du_r = (self._VT @ dw_r).reshape(nt, 3, -1)
        return _Crossings(CPr, t0, frame, u_r, du_r)

    def _toas(self, cx: _Crossings, phi_c, t_r, blade, z_ref_t):
        """Stage A for the two candidate nodes of every crossing, stage B between them, and
        every node where they did not straddle the probe (steps 3-4 of :meth:`_chunk`).

        Returns the TOAs (n,), whether a pair bracketed the probe (n,) and the largest final
        Newton step."""
        nt, scn = self.model.n_tip, self.scn
        frame, CPr, u_r, du_r = cx.frame, cx.CPr, cx.u_r, cx.du_r
        phi_r, om_r = frame.phi_ref, frame.om_ref
        dz_est = z_ref_t + u_r[:, 2]
        dz_est -= self.z_probe  # (nt, n)
        k = _clip_index(np.sum(dz_est >= 0, axis=0) - 1, nt - 2)  # dz >= 0 for nodes <= k (Eq. 10)
        # 3. the two candidate nodes k, k+1 of every crossing, from one projection onto the
        # nodes k_min .. k_max + 1 of the batch
        k_lo, k_hi = int(k.min()), int(k.max())
        P_u = project_planes(CPr, self.basis.nodes[:, k_lo:k_hi + 2, :])  # (4, n_exc, q_u, 3, 2, n)
        P2 = _pair(lambda o: P_u[:, :, o:o + 2], k - k_lo, k_hi - k_lo)
        flat = blade * nt + k  # (blade, node k) of every crossing, flattened
        cand = flat[None, :] + np.arange(2)[:, None]  # (2, n): nodes k, k + 1
        lm = frame.with_P(P2)
        tgt = (phi_c - phi_r)[None, :] + np.take(self._dtheta, cand)  # rotor-angle target minus phi(t_r)
        t_det, dz, residual = self._stage_a(lm, np.take(self._radius, cand), np.take(self._z_ref, cand), tgt,
                                            t_r, om_r,
                                            _pair(lambda o: u_r[k_lo + o:k_lo + o + 2], k - k_lo, k_hi - k_lo),
                                            _pair(lambda o: du_r[k_lo + o:k_lo + o + 2], k - k_lo, k_hi - k_lo))
        if scn.toa.axial_interpolation:  # stage B for a pair (Eq. 9-11), as stage_b does
            pos0 = dz[0] >= 0
            bracketed = pos0 != (dz[1] >= 0)
            t1, t2 = np.where(pos0, t_det[0], t_det[1]), np.where(pos0, t_det[1], t_det[0])
            z1, z2 = np.where(pos0, dz[0], dz[1]), np.where(pos0, dz[1], dz[0])
            toa = t1 - z1 * (t2 - t1) / (z2 - z1)
        else:
            toa, _, bracketed = stage_b(t_det.T, dz.T, False)
        bad = np.flatnonzero(~bracketed)
        if bad.size:  # the deflection moved the straddling pair: take every node there
            lm_b = frame.take(bad).with_P(project_planes(CPr[..., bad], self.basis.nodes))
            bb = blade[bad]
            t_b, dz_b, res_b = self._stage_a(lm_b, self._radius[bb].T, self._z_ref[bb].T,
                                             (phi_c - phi_r)[bad][None, :] + self._dtheta[bb].T, t_r[bad],
                                             om_r[bad], u_r[..., bad], du_r[..., bad])
            residual = max(residual, res_b)
            toa[bad], _, bracketed[bad] = stage_b(t_b.T, dz_b.T, scn.toa.axial_interpolation)
        return toa, bracketed, residual

    def _truth_envelopes(self, cx: _Crossings, toa, t_r):
        """P_nom's tangential, axial and ``d_eqv`` (Eq. 3-4) envelopes at the TOAs, shape
        (n_exc, 3, 2 [re, im], n), and every carrier's ``exp(i theta(t_TOA))`` as real and
        imaginary parts (n_exc, n)."""
        frame = cx.frame
        P_t = project_planes(cx.CPr, self._V_truth)[:, :, 0]  # (4, n_exc, 3, 2, n): tang, axial, eqv
        X = eval_planes(P_t, toa - cx.t0)  # (n_exc, 3, 2, n)
        th = self.eo[:, None] * frame.angle_change(self.speed, toa[None, :])[0]  # (n_exc, n)
        if self.omega is not None:
            th += self.omega[:, None] * (toa - t_r)[None, :]
        cd, sd = np.cos(th), np.sin(th)
        c0, s0 = frame.rot[:, 0], frame.rot[:, 1]
        return X, cd * c0 - sd * s0, sd * c0 + cd * s0  # exp(i EO phi(t_TOA))

    def _radial_at_toa(self, cx: _Crossings, toa, cr, ci) -> np.ndarray:
        """Radial displacement of P_nom at the TOAs, m (n,): the tip clearance's change."""
        p = self.p
        X_r = eval_planes(project_planes(cx.CPr, self.basis.nodes[:, p:p + 1, 0:1])[:, :, 0], toa - cx.t0)
        return np.sum(X_r[:, 0, 1] * cr + X_r[:, 0, 0] * ci, axis=0)

    def _chunk_pattern(self, nr: int):
        """The blade of every crossing of ``nr`` revolutions, shape (n,), and the blades'
        reference tip-node z, shape (n_tip, n) (cached: every chunk but the last has the same)."""
        cached = self._pattern.get(nr)
        if cached is None:
            blade = np.tile(np.repeat(np.arange(self.model.n_blades), self.psi.shape[1]), nr)
            cached = self._pattern[nr] = (blade, np.ascontiguousarray(self._z_ref[blade].T))
        return cached

    def _stage_a(self, lm, rad, z_ref, target_rel, t_r, om_r, u_r, du_r):
        """Stage A for the candidate nodes (q per crossing): first-order start, HP Newton,
        then AD / PAD on the grid if asked.

        Parameters
        ----------
        lm : LocalMotion
            The candidates' (radial, tangential, axial) motion.
        rad, z_ref, target_rel : ndarray, shape (q, n)
            Reference radius and axial position of each candidate, and the rotor angle at
            which it would reach the probe rigidly, minus ``phi(t_r)``.
        u_r, du_r : ndarray, shape (q, 3, n)
            Displacements and velocities at ``t_r``.

        Returns the crossing times, ``z_node(t) - z_probe`` (both (q, n)) and the largest
        final Newton step."""
        x = rad + u_r[:, 0]
        ut = u_r[:, 1]
        delta = np.arctan2(ut, x)
        ddelta = (x * du_r[:, 1] - ut * du_r[:, 0]) / (x * x + ut * ut)
        # first-order start: rigid node time corrected by the deflection and its rate at t_r
        t_start = t_r - (delta - target_rel) / (om_r + ddelta)
        t_det, u, residual = hp_crossings(lm, self.speed, target_rel, rad, t_start)
        t_det, u = self.toa_method.refine(lm, self.speed, target_rel, rad, t_det, u)
        dz = z_ref + u[:, 2] - self.z_probe
        return t_det, dz, residual

    def _acquire(self, revs, truth: Truth, residual: float, bracketed, passages: Passages) -> RevolutionBatch:
        """The batch as acquired: the exact TOAs and OPR times through every acquisition stage."""
        acq = Acquired(toa_s=truth.toa_s.copy(), opr_s=truth.opr_s.copy())
        for stage in self.stages:
            stage.apply(acq, passages)
        return RevolutionBatch(revolution=revs.astype(np.int64), opr_s=acq.opr_s, toa_s=acq.toa_s,
                               opr_ticks=acq.opr_ticks, toa_ticks=acq.toa_ticks, truth=truth,
                               residual_s=residual, bracketed=bracketed, n_edges=acq.n_edges,
                               clearance_m=acq.clearance_m, signal=acq.signal, extra_passage=acq.extra_passage,
                               extra_toa_s=acq.extra_toa_s, extra_toa_ticks=acq.extra_toa_ticks)

    def __iter__(self) -> Iterator[RevolutionBatch]:
        for n0 in range(0, self.n_revolutions, self.chunk):
            yield self._chunk(np.arange(n0, min(n0 + self.chunk, self.n_revolutions)))


@dataclass(frozen=True, slots=True, eq=False)
class _Crossings:
    """A batch's crossings at their rigid times ``t_r`` (crossings on the last axis).

    Attributes
    ----------
    CPr : ndarray, shape (4, n_exc, r, 2, n)
        Cubic Hermite coefficients of each crossing's blade envelope from grid time ``t0``.
    t0 : ndarray, shape (n,)
    frame : CrossingFrame
        Carrier rotation and rotor phase at ``t_r`` (:func:`~bttsim_stream.sim.toa.crossing_frame`).
    u_r, du_r : ndarray, shape (n_tip, 3, n)
        Tip-node displacements and velocities at ``t_r``.
    """

    CPr: np.ndarray
    t0: np.ndarray
    frame: object
    u_r: np.ndarray
    du_r: np.ndarray


def _rows(idx: np.ndarray):
    """Carrier indices as a slice when they run without a gap (a view, not a copy)."""
    if idx.size and np.all(np.diff(idx) == 1):
        return slice(int(idx[0]), int(idx[-1]) + 1)
    return idx


def _family_curves(model) -> dict:
    """``family_speed_rad_s`` and ``family_freq_hz_at_speed`` of :class:`RunInfo` (None for a
    zero-speed model, or one without a Campbell table at its speeds)."""
    e = model.extra
    if model.campbell_freq_hz is None or not is_speed_dependent(model) or "campbell_freq_hz_at_speed" not in e:
        return {"family_speed_rad_s": None, "family_freq_hz_at_speed": None}
    return {"family_speed_rad_s": np.array(e["speed_rad_s"], float),
            "family_freq_hz_at_speed": np.array(e["campbell_freq_hz_at_speed"], float)}


def _clip_index(k: np.ndarray, top: int) -> np.ndarray:
    """Integer indices ``k`` clipped to ``0 .. top`` (``np.clip``'s Python-level checks cost more
    than the two comparisons on a batch)."""
    k = np.maximum(k, 0, out=k)
    return np.minimum(k, top, out=k)


def _pair(window, off: np.ndarray, n_off: int) -> np.ndarray:
    """Per crossing (last axis), the node pair ``window(off)`` of its own offset ``off``.

    ``window(o)`` is an array holding nodes ``k_lo + o`` and ``k_lo + o + 1`` on some axis;
    ``off`` (n,) lies in ``0 .. n_off``. One elementwise selection per extra offset (the
    offsets of a batch span one or two nodes), cheaper than a gather.
    """
    out = window(0)
    for o in range(1, n_off + 1):
        out = np.where(off == o, window(o), out)
    return out


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
                           bracketed=cat(lambda b: b.bracketed), n_edges=cat(lambda b: b.n_edges),
                           clearance_m=cat(lambda b: b.clearance_m),
                           signal=(None if batches[0].signal is None
                                   else RawSignals.concatenate(b.signal for b in batches)),
                           extra_passage=None if batches[0].extra_passage is None else np.concatenate(
                               [b.extra_passage + off for b, off in zip(batches, np.cumsum(
                                   [0] + [b.toa_s.size for b in batches[:-1]]))]),
                           extra_toa_s=cat(lambda b: b.extra_toa_s), extra_toa_ticks=cat(lambda b: b.extra_toa_ticks))

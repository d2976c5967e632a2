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

from ..defaults import MAX_TIP_AMPLITUDE_FRACTION
from ..errors import BttsimError
from ..model import build_model, load_model
from ..model.speed_modes import check_speed_range, crossing_speeds, is_speed_dependent, models_at_speeds
from .modal import (TRANSIENT_TOL_S, EnvelopeIntegrator, GridPoints, modal_forcing, modal_response_bound,
                    tip_basis)
from .nsv import build_nsv
from .speed_modal import SpeedDependentIntegrator, speed_tip_basis
from .signal import (Digitiser, LowFrequencyNoise, ProbeModel, PulseParameters, RawSignals, Trigger, apply_triggers,
                     centrifugal_growth_m, pulse_parameters, synthesise)
from .speed import SpeedProfile, speed_profile_from_scenario
from .toa import (crossing_frame, eval_local, eval_planes, grid_crossings, hermite_in_place, hp_crossings,
                  project_planes, stage_b)

__all__ = ["CROSSINGS_PER_CHUNK", "RunInfo", "Truth", "RevolutionBatch", "RunUpSimulator", "load_scenario_model",
           "TipAmplitudeBound", "tip_amplitude_bound", "check_tip_amplitude", "collect"]

TWO_PI = 2.0 * np.pi

#: Crossings per batch by default: large enough that per-batch costs vanish, small enough
#: that a batch's crossing arrays (tens of values per crossing) stay in a core's cache
#: (measured best between about 2,000 and 4,000 for 1 to 16 probes).
CROSSINGS_PER_CHUNK = 2320


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
        The model's mode family frequencies per nodal diameter (Campbell diagram), Hz, at
        zero speed.
    family_speed_rad_s : ndarray, shape (S,), or None
        A speed-dependent model's sample speeds (``speed_rad_s``), rad/s, strictly ascending
        from 0; None: the family frequencies do not change with speed (a zero-speed model).
    family_freq_hz_at_speed : ndarray, shape (S, n_families, n_blades // 2 + 1), or None
        ``family_freq_hz`` at each of those speeds (row 0 is ``family_freq_hz``; the model's
        ``campbell_freq_hz_at_speed``), Hz; between them interpolated as the modes are
        (:func:`~bttsim_stream.model.speed_modes.interpolate_freq_hz`). Given with
        ``family_speed_rad_s`` and ``family_freq_hz`` or not at all.
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
    family_speed_rad_s: np.ndarray | None = None
    family_freq_hz_at_speed: np.ndarray | None = None
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
        revolution's arrivals of ``2 sum_m |G_eqv,m|`` over the engine-order excitations;
        exact for one engine order).
    omega_mean : ndarray, shape (n_rev,)
        Mean speed over the revolution, rad/s.
    nsv_kind : ndarray of str, shape (n_rev, n_nsv), or None
        With non-synchronous vibration in the scenario (:mod:`~bttsim_stream.sim.nsv`), per
        revolution and component: ``"rotating_stall"``, ``"flutter"`` or ``"broadband"``
        (None: the scenario has none; the ``nsv_*`` fields are all None then).
    nsv_freq_hz : ndarray, shape (n_rev, n_nsv)
        Frequency in the rotor frame at the revolution's mean speed, Hz (broadband: the band
        centre).
    nsv_nd : ndarray of int64, shape (n_rev, n_nsv)
        Signed nodal diameter (:mod:`~bttsim_stream.process.travelling_wave` convention);
        broadband: 0 (random blade phases: every ND).
    nsv_amp_pkpk_m : ndarray, shape (n_rev, n_nsv)
        Peak-to-peak ``d_eqv`` at P_nom: largest over the revolution's arrivals of
        ``2 |G_eqv|`` of the component (0 when absent, e.g. flutter before onset);
        broadband: ``2 sqrt(2)`` times its rms (a sine of that rms).
    nsv_rms_m : ndarray, shape (n_rev, n_nsv)
        Rms of the component's ``d_eqv`` at P_nom over the revolution's arrivals
        (``sqrt(mean sum_j |G_eqv,j|^2 / 2)``), m.
    nsv_band_hz : ndarray, shape (n_rev, n_nsv, 2)
        Broadband: the force band (low, high), Hz; else (0, 0).
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
    nsv_kind: np.ndarray | None = None
    nsv_freq_hz: np.ndarray | None = None
    nsv_nd: np.ndarray | None = None
    nsv_amp_pkpk_m: np.ndarray | None = None
    nsv_rms_m: np.ndarray | None = None
    nsv_band_hz: np.ndarray | None = None


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
    n_edges : ndarray of int64, shape (n_rev, n_blades, n_probes), or None
        With ``[acquisition.signal]``: trigger edges in each passage's window (0: a missing
        pulse, NaN TOA and tick -1; above 1: a double pulse, of which the first edge is
        latched). None without the signal chain.
    clearance_m : ndarray, shape (n_rev, n_blades, n_probes), or None
        With ``[acquisition.signal]``: the tip clearance at each passage, m.
    signal : RawSignals or None
        With ``[acquisition.signal] publish``: the digitised window of every passage.
    extra_passage : ndarray of int64, shape (m,), or None
        With ``[acquisition.signal]``: the passage of every trigger edge after its window's
        first (double pulses), as an index into the batch's ``(revolution, blade, probe)``
        arrays flattened, in passage then time order.
    extra_toa_s : ndarray, shape (m,), or None
        Their times as acquired (latched on the clock like the TOAs), s.
    extra_toa_ticks : ndarray of int64, shape (m,), or None
        The same in clock ticks when the clock is quantised.
    """

    revolution: np.ndarray
    opr_s: np.ndarray
    toa_s: np.ndarray
    opr_ticks: np.ndarray | None
    toa_ticks: np.ndarray | None
    truth: Truth
    residual_s: float
    bracketed: np.ndarray
    n_edges: np.ndarray | None = None
    clearance_m: np.ndarray | None = None
    signal: RawSignals | None = None
    extra_passage: np.ndarray | None = None
    extra_toa_s: np.ndarray | None = None
    extra_toa_ticks: np.ndarray | None = None


def load_scenario_model(scn):
    """The scenario's modal model: built-in (built now) or a user's file."""
    if scn.model.source == "builtin":
        return build_model(scn)
    return load_model(scn.model.source)


@dataclass(frozen=True, slots=True, eq=False)
class TipAmplitudeBound:
    """Upper bounds of a scenario's tip response over the whole run (:func:`tip_amplitude_bound`).

    Attributes
    ----------
    deqv_pkpk_m : ndarray, shape (n_blades,)
        Bound of the peak-to-peak ``d_eqv = d_tang + d_z / tan(eta_tip)`` (Eq. 3-4) at the
        nominal sensing node P_nom, per blade, m: what the product reports as amplitude.
    tip_0pk_m : ndarray, shape (n_blades,)
        Bound of the zero-to-peak displacement magnitude (radial, tangential and axial) of any
        tip node, per blade, m: the quantity held to :data:`~bttsim_stream.defaults.MAX_TIP_AMPLITUDE_FRACTION`
        of the tip radius.
    radius_m : float
        Mean radius of P_nom, m.
    proven : bool
        True: a bound for the linear model (:func:`~bttsim_stream.sim.modal.modal_response_bound`).
        False: a model with speed-dependent modes, whose bound is the largest over its modes
        frozen at the profile's end speeds and Campbell crossings (an estimate).
    """

    deqv_pkpk_m: np.ndarray
    tip_0pk_m: np.ndarray
    radius_m: float
    proven: bool = True

    @property
    def limit_m(self) -> float:
        """Largest allowed zero-to-peak tip displacement, m (5 % of the tip radius)."""
        return MAX_TIP_AMPLITUDE_FRACTION * self.radius_m

    def describe(self) -> str:
        """One line: what is bounded, on which basis, against which limit."""
        word = "upper bound" if self.proven else "estimate, speed-dependent modes"
        return (f"d_eqv at the nominal sensing node at most {np.max(self.deqv_pkpk_m) * 1e3:.3g} mm pk-pk, "
                f"any tip node's displacement at most {np.max(self.tip_0pk_m) * 1e3:.3g} mm 0-pk "
                f"({word}; limit {self.limit_m * 1e3:.3g} mm 0-pk, "
                f"{MAX_TIP_AMPLITUDE_FRACTION:.0%} of the {self.radius_m * 1e3:.4g} mm tip radius)")


def _tip_bound(model, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per blade: 0-pk bound of ``d_eqv`` at P_nom and of any tip node's displacement
    magnitude from the modal bounds ``Q`` (n_modes,), summed over modes in absolute value."""
    tip = np.asarray(model.tip_shapes, float)  # (n_modes, n_blades, n_tip, 3)
    v = tip[:, :, model.nominal_node, :]
    eqv = v[:, :, 1] + v[:, :, 2] / np.tan(np.deg2rad(float(model.meta["stagger_deg"])))  # Eq. 3-4
    with np.errstate(invalid="ignore"):
        deqv = np.where(Q[:, None] > 0, np.abs(eqv) * Q[:, None], 0.0).sum(axis=0)
        mag = np.where(Q[:, None, None] > 0, np.linalg.norm(tip, axis=3) * Q[:, None, None], 0.0).sum(axis=0)
    return deqv, np.max(mag, axis=1)


def tip_amplitude_bound(scn, model, nsv=None) -> TipAmplitudeBound:
    """Upper bounds of the run's tip response, per blade (the scenario's forces, its speed profile).

    Per mode, the envelope bound of :func:`~bttsim_stream.sim.modal.modal_response_bound` (the
    modal force ``|phi_force . F|`` summed over blades with the travelling-wave phases of
    Eq. 5-7, times the SDOF amplification peak ``1 / (2 zeta sqrt(1 - zeta^2) w^2)``, or less
    where a sweep or the distance to resonance caps it), times the mode's tip shape, summed over
    modes and excitations in absolute value (triangle inequality).

    Non-synchronous forcing (:mod:`~bttsim_stream.sim.nsv`): the stall and broadband carriers
    are forced carriers like the engine orders and are bounded the same way. Flutter is
    self-excited (unbounded growth in linear theory); the simulator saturates it at its limit
    cycle, so its bound is the limit cycle (``max(limit, seed)`` of ``[flutter]``). ``nsv``: the
    simulator's :class:`~bttsim_stream.sim.nsv.NsvSetup` (built here when None).

    A model with speed-dependent modes is bounded with its modes frozen at the profile's
    slowest and fastest speeds and at every Campbell crossing in between
    (:func:`~bttsim_stream.model.speed_modes.crossing_speeds`), the largest kept: an estimate
    (``proven`` False), since the modes move during the run.
    """
    speed = speed_profile_from_scenario(scn)
    initial = scn.speed.initial
    has_nsv = bool(scn.rotating_stall) or scn.flutter.enabled or scn.broadband.enabled
    radius = float(np.mean(model.tip_ref[:, model.nominal_node, 0]))

    def forced(m, C, eo, omega=None):
        return _tip_bound(m, modal_response_bound(m.freq_hz, m.damping_ratio, C, eo, speed, omega, initial))

    if is_speed_dependent(model):
        if has_nsv:
            raise BttsimError("[[rotating_stall]], [flutter] and [broadband] are not supported with speed-dependent "
                              "modes ([model] centrifugal or a model file with speed arrays) yet")
        check_speed_range(model, float(np.max(speed.omega)))
        lo, hi = float(np.min(speed.omega)), float(np.max(speed.omega))
        at = np.concatenate(([lo, hi], crossing_speeds(model, [e.engine_order for e in scn.excitation], lo, hi)))
        parts = [forced(frozen, *modal_forcing(frozen, scn.excitation)) for frozen in models_at_speeds(model, at)]
        deqv = np.max([p[0] for p in parts], axis=0)
        tip = np.max([p[1] for p in parts], axis=0)
        return TipAmplitudeBound(2.0 * deqv, tip, radius, proven=False)
    deqv, tip = forced(model, *modal_forcing(model, scn.excitation))
    if has_nsv:
        basis = tip_basis(model.tip_shapes)
        stagger = np.deg2rad(float(model.meta["stagger_deg"]))
        if nsv is None:
            v = basis.nodes[:, model.nominal_node, :]
            nsv = build_nsv(scn, model, speed, basis, v[:, 1] + v[:, 2] / np.tan(stagger))
        if nsv.eo.size:
            d, u = forced(model, nsv.C, nsv.eo, nsv.omega)
            deqv, tip = deqv + d, tip + u
        if nsv.flutter is not None:  # the limit cycle, which the logistic growth never exceeds
            f = nsv.flutter
            r_max = max(f.limit_m, f.seed_m)
            nodes = basis.nodes  # (r, n_tip, 3)
            v = nodes[:, model.nominal_node, :]
            deqv = deqv + r_max * np.abs(f.shape @ (v[:, 1] + v[:, 2] / np.tan(stagger)))
            A = np.einsum("br,rnj->bnj", f.shape, nodes)  # (n_blades, n_tip, 3) complex
            tip = tip + r_max * np.max(np.sqrt(np.sum(np.abs(A) ** 2, axis=2)), axis=1)
    return TipAmplitudeBound(2.0 * deqv, tip, radius)


def check_tip_amplitude(scn, model, nsv=None) -> TipAmplitudeBound:
    """Refuse a scenario whose tip motion could leave the linear model's validity.

    The bound of the zero-to-peak displacement of any tip node over the run
    (:func:`tip_amplitude_bound`) must stay within
    :data:`~bttsim_stream.defaults.MAX_TIP_AMPLITUDE_FRACTION` (5 %) of the tip radius. A
    model with speed-dependent modes must also hold modes up to the profile's top speed
    (:func:`~bttsim_stream.model.speed_modes.check_speed_range`).

    Returns
    -------
    TipAmplitudeBound
        The bounds (the pk-pk ``d_eqv`` at P_nom among them).

    Raises
    ------
    BttsimError
        One line naming the bound, the limit and the force to lower (or the speed), or the
        non-synchronous options that a speed-dependent model does not support.
    """
    bound = tip_amplitude_bound(scn, model, nsv)
    amp = float(np.max(bound.tip_0pk_m))
    if not amp <= bound.limit_m:
        has_nsv = bool(scn.rotating_stall) or scn.flutter.enabled or scn.broadband.enabled
        forces = ", ".join(f"{e.amplitude_n:g}" for e in scn.excitation)
        raise BttsimError(
            f"[[excitation]] amplitude_n = {forces} N: the tip amplitude may reach {amp * 1e3:.3g} mm 0-pk (upper "
            f"bound, any tip node), above {MAX_TIP_AMPLITUDE_FRACTION:.0%} of the tip radius "
            f"({bound.limit_m * 1e3:.3g} mm of {bound.radius_m * 1e3:.4g} mm), where the linear modal model no "
            f"longer holds: lower the force"
            + (" (or the non-synchronous forcing, the flutter limit_amplitude_m)" if has_nsv else ""))
    return bound


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
        if m.n_blades != scn.rotor.n_blades and scn.model.source != "builtin":
            pass  # a user's model defines the blade count
        if np.any(m.damping_ratio >= 1.0):
            raise BttsimError("model: damping ratios must be < 1 (underdamped modes)")
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
        self.chunk = (int(chunk_revolutions) if chunk_revolutions is not None else
                      max(1, min(64, round(CROSSINGS_PER_CHUNK / (m.n_blades * probes.size)))))
        self.psi = np.mod(self.probe_actual[None, :] - self.theta_p[:, None] - self.theta_opr, TWO_PI)
        C, eo = modal_forcing(m, scn.excitation)
        initial = scn.speed.initial if initial is None else initial
        speed_dependent = is_speed_dependent(m)
        if speed_dependent:  # modes that follow the speed (centrifugal effects): their own path
            self.basis, psi_at_speed = speed_tip_basis(m)
        else:
            self.basis = tip_basis(m.tip_shapes)
        v = self.basis.nodes[:, p, :]  # (r, 3)
        v_eqv = v[:, 1] + v[:, 2] / np.tan(self.stagger)  # (r,): d_eqv at P_nom (Eq. 3-4)
        # non-synchronous vibration: forced carriers through the recursion, flutter in closed form
        self.nsv = None if speed_dependent else build_nsv(scn, m, self.speed, self.basis, v_eqv)
        self._n_eo = eo.size
        check_tip_amplitude(scn, m, self.nsv)  # refuses non-synchronous options with speed-dependent modes
        omega = None
        if self.nsv is not None:
            C = np.concatenate([C, self.nsv.C], axis=1)
            omega = np.concatenate([np.zeros(eo.size), self.nsv.omega])
            eo = np.concatenate([eo, self.nsv.eo])
        self._n_forced = eo.size  # carriers of the envelope recursion
        if speed_dependent:
            self.integrator = SpeedDependentIntegrator(m, scn.excitation, psi_at_speed, self.speed, initial=initial)
        else:
            self.integrator = EnvelopeIntegrator(m.freq_hz, m.damping_ratio, C, eo, self.basis,
                                                 self.speed, initial=initial, omega=omega)
        #: carrier phases ``EO_m phi(t) + omega_m t`` of every carrier (None: all omega 0)
        self.eo, self.omega = eo, omega
        if self.nsv is not None and self.nsv.flutter is not None:
            self.eo = np.concatenate([eo, [0.0]])
            self.omega = np.concatenate([omega, [self.nsv.flutter.omega]])
        # shorter envelope steps where a free response is present (a start from rest, a speed knot)
        radius = float(np.mean(m.tip_ref[:, p, 0]))
        near = np.argsort(np.abs(m.tip_ref[..., 2] - self.z_probe), axis=1)[:, :4]  # candidate nodes
        reach = radius * float(np.max(np.abs(self.theta_p[:, None] - np.take_along_axis(m.tip_ref[..., 1], near, 1))))
        self.grid = GridPoints(self.speed, envelope_step_s,
                               self.integrator.transient_grid(envelope_step_s, radius, reach))
        self.h_env = envelope_step_s
        if self.nsv is not None and self.nsv.flutter is not None:
            fw = self.nsv.flutter  # cubic Hermite error of the logistic envelope, <= L sigma^4 h^4 / 384
            err_m = fw.limit_m * fw.sigma**4 * envelope_step_s**4 / 384.0
            tol_m = TRANSIENT_TOL_S * radius * float(np.min(self.speed.omega))
            if err_m > 100.0 * tol_m:
                msg = (f"[flutter]: growth rate {fw.sigma:.3g} /s is fast for the {envelope_step_s * 1e3:g} ms envelope "
                       f"grid; TOAs may differ from the exact ones by up to {err_m / tol_m * TRANSIENT_TOL_S:.1g} s")
                self.integrator.warnings.append(msg)
        self._i_grid = 0
        self._buf_t: np.ndarray | None = None  # envelope grid points kept: [_lo, _hi)
        self._buf: np.ndarray | None = None
        self._lo = self._hi = 0
        #: CPU time spent integrating envelopes (per simulated second, scales with the
        #: responding modes) and on the crossings (per TOA, independent of the modes)
        self.timing = {"envelopes_s": 0.0, "crossings_s": 0.0}
        total = int(np.floor((self.speed.angle(self.speed.duration_s) - self.theta_opr) / TWO_PI))
        self.n_revolutions = max(0, total if n_revolutions is None else min(total, n_revolutions))
        self._v_eqv = v_eqv
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
        acq = scn.acquisition
        self._signal = _SignalChain(scn, probes.size, float(np.mean(m.tip_ref[:, p, 0]))) if acq.signal.enabled else None
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
            if self._n_forced < n_exc:  # the flutter carrier's closed-form envelope
                G, dG = self.nsv.flutter.envelope(t_blk[first:])
                for g, X in enumerate((G, dG)):
                    X = X.reshape(X.shape[0], -1)
                    planes[g, n_exc - 1, 0] = X.real
                    planes[g, n_exc - 1, 1] = X.imag
            self._buf_t[hi:hi + n_new] = t_blk[first:]
            self._hi = hi + n_new
            self._i_grid = stop
            if stop == self.grid.size - 1:
                break
        lo, hi = self._lo, self._hi
        self._lo = max(lo, lo + int(np.searchsorted(self._buf_t[lo:hi], t_start, side="right")) - 2)
        return self._buf_t[self._lo:hi], self._buf, self._lo

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
        """
        m, scn = self.model, self.scn
        nb, npr, nt, p = m.n_blades, self.psi.shape[1], m.n_tip, self.p
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
        phi_r, om_r = frame.phi_ref, frame.om_ref
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
                                            t_r, om_r, _pair(lambda o: u_r[k_lo + o:k_lo + o + 2], k - k_lo, k_hi - k_lo),
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
        # truth at the TOA: P_nom displacements, d_eqv (Eq. 3-4), Eq. 1 with exact t_exp;
        # pk-pk envelope of d_eqv: 2 sum_m |G_eqv,m(t_TOA)|
        P_t = project_planes(CPr, self._V_truth)[:, :, 0]  # (4, n_exc, 3, 2, n): tang, axial, eqv
        X = eval_planes(P_t, toa - t0)  # (n_exc, 3, 2, n)
        th = self.eo[:, None] * frame.angle_change(self.speed, toa[None, :])[0]  # (n_exc, n)
        if self.omega is not None:
            th += self.omega[:, None] * (toa - t_r)[None, :]
        cd, sd = np.cos(th), np.sin(th)
        c0, s0 = frame.rot[:, 0], frame.rot[:, 1]
        cr, ci = cd * c0 - sd * s0, sd * c0 + cd * s0  # exp(i EO phi(t_TOA))
        d_tang = np.sum(X[:, 0, 1] * cr + X[:, 0, 0] * ci, axis=0)
        d_z = np.sum(X[:, 1, 1] * cr + X[:, 1, 0] * ci, axis=0)
        d_eqv = d_tang + d_z / np.tan(self.stagger)
        sig = None
        if self._signal is not None:  # radial displacement of P_nom at the TOA: the tip clearance
            X_r = eval_planes(project_planes(CPr, self.basis.nodes[:, p:p + 1, 0:1])[:, :, 0], toa - t0)
            d_rad = np.sum(X_r[:, 0, 1] * cr + X_r[:, 0, 0] * ci, axis=0)
            probe_of = np.tile(np.arange(npr), nr * nb)
            sig = self._signal(toa, blade, probe_of, d_rad, self.speed.speed(toa), self.tip_ref[blade, p, 0])
        ne = self._n_eo
        amp = 2.0 * np.sum(np.hypot(X[:ne, 2, 0], X[:ne, 2, 1]), axis=0)
        omega_mean = TWO_PI / np.diff(opr_edges)
        nsv_truth = {} if self.nsv is None else self._nsv_truth(X[ne:, 2], omega_mean, shape)
        r_p = self.tip_ref[:, p, 0][None, :, None]
        d_eq1 = omega_mean[:, None, None] * r_p * (t_r.reshape(shape) - toa.reshape(shape))
        pkpk = amp.reshape(shape).max(axis=2)
        truth = Truth(opr_s=opr_edges[:-1], toa_s=toa.reshape(shape), t_exp_s=t_r.reshape(shape),
                      d_eqv_m=d_eqv.reshape(shape), d_tang_m=d_tang.reshape(shape),
                      d_z_m=d_z.reshape(shape), d_eq1_m=d_eq1, d_eqv_pkpk_m=pkpk,
                      omega_mean=omega_mean, **nsv_truth)
        out = self._acquire(revs, truth, float(residual), bracketed.reshape(shape), sig)
        self.timing["crossings_s"] += time.process_time() - t_clock
        return out

    def _nsv_truth(self, X, omega_mean, shape) -> dict:
        """The ``nsv_*`` fields of :class:`Truth` from the NSV carriers' ``d_eqv`` envelopes
        ``X`` (n_nsv_carriers, 2 [re, im], n) at the TOAs."""
        comps = self.nsv.components
        nr, nc = shape[0], len(comps)
        freq, amp, rms = np.zeros((nr, nc)), np.zeros((nr, nc)), np.zeros((nr, nc))
        nd = np.zeros((nr, nc), np.int64)
        band = np.zeros((nr, nc, 2))
        p2 = (X[:, 0] ** 2 + X[:, 1] ** 2).reshape(X.shape[0], nr, -1)  # |G_eqv|^2 per carrier, arrival
        for j, c in enumerate(comps):
            idx = list(c.carriers)
            ms = 0.5 * np.sum(p2[idx], axis=0)  # mean square of d_eqv per arrival (incommensurate lines)
            rms[:, j] = np.sqrt(np.mean(ms, axis=1))
            if c.kind == "broadband":
                freq[:, j] = c.omega / TWO_PI
                amp[:, j] = 2.0 * np.sqrt(2.0) * rms[:, j]
                band[:, j] = c.band_hz
                continue
            amp[:, j] = 2.0 * np.sqrt(np.max(p2[idx[0]], axis=1))
            rate = c.eo * omega_mean + c.omega  # rad/s in the rotor frame
            freq[:, j] = np.abs(rate) / TWO_PI
            nd[:, j] = np.where(rate < 0, -c.nodal_diameter, c.nodal_diameter)
        kind = np.broadcast_to(np.array([c.kind for c in comps]), (nr, nc)).copy()
        return {"nsv_kind": kind, "nsv_freq_hz": freq, "nsv_nd": nd, "nsv_amp_pkpk_m": amp, "nsv_rms_m": rms,
                "nsv_band_hz": band}

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
        method = self.scn.toa.method
        if method in ("AD", "PAD"):
            t_det = grid_crossings(lm, self.speed, target_rel, rad, t_det, self.scn.toa.grid_step_s, method)
            u, _, _, _ = eval_local(lm, self.speed, t_det, derivative=False)
        dz = z_ref + u[:, 2] - self.z_probe
        return t_det, dz, residual

    def _acquire(self, revs, truth: Truth, residual: float, bracketed, sig=None) -> RevolutionBatch:
        acq = self.scn.acquisition
        toa = truth.toa_s.copy() if sig is None else sig[0].reshape(truth.toa_s.shape)
        opr = truth.opr_s.copy()
        if acq.trigger_jitter_s > 0:
            toa += acq.trigger_jitter_s * self._rng["jitter"].standard_normal(toa.shape)
        if acq.opr_jitter_s > 0:
            opr += acq.opr_jitter_s * self._rng["opr"].standard_normal(opr.shape)
        toa_ticks = opr_ticks = None
        extra_t = None if sig is None else sig[5]
        extra_ticks = None
        if acq.clock_hz > 0:
            if sig is None:
                toa_ticks = np.floor(toa * acq.clock_hz).astype(np.int64)
            else:  # the counter latches the trigger; no pulse: tick -1 and TOA NaN
                found = np.isfinite(toa)
                toa_ticks = np.where(found, np.floor(np.where(found, toa, 0.0) * acq.clock_hz), -1).astype(np.int64)
            opr_ticks = np.floor(opr * acq.clock_hz).astype(np.int64)
            if sig is not None:
                extra_ticks = np.floor(extra_t * acq.clock_hz).astype(np.int64)
                extra_t = extra_ticks / acq.clock_hz
            toa = toa_ticks / acq.clock_hz
            if sig is not None:
                toa[toa_ticks < 0] = np.nan
            opr = opr_ticks / acq.clock_hz
        extra = {} if sig is None else {"n_edges": sig[1].reshape(toa.shape), "clearance_m": sig[2].reshape(toa.shape),
                                        "signal": sig[3], "extra_passage": sig[4], "extra_toa_s": extra_t,
                                        "extra_toa_ticks": extra_ticks}
        return RevolutionBatch(revolution=revs.astype(np.int64), opr_s=opr, toa_s=toa,
                               opr_ticks=opr_ticks, toa_ticks=toa_ticks, truth=truth,
                               residual_s=residual, bracketed=bracketed, **extra)

    def __iter__(self) -> Iterator[RevolutionBatch]:
        for n0 in range(0, self.n_revolutions, self.chunk):
            yield self._chunk(np.arange(n0, min(n0 + self.chunk, self.n_revolutions)))


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
                           signal=None if batches[0].signal is None else RawSignals.concatenate(b.signal for b in batches),
                           extra_passage=None if batches[0].extra_passage is None else np.concatenate(
                               [b.extra_passage + off for b, off in zip(batches, np.cumsum(
                                   [0] + [b.toa_s.size for b in batches[:-1]]))]),
                           extra_toa_s=cat(lambda b: b.extra_toa_s), extra_toa_ticks=cat(lambda b: b.extra_toa_ticks))


class _SignalChain:
    """The scenario's ``[acquisition.signal]``: exact passages in, triggered TOAs out.

    Random streams of their own (``SeedSequence([seed, 3])`` for the white noise,
    ``[seed, 4]`` for the low-frequency noise), so the other acquisition errors draw what
    they drew before; the white noise is drawn passage by passage, so the TOAs do not
    depend on how revolutions are batched.
    """

    def __init__(self, scn, n_probes: int, radius_m: float) -> None:
        sig, seed = scn.acquisition.signal, scn.run.seed
        self.sig = sig

        def per_probe(v):
            return (v,) * n_probes if isinstance(v, str) else tuple(v)

        self.probes = [ProbeModel(kind=k, diameter_m=sig.spot_diameter_m if k == "optical" else sig.electrode_diameter_m,
                                  tip_thickness_m=sig.tip_thickness_m,
                                  reference_clearance_m=sig.reference_clearance_m,
                                  height_v=sig.height_v, fringe_factor=sig.fringe_factor,
                                  bandwidth_hz=sig.bandwidth_hz) for k in per_probe(sig.probe_type)]
        self.triggers = [Trigger(kind=k, level_v=sig.level_v, hysteresis_v=sig.hysteresis_v, edge=sig.edge,
                                 fraction=sig.fraction) for k in per_probe(sig.trigger)]
        self.dig = Digitiser(sample_rate_hz=sig.sample_rate_hz, bits=sig.bits, range_lo_v=sig.range_lo_v,
                             range_hi_v=sig.range_hi_v, noise_v=sig.noise_v, lf_noise_v=sig.lf_noise_v,
                             lf_corner_hz=sig.lf_corner_hz, offset_v=sig.offset_v,
                             offset_drift_v_per_s=sig.offset_drift_v_per_s, gain_drift_per_s=sig.gain_drift_per_s)
        self.rng = np.random.default_rng(np.random.SeedSequence([seed, 3]))
        self.lf = (LowFrequencyNoise(sig.lf_noise_v, sig.lf_corner_hz, n_probes,
                                     np.random.default_rng(np.random.SeedSequence([seed, 4])))
                   if sig.lf_noise_v > 0 else None)
        self.radius_m = radius_m
        self.tau_s = np.array([p.tau_s for p in self.probes])

    def __call__(self, toa, blade, probe, d_rad_m, omega, radius_m):
        """Triggered TOAs, edge counts and clearances of passages (all shape (n,)), their
        :class:`RawSignals` when the scenario publishes them (else None), and the later edges
        of double pulses (passage, time)."""
        sig = self.sig
        growth = centrifugal_growth_m(omega, self.radius_m, sig.density_kg_m3, sig.youngs_modulus_pa)
        clearance = sig.clearance_m - growth - d_rad_m
        speed = omega * (radius_m + growth + d_rad_m)
        height = np.empty(toa.size)
        half = np.empty(toa.size)
        scale = np.empty(toa.size)
        for j, pm in enumerate(self.probes):
            cols = probe == j
            pp = pulse_parameters(pm, clearance[cols], speed[cols])
            height[cols], half[cols], scale[cols] = pp.height_v, pp.half_width_s, pp.scale_s
        win = synthesise(toa, PulseParameters(height, half, scale), self.tau_s[probe], probe, self.dig, self.rng,
                         self.lf)
        out = apply_triggers(win, self.triggers, probe)
        raw = None
        if sig.publish:
            raw = RawSignals(win.first_sample, win.n_samples, win.codes, win.sample_rate_hz, self.dig.range_lo_v,
                             self.dig.lsb_v, self.dig.bits, tuple(t.kind for t in self.triggers), sig.level_v,
                             sig.hysteresis_v, sig.edge, sig.fraction)
        return out.toa_s, out.n_edges, clearance, raw, out.extra_passage, out.extra_toa_s

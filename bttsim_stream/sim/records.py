"""The simulator's records that cross module boundaries: the run metadata (:class:`RunInfo`),
ground truth (:class:`Truth`) and a batch of acquired revolutions (:class:`RevolutionBatch`).

They live apart from the simulator (:mod:`bttsim_stream.sim.core`, which re-exports them) so
that a consumer of the bus -- the codec, a recorder, a processor, a viewer -- imports these
dataclasses without the modal model and the simulator behind them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..defaults import DEFAULT_RIG
from .signal import RawSignals

__all__ = ["RunInfo", "Truth", "RevolutionBatch"]


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
    rig: str = DEFAULT_RIG
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
    eo_engine_order : ndarray of int64, shape (n_rev, n_eo), or None
        The run's distinct engine orders, ascending (the columns of ``eo_pkpk_m``); None:
        not known (a truth recorded before the field existed).
    eo_pkpk_m : ndarray, shape (n_rev, n_blades, n_eo), or None
        Each engine order's own response: peak-to-peak envelope of its part of ``d_eqv(t)``,
        largest over the revolution's arrivals of ``2 |sum_m G_eqv,m|`` over the excitations
        of that order (the system is linear: the responses superpose, and excitations of one
        order share its carrier). With one engine order it equals ``d_eqv_pkpk_m``.
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
    eo_engine_order: np.ndarray | None = None
    eo_pkpk_m: np.ndarray | None = None
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

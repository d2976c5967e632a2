"""Upper bounds of the response over a whole run, and the check that keeps it linear.

:func:`modal_response_bound` bounds every modal coordinate of a mode forced by carriers
``Im(C exp(i (EO phi(t) + omega t)))`` over a speed profile; :func:`tip_amplitude_bound` turns
the bounds into the tip motion of a scenario, and :func:`check_tip_amplitude` refuses a
scenario whose tip motion could leave the linear model's validity
(:data:`~bttsim_stream.defaults.MAX_TIP_AMPLITUDE_FRACTION` of the tip radius).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..defaults import MAX_TIP_AMPLITUDE_FRACTION
from ..errors import BttsimError
from ..model.speed_modes import check_speed_range, crossing_speeds, is_speed_dependent, models_at_speeds
from .forcing import modal_forcing
from .modal import FixedModes, quasi_steady_envelope
from .sources import excitation_sources
from .speed import SpeedProfile, speed_profile_from_scenario

__all__ = ["EULER_CHORD", "modal_response_bound", "TipAmplitudeBound", "tip_amplitude_bound", "check_tip_amplitude",
           "check_tip_nodes"]


#: Longest chord of the Euler (Cornu) spiral, ``max |int_s1^s2 exp(i pi x^2 / 2) dx|`` over all
#: ``s1 < s2`` (1.898113 at ``s2 = -s1 = 1.2094``), rounded up: an undamped mode swept through
#: resonance at ``r`` rad/s^2 gathers at most ``EULER_CHORD sqrt(pi / r)`` times its forcing
#: in its envelope, whatever the start and end of the sweep.
EULER_CHORD = 1.8982


def modal_response_bound(freq_hz, damping_ratio, C, eo, speed: SpeedProfile, omega=None,
                         initial: str = "steady") -> np.ndarray:
    """Upper bound of every modal coordinate ``|q_k(t)|`` over a whole run (any ``t``).

    Parameters
    ----------
    freq_hz, damping_ratio : ndarray, shape (n_modes,)
        Undamped natural frequencies, Hz, and damping ratios (``< 1``).
    C : ndarray, shape (n_modes, n_car), complex
        Modal forces (:func:`modal_forcing`): carrier ``m`` forces mode ``k`` with
        ``Im(C[k, m] exp(i theta_m(t)))``, ``theta_m = EO_m phi(t) + omega_m t`` (Eq. 5-7).
    eo : ndarray, shape (n_car,)
    speed : SpeedProfile
    omega : ndarray, shape (n_car,), optional
        Constant rotor-frame carrier frequencies, rad/s (non-synchronous forcing); default 0.
    initial : {"steady", "rest"}
        The simulator's start (:class:`EnvelopeIntegrator`).

    Returns
    -------
    ndarray, shape (n_modes,)
        ``Q_k >= max_t |q_k(t)|``, m per unit mass-normalised coordinate.

    Notes
    -----
    ``q = Im(a_+ e^{i theta} - conj(a_-) e^{-i theta}) / w_d`` (module conventions), so
    ``|q| <= (|a_+| + |a_-|) / w_d`` per carrier, summed over carriers. Each envelope is
    ``a(t) = a(0) exp(int_0^t mu) + c int_0^t exp(int_s^t mu) ds``, ``|c| = |C| / 2``,
    ``mu = lambda -+ i (EO Omega + omega)``, ``|exp(int_s^t mu)| <= exp(-zeta w (t - s))``; the
    least of three bounds is kept:

    * any forcing history: ``|a| <= |c| / (zeta w)``, hence
      ``|q| <= |C| / (2 zeta sqrt(1 - zeta^2) w^2)`` per carrier -- the peak of the SDOF dynamic
      amplification, reached by the resonant carrier on a dwell; a start in the quasi-steady
      state (:func:`quasi_steady_envelope`) obeys the same bound;
    * quasi-statically, ``a = -c / mu(t) + r`` with ``r' = mu r - c mu' / mu^2`` (``mu`` is
      continuous, ``mu' = -+ i EO alpha`` piecewise constant): ``|a| <= |c| / min |mu| +
      |a(0) + c / mu(0)| + |c| sum_j EO |alpha_j| min(T_j, 1 / (zeta w)) / m_j^2``, tight for a
      carrier that stays away from resonance (``m_j``: least ``|mu|`` on segment ``j``);
    * speed segment by segment, ``|a(t)| <= |a(0)| + sum_j S_j`` with ``S_j`` the least of: the
      segment's duration; ``1 / (zeta w)``; integration by parts where the carrier stays away
      from resonance (``|mu| >= m_j`` on the segment), ``2 / m_j + EO |alpha_j| min(T_j,
      1 / (zeta w)) / m_j^2``; on a ramp, the longest chord of the Euler spiral,
      ``EULER_CHORD sqrt(pi / (EO |alpha_j|))`` (the damping weight, increasing in ``s`` and at
      most 1, cannot lengthen a chord). This caps undamped or fast-swept crossings.

    The bound holds for the transient through resonance as well as for any steady state: a
    linear sweep never exceeds it (the resonant carrier's ``1 / (zeta w)`` is the stationary
    peak, the other carrier adds ``O(zeta)``).
    """
    w = 2.0 * np.pi * np.asarray(freq_hz, float)
    zeta = np.asarray(damping_ratio, float)
    C = np.asarray(C, complex).reshape(w.size, -1)
    eo = np.asarray(eo, float).reshape(-1)
    om_c = np.zeros(eo.size) if omega is None else np.asarray(omega, float).reshape(-1)
    wd = w * np.sqrt(1.0 - zeta**2)
    zw = zeta * w
    lam = -zw + 1j * wd
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        g = np.where(zw > 0, 1.0 / zw, np.inf)  # any history
    knots = np.asarray(speed.omega, float)
    T = np.diff(np.asarray(speed.t_s, float))
    alpha = np.asarray(speed.alpha, float)[:-1]
    om0, al0 = float(knots[0]), float(speed.alpha[0])
    Q = np.zeros(w.size)
    for m in range(eo.size):
        c = 0.5 * np.abs(C[:, m])
        if not np.any(c > 0):
            continue
        for sign in (1.0, -1.0):
            # carrier frequency seen by the envelope over each segment: sign (EO Omega + omega)
            xa = sign * (eo[m] * knots[:-1] + om_c[m])
            xb = sign * (eo[m] * knots[1:] + om_c[m])
            lo, hi = np.minimum(xa, xb), np.maximum(xa, xb)
            dist = np.maximum(0.0, np.maximum(lo[None, :] - wd[:, None], wd[:, None] - hi[None, :]))
            mj = np.sqrt(zw[:, None] ** 2 + dist**2)  # least |mu| on the segment, (n_modes, n_seg)
            rate = np.abs(eo[m] * alpha)[None, :]
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                ibp = 2.0 / mj + rate * np.minimum(T[None, :], g[:, None]) / mj**2
                chord = np.where(rate > 0, EULER_CHORD * np.sqrt(np.pi / rate), np.inf)
                S = np.minimum(np.minimum(T[None, :], g[:, None]), np.minimum(np.nan_to_num(ibp, nan=np.inf), chord))
            mu0 = lam - sign * 1j * (eo[m] * om0 + om_c[m])
            a0 = np.zeros(w.size, complex)
            if initial == "steady":
                q0 = quasi_steady_envelope(np.ones(w.size), mu0, -sign * 1j * eo[m] * al0)
                a0 = np.where(np.isfinite(q0), q0, 0.0)  # none: the simulator starts at rest
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                # quasi-static part -1/mu(t) plus a remainder r' = mu r - mu' / mu^2 (per unit c)
                drift = np.sum(rate * np.minimum(T[None, :], g[:, None]) / mj**2, axis=1)
                qs = 1.0 / np.min(mj, axis=1) + np.abs(a0 + 1.0 / mu0) + drift
            env = np.minimum(np.minimum(g, np.abs(a0) + np.sum(S, axis=1)), np.nan_to_num(qs, nan=np.inf))
            with np.errstate(invalid="ignore"):
                Q += np.where(c > 0, c * env / wd, 0.0)
    return Q


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
        True: a bound for the linear model (:func:`modal_response_bound`).
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


def tip_amplitude_bound(scn, model, sources=None) -> TipAmplitudeBound:
    """Upper bounds of the run's tip response, per blade (the scenario's forces, its speed profile).

    Per mode, the envelope bound of :func:`modal_response_bound` (the
    modal force ``|phi_force . F|`` summed over blades with the travelling-wave phases of
    Eq. 5-7, times the SDOF amplification peak ``1 / (2 zeta sqrt(1 - zeta^2) w^2)``, or less
    where a sweep or the distance to resonance caps it), times the mode's tip shape, summed over
    modes and excitations in absolute value (triangle inequality).

    Non-synchronous forcing (:mod:`~bttsim_stream.sim.nsv`): the stall and broadband carriers
    are forced carriers like the engine orders and are bounded the same way. Flutter is
    self-excited (unbounded growth in linear theory); the simulator saturates it at its limit
    cycle, so its bound is the limit cycle (``max(limit, seed)`` of ``[flutter]``). Each
    excitation source gives its own terms (``bound_terms``); ``sources``: the simulator's
    (:func:`~bttsim_stream.sim.sources.excitation_sources`, built here when None).

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
    if sources is None:
        modes = FixedModes(model)
        v = modes.basis.nodes[:, model.nominal_node, :]
        v_eqv = v[:, 1] + v[:, 2] / np.tan(np.deg2rad(float(model.meta["stagger_deg"])))
        sources = excitation_sources(scn, model, speed, modes, v_eqv)
    terms = [t for s in sources for t in s.bound_terms(lambda C, eo, omega: forced(model, C, eo, omega))]
    deqv, tip = terms[0]
    for d, u in terms[1:]:
        deqv, tip = deqv + d, tip + u
    return TipAmplitudeBound(2.0 * deqv, tip, radius)


def check_tip_nodes(model, z_probe: float) -> None:
    """The probe's axial position within the tip nodes, which run from the trailing edge.

    Raises
    ------
    BttsimError
        One line naming the position and the nodes' range, or the nodes' order.
    """
    z_nodes = model.tip_ref[..., 2]
    if np.any(z_probe > z_nodes.max(axis=1)) or np.any(z_probe < z_nodes.min(axis=1)):
        raise BttsimError(
            f"[probes] axial_position_m = {z_probe * 1e3:.3f} mm lies outside the model's tip "
            f"nodes (z {z_nodes.min() * 1e3:.3f} .. {z_nodes.max() * 1e3:.3f} mm)")
    order = np.argsort(-z_nodes, axis=1)
    if not np.all(order == np.arange(model.n_tip)):
        raise BttsimError("model: tip nodes must be ordered from the trailing edge (z decreasing)")


def check_tip_amplitude(scn, model, sources=None) -> TipAmplitudeBound:
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
    check_tip_nodes(model, scn.probes.axial_position_m)  # where the probe sees the tip, first
    bound = tip_amplitude_bound(scn, model, sources)
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

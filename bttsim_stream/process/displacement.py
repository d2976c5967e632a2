"""BTT displacements from OPR and TOA times (paper Eq. 1), and blade identification.

Conventions (written once for the processing package): arrays are ``(revolution, blade,
probe)``; times in s, angles in rad (anticlockwise from +x, the direction of rotation),
speeds in rad/s, displacements in m. Revolution ``n`` starts at OPR pulse ``n`` and holds,
for every blade and probe, the arrival whose *rigid* crossing of the probe falls in
``[OPR_n, OPR_n+1)`` (the simulator's convention, and that of :func:`identify_blades`).
A missing arrival is NaN; everything here propagates NaN instead of failing.

Expected arrival times
----------------------
A real system knows only the OPR times. Between OPR pulses it models the rotor angle; the
linear model ``phi = Omega_n (t - OPR_n)`` of the textbook is wrong by
``alpha T^2 / 8`` rad mid-revolution under an acceleration ``alpha`` (200 um of Eq. 1
displacement at 1000 rpm in the paper's run-up). We use instead, per revolution, the
quadratic (constant-acceleration) angle through the previous, current and next OPR pulses
(:class:`RotorPhase`): it is exact for the piecewise-linear speed of the run-up
(expected times within 3e-10 s of the truth) and needs only the next OPR pulse, i.e. one
revolution of latency.

The angle at which a blade reaches a probe after the OPR pulse, ``psi[b, j]``, is either
nominal, ``(theta_probe_j - theta_blade_b - theta_opr) mod 2 pi`` with the geometry's blade
angles (default ``2 pi b / N_b``), or -- the default of the pipeline and what real systems
do -- **calibrated** per blade and probe as the median measured arrival angle over a
reference window of low-speed revolutions (:func:`calibrate_arrival_angles`). Calibration
absorbs the unknown angular position of the sensing point on each blade (P_nom sits 1.89 deg
behind the nominal blade angle in the built-in model), static probe angle errors, and the
small quasi-static forced response present in the reference window; it assumes the window
is free of resonances.

Whichever ``psi`` is used, the expected time of an arrival is the time at which the rotor
angle model reaches the representative of ``psi + 2 pi k`` nearest to the measured angle,
so a blade whose arrival falls close to the OPR pulse is never assigned to the wrong
revolution. Eq. 1 then uses the revolution-mean speed ``Omega_n = 2 pi / (OPR_n+1 - OPR_n)``.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np

from .history import ScratchRows

__all__ = [
    "assign_extra_edges",
    "DoublePulses",
    "Geometry",
    "RotorPhase",
    "Displacements",
    "DisplacementRows",
    "first_pass_rows",
    "mean_speed_from_opr",
    "rotor_phase_from_opr",
    "calibrate_arrival_angles",
    "expected_times",
    "btt_displacement",
    "compute_displacements",
    "displacements_from_phase",
    "revolution_displacements",
    "outside_revolution",
    "identify_blades",
]

TWO_PI = 2.0 * np.pi


@dataclass(frozen=True, slots=True, eq=False)
class Geometry:
    """What the processing needs to know about the rig (the run's acquisition metadata).

    Attributes
    ----------
    n_blades : int
    probe_angles_rad : ndarray, shape (n_probes,)
        Probe angles, rad, anticlockwise from +x.
    tip_radius_m : float
        Radius of the nominal sensing point, m (``R_Pnom`` in Eq. 1).
    opr_angle_rad : float
        Angle of the OPR sensor, rad.
    blade_angles_rad : ndarray, shape (n_blades,)
        Angle of each blade's sensing point in the rotor frame at the OPR pulse (rotor angle
        0), rad. Default nominal: ``2 pi b / n_blades``.
    """

    n_blades: int
    probe_angles_rad: np.ndarray
    tip_radius_m: float
    opr_angle_rad: float = 0.0
    blade_angles_rad: np.ndarray | None = None

    def __post_init__(self) -> None:
        nb = int(self.n_blades)
        if nb < 1:
            raise ValueError(f"n_blades must be >= 1, got {self.n_blades}")
        probes = np.atleast_1d(np.asarray(self.probe_angles_rad, dtype=float))
        if probes.ndim != 1 or probes.size < 1 or not np.all(np.isfinite(probes)):
            raise ValueError("probe_angles_rad must be a finite 1-D array of at least one angle")
        if not (np.isfinite(self.tip_radius_m) and self.tip_radius_m > 0):
            raise ValueError(f"tip_radius_m must be > 0, got {self.tip_radius_m}")
        blades = (TWO_PI * np.arange(nb) / nb if self.blade_angles_rad is None
                  else np.asarray(self.blade_angles_rad, dtype=float))
        if blades.shape != (nb,) or not np.all(np.isfinite(blades)):
            raise ValueError(f"blade_angles_rad must be finite with shape ({nb},), got {blades.shape}")
        object.__setattr__(self, "n_blades", nb)
        object.__setattr__(self, "probe_angles_rad", probes)
        object.__setattr__(self, "tip_radius_m", float(self.tip_radius_m))
        object.__setattr__(self, "opr_angle_rad", float(self.opr_angle_rad))
        object.__setattr__(self, "blade_angles_rad", blades)

    @property
    def n_probes(self) -> int:
        return int(self.probe_angles_rad.size)

    @classmethod
    def from_info(cls, info, model=None) -> "Geometry":
        """Geometry from run metadata (``RunInfo``, ``RunMetadataMsg`` or a ``Geometry``).

        Parameters
        ----------
        info : object
            Anything with ``n_blades``, ``probe_angles_rad``, ``tip_radius_m`` and
            ``opr_angle_rad`` attributes.
        model : ModalModel, optional
            When given, the blade angles are those of its nominal sensing node
            (``model.tip_ref[:, model.nominal_node, 1]``) instead of ``2 pi b / n_blades``.
        """
        if isinstance(info, Geometry) and model is None:
            return info
        blades = getattr(info, "blade_angles_rad", None)
        if model is not None:
            blades = np.asarray(model.tip_ref)[:, model.nominal_node, 1]
        return cls(n_blades=int(info.n_blades), probe_angles_rad=info.probe_angles_rad,
                   tip_radius_m=float(info.tip_radius_m),
                   opr_angle_rad=float(getattr(info, "opr_angle_rad", 0.0)),
                   blade_angles_rad=blades)

    def nominal_arrival_angles(self) -> np.ndarray:
        """Rotor angle after the OPR pulse at which each blade reaches each probe.

        Returns
        -------
        ndarray, shape (n_blades, n_probes)
            ``(theta_probe - theta_blade - theta_opr) mod 2 pi``, rad.
        """
        return np.mod(self.probe_angles_rad[None, :] - self.blade_angles_rad[:, None]
                      - self.opr_angle_rad, TWO_PI)


@dataclass(frozen=True, slots=True, eq=False)
class RotorPhase:
    """Rotor angle after each OPR pulse: ``phi_n(t) = w_n tau + alpha_n tau^2 / 2``, ``tau = t - OPR_n``.

    Attributes
    ----------
    opr_s : ndarray, shape (n_rev,)
    omega0_rad_s : ndarray, shape (n_rev,)
        Speed at the OPR pulse, rad/s.
    alpha_rad_s2 : ndarray, shape (n_rev,)
        Angular acceleration over the revolution, rad/s^2.
    omega_mean_rad_s : ndarray, shape (n_rev,)
        Mean speed over the revolution, ``2 pi / (OPR_n+1 - OPR_n)`` (Eq. 1's Omega).
    """

    opr_s: np.ndarray
    omega0_rad_s: np.ndarray
    alpha_rad_s2: np.ndarray
    omega_mean_rad_s: np.ndarray

    def rows(self, sel) -> "RotorPhase":
        """The model of some revolutions (``sel``: a slice or index array along axis 0)."""
        return RotorPhase(opr_s=self.opr_s[sel], omega0_rad_s=self.omega0_rad_s[sel],
                          alpha_rad_s2=self.alpha_rad_s2[sel], omega_mean_rad_s=self.omega_mean_rad_s[sel])

    def angle(self, t_s: np.ndarray) -> np.ndarray:
        """Rotor angle since the revolution's OPR pulse at times ``t_s`` (axis 0 = revolution), rad."""
        t = np.asarray(t_s, dtype=float)
        ex = (slice(None),) + (None,) * (t.ndim - 1)
        return _rotor_angle(t - self.opr_s[ex], self.omega0_rad_s[ex], self.alpha_rad_s2[ex])

    def time_at_angle(self, angle_rad: np.ndarray) -> np.ndarray:
        """Time at which the rotor angle model reaches ``angle_rad`` (axis 0 = revolution), s."""
        a = np.asarray(angle_rad, dtype=float)
        ex = (slice(None),) + (None,) * (a.ndim - 1)
        return self.opr_s[ex] + self.delay_at_angle(a)

    def delay_at_angle(self, angle_rad: np.ndarray) -> np.ndarray:
        """Time after the revolution's OPR pulse at which the model reaches ``angle_rad``, s."""
        a = np.asarray(angle_rad, dtype=float)
        ex = (slice(None),) + (None,) * (a.ndim - 1)
        return _delay_at_angle(a, self.omega0_rad_s[ex], self.alpha_rad_s2[ex])


# The formulas of the rotor angle model, written once. Each works on arrays (one value per
# revolution, broadcast) and on Python floats (the per-revolution fast path), with the same
# floating-point operations in the same order, so that both paths agree bit for bit.

def _rotor_angle(tau, w0, alpha, out=None):
    """``tau (w0 + alpha tau / 2)``: the rotor angle ``tau`` s after the OPR pulse, rad."""
    x = np.multiply(0.5 * alpha, tau, out=out)
    x = np.add(w0, x, out=x)
    return np.multiply(tau, x, out=x)


def _delay_at_angle(a, w0, alpha, work=None, out=None):
    """The time after the OPR pulse at which the angle reaches ``a``, s: the stable root
    ``2 a / (w0 + sqrt(w0^2 + 2 alpha a))`` of ``w0 tau + alpha tau^2 / 2 = a`` (no
    cancellation as alpha -> 0). ``work`` and ``out`` (may be ``a``): arrays to reuse."""
    y = np.multiply(2.0 * alpha, a, out=work)
    y = np.add(w0 * w0, y, out=y)
    y = np.sqrt(y, out=y)
    y = np.add(w0, y, out=y)
    num = np.multiply(2.0, a, out=out)
    return np.divide(num, y, out=num)


def _acceleration(s, t):
    """Acceleration of the quadratic angle through three OPR pulses, periods ``s`` then ``t``, rad/s^2."""
    return 2.0 * TWO_PI * (s - t) / (t * s * (t + s))


def _speed_at_pulse(alpha, t):
    """Speed at the OPR pulse of a revolution of period ``t`` under ``alpha``, rad/s."""
    return (TWO_PI - 0.5 * alpha * t * t) / t


def _speed_at_first_pulse(alpha, t):
    """:func:`_speed_at_pulse` of the first revolution (which takes the second one's ``alpha``)."""
    return (TWO_PI - 0.5 * alpha * t ** 2) / t


def _extrapolated_speed(last, before):
    """Mean speed of the revolution after ``before``, ``last``: linear, rad/s."""
    return 2.0 * last - before


def mean_speed_from_opr(opr_s: np.ndarray) -> np.ndarray:
    """Mean speed of each revolution from consecutive OPR times.

    Parameters
    ----------
    opr_s : ndarray, shape (n_rev,)
        OPR pulse times, s, increasing; ``n_rev >= 2``.

    Returns
    -------
    ndarray, shape (n_rev,)
        ``Omega_n = 2 pi / (OPR_n+1 - OPR_n)``, rad/s; the last revolution, whose end is not
        known, is extrapolated linearly, ``2 Omega_{n-1} - Omega_{n-2}``.
    """
    opr = np.asarray(opr_s, dtype=float)
    if opr.ndim != 1 or opr.size < 2:
        raise ValueError("at least two OPR times are needed for a speed")
    om = TWO_PI / np.diff(opr)
    last = _extrapolated_speed(om[-1], om[-2]) if om.size >= 2 else om[-1]
    return np.append(om, last)


def _phase_coefficients(t_prev: np.ndarray, t_cur: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Speed at the OPR pulse and acceleration of the quadratic angle through three OPR pulses.

    ``w T + alpha T^2 / 2 = 2 pi`` (next pulse) and ``-w S + alpha S^2 / 2 = -2 pi``
    (previous pulse), with ``T = t_cur``, ``S = t_prev`` the periods; ``S`` NaN: linear.
    """
    s, t = np.asarray(t_prev, float), np.asarray(t_cur, float)
    alpha = _acceleration(s, t)
    alpha = np.where(np.isfinite(alpha), alpha, 0.0)
    return _speed_at_pulse(alpha, t), alpha


def rotor_phase_from_opr(opr_s: np.ndarray) -> RotorPhase:
    """Per-revolution quadratic rotor angle from the OPR times alone.

    Parameters
    ----------
    opr_s : ndarray, shape (n_rev,)
        OPR times, s, increasing; ``n_rev >= 2``.

    Returns
    -------
    RotorPhase

    Notes
    -----
    Revolution ``n`` uses the pulses ``n-1, n, n+1`` (constant acceleration over two
    revolutions; exact for a piecewise-linear speed away from its knots). The first
    revolution takes the acceleration of the second; the last one, whose end is unknown,
    uses the extrapolated mean speed of :func:`mean_speed_from_opr`.
    """
    opr = np.asarray(opr_s, dtype=float)
    om = mean_speed_from_opr(opr)
    period = TWO_PI / om
    prev = np.concatenate([[np.nan], period[:-1]])
    w0, alpha = _phase_coefficients(prev, period)
    if opr.size >= 2:
        alpha[0] = alpha[1]
        w0[0] = _speed_at_first_pulse(alpha[0], period[0])
    return RotorPhase(opr_s=opr, omega0_rad_s=w0, alpha_rad_s2=alpha, omega_mean_rad_s=om)


def _phase_row(opr_s: np.ndarray, row: int) -> tuple[float, float, float] | None:
    """Row ``row`` of ``rotor_phase_from_opr(opr_s)`` for 2 or 3 pulses, as Python floats
    ``(omega0, alpha, omega_mean)`` (the same operations as the array code); None when the
    window is degenerate (repeated pulses: the array code handles it)."""
    o = opr_s.tolist()
    n = len(o)
    try:
        om = [TWO_PI / (o[j + 1] - o[j]) for j in range(n - 1)]  # mean_speed_from_opr
        om.append(_extrapolated_speed(om[-1], om[-2]) if len(om) >= 2 else om[-1])
        period = [TWO_PI / w for w in om]
        if row == 0:  # the first revolution takes the second one's acceleration
            alpha = _finite_or_zero(_acceleration(period[0], period[1])) if n >= 2 else 0.0
            w0 = _speed_at_first_pulse(alpha, period[0])
        else:
            alpha = _finite_or_zero(_acceleration(period[row - 1], period[row]))
            w0 = _speed_at_pulse(alpha, period[row])
    except (ZeroDivisionError, OverflowError, IndexError):
        return None
    if not (math.isfinite(w0) and math.isfinite(alpha) and math.isfinite(om[row])):
        return None
    return w0, alpha, om[row]


def _finite_or_zero(x: float) -> float:
    return x if math.isfinite(x) else 0.0


def calibrate_arrival_angles(phase: RotorPhase, toa_s: np.ndarray,
                             revolutions: slice | tuple[int, int] | int) -> np.ndarray:
    """Arrival angle of each blade at each probe, calibrated over a reference window.

    Parameters
    ----------
    phase : RotorPhase
        Rotor angle model of the revolutions of ``toa_s``.
    toa_s : ndarray, shape (n_rev, n_blades, n_probes)
        TOAs, s (NaN for missing).
    revolutions : int, (start, stop) or slice
        The reference window (an int ``n`` means the first ``n`` revolutions). It should
        be at low speed and free of resonances: any vibration in it becomes the reference.

    Returns
    -------
    ndarray, shape (n_blades, n_probes)
        Median over the window of the rotor angle since the OPR pulse at the TOA, rad;
        NaN where no arrival was seen.
    """
    if isinstance(revolutions, (int, np.integer)):
        sel = slice(0, int(revolutions))
    elif isinstance(revolutions, slice):
        sel = revolutions
    else:
        sel = slice(int(revolutions[0]), int(revolutions[1]))
    toa = toa_s[sel] if isinstance(toa_s, ScratchRows) else np.asarray(toa_s, dtype=float)[sel]
    if toa.shape[0] == 0:
        raise ValueError("the calibration window holds no revolution")
    ang = phase.rows(sel).angle(toa)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # an all-NaN column stays NaN
        return np.nanmedian(ang, axis=0)


def expected_times(phase: RotorPhase, arrival_angles_rad: np.ndarray, toa_s: np.ndarray) -> np.ndarray:
    """Expected arrival times of the undeformed blades from the OPR model.

    Parameters
    ----------
    phase : RotorPhase
    arrival_angles_rad : ndarray, shape (n_blades, n_probes)
        Rotor angle after the OPR pulse at which each blade reaches each probe, rad.
    toa_s : ndarray, shape (n_rev, n_blades, n_probes)
        Measured TOAs, s; they select, for each arrival, the representative
        ``psi + 2 pi k`` nearest to the measured angle (NaN TOA: ``k = 0``).

    Returns
    -------
    ndarray, shape (n_rev, n_blades, n_probes)
        ``t_exp``, s.
    """
    return phase.opr_s[:, None, None] + _expected_delay(phase, np.asarray(toa_s, dtype=float),
                                                        np.asarray(arrival_angles_rad, dtype=float))


def _expected_delay(phase: RotorPhase, toa: np.ndarray, psi: np.ndarray) -> np.ndarray:
    """Time after each revolution's OPR pulse at which the rotor model reaches the
    representative ``psi + 2 pi k`` nearest to the measured angle of each TOA (``k = 0``
    where the TOA is missing), s."""
    ex = (slice(None),) + (None,) * (toa.ndim - 1)
    return _delay_to_nearest(toa - phase.opr_s[ex], phase.omega0_rad_s[ex], phase.alpha_rad_s2[ex], psi)


def _delay_to_nearest(tau, w0, alpha, psi):
    """:func:`_expected_delay` from the arrivals' times ``tau`` after their OPR pulse (a new
    array, s), the phase ``w0``, ``alpha`` (broadcast against ``tau``) and ``psi``."""
    x = _rotor_angle(tau, w0, alpha)
    x -= psi
    x /= TWO_PI
    k = np.rint(x, out=x)  # np.round: the revolution number of the nearest representative
    a = np.where(np.isfinite(k), k, 0.0)
    a = np.multiply(TWO_PI, a, out=a)
    a = np.add(psi, a, out=a)  # psi + 2 pi k
    return _delay_at_angle(a, w0, alpha, work=x, out=a)


def btt_displacement(omega_rad_s: np.ndarray, tip_radius_m: float, t_exp_s: np.ndarray,
                     toa_s: np.ndarray) -> np.ndarray:
    """Eq. 1: ``d = Omega R (t_exp - t_TOA)``.

    Parameters
    ----------
    omega_rad_s : ndarray, shape (n_rev,)
        Mean speed over each revolution, rad/s.
    tip_radius_m : float
    t_exp_s, toa_s : ndarray, shape (n_rev, n_blades, n_probes)

    Returns
    -------
    ndarray, shape (n_rev, n_blades, n_probes)
        Displacement in the direction of rotation, m (a blade arriving early is positive).
    """
    om = np.asarray(omega_rad_s, dtype=float)
    return (om * float(tip_radius_m))[:, None, None] * (np.asarray(t_exp_s, float) - np.asarray(toa_s, float))


@dataclass(frozen=True, slots=True, eq=False)
class Displacements:
    """Eq. 1 displacements with how they were obtained.

    Attributes
    ----------
    d_m : ndarray or ScratchRows, shape (n_rev, n_blades, n_probes)
        (:class:`~.history.ScratchRows`: written to scratch files, read by rows or columns.)
    omega_rad_s : ndarray, shape (n_rev,)
        Mean speed of each revolution (from the OPR times), rad/s.
    exact_t_exp_s : ndarray, shape (n_rev, n_blades, n_probes), or None
        The exact expected times given (None: from the OPR model).
    arrival_angles_rad : ndarray, shape (n_blades, n_probes), or None
        The ``psi`` used (None with exact expected times).
    method : str
        ``"exact"``, ``"calibrated"`` or ``"nominal"``.
    phase : RotorPhase or None
        The rotor angle model (OPR-based expected times).
    toa_s : ndarray, shape (n_rev, n_blades, n_probes), or None
        The TOAs the displacements come from (OPR-based expected times).

    Notes
    -----
    :attr:`t_exp_s` (a whole-run array) is computed when asked for, not kept: the same
    numbers as the displacements used (:func:`expected_times`).
    """

    d_m: np.ndarray
    omega_rad_s: np.ndarray
    exact_t_exp_s: np.ndarray | None
    arrival_angles_rad: np.ndarray | None
    method: str
    phase: RotorPhase | None = None
    toa_s: np.ndarray | None = None

    @property
    def t_exp_s(self) -> np.ndarray:
        """Expected arrival times, shape (n_rev, n_blades, n_probes), s."""
        if self.exact_t_exp_s is not None:
            return self.exact_t_exp_s
        return expected_times(self.phase, self.arrival_angles_rad, self.toa_s)

    def t_exp_at(self, rows: slice) -> np.ndarray:
        """``t_exp_s[rows]`` (a slice of revolutions; the same numbers: :func:`expected_times`
        is element-wise) without the whole run's array; the TOAs read for those rows only
        (an array or a :class:`~.history.ScratchRows`)."""
        if self.exact_t_exp_s is not None:
            return np.asarray(self.exact_t_exp_s[rows], dtype=float)
        return expected_times(self.phase.rows(rows), self.arrival_angles_rad, self.toa_s[rows])


def _run_arrays(opr_s, toa_s, geometry: Geometry) -> tuple[np.ndarray, np.ndarray]:
    """OPR times and TOAs as float arrays, their shapes checked against each other and the
    geometry (ValueError)."""
    opr = np.asarray(opr_s, dtype=float)
    toa = toa_s if isinstance(toa_s, ScratchRows) else np.asarray(toa_s, dtype=float)
    if toa.ndim != 3 or toa.shape[0] != opr.size:
        raise ValueError(f"toa_s must be (n_rev, n_blades, n_probes) with n_rev = {opr.size}, got {toa.shape}")
    if toa.shape[1:] != (geometry.n_blades, geometry.n_probes):
        raise ValueError(f"toa_s has {toa.shape[1:]} (blades, probes); the geometry "
                         f"({geometry.n_blades}, {geometry.n_probes})")
    return opr, toa


def compute_displacements(opr_s: np.ndarray, toa_s: np.ndarray, geometry: Geometry, *,
                          t_exp_s: np.ndarray | None = None,
                          calibration: int | tuple[int, int] | None = 64,
                          arrival_angles_rad: np.ndarray | None = None, scratch: bool = False) -> Displacements:
    """BTT displacements (Eq. 1) from OPR and TOA arrays.

    Parameters
    ----------
    opr_s : ndarray, shape (n_rev,)
        OPR times, s.
    toa_s : ndarray, shape (n_rev, n_blades, n_probes)
        TOAs, s (NaN for a missing arrival).
    geometry : Geometry
    t_exp_s : ndarray, shape (n_rev, n_blades, n_probes), optional
        Exact expected times (the simulator's truth, as in the paper); the OPR times then
        only give the speed.
    calibration : int or (start, stop), optional
        Reference window for :func:`calibrate_arrival_angles` (int: the first revolutions);
        None or 0: the nominal arrival angles of ``geometry``.
    arrival_angles_rad : ndarray, shape (n_blades, n_probes), optional
        Use these arrival angles (e.g. from an earlier calibration) instead.
    scratch : bool
        Write the displacements, block by block, to a :class:`~.history.ScratchRows` (two
        scratch files read back by rows or columns, the same numbers) instead of holding them
        (``d_m`` is then that object): for a report of a long run.

    Returns
    -------
    Displacements
    """
    opr, toa = _run_arrays(opr_s, toa_s, geometry)
    d = ScratchRows(toa.shape[1:]) if scratch else np.empty(toa.shape)
    phase = rotor_phase_from_opr(opr)
    if t_exp_s is not None:
        t_exp = np.asarray(t_exp_s, dtype=float)
        om = phase.omega_mean_rad_s
        for a, b in _blocks(opr.size):  # element-wise: by blocks, the same numbers
            _put(d, a, b, btt_displacement(om[a:b], geometry.tip_radius_m, t_exp[a:b], toa[a:b]))
        return Displacements(d, om, t_exp, None, "exact")
    if arrival_angles_rad is not None:
        psi, method = np.asarray(arrival_angles_rad, dtype=float), "calibrated"
    elif calibration:
        psi, method = calibrate_arrival_angles(phase, toa, calibration), "calibrated"
        nominal = geometry.nominal_arrival_angles()
        psi = np.where(np.isfinite(psi), psi, nominal)
    else:
        psi, method = geometry.nominal_arrival_angles(), "nominal"
    for a, b in _blocks(opr.size):  # in blocks: bounded temporaries (Eq. 1 is per revolution)
        _put(d, a, b, displacements_from_phase(phase.rows(slice(a, b)), toa[a:b], psi, geometry.tip_radius_m)[0])
    return Displacements(d, phase.omega_mean_rad_s, None, psi, method, phase=phase, toa_s=toa)


#: Revolutions of Eq. 1 computed at once by :func:`compute_displacements`.
DISPLACEMENT_CHUNK = 4096


def _blocks(n: int):
    """``(a, b)``: revolutions ``a .. b - 1``, :data:`DISPLACEMENT_CHUNK` at a time."""
    return ((a, min(a + DISPLACEMENT_CHUNK, n)) for a in range(0, n, DISPLACEMENT_CHUNK))


def _put(d, a: int, b: int, block: np.ndarray) -> None:
    """Rows ``a .. b - 1`` of ``d`` (an array, or a :class:`~.history.ScratchRows` written in order)."""
    if isinstance(d, ScratchRows):
        d.write(block)
    else:
        d[a:b] = block


@dataclass(frozen=True, slots=True, eq=False)
class DisplacementRows:
    """Eq. 1 displacements computed when asked for, not held: ``rows[a:b]`` (a slice of
    revolutions) or :meth:`blades` (every revolution of some blades) are the same numbers as
    the rows or blades of :func:`compute_displacements`'s ``d_m`` (Eq. 1 is element-wise).

    Attributes
    ----------
    phase : RotorPhase
    toa_s : ndarray, shape (n_rev, n_blades, n_probes)
    arrival_angles_rad : ndarray, shape (n_blades, n_probes), or None
        ``psi`` (None with exact expected times).
    tip_radius_m : float
    exact_t_exp_s : ndarray, shape (n_rev, n_blades, n_probes), or None
        Exact expected times (the truth's), instead of the OPR model's.
    """

    phase: RotorPhase
    toa_s: np.ndarray
    arrival_angles_rad: np.ndarray | None
    tip_radius_m: float
    exact_t_exp_s: np.ndarray | None = None

    @property
    def shape(self) -> tuple:
        return self.toa_s.shape

    @property
    def omega_rad_s(self) -> np.ndarray:
        """Mean speed of each revolution, rad/s."""
        return self.phase.omega_mean_rad_s

    def __getitem__(self, rows: slice) -> np.ndarray:
        if not isinstance(rows, slice):
            raise TypeError(f"DisplacementRows takes a slice of revolutions, got {type(rows).__name__}")
        return self._eq1(rows, slice(None))

    def blades(self, sel: slice) -> np.ndarray:
        """Every revolution of blades ``sel``, shape (n_rev, n_selected, n_probes), computed
        :data:`DISPLACEMENT_CHUNK` revolutions at a time."""
        n = self.toa_s.shape[0]
        out = np.empty((n,) + self.toa_s[:1, sel].shape[1:])
        for a in range(0, n, DISPLACEMENT_CHUNK):
            b = min(a + DISPLACEMENT_CHUNK, n)
            out[a:b] = self._eq1(slice(a, b), sel)
        return out

    def _eq1(self, rows: slice, sel: slice) -> np.ndarray:
        toa = self.toa_s[rows, sel]
        if self.exact_t_exp_s is not None:
            return btt_displacement(self.phase.omega_mean_rad_s[rows], self.tip_radius_m,
                                    self.exact_t_exp_s[rows, sel], toa)
        return displacements_from_phase(self.phase.rows(rows), toa, self.arrival_angles_rad[sel],
                                        self.tip_radius_m)[0]


def first_pass_rows(opr_s: np.ndarray, toa_s: np.ndarray, geometry: Geometry, *,
                    t_exp_s: np.ndarray | None = None) -> DisplacementRows:
    """The displacements of :func:`compute_displacements` with the nominal geometry (or exact
    expected times) and no calibration, as :class:`DisplacementRows`: computed when asked for."""
    opr, toa = _run_arrays(opr_s, toa_s, geometry)
    phase = rotor_phase_from_opr(opr)
    if t_exp_s is not None:
        return DisplacementRows(phase, toa, None, geometry.tip_radius_m, np.asarray(t_exp_s, dtype=float))
    return DisplacementRows(phase, toa, geometry.nominal_arrival_angles(), geometry.tip_radius_m)


def displacements_from_phase(phase: RotorPhase, toa_s: np.ndarray, arrival_angles_rad: np.ndarray,
                             tip_radius_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 1 displacements of some revolutions, given their rotor phase and arrival angles.

    This is the one implementation of Eq. 1 with OPR-based expected times: the offline
    pipeline (:func:`compute_displacements`), the streaming processor (one revolution at a
    time) and the views all call it.

    Parameters
    ----------
    phase : RotorPhase
        The rotor angle model of these revolutions (:func:`rotor_phase_from_opr`, or rows of it).
    toa_s : ndarray, shape (n_rev, n_blades, n_probes)
        TOAs, s (NaN: missing).
    arrival_angles_rad : ndarray, shape (n_blades, n_probes)
        ``psi``: nominal or calibrated (:func:`calibrate_arrival_angles`).
    tip_radius_m : float

    Returns
    -------
    d_m : ndarray, shape (n_rev, n_blades, n_probes)
        ``Omega R (t_exp - t_TOA)``, m.
    tau_exp_s : ndarray, shape (n_rev, n_blades, n_probes)
        Expected arrival times after the revolution's OPR pulse, s.
    """
    toa = np.asarray(toa_s, dtype=float)
    # times relative to the OPR pulse: no cancellation of the absolute time (130 s) in Eq. 1
    tau = toa - phase.opr_s[:, None, None]
    tau_exp = _delay_to_nearest(tau, phase.omega0_rad_s[:, None, None], phase.alpha_rad_s2[:, None, None],
                                np.asarray(arrival_angles_rad, dtype=float))
    return btt_displacement(phase.omega_mean_rad_s, tip_radius_m, tau_exp, tau), tau_exp


def revolution_displacements(opr_s: np.ndarray, row: int, toa_s: np.ndarray, arrival_angles_rad: np.ndarray,
                             tip_radius_m: float, out: np.ndarray) -> float:
    """Eq. 1 displacements of one revolution, fast (the streaming processor's entry point).

    Row ``row`` of ``displacements_from_phase(rotor_phase_from_opr(opr_s), ...)``, bit for
    bit, with the rotor phase as Python floats and two work arrays: a few microseconds
    instead of the array code's tens.

    Parameters
    ----------
    opr_s : ndarray, shape (2,) or (3,)
        The OPR pulses of the revolution's phase model (:func:`rotor_phase_from_opr`), s.
    row : int
        The revolution's index in ``opr_s``.
    toa_s : ndarray, shape (n_blades, n_probes)
        The revolution's TOAs, s (NaN: missing).
    arrival_angles_rad : ndarray, shape (n_blades, n_probes)
    tip_radius_m : float
    out : ndarray, shape (n_blades, n_probes)
        Written with the displacements, m.

    Returns
    -------
    float
        The revolution's mean speed (Eq. 1's Omega), rad/s.
    """
    phase = _phase_row(opr_s, row)
    if phase is None:  # a degenerate OPR window (e.g. repeated pulses): the array code
        rows = rotor_phase_from_opr(opr_s).rows(slice(row, row + 1))
        d, _ = displacements_from_phase(rows, toa_s[None], arrival_angles_rad, tip_radius_m)
        out[...] = d[0]
        return float(rows.omega_mean_rad_s[0])
    w0, alpha, om = phase
    tau = np.subtract(toa_s, float(opr_s[row]))
    d = _delay_to_nearest(tau, w0, alpha, arrival_angles_rad)
    d -= tau
    np.multiply(om * float(tip_radius_m), d, out=out)  # btt_displacement
    return om


def outside_revolution(toa_s: np.ndarray, opr_s: np.ndarray, period_s: np.ndarray) -> np.ndarray:
    """Which TOAs are impossible for Eq. 1: neither NaN (missing) nor within a revolution of
    their OPR pulse, ``opr - T <= toa <= opr + 2 T`` (``T`` the revolution's period, from its
    OPR pulse to the next; the last revolution's, the one before). Recordings holding one are
    refused; the live processor drops them. Shapes broadcast (``opr_s`` and ``period_s``
    against the revolution axis of ``toa_s``); a period that is not positive makes every TOA of
    its revolution impossible."""
    toa = np.asarray(toa_s, dtype=float)
    rel = toa - opr_s
    with np.errstate(invalid="ignore"):
        return ~np.isnan(toa) & ~((rel >= -period_s) & (rel <= 2.0 * period_s))


def assign_extra_edges(toa_s: np.ndarray, edge_s: np.ndarray, *, tolerance: float = 0.5) -> np.ndarray:
    """The blade whose window each extra trigger edge (a double pulse) falls in.

    Parameters
    ----------
    toa_s : ndarray, shape (n_blades,)
        One probe's TOAs of one revolution (the first edge latched in each blade's window),
        s; NaN: missing.
    edge_s : ndarray, shape (n_edges,)
        The later edges the acquisition reported for that probe and revolution, s.
    tolerance : float
        Largest distance of an edge from its blade's TOA, as a fraction of the blade spacing
        in time (the median gap between consecutive TOAs).

    Returns
    -------
    ndarray of int64, shape (n_edges,)
        The blade of each edge, -1 for an edge in no blade's window (spurious, or fewer than
        two TOAs to size a window).

    Notes
    -----
    Blade ``b``'s window is ``|t - toa_b| <= tolerance * median(diff(sort(toa)))``; an edge
    goes to the nearest TOA within it. A double pulse is the noise re-crossing the trigger
    level within one passage: its extra edges lie microseconds after the first, a blade
    spacing is hundreds of microseconds, so the nearest TOA is the blade's own. The first
    edge stays the blade's TOA (what the hardware latched); the extra ones are counted
    (:class:`DoublePulses`), not used.
    """
    t = np.asarray(toa_s, dtype=float)
    e = np.asarray(edge_s, dtype=float).ravel()
    out = np.full(e.size, -1, dtype=np.int64)
    blades = np.flatnonzero(np.isfinite(t))
    if e.size == 0 or blades.size < 2:
        return out
    order = np.argsort(t[blades])
    ts, bs = t[blades][order], blades[order]
    window = tolerance * float(np.median(np.diff(ts)))
    i = np.clip(np.searchsorted(ts, e), 1, ts.size - 1)
    near = np.where(np.abs(e - ts[i - 1]) <= np.abs(ts[i] - e), i - 1, i)
    ok = np.isfinite(e) & (np.abs(e - ts[near]) <= window)
    out[ok] = bs[near[ok]]
    return out


class DoublePulses:
    """Counts of double pulses in the TOA batches of a run (the summary's ``double_pulses``,
    ``extra_edges``, ``stray_edges``).

    Attributes
    ----------
    double_pulses : int
        Passages (revolution, blade, probe) with at least one extra edge.
    extra_edges : int
        Extra edges assigned to a blade's window (:func:`assign_extra_edges`).
    stray_edges : int
        Extra edges in no blade's window.
    """

    def __init__(self) -> None:
        self.double_pulses = self.extra_edges = self.stray_edges = 0

    def add(self, toa_s: np.ndarray, edge_s: np.ndarray) -> None:
        """One probe's TOAs of one revolution and the extra edges reported with them."""
        if np.size(edge_s) == 0:
            return
        blade = assign_extra_edges(toa_s, edge_s)
        mine = blade[blade >= 0]
        self.extra_edges += int(mine.size)
        self.stray_edges += int(blade.size - mine.size)
        self.double_pulses += int(np.unique(mine).size)

    def to_summary(self) -> dict:
        return {"double_pulses": self.double_pulses, "extra_edges": self.extra_edges,
                "stray_edges": self.stray_edges}


def identify_blades(opr_s: np.ndarray, pulse_s: np.ndarray, probe_angle_rad: float,
                    geometry: Geometry, *, tolerance: float = 0.25) -> np.ndarray:
    """Assign one probe's raw, unlabelled pulse times to revolutions and blades.

    Parameters
    ----------
    opr_s : ndarray, shape (n_rev,)
        OPR times, s.
    pulse_s : ndarray, shape (n_pulses,)
        Pulse times at the probe, s, in any order; may miss pulses and hold spurious ones.
    probe_angle_rad : float
    geometry : Geometry
        Blade count, blade angles and OPR angle.
    tolerance : float
        Largest distance of a pulse from its blade's expected angle, as a fraction of the
        blade pitch ``2 pi / n_blades``; pulses further away are dropped as spurious.

    Returns
    -------
    ndarray, shape (n_rev, n_blades)
        The pulse time of each blade in each revolution, s; NaN where none was assigned.

    Notes
    -----
    Each pulse's total rotor angle ``Phi = 2 pi n + phi_n(t)`` (quadratic OPR model) is
    matched to the nearest expected angle ``psi_b + 2 pi m``; ``m`` is the revolution (the
    one whose rigid crossing it belongs to) and ``b`` the blade, so a missing pulse leaves a
    NaN and shifts nothing. When several pulses claim one ``(m, b)``, the nearest wins.
    With the sensing points' true angles (``Geometry.from_info(info, model)``) the labels
    are the simulator's; with nominal angles a blade whose crossing lies within the angle
    error of the OPR pulse may be labelled one revolution apart, consistently, which
    :func:`compute_displacements` handles (nearest representative of ``psi``).
    """
    opr = np.asarray(opr_s, dtype=float)
    t = np.asarray(pulse_s, dtype=float).ravel()
    t = t[np.isfinite(t)]
    nr, nb = opr.size, geometry.n_blades
    out = np.full((nr, nb), np.nan)
    if t.size == 0:
        return out
    phase = rotor_phase_from_opr(opr)
    n = np.clip(np.searchsorted(opr, t, side="right") - 1, 0, nr - 1)
    total = TWO_PI * n + phase.rows(n).angle(t)
    psi = np.mod(float(probe_angle_rad) - geometry.blade_angles_rad - geometry.opr_angle_rad, TWO_PI)
    order = np.argsort(psi)
    ps = psi[order]
    r = np.mod(total, TWO_PI)
    i = np.searchsorted(ps, r)
    lo, hi = (i - 1) % nb, i % nb
    d_lo = np.abs(np.mod(r - ps[lo] + np.pi, TWO_PI) - np.pi)
    d_hi = np.abs(np.mod(r - ps[hi] + np.pi, TWO_PI) - np.pi)
    pick = np.where(d_lo <= d_hi, lo, hi)
    blade = order[pick]
    resid = np.minimum(d_lo, d_hi)
    m = np.round((total - psi[blade]) / TWO_PI).astype(np.int64)
    ok = (resid <= tolerance * TWO_PI / nb) & (m >= 0) & (m < nr)
    if not np.any(ok):
        return out
    m, blade, resid, t = m[ok], blade[ok], resid[ok], t[ok]
    key = m * nb + blade
    srt = np.lexsort((resid, key))
    first = np.ones(srt.size, bool)
    first[1:] = key[srt][1:] != key[srt][:-1]
    keep = srt[first]
    out[m[keep], blade[keep]] = t[keep]
    return out

"""Non-synchronous vibration (NSV): rotating stall, flutter and broadband blade forcing.

Conventions
-----------
Blades ``b = 0 .. N_b - 1`` sit at rotor angles ``theta_b = 2 pi b / N_b`` (anticlockwise,
the direction of rotation). Every response is written as carriers
``Im(G_b(t) exp(i theta(t)))`` with the carrier phase ``theta(t) = EO phi(t) + omega t``
(:class:`~bttsim_stream.sim.modal.EnvelopeIntegrator`): ``EO`` need not be an integer and
``omega`` (rad/s) is a constant frequency in the rotor frame. Signed nodal diameters follow
:mod:`bttsim_stream.process.travelling_wave`: a response whose phase, at positive frequency,
advances by ``+2 pi k / N_b`` from blade ``b`` to ``b + 1`` has ND ``+k`` (forward).

Rotating stall / non-integral forcing (``[[rotating_stall]]``)
    ``N_s`` cells turning at ``r Omega`` in the stationary frame load blade ``b`` with
    ``F cos(N_s (1 - r) phi(t) + N_s theta_b)``: ``EO = N_s (1 - r)`` (non-integer),
    ``omega = 0``, spatial order ``N_s`` (ND ``N_s mod N_b``). A pattern of fixed
    stationary-frame frequency ``f_s`` gives ``F cos(N_s phi(t) + N_s theta_b - 2 pi f_s t)``:
    ``EO = N_s``, ``omega = -2 pi f_s``. Rotor-frame frequency ``|EO Omega + omega| / 2 pi``.
    Both are forced carriers of the exact envelope recursion, so the response is exact
    (start-up, resonance crossings) like the engine-order response.

Flutter (``[flutter]``)
    A travelling wave of one mode pair (family, ND) with negative aerodynamic damping
    ``zeta_a`` above the structural ``zeta_s``; the opposite direction of the pair is taken as
    aerodynamically stable and is not excited. Model: the wave's modal amplitude obeys the
    Van der Pol equation ``q'' + 2 zeta_s w q' - 2 zeta_a w (1 - beta q^2) q' + w^2 q = 0``
    averaged over a cycle (Krylov-Bogoliubov; ``sigma / w`` ~ 1e-2 or less), i.e. the
    logistic law ``R' = sigma R (1 - R^2 / R_lim^2)``, ``sigma = (zeta_a - zeta_s) w``,
    ``R_lim^2 = 4 (zeta_a - zeta_s) / (zeta_a beta)`` (set by ``limit_amplitude_m``), with the
    closed form ``R(t) = R_lim / sqrt(1 + (R_lim^2 / R_0^2 - 1) exp(-2 sigma (t - t_on)))``
    from the seed ``R_0`` at onset ``t_on`` (``R = 0`` before), at the damped frequency
    ``w_d = w sqrt(1 - zeta_s^2)``. It is one more carrier (``EO = 0``, ``omega = w_d``)
    whose envelope ``G_b = R(t) T_b`` and exact derivative ``R'(t) T_b`` are evaluated on the
    envelope grid (no recursion), added to the forced linear response. ``T_b`` is the pair's
    travelling shape at the tip (compressed basis), scaled so that ``R`` is the pk-pk
    ``d_eqv`` at P_nom of the blade with the largest. The jump of ``R`` from 0 to ``R_0`` at
    onset, inside one envelope step, is interpolated: it moves the TOAs of that step by at
    most about ``R_0 / (R_tip Omega)`` (2e-11 s for the default 1 nm seed).

Broadband forcing (``[broadband]``)
    A flat one-sided force PSD ``S`` (N^2/Hz) over ``[f_lo, f_hi]``, realised as ``n`` lines at
    the centres of ``n`` equal sub-bands (width ``df``), each of amplitude ``sqrt(2 S df)`` per
    blade with a phase drawn per blade and line from ``SeedSequence([seed, 5])`` (bit-identical
    per seed): ``n`` forced carriers ``EO = 0``, ``omega = 2 pi f_j``, each exact. Cost: like
    ``n`` excitations (every mode responds to random blade phases), i.e. roughly ``n`` times
    the envelope work of one excitation and ``n + 1`` carriers per crossing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import BttsimError
from .forcing import edge_shapes

__all__ = ["KINDS", "NsvComponent", "FlutterWave", "NsvSetup", "signed_nd", "build_nsv", "flutter_onset_s"]

KINDS = ("rotating_stall", "flutter", "broadband")
TWO_PI = 2.0 * np.pi


def signed_nd(k, n_blades: int):
    """Spatial order ``k`` as a signed nodal diameter in ``(-N_b / 2, N_b / 2]``."""
    k = np.mod(np.asarray(k, np.int64), n_blades)
    return np.where(2 * k > n_blades, k - n_blades, k)


@dataclass(frozen=True, slots=True, eq=False)
class NsvComponent:
    """One non-synchronous vibration of the scenario, as the truth describes it.

    Attributes
    ----------
    kind : str
        One of :data:`KINDS`.
    nodal_diameter : int
        Signed ND at positive ``EO Omega + omega`` (broadband: 0, every ND).
    eo, omega : float
        Carrier phase ``EO phi + omega t`` (omega in rad/s); broadband: 0 and the band centre.
    band_hz : tuple of float
        Broadband: ``(low, high)``; else ``(0, 0)``.
    carriers : tuple of int
        Indices of the component's carriers among the simulator's carriers.
    """

    kind: str
    nodal_diameter: int
    eo: float
    omega: float
    band_hz: tuple
    carriers: tuple


@dataclass(frozen=True, slots=True, eq=False)
class FlutterWave:
    """A flutter travelling wave: closed-form amplitude, fixed shape (see the module notes).

    Attributes
    ----------
    omega : float
        Damped frequency of the mode pair, rad/s (the carrier frequency).
    sigma : float
        Growth rate ``(zeta_a - zeta_s) w``, 1/s.
    t_on : float
        Onset time, s.
    seed_m, limit_m : float
        Amplitude at onset and limit amplitude, m pk-pk.
    shape : ndarray, shape (n_blades, r), complex
        Compressed tip shape per unit amplitude, phase included (``G_b = R(t) shape_b``).
    nodal_diameter : int
    modes : tuple of int
    """

    omega: float
    sigma: float
    t_on: float
    seed_m: float
    limit_m: float
    shape: np.ndarray
    nodal_diameter: int
    modes: tuple

    def amplitude(self, t) -> tuple[np.ndarray, np.ndarray]:
        """``R(t)`` (m pk-pk) and ``R'(t)`` (m/s): 0 before onset, the logistic law after."""
        t = np.asarray(t, float)
        s = np.maximum(t - self.t_on, 0.0)
        k = (self.limit_m / self.seed_m) ** 2 - 1.0
        R = self.limit_m / np.sqrt(1.0 + k * np.exp(-2.0 * self.sigma * s))
        on = t >= self.t_on
        R = np.where(on, R, 0.0)
        dR = self.sigma * R * (1.0 - (R / self.limit_m) ** 2)
        return R, dR

    def tip_amplitude(self, nodes_p: np.ndarray) -> np.ndarray:
        """Zero-to-peak amplitude of each blade's P_nom at the limit cycle, m (n_blades,);
        ``nodes_p`` (r, 3): compressed coordinates -> P_nom (radial, tangential, axial)."""
        A = self.limit_m * (self.shape @ nodes_p)  # (n_blades, 3) complex
        return np.sqrt(np.sum(np.abs(A) ** 2, axis=1))

    def envelope(self, t) -> tuple[np.ndarray, np.ndarray]:
        """Envelope ``G`` and its exact derivative, shape (n, n_blades, r), complex."""
        R, dR = self.amplitude(t)
        return R[:, None, None] * self.shape[None], dR[:, None, None] * self.shape[None]


@dataclass(frozen=True, slots=True, eq=False)
class NsvSetup:
    """The scenario's NSV, ready for the simulator.

    Attributes
    ----------
    C : ndarray, shape (n_modes, n_forced), complex
        Modal forces of the forced carriers (stall, broadband), as
        :func:`~bttsim_stream.sim.forcing.modal_forcing`.
    eo, omega : ndarray, shape (n_forced,)
    flutter : FlutterWave or None
    components : tuple of NsvComponent
        Carrier indices count from the first NSV carrier (forced ones, then flutter).
    """

    C: np.ndarray
    eo: np.ndarray
    omega: np.ndarray
    flutter: FlutterWave | None
    components: tuple

    @property
    def n_carriers(self) -> int:
        return self.eo.size + (self.flutter is not None)


def _force_column(model, node, direction, pattern: np.ndarray) -> np.ndarray:
    """Modal force ``(shapes @ d) @ pattern`` of a per-blade complex force pattern (N)."""
    d = np.asarray(direction, float)
    d = d / np.linalg.norm(d)
    return (edge_shapes(model, node) @ d) @ pattern


def flutter_onset_s(fl, speed) -> float:
    """Onset time of ``[flutter]``: ``start_s``, or the first time the speed reaches ``start_rpm``."""
    if fl.start_rpm <= 0:
        return float(fl.start_s)
    target = fl.start_rpm * np.pi / 30.0
    T, Om, al = speed.t_s, speed.omega, speed.alpha
    for k in range(T.size - 1):
        lo, hi = min(Om[k], Om[k + 1]), max(Om[k], Om[k + 1])
        if lo <= target <= hi:
            return float(T[k]) if al[k] == 0 else float(T[k] + (target - Om[k]) / al[k])
    raise BttsimError(f"[flutter] start_rpm = {fl.start_rpm:g}: the speed profile never reaches it")


def _flutter(model, fl, speed, basis, v_eqv) -> FlutterWave:
    if model.family is None or model.nodal_diameter is None:
        raise BttsimError("[flutter] needs the model's mode families and nodal diameters (family, nodal_diameter "
                          "in the model file)")
    nb = model.n_blades
    nd = int(fl.nodal_diameter)
    modes = np.flatnonzero((np.asarray(model.family) == fl.family - 1) & (np.asarray(model.nodal_diameter) == abs(nd)))
    if modes.size not in (1, 2):
        raise BttsimError(f"[flutter] family = {fl.family}, nodal_diameter = {nd}: the model has {modes.size} modes "
                          "of that family and ND (expected 1 or 2)")
    w = TWO_PI * float(np.mean(model.freq_hz[modes]))
    zs = float(np.mean(model.damping_ratio[modes]))
    if not fl.aero_damping_ratio > zs:
        raise BttsimError(f"[flutter] aero_damping_ratio = {fl.aero_damping_ratio:g} must exceed the mode's structural "
                          f"damping ratio {zs:.4g} (else the wave decays)")
    psi = basis.psi[modes]  # (1 or 2, nb, r)
    b = np.arange(nb)
    target = np.exp(2j * np.pi * b * nd / nb)
    if modes.size == 1:
        T = psi[0].astype(complex)
    else:  # the pair's two travelling combinations; keep the one whose phase advances as asked
        cands = [psi[0] + 1j * psi[1], psi[0] - 1j * psi[1]]
        score = [abs(np.vdot(target, c @ v_eqv)) for c in cands]
        T = cands[int(np.argmax(score))]
    y = T @ v_eqv
    scale = 2.0 * float(np.max(np.abs(y)))
    if not scale > 0:
        raise BttsimError(f"[flutter] family {fl.family} ND {nd}: the mode does not move P_nom in the BTT direction")
    t_on = flutter_onset_s(fl, speed)
    wd = w * np.sqrt(1.0 - zs**2)
    shape = T / scale * np.exp(1j * (np.deg2rad(fl.phase_deg) - wd * t_on))
    return FlutterWave(omega=wd, sigma=(fl.aero_damping_ratio - zs) * w, t_on=t_on, seed_m=fl.seed_amplitude_m,
                       limit_m=fl.limit_amplitude_m, shape=np.ascontiguousarray(shape), nodal_diameter=nd,
                       modes=tuple(int(k) for k in modes))


def build_nsv(scn, model, speed, basis, v_eqv) -> NsvSetup | None:
    """The scenario's non-synchronous vibration, or None when it has none.

    Parameters
    ----------
    scn : Scenario
    model : ModalModel
    speed : SpeedProfile
    basis : TipBasis
    v_eqv : ndarray, shape (r,)
        Compressed coordinates -> ``d_eqv`` at P_nom (Eq. 3-4).
    """
    stalls, fl, bb = scn.rotating_stall, scn.flutter, scn.broadband
    if not stalls and not fl.enabled and not bb.enabled:
        return None
    nb = model.n_blades
    b = np.arange(nb)
    cols, eo, om, comps = [], [], [], []
    for st in stalls:
        n_s = st.cells
        pattern = st.amplitude_n * np.exp(2j * np.pi * b * n_s / nb)
        if st.frequency_hz > 0:
            e, w = float(n_s), -TWO_PI * st.frequency_hz
        else:
            e, w = n_s * (1.0 - st.speed_fraction), 0.0
        comps.append(NsvComponent("rotating_stall", int(signed_nd(n_s, nb)), e, w, (0.0, 0.0), (len(cols),)))
        cols.append(_force_column(model, st.node, st.direction, pattern))
        eo.append(e)
        om.append(w)
    if bb.enabled:
        lo, hi = bb.band_hz
        df = (hi - lo) / bb.n_lines
        f = lo + df * (np.arange(bb.n_lines) + 0.5)
        rng = np.random.default_rng(np.random.SeedSequence([scn.run.seed, 5]))
        phase = rng.uniform(0.0, TWO_PI, size=(bb.n_lines, nb))
        amp = np.sqrt(2.0 * bb.psd_n2_per_hz * df)
        first = len(cols)
        for j in range(bb.n_lines):
            cols.append(_force_column(model, bb.node, bb.direction, amp * np.exp(1j * phase[j])))
            eo.append(0.0)
            om.append(TWO_PI * float(f[j]))
        comps.append(NsvComponent("broadband", 0, 0.0, np.pi * (lo + hi), (float(lo), float(hi)),
                                  tuple(range(first, len(cols)))))
    flutter = None
    if fl.enabled:
        flutter = _flutter(model, fl, speed, basis, v_eqv)
        comps.append(NsvComponent("flutter", flutter.nodal_diameter, 0.0, flutter.omega, (0.0, 0.0), (len(cols),)))
    C = np.stack(cols, axis=1) if cols else np.zeros((model.n_modes, 0), complex)
    return NsvSetup(C=C, eo=np.asarray(eo, float), omega=np.asarray(om, float), flutter=flutter,
                    components=tuple(comps))

"""Synthetic BTT data from an analytic non-synchronous blade response (test fixtures).

``x_b(t) = A(t) sin(2 pi f(t) t + 2 pi k b / N_b + c)`` (tangential tip displacement, m,
positive in the direction of rotation) on a rotor turning by ``phi(t) = omega0 t +
alpha t^2 / 2`` (OPR pulse at ``phi = 2 pi n``). Blade ``b`` (nominal angle ``2 pi b / N_b``)
reaches probe ``j`` when ``phi(t) + theta_b + x_b(t) / R = theta_j + 2 pi n'``; each arrival
is found by Newton's method from the rigid crossing, to 1e-15 s, vectorised over all
arrivals. Independent of the processing code (no import of it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

TWO_PI = 2.0 * np.pi
PROBES_DEG = (5.0, 15.15, 23.82, 220.0, 301.5)


@dataclass(frozen=True)
class NsvTruth:
    """The simulator's per-revolution NSV truth fields (``Truth.nsv_*``), one component."""

    nsv_kind: np.ndarray  # (n_rev, 1)
    nsv_freq_hz: np.ndarray
    nsv_nd: np.ndarray
    nsv_amp_pkpk_m: np.ndarray


@dataclass(frozen=True)
class NsvRun:
    opr_s: np.ndarray
    toa_s: np.ndarray
    omega_rad_s: np.ndarray  # mean speed per revolution
    n_blades: int
    probe_angles_rad: np.ndarray
    tip_radius_m: float
    truth: NsvTruth | None = None


def logistic(a0: float, a_lim: float, rate_per_s: float):
    """Flutter's envelope: ``A' = rate A (1 - A / a_lim)``, ``A(0) = a0``, i.e.
    ``A(t) = a_lim / (1 + (a_lim / a0 - 1) exp(-rate t))``."""
    def amp(t):
        return a_lim / (1.0 + (a_lim / a0 - 1.0) * np.exp(-rate_per_s * t))
    return amp


def synthesize(*, n_rev: int, rpm0: float, rpm1: float | None = None, n_blades: int = 29,
               probes_deg=PROBES_DEG, tip_radius_m: float = 0.19, amp_pk_m=None, freq_hz=None,
               order: float | None = None, nd: int = 0, c: float = 0.3, sync=None,
               noise_s: float = 0.0, seed: int = 0) -> NsvRun:
    """Simulate OPR and TOAs of ``n_rev`` revolutions.

    Parameters
    ----------
    amp_pk_m : float or callable(t) -> ndarray
        Zero-to-peak amplitude ``A(t)``, m.
    freq_hz : float, optional
        Fixed rotor-frame frequency (flutter).
    order : float, optional
        Or a fixed order ``f / f_shaft`` (rotating stall, ``N_s (1 - r)``): the phase is then
        ``order phi(t)``.
    nd : int
        Signed nodal diameter ``k``.
    sync : (eo, amp_pk_m, phase) or None
        An added synchronous response ``A sin(EO phi + EO theta_b + phase)`` (casing-fixed;
        ``amp_pk_m`` a float or a callable of t).
    noise_s : float
        Gaussian jitter on each TOA, s (seeded).
    """
    rpm1 = rpm0 if rpm1 is None else rpm1
    w0, w1 = rpm0 * TWO_PI / 60.0, rpm1 * TWO_PI / 60.0
    # phi(T) = 2 pi n_rev with a linear speed from w0 to w1: T = 4 pi n_rev / (w0 + w1)
    T = 2.0 * TWO_PI * n_rev / (w0 + w1)
    alpha = (w1 - w0) / T
    phi_of = lambda t: w0 * t + 0.5 * alpha * t * t  # noqa: E731
    dphi = lambda t: w0 + alpha * t  # noqa: E731

    def time_at(phi):
        if alpha == 0.0:
            return phi / w0
        return 2.0 * phi / (w0 + np.sqrt(w0 * w0 + 2.0 * alpha * phi))

    opr = time_at(TWO_PI * np.arange(n_rev + 1))
    th_b = TWO_PI * np.arange(n_blades) / n_blades
    th_p = np.deg2rad(np.asarray(probes_deg, float))
    psi = np.mod(th_p[None, :] - th_b[:, None], TWO_PI)
    phi_rigid = TWO_PI * np.arange(n_rev)[:, None, None] + psi[None]
    amp = amp_pk_m if callable(amp_pk_m) else (lambda t, a=float(amp_pk_m): np.full_like(t, a))
    blade_phase = TWO_PI * nd * np.arange(n_blades)[None, :, None] / n_blades + c

    def x_and_dx(t):
        if order is not None:
            arg = order * phi_of(t) + blade_phase
            darg = order * dphi(t)
        else:
            arg = TWO_PI * freq_hz * t + blade_phase
            darg = TWO_PI * freq_hz
        h = 1e-7
        a = amp(t)
        da = (amp(t + h) - amp(t - h)) / (2 * h)
        x = a * np.sin(arg)
        dx = da * np.sin(arg) + a * darg * np.cos(arg)
        if sync is not None:
            eo, a_s, ph = sync
            sarg = eo * (phi_of(t) + th_b[None, :, None]) + ph
            if callable(a_s):
                av, dav = a_s(t), (a_s(t + h) - a_s(t - h)) / (2 * h)
            else:
                av, dav = a_s, 0.0
            x = x + av * np.sin(sarg)
            dx = dx + dav * np.sin(sarg) + av * eo * dphi(t) * np.cos(sarg)
        return x, dx

    t = time_at(phi_rigid)
    for _ in range(50):
        x, dx = x_and_dx(t)
        g = phi_of(t) + x / tip_radius_m - phi_rigid
        step = g / (dphi(t) + dx / tip_radius_m)
        t = t - step
        if np.max(np.abs(step)) < 1e-15:
            break
    if noise_s > 0:
        t = t + np.random.default_rng(seed).normal(0.0, noise_s, t.shape)
    omega = TWO_PI / np.diff(opr)
    t_mid = 0.5 * (opr[:-1] + opr[1:])
    f_rev = order * omega / TWO_PI if order is not None else np.full(n_rev, float(freq_hz))
    truth = NsvTruth(nsv_kind=np.full((n_rev, 1), "rotating_stall" if order is not None else "flutter"),
                     nsv_freq_hz=f_rev[:, None], nsv_nd=np.full((n_rev, 1), nd, np.int64),
                     nsv_amp_pkpk_m=2.0 * amp(t_mid)[:, None])
    return NsvRun(opr_s=opr[:-1], toa_s=t, omega_rad_s=omega, n_blades=n_blades,
                  probe_angles_rad=th_p, tip_radius_m=tip_radius_m, truth=truth)


def write_recording(path, run: NsvRun, *, run_id: str = "nsv-synthetic", rig: str = "rig1") -> None:
    """An MCAP recording of ``run`` as the simulator would publish it (metadata, OPR, TOAs;
    no truth), for the CLI and the viewer."""
    from bttsim_stream.bus.recording import McapRecorder
    from bttsim_stream.bus.stream import MessageStream
    from bttsim_stream.sim.core import RevolutionBatch, RunInfo

    n_rev = run.opr_s.size
    info = RunInfo(n_blades=run.n_blades, n_probes=run.probe_angles_rad.size, n_revolutions=n_rev,
                   probe_angles_rad=run.probe_angles_rad, probe_axial_m=0.01226, tip_radius_m=run.tip_radius_m,
                   opr_angle_rad=0.0, clock_hz=0.0, stagger_deg=41.5, engine_orders=(8,), nodal_diameters=(1,),
                   toa_method="HP", duration_s=float(run.opr_s[-1] + 2 * np.pi / run.omega_rad_s[-1]), seed=0,
                   rig=rig, run_id=run_id, has_truth=False)
    stream = MessageStream(run_id, rig)
    batch = RevolutionBatch(revolution=np.arange(n_rev, dtype=np.int64), opr_s=run.opr_s, toa_s=run.toa_s,
                            opr_ticks=None, toa_ticks=None, truth=None, residual_s=0.0,
                            bracketed=np.ones(run.toa_s.shape, bool))
    with McapRecorder(path) as rec:
        rec.write_message(stream.run_metadata(info))
        rec.write_all(stream.acquisition(batch, include_truth=False))

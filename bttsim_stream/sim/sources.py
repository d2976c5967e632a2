"""Excitation sources: the parts of the blade forcing that the simulator adds up.

Every source contributes *carriers* ``Im(G_b(t) exp(i theta(t)))``, ``theta = EO phi(t) +
omega t`` (:mod:`~bttsim_stream.sim.modal` conventions), of two sorts:

- forced carriers, modal forces ``C`` (n_modes, k) integrated exactly by the envelope
  recursion (engine orders, rotating stall, broadband lines);
- closed-form carriers, whose per-blade envelopes the source evaluates itself on the
  envelope grid (flutter's logistic growth).

The simulator lays the carriers out as every source's forced carriers, in source order, then
every source's closed-form ones; each source reads its own carriers back at the TOAs to write
its part of the truth. A new kind of forcing is a new class with the members of
:class:`ExcitationSource` and an entry in :data:`EXCITATION_SOURCES`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator, Protocol

import numpy as np

from .forcing import modal_forcing
from .modal import TRANSIENT_TOL_S
from .nsv import NsvSetup, build_nsv

__all__ = ["Carriers", "ExcitationSource", "EngineOrderForcing", "NonSynchronous", "EXCITATION_SOURCES",
           "excitation_sources"]

TWO_PI = 2.0 * np.pi


@dataclass(frozen=True, slots=True, eq=False)
class Carriers:
    """Carrier phases ``EO phi(t) + omega t`` and, for forced carriers, their modal forces.

    Attributes
    ----------
    eo : ndarray, shape (k,)
    omega : ndarray, shape (k,), or None
        Rotor-frame frequencies, rad/s; None: all 0 (engine orders).
    C : ndarray, shape (n_modes, k), complex, or None
        Modal forces (:func:`~bttsim_stream.sim.forcing.modal_forcing`); None for closed-form
        carriers.
    """

    eo: np.ndarray
    omega: np.ndarray | None = None
    C: np.ndarray | None = None

    @property
    def size(self) -> int:
        return self.eo.size


NO_CARRIERS = Carriers(np.zeros(0))


class ExcitationSource(Protocol):
    """What the simulator asks of a part of the forcing."""

    #: carriers of the exact envelope recursion
    forced: Carriers
    #: carriers whose envelopes :meth:`closed_envelopes` gives
    closed: Carriers

    def closed_envelopes(self, t: np.ndarray) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """Per closed-form carrier: envelope ``G`` and exact derivative at grid times ``t``
        (n,), each shape (n, n_blades, r), complex."""

    def truth(self, X: np.ndarray, omega_mean: np.ndarray, shape: tuple) -> dict:
        """This source's fields of :class:`~bttsim_stream.sim.core.Truth` from its carriers'
        ``d_eqv`` envelopes ``X`` (k_forced + k_closed, 2 [re, im], n) at the TOAs (n =
        ``prod(shape)``, shape (n_rev, n_blades, n_probes)) and the revolutions' mean speeds,
        rad/s."""

    def warnings(self, step_s: float, radius_m: float, speed) -> list[str]:
        """Warnings about the envelope grid step ``step_s`` for this source."""

    def bound_terms(self, forced_bound) -> list[tuple[np.ndarray, np.ndarray]]:
        """Upper bounds of this source's response over the run, per blade: terms ``(d_eqv 0-pk
        at P_nom, any tip node's displacement 0-pk)``, each (n_blades,), m, summed by
        :func:`~bttsim_stream.sim.bounds.tip_amplitude_bound`; ``forced_bound(C, eo, omega)``
        gives them for forced carriers."""


class EngineOrderForcing:
    """Chirps at fixed engine orders with travelling-wave phases (paper Eq. 5-7): the scenario's
    ``[[excitation]]``; truth: the pk-pk envelope ``d_eqv_pkpk_m``."""

    closed = NO_CARRIERS

    def __init__(self, model, excitations) -> None:
        C, eo = modal_forcing(model, excitations)
        self.forced = Carriers(eo, None, C)

    @classmethod
    def from_scenario(cls, scn, model, speed, modes, v_eqv) -> EngineOrderForcing:
        return cls(model, scn.excitation)

    def closed_envelopes(self, t):
        return iter(())

    def truth(self, X, omega_mean, shape) -> dict:
        """``d_eqv_pkpk_m``: largest over the revolution's arrivals of ``2 sum_m |G_eqv,m|``;
        ``eo_pkpk_m``: the same of each engine order's own response, ``2 |sum_m G_eqv,m|``
        over its excitations (one carrier ``EO phi(t)``: their envelopes add), and the orders
        ``eo_engine_order`` of its columns."""
        amp = 2.0 * np.sum(np.hypot(X[:, 0], X[:, 1]), axis=0)
        orders = np.unique(self.forced.eo)
        per_eo = np.empty((orders.size,) + amp.shape)
        for j, eo in enumerate(orders):
            rows = np.flatnonzero(self.forced.eo == eo)
            per_eo[j] = 2.0 * np.hypot(X[rows, 0].sum(axis=0), X[rows, 1].sum(axis=0))
        nr = shape[0]
        return {"d_eqv_pkpk_m": amp.reshape(shape).max(axis=2),
                "eo_pkpk_m": np.moveaxis(per_eo.reshape((orders.size,) + shape).max(axis=3), 0, -1),
                "eo_engine_order": np.broadcast_to(orders.astype(np.int64), (nr, orders.size)).copy()}

    def warnings(self, step_s, radius_m, speed) -> list[str]:
        return []

    def bound_terms(self, forced_bound) -> list:
        f = self.forced
        return [forced_bound(f.C, f.eo, f.omega)]


class NonSynchronous:
    """Rotating stall, broadband (forced carriers) and flutter (closed form): the scenario's
    non-synchronous vibration (:mod:`~bttsim_stream.sim.nsv`); truth: the ``nsv_*`` fields."""

    def __init__(self, nsv: NsvSetup, nodes: np.ndarray, v_eqv: np.ndarray) -> None:
        self.nsv = nsv
        self.nodes, self.v_eqv = nodes, v_eqv  # tip basis (r, n_tip, 3); d_eqv at P_nom (r,)
        self.forced = Carriers(nsv.eo, nsv.omega, nsv.C)
        fw = nsv.flutter
        self.closed = NO_CARRIERS if fw is None else Carriers(np.array([0.0]), np.array([fw.omega]))

    @classmethod
    def from_scenario(cls, scn, model, speed, modes, v_eqv) -> NonSynchronous | None:
        """None when the scenario has none, or the modes change with speed (refused by
        :func:`~bttsim_stream.sim.bounds.check_tip_amplitude`)."""
        if not modes.nonsynchronous:
            return None
        nsv = build_nsv(scn, model, speed, modes.basis, v_eqv)
        return None if nsv is None else cls(nsv, modes.basis.nodes, v_eqv)

    def closed_envelopes(self, t):
        if self.nsv.flutter is not None:
            yield self.nsv.flutter.envelope(t)

    def truth(self, X, omega_mean, shape) -> dict:
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

    def warnings(self, step_s, radius_m, speed) -> list[str]:
        fw = self.nsv.flutter
        if fw is None:
            return []
        err_m = fw.limit_m * fw.sigma**4 * step_s**4 / 384.0  # cubic Hermite error of the logistic envelope
        tol_m = TRANSIENT_TOL_S * radius_m * float(np.min(speed.omega))
        if err_m > 100.0 * tol_m:
            return [f"[flutter]: growth rate {fw.sigma:.3g} /s is fast for the {step_s * 1e3:g} ms envelope "
                    f"grid; TOAs may differ from the exact ones by up to {err_m / tol_m * TRANSIENT_TOL_S:.1g} s"]
        return []

    def bound_terms(self, forced_bound) -> list:
        """Stall and broadband: forced carriers. Flutter: its limit cycle, which the logistic
        growth never exceeds."""
        nsv, terms = self.nsv, []
        if nsv.eo.size:
            terms.append(forced_bound(nsv.C, nsv.eo, nsv.omega))
        if nsv.flutter is not None:
            f = nsv.flutter
            r_max = max(f.limit_m, f.seed_m)
            A = np.einsum("br,rnj->bnj", f.shape, self.nodes)  # (n_blades, n_tip, 3) complex
            terms.append((r_max * np.abs(f.shape @ self.v_eqv),
                          r_max * np.max(np.sqrt(np.sum(np.abs(A) ** 2, axis=2)), axis=1)))
        return terms


#: The kinds of forcing, in carrier order: each ``from_scenario(scn, model, speed, modes, v_eqv)``
#: gives the source, or None when the scenario has none of it.
EXCITATION_SOURCES = (EngineOrderForcing, NonSynchronous)


def excitation_sources(scn, model, speed, modes, v_eqv) -> list:
    """The scenario's excitation sources (:data:`EXCITATION_SOURCES` that it has).

    Parameters
    ----------
    modes : FixedModes or SpeedDependentModes
        The modal path (its ``basis`` and whether it takes non-synchronous forcing).
    v_eqv : ndarray, shape (r,)
        Compressed coordinates -> ``d_eqv`` at P_nom (Eq. 3-4).
    """
    found = (kind.from_scenario(scn, model, speed, modes, v_eqv) for kind in EXCITATION_SOURCES)
    return [s for s in found if s is not None]

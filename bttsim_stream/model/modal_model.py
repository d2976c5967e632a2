"""The modal model: what the simulator needs from a bladed disk, and its ``.npz`` file.

Shapes (written once): ``n_modes`` modes, ``n_blades`` blades, ``n_tip`` tip nodes.

* ``freq_hz`` (n_modes,), ``damping_ratio`` (n_modes,)
* ``tip_ref`` (n_blades, n_tip, 3): undeformed tip nodes as (radius m, angle rad, axial z m)
  in the rotor frame at t = 0; angles anticlockwise from +x, not wrapped.
* ``tip_shapes`` (n_modes, n_blades, n_tip, 3): mass-normalised mode shapes at the tip nodes
  as (radial, tangential, axial) components in each node's own polar directions, m per unit
  modal coordinate (modal coordinates in m*sqrt(kg)... i.e. ``Phi^T M Phi = I``).
* ``force_ref`` (n_blades, 3), ``force_shapes`` (n_modes, n_blades, 3): the same at the
  excitation node (leading edge) of each blade.

The file format is documented in ``schemas/modal_model.md``.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from .. import __version__
from ..defaults import MAX_BLADES, MAX_MODE_FREQ_HZ, MAX_SPEEDS
from ..errors import ModelFileError, ScenarioError, replaceable_file
from ..scenario import Scenario
from .bladed_disk import (
    BladedDiskDesign,
    WheelModes,
    assemble_full_wheel,
    assemble_sector,
    asymmetry_pattern,
    blade_alone_frequencies,
    expand_cyclic,
    solve_cyclic,
    solve_full_wheel,
)
from .bladed_disk import expand_unsorted
from .centrifugal import (MAC_REFINE, N_SPARE, centrifugal_sector, full_wheel_centrifugal, solve_cyclic_speeds,
                          solve_full_wheel_speeds, speed_grid)
from .npzfile import read_npz

__all__ = [
    "SCHEMA",
    "SCHEMA_VERSION",
    "SPEED_ARRAYS",
    "ModalModel",
    "build_model",
    "design_from_scenario",
    "mistuning_factors",
    "localisation",
    "save_model",
    "load_model",
    "model_from_cartesian",
    "label_modes",
    "to_cartesian",
]

SCHEMA = "bttsim.modal_model"
SCHEMA_VERSION = 1
#: Disk stiffness harmonics (1, 2) of the asymmetric-disk option: harmonic 2 splits the ND 1
#: pair by 0.05 Hz (paper Fig. 3: 343.89 / 343.94 Hz).
DISK_ASYMMETRY = (0.0, 0.0218)

_REQUIRED = {
    "freq_hz": 1, "damping_ratio": 1, "tip_ref": 3, "tip_shapes": 4,
    "force_ref": 2, "force_shapes": 3, "meta": 0,
}
_OPTIONAL = {
    "family": 1, "nodal_diameter": 1, "campbell_freq_hz": 2, "blade_alone_freq_hz": 1,
    "force_ref_trailing_edge": 2, "force_shapes_trailing_edge": 3,
    "stiffness_factors": 1, "mass_factors": 1,
    # speed-dependent modes (centrifugal effects): see SPEED_ARRAYS
    "speed_rad_s": 1, "freq_hz_at_speed": 2, "tip_shapes_at_speed": 5, "force_shapes_at_speed": 4,
    "force_shapes_trailing_edge_at_speed": 4, "campbell_freq_hz_at_speed": 3,
}
#: Arrays of a speed-dependent model (all or none of the first four): the modes at speeds
#: ``speed_rad_s`` (S,), strictly ascending from 0, S in [2, 64]; row ``s`` of each
#: ``*_at_speed`` array holds the same quantity as its zero-speed array at speed ``s``
#: (row 0 equal to it), in the same mode order (modes tracked across speeds), each mode
#: mass-normalised and sign/phase-aligned with its zero-speed shape.
SPEED_ARRAYS = ("speed_rad_s", "freq_hz_at_speed", "tip_shapes_at_speed", "force_shapes_at_speed")


@dataclass(frozen=True, slots=True, eq=False)
class ModalModel:
    """Mass-normalised modal model of a bladed disk at the BTT-relevant points.

    Attributes
    ----------
    freq_hz, damping_ratio : ndarray, shape (n_modes,)
    tip_ref : ndarray, shape (n_blades, n_tip, 3)
    tip_shapes : ndarray, shape (n_modes, n_blades, n_tip, 3)
    force_ref : ndarray, shape (n_blades, 3)
    force_shapes : ndarray, shape (n_modes, n_blades, 3)
    meta : dict
        Schema, ``n_blades``, ``nominal_node`` (0-based tip node index of P_nom),
        ``stagger_deg``, ``damping_beta_s``, ``provenance``...
    family, nodal_diameter : ndarray of int, shape (n_modes,), optional
        Mode family (0-based) and dominant nodal diameter of each mode.
    campbell_freq_hz : ndarray, shape (n_families, n_nd), optional
        Family frequencies per nodal diameter of the tuned wheel (zero speed).
    blade_alone_freq_hz : ndarray, optional
        Natural frequencies of the clamped blade.
    extra : dict of ndarray
        Other optional arrays (trailing-edge force node, mistuning factors).
    """

    freq_hz: np.ndarray
    damping_ratio: np.ndarray
    tip_ref: np.ndarray
    tip_shapes: np.ndarray
    force_ref: np.ndarray
    force_shapes: np.ndarray
    meta: dict
    family: np.ndarray | None = None
    nodal_diameter: np.ndarray | None = None
    campbell_freq_hz: np.ndarray | None = None
    blade_alone_freq_hz: np.ndarray | None = None
    extra: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        _validate(self.as_arrays(), "model")

    @property
    def n_modes(self) -> int:
        return int(self.freq_hz.shape[0])

    @property
    def n_blades(self) -> int:
        return int(self.tip_ref.shape[0])

    @property
    def n_tip(self) -> int:
        return int(self.tip_ref.shape[1])

    @property
    def nominal_node(self) -> int:
        return int(self.meta["nominal_node"])

    def as_arrays(self) -> dict:
        out = {
            "freq_hz": self.freq_hz, "damping_ratio": self.damping_ratio,
            "tip_ref": self.tip_ref, "tip_shapes": self.tip_shapes,
            "force_ref": self.force_ref, "force_shapes": self.force_shapes,
            "meta": np.array(json.dumps(self.meta, sort_keys=True)),
        }
        for name in ("family", "nodal_diameter", "campbell_freq_hz", "blade_alone_freq_hz"):
            if getattr(self, name) is not None:
                out[name] = getattr(self, name)
        out.update(self.extra)
        return out


def design_from_scenario(scn) -> BladedDiskDesign:
    """The built-in design with the scenario's rotor geometry and model options."""
    r, m = scn.rotor, scn.model
    return replace(
        BladedDiskDesign(),
        n_blades=r.n_blades, tip_radius_m=r.tip_radius_m,
        stagger_rad=float(np.deg2rad(r.stagger_deg)), tip_chord_m=r.tip_chord_m,
        n_tip_nodes=r.n_tip_nodes, tip_node_spacing_m=r.tip_node_spacing_m,
        nominal_node=r.nominal_node - 1, n_families=m.n_families,
        asymmetry=DISK_ASYMMETRY if m.disk_asymmetry else (0.0, 0.0),
    )


def mistuning_factors(scn) -> tuple[np.ndarray, np.ndarray]:
    """Per-blade (stiffness, mass) factors: explicit lists times seeded random ``1 + N(0, std)``."""
    m, n = scn.model, scn.rotor.n_blades
    rng = np.random.default_rng(np.random.SeedSequence([scn.run.seed, 0x6D69737475]))
    k = np.asarray(m.stiffness_factors, float) if len(m.stiffness_factors) else np.ones(n)
    ms = np.asarray(m.mass_factors, float) if len(m.mass_factors) else np.ones(n)
    k = k * (1.0 + m.stiffness_std * rng.standard_normal(n))
    ms = ms * (1.0 + m.mass_std * rng.standard_normal(n))
    if np.any(k <= 0) or np.any(ms <= 0):
        raise ModelFileError("mistuning: a random stiffness or mass factor came out <= 0; "
                             "reduce stiffness_std / mass_std")
    return k, ms


def label_modes(freq_hz: np.ndarray, tip_shapes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Family (frequency rank // n_blades) and dominant ND of modes that come unlabelled.

    The nodal diameter is the spatial DFT harmonic (k and N-k folded) that holds most of the
    tip-node motion across the blades.

    Parameters
    ----------
    freq_hz : ndarray, shape (n_modes,)
    tip_shapes : ndarray, shape (n_modes, n_blades, n_tip, 3)
    """
    n_modes, n_blades = tip_shapes.shape[:2]
    rank = np.empty(n_modes, np.int64)
    rank[np.argsort(freq_hz, kind="stable")] = np.arange(n_modes)
    F = np.fft.fft(tip_shapes.reshape(n_modes, n_blades, -1), axis=1)
    e = np.sum(np.abs(F) ** 2, axis=2)
    k = np.arange(n_blades)
    folded = np.zeros((n_modes, n_blades // 2 + 1))
    np.add.at(folded, (slice(None), np.minimum(k, n_blades - k)), e)
    return rank // n_blades, np.argmax(folded, axis=1).astype(np.int64)


def localisation(model: ModalModel, family: int = 0) -> np.ndarray:
    """Localisation of each mode of a family: ``N * sum_b p_b^2`` (inverse participation ratio).

    ``p_b`` is blade ``b``'s share of the tip-node displacement energy. 1 means every blade
    moves equally (a travelling-wave combination), 1.5 a tuned standing wave
    (``cos^2`` over the blades), ``N`` a mode confined to one blade.
    """
    fam = model.family if model.family is not None else label_modes(model.freq_hz, model.tip_shapes)[0]
    e = np.sum(model.tip_shapes[fam == family] ** 2, axis=(2, 3))
    p = e / np.sum(e, axis=1, keepdims=True)
    return model.n_blades * np.sum(p**2, axis=1)


def _sector_points(sector, shapes: np.ndarray, maps: np.ndarray) -> np.ndarray:
    """(n_modes, n_blades, m) x (n_pts, 3, m) -> (n_modes, n_blades, n_pts, 3)."""
    return np.einsum("kbm,pcm->kbpc", shapes, maps, optimize=True)


def _rotor_ref(ref: np.ndarray, n_blades: int) -> np.ndarray:
    """Sector-frame (r, angle, z) points -> every blade's (r, angle, z) in the rotor frame."""
    out = np.repeat(ref[None], n_blades, axis=0).astype(float)
    out[..., 1] += (2.0 * np.pi * np.arange(n_blades) / n_blades).reshape((-1,) + (1,) * (ref.ndim - 1))
    return out


def _checked_speeds(speed_rad_s) -> np.ndarray:
    """The speeds of a speed-dependent model, rad/s: 2..MAX_SPEEDS, finite, ascending from 0."""
    speed_rad_s = np.asarray(speed_rad_s, float)
    if (speed_rad_s.ndim != 1 or not 2 <= speed_rad_s.size <= MAX_SPEEDS or speed_rad_s[0] != 0.0
            or np.any(np.diff(speed_rad_s) <= 0) or not np.all(np.isfinite(speed_rad_s))):
        raise ScenarioError(f"centrifugal speeds must be 2..{MAX_SPEEDS} finite speeds ascending from 0 rad/s")
    return speed_rad_s


def _model_meta(design: BladedDiskDesign, damping_beta_s: float, method: str, build_time: float) -> dict:
    """The model file's metadata: schema, geometry, units, frames and provenance."""
    meta = {
        "schema": SCHEMA,
        "schema_version": SCHEMA_VERSION,
        "n_blades": design.n_blades,
        "n_tip_nodes": design.n_tip_nodes,
        "nominal_node": design.nominal_node,
        "stagger_deg": float(np.rad2deg(design.stagger_rad)),
        "tip_radius_m": design.tip_radius_m,
        "damping_beta_s": float(damping_beta_s),
        "units": "SI: Hz, m, rad; shapes in m per unit mass-normalised modal coordinate",
        "frames": ("ref: (radius, angle anticlockwise from +x, z) at t=0; "
                   "shapes: (radial, tangential, axial) at each node"),
        "force_node": "leading_edge",
        "provenance": {
            "builder": f"bttsim_stream {__version__} parametric bladed disk",
            "method": method,
            "design": {k: (list(v) if isinstance(v, tuple) else v)
                       for k, v in ((f, getattr(design, f)) for f in design.__dataclass_fields__)},
            "build_time_s": build_time,
        },
    }
    return meta


def build_model(scn=None, design: BladedDiskDesign | None = None, damping_beta_s: float | None = None,
                stiffness_factors=None, mass_factors=None, speed_rad_s=None) -> ModalModel:
    """Build the parametric bladed-disk modal model.

    Tuned wheels (uniform blade factors, no disk asymmetry) are solved per nodal diameter
    with cyclic symmetry and expanded (``n_families`` per ND: ND 0 single, the others pairs);
    mistuned or asymmetric wheels are solved exactly as a full wheel (lowest
    ``n_families * n_blades`` modes).

    Parameters
    ----------
    scn : Scenario, optional
        Takes the rotor geometry, model options, damping and mistuning from it.
    design : BladedDiskDesign, optional
        Overrides the design derived from ``scn``.
    damping_beta_s : float, optional
        Stiffness-proportional damping coefficient (``zeta = beta * omega / 2``).
    stiffness_factors, mass_factors : array_like, shape (n_blades,), optional
        Per-blade mistuning factors (override the scenario's).
    speed_rad_s : array_like, shape (S,), optional
        Build a speed-dependent model (centrifugal effects, :mod:`.centrifugal`) with the modes
        at these speeds (ascending from 0; a mistuned or asymmetric wheel is solved as a full
        wheel). Default: the scenario's ``[model] centrifugal`` option (``centrifugal_speeds``
        speeds uniform in Omega from 0 to
        :meth:`~bttsim_stream.scenario.Scenario.centrifugal_max_rpm`), else none.
    """
    t0 = time.perf_counter()
    if design is None:
        if scn is None:
            scn = Scenario()
        design = design_from_scenario(scn)
    if design.span_m < 0.1 * design.rim_radius_m:
        raise ScenarioError(f"[rotor] tip_radius_m = {design.tip_radius_m:g} m: the built-in model's blades start "
                            f"at its rim ({design.rim_radius_m:g} m), so the tip radius must be at least "
                            f"{1.1 * design.rim_radius_m:.4g} m")
    if damping_beta_s is None:
        damping_beta_s = scn.model.damping_beta_s if scn is not None else 9e-6
    N = design.n_blades
    if stiffness_factors is None and mass_factors is None and scn is not None:
        stiffness_factors, mass_factors = mistuning_factors(scn)
    k_f = np.ones(N) if stiffness_factors is None else np.asarray(stiffness_factors, float)
    m_f = np.ones(N) if mass_factors is None else np.asarray(mass_factors, float)
    disk_f = asymmetry_pattern(design)
    if speed_rad_s is None and scn is not None and scn.model.centrifugal:
        speed_rad_s = speed_grid(scn.centrifugal_max_rpm() * np.pi / 30.0, scn.model.centrifugal_speeds)
    if speed_rad_s is not None:
        speed_rad_s = _checked_speeds(speed_rad_s)

    with threadpool_limits(limits=1):
        nominal = assemble_sector(design)
        campbell = solve_cyclic(design, nominal)
        blade_alone = blade_alone_frequencies(design, 3)
        uniform = (np.ptp(k_f) == 0 and np.ptp(m_f) == 0 and np.ptp(disk_f) == 0)
        if uniform:
            sector = assemble_sector(design, k_f[0], m_f[0], disk_f[0])
            sol = campbell if (k_f[0] == 1 and m_f[0] == 1 and disk_f[0] == 1) else solve_cyclic(design, sector)
            modes: WheelModes = expand_cyclic(design, sol)
            method = "cyclic symmetry, expanded to the full wheel"
            if speed_rad_s is not None:
                at_speed = _speed_modes(design, nominal, campbell, sector, sol, speed_rad_s)
                method += "; centrifugal stiffening and spin softening at speed (Coriolis neglected)"
        else:
            modes, _ = solve_full_wheel(design, design.n_families * N, k_f, m_f, disk_f)
            sector = nominal
            method = "full wheel (mistuned / asymmetric), shift-invert Lanczos + Rayleigh-Ritz"
            if speed_rad_s is not None:
                at_speed = _speed_modes_full(design, nominal, campbell, modes, k_f, m_f, disk_f, speed_rad_s)
                method += "; centrifugal stiffening and spin softening at speed (Coriolis neglected)"

    tip = _sector_points(sector, modes.shapes, sector.tip_map)
    force = _sector_points(sector, modes.shapes, sector.force_map)
    omega = 2.0 * np.pi * modes.freq_hz
    build_time = time.perf_counter() - t0
    meta = _model_meta(design, damping_beta_s, method, build_time)
    model = ModalModel(
        freq_hz=modes.freq_hz, damping_ratio=0.5 * damping_beta_s * omega,
        tip_ref=_rotor_ref(sector.tip_ref, N), tip_shapes=tip[..., :, :],
        force_ref=_rotor_ref(sector.force_ref[0], N), force_shapes=force[:, :, 0, :],
        meta=meta, family=modes.family.astype(np.int64),
        nodal_diameter=modes.nodal_diameter.astype(np.int64),
        campbell_freq_hz=campbell.freq_hz.T.copy(), blade_alone_freq_hz=blade_alone,
        extra={"force_ref_trailing_edge": _rotor_ref(sector.force_ref[1], N),
               "force_shapes_trailing_edge": force[:, :, 1, :].copy(),
               "stiffness_factors": k_f, "mass_factors": m_f},
    )
    if speed_rad_s is None:
        return model
    meta["provenance"]["centrifugal"] = at_speed.pop("provenance")
    meta["provenance"]["build_time_s"] = time.perf_counter() - t0
    tip_s, force_s = at_speed.pop("tip"), at_speed.pop("force")
    arrays = {
        "speed_rad_s": speed_rad_s,
        "freq_hz_at_speed": at_speed["freq_hz"],
        "tip_shapes_at_speed": tip_s,
        "force_shapes_at_speed": force_s[..., 0, :],
        "force_shapes_trailing_edge_at_speed": force_s[..., 1, :],
        "campbell_freq_hz_at_speed": at_speed["campbell"],
    }
    # row 0 is the zero-speed model itself (the same solve; copied so that it is bit-identical)
    for key, zero in (("freq_hz_at_speed", model.freq_hz), ("tip_shapes_at_speed", model.tip_shapes),
                      ("force_shapes_at_speed", model.force_shapes),
                      ("force_shapes_trailing_edge_at_speed", model.extra["force_shapes_trailing_edge"]),
                      ("campbell_freq_hz_at_speed", model.campbell_freq_hz)):
        arrays[key] = np.ascontiguousarray(arrays[key])
        arrays[key][0] = zero
    return replace(model, meta=meta, extra={**model.extra, **arrays})


def _speed_modes_full(design: BladedDiskDesign, nominal, campbell, modes: WheelModes, k_f, m_f, disk_f,
                      speed_rad_s: np.ndarray) -> dict:
    """:func:`_speed_modes` for a mistuned or asymmetric wheel: the full wheel's prestress and
    modes at speed (:func:`~.centrifugal.solve_full_wheel_speeds`)."""
    t0 = time.perf_counter()
    K, M, sectors = assemble_full_wheel(design, k_f, m_f, disk_f)
    G, _ = full_wheel_centrifugal(sectors, K)
    N, m = design.n_blades, sectors[0].n_dof
    zero = modes.shapes.reshape(modes.shapes.shape[0], -1).T
    freq, shapes, min_mac = solve_full_wheel_speeds(K, M, G, zero, speed_rad_s)
    freq[0] = modes.freq_hz
    tip, force = [], []
    for V in shapes:
        sh = V.T.reshape(-1, N, m)
        tip.append(_sector_points(nominal, sh, nominal.tip_map))
        force.append(_sector_points(nominal, sh, nominal.force_map))
    camp_track = solve_cyclic_speeds(design, nominal, centrifugal_sector(nominal, N), speed_rad_s, campbell)
    camp = np.array([c.freq_hz.T for c in camp_track.solutions])
    prov = {
        "model": "K(Omega) = K_e + Omega^2 (K_g - K_s): linear centrifugal prestress (static solve of the full "
                 "mistuned wheel at 1 rad/s), beam geometric stiffness of the element axial and ring hoop forces, "
                 "spin softening (in-plane consistent mass); Coriolis and the sections' propeller moment neglected",
        "speeds_rad_s": [float(v) for v in speed_rad_s],
        "tracking": f"full wheel: Ritz basis of the zero-speed modes and their static corrections K^-1 G Phi_0, "
                    f"mass-weighted MAC (an interval matched below {MAC_REFINE} is halved in Omega^2); phase-aligned",
        "tracking_min_mac": min_mac,
        "campbell": "the nominal (tuned) wheel's, tracked",
        "build_time_s": time.perf_counter() - t0,
    }
    return {"freq_hz": np.array(freq), "tip": np.array(tip), "force": np.array(force), "campbell": camp,
            "provenance": prov}


def _speed_modes(design: BladedDiskDesign, nominal, campbell, sector, sol, speed_rad_s: np.ndarray) -> dict:
    """The tracked modes at ``speed_rad_s`` (:mod:`.centrifugal`), at the tip and force nodes.

    Returns ``freq_hz`` (S, n_modes), ``tip`` (S, n_modes, n_blades, n_tip, 3), ``force``
    (S, n_modes, n_blades, 2, 3), ``campbell`` (S, n_families, n_nd) and ``provenance``.
    """
    t0 = time.perf_counter()
    cent = centrifugal_sector(sector, design.n_blades)
    track = solve_cyclic_speeds(design, sector, cent, speed_rad_s, sol)
    freqs, _, fam, nds = expand_unsorted(design, sol)
    order = np.lexsort((nds, freqs, fam))  # the zero-speed model's mode order, kept at every speed
    S = speed_rad_s.size
    tip, force, freq = [], [], []
    for s in range(S):
        modes = expand_cyclic(design, track.solutions[s], order=order, fix_phase=False)
        tip.append(_sector_points(sector, modes.shapes, sector.tip_map))
        force.append(_sector_points(sector, modes.shapes, sector.force_map))
        freq.append(modes.freq_hz)
    if sol is campbell:
        camp_track = track
    else:  # the Campbell table is the nominal wheel's (as at zero speed)
        camp_track = solve_cyclic_speeds(design, nominal, centrifugal_sector(nominal, design.n_blades),
                                         speed_rad_s, campbell)
    camp = np.array([c.freq_hz.T for c in camp_track.solutions])
    w = 2.0 * np.pi * np.asarray(campbell.freq_hz.T)
    southwell = (np.square(2.0 * np.pi * camp[-1]) - w**2) / speed_rad_s[-1] ** 2
    prov = {
        "model": "K(Omega) = K_e + Omega^2 (K_g - K_s): linear centrifugal prestress (ND 0 static solve at "
                 "1 rad/s), beam geometric stiffness of the element axial and ring hoop forces, spin softening "
                 "(in-plane consistent mass); Coriolis and the sections' propeller moment neglected",
        "speeds_rad_s": [float(v) for v in speed_rad_s],
        "tracking": f"mass-weighted MAC assignment over {N_SPARE} spare modes (an interval matched below "
                    f"{MAC_REFINE} is halved in Omega^2); phase-aligned (v_prev^H M v > 0)",
        "tracking_min_mac": track.min_mac,
        "southwell_family1_nd0_nd_max": [float(southwell[0, 0]), float(southwell[0, -1])],
        "root_force_n_at_1_rad_s": float(cent.axial_force_n[design.n_disk_elements]),
        "build_time_s": time.perf_counter() - t0,
    }
    return {"freq_hz": np.array(freq), "tip": np.array(tip), "force": np.array(force), "campbell": camp,
            "provenance": prov}


def to_cartesian(ref: np.ndarray, shapes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(r, angle, z) points and (radial, tangential, axial) shapes -> rotor-frame x, y, z.

    Parameters
    ----------
    ref : ndarray, shape (..., 3)
    shapes : ndarray, shape (n_modes, ..., 3)
    """
    r, ang, z = np.moveaxis(ref, -1, 0)
    c, s = np.cos(ang), np.sin(ang)
    xyz = np.stack([r * c, r * s, z], axis=-1)
    ur, ut, uz = np.moveaxis(shapes, -1, 0)
    uxyz = np.stack([ur * c - ut * s, ur * s + ut * c, uz], axis=-1)
    return xyz, uxyz


def to_polar(xyz: np.ndarray, uxyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    x, y, z = np.moveaxis(xyz, -1, 0)
    ang = np.unwrap(np.arctan2(y, x), axis=0) if xyz.ndim > 1 else np.arctan2(y, x)
    c, s = np.cos(ang), np.sin(ang)
    ref = np.stack([np.hypot(x, y), ang, z], axis=-1)
    ux, uy, uz = np.moveaxis(uxyz, -1, 0)
    return ref, np.stack([ux * c + uy * s, -ux * s + uy * c, uz], axis=-1)


def model_from_cartesian(freq_hz, tip_xyz, tip_shapes_xyz, force_xyz, force_shapes_xyz, *,
                         nominal_node: int, stagger_deg: float, damping_ratio=None,
                         damping_beta_s: float | None = None, provenance: dict | None = None,
                         family=None, nodal_diameter=None) -> ModalModel:
    """A model from an FE package's export in rotor-frame Cartesian coordinates.

    Parameters
    ----------
    freq_hz : array_like, shape (n_modes,)
        Natural frequencies, Hz.
    tip_xyz : array_like, shape (n_blades, n_tip, 3)
        Undeformed tip node positions (x, y, z), m, at t = 0; rotation anticlockwise about +z;
        tip nodes ordered from the trailing edge; blade b near angle 2*pi*b/n_blades.
    tip_shapes_xyz : array_like, shape (n_modes, n_blades, n_tip, 3)
        Mass-normalised mode shapes (UX, UY, UZ) at the tip nodes.
    force_xyz, force_shapes_xyz : array_like, shapes (n_blades, 3), (n_modes, n_blades, 3)
        The same at the excitation node of each blade.
    nominal_node : int
        0-based index of P_nom among the tip nodes.
    stagger_deg : float
        Tip stagger (angle of the tip chord from the tangential direction).
    damping_ratio : array_like, optional
        Modal damping ratios; or give ``damping_beta_s`` for stiffness-proportional damping.
    """
    freq = np.asarray(freq_hz, float)
    if damping_ratio is None:
        beta = 9e-6 if damping_beta_s is None else float(damping_beta_s)
        damping_ratio = 0.5 * beta * 2.0 * np.pi * freq
    tip_ref, tip_shapes = to_polar(np.asarray(tip_xyz, float), np.asarray(tip_shapes_xyz, float))
    force_ref, force_shapes = to_polar(np.asarray(force_xyz, float), np.asarray(force_shapes_xyz, float))
    n_blades, n_tip = tip_ref.shape[:2]
    if family is None or nodal_diameter is None:
        fam, nd = label_modes(freq, tip_shapes)
        family = fam if family is None else family
        nodal_diameter = nd if nodal_diameter is None else nodal_diameter
    meta = {
        "schema": SCHEMA, "schema_version": SCHEMA_VERSION, "n_blades": int(n_blades),
        "n_tip_nodes": int(n_tip), "nominal_node": int(nominal_node), "stagger_deg": float(stagger_deg),
        "tip_radius_m": float(np.mean(tip_ref[:, nominal_node, 0])),
        "damping_beta_s": damping_beta_s, "force_node": "leading_edge",
        "provenance": provenance or {"builder": "user FE export"},
    }
    return ModalModel(freq_hz=freq, damping_ratio=np.asarray(damping_ratio, float), tip_ref=tip_ref,
                      tip_shapes=tip_shapes, force_ref=force_ref, force_shapes=force_shapes, meta=meta,
                      family=None if family is None else np.asarray(family, np.int64),
                      nodal_diameter=None if nodal_diameter is None else np.asarray(nodal_diameter, np.int64))


def save_model(model: ModalModel, path) -> None:
    """Write the model as an uncompressed ``.npz`` (no pickled objects)."""
    path = replaceable_file(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".part")
        with open(tmp, "wb") as fh:
            np.savez(fh, **model.as_arrays())
        tmp.replace(path)
    except OSError as exc:
        raise ModelFileError(f"{path}: cannot write: {exc.strerror or exc}") from None


def load_model(path) -> ModalModel:
    """Load and validate a model file (``allow_pickle=False``); errors are one line."""
    path = Path(path)
    arrays = read_npz(path, "model file")
    meta = _validate(arrays, str(path))
    known = {"freq_hz", "damping_ratio", "tip_ref", "tip_shapes", "force_ref", "force_shapes", "meta",
             "family", "nodal_diameter", "campbell_freq_hz", "blade_alone_freq_hz"}
    return ModalModel(
        freq_hz=arrays["freq_hz"], damping_ratio=arrays["damping_ratio"],
        tip_ref=arrays["tip_ref"], tip_shapes=arrays["tip_shapes"],
        force_ref=arrays["force_ref"], force_shapes=arrays["force_shapes"], meta=meta,
        family=arrays.get("family"), nodal_diameter=arrays.get("nodal_diameter"),
        campbell_freq_hz=arrays.get("campbell_freq_hz"),
        blade_alone_freq_hz=arrays.get("blade_alone_freq_hz"),
        extra={k: v for k, v in arrays.items() if k not in known},
    )


def _validate(a: dict, where: str) -> dict:
    """Check keys, dtypes, shapes, finiteness and the schema; return the parsed meta."""
    missing = [k for k in _REQUIRED if k not in a]
    if missing:
        raise ModelFileError(f"{where}: missing array(s) {', '.join(missing)}")
    unknown = [k for k in a if k not in _REQUIRED and k not in _OPTIONAL]
    if unknown:
        raise ModelFileError(f"{where}: unknown array(s) {', '.join(sorted(unknown))}")
    for k, v in a.items():
        ndim = _REQUIRED.get(k, _OPTIONAL.get(k))
        v = np.asarray(v)
        if k == "meta":
            if v.ndim != 0 or v.dtype.kind != "U":
                raise ModelFileError(f"{where}: meta must be a JSON string")
            continue
        if v.ndim != ndim:
            raise ModelFileError(f"{where}: {k} must have {ndim} dimension(s), has {v.ndim}")
        if k in ("family", "nodal_diameter"):
            if v.dtype.kind not in "iu":
                raise ModelFileError(f"{where}: {k} must be integers, got {v.dtype}")
        elif v.dtype.kind != "f" or v.dtype.itemsize not in (4, 8):
            raise ModelFileError(f"{where}: {k} must be floating point (float32 or float64), got {v.dtype}")
        if not np.all(np.isfinite(v)):
            raise ModelFileError(f"{where}: {k} holds non-finite values")
    try:
        meta = json.loads(str(a["meta"]))
    except json.JSONDecodeError as exc:
        raise ModelFileError(f"{where}: meta is not valid JSON ({exc.msg})") from None
    if not isinstance(meta, dict):
        raise ModelFileError(f"{where}: meta must be a JSON object")
    if meta.get("schema") != SCHEMA:
        raise ModelFileError(f"{where}: meta.schema must be {SCHEMA!r}, got {meta.get('schema')!r}")
    if meta.get("schema_version") != SCHEMA_VERSION:
        raise ModelFileError(f"{where}: unsupported schema_version {meta.get('schema_version')!r} "
                             f"(this version reads {SCHEMA_VERSION})")
    for key in ("n_blades", "nominal_node", "stagger_deg"):
        if key not in meta:
            raise ModelFileError(f"{where}: meta.{key} is missing")
    n_modes = a["freq_hz"].shape[0]
    n_blades, n_tip = a["tip_ref"].shape[:2]
    expect = {
        "damping_ratio": (n_modes,), "tip_ref": (n_blades, n_tip, 3),
        "tip_shapes": (n_modes, n_blades, n_tip, 3), "force_ref": (n_blades, 3),
        "force_shapes": (n_modes, n_blades, 3), "family": (n_modes,), "nodal_diameter": (n_modes,),
        "force_ref_trailing_edge": (n_blades, 3), "force_shapes_trailing_edge": (n_modes, n_blades, 3),
        "stiffness_factors": (n_blades,), "mass_factors": (n_blades,),
    }
    if any(k in a for k in _OPTIONAL if k.endswith("_at_speed") or k == "speed_rad_s"):
        missing = [k for k in SPEED_ARRAYS if k not in a]
        if missing:
            raise ModelFileError(f"{where}: a speed-dependent model needs {', '.join(SPEED_ARRAYS)}; "
                                 f"missing {', '.join(missing)}")
        sp = np.asarray(a["speed_rad_s"], float)
        S = sp.shape[0]
        if not 2 <= S <= MAX_SPEEDS or sp[0] != 0.0 or np.any(np.diff(sp) <= 0):
            raise ModelFileError(f"{where}: speed_rad_s must hold 2..{MAX_SPEEDS} speeds, strictly ascending "
                                 "from 0")
        expect.update({
            "freq_hz_at_speed": (S, n_modes), "tip_shapes_at_speed": (S, n_modes, n_blades, n_tip, 3),
            "force_shapes_at_speed": (S, n_modes, n_blades, 3),
            "force_shapes_trailing_edge_at_speed": (S, n_modes, n_blades, 3),
        })
        if "campbell_freq_hz_at_speed" in a and (a["campbell_freq_hz_at_speed"].shape[0] != S
                                                 or "campbell_freq_hz" not in a
                                                 or a["campbell_freq_hz_at_speed"].shape[1:]
                                                 != a["campbell_freq_hz"].shape):
            raise ModelFileError(f"{where}: campbell_freq_hz_at_speed must have shape (S, *campbell_freq_hz.shape)")
        if ("force_shapes_trailing_edge_at_speed" in a) != ("force_shapes_trailing_edge" in a):
            raise ModelFileError(f"{where}: force_shapes_trailing_edge and its _at_speed array go together")
    for k, shape in expect.items():
        if k in a and tuple(a[k].shape) != shape:
            raise ModelFileError(f"{where}: {k} has shape {tuple(a[k].shape)}, expected {shape}")
    if n_modes < 1 or n_blades < 1 or n_tip < 2:
        raise ModelFileError(f"{where}: needs at least 1 mode, 1 blade and 2 tip nodes")
    if n_blades > MAX_BLADES:
        raise ModelFileError(f"{where}: {n_blades} blades, more than the {MAX_BLADES} of a run")
    if meta["n_blades"] != n_blades:
        raise ModelFileError(f"{where}: meta.n_blades = {meta['n_blades']} but tip_ref has {n_blades} blades")
    if not (isinstance(meta["nominal_node"], int) and 0 <= meta["nominal_node"] < n_tip):
        raise ModelFileError(f"{where}: meta.nominal_node must be an index 0..{n_tip - 1}")
    stagger = meta["stagger_deg"]
    if isinstance(stagger, bool) or not isinstance(stagger, (int, float)) or not 0.0 < float(stagger) < 90.0:
        raise ModelFileError(f"{where}: meta.stagger_deg must be a number in (0, 90)")
    if not isinstance(meta.get("provenance", {}), dict):
        raise ModelFileError(f"{where}: meta.provenance must be a JSON object")
    if "blade_alone_freq_hz" in a and (a["blade_alone_freq_hz"].size == 0 or np.any(a["blade_alone_freq_hz"] <= 0)):
        raise ModelFileError(f"{where}: blade_alone_freq_hz must hold at least one frequency, all > 0")
    if "nodal_diameter" in a and np.any((a["nodal_diameter"] < 0) | (a["nodal_diameter"] > n_blades // 2)):
        raise ModelFileError(f"{where}: nodal_diameter must lie in [0, n_blades // 2 = {n_blades // 2}]")
    if "family" in a and np.any((a["family"] < 0) | (a["family"] >= n_modes)):
        raise ModelFileError(f"{where}: family must lie in [0, n_modes)")
    if "campbell_freq_hz" in a and (a["campbell_freq_hz"].shape[1] != n_blades // 2 + 1
                                     or not 1 <= a["campbell_freq_hz"].shape[0] <= 64
                                     or np.any(a["campbell_freq_hz"] <= 0)):
        raise ModelFileError(f"{where}: campbell_freq_hz must have shape (n_families <= 64, {n_blades // 2 + 1}), "
                             "frequencies > 0")
    for k in ("freq_hz", "freq_hz_at_speed"):
        if k in a and not np.all((a[k] > 0) & (a[k] <= MAX_MODE_FREQ_HZ)):
            raise ModelFileError(f"{where}: {k} must be in (0, {MAX_MODE_FREQ_HZ:g}] Hz")
    if "speed_rad_s" in a:
        for k in ("freq_hz", "tip_shapes", "force_shapes", "force_shapes_trailing_edge", "campbell_freq_hz"):
            if k + "_at_speed" in a and not np.array_equal(a[k + "_at_speed"][0], a[k]):
                raise ModelFileError(f"{where}: row 0 of {k}_at_speed (speed 0) differs from {k}")
    for k in ("stiffness_factors", "mass_factors"):
        if k in a and np.any(a[k] <= 0):
            raise ModelFileError(f"{where}: {k} must be > 0 (a blade's factor on the tuned blade), got "
                                 f"{float(a[k].min()):g}")
    if np.any(a["damping_ratio"] < 0) or np.any(a["damping_ratio"] >= 1):
        raise ModelFileError(f"{where}: damping_ratio must be in [0, 1)")
    if np.any(a["tip_ref"][..., 0] <= 0) or np.any(a["force_ref"][..., 0] <= 0):
        raise ModelFileError(f"{where}: reference radii must be > 0")
    return meta

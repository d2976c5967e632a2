"""Human-readable views of a modal model: the family / nodal-diameter table, Fig. 3's plot and
the Campbell diagram (family frequencies against speed, engine-order lines, their crossings).

Campbell conventions: engine order ``EO`` excites the nodal diameter ``EO mod N`` folded to
``0 .. N // 2`` (``k`` and ``N - k`` are one ND); its line is ``f = EO * rpm / 60``. A crossing is
where that line meets a family's frequency at the excited ND. A speed-dependent model
(``speed_rad_s`` and the ``*_at_speed`` arrays) gives the families at its sampled speeds; a
zero-speed model gives flat lines.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._plotting import pyplot
from ..errors import BttsimError
from .modal_model import ModalModel, label_modes, localisation

__all__ = ["family_table", "plot_family_frequencies", "Crossing", "campbell_data", "campbell_crossings",
           "campbell_table", "excited_nodal_diameter", "DEFAULT_ENGINE_ORDERS", "ZERO_SPEED_TOP_RPM"]

#: Engine orders listed and drawn by default (as the run's Campbell view).
DEFAULT_ENGINE_ORDERS = tuple(range(1, 13))
#: Right edge of a zero-speed model's Campbell diagram, rpm (the paper's run-up ends at 4000).
ZERO_SPEED_TOP_RPM = 5000.0


def _labels(model: ModalModel) -> tuple[np.ndarray, np.ndarray]:
    if model.family is not None and model.nodal_diameter is not None:
        return model.family, model.nodal_diameter
    return label_modes(model.freq_hz, model.tip_shapes)


def family_table(model: ModalModel) -> str:
    """Text table: every family's modes by nodal diameter, blade-alone modes, localisation."""
    fam, nd = _labels(model)
    m = model.meta
    prov = m.get("provenance", {})
    lines = [
        f"modal model: {model.n_modes} modes, {model.n_blades} blades, {model.n_tip} tip nodes "
        f"(P_nom = node {model.nominal_node + 1} from the TE), stagger {m['stagger_deg']:.2f} deg",
        f"source: {prov.get('builder', 'user file')}; {prov.get('method', '')}".rstrip("; "),
    ]
    if model.blade_alone_freq_hz is not None:
        lines.append("blade alone (clamped root): " +
                     ", ".join(f"{f:.2f} Hz" for f in model.blade_alone_freq_hz))
    lines.append(f"damping: zeta {model.damping_ratio.min():.4g} .. {model.damping_ratio.max():.4g}")
    n_nd = int(nd.max()) + 1
    fams = np.unique(fam)
    header = "  ND " + "".join(f"  family {f + 1:<2d} (Hz)      " for f in fams)
    lines += ["", header]
    for n in range(n_nd):
        row = f"  {n:2d} "
        for f in fams:
            sel = np.sort(model.freq_hz[(fam == f) & (nd == n)])
            cell = " / ".join(f"{x:.2f}" for x in sel[:2]) + (" ..." if len(sel) > 2 else "")
            row += f"  {cell:<24s}"
        lines.append(row)
    if 0 in fams:
        loc = localisation(model, 0)
        lines += ["", f"family 1 localisation (N * sum p_b^2; 1.5 tuned standing wave): "
                      f"mean {loc.mean():.2f}, max {loc.max():.2f}"]
    return "\n".join(lines)


def plot_family_frequencies(model: ModalModel, png: Path, engine_orders=DEFAULT_ENGINE_ORDERS) -> None:
    """PNG: frequency vs nodal diameter for each family (like the paper's Fig. 3) and, below,
    the Campbell diagram (:func:`campbell_crossings`).

    Raises
    ------
    bttsim_stream._plotting.PlotExtraMissing
        matplotlib (the ``plot`` extra) is not installed (a :class:`BttsimError`).
    BttsimError
        ``png`` cannot be written.
    """
    plt = pyplot("the model plot")
    fam, nd = _labels(model)
    fams = np.unique(fam)
    fig = plt.figure(figsize=(11, 9.0))
    grid = fig.add_gridspec(2, 2, height_ratios=(1.0, 1.25))
    axes = [fig.add_subplot(grid[0, 0]), fig.add_subplot(grid[0, 1])]
    _plot_campbell(fig.add_subplot(grid[1, 0]), model, engine_orders)
    _plot_campbell(fig.add_subplot(grid[1, 1]), model, engine_orders, family=0)
    ax = axes[0]
    sel = fam == 0
    ax.plot(nd[sel], model.freq_hz[sel], "o", ms=5, label="assembly, family 1")
    if model.blade_alone_freq_hz is not None:
        ax.axhline(model.blade_alone_freq_hz[0], color="k", ls="--", lw=1, label="blade alone, mode 1")
    ax.set_xlabel("nodal diameter")
    ax.set_ylabel("natural frequency (Hz)")
    ax.set_title("1st blade-dominated family (cf. paper Fig. 3)")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right")
    ax = axes[1]
    for f in fams:
        s = fam == f
        ax.plot(nd[s], model.freq_hz[s], "o-" if model.campbell_freq_hz is None else "o",
                ms=4, label=f"family {f + 1}")
    ax.set_xlabel("nodal diameter")
    ax.set_ylabel("natural frequency (Hz)")
    ax.set_title("all families")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    png = Path(png)
    tmp = png.with_name(png.name + ".part")  # a failed write leaves the previous plot as it was
    try:
        png.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(tmp, dpi=110, format="png")
        tmp.replace(png)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise BttsimError(f"{png}: cannot write: {exc.strerror or exc}") from None
    finally:
        plt.close(fig)


def excited_nodal_diameter(engine_order: int, n_blades: int) -> int:
    """The nodal diameter (``0 .. n_blades // 2``) that engine order ``engine_order`` excites."""
    k = int(engine_order) % int(n_blades)
    return min(k, int(n_blades) - k)


def campbell_data(model: ModalModel) -> tuple[np.ndarray, np.ndarray]:
    """The family frequencies per ND at the model's speeds.

    Returns
    -------
    speed_rad_s : ndarray, shape (S,)
        ``[0]`` for a zero-speed model.
    freq_hz : ndarray, shape (S, n_families, n_blades // 2 + 1)
        ``campbell_freq_hz(_at_speed)`` when the model has it, else the mean frequency of the
        modes labelled with each (family, ND); NaN where no mode has that label.
    """
    e = model.extra
    speeds = np.asarray(e["speed_rad_s"], float) if "speed_rad_s" in e else np.zeros(1)
    if "campbell_freq_hz_at_speed" in e:
        return speeds, np.asarray(e["campbell_freq_hz_at_speed"], float)
    if model.campbell_freq_hz is not None and speeds.size == 1:
        return speeds, np.asarray(model.campbell_freq_hz, float)[None]
    fam, nd = _labels(model)
    freq = np.asarray(e["freq_hz_at_speed"], float) if "freq_hz_at_speed" in e else model.freq_hz[None]
    n_fam, n_nd = int(fam.max()) + 1, model.n_blades // 2 + 1
    out = np.full((speeds.size, n_fam, n_nd), np.nan)
    for f in range(n_fam):
        for n in range(n_nd):
            sel = (fam == f) & (nd == n)
            if np.any(sel):
                out[:, f, n] = freq[:, sel].mean(axis=1)
    return speeds, out


@dataclass(frozen=True, slots=True)
class Crossing:
    """An engine-order line meeting a family at the ND it excites.

    Attributes
    ----------
    engine_order, nodal_diameter, family : int
        ``family`` 0-based.
    rpm : float
        Speed of the crossing, rpm.
    freq_hz : float
        Frequency there, Hz (``engine_order * rpm / 60``).
    """

    engine_order: int
    nodal_diameter: int
    family: int
    rpm: float
    freq_hz: float


def campbell_crossings(model: ModalModel, engine_orders=DEFAULT_ENGINE_ORDERS,
                       nodal_diameters=None) -> list[Crossing]:
    """Every crossing of the given engine orders with every family, by speed.

    ``nodal_diameters`` (one per engine order, signed or ``0 .. N - 1``, folded to
    ``0 .. N // 2``): the ND each engine order's force excites, as a scenario sets it with the
    travelling-wave phase ``2 pi (b - 1) N_ND / N_b`` (Eq. 5-7); None: the classic aliasing
    ``ND = EO mod N`` (folded), what a force fixed in the casing excites.

    A speed-dependent model: within its speed range, between two sampled speeds the squared
    frequency taken linear in ``Omega^2`` (exact to first order in the prestress; the samples
    are what the model file holds); a zero-speed model: ``rpm = 60 f / EO``, any speed.
    """
    speeds, table = campbell_data(model)
    N = model.n_blades
    if nodal_diameters is None:
        pairs = {(int(e), excited_nodal_diameter(e, N)) for e in engine_orders if int(e) > 0}
    else:
        pairs = {(int(e), excited_nodal_diameter(n, N)) for e, n in zip(engine_orders, nodal_diameters)
                 if int(e) > 0}
    out = []
    for eo, nd in sorted(pairs):
        c = eo / (2.0 * np.pi)  # Hz per rad/s
        for f in range(table.shape[1]):
            F = table[:, f, nd]
            if not np.all(np.isfinite(F)):
                continue
            if speeds.size == 1:
                out.append(Crossing(eo, nd, f, 60.0 * float(F[0]) / eo, float(F[0])))
                continue
            u = speeds**2
            g = F**2 - c * c * u  # > 0 below the crossing
            for s in np.flatnonzero((g[:-1] > 0) & (g[1:] <= 0)):
                b = (F[s + 1] ** 2 - F[s] ** 2) / (u[s + 1] - u[s])
                a = F[s] ** 2 - b * u[s]
                w = math.sqrt(a / (c * c - b))
                out.append(Crossing(eo, nd, f, 30.0 * w / math.pi, c * w))
    return sorted(out, key=lambda x: (x.family, x.rpm))


def campbell_table(model: ModalModel, engine_orders=DEFAULT_ENGINE_ORDERS, families: int = 2,
                   excitations=None, source: str = "the scenario") -> str:
    """Text: the families' frequency range at the model's lowest and highest speed, and the
    crossings of ``engine_orders`` with the first ``families`` families.

    ``engine_orders`` are listed with the ND each aliases to (``EO mod N``, folded);
    ``excitations``, a sequence of ``(engine_order, nodal_diameter)`` (a scenario's
    ``[[excitation]]``, whose travelling-wave ND is set independently of the EO, Eq. 5-7),
    adds the crossings those forces excite, introduced as ``source``."""
    speeds, table = campbell_data(model)
    rpm = 30.0 * speeds / math.pi
    lines = ["", "Campbell diagram (EO n excites ND n mod N, folded):"]
    if speeds.size == 1:
        lines.append("  zero-speed model: the family frequencies do not change with speed")
    else:
        lines.append(f"  speed-dependent model: {speeds.size} speeds, 0 .. {rpm[-1]:.0f} rpm")
    for f in range(min(families, table.shape[1])):
        lo, hi = table[0, f], table[-1, f]
        if not np.any(np.isfinite(lo)):
            continue
        text = f"  family {f + 1}: {np.nanmin(lo):.2f} .. {np.nanmax(lo):.2f} Hz at 0 rpm"
        if speeds.size > 1:
            text += f", {np.nanmin(hi):.2f} .. {np.nanmax(hi):.2f} Hz at {rpm[-1]:.0f} rpm"
        lines.append(text)
    cross = [c for c in campbell_crossings(model, engine_orders) if c.family < families]
    where = "" if speeds.size == 1 else f" within 0 .. {rpm[-1]:.0f} rpm"
    lines.append(f"  crossings of EO {_eo_text(engine_orders)}{where}:")
    if not cross:
        lines.append("    none")
    for c in cross:
        lines.append(f"    EO {c.engine_order:2d} x ND {c.nodal_diameter:2d}, family {c.family + 1}: "
                     f"{c.rpm:8.1f} rpm, {c.freq_hz:8.2f} Hz")
    if excitations:
        eos = [int(e) for e, _ in excitations]
        nds = [int(n) for _, n in excitations]
        lines.append(f"  crossings the forces of {source} excite (their own ND):")
        fc = [c for c in campbell_crossings(model, eos, nds) if c.family < families]
        if not fc:
            lines.append("    none")
        for c in fc:
            lines.append(f"    EO {c.engine_order:2d} x ND {c.nodal_diameter:2d}, family {c.family + 1}: "
                         f"{c.rpm:8.1f} rpm, {c.freq_hz:8.2f} Hz")
        lines.append("  note: a force's ND is set by its travelling-wave phase 2 pi (b-1) N_ND / N_b (Eq. 5-7), "
                     "not by its EO; the list above assumes ND = EO mod N (folded), as a force fixed in space gives")
    return "\n".join(lines)


def _eo_text(engine_orders) -> str:
    eos = sorted({int(e) for e in engine_orders})
    if len(eos) > 2 and eos == list(range(eos[0], eos[-1] + 1)):
        return f"{eos[0]}..{eos[-1]}"
    return ", ".join(map(str, eos))


def _plot_campbell(ax, model: ModalModel, engine_orders, family: int | None = None) -> None:
    """Family lines (one per ND), EO lines and crossings on ``ax``; ``family`` (0-based): only
    that family, zoomed to its frequency range."""
    speeds, table = campbell_data(model)
    rpm = 30.0 * speeds / math.pi
    top = float(rpm[-1]) if speeds.size > 1 else ZERO_SPEED_TOP_RPM
    x = rpm if speeds.size > 1 else np.array([0.0, top])
    rows_all = table if speeds.size > 1 else np.repeat(table[:1], 2, axis=0)
    eos = sorted({int(e) for e in engine_orders if int(e) > 0})
    fams = [f for f in range(table.shape[1]) if (family is None or f == family)
            and np.any(np.isfinite(rows_all[:, f]))]
    if family is None:
        finite = rows_all[np.isfinite(rows_all)]
        f_lo, f_top = 0.0, min(1.1 * float(finite.max()), 1.25 * max(eos) * top / 60.0) if finite.size else 1.0
    else:
        sel = rows_all[:, family][np.isfinite(rows_all[:, family])]
        pad = max(0.15 * float(np.ptp(sel)), 0.5) if sel.size else 1.0
        f_lo, f_top = (float(sel.min()) - pad, float(sel.max()) + pad) if sel.size else (0.0, 1.0)
    colors = _colors()
    cmap = pyplot("the model plot").get_cmap("viridis")
    for f in fams:
        rows = rows_all[:, f]
        for n in range(rows.shape[1]):
            color = cmap(n / max(rows.shape[1] - 1, 1)) if family is not None else colors[f % len(colors)]
            label = (f"ND {n}" if n in (0, rows.shape[1] - 1) else None) if family is not None else \
                (f"family {f + 1} (ND 0..{rows.shape[1] - 1})" if n == 0 else None)
            ax.plot(x, rows[:, n], "-", color=color, lw=0.8, alpha=0.9, label=label)
    for eo in eos:
        x_end = min(top, 60.0 * f_top / eo)
        if eo * x_end / 60.0 < f_lo:
            continue
        ax.plot([0.0, x_end], [0.0, eo * x_end / 60.0], color="0.6", lw=0.8, zorder=1)
        ax.annotate(f"EO {eo}", (x_end, eo * x_end / 60.0), fontsize=7, color="0.35",
                    xytext=(2, 2), textcoords="offset points", annotation_clip=False)
    cross = [c for c in campbell_crossings(model, eos) if c.rpm <= top and (family is None or c.family == family)]
    if cross:
        ax.plot([c.rpm for c in cross], [c.freq_hz for c in cross], "o", ms=3.5, color="crimson",
                label="crossing (EO x its ND)", zorder=3)
        if family is not None:
            for c in cross:
                ax.annotate(f"{c.rpm:.0f}", (c.rpm, c.freq_hz), fontsize=6, color="crimson",
                            xytext=(3, -8), textcoords="offset points")
    ax.set_xlim(0.0, top)
    ax.set_ylim(f_lo, f_top)
    ax.set_xlabel("speed (rpm)")
    ax.set_ylabel("frequency (Hz)")
    kind = "with centrifugal effects" if speeds.size > 1 else "zero-speed model: flat lines"
    ax.set_title(f"Campbell diagram ({kind})" if family is None else f"family {family + 1}, every ND (zoom)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper left")


def _colors() -> list:
    return ["tab:blue", "tab:orange", "tab:green", "tab:purple", "tab:brown", "tab:cyan", "tab:olive"]

"""Human-readable views of a modal model: the family / nodal-diameter table and Fig. 3's plot."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .._plotting import pyplot
from ..errors import BttsimError
from .modal_model import ModalModel, label_modes, localisation

__all__ = ["family_table", "plot_family_frequencies"]


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


def plot_family_frequencies(model: ModalModel, png: Path) -> None:
    """PNG like the paper's Fig. 3: frequency vs nodal diameter for each family.

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
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
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
    try:
        png.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(png, dpi=110)
    except OSError as exc:
        raise BttsimError(f"{png}: cannot write: {exc.strerror or exc}") from None
    finally:
        plt.close(fig)

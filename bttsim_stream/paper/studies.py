"""Reproduce the paper's studies (Table 2, Table 3, Sec. 3.3.4, Figs. 6-13), ours beside its numbers.

Each study is one function ``study_<name>(out_dir) -> dict`` that simulates what it needs
with the library (:func:`bttsim_stream.paper.validate_processing.simulate`, cached per
process), processes it with :func:`bttsim_stream.process.pipeline.process_arrays`, and writes
``<out_dir>/<name>.md`` (a Markdown table with the paper's values beside ours),
``<out_dir>/<name>.json`` and PNG figures. Errors are percent, amplitudes peak-to-peak;
"ours" uses the default pipeline (OPR-based expected times, calibrated arrival angles, peak
pick) unless a table says otherwise.

Run ``bttsim study NAME --out DIR`` or ``python -m bttsim_stream.paper.studies NAME --out DIR``
with NAME one of :data:`STUDIES` or ``all`` (the repository's copy is ``docs/results``). The
figures need matplotlib (the ``plot`` extra). Numerical only: never imports zenoh, protobuf,
mcap or rerun.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from ..errors import BttsimError
from ..process.pipeline import ProcessOptions, process_arrays
from ..process.probes import (
    PAPER_CANDIDATES_DEG,
    PAPER_TABLE3,
    condition_number,
    rank_layouts,
)
from ._report import md_table, out_dir_mk, pyplot, savefig, write_study
from .bench_ref import reference_hp_toas, study_bench
from .validate_processing import PAPER_TABLE2, default_model, simulate

__all__ = [
    "STUDIES",
    "main",
    "reference_hp_toas",
    "run",
    "study_bench",
    "study_figures",
    "study_nd",
    "study_probe_count",
    "study_table2",
    "study_table3",
]

METHODS = ("HP", "AD", "PAD")
STATS = ("max_E_A_pct", "mean_E_A_pct", "max_E_f_pct", "mean_E_f_pct")

#: Why our numbers can differ from the paper's (quoted in the tables' notes).
WHY = ("Our processing is exact least squares (Eq. 16) on exactly simulated data with our own, "
       "documented data preparation (docs/processing.md); the paper processed its data with a "
       "commercial package (MultiTool) whose data preparation and peak identification are "
       "proprietary. Our model is a beam model calibrated to the paper's frequencies and "
       "resonant amplitude (docs/simulation.md), not the paper's scanned-CAD FE model, and the "
       "paper's blades carry a small disk mistuning that our tuned default wheel does not.")


# ----------------------------------------------------------------------------- helpers
def _process(run, *, prep: bool = True, expected_times: str = "opr", peak_method: str = "max"):
    opts = ProcessOptions(expected_times=expected_times, prep=prep, peak_method=peak_method)
    return process_arrays(run.opr_s, run.toa_s, run.info, opts, truth=run.truth)


def _stats(summary: dict) -> dict:
    return {k: float(summary[k]) for k in STATS}


def _per_blade(summary: dict, key: str) -> np.ndarray:
    return np.array([b[key] for b in summary["blades"]], dtype=float)


# ----------------------------------------------------------------------------- Table 2
def study_table2(out_dir: Path) -> dict:
    """Table 2: HP / AD / PAD TOAs x with / without data preparation, and Fig. 9."""
    t0 = time.perf_counter()
    runs = {m: simulate({"toa": {"method": m}} if m != "HP" else None) for m in METHODS}
    res: dict = {}
    summaries: dict = {}
    for expected in ("opr", "exact"):
        res[expected] = {}
        for prep in (True, False):
            key = "with_prep" if prep else "without_prep"
            res[expected][key] = {}
            for m in METHODS:
                s = _process(runs[m], prep=prep, expected_times=expected).summary
                res[expected][key][m] = _stats(s)
                if expected == "opr":
                    summaries[(m, key)] = s
    # Fig. 9: PAD per blade, with / without preparation
    plt = pyplot()
    fig, ax = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    blades = np.arange(1, 30)
    for i, (key, lab) in enumerate((("with_prep", "with data prep."), ("without_prep", "without data prep."))):
        s = summaries[("PAD", key)]
        w = 0.4
        ax[0].bar(blades + (i - 0.5) * w, _per_blade(s, "E_A_pct"), w, label=lab)
        ax[1].bar(blades + (i - 0.5) * w, _per_blade(s, "E_f_pct"), w, label=lab)
    ax[0].set_ylabel("E_A %")
    ax[1].set_ylabel("E_f %")
    ax[1].set_xlabel("blade")
    ax[0].legend()
    ax[0].set_title("PAD TOAs, default pipeline (cf. paper Fig. 9)")
    figs = [savefig(fig, out_dir_mk(out_dir) / "fig9_pad_errors_per_blade.png")]
    wall = time.perf_counter() - t0

    # the table: ours (OPR-based expected times) beside the paper; flag beyond paper scatter
    rows = []
    flags = []
    for key, lab in (("with_prep", "with prep."), ("without_prep", "without prep.")):
        for q in ("E_A", "E_f"):
            for stat in ("max", "mean"):
                qi = {"E_A": 0, "E_f": 2}[q] + (stat == "mean")
                cells = [lab, f"{stat} {q} %"]
                for m in METHODS:
                    ours = res["opr"][key][m][f"{stat}_{q}_pct"]
                    paper = PAPER_TABLE2[key][m][qi]
                    cells.append(f"{ours:.3g} ({paper:.3g})")
                    if stat == "mean":
                        pmax = PAPER_TABLE2[key][m][qi - 1]
                        scatter = pmax - paper  # paper's blade-to-blade spread proxy: max - mean
                        if abs(ours - paper) > scatter:
                            flags.append(f"{m} {lab} mean {q}: ours {ours:.3g} vs paper {paper:.3g} "
                                         f"(paper max - mean {scatter:.3g})")
                rows.append(cells)
    exact_rows = []
    for key, lab in (("with_prep", "with prep."), ("without_prep", "without prep.")):
        exact_rows.append([lab] + [" / ".join(f"{res['exact'][key][m][s]:.3g}" for s in STATS) for m in METHODS])
    text = [
        "# Table 2: resonance errors by TOA method and data preparation",
        "",
        (f"`bttsim study table2 --out DIR` ({wall:.0f} s). Default scenario (Table 1), 29 blades, "
        "EO 8 / ND 1 run-up 1000 -> 4000 rpm in 130 s; default pipeline (OPR-based expected times, "
        "calibrated arrival angles, peak pick). Cells: **ours (paper Table 2)**, percent."),
        "",
        md_table(["processing", "statistic", "HP", "AD", "PAD"], rows),
        "",
        "Exact expected times (from the simulator's truth), max E_A / mean E_A / max E_f / mean E_f %:",
        "",
        md_table(["processing", "HP", "AD", "PAD"], exact_rows),
        "",
        "![Fig. 9](fig9_pad_errors_per_blade.png)",
        "",
        "## Where we differ from the paper beyond its own blade-to-blade scatter",
        "",
        "(scatter proxy: the paper's max minus its mean in the same cell)",
        "",
    ]
    text += [f"* {f}" for f in flags] or ["* none"]
    text += [
        "",
        "Why: HP and AD data are exact to 1e-13 s / 4e-8 m here, so without preparation the only "
        "errors left are the peak pick's sampling (one revolution = 0.021 % in frequency) "
        "and the fit's window; the paper's 0.8-1.2 % floor comes from its package and its "
        "model. With preparation, the paper's package *increased* HP/AD errors (to ~3 %), ours "
        "raises them only slightly (by about 0.05 percentage points): our offset removal bridges "
        "the resonance region with a smooth "
        "baseline and our smoothing half-width scales with the half-power width (W/8), costing "
        "0.04 % of amplitude. PAD without preparation matches the paper (noise of ~10 % NSR, "
        "calibrated to the paper's figure); with preparation our smoother removes more of the "
        "noise than the paper's. " + WHY,
    ]
    data = {"ours": res, "paper": {k: {m: dict(zip(STATS, v)) for m, v in r.items()} for k, r in PAPER_TABLE2.items()},
            "flags": flags, "figures": figs, "wall_s": wall}
    write_study(out_dir, "table2", "\n".join(text), data)
    return data


# ----------------------------------------------------------------------------- Table 3
def table3_cn() -> dict:
    """Condition numbers of Table 3's layouts and the 462-layout range (no simulation)."""
    rows = [{"probes_deg": list(a), "paper_cn": p, "cn": condition_number(8, a)} for a, p in PAPER_TABLE3]
    ranked = rank_layouts(8, PAPER_CANDIDATES_DEG, 5)
    return {"rows": rows, "n_layouts": len(ranked), "cn_min": ranked[0].cn, "cn_max": ranked[-1].cn,
            "best": list(ranked[0].probe_angles_deg), "worst": list(ranked[-1].probe_angles_deg)}


def study_table3(out_dir: Path, *, simulate_layouts: bool = True) -> dict:
    """Table 3 / Fig. 11: E_A and E_f against CN for the nine layouts (PAD TOAs, with prep.)."""
    t0 = time.perf_counter()
    out_dir = out_dir_mk(out_dir)
    data = table3_cn()
    if simulate_layouts:
        for r in data["rows"]:
            run = simulate({"toa": {"method": "PAD"}, "probes": {"angles_deg": r["probes_deg"]}})
            r.update(_stats(_process(run).summary))
            r.update({f"noprep_{k}": v for k, v in _stats(_process(run, prep=False).summary).items()})
    wall = time.perf_counter() - t0
    figs = []
    if simulate_layouts:
        plt = pyplot()
        cn = [r["cn"] for r in data["rows"]]
        fig, ax = plt.subplots(1, 2, figsize=(10, 4))
        for k, lab, st in (("max_E_A_pct", "max E_A", "o-"), ("mean_E_A_pct", "mean E_A", "s-")):
            ax[0].plot(cn, [r[k] for r in data["rows"]], st, label=lab)
        for k, lab, st in (("max_E_f_pct", "max E_f", "o-"), ("mean_E_f_pct", "mean E_f", "s-")):
            ax[1].plot(cn, [r[k] for r in data["rows"]], st, label=lab)
        for a, y in ((ax[0], "E_A %"), (ax[1], "E_f %")):
            a.set_xlabel("condition number (EO 8)")
            a.set_ylabel(y)
            a.legend()
        ax[0].set_title("PAD TOAs, with data prep. (cf. Fig. 11a)")
        ax[1].set_title("(cf. Fig. 11b)")
        figs.append(savefig(fig, out_dir / "fig11_errors_vs_cn.png"))
    head = ["probes (deg)", "CN ours", "CN paper"]
    if simulate_layouts:
        head += ["max E_A %", "mean E_A %", "max E_f %", "mean E_f %", "mean E_A % no prep."]
    rows = []
    for r in data["rows"]:
        c = [", ".join(f"{a:g}" for a in r["probes_deg"]), f"{r['cn']:.2f}", f"{r['paper_cn']:.1f}"]
        if simulate_layouts:
            c += [f"{r['max_E_A_pct']:.3f}", f"{r['mean_E_A_pct']:.3f}", f"{r['max_E_f_pct']:.4f}",
                  f"{r['mean_E_f_pct']:.4f}", f"{r['noprep_mean_E_A_pct']:.3f}"]
        rows.append(c)
    text = [
        "# Table 3 / Fig. 11: effect of the condition number",
        "",
        (f"`bttsim study table3 --out DIR` ({wall:.0f} s). EO 8; each layout simulated with PAD TOAs "
        "(grid step 1.2e-5 s, NSR ~10 %) and processed with data preparation, as in the paper."),
        "",
        md_table(head, rows),
        "",
        (f"All {data['n_layouts']} five-probe layouts of the 11 candidate angles: CN "
        f"{data['cn_min']:.3f} .. {data['cn_max']:.3f} (paper 1.4 .. 16.7); best {data['best']} "
        f"(Table 1's layout), worst {data['worst']}."),
    ]
    if simulate_layouts:
        rs = data["rows"]
        lo = [r for r in rs if r["cn"] < 10.0]
        text += [
            "",
            "![Fig. 11](fig11_errors_vs_cn.png)",
            "",
            "Paper's statements (Fig. 11) beside ours:",
            "",
            md_table(["paper", "ours"], [
                ["mean E_A < 4 % for CN < 10", f"mean E_A <= {max(r['mean_E_A_pct'] for r in lo):.2f} % for CN < 10"],
                ["max E_A local peak > 10 % at CN 7.3",
                 (f"max E_A at CN 7.3: {rs[6]['max_E_A_pct']:.2f} % (largest over layouts "
                 f"{max(r['max_E_A_pct'] for r in rs):.2f} % at CN "
                 f"{max(rs, key=lambda r: r['max_E_A_pct'])['cn']:.1f})")],
                ["max E_f has a local peak at CN 7.3 (mirroring max E_A)",
                 (f"max E_f at CN 5.0 / 7.3 / 10.0: {rs[5]['max_E_f_pct']:.3f} / {rs[6]['max_E_f_pct']:.3f} / "
                 f"{rs[7]['max_E_f_pct']:.3f} %")],
                ["E_f < 0.62 % for all CN", f"max E_f <= {max(r['max_E_f_pct'] for r in rs):.3f} %"],
                ["E_f < 0.31 % for CN 1.4-2.6",
                 f"max E_f <= {max(r['max_E_f_pct'] for r in rs if r['cn'] < 2.7):.3f} % for CN <= 2.6"],
            ]),
            "",
            ("Our errors grow with the CN as the paper's do: the least-squares fit (Eq. 16) amplifies what "
             "noise the data preparation leaves by up to the CN. Mean E_A is close to the paper's bound "
             "(about 4 % for CN < 10) and E_f stays well inside the paper's bounds. The paper's non-monotone "
             "detail (a local max E_A peak over 10 % at CN 7.3) is a property of one noise realisation and "
             "one blade's peak; ours is 9.0 % there, from a different noise realisation (our PAD noise is "
             "deterministic in the crossing position within the grid step) and different processing. ") + WHY,
        ]
    data.update(wall_s=wall, figures=figs)
    write_study(out_dir, "table3", "\n".join(text), data)
    return data


# ----------------------------------------------------------------------------- ND 1 vs ND 14
def study_nd(out_dir: Path) -> dict:
    """Sec. 3.3.4, Figs. 12-13: ND 1 vs ND 14 resonant frequency and amplitude per blade."""
    t0 = time.perf_counter()
    out_dir = out_dir_mk(out_dir)
    res = {}
    for nd in (1, 14):
        run = simulate(None if nd == 1 else {"excitation": [{"engine_order": 8, "nodal_diameter": nd}]})
        s = _process(run).summary
        res[nd] = {"identified_nd": s["nd"], "freq_hz": _per_blade(s, "freq_hz"),
                   "amp_mm": 1e3 * _per_blade(s, "amp_pkpk_m"), "truth_freq_hz": _per_blade(s, "truth_freq_hz"),
                   "truth_amp_mm": 1e3 * _per_blade(s, "truth_amp_pkpk_m"), **_stats(s)}
    wall = time.perf_counter() - t0
    m = default_model()
    f1, f14 = (float(np.min(m.freq_hz[m.nodal_diameter == k])) for k in (1, 14))
    fnat = 100 * (f14 - f1) / f1

    def pct(a14, a1):
        return float(np.mean(100 * (a14 - a1) / a1))

    d = {"btt_freq_pct": pct(res[14]["freq_hz"], res[1]["freq_hz"]),
         "truth_freq_pct": pct(res[14]["truth_freq_hz"], res[1]["truth_freq_hz"]),
         "btt_amp_pct": pct(res[1]["amp_mm"], res[14]["amp_mm"]),
         "truth_amp_pct": pct(res[1]["truth_amp_mm"], res[14]["truth_amp_mm"])}
    d_abs_amp = {"btt": float(np.mean(100 * np.abs(res[14]["amp_mm"] - res[1]["amp_mm"]) / res[1]["amp_mm"])),
                 "truth": float(np.mean(100 * np.abs(res[14]["truth_amp_mm"] - res[1]["truth_amp_mm"])
                                        / res[1]["truth_amp_mm"]))}
    plt = pyplot()
    blades = np.arange(1, 30)
    figs = []
    for q, tq, unit, fname, title in (("freq_hz", "truth_freq_hz", "Hz", "fig12_nd_freq.png", "Fig. 12"),
                                      ("amp_mm", "truth_amp_mm", "mm pk-pk", "fig13_nd_amp.png", "Fig. 13")):
        fig, ax = plt.subplots(1, 2, figsize=(11, 4), sharey=False)
        for a, nd in zip(ax, (1, 14)):
            a.plot(blades, res[nd][q], "o", label="BTT (processed)")
            a.plot(blades, res[nd][tq], "x", label="d_eqv truth")
            a.set_title(f"ND {nd} (cf. {title}{'a' if nd == 1 else 'b'})")
            a.set_xlabel("blade")
            a.set_ylabel(unit)
            a.legend()
        figs.append(savefig(fig, out_dir / fname))
    rows = [
        ["identified ND", f"{res[1]['identified_nd']} / {res[14]['identified_nd']}", "1 / 14"],
        ["mean resonant frequency, ND 1 / ND 14 (Hz)",
         f"{res[1]['freq_hz'].mean():.2f} / {res[14]['freq_hz'].mean():.2f}", "-"],
        ["mean frequency difference ND 14 vs ND 1, BTT", f"{d['btt_freq_pct']:.3f} %", "0.99 %"],
        ["mean frequency difference, d_eqv truth", f"{d['truth_freq_pct']:.3f} %", "0.99 % (methods ii, iii)"],
        ["natural-frequency difference of the family-1 mode pairs (model)", f"{fnat:.3f} %", "1.05 %"],
        ["mean resonant amplitude, ND 1 / ND 14 (mm pk-pk)",
         f"{res[1]['amp_mm'].mean():.3f} / {res[14]['amp_mm'].mean():.3f}", "-"],
        ["mean amplitude difference (A_ND1 - A_ND14) / A_ND14, BTT", f"{d['btt_amp_pct']:.2f} %", "11.62 %"],
        ["mean amplitude difference, d_eqv truth", f"{d['truth_amp_pct']:.2f} %", "11.48 % (ii) / 11.57 % (iii)"],
        ["mean abs(A_ND14 - A_ND1) / A_ND1, BTT / truth",
         f"{d_abs_amp['btt']:.2f} % / {d_abs_amp['truth']:.2f} %", "-"],
        ["mean E_A / E_f %, ND 1", f"{res[1]['mean_E_A_pct']:.3f} / {res[1]['mean_E_f_pct']:.4f}", "-"],
        ["mean E_A / E_f %, ND 14", f"{res[14]['mean_E_A_pct']:.3f} / {res[14]['mean_E_f_pct']:.4f}", "-"],
    ]
    text = [
        "# Sec. 3.3.4 / Figs. 12-13: ND 1 vs ND 14",
        "",
        (f"`bttsim study nd --out DIR` ({wall:.0f} s). Default scenario (HP TOAs) with the EO 8 forcing "
        "phased for ND 1 and for ND 14; default pipeline. The paper does not say which way its amplitude "
        "difference is taken; we give (A_ND1 - A_ND14) / A_ND14 and the mean absolute difference."),
        "",
        md_table(["quantity", "ours", "paper"], rows),
        "",
        "![Fig. 12](fig12_nd_freq.png)",
        "",
        "![Fig. 13](fig13_nd_amp.png)",
        "",
        "The frequency split is a property of the model: ours puts the family-1 ND 1 and ND 14 modes at "
        "343.9 and 347.5 Hz (paper Fig. 3: 343.89/343.94 and 347.43/347.65 Hz), so BTT and truth both land "
        "near the paper's 0.99 %. The amplitude ratio is set by how much the disk takes part in each "
        "ND's mode (modal force per modal mass at the forced node) and by the damping; our beam-on-disk "
        "model was calibrated to the frequencies and to the ND 1 resonant amplitude only, so its ND 14 "
        "amplitude (ND 1's is about 16 % above ND 14's, BTT and truth alike, against the paper's 11.6 %) is a "
        "prediction of the model, not of the processing: BTT and truth agree to 0.03 % here. " + WHY,
    ]
    data = {"nd1": res[1], "nd14": res[14], "differences_pct": d, "abs_amp_difference_pct": d_abs_amp,
            "paper": {"freq_pct": 0.99, "amp_pct": 11.62, "amp_pct_ii": 11.48, "amp_pct_iii": 11.57},
            "figures": figs, "wall_s": wall}
    write_study(out_dir, "nd", "\n".join(text), {k: (v if not isinstance(v, dict) else
                                                {kk: (vv.tolist() if isinstance(vv, np.ndarray) else vv)
                                                 for kk, vv in v.items()}) for k, v in data.items()})
    return data


# ----------------------------------------------------------------------------- probe count
def study_probe_count(out_dir: Path, *, target_cn: float = 1.5) -> dict:
    """3..9 probes from the 11 candidates at CN near 1.5: mean E_A / E_f per count (PAD, with prep.)."""
    t0 = time.perf_counter()
    out_dir = out_dir_mk(out_dir)
    rows = []
    for n in range(3, 10):
        ranked = rank_layouts(8, PAPER_CANDIDATES_DEG, n)
        best = min(ranked, key=lambda c: abs(c.cn - target_cn))
        run = simulate({"toa": {"method": "PAD"}, "probes": {"angles_deg": list(best.probe_angles_deg)}})
        s = _stats(_process(run).summary)
        rows.append({"n_probes": n, "probes_deg": list(best.probe_angles_deg), "cn": best.cn,
                     "cn_min": ranked[0].cn, **s})
    wall = time.perf_counter() - t0
    plt = pyplot()
    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    n = [r["n_probes"] for r in rows]
    ax[0].plot(n, [r["mean_E_A_pct"] for r in rows], "o-", label="mean E_A")
    ax[0].plot(n, [r["max_E_A_pct"] for r in rows], "s--", label="max E_A")
    ax[1].plot(n, [r["mean_E_f_pct"] for r in rows], "o-", label="mean E_f")
    ax[1].plot(n, [r["max_E_f_pct"] for r in rows], "s--", label="max E_f")
    for a, y in ((ax[0], "E_A %"), (ax[1], "E_f %")):
        a.set_xlabel("number of probes (CN closest to 1.5)")
        a.set_ylabel(y)
        a.legend()
    figs = [savefig(fig, out_dir / "probe_count.png")]
    table = md_table(["probes", "layout (deg)", "CN", "lowest CN at this count", "mean E_A %", "max E_A %",
                       "mean E_f %", "max E_f %"],
                      [[r["n_probes"], ", ".join(f"{a:g}" for a in r["probes_deg"]), f"{r['cn']:.3f}",
                        f"{r['cn_min']:.3f}", f"{r['mean_E_A_pct']:.3f}", f"{r['max_E_A_pct']:.3f}",
                        f"{r['mean_E_f_pct']:.4f}", f"{r['max_E_f_pct']:.4f}"] for r in rows])
    text = [
        "# Number of probes at CN ~ 1.5 (Sec. 3.3.3, last paragraph)",
        "",
        (f"`bttsim study probe_count --out DIR` ({wall:.0f} s). For each count, the layout of the 11 "
        "candidate angles whose EO 8 condition number is closest to 1.5; PAD TOAs, default pipeline with "
        "data preparation."),
        "",
        table,
        "",
        "![probe count](probe_count.png)",
        "",
        ("Paper: \"convergence in mean(E_A) and mean(E_f) is evident as the number of probes is increased "
        "from 5 to 9 ..., the reduction in these values was not significant\" (no numbers printed; details "
        "in its ref. [31]). With 3 probes the fit of 3 unknowns is exactly determined, so nothing averages "
        "the PAD noise and no residual is left to judge the fit."),
    ]
    data = {"rows": rows, "figures": figs, "wall_s": wall}
    write_study(out_dir, "probe_count", "\n".join(text), data)
    return data


# ----------------------------------------------------------------------------- figures
WINDOW = {"speed": {"start_rpm": 2450.0, "segments": [{"duration_s": 10.0, "end_rpm": 2700.0}]}}


def study_figures(out_dir: Path, *, blade: int = 0, probe: int = 4) -> dict:
    """Fig. 6, 7, 8 and 10 equivalents (one blade / probe around resonance; travelling-wave map)."""
    t0 = time.perf_counter()
    out_dir = out_dir_mk(out_dir)
    plt = pyplot()
    figs = []
    hp = simulate(WINDOW)
    tr = hp.truth
    rpm = tr.omega_mean * 60 / (2 * np.pi)
    # Fig. 6: Eq. 1 vs d_eqv and d_tang
    fig, ax = plt.subplots(2, 1, figsize=(9, 6))
    for a, sl in ((ax[0], slice(None)), (ax[1], None)):
        if sl is None:
            i = int(np.argmax(tr.d_eqv_pkpk_m[:, blade]))
            sl = slice(max(i - 40, 0), i + 40)
        a.plot(rpm[sl], 1e3 * tr.d_eq1_m[sl, blade, probe], "-", label="d_j Eq. 1 (HP)")
        a.plot(rpm[sl], 1e3 * tr.d_eqv_m[sl, blade, probe], "--", label="d_eqv(t_TOA)")
        a.plot(rpm[sl], 1e3 * tr.d_tang_m[sl, blade, probe], ":", label="d_tang")
        a.set_xlabel("rpm")
        a.set_ylabel("mm")
        a.legend(fontsize=8)
    ax[0].set_title(f"blade {blade + 1}, probe {probe + 1} (cf. Fig. 6)")
    figs.append(savefig(fig, out_dir / "fig6_eq1_vs_deqv.png"))
    # Fig. 7: axial interpolation on / off
    near = simulate({**WINDOW, "toa": {"axial_interpolation": False}})
    fig, ax = plt.subplots(figsize=(9, 4))
    ax.plot(rpm, 1e3 * tr.d_eq1_m[:, blade, probe], "-", lw=1, label="axial interpolation (Eq. 9-11)")
    ax.plot(rpm, 1e3 * near.truth.d_eq1_m[:, blade, probe], "-", lw=1, label="nearest tip node")
    ax.plot(rpm, 1e3 * tr.d_eqv_m[:, blade, probe], "k--", lw=0.8, label="d_eqv(t_TOA)")
    ax.set_xlabel("rpm")
    ax.set_ylabel("mm")
    ax.legend(fontsize=8)
    ax.set_title(f"blade {blade + 1}, probe {probe + 1} (cf. Fig. 7)")
    figs.append(savefig(fig, out_dir / "fig7_axial_interpolation.png"))
    jumps = {name: float(1e3 * np.max(np.abs(np.diff(r.truth.d_eq1_m, axis=0))))
             for name, r in (("axial_interpolation", hp), ("nearest_node", near))}
    # Fig. 8: HP / AD / PAD
    ad = simulate({**WINDOW, "toa": {"method": "AD"}})
    pad = simulate({**WINDOW, "toa": {"method": "PAD"}})
    fig, ax = plt.subplots(2, 1, figsize=(9, 6))
    i = int(np.argmax(tr.d_eqv_pkpk_m[:, blade]))
    for a, sl in ((ax[0], slice(None)), (ax[1], slice(max(i - 30, 0), i + 30))):
        for r, lab, st in ((pad, "PAD", "-"), (ad, "AD", "-"), (hp, "HP", "--")):
            a.plot(rpm[sl], 1e3 * r.truth.d_eq1_m[sl, blade, probe], st, lw=1, label=f"d_{probe + 1} {lab}")
        a.plot(rpm[sl], 1e3 * tr.d_eqv_m[sl, blade, probe], "k:", lw=1, label="d_eqv")
        a.set_xlabel("rpm")
        a.set_ylabel("mm")
        a.legend(fontsize=8)
    ax[0].set_title(f"blade {blade + 1}, probe {probe + 1}: HP / AD / PAD (cf. Fig. 8)")
    figs.append(savefig(fig, out_dir / "fig8_hp_ad_pad.png"))
    win = tr.d_eqv_pkpk_m.max(axis=1) > 0.5 * tr.d_eqv_pkpk_m.max()
    nsr = {}
    for lab, r in (("AD", ad), ("PAD", pad)):
        e = (r.truth.d_eq1_m - tr.d_eq1_m)[win]
        nsr[lab] = float(100 * np.std(e - e.mean(axis=0)) / np.std(tr.d_eq1_m[win]))
    # Fig. 10: travelling-wave map, full default run with PAD TOAs (as the paper)
    full = simulate({"toa": {"method": "PAD"}})
    res = _process(full)
    tw = res.fit_tw
    nb = tw.n_blades
    half = nb // 2
    # signed ND axis -half..half: backward ND k at -k, forward at +k
    img = np.concatenate([tw.backward_m[:, 1:half + 1][:, ::-1], tw.forward_m[:, :half + 1]], axis=1)
    ptw = res.probe_tw
    pimg = np.concatenate([ptw.backward_m[:, 0, 1:half + 1][:, ::-1], ptw.forward_m[:, 0, :half + 1]], axis=1)
    fig, ax = plt.subplots(1, 2, figsize=(11, 5))
    nds = np.arange(-half, half + 1)
    for a, im, title in ((ax[0], pimg, "probe 1 spectrum (cf. Fig. 10)"), (ax[1], img, "fit spectrum (all probes)")):
        m = a.imshow(1e3 * im, aspect="auto", origin="lower", interpolation="nearest",
                     extent=[nds[0] - 0.5, nds[-1] + 0.5, 0, im.shape[0]], cmap="viridis")
        a.set_xlabel("signed ND (negative: backward)")
        a.set_ylabel("revolution")
        a.set_title(title)
        fig.colorbar(m, ax=a, label="mm pk-pk")
    figs.append(savefig(fig, out_dir / "fig10_travelling_wave.png"))
    wall = time.perf_counter() - t0
    rows = [
        ["Fig. 6", "max abs(d_j - d_eqv(t_TOA)) / max pk-pk (window, all blades/probes)",
         f"{100 * np.max(np.abs(tr.d_eq1_m - tr.d_eqv_m)) / tr.d_eqv_pkpk_m.max():.3f} %", "close agreement"],
        ["Fig. 6", "max abs(d_tang - d_eqv) / max pk-pk",
         f"{100 * np.max(np.abs(tr.d_tang_m - tr.d_eqv_m)) / tr.d_eqv_pkpk_m.max():.1f} %", "significant difference"],
        ["Fig. 7", "largest rev-to-rev jump, axial interpolation / nearest node",
         f"{jumps['axial_interpolation']:.3f} / {jumps['nearest_node']:.3f} mm", "smooth / discontinuities"],
        ["Fig. 8", "NSR vs HP in the resonance window, AD / PAD",
         f"{nsr['AD']:.3g} % / {nsr['PAD']:.3g} %", "AD close to HP / PAD ~10 %"],
        ["Fig. 10", "identified ND (fit spectrum, PAD with prep.)", f"{res.summary['nd']}", "1"],
    ]
    text = [
        "# Figs. 6, 7, 8, 10",
        "",
        (f"`bttsim study figures --out DIR` ({wall:.0f} s). Figs. 6-8: a 10 s run-up through the resonance "
        f"(2450 -> 2700 rpm, same sweep rate as the default run), blade {blade + 1}, probe {probe + 1}. "
        "Fig. 10: the default run with PAD TOAs."),
        "",
        md_table(["figure", "quantity", "ours", "paper"], rows),
        "",
        "![Fig. 6](fig6_eq1_vs_deqv.png)",
        "",
        "![Fig. 7](fig7_axial_interpolation.png)",
        "",
        "![Fig. 8](fig8_hp_ad_pad.png)",
        "",
        "![Fig. 10](fig10_travelling_wave.png)",
        "",
        ("Fig. 10 in the paper is the per-probe DFT across blades (probe 1), which also shows ND 1's "
        "image at backward ND 14 (a single probe cannot separate ND k from 2 EO - k); the right panel is "
        "our all-probe fit spectrum, which has no image."),
    ]
    data = {"jumps_mm": jumps, "nsr_pct": nsr, "nd": res.summary["nd"], "figures": figs, "wall_s": wall}
    write_study(out_dir, "figures", "\n".join(text), data)
    return data


STUDIES = {"table2": study_table2, "table3": study_table3, "nd": study_nd, "figures": study_figures,
           "probe_count": study_probe_count, "bench": study_bench}


def run(name: str, out_dir) -> None:
    """Run one study, or all of them, into ``out_dir`` (progress on stderr).

    Parameters
    ----------
    name : str
        A key of :data:`STUDIES`, or ``"all"``.
    out_dir : path-like
        Output folder, created if missing (the repository's copy is ``docs/results``).

    Raises
    ------
    BttsimError
        Unknown study, an output folder that cannot be created, or (before any simulation)
        matplotlib missing for a study that draws figures.
    """
    if name != "all" and name not in STUDIES:
        raise BttsimError(f"unknown study {name!r} (choose from {', '.join([*STUDIES, 'all'])})")
    names = list(STUDIES) if name == "all" else [name]
    if any(n != "bench" for n in names):
        pyplot()  # fail now, not at the first figure after minutes of simulation
    try:
        out_dir = out_dir_mk(out_dir)
    except OSError as exc:
        raise BttsimError(f"{out_dir}: cannot create the output folder ({exc.strerror or exc})") from None
    for n in names:
        t0 = time.perf_counter()
        STUDIES[n](out_dir)
        print(f"{n}: wrote {out_dir / (n + '.md')} in {time.perf_counter() - t0:.1f} s", file=sys.stderr)


def main(argv=None) -> int:
    """``python -m bttsim_stream.paper.studies NAME --out DIR``; NAME in :data:`STUDIES` or ``all``."""
    p = argparse.ArgumentParser(prog="python -m bttsim_stream.paper.studies", description=__doc__.splitlines()[0])
    p.add_argument("name", choices=[*STUDIES, "all"])
    p.add_argument("--out", type=Path, required=True, metavar="DIR",
                   help="output folder (the repository's copy: docs/results)")
    a = p.parse_args(argv)
    try:
        run(a.name, a.out)
    except BttsimError as exc:
        print(f"{p.prog}: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

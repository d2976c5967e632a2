"""The ``bttsim`` command line: one entry point, one subcommand per job.

Every user error (missing or malformed file, impossible parameter) ends with one line on
stderr, ``bttsim: error: ...``, and exit status 2 -- never a traceback.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .errors import BttsimError

__all__ = ["main", "build_parser"]


class _Parser(argparse.ArgumentParser):
    """argparse with the project's one-line error format (argparse already exits 2)."""

    def error(self, message: str) -> None:  # pragma: no cover - exercised via CLI tests
        self.exit(2, f"bttsim: error: {message}\n")


def _cmd_scenario(args: argparse.Namespace) -> None:
    from . import scenario

    if args.check is not None:
        scn = scenario.load_scenario(args.check)
        print(f"{args.check}: ok ({scn.rotor.n_blades} blades, {len(scn.probes.angles_deg)} probes)")
        return
    sys.stdout.write(scenario.default_toml())


def _cmd_model_build(args: argparse.Namespace) -> None:
    from . import scenario
    from .model import build_model, save_model

    scn = scenario.load_scenario(args.scenario) if args.scenario else scenario.Scenario()
    model = build_model(scn)
    save_model(model, args.out)
    print(f"wrote {args.out}: {model.n_modes} modes, {model.n_blades} blades, "
          f"build {model.meta['provenance']['build_time_s']:.2f} s")


def _cmd_model_show(args: argparse.Namespace) -> None:
    from ._plotting import PlotExtraMissing
    from .model import load_model
    from .model.report import family_table, plot_family_frequencies

    model = load_model(args.model)
    print(family_table(model), flush=True)
    png = Path(args.png) if args.png else Path(args.model).with_suffix(".png")
    try:
        plot_family_frequencies(model, png)
    except PlotExtraMissing as exc:
        if args.png:  # asked for the plot: the one-line error, exit 2
            raise
        print(f"bttsim: note: no plot written: {exc}", file=sys.stderr)  # the table is what was asked
        return
    print(f"wrote {png}")


def _scenario(path):
    from . import scenario

    return scenario.load_scenario(path) if path else scenario.Scenario()


def _cmd_simulate(args: argparse.Namespace) -> None:
    import time

    from .acquisition import simulate_to_mcap

    scn = _scenario(args.scenario)
    t0 = time.perf_counter()

    def progress(n, total):
        if not args.quiet:
            print(f"\rrevolution {n}/{total}", end="", file=sys.stderr, flush=True)

    out = simulate_to_mcap(scn, args.out, include_truth=not args.no_truth, progress=progress)
    if not args.quiet:
        print(file=sys.stderr)
    print(f"wrote {args.out}: {out['messages']} messages, {out['revolutions']} revolutions, "
          f"run {out['run_id']}, {time.perf_counter() - t0:.1f} s")


def _node_args(args: argparse.Namespace) -> list[str]:
    out = ["-m", args.mode]
    for e in args.connect:
        out += ["-e", e]
    for e in args.listen:
        out += ["-l", e]
    if args.config:
        out += ["-c", args.config]
    if args.multicast_scouting:
        out.append("--multicast-scouting")
    return out


def _cmd_replay(args: argparse.Namespace) -> None:
    from .nodes import replay_node
    from .nodes.sim_node import parse_rate
    from .transport import config_from_args

    res = replay_node.main(config_from_args(args), args.mcap, rate=parse_rate(args.rate), wait_s=args.wait,
                           allow_truncated=args.allow_truncated, duration_s=args.duration)
    print(f"replayed {res['messages']} of {res['of']} messages")


def _cmd_record(args: argparse.Namespace) -> None:
    import json

    from .nodes import recorder_node
    from .transport import config_from_args

    until = tuple(n for n in args.until.split(",") if n) or None
    print(json.dumps(recorder_node.main(config_from_args(args), args.out, args.rig,
                                        duration_s=args.duration, until=until)))


def _cmd_sim_node(args: argparse.Namespace) -> None:
    from .nodes import sim_node
    from .transport import config_from_args

    sim_node.main(config_from_args(args), _scenario(args.scenario), rate=sim_node.parse_rate(args.rate),
                  lossy=args.lossy, truth=not args.no_truth, wait_for=args.wait_for,
                  duration_s=args.duration, revolutions=args.revolutions, linger_s=args.linger,
                  progress=args.progress)


def _cmd_process(args: argparse.Namespace) -> None:
    import json

    from .offline import load_run
    from .process.pipeline import ProcessOptions, process_arrays
    from .process.resonance import summary_table

    run = load_run(args.mcap)
    if args.exact_expected and run.truth is None:
        raise BttsimError(f"{args.mcap}: --exact-expected needs a recording with truth")
    opts = ProcessOptions(expected_times="exact" if args.exact_expected else "opr", prep=not args.no_prep,
                          window=args.window)
    result = process_arrays(run.opr_s, run.toa_s, run.meta, opts, truth=run.truth)
    summary = result.summary
    print(summary_table(summary))
    if args.summary:
        try:
            Path(args.summary).write_text(json.dumps(summary, indent=2) + "\n")
        except OSError as exc:
            raise BttsimError(f"{args.summary}: cannot write ({exc.strerror or exc})") from None
        print(f"wrote {args.summary}")


def _cmd_run(args: argparse.Namespace) -> None:
    from .orchestrate import run_all
    from .process.resonance import summary_table

    res = run_all(args.scenario, args.out, web=args.web, web_port=args.web_port, realtime=args.realtime,
                  connect=args.connect, config=args.config, quiet=args.quiet)
    if res["summary"] is not None:
        print(summary_table(res["summary"]))
    files = res["files"]
    print(f"wrote {files['mcap']}, {files['rrd']}, {files['summary']} in {res['wall_s']:.1f} s"
          + (" (interrupted)" if res["interrupted"] else ""))


def _cmd_view(args: argparse.Namespace) -> None:
    import tempfile
    import time

    from .offline import with_processing
    from .views import log_recording

    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bttsim-view-") as tmp:
        src = with_processing(args.mcap, Path(tmp) / "processed.mcap")
        session = log_recording(src, args.rrd, serve_web=args.web, web_port=args.web_port)
        if args.web:
            from .transport import StopFlag

            print(f"web viewer: {session.sinks.web_url}  (Ctrl-C to stop)", flush=True)
            stop = StopFlag()
            while not stop.wait(0.5):
                pass
        session.close()
    if args.rrd:
        print(f"wrote {args.rrd} in {time.perf_counter() - t0:.1f} s")


def _cmd_cn(args: argparse.Namespace) -> None:
    from .process.probes import condition_number

    print(f"{condition_number(args.eo, _angles(args.probes)):.4g}")


def _cmd_probes(args: argparse.Namespace) -> None:
    from .process.probes import PAPER_CANDIDATES_DEG, rank_layouts

    cands = _angles(args.candidates) if args.candidates else PAPER_CANDIDATES_DEG
    ranked = rank_layouts(args.eo, cands, args.n)
    finite = [r.cn for r in ranked if r.cn != float("inf")]
    print(f"{len(ranked)} layouts of {args.n} probes from {len(cands)} candidates at EO {args.eo}; "
          f"CN {min(finite):.3g} .. {max(finite):.3g}")
    for r in ranked[: args.top]:
        print(f"  CN {r.cn:8.3f}   " + ", ".join(f"{a:g}" for a in r.probe_angles_deg))


def _angles(text: str) -> list[float]:
    import math

    try:
        vals = [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise BttsimError(f"probe angles must be comma-separated degrees, got {text!r}") from None
    if not vals or not all(math.isfinite(v) for v in vals):
        raise BttsimError(f"probe angles must be finite numbers, got {text!r}")
    return vals


def _cmd_study(args: argparse.Namespace) -> None:
    from .paper import studies  # the paper's code: loaded only by this command and validate

    studies.run(args.name, args.out)


def _cmd_validate(args: argparse.Namespace) -> None:
    import json

    if args.processing:
        from .paper.validate_processing import format_validation, validate as validate_processing

        print(format_validation(validate_processing()))
        return
    from .paper.validate_sim import validate

    print(json.dumps(validate(), indent=2))


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="bttsim", description="Virtual blade tip timing acquisition system.")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    p = sub.add_parser("run", help="the main job: simulator, processor, recorder and viewer on Zenoh")
    p.add_argument("scenario", nargs="?", help="scenario TOML (default: the paper's Table 1)")
    p.add_argument("--out", required=True, help="output folder: run.mcap, views.rrd, summary.json")
    p.add_argument("--web", action="store_true", help="serve the Rerun web viewer and print its URL")
    p.add_argument("--web-port", type=int, default=9090)
    p.add_argument("--realtime", action="store_true", help="pace the simulator like real hardware")
    p.add_argument("-e", "--connect", action="append", default=[], metavar="ENDPOINT",
                   help="join an existing Zenoh network instead of the embedded one")
    p.add_argument("-c", "--config", metavar="FILE", help="Zenoh JSON5 configuration for every node")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress line")
    p.set_defaults(func=_cmd_run)

    p = sub.add_parser("scenario", help="print the default scenario (TOML) or check one")
    p.add_argument("--check", metavar="SCENARIO.toml", help="validate a scenario file and report")
    p.set_defaults(func=_cmd_scenario)

    p = sub.add_parser("model", help="build or inspect a bladed-disk modal model")
    msub = p.add_subparsers(dest="model_command", required=True, parser_class=_Parser)
    b = msub.add_parser("build", help="build the parametric bladed-disk model")
    b.add_argument("scenario", nargs="?", help="scenario TOML (default: the paper's rotor)")
    b.add_argument("--out", required=True, help="output model file (.npz)")
    b.set_defaults(func=_cmd_model_build)
    s = msub.add_parser("show", help="print the family / nodal-diameter table and plot it")
    s.add_argument("model", help="model file (.npz)")
    s.add_argument("--png", help="frequency vs ND plot (default: MODEL.png)")
    s.set_defaults(func=_cmd_model_show)
    from .transport import add_session_args

    p = sub.add_parser("simulate", help="simulate a scenario straight to MCAP (no Zenoh)")
    p.add_argument("scenario", nargs="?", help="scenario TOML (default: the paper's Table 1)")
    p.add_argument("--out", required=True, help="output MCAP file")
    p.add_argument("--no-truth", action="store_true", help="leave the truth channel out")
    p.add_argument("-q", "--quiet", action="store_true")
    p.set_defaults(func=_cmd_simulate)

    p = sub.add_parser("sim-node", help="run the simulator node (publish a run-up on Zenoh)")
    p.add_argument("scenario", nargs="?", help="scenario TOML (default: the paper's Table 1)")
    p.add_argument("--rate", default="max", help="'max' (default), 'realtime', or a speed-up factor")
    p.add_argument("--lossy", action="store_true", help="drop under congestion instead of blocking")
    p.add_argument("--no-truth", action="store_true")
    p.add_argument("--wait-for", type=int, default=0, metavar="N", help="wait for N other nodes")
    p.add_argument("--duration", type=float)
    p.add_argument("--revolutions", type=int)
    p.add_argument("--linger", type=float, default=0.0)
    p.add_argument("--progress", action="store_true")
    add_session_args(p)
    p.set_defaults(func=_cmd_sim_node)

    p = sub.add_parser("record", help="record every bttsim/** sample to MCAP")
    p.add_argument("--out", required=True)
    p.add_argument("--rig", default="*")
    p.add_argument("--duration", type=float)
    p.add_argument("--until", default="sim", help="nodes whose end ends the recording (comma-separated)")
    add_session_args(p)
    p.set_defaults(func=_cmd_record)

    p = sub.add_parser("replay", help="republish a recording on Zenoh")
    p.add_argument("mcap")
    p.add_argument("--rate", default="max", help="'max' (default), 'realtime', or a speed-up factor")
    p.add_argument("--wait", type=float, default=5.0, help="seconds to wait for subscribers (5)")
    p.add_argument("--allow-truncated", action="store_true")
    p.add_argument("--duration", type=float)
    add_session_args(p)
    p.set_defaults(func=_cmd_replay)

    p = sub.add_parser("process", help="process a recording offline into the resonance report")
    p.add_argument("mcap", help="recording (MCAP)")
    p.add_argument("--summary", help="write the summary JSON here")
    p.add_argument("--exact-expected", action="store_true",
                   help="use the truth's exact expected arrival times (reproduces the paper)")
    p.add_argument("--no-prep", action="store_true", help="no data preparation")
    p.add_argument("--window", type=int, default=1, help="revolutions per sine fit (1)")
    p.set_defaults(func=_cmd_process)

    p = sub.add_parser("view", help="Rerun views of a recording (.rrd file and/or web viewer)")
    p.add_argument("mcap", help="recording (MCAP); processed first if it holds no fits")
    p.add_argument("--rrd", help="write the views to this .rrd file")
    p.add_argument("--web", action="store_true", help="serve the web viewer until Ctrl-C")
    p.add_argument("--web-port", type=int, default=9090)
    p.set_defaults(func=_cmd_view)

    p = sub.add_parser("study", help="reproduce one of the paper's studies (NAME.md, NAME.json, PNGs) into --out")
    p.add_argument("name", choices=("table2", "table3", "nd", "figures", "probe_count", "bench", "all"))
    p.add_argument("--out", required=True, type=Path, metavar="DIR",
                   help="output folder (the repository's copy: docs/results); figures need the plot extra")
    p.set_defaults(func=_cmd_study)

    p = sub.add_parser("cn", help="condition number of B (Eq. 16) for an EO and probe angles")
    p.add_argument("--eo", type=int, default=8)
    p.add_argument("--probes", default="5,15.15,23.82,220,301.5", help="comma-separated angles, deg")
    p.set_defaults(func=_cmd_cn)

    p = sub.add_parser("probes", help="probe layouts ranked by condition number")
    p.add_argument("--eo", type=int, default=8)
    p.add_argument("--n", type=int, default=5, help="number of probes")
    p.add_argument("--candidates", help="comma-separated candidate angles, deg (default: the paper's 11)")
    p.add_argument("--top", type=int, default=10)
    p.set_defaults(func=_cmd_probes)

    p = sub.add_parser("validate", help="check the simulator (or, --processing, the processing) against the paper")
    p.add_argument("--processing", action="store_true",
                   help="Table 2 (HP/AD/PAD x data prep.), ND 1 vs ND 14, Table 3 (about a minute)")
    p.set_defaults(func=_cmd_validate)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        args.func(args)
    except BttsimError as exc:
        print(f"bttsim: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

"""The ``bttsim`` command line: one entry point, one subcommand per job.

Every user error (missing or malformed file, impossible parameter) ends with one line on
stderr, ``bttsim: error: ...``, and exit status 2 -- never a traceback.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from .bus.certs import IDENTITIES
from .bus.session import CONNECT_TIMEOUT_S
from .errors import BttsimError, comma_values, exit_status, replaceable_file
from .nodes import program, programs
from .processing_flags import add_processing_arguments, parse_engine_orders, processing_options
from .runtime import Parser as _Parser
from .runtime import Progress, add_drain_argument, add_node_parser, add_web_arguments, checked, positive_count, \
    positive_seconds, rig_name, run_parsed
from .threads import single_threaded_blas

# Here: what the parser needs. Each command imports what it uses (the scenario, the
# simulator, the model, recordings, the processing, the live run, the views: rerun takes
# 0.5 s, the paper's code is never loaded by the runtime), so a command pays for its own
# imports only; matplotlib (an optional extra) is imported by the plot functions when they run.

__all__ = ["main", "build_parser", "EXIT_INCOMPLETE"]

#: Exit status of ``bttsim run`` when it finished but its result is not the whole run
#: (lost messages, revolutions missing, no report); 2 is bad input, 130 Ctrl-C.
EXIT_INCOMPLETE = 3


def _cmd_scenario(args: argparse.Namespace) -> None:
    from . import scenario

    if args.check is not None:
        from .process.probes import LayoutError, layout_report
        from .sim.bounds import check_tip_amplitude
        from .sim.core import load_scenario_model

        scn = scenario.load_scenario(args.check)
        eos = [int(e.engine_order) for e in scn.excitation]
        try:  # a layout that cannot separate an engine order is refused before anything runs
            rows, warns = layout_report(eos, scn.probes.angles_deg)
        except LayoutError as exc:
            raise BttsimError(f"{args.check}: [probes] angles_deg: {exc}") from None
        cns = ", ".join(f"CN {cn:.3g} at {label}" for label, cn in rows)
        try:  # the model too: an absurd force is refused here, not after a run
            model = load_scenario_model(scn)
            # a force near the float limit overflows the bound to inf, which is refused: that
            # refusal, one line, says it all (the overflow warnings would only repeat it)
            with np.errstate(over="ignore", invalid="ignore"):
                bound = check_tip_amplitude(scn, model)
        except BttsimError as exc:
            raise BttsimError(f"{args.check}: {exc}") from None
        print(f"{args.check}: ok ({scn.rotor.n_blades} blades, {len(scn.probes.angles_deg)} probes; {cns}; "
              f"{bound.describe()})")
        for w in warns:
            print(f"bttsim: warning: {args.check}: {w}", file=sys.stderr)
        return
    sys.stdout.write(scenario.default_toml())


def _cmd_crb(args: argparse.Namespace) -> None:
    from . import scenario
    from .crb_report import bounds_table, scenario_bounds
    from .process.probes import LayoutError

    sigma = args.toa_sigma_s
    if sigma is not None and not (sigma == 0 or 1e-15 <= sigma <= 1e-3):  # NaN fails both
        raise BttsimError(f"--toa-sigma-s must be 0 or a time in s in [1e-15, 1e-3], got {sigma!r}")
    scn = scenario.load_scenario(args.scenario)
    try:
        bounds = scenario_bounds(scn, args.toa_sigma_s)
    except (ValueError, LayoutError) as exc:
        raise BttsimError(f"{args.scenario}: {exc}") from None
    print(bounds_table(bounds))
    bad = [b.eo for b in bounds if not (np.all(np.isfinite(b.crb_amp_m)) and np.all(np.isfinite(b.crb_freq_hz)))]
    if bad:
        print(f"bttsim: warning: {args.scenario}: no bound (nan) for EO {', '.join(map(str, bad))}: the crossing's "
              f"revolutions cannot resolve its SDOF parameters", file=sys.stderr)
    if bounds and bounds[0].toa_sigma_s == 0:
        print("bttsim: note: the scenario has no TOA noise (trigger_jitter_s 0, no clock): every bound is 0; "
              "give --toa-sigma-s", file=sys.stderr)


def _cmd_model_build(args: argparse.Namespace) -> None:
    from . import scenario
    from .model import build_model, save_model

    scn = scenario.load_scenario(args.scenario) if args.scenario else scenario.Scenario()
    model = build_model(scn)
    save_model(model, args.out)
    print(f"wrote {args.out}: {model.n_modes} modes, {model.n_blades} blades, "
          f"build {model.meta['provenance']['build_time_s']:.2f} s")


def _cmd_model_show(args: argparse.Namespace) -> None:
    from . import scenario
    from ._plotting import PlotExtraMissing
    from .model import load_model
    from .model.report import DEFAULT_ENGINE_ORDERS, campbell_table, family_table, plot_family_frequencies

    eos = _ints(args.eo, "--eo") if args.eo else list(DEFAULT_ENGINE_ORDERS)
    if not eos or any(e < 1 or e > 1000 for e in eos):
        raise BttsimError(f"--eo must be engine orders in [1, 1000], got {args.eo!r}")
    png = Path(args.png) if args.png else Path(args.model).with_suffix(".png")
    target = replaceable_file(png, "--png" if args.png else "the plot")  # not a folder, device or pipe
    if png.suffix.lower() != ".png":
        raise BttsimError(f"--png {png}: the plot is a PNG image: give a file name ending in .png")
    if target == Path(args.model).resolve():
        raise BttsimError(f"--png {png}: is the model file itself")
    model = load_model(args.model)
    if args.scenario:
        scn, source = scenario.load_scenario(args.scenario), f"scenario {args.scenario}"
    else:
        scn, source = scenario.Scenario(), "the default scenario (--scenario for another)"
    forced = [(int(e.engine_order), int(e.nodal_diameter)) for e in scn.excitation]
    print(family_table(model), flush=True)
    print(campbell_table(model, eos, excitations=forced, source=source), flush=True)
    try:
        plot_family_frequencies(model, target, eos)
    except PlotExtraMissing as exc:
        if args.png:  # asked for the plot: the one-line error, exit 2
            raise
        print(f"bttsim: note: no plot written: {exc}", file=sys.stderr)  # the table is what was asked
        return
    print(f"wrote {png}")


def _cmd_model_import(args: argparse.Namespace) -> None:
    from .model import save_model
    from .model.importers import (ImportOptions, check_options, format_report, import_model, import_model_speeds,
                                  load_import_options)
    from .model.report import family_table

    opts = load_import_options(args.options) if args.options else ImportOptions()
    flags = {"format": args.format, "deck": args.deck, "n_sectors": args.n_sectors, "tip_nset": args.tip_nset,
             "force_node": args.force_node, "nominal_node": args.nominal_node}
    if args.tip_nodes:
        flags["tip_nodes"] = tuple(_ints(args.tip_nodes, "--tip-nodes"))
    if args.force_xyz:
        flags["force_xyz"] = tuple(_floats(args.force_xyz, "--force-xyz", 3))
    if args.speeds_rpm:
        flags["speeds_rpm"] = tuple(_floats(args.speeds_rpm, "--speeds-rpm", len(args.speeds_rpm.split(","))))
    flags = {k: v for k, v in flags.items() if v is not None}
    if {"tip_nset", "tip_nodes"} & set(flags):  # a flag replaces the options file's choice
        opts = replace(opts, tip_nodes=(), tip_nset=None, tip_xyz=())
    if {"force_node", "force_xyz"} & set(flags):
        opts = replace(opts, force_node=None, force_nset=None, force_xyz=None)
    try:
        opts = check_options(replace(opts, **flags), "options")
    except TypeError as exc:
        raise BttsimError(str(exc)) from None
    if len(args.results) > 1 or opts.speeds_rpm:
        model, report = import_model_speeds(args.results, opts)
    else:
        model, report = import_model(args.results[0], opts)
    print(format_report(report), flush=True)
    save_model(model, args.out)
    print(f"wrote {args.out}: {model.n_modes} modes, {model.n_blades} blades; `bttsim model show {args.out}`:\n")
    print(family_table(model))


def _ints(text: str, what: str) -> list:
    return comma_values(text, int, what, "comma-separated whole numbers")


def _floats(text: str, what: str, n: int) -> list:
    vals = comma_values(text, float, what, f"{n} comma-separated numbers")
    if len(vals) != n:
        raise BttsimError(f"{what} must be {n} comma-separated numbers, got {text!r}")
    return vals


def _scenario(path):
    from . import scenario

    return scenario.load_scenario(path) if path else scenario.Scenario()


def _cmd_simulate(args: argparse.Namespace) -> None:
    from .acquisition import simulate_to_mcap
    from .diskspace import check_free_space, estimate_output_bytes
    from .sim.core import load_scenario_model

    scn = _scenario(args.scenario)
    model = None
    if not args.force:  # a run that cannot fit is refused before it starts (the model built once)
        model = load_scenario_model(scn)
        with np.errstate(over="ignore", invalid="ignore"):
            need = estimate_output_bytes(scn, model=model, include_truth=not args.no_truth)
        check_free_space(args.out, need, what="bttsim simulate")
    t0 = time.perf_counter()
    progress = Progress(not args.quiet)
    out = simulate_to_mcap(scn, args.out, model=model, include_truth=not args.no_truth,
                           progress=lambda n, total: progress.update(f"revolution {n}/{total}"))
    progress.close()
    print(f"wrote {args.out}: {out['messages']} messages, {out['revolutions']} revolutions, "
          f"run {out['run_id']}, {time.perf_counter() - t0:.1f} s")


def _cmd_export(args: argparse.Namespace) -> None:
    from .export import export_run

    t0 = time.perf_counter()
    counts = export_run(args.mcap, args.out, args.format, rig=args.rig)
    rows = ", ".join(f"{name} {n}" for name, n in counts.items())
    print(f"wrote {args.out}: {len(counts)} {args.format} tables ({rows} rows) and run.json in "
          f"{time.perf_counter() - t0:.1f} s")
    if counts.incomplete:
        print(f"bttsim: warning: {args.mcap}: INCOMPLETE: {counts.incomplete}: the tables are not the whole run",
              file=sys.stderr)


class _Tagged(argparse.Action):
    """Append ``(option name, value)`` to one list: --probe and --signal keep their order."""

    def __call__(self, parser, namespace, values, option_string=None):
        items = list(getattr(namespace, self.dest, None) or [])
        items.append((option_string.lstrip("-"), values))
        setattr(namespace, self.dest, items)


def _cmd_ingest(args: argparse.Namespace) -> None:
    from .ingest import SignalOptions, ingest_export, ingest_pulses, parse_probe, parse_signal

    t0 = time.perf_counter()
    if args.from_export:
        if args.opr or args.sources:
            raise BttsimError("--from-export takes no --opr / --probe / --signal (the export holds them)")
        res = ingest_export(args.from_export, args.out, rig=args.rig)
    else:
        if not args.opr:
            raise BttsimError("--opr FILE is required (the once-per-revolution pulse times), or --from-export DIR")
        if not args.sources:
            raise BttsimError("at least one --probe ANGLE_DEG=FILE (or --signal ANGLE_DEG=FILE) is required")
        eos = parse_engine_orders(args.eo) if args.eo else None
        probes = [parse_probe(v) if k == "probe" else parse_signal(v) for k, v in args.sources]
        signal_flags = [f for f in ("sample_rate", "trigger", "level_v", "hysteresis_v", "edge", "fraction", "clock_hz")
                        if getattr(args, f, None) is not None]
        signal_flags += [f for f, default in (("signal_start_s", 0.0), ("holdoff", 0.25))
                         if getattr(args, f) != default]
        if signal_flags and not any(k == "signal" for k, _ in args.sources):
            raise BttsimError(f"--{signal_flags[0].replace('_', '-')} is for raw probe signals: give them with "
                              "--signal ANGLE_DEG=FILE (a --probe file holds pulse times)")
        trig = args.trigger.split(",") if args.trigger else None
        signal = SignalOptions(sample_rate_hz=args.sample_rate, start_s=args.signal_start_s,
                               trigger=None if trig is None else (trig[0] if len(trig) == 1 else tuple(trig)),
                               level_v=args.level_v, hysteresis_v=args.hysteresis_v, edge=args.edge,
                               fraction=args.fraction, clock_hz=args.clock_hz, holdoff=args.holdoff)
        res = ingest_pulses(args.opr, probes, args.out, n_blades=args.blades,
                            tip_radius_m=args.tip_radius_m, rig=args.rig, engine_orders=eos,
                            scenario_path=args.scenario, column=args.column, signal=signal,
                            encoder_pulses=args.encoder_pulses, encoder_index=args.encoder_index)
    dt = time.perf_counter() - t0
    for note in res.notes:
        print(f"bttsim: note: {note}", file=sys.stderr)
    for p in res.per_probe:
        print(f"probe {p['probe']} at {p['angle_deg']:g} deg: {p['toas']} TOAs, {p['missing']} missing, "
              f"{p['extra']} extra, {p['stray']} stray, {p['outside']} outside"
              + (f", {p['double']} double edges" if "signal" in p else "") + " "
              f"(median {p['median_pulses_per_revolution']:g} pulses/revolution)")
    print(f"wrote {args.out}: {res.revolutions} revolutions, {res.n_blades} blades, {res.n_probes} probes, "
          f"{res.toas} TOAs ({res.missing} missing, {res.extra} extra, {res.stray} stray, {res.outside} outside), "
          f"median {res.median_rpm:.1f} rpm, run {res.run_id}, {dt:.1f} s ({res.toas / max(dt, 1e-9):.3g} TOA/s)")


def _cmd_node(args: argparse.Namespace):
    return run_parsed(args)  # the node's exit status (3: its result is not whole)


def _cmd_process(args: argparse.Namespace) -> None:
    from .offline import PROCESS_TRUTH_FIELDS, check_probes, completeness, load_run, missing_toas, result_warnings
    from .process.pipeline import check_window, process_arrays
    from .process.resonance import summary_table
    from .summary import build_summary

    # the phases on a terminal only: on a pipe, stderr stays the errors and warnings
    opts = processing_options(args, expected_times="exact" if args.exact_expected else "opr")  # before the read
    progress = Progress(sys.stderr.isatty())
    progress.phase(f"reading {args.mcap} ...")
    # the exact expected times (a whole-run array as large as the TOAs) only when asked for
    kept = PROCESS_TRUTH_FIELDS if args.exact_expected else tuple(f for f in PROCESS_TRUTH_FIELDS if f != "t_exp_s")
    run = load_run(args.mcap, truth_fields=kept, rig=args.rig, scratch=True)  # the TOAs in a scratch file
    if args.exact_expected and run.truth is None:
        raise BttsimError(f"{args.mcap}: --exact-expected needs a recording with truth")
    probe_notes = check_probes(args.mcap, run, opts)
    try:
        check_window(opts.window, run.revolution.size)
    except ValueError as exc:
        raise BttsimError(f"{args.mcap}: {exc}") from None
    progress.phase(f"processing {run.revolution.size} revolutions ...")
    progress.close()
    missing = missing_toas(run.toa_s)  # pulses that did not trigger
    try:
        result = process_arrays(run.opr_s, run.toa_s, run.meta, opts, truth=run.truth,
                                revolution0=int(run.revolution[0]), spectra=False)  # the report only
    except ValueError as exc:  # an impossible layout (LayoutError), inconsistent arrays
        raise BttsimError(f"{args.mcap}: {exc}") from None
    except (np.linalg.LinAlgError, FloatingPointError) as exc:  # numerics that should not fail: one line anyway
        raise BttsimError(f"{args.mcap}: the processing failed ({type(exc).__name__}: {exc})") from None
    finally:
        run.toa_s.close()
    summary = build_summary(result.summary, completeness(run), missing_toas=missing,
                            doubles=run.doubles)  # extra trigger edges, each in its blade's window
    if probe_notes:
        summary["notes"] = probe_notes + list(summary.get("notes", []))
    if args.summary:  # before anything is printed: a closed stdout must not lose it
        try:
            Path(args.summary).write_text(json.dumps(summary, indent=2) + "\n")
        except OSError as exc:
            raise BttsimError(f"{args.summary}: cannot write ({exc.strerror or exc})") from None
    print(summary_table(summary))
    for w in result_warnings(summary, run.meta.tip_radius_m):
        print(f"bttsim: warning: {args.mcap}: {w}", file=sys.stderr)
    if args.summary:
        print(f"wrote {args.summary}")


def _cmd_certs(args: argparse.Namespace) -> None:
    from .bus.certs import generate_certificates
    from .bus.security import write_config_files

    names = [n.strip() for n in args.names.split(",") if n.strip()]
    made = [n for n in generate_certificates(args.dir, names, hosts=args.host, days=args.days,
                                             overwrite=args.force) if n != "ca"]
    write_config_files(args.dir, made)
    print(f"wrote {args.dir}: ca.pem (keep ca-key.pem off the nodes), NAME.pem, NAME-key.pem and the "
          f"Zenoh configuration NAME.json5 (for -c) of {', '.join(made)}")


def _print_run(res: dict) -> None:
    from .process.resonance import summary_table

    summary, files = res["summary"], res["files"]
    if summary is not None and "error" in summary:
        print(f"NO REPORT: {summary['error']}")
    elif summary is not None:
        print(summary_table(summary))
    print(f"wrote {files['mcap']}, {files['rrd']}, {files['summary']} in {res['wall_s']:.1f} s"
          + (" (interrupted)" if res["interrupted"] else ""), flush=True)


def _cmd_run(args: argparse.Namespace) -> int:
    from .orchestrate import run_all
    from .summary import describe_exit

    served: list[dict] = []

    def on_serving(res: dict) -> None:  # --web: the result now, while the viewer serves on
        _print_run(res)
        print("bttsim: the web viewer keeps serving until Ctrl-C", file=sys.stderr, flush=True)
        served.append(res)

    res = run_all(args.scenario, args.out, web=args.web, web_port=args.web_port, grpc_port=args.grpc_port,
                  bind=args.bind, realtime=args.realtime, connect=args.connect, config=args.config,
                  quiet=args.quiet, mode=args.mode, on_serving=on_serving, tls_dir=args.tls_dir,
                  access_control=not args.no_access_control, connect_timeout_s=args.connect_timeout,
                  force=args.force, drain_timeout_s=args.drain_timeout)
    if served:
        res = served[0]  # the run's result: the Ctrl-C after it only ended the serving
    else:
        _print_run(res)
    summary = res["summary"]
    if res["interrupted"]:
        return 130
    problems = [f"the {n} node failed ({describe_exit(rc)}; see {Path(args.out) / (n + '.log')})"
                for n, rc in res["failed"].items()]
    if summary is None:
        problems.append("no summary (the processor gave no report; see processor.log)")
    elif not res.get("result_complete", summary.get("complete", False)):
        problems.append("the result is incomplete")
    recording = res["recording"]
    if not recording["complete"] and "recorder" not in res["failed"]:
        problems.append(f"the recording is incomplete: {recording.get('incomplete') or 'see recorder.log'}")
    if res.get("write_error"):
        problems.append(res["write_error"])
    viewer = res["viewer"]
    if viewer.get("missing") or viewer.get("gaps"):
        by_key = {k: sum(m.values()) for k, m in viewer["missing_by_key"].items()} if "missing_by_key" in viewer \
            else viewer.get("gaps_by_key")
        problems.append(f"the views miss {viewer.get('missing') or viewer['gaps']} messages{_by_key(by_key)}")
    elif viewer and viewer.get("complete") is False:
        problems.append(f"the views are incomplete: {viewer.get('incomplete') or 'see viewer.log'}")
    if problems:
        print(f"bttsim: warning: {'; '.join(problems)}", file=sys.stderr)
        return EXIT_INCOMPLETE
    return 0


def _by_key(counts) -> str:
    """`` (truth 60, fit 21)``: a count per key, the rig prefix left out."""
    if not isinstance(counts, dict) or not counts:
        return ""
    return " (" + ", ".join(f"{str(k).split('/', 2)[-1]} {v}" for k, v in counts.items()) + ")"


def _cmd_view(args: argparse.Namespace) -> None:
    if not (args.rrd or args.web):  # refused before the recording is read and processed
        raise BttsimError("no output: give --rrd OUT.rrd and/or --web")
    import tempfile

    from .bus.ports import check_web_ports
    from .offline import completeness, load_run, with_processing

    if args.web:  # a busy port too
        args.bind = check_web_ports(args.bind, args.web_port, args.grpc_port)
    from .views import log_recording  # rerun takes 0.5 s to import: after the checks above

    t0 = time.perf_counter()
    # checked as a run; its TOAs in a scratch file (only completeness and metadata are used)
    run = load_run(args.mcap, truth_fields=(), rig=args.rig, scratch=True)
    whole, meta = completeness(run), run.meta
    run.toa_s.close()
    del run
    with tempfile.TemporaryDirectory(prefix="bttsim-view-") as tmp:
        src = with_processing(args.mcap, Path(tmp) / "processed.mcap", meta=meta)
        try:
            session = log_recording(src, args.rrd, serve_web=args.web, web_port=args.web_port,
                                    grpc_port=args.grpc_port, bind=args.bind, rig=meta.rig)
        except BttsimError as exc:  # name the user's file, not the processed copy
            raise BttsimError(str(exc).replace(str(src), str(args.mcap), 1)) from None
        if not whole.complete:
            print(f"bttsim: warning: {args.mcap}: INCOMPLETE: {whole.revolutions_processed} of "
                  f"{whole.revolutions_expected} revolutions" + (f", {whole.lost} messages lost" if whole.lost else "")
                  + ": the views are not the whole run", file=sys.stderr, flush=True)
        if args.web:
            from .bus.session import StopFlag

            print(f"web viewer: {session.sinks.web_url}  (Ctrl-C to stop)", flush=True)
            stop = StopFlag()
            while not stop.wait(0.5):
                pass
        session.close()
    if args.rrd:
        print(f"wrote {args.rrd} in {time.perf_counter() - t0:.1f} s")


def _cmd_cn(args: argparse.Namespace) -> None:
    from .process.probes import CN_WARN, check_layout

    # impossible input (EO < 1, too few probes, angles outside [0, 360), a singular layout):
    # LayoutError, one line, exit 2
    eos = parse_engine_orders(args.eo)
    cn = check_layout(eos, _angles(args.probes))
    print(f"{cn:.4g}")
    if cn > CN_WARN:
        print(f"bttsim: warning: condition number {cn:.3g} is above {CN_WARN:g}: expect large amplitude errors "
              f"(paper Fig. 11); try `bttsim probes --eo {args.eo}`", file=sys.stderr)


def _cmd_probes(args: argparse.Namespace) -> None:
    from .process.probes import CN_SINGULAR, PAPER_CANDIDATES_DEG, rank_layouts

    eos = parse_engine_orders(args.eo)
    cands = _angles(args.candidates, "candidate angles") if args.candidates else PAPER_CANDIDATES_DEG
    unknowns = 1 + 2 * len(eos)
    label = "EO " + "+".join(str(e) for e in eos)
    if args.n < unknowns:
        raise BttsimError(f"--n {args.n}: a layout needs at least {unknowns} probes to separate the {unknowns} "
                          f"unknowns of the sine fit at {label} (Eq. 16)")
    if args.n > len(cands):
        raise BttsimError(f"--n {args.n}: only {len(cands)} candidate angles to choose from")
    if args.top < 1:
        raise BttsimError(f"--top must be >= 1, got {args.top}")
    ranked = rank_layouts(eos, cands, args.n)
    finite = [r.cn for r in ranked if r.cn < CN_SINGULAR]
    if not finite:
        raise BttsimError(f"every layout of {args.n} probes from these {len(cands)} candidates is singular at "
                          f"{label}: add or move candidate angles")
    print(f"{len(ranked)} layouts of {args.n} probes from {len(cands)} candidates at {label}; "
          f"CN {min(finite):.3g} .. {max(finite):.3g}"
          + (f" ({len(ranked) - len(finite)} singular)" if len(finite) < len(ranked) else ""))
    for r in ranked[: args.top]:
        print(f"  CN {r.cn:8.3f}   " + ", ".join(f"{a:g}" for a in r.probe_angles_deg))


def _angles(text: str, what: str = "probe angles") -> tuple:
    from .process.probes import check_angles

    return check_angles(comma_values(text, float, what, "comma-separated degrees"), what)


def _cmd_study(args: argparse.Namespace) -> None:
    from .paper import studies  # the paper's code: loaded only by this command and validate

    studies.run(args.name, args.out)


def _cmd_campaign(args: argparse.Namespace) -> int:
    from .campaign import load_spec, run_campaign
    from .campaign.driver import tls_security

    spec = load_spec(args.spec)  # a bad spec is one line before any cluster starts
    if args.tls_dir and not args.scheduler:
        raise BttsimError("--tls-dir needs --scheduler tls://HOST:PORT (the embedded cluster stays on loopback)")
    security = tls_security(args.tls_dir) if args.tls_dir else None
    res = run_campaign(spec, args.out, scheduler=args.scheduler, n_workers=args.workers, resume=args.resume,
                       progress=Progress(not args.quiet), timeout_s=args.connect_timeout, dashboard=args.dashboard,
                       security=security)
    print(f"wrote {res.results} ({res.rows} rows) and {res.report}: {res.executed} run(s) in {res.wall_s:.1f} s "
          f"on {res.workers} worker(s) ({res.runs_per_s:.3g} runs/s), {res.skipped} resumed, {res.failed} failed")
    return 0


def _cmd_validate(args: argparse.Namespace) -> None:
    if args.processing:
        from .paper.validate_processing import format_validation, validate as validate_processing

        print(format_validation(validate_processing()))
        return
    from .paper.validate_sim import validate

    print(json.dumps(validate(), indent=2))


def _add_run_parser(sub) -> None:
    """``bttsim run``: the whole live system on Zenoh."""
    p = sub.add_parser("run", help="the main job: simulator, processor, recorder and viewer on Zenoh")
    p.add_argument("scenario", nargs="?", help="scenario TOML (default: the paper's Table 1)")
    p.add_argument("--out", required=True, help="output folder: run.mcap, views.rrd, summary.json")
    p.add_argument("--web", action="store_true",
                   help="serve the Rerun web viewer, print its URL, keep serving after the run until Ctrl-C")
    add_web_arguments(p)
    p.add_argument("--realtime", action="store_true", help="pace the simulator like real hardware")
    p.add_argument("-e", "--connect", action="append", default=[], metavar="ENDPOINT",
                   help="join an existing Zenoh network instead of the embedded one")
    p.add_argument("-c", "--config", metavar="FILE", help="Zenoh JSON5 configuration for every node")
    p.add_argument("-m", "--mode", choices=("peer", "client"), default="peer",
                   help="session mode of every node (peer; client: through a Zenoh router given with -e)")
    p.add_argument("--connect-timeout", type=positive_seconds, default=CONNECT_TIMEOUT_S, metavar="S",
                   help=f"a node that cannot reach its endpoints after S seconds fails ({CONNECT_TIMEOUT_S:g})")
    add_drain_argument(p)  # the recorder's, the processor's and the viewer's
    p.add_argument("--tls-dir", metavar="DIR",
                   help="mutual TLS and access control for every node, certificates from DIR (bttsim certs DIR)")
    p.add_argument("--no-access-control", action="store_true", help="with --tls-dir, authenticate only")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress line")
    p.add_argument("--force", action="store_true",
                   help="run even when the estimated output size exceeds the free space of --out")
    p.set_defaults(func=_cmd_run)


def _add_certs_parser(sub) -> None:
    """``bttsim certs``: the CA and node certificates for ``--tls-dir``."""
    p = sub.add_parser("certs", help="make a CA and per-node certificates for --tls-dir (docs/security.md)")
    p.add_argument("dir", help="output folder: ca.pem, ca-key.pem, NAME.pem, NAME-key.pem, NAME.json5")
    p.add_argument("--names", default=",".join(IDENTITIES),
                   help=f"comma-separated identities ({','.join(IDENTITIES)})")
    p.add_argument("--host", action="append", default=[], metavar="NAME_OR_IP",
                   help="a host name or address the certificates are valid for, besides loopback (repeatable)")
    p.add_argument("--days", type=int, default=365, help="validity in days (365)")
    p.add_argument("--force", action="store_true", help="replace the files of an existing folder")
    p.set_defaults(func=_cmd_certs)


def _add_scenario_parser(sub) -> None:
    """``bttsim scenario``: print or check a scenario."""
    p = sub.add_parser("scenario", help="print the default scenario (TOML) or check one")
    p.add_argument("--check", metavar="SCENARIO.toml", help="validate a scenario file and report")
    p.set_defaults(func=_cmd_scenario)


def _add_model_parser(sub) -> None:
    """``bttsim model build|show|import``."""
    p = sub.add_parser("model", help="build or inspect a bladed-disk modal model")
    msub = p.add_subparsers(dest="model_command", required=True, parser_class=_Parser)
    b = msub.add_parser("build", help="build the parametric bladed-disk model")
    b.add_argument("scenario", nargs="?", help="scenario TOML (default: the paper's rotor)")
    b.add_argument("--out", required=True, help="output model file (.npz)")
    b.set_defaults(func=_cmd_model_build)
    s = msub.add_parser("show", help="print the family / nodal-diameter table and the Campbell crossings; plot both")
    s.add_argument("model", help="model file (.npz)")
    s.add_argument("--png", help="frequency vs ND and Campbell plot (default: MODEL.png)")
    s.add_argument("--eo", help="engine orders of the Campbell lines and crossings, comma-separated (default 1..12)")
    s.add_argument("--scenario", metavar="SCENARIO.toml",
                   help="also list the crossings this scenario's forces excite (their own ND; default: the "
                        "default scenario's EO 8 x ND 1)")
    s.set_defaults(func=_cmd_model_show)
    i = msub.add_parser("import", help="a cyclic-symmetry FE sector solution (CalculiX .frd, neutral .npz) "
                                       "to the model file",
                        description="Expand a cyclic-symmetry sector solution to the full-wheel model file; "
                                    "see schemas/cyclic_sector.md.")
    i.add_argument("results", nargs="+", help="sector results: CalculiX .frd or the neutral sector .npz; several "
                                              "(one per speed, with --speeds-rpm) for a speed-dependent model")
    i.add_argument("--out", required=True, help="output model file (.npz)")
    i.add_argument("--format", choices=("frd", "npz", "rst"),
                   help="results format (default: from the extension; rst: not read yet, see schemas/cyclic_sector.md)")
    i.add_argument("--options", metavar="IMPORT.toml", help="import options (nodes, units, damping)")
    i.add_argument("--deck", help="CalculiX input deck for node sets and N (default: RESULTS with .inp)")
    i.add_argument("--n-sectors", type=int, help="number of sectors (default: from the deck)")
    i.add_argument("--tip-nset", help="node set of the tip nodes")
    i.add_argument("--tip-nodes", help="tip node numbers, comma-separated")
    i.add_argument("--force-node", type=int, help="excitation node number")
    i.add_argument("--force-xyz", help="excitation node: the node nearest to x,y,z")
    i.add_argument("--nominal-node", type=int, help="0-based tip node of P_nom (default: the middle one)")
    i.add_argument("--speeds-rpm", help="speed of each results file (or of each frequency step of one .frd), rpm, "
                                        "comma-separated, ascending from 0: a speed-dependent model")
    i.set_defaults(func=_cmd_model_import)


def _add_simulate_parser(sub) -> None:
    """``bttsim simulate``: a scenario straight to MCAP."""
    p = sub.add_parser("simulate", help="simulate a scenario straight to MCAP (no Zenoh)")
    p.add_argument("scenario", nargs="?", help="scenario TOML (default: the paper's Table 1)")
    p.add_argument("--out", required=True, help="output MCAP file")
    p.add_argument("--no-truth", action="store_true", help="leave the truth channel out")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress line")
    p.add_argument("--force", action="store_true",
                   help="write even when the estimated file size exceeds the free space")
    p.set_defaults(func=_cmd_simulate)


def _add_node_parsers(sub) -> None:
    """``bttsim node NAME`` and the nodes under their historical names (``sim-node``, ``record``, ...)."""
    p = sub.add_parser("node", help="run one node program on Zenoh (sim, recorder, processor, viewer, replay)",
                       description="Run one node program; `bttsim node NAME --help` lists its options.")
    nsub = p.add_subparsers(dest="node", required=True, parser_class=_Parser)
    for prog in programs():
        add_node_parser(nsub, prog).set_defaults(func=_cmd_node)
    # the same programs under their historical names
    add_node_parser(sub, program("sim"), "sim-node").set_defaults(func=_cmd_node)
    add_node_parser(sub, program("recorder"), "record").set_defaults(func=_cmd_node)
    add_node_parser(sub, program("replay"), "replay").set_defaults(func=_cmd_node)
    add_node_parser(sub, program("router"), "router").set_defaults(func=_cmd_node)


def _add_crb_parser(sub) -> None:
    """``bttsim crb``: Cramér-Rao bounds of a scenario's resonances."""
    p = sub.add_parser("crb", help="Cramér-Rao lower bounds of the resonance amplitude and frequency of a scenario",
                       description="For each engine order's predicted crossing: the least standard deviation "
                                   "any unbiased estimate of each blade's resonant amplitude and frequency can have, "
                                   "from the probe layout, the TOA noise and the revolutions through the resonance "
                                   "(docs/processing.md).")
    p.add_argument("scenario", help="scenario (TOML)")
    p.add_argument("--toa-sigma-s", type=float, metavar="S",
                   help="TOA noise standard deviation, s (default: the scenario's trigger_jitter_s and clock)")
    p.set_defaults(func=_cmd_crb)


def _add_rig_argument(p) -> None:
    """``--rig``: which run of a recording of several rigs is read."""
    p.add_argument("--rig", type=rig_name, help="the rig whose run is read (needed when the recording holds "
                                                "several rigs' runs; default its only one)")


def _add_process_parser(sub) -> None:
    """``bttsim process``: a recording to the resonance report."""
    p = sub.add_parser("process", help="process a recording offline into the resonance report")
    p.add_argument("mcap", help="recording (MCAP)")
    p.add_argument("--summary", help="write the summary JSON here")
    _add_rig_argument(p)
    p.add_argument("--exact-expected", action="store_true",
                   help="use the truth's exact expected arrival times (reproduces the paper)")
    add_processing_arguments(p)
    p.set_defaults(func=_cmd_process)


def _add_export_parser(sub) -> None:
    """``bttsim export``: a recording's tables as CSV or Parquet."""
    p = sub.add_parser("export",
                       help="tidy tables of a recording (OPR, TOAs, displacements, fits, truth) as CSV or Parquet")
    p.add_argument("mcap", help="recording (MCAP)")
    p.add_argument("--format", choices=("csv", "parquet"), default="csv",
                   help="csv (always available) or parquet (the parquet extra: pyarrow)")
    p.add_argument("--out", required=True, help="output folder: one file per table and run.json")
    _add_rig_argument(p)
    p.set_defaults(func=_cmd_export)


def _add_ingest_parser(sub) -> None:
    """``bttsim ingest``: measured pulse trains or raw signals to a recording."""
    p = sub.add_parser("ingest", help="measured pulse trains (or an export folder) to a recording (schemas/ingest.md)",
                       description="A rig's OPR and per-probe pulse times to an MCAP recording that process, view, "
                                   "export and replay treat like a simulated run; see schemas/ingest.md.")
    p.add_argument("--out", required=True, help="output recording (MCAP)")
    p.add_argument("--from-export", metavar="DIR", help="the labelled tables of `bttsim export` (csv or parquet)")
    p.add_argument("--opr", metavar="FILE", help="OPR pulse times, s (CSV first column or Parquet)")
    p.add_argument("--probe", action=_Tagged, dest="sources", default=[], metavar="ANGLE_DEG=FILE",
                   help="a probe's angle (deg, anticlockwise from +x) and its pulse times, s (repeatable)")
    p.add_argument("--signal", action=_Tagged, dest="sources", metavar="ANGLE_DEG=FILE[@START_S]",
                   help="a probe's raw signal, volts (.npy or one-column CSV; NaN = not recorded), "
                        "triggered like the simulator's signal chain; @START_S: its first sample's time, s "
                        "(repeatable)")
    g = p.add_argument_group("raw signals (defaults: the --scenario's [acquisition.signal], else its defaults)")
    g.add_argument("--sample-rate", type=float, metavar="HZ", help="ADC sample rate, Hz")
    g.add_argument("--signal-start-s", type=float, default=0.0, metavar="T",
                   help="time of the first sample of each signal file without @START_S, s (default 0)")
    g.add_argument("--trigger", metavar="KIND[,KIND...]", help="threshold, constant_fraction or peak (one per probe)")
    g.add_argument("--level-v", type=float, help="trigger level (arming level of constant_fraction / peak), V")
    g.add_argument("--hysteresis-v", type=float, help="threshold hysteresis, V")
    g.add_argument("--edge", choices=("rising", "falling"), help="threshold edge")
    g.add_argument("--fraction", type=float, help="constant fraction, in (0, 1)")
    g.add_argument("--clock-hz", type=float, help="counter latching the trigger, Hz (0: none; default the "
                                                   "scenario's [acquisition] clock_hz)")
    g.add_argument("--holdoff", type=float, default=0.25,
                   help="hold-off between pulses, blade passing periods (default 0.25)")
    p.add_argument("--encoder-pulses", type=int, metavar="K",
                   help="the --opr file is a K-pulse shaft encoder (pulse 0: after a missing-tooth gap)")
    p.add_argument("--encoder-index", type=int, metavar="I",
                   help="with --encoder-pulses, for a wheel without a gap: pulse I of the file is pulse 0")
    p.add_argument("--blades", type=int, help="number of blades (or from --scenario)")
    p.add_argument("--tip-radius-m", type=float, help="tip radius of the sensing point, m (or from --scenario)")
    p.add_argument("--scenario", metavar="S.toml",
                   help="rotor geometry (blades, radius, OPR angle, model) from a scenario")
    p.add_argument("--eo", metavar="EO[,EO...]", help="expected engine orders (into the run metadata)")
    p.add_argument("--rig", help="rig name on the bus (default rig1, or the export's)")
    p.add_argument("--column", metavar="NAME", help="the column of the time files to read (default: the first)")
    p.set_defaults(func=_cmd_ingest)


def _add_view_parser(sub) -> None:
    """``bttsim view``: Rerun views of a recording."""
    p = sub.add_parser("view", help="Rerun views of a recording (.rrd file and/or web viewer)")
    p.add_argument("mcap", help="recording (MCAP); processed first if it holds no fits")
    p.add_argument("--rrd", help="write the views to this .rrd file")
    p.add_argument("--web", action="store_true", help="serve the web viewer until Ctrl-C")
    _add_rig_argument(p)
    add_web_arguments(p)
    p.set_defaults(func=_cmd_view)


def _add_study_parser(sub) -> None:
    """``bttsim study``: one of the paper's studies."""
    p = sub.add_parser("study", help="reproduce one of the paper's studies (NAME.md, NAME.json, PNGs) into --out")
    p.add_argument("name", choices=("table2", "table3", "nd", "figures", "probe_count", "bench", "all"),
                   help="the study to run (all: every one)")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="output folder (the repository's copy: docs/results); figures need the plot extra")
    p.set_defaults(func=_cmd_study)


def _add_campaign_parser(sub) -> None:
    """``bttsim campaign``: many runs on Dask, scored against truth."""
    p = sub.add_parser("campaign", help="a study of many runs scored against truth, on Dask (docs/campaign.md)")
    p.add_argument("spec", help="campaign spec (TOML): base scenario, axes, seeds, processors")
    p.add_argument("--out", required=True, help="output folder: results.parquet, report.md, runs/")
    p.add_argument("--scheduler", metavar="ADDRESS", help="a running Dask scheduler (tcp://HOST:PORT); default: an "
                                                         "embedded LocalCluster on loopback")
    p.add_argument("--workers", type=_worker_count, metavar="N",
                   help="workers of the embedded cluster (default: one per core; never more than the runs)")
    p.add_argument("--tls-dir", metavar="DIR", help="TLS to a tls:// scheduler with the certificates of bttsim certs: "
                                                   "DIR/ca.pem, DIR/campaign.pem, DIR/campaign-key.pem")
    p.add_argument("--resume", action="store_true", help="keep the runs already in --out, run the rest")
    p.add_argument("--connect-timeout", type=positive_seconds, default=10.0, metavar="S",
                   help="scheduler connect timeout (10)")
    p.add_argument("--dashboard", type=_dashboard_address, metavar="HOST:PORT",
                   help="serve the embedded cluster's Dask dashboard there (needs bokeh; e.g. 127.0.0.1:8787)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress line")
    p.set_defaults(func=_cmd_campaign)


def _worker_count(text: str) -> int:
    """``--workers N``: 1 to the embedded cluster's maximum."""
    from .campaign.driver import MAX_WORKERS

    n = positive_count(text)
    if n > MAX_WORKERS:
        raise argparse.ArgumentTypeError(f"{text!r} is above {MAX_WORKERS} (the most workers of the embedded cluster)")
    return n


def _dashboard_address(text: str) -> str:
    """``--dashboard HOST:PORT`` (as Dask takes it: a host name or address, or none for every
    interface) with a port in [0, 65535]."""
    import re

    host, sep, port = text.rpartition(":")
    ok = bool(sep) and port.isdigit() and int(port) <= 65535 and re.fullmatch(r"[A-Za-z0-9.\-]*|\[[0-9A-Fa-f:.]+\]",
                                                                              host) is not None
    if not ok:
        raise argparse.ArgumentTypeError(f"{text!r} is not HOST:PORT (e.g. 127.0.0.1:8787)")
    return text


def _add_probe_layout_parsers(sub) -> None:
    """``bttsim cn`` and ``bttsim probes``: condition numbers of probe layouts."""
    p = sub.add_parser("cn", help="condition number of B (Eq. 16) for an EO and probe angles")
    p.add_argument("--eo", default="8", help="engine order (>= 1), or several comma-separated (fitted jointly)")
    p.add_argument("--probes", default="5,15.15,23.82,220,301.5", help="comma-separated angles, deg")
    p.set_defaults(func=_cmd_cn)

    p = sub.add_parser("probes", help="probe layouts ranked by condition number")
    p.add_argument("--eo", default="8", help="engine order (>= 1), or several comma-separated (fitted jointly)")
    p.add_argument("--n", type=int, default=5, help="number of probes")
    p.add_argument("--candidates", help="comma-separated candidate angles, deg (default: the paper's 11)")
    p.add_argument("--top", type=int, default=10, help="how many layouts to print (10)")
    p.set_defaults(func=_cmd_probes)


def _add_validate_parser(sub) -> None:
    """``bttsim validate``: the simulator or the processing against the paper."""
    p = sub.add_parser("validate", help="check the simulator (or, --processing, the processing) against the paper")
    p.add_argument("--processing", action="store_true",
                   help="Table 2 (HP/AD/PAD x data prep.), ND 1 vs ND 14, Table 3 (about a minute)")
    p.set_defaults(func=_cmd_validate)


class _Version(argparse.Action):
    """``--version``: argparse's own, but the version is read only when asked (the package
    metadata: 40 ms of imports every other command would pay)."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS,
                 help="show program's version number and exit"):
        super().__init__(option_strings=option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        from . import __version__

        print(f"bttsim {__version__}")
        parser.exit()


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="bttsim", description="Virtual blade tip timing acquisition system.")
    parser.add_argument("--version", action=_Version)
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    _add_run_parser(sub)
    _add_certs_parser(sub)
    _add_scenario_parser(sub)
    _add_model_parser(sub)
    _add_simulate_parser(sub)
    _add_node_parsers(sub)
    _add_process_parser(sub)
    _add_crb_parser(sub)
    _add_export_parser(sub)
    _add_ingest_parser(sub)
    _add_view_parser(sub)
    _add_study_parser(sub)
    _add_campaign_parser(sub)
    _add_probe_layout_parsers(sub)
    _add_validate_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    single_threaded_blas()
    parser = build_parser()
    args = parser.parse_args(argv)
    return exit_status(checked, args.func, args)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

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
    from .model import load_model
    from .model.report import family_table, plot_family_frequencies

    model = load_model(args.model)
    print(family_table(model))
    png = Path(args.png) if args.png else Path(args.model).with_suffix(".png")
    plot_family_frequencies(model, png)
    print(f"wrote {png}")


def _cmd_validate(args: argparse.Namespace) -> None:
    import json

    from .sim.validate import validate

    print(json.dumps(validate(), indent=2))


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="bttsim", description="Virtual blade tip timing acquisition system.")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

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
    p = sub.add_parser("validate", help="check the simulator against the paper (Sec. 3.2-3.3.1)")
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

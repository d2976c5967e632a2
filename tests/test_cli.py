"""The command line as a new user meets it: help text, hints that can be pasted, errors that
come before the work."""

import shlex
import shutil
from pathlib import Path

from bttsim_stream import cli, orchestrate

REPO = Path(__file__).resolve().parents[1]
RECORDING = REPO / "recordings" / "resonance_window.mcap"


def test_no_report_hint_names_the_recording_of_the_run(tmp_path, capsys):
    """A run whose processor ended before its report prints the command that processes its
    recording, with the output folder the user gave: pasted back, it works."""
    mcap = tmp_path / "my out" / "run.mcap"
    summary = orchestrate._no_report_summary(429, -9, mcap)
    cli._print_run({"summary": summary, "files": {"mcap": str(mcap), "rrd": "views.rrd", "summary": "s.json"},
                    "wall_s": 1.0, "interrupted": False})
    line = next(ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("NO REPORT:"))
    assert "killed by SIGKILL" in line
    command = shlex.split(line.split(": ", 2)[-1])
    assert command == ["bttsim", "process", str(mcap)], line
    mcap.parent.mkdir()
    shutil.copyfile(RECORDING, mcap)
    assert cli.main(command[1:]) == 0
    assert capsys.readouterr().out.startswith("RESONANCE")


def _parsers(parser, path=("bttsim",)):
    """Every parser of the command line, with its command words."""
    import argparse

    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _parsers(sub, (*path, name))


def test_help_is_plain_text():
    """No ``--help`` shows reST markup: double backquotes or :func:/:class: roles."""
    import re

    seen = []
    for path, parser in _parsers(cli.build_parser()):
        text = parser.format_help()
        assert "``" not in text, (path, text)
        assert not re.search(r":[a-z]+:`", text), (path, text)
        seen.append(" ".join(path))
    assert {"bttsim", "bttsim run", "bttsim node sim", "bttsim node viewer", "bttsim model import",
            "bttsim replay"} <= set(seen)

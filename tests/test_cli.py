"""The command line as a new user meets it: help text, hints that can be pasted, errors that
come before the work."""

import shlex
import shutil
from pathlib import Path

import pytest

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


@pytest.mark.integration
@pytest.mark.parametrize("which", ["--web-port", "--grpc-port"])
def test_view_web_with_a_busy_port_fails_before_processing(tmp_path, which):
    """`bttsim view REC --web` on a busy port: one line, exit 2, before the recording (which
    holds no fits, so would be processed first) is processed or any view is written."""
    import socket
    import subprocess
    import sys

    from bttsim_stream.bus.session import free_port

    ports = {"--web-port": free_port(), "--grpc-port": free_port()}
    rrd = tmp_path / "views.rrd"
    garbage = tmp_path / "garbage.mcap"  # would fail as soon as it is read
    garbage.write_bytes(b"not an MCAP file\n" * 64)
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", ports[which]))
        busy.listen()
        results = [subprocess.run([sys.executable, "-m", "bttsim_stream.cli", "view", rec, "--rrd", rrd, "--web",
                                   "--web-port", str(ports["--web-port"]), "--grpc-port", str(ports["--grpc-port"])],
                                  cwd=REPO, capture_output=True, text=True, timeout=120)
                   for rec in (RECORDING, garbage)]
    for res in results:  # the port is the error, also for a recording that cannot be read: checked first
        assert res.returncode == 2, res.stdout + res.stderr
        lines = res.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("bttsim: error:") and which in lines[0], res.stderr
        assert f"127.0.0.1:{ports[which]}" in lines[0] and "in use" in lines[0]
        assert res.stdout == "" and not rrd.exists()  # nothing processed, no view written


def test_view_without_an_output_is_refused_before_processing(capsys):
    assert cli.main(["view", str(RECORDING)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("bttsim: error: no output") and err.count("\n") == 1

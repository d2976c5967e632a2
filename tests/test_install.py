"""The installed package: its version, and the main job on the protobuf runtime the install resolved.

The README's install resolves the newest protobuf the range allows (7.x at the time of
writing); ``.ci/run`` also smoke-runs runtime-only installs at the newest and the lowest
releases of every dependency (``.ci/smoke``).
"""

import json
import subprocess
import sys
import tomllib
from importlib.metadata import version
from pathlib import Path

import google.protobuf
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

import bttsim_stream
from bttsim_stream.bus import codec
from bttsim_stream.bus._gen.bttsim.v1 import bttsim_pb2 as pb

REPO = Path(__file__).resolve().parents[1]
SHORT = "[speed]\nstart_rpm = 2400.0\nend_rpm = 2700.0\nduration_s = 6.0\n"


def _cli(*args, **kw):
    return subprocess.run([sys.executable, "-m", "bttsim_stream.cli", *map(str, args)], capture_output=True,
                          text=True, timeout=600, **kw)


def test_version_comes_from_the_package_metadata():
    meta = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["version"]
    assert bttsim_stream.__version__ == version("bttsim-stream") == meta
    res = _cli("--version")
    assert res.returncode == 0 and res.stdout.strip() == f"bttsim {meta}", res.stdout + res.stderr


def test_repeated_fields_known_on_every_protobuf_release():
    """The codec's notion of a repeated field agrees with what a message instance holds."""
    for name in ("ToaBatch", "TruthBatch", "RunMetadata", "ResonanceReport", "SignalBatch", "NonSynchronous"):
        cls = getattr(pb, name)
        msg = cls()
        for f in cls.DESCRIPTOR.fields:
            holds_a_list = hasattr(getattr(msg, f.name), "extend")
            assert codec.is_repeated(f) == holds_a_list, f"{name}.{f.name}"


@pytest.mark.integration
def test_run_end_to_end_on_the_installed_protobuf(tmp_path):
    """``bttsim run`` writes a recording that a third-party reader decodes, on this protobuf."""
    low, high = 5, 7
    major = int(google.protobuf.__version__.split(".")[0])
    assert low <= major <= high, f"protobuf {google.protobuf.__version__} is outside the tested range"
    scn = tmp_path / "short.toml"
    scn.write_text(SHORT)
    out = tmp_path / "out"
    res = _cli("run", scn, "--out", out, "-q", cwd=tmp_path)
    assert res.returncode == 0, res.stdout + res.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "resonance" and summary["complete"] and len(summary["blades"]) == 29
    with open(out / "run.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        meta = [m for _, ch, _, m in reader.iter_decoded_messages() if ch.topic.endswith("/meta")]
    assert meta and meta[0].software_version == version("bttsim-stream")

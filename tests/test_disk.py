"""A full disk, an unwritable output and an output too big for the free space: one line, a
non-zero exit, and every file written so far valid.

Each case runs in a mount namespace of its own (``unshare -rm``) with a small tmpfs mounted
over a folder of the test: the rest of the machine is untouched. Skipped where user
namespaces or tmpfs mounts are not allowed.
"""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from bttsim_stream.bus.recording import read_recording

pytestmark = pytest.mark.integration

REPO = Path(__file__).resolve().parents[1]
SCENARIO = "[speed]\nstart_rpm = 2400.0\nend_rpm = 2800.0\nduration_s = 6.0\n"


def _in_tmpfs(mount: Path, options: str, *args, timeout: float = 300) -> subprocess.CompletedProcess:
    """``bttsim ARGS`` with a tmpfs (mount ``options``) over ``mount``, in a new mount namespace."""
    script = f'mount -t tmpfs -o {options} tmpfs "$0" && exec "$@"'
    return subprocess.run(["unshare", "-rm", "sh", "-c", script, str(mount), sys.executable, "-m",
                           "bttsim_stream.cli", *map(str, args)], cwd=REPO, capture_output=True, text=True,
                          timeout=timeout)


@pytest.fixture(scope="module")
def namespaces(tmp_path_factory):
    """Skip unless a tmpfs can be mounted in a user + mount namespace here."""
    if shutil.which("unshare") is None:
        pytest.skip("no unshare(1) on this machine")
    d = tmp_path_factory.mktemp("probe")
    res = subprocess.run(["unshare", "-rm", "sh", "-c", 'mount -t tmpfs -o size=1m tmpfs "$0"', str(d)],
                         capture_output=True, text=True, timeout=30)
    if res.returncode != 0:
        pytest.skip(f"user/mount namespaces or tmpfs mounts not allowed here: {res.stderr.strip()}")


@pytest.fixture
def scenario(tmp_path) -> Path:
    path = tmp_path / "scn.toml"
    path.write_text(SCENARIO)
    return path


def _one_line(text: str) -> str:
    lines = [ln for ln in text.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in text, text
    return lines[0]


def test_simulate_refuses_an_output_bigger_than_the_free_space_and_stops_cleanly_when_full(namespaces, scenario,
                                                                                        tmp_path):
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    res = _in_tmpfs(mnt, "size=1m", "simulate", scenario, "--out", mnt / "a.mcap", "-q")
    assert res.returncode == 2
    line = _one_line(res.stderr)
    assert "would write about 2." in line and "MB" in line and "--force" in line, line
    # --force: it writes until the disk is full, then one line; the file reads back up to its cut
    script = 'mount -t tmpfs -o size=1m tmpfs "$0" && "$1" -m bttsim_stream.cli simulate "$2" --out "$0/b.mcap" -q ' \
             '--force; rc=$?; cp "$0/b.mcap" "$3"; exit $rc'
    res = subprocess.run(["unshare", "-rm", "sh", "-c", script, str(mnt), sys.executable, str(scenario),
                          str(tmp_path / "b.mcap")], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert res.returncode == 2
    assert "No space left on device" in _one_line(res.stderr)
    rec = read_recording(tmp_path / "b.mcap")
    assert rec.truncated and len(rec.messages) > 100


def test_an_unwritable_out_is_one_line(namespaces, scenario, tmp_path):
    mnt = tmp_path / "ro"
    mnt.mkdir()
    for args in (("simulate", scenario, "--out", mnt / "a.mcap", "-q", "--force"),
                 ("run", scenario, "--out", mnt / "o", "-q", "--force")):
        res = _in_tmpfs(mnt, "ro,size=1m", *args)
        assert res.returncode == 2, res.stderr
        assert "Read-only file system" in _one_line(res.stderr), res.stderr


def test_a_run_whose_disk_fills_up_says_so_and_leaves_valid_files(namespaces, scenario, tmp_path):
    """``bttsim run --force`` into 3 MB (the run writes about 4.4 MB): exit 3, one line, the
    summary (the processor's, written before the disk filled) and the recording's prefix readable."""
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    keep = tmp_path / "kept"
    script = ('mount -t tmpfs -o size=3m tmpfs "$0" && "$1" -m bttsim_stream.cli run "$2" --out "$0/o" -q --force '
              '2>"$3.err"; rc=$?; cp -r "$0/o" "$3"; exit $rc')
    res = subprocess.run(["unshare", "-rm", "sh", "-c", script, str(mnt), sys.executable, str(scenario), str(keep)],
                         cwd=REPO, capture_output=True, text=True, timeout=300)
    err = Path(f"{keep}.err").read_text()
    assert res.returncode == 3, err
    line = _one_line(err)
    assert "No space left on device" in line and "node failed" in line, line
    for name in ("summary.json",):
        json.loads((keep / name).read_text())  # whole, or not replaced
    rec = read_recording(keep / "run.mcap")
    assert rec.truncated and len(rec.messages) > 0

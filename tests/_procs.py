"""Starting and stopping the node processes that tests run (each stopped by its own PID)."""

import signal
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def start(*args, stdout=subprocess.PIPE) -> subprocess.Popen:
    """``python -m ARGS...`` in the repository, stderr captured."""
    return subprocess.Popen([sys.executable, "-m", *map(str, args)], cwd=REPO, stdout=stdout,
                            stderr=subprocess.PIPE, text=True)


def stop(proc: subprocess.Popen, sig=signal.SIGTERM, timeout: float = 30) -> int:
    """Signal ``proc`` if it still runs, wait, kill it if it does not end; its return code."""
    if proc.poll() is None:
        proc.send_signal(sig)
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return proc.returncode

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


class LineWatch:
    """Collects the lines of a process's text stream on a thread, so that a test can wait for
    one (readiness) without blocking on the pipe."""

    def __init__(self, stream) -> None:
        import threading

        self.lines: list[str] = []
        self._cond = threading.Condition()
        self._thread = threading.Thread(target=self._read, args=(stream,), daemon=True)
        self._thread.start()

    def _read(self, stream) -> None:
        with stream:  # closed at the end of the stream: no pipe left for the garbage collector
            for line in stream:
                if isinstance(line, bytes):
                    line = line.decode(errors="replace")
                with self._cond:
                    self.lines.append(line)
                    self._cond.notify_all()
        with self._cond:
            self.lines.append(None)  # end of stream
            self._cond.notify_all()

    def wait_for(self, predicate, timeout: float = 120.0) -> str:
        """The first line for which ``predicate(line)`` is true; AssertionError on timeout or EOF."""
        import time

        deadline = time.monotonic() + timeout
        i = 0
        with self._cond:
            while True:
                while i < len(self.lines):
                    line = self.lines[i]
                    i += 1
                    if line is None:
                        raise AssertionError(f"stream ended without the line; got: {''.join(self.lines[:-1])[-2000:]}")
                    if predicate(line):
                        return line
                left = deadline - time.monotonic()
                if left <= 0:
                    raise AssertionError(f"timed out; got: {''.join(l for l in self.lines if l)[-2000:]}")
                self._cond.wait(left)

    def text(self) -> str:
        with self._cond:
            return "".join(l for l in self.lines if l)

"""Children that end with their parent: the parent-death signal set between fork and exec."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from _net import alive

REPO = Path(__file__).resolve().parents[1]

_PARENT = """
import subprocess, sys, time
from bttsim_stream.children import die_with_parent
pre = die_with_parent() if sys.argv[1] == "yes" else None
child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(300)"], preexec_fn=pre,
                         start_new_session=True)
print(child.pid, flush=True)
time.sleep(300)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux only")
@pytest.mark.parametrize("ask", ["yes", "no"], ids=["with die_with_parent", "without (the orphan lives on)"])
def test_a_child_ends_when_its_parent_is_killed(ask):
    parent = subprocess.Popen([sys.executable, "-c", _PARENT, ask], cwd=REPO, stdout=subprocess.PIPE, text=True)
    child = int(parent.stdout.readline())
    try:
        assert alive(child)
        parent.kill()
        parent.wait(timeout=30)
        deadline = time.monotonic() + (10 if ask == "yes" else 2)  # the signal comes in ms
        while alive(child) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert alive(child) is (ask == "no")
    finally:
        if parent.poll() is None:
            parent.kill()
            parent.wait()
        if alive(child):
            os.kill(child, signal.SIGKILL)


def test_die_with_parent_is_a_callable_on_linux():
    from bttsim_stream.children import die_with_parent

    pre = die_with_parent()
    assert (pre is not None) is sys.platform.startswith("linux")


def test_a_signal_asked_ignored_does_not_end_the_child_before_it_handles_it():
    """``bttsim run`` starts its nodes with the gone signal ignored: one that comes before a
    node has installed its handler (its default action is to terminate) is lost, not fatal;
    the node's own handler, once installed, still gets the next one."""
    from bttsim_stream.bus.session import GONE_SIGNAL
    from bttsim_stream.children import die_with_parent

    code = ("import signal, sys\n"
            "print(signal.getsignal(signal.SIGUSR1) == signal.SIG_IGN, flush=True)\n"
            "sys.stdin.readline()\n"  # the first signal comes meanwhile: ignored
            "got = []\n"
            "signal.signal(signal.SIGUSR1, lambda *a: got.append(1))\n"
            "print('handling', flush=True)\n"
            "import time\n"
            "while not got:\n"
            "    time.sleep(0.01)\n"
            "print('handled', flush=True)\n")
    child = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                             preexec_fn=die_with_parent(ignore=(GONE_SIGNAL,)))
    try:
        assert child.stdout.readline().strip() == "True"
        child.send_signal(GONE_SIGNAL)
        child.stdin.write("\n")
        child.stdin.flush()
        assert child.stdout.readline().strip() == "handling"
        child.send_signal(GONE_SIGNAL)
        assert child.stdout.readline().strip() == "handled"
        assert child.wait(30) == 0
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()

"""Child processes that end with their parent.

``bttsim run`` starts its nodes in their own sessions (``start_new_session``: Ctrl-C reaches
only the orchestrator, which stops them in order). Then nothing ends them if the orchestrator
itself is killed (SIGKILL, an OOM kill): a web viewer would serve forever. On Linux each child
therefore asks the kernel for a parent-death signal (``prctl(PR_SET_PDEATHSIG, SIGTERM)``)
between ``fork`` and ``exec``: SIGTERM, which every node handles like Ctrl-C (files
finalised, servers closed).

Notes
-----
The signal comes when the *thread* that forked the child ends, so children must be started
from a thread that lives as long as the parent (the main thread). On other systems
:func:`die_with_parent` returns None and children outlive a killed parent.
"""

from __future__ import annotations

import os
import signal
import sys
from collections.abc import Callable

__all__ = ["die_with_parent"]

_PR_SET_PDEATHSIG = 1


def die_with_parent(sig: int = signal.SIGTERM) -> Callable[[], None] | None:
    """A ``preexec_fn`` for :class:`subprocess.Popen`: the child gets ``sig`` when this
    process ends (Linux), or None where the kernel offers no such request.

    libc is loaded here, in the parent: a forked child of a threaded process must not
    ``dlopen``. If the parent already died before the request took effect, the child exits.
    """
    if not sys.platform.startswith("linux"):
        return None
    import ctypes

    prctl = ctypes.CDLL(None, use_errno=True).prctl
    parent = os.getpid()

    def preexec() -> None:
        if prctl(_PR_SET_PDEATHSIG, int(sig), 0, 0, 0) != 0:
            raise OSError(ctypes.get_errno(), "prctl(PR_SET_PDEATHSIG) failed")  # Popen raises it
        if os.getppid() != parent:  # the parent is gone already: the signal will never come
            os._exit(125)

    return preexec

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


def die_with_parent(sig: int = signal.SIGTERM, ignore: tuple = ()) -> Callable[[], None] | None:
    """A ``preexec_fn`` for :class:`subprocess.Popen`: the child gets ``sig`` when this
    process ends (Linux), or None where the kernel offers no such request (and nothing is
    to be ignored).

    ``ignore``: signals the child starts with ignored (an ignored signal stays ignored across
    ``exec``), for those a node handles once it is running and that must not end it before
    (their default action) -- e.g. :data:`~bttsim_stream.bus.session.GONE_SIGNAL`.

    libc is loaded here, in the parent: a forked child of a threaded process must not
    ``dlopen``. If the parent already died before the request took effect, the child exits.
    """
    ignored = tuple(int(s) for s in ignore)

    def ignore_them() -> None:
        for s in ignored:
            signal.signal(s, signal.SIG_IGN)

    if not sys.platform.startswith("linux"):
        return ignore_them if ignored else None
    import ctypes

    prctl = ctypes.CDLL(None, use_errno=True).prctl
    parent = os.getpid()

    def preexec() -> None:
        ignore_them()
        if prctl(_PR_SET_PDEATHSIG, int(sig), 0, 0, 0) != 0:
            raise OSError(ctypes.get_errno(), "prctl(PR_SET_PDEATHSIG) failed")  # Popen raises it
        if os.getppid() != parent:  # the parent is gone already: the signal will never come
            os._exit(125)

    return preexec

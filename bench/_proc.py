"""What the benchmarks read of a running ``bttsim run`` from ``/proc`` (Linux): its child
processes, which node each is, and its memory."""

from __future__ import annotations

import os
from pathlib import Path


def children(pid: int) -> list[int]:
    """The PIDs of ``pid``'s child processes (empty once it is gone)."""
    try:
        return [int(c) for t in os.listdir(f"/proc/{pid}/task")
                for c in Path(f"/proc/{pid}/task/{t}/children").read_text().split()]
    except OSError:
        return []


def node_name(pid: int) -> str | None:
    """The node a ``python -m bttsim_stream.nodes NAME`` process runs, None for another."""
    try:
        argv = [a.decode(errors="replace") for a in Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")]
    except OSError:
        return None
    if "bttsim_stream.nodes" in argv:
        i = argv.index("bttsim_stream.nodes")
        return argv[i + 1] if i + 1 < len(argv) else None
    return None


def memory_mb(pid: int, field: str = "VmRSS") -> float | None:
    """``field`` of ``/proc/PID/status`` (``VmRSS`` now, ``VmHWM`` its peak), MB."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None

"""Will the output fit? An estimate of a run's output size from its scenario, checked against
the free space before anything is written (``bttsim simulate``, ``bttsim run``; ``--force``
skips the check).

The estimate encodes the run's first revolutions (:class:`~bttsim_stream.acquisition.AcquisitionStream`:
the messages the simulator publishes), compresses them as the recorder's chunks are (zstd),
and scales the bytes per revolution to the run's revolution count. ``bttsim run`` writes more
than the acquisition: the processor's results (fits, travelling waves) and the views
(``views.rrd``) are counted as :data:`RUN_FACTOR` times the acquisition, a margin measured on
the example scenarios (results plus views stayed below the acquisition's size).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import zstandard

from .errors import BttsimError

__all__ = ["estimate_output_bytes", "check_free_space", "RUN_FACTOR", "SAMPLE_REVOLUTIONS"]

#: Revolutions encoded for the estimate.
SAMPLE_REVOLUTIONS = 32
#: ``bttsim run``'s output (recording with results, views) over the acquisition's size.
RUN_FACTOR = 2.0
#: Fixed overhead of a file (schemas, summary, index), bytes.
_OVERHEAD = 1 << 20


def estimate_output_bytes(scn, *, model=None, include_truth: bool = True, run: bool = False) -> int:
    """Estimated bytes written by ``simulate`` (``run`` False: the MCAP file) or by ``run``
    (the output folder) for scenario ``scn`` (``model``: its modal model, when already built)."""
    from .acquisition import AcquisitionStream  # the simulator: only when asked

    # in the simulator's own batches (as ``simulate`` runs it): a batch of SAMPLE_REVOLUTIONS
    # revolutions of 16 probes held 48 MB of crossings at once, more than the whole simulation
    acq = AcquisitionStream(scn, model, include_truth=include_truth, chunk_revolutions=None)
    n_rev = int(acq.info.n_revolutions)
    payload, revs = [], 0
    for batch, msgs in acq.batches():
        payload += [m.payload for m in msgs]
        revs += len(batch.revolution)
        if revs >= SAMPLE_REVOLUTIONS:
            break
    if revs == 0:
        return _OVERHEAD
    raw = b"".join(payload)
    packed = len(zstandard.ZstdCompressor().compress(raw)) + 31 * len(payload)  # message records
    total = packed / revs * n_rev + _OVERHEAD
    return int(total * (RUN_FACTOR if run else 1.0))


def _size(n: float) -> str:
    for unit in ("B", "KB", "MB", "GB", "TB"):
        if n < 1000 or unit == "TB":
            return f"{n:.3g} {unit}"
        n /= 1000
    return f"{n:.3g} TB"


def check_free_space(path, need_bytes: int, *, what: str) -> None:
    """Refuse (one line) when ``need_bytes`` exceed the free space where ``path`` goes.

    Raises
    ------
    BttsimError
        ``"WHAT would write about N GB to PATH, which has M GB free (--force: write anyway)"``.
    """
    p = Path(path).absolute()
    where = p
    while not where.exists() and where != where.parent:
        where = where.parent
    try:
        free = shutil.disk_usage(where).free
    except OSError:
        return  # nothing known: nothing refused
    if need_bytes > free:
        raise BttsimError(f"{what} would write about {_size(need_bytes)} to {p}, which has {_size(free)} free "
                          f"(--force: write anyway)")

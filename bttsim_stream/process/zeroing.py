"""The zeroing correction: the response a calibrated zeroing reference held, estimated from a
crossing's growth and added back (``docs/processing.md``, "Zeroing away from the resonances").

``ctx`` is the pipeline's processing context (its ``reference``, ``offset_removed``,
``crossings``, ``omega``, report ``fit``, ``tail_phasors`` and the ``corrections`` made).
"""

from __future__ import annotations

import math

import numpy as np

from .detect import Crossing, predicted_response
from .fit import quiet

__all__ = ["TAIL_LEVEL", "TAIL_BLOCK", "zeroing_correction", "tail_revolutions", "tail_gain", "correction_size"]

#: The zeroing correction fits the response's growth where the predicted response is at most
#: this fraction of the peak (the skirt between the reference and the crossing).
TAIL_LEVEL = 0.3

#: Revolutions of the skirt read at a time by :func:`tail_gain`: the skirt runs from the
#: reference to the crossing, as long as the run between them, and its responses are summed
#: block by block instead of read whole.
TAIL_BLOCK = 1 << 12


def zeroing_correction(ctx, c: Crossing, i: int) -> np.ndarray | None:
    """The response the zeroing reference held, per blade, to add back to the crossing's
    complex responses (None: not needed or not estimable).

    The reference subtracted the response ``P_ref`` it held from every revolution. Between
    the reference and the crossing the measured response is ``P(n) = K (h(n) - h_ref)``,
    ``h`` the crossing's predicted SDOF shape (:func:`~.detect.predicted_response`): a complex
    ``K`` per blade fitted there by least squares gives ``P_ref = K h_ref``. Only the growth
    law ``h`` is assumed, not the phase of the peak, so it also holds for a blade whose peak
    mixes several (mistuned) modes. When the data preparation removed a baseline fitted
    around the reference, that baseline took the reference's response already: no
    correction.
    """
    key = (c.eo, c.peak, i)
    if key not in ctx.corrections:  # one per crossing and order: its crossing and the dwells read it
        tail = tail_revolutions(ctx.reference, ctx.offset_removed, ctx.crossings, ctx.omega, c)
        if tail is None:
            ctx.corrections[key] = None
        else:
            h_ref, g, idx = tail
            read = ctx.fit.phasor_at if ctx.tail_phasors is None else ctx.tail_phasors
            ctx.corrections[key] = tail_gain(g, lambda rows: read(i, idx[rows])) * h_ref
    corr = ctx.corrections[key]
    return None if corr is None else corr.copy()


def tail_revolutions(ref, offset_removed: bool, crossings, omega: np.ndarray, c: Crossing):
    """``(h_ref, g, idx)`` of :func:`zeroing_correction` (None: no correction): the growth law
    at the reference, its rise ``g = h - h_ref`` over the skirt's revolutions ``idx`` (in
    revolution order), whose responses it reads. ``ref``: the zeroing reference;
    ``crossings``: every crossing of the run."""
    if ref is None or ref.start is None or offset_removed:
        return None
    same = [k for k in crossings if k.eo == c.eo]
    h = predicted_response(omega, same)
    h_ref = complex(np.mean(h[ref.start:ref.stop]))
    idx = np.arange(ref.start, c.peak) if ref.start < c.peak else np.arange(c.peak + 1, ref.stop)
    idx = idx[np.abs(h[idx]) <= TAIL_LEVEL]
    if idx.size < 16:
        return None
    return h_ref, h[idx] - h_ref, idx


def tail_gain(g: np.ndarray, P, block: int | None = None) -> np.ndarray:
    """Least-squares ``K`` per blade of ``P = K g`` (0 where no data).

    ``P``: the responses, shape ``(g.size, n_blades)``, or a function giving the rows of a
    slice of them, read ``block`` rows (default :data:`TAIL_BLOCK`) at a time. The sums over
    the rows go on from one block to the next in row order, the order numpy adds the rows of
    a whole array in (a sum along axis 0 adds row after row; a single column is summed
    pairwise, so one blade's responses are read at once): the same numbers as from the
    whole array."""
    read = P if callable(P) else P.__getitem__
    block = TAIL_BLOCK if block is None else int(block)
    n = int(g.size)
    first = read(slice(0, min(n, block)))
    if first.ndim != 2 or first.shape[1] < 2:
        block = max(n, 1)  # one column: numpy sums it pairwise, not row after row
        first = read(slice(0, n))
    w = num = None
    for a in range(0, max(n, 1), block):
        Pb = first if a == 0 else read(slice(a, min(a + block, n)))
        gb = g[a:a + block]  # (the products' loops, and so their rounding, follow the layout)
        ok = np.isfinite(Pb)
        wb = np.where(ok, np.abs(gb)[:, None] ** 2, 0.0)
        with np.errstate(all="ignore"):
            nb = np.where(ok, np.conj(gb)[:, None] * np.where(ok, Pb, 0.0), 0.0)
        if w is not None:  # the running sums as the first row: added on in row order
            wb, nb = np.concatenate([w[None], wb]), np.concatenate([num[None], nb])
        w, num = wb.sum(axis=0), nb.sum(axis=0)
    with np.errstate(all="ignore"):
        K = num / w
    return np.where(w > 0, K, 0.0)


def correction_size(corr, P) -> float:
    """Blade mean of ``|correction| / |peak response|`` (NaN: no correction)."""
    if corr is None:
        return math.nan
    with quiet():
        peak = np.nanmax(np.abs(P), axis=0)
        return float(np.nanmean(np.abs(corr) / peak))

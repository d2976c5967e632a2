"""The zeroing correction: the response a calibrated zeroing reference held, estimated from a
crossing's growth and added back (``docs/processing.md``, "Zeroing away from the resonances").

``ctx`` is the pipeline's processing context (its ``reference``, ``offset_removed``,
``crossings``, ``omega`` and report ``fit``).
"""

from __future__ import annotations

import math

import numpy as np

from .detect import Crossing, predicted_response
from .fit import quiet

__all__ = ["TAIL_LEVEL", "zeroing_correction", "zeroing_tail", "tail_revolutions", "tail_gain", "correction_size"]

#: The zeroing correction fits the response's growth where the predicted response is at most
#: this fraction of the peak (the skirt between the reference and the crossing).
TAIL_LEVEL = 0.3


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
    tail = zeroing_tail(ctx, c, i)
    if tail is None:
        return None
    h_ref, g, P = tail
    return tail_gain(g, P) * h_ref


def zeroing_tail(ctx, c: Crossing, i: int):
    """``(h_ref, g, P)`` of :func:`zeroing_correction` (None: no correction): the growth law
    at the reference, its rise ``g = h - h_ref`` over the skirt's revolutions (in revolution
    order) and the responses there."""
    tail = tail_revolutions(ctx.reference, ctx.offset_removed, ctx.crossings, ctx.omega, c)
    if tail is None:
        return None
    h_ref, g, idx = tail
    return h_ref, g, ctx.fit.phasor_at(i, idx)


def tail_revolutions(ref, offset_removed: bool, crossings, omega: np.ndarray, c: Crossing):
    """``(h_ref, g, idx)``: :func:`zeroing_tail` without the responses, ``idx`` the skirt's
    revolutions whose responses it reads (None: no correction). ``ref``: the zeroing
    reference; ``crossings``: every crossing of the run."""
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


def tail_gain(g: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Least-squares ``K`` per blade of ``P = K g`` (0 where no data)."""
    ok = np.isfinite(P)
    w = np.where(ok, np.abs(g)[:, None] ** 2, 0.0).sum(axis=0)
    with np.errstate(all="ignore"):
        K = np.where(ok, np.conj(g)[:, None] * np.where(ok, P, 0.0), 0.0).sum(axis=0) / w
    return np.where(w > 0, K, 0.0)


def correction_size(corr, P) -> float:
    """Blade mean of ``|correction| / |peak response|`` (NaN: no correction)."""
    if corr is None:
        return math.nan
    with quiet():
        peak = np.nanmax(np.abs(P), axis=0)
        return float(np.nanmean(np.abs(corr) / peak))

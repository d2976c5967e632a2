"""The processing flags shared by ``bttsim process`` and the processor node, and their checks.

Kept apart from :mod:`bttsim_stream.offline` (which reads recordings: the codec, MCAP, the
processing pipeline): every ``bttsim`` command builds the parsers of both users, and that
must not load what only processing needs.
"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from .errors import BttsimError, comma_values
from .process.methods import METHODS
from .process.probes import check_engine_orders

if TYPE_CHECKING:
    from .process.options import ProcessOptions

__all__ = ["add_processing_arguments", "processing_options", "parse_engine_orders"]


def add_processing_arguments(p: argparse.ArgumentParser) -> None:
    """The processing flags shared by ``bttsim process`` and the processor node."""
    p.add_argument("--method", choices=METHODS, default="peak",
                   help="resonance method: peak (per-revolution sine-fit peak, the paper's), sdof (swept "
                        "single-degree-of-freedom fit of amplitude and phase: frequency, damping, amplitude, "
                        "sweep-corrected) or cff (circumferential Fourier fit over a few revolutions)")
    p.add_argument("--eo", metavar="EO[,EO...]", help="engine orders to fit (default: the run metadata's)")
    p.add_argument("--eo-range", metavar="LO-HI",
                   help="engine order unknown: scan LO..HI for resonance crossings (each order fitted on its own)")
    p.add_argument("--no-prep", action="store_true", help="no data preparation")
    p.add_argument("--window", type=int, default=1, metavar="N", help="revolutions per sine fit (1)")


def processing_options(args: argparse.Namespace, **extra) -> ProcessOptions:
    """:class:`ProcessOptions` from the flags of :func:`add_processing_arguments` (``extra``:
    further options); a bad value is a :class:`BttsimError`."""
    eos = parse_engine_orders(args.eo) if getattr(args, "eo", None) else None
    eo_range = _eo_range(args.eo_range) if getattr(args, "eo_range", None) else None
    if eos is not None and eo_range is not None:
        raise BttsimError("give --eo (the orders to fit) or --eo-range (a scan), not both")
    from .process.options import ProcessOptions  # the processing's own modules: only once it runs

    try:
        return ProcessOptions(prep=not args.no_prep, window=args.window, method=args.method, engine_orders=eos,
                              eo_range=eo_range, **extra)
    except ValueError as exc:
        raise BttsimError(str(exc)) from None


def _eo_range(text: str) -> tuple:
    parts = str(text).replace(":", "-").split("-")
    try:
        lo, hi = (int(x) for x in parts)
    except ValueError:
        raise BttsimError(f"--eo-range must be LO-HI (whole numbers), got {text!r}") from None
    if lo < 1 or hi < lo:
        raise BttsimError(f"--eo-range must satisfy 1 <= LO <= HI, got {text!r}")
    return lo, hi


def parse_engine_orders(text: str) -> tuple:
    """``--eo 8`` or ``--eo 8,9``: the engine orders, checked (:class:`BttsimError` otherwise)."""
    vals = comma_values(text, int, "--eo", "comma-separated whole numbers")
    twice = sorted({v for v in vals if vals.count(v) > 1})
    if twice:  # a fit of one order twice is singular
        raise BttsimError(f"--eo: engine order {twice[0]} given twice")
    return check_engine_orders(vals)

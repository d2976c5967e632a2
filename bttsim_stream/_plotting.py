"""matplotlib, the optional ``plot`` extra: imported on demand, a one-line error when missing."""

from __future__ import annotations

from .errors import BttsimError

__all__ = ["INSTALL_HINT", "PlotExtraMissing", "pyplot"]

INSTALL_HINT = "pip install 'bttsim-stream[plot]'"


class PlotExtraMissing(BttsimError):
    """matplotlib (the ``plot`` extra) is not installed."""


def pyplot(what: str):
    """``matplotlib.pyplot`` with the non-interactive Agg backend.

    Parameters
    ----------
    what : str
        What needs the plot, for the error message (e.g. ``"the model plot"``).

    Returns
    -------
    module
        ``matplotlib.pyplot``.

    Raises
    ------
    PlotExtraMissing
        matplotlib is not installed: ``"<what> needs matplotlib: pip install 'bttsim-stream[plot]'"``.
    """
    try:
        import matplotlib
    except ImportError:
        raise PlotExtraMissing(f"{what} needs matplotlib: {INSTALL_HINT}") from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt

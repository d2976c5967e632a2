"""The summary JSON, assembled in one place for ``bttsim run`` (the processor node),
``bttsim process`` and the run's recording verdict.

* :func:`build_summary` -- the processing result with what it rests on (completeness, missing
  TOAs, double pulses), the same keys in the same order live and offline.
* :func:`recording_block` and :func:`with_recording` -- ``bttsim run``'s ``recording`` block
  from the recorder's final statistics; the run is ``complete`` only with a complete recording.
* :func:`no_report_summary` -- what a run whose processor ended without a report says.
"""

from __future__ import annotations

import shlex
import signal
from pathlib import Path

from .bus.stream import Completeness

__all__ = ["build_summary", "recording_block", "with_recording", "no_report_summary", "describe_exit"]


def build_summary(result: dict, completeness: Completeness, *, missing_toas: int, doubles: dict) -> dict:
    """The summary dict (the brief's form) of a processing result.

    Parameters
    ----------
    result : dict
        The processing pipeline's summary (resonances, dwells, blades, errors).
    completeness : Completeness
        What of the run the result rests on.
    missing_toas : int
        TOAs received as NaN (pulses that did not trigger).
    doubles : dict
        Extra trigger edges (``DoublePulses.to_summary()``).
    """
    summary = dict(result, **completeness.to_summary())
    summary["missing_toas"] = int(missing_toas)
    summary.update(doubles)
    return summary


def recording_block(stats: dict) -> dict:
    """The summary's ``recording`` block from the recorder's final statistics (its status):
    ``complete``, ``missing`` (messages), ``missing_by_key`` (``{key: {"head", "gaps", "tail"}}``),
    ``messages``, ``duplicates``, ``rejected`` and ``incomplete`` (why, "" if complete)."""
    if "complete" not in stats:
        return {"complete": False, "missing": None, "missing_by_key": {}, "messages": stats.get("messages"),
                "duplicates": None, "rejected": None,
                "incomplete": "the recorder gave no completeness statistics (see recorder.log)"}
    return {"complete": bool(stats["complete"]), "missing": stats.get("missing"),
            "missing_by_key": stats.get("missing_by_key", {}), "messages": stats.get("messages"),
            "duplicates": stats.get("duplicates_skipped"), "rejected": stats.get("rejected"),
            "incomplete": stats.get("incomplete", "")}


def with_recording(summary: dict, recorder_stats: dict) -> dict:
    """``summary`` with its ``recording`` block; ``complete`` only if the result and the
    recording both are (the result's own verdict is ``summary["complete"]`` before)."""
    out = dict(summary)
    out["recording"] = recording_block(recorder_stats)
    out["complete"] = bool(summary.get("complete", False)) and out["recording"]["complete"]
    return out


def describe_exit(returncode: int) -> str:
    """``"exit 1"`` or ``"killed by SIGKILL"``."""
    if returncode < 0:
        try:
            return f"killed by {signal.Signals(-returncode).name}"
        except ValueError:
            return f"killed by signal {-returncode}"
    return f"exit {returncode}"


def no_report_summary(n_revolutions: int, returncode: int, mcap: Path | str) -> dict:
    """The summary of a run whose processor ended without its report: nothing claimed; the
    error names the command that processes the recording ``mcap`` (the path as given)."""
    return {"status": "none", "complete": False, "revolutions_expected": int(n_revolutions),
            "revolutions_processed": 0, "lost": None, "duplicates": None, "rejected": None,
            "resonances": [], "steady": [], "blades": [],
            "error": f"the processor ended ({describe_exit(returncode)}) before its report; "
                     f"the recording may still hold the run: bttsim process {shlex.quote(str(mcap))}"}

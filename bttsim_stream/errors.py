"""User-facing errors: the CLI prints them as one line and exits with status 2."""

from __future__ import annotations

__all__ = ["BttsimError", "ScenarioError", "ModelFileError"]


class BttsimError(Exception):
    """An error caused by the user's input (file, parameter), reported without a traceback."""


class ScenarioError(BttsimError):
    """A scenario file is missing, malformed, or holds an impossible value."""


class ModelFileError(BttsimError):
    """A modal model file is missing, corrupt, pickled, or inconsistent."""

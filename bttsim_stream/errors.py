"""User-facing errors: the CLI prints them as one line and exits with status 2."""

from __future__ import annotations

import errno
import os
import stat
import sys
from pathlib import Path

__all__ = ["BttsimError", "ScenarioError", "ModelFileError", "exit_status", "replaceable_file", "comma_values"]


class BttsimError(Exception):
    """An error caused by the user's input (file, parameter), reported without a traceback."""


class ScenarioError(BttsimError):
    """A scenario file is missing, malformed, or holds an impossible value."""


class ModelFileError(BttsimError):
    """A modal model file is missing, corrupt, pickled, or inconsistent."""


def replaceable_file(path, flag: str = "--out") -> Path:
    """The file an output written through a temporary file and a rename replaces: ``path``
    itself, or what its symbolic link points to (the link stays). A folder, or an existing
    device, pipe or socket (a rename would put a regular file in its place), is a
    :class:`BttsimError` naming ``flag``."""
    path = Path(path)
    if not str(path).strip() or path.name in ("", ".", ".."):
        raise BttsimError(f"{flag} {path}: names a folder, not a file")
    target = Path(os.path.realpath(path))
    try:
        mode = os.stat(target).st_mode
    except OSError:
        return target  # not there yet (or not readable: the write says why)
    if stat.S_ISDIR(mode):
        raise BttsimError(f"{flag} {path}: is a folder, not a file")
    if not stat.S_ISREG(mode):
        raise BttsimError(f"{flag} {path}: is not a regular file (a device, pipe or socket); it would be "
                          "replaced by one")
    return target


#: File-system errors that are the environment's, not a bug: a full disk, no permission, a
#: read-only file system, a missing folder... (one line, status 2, like bad input).
_FILE_ERRNOS = frozenset((errno.ENOSPC, errno.EDQUOT, errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOENT,
                          errno.ENOTDIR, errno.EISDIR, errno.EFBIG, errno.EEXIST, errno.EIO))


def comma_values(text, convert, what: str, expected: str) -> list:
    """The comma-separated values of an option, each converted (``int``, ``float``); an empty
    item (``8,,9``, ``,8``, a trailing comma) or one that does not convert is a one-line error
    ``{what} must be {expected}, got '...'``."""
    items = str(text).split(",")
    try:
        if any(not x.strip() for x in items):
            raise ValueError
        return [convert(x) for x in items]
    except ValueError:
        raise BttsimError(f"{what} must be {expected}, got {text!r}") from None


def exit_status(fn, *args) -> int:
    """Run ``fn(*args)`` for a program: its return value if that is an int (an exit status),
    else 0; a
    :class:`BttsimError`, or a file-system error of the environment (a full disk, no
    permission), or running out of memory, becomes one line ``bttsim: error: ...`` on stderr and status 2;
    Ctrl-C status 130, a closed output pipe 141 (no traceback)."""
    try:
        status = fn(*args)
    except BttsimError as exc:
        print(f"bttsim: error: {exc}", file=sys.stderr)
        return 2
    except MemoryError as exc:  # an input asking for more than the machine has (a run of 1e9 s)
        text = " ".join(str(exc).split())[:200]
        print(f"bttsim: error: out of memory{': ' + text if text else ''}: the input asks for more than this "
              "machine has", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # ``bttsim process F.mcap | head``: the reader has all it wanted
        _quiet_stdout()
        return 141  # as a shell tool killed by SIGPIPE
    except OSError as exc:
        if exc.errno not in _FILE_ERRNOS:
            raise
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"bttsim: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return 2
    return status if isinstance(status, int) and not isinstance(status, bool) else 0


def _quiet_stdout() -> None:
    """Point stdout at /dev/null: Python's flush at exit would fail on the closed pipe again."""
    import os

    try:
        fd = os.open(os.devnull, os.O_WRONLY)
        os.dup2(fd, sys.stdout.fileno())
        os.close(fd)
    except (OSError, ValueError):
        pass

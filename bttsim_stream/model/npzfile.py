"""Reading a user's ``.npz`` archive (a modal model file, a cyclic sector file) safely.

``np.load(path, allow_pickle=False)`` on a damaged or forged file raises anything from
``zipfile.BadZipFile`` to ``MemoryError`` (a ``.npy`` header may declare any shape), or calls a
text file "pickled". :func:`read_npz` checks the file before numpy decodes it: a zip archive,
at most :data:`MAX_NPZ_BYTES` on disk and unpacked, every member a ``.npy`` array whose header
declares no more bytes than the member holds and no object (pickled) data; any problem is one
line naming the file (:class:`~bttsim_stream.errors.ModelFileError`).
"""

from __future__ import annotations

import math
import zipfile
import zlib
from pathlib import Path

import numpy as np

from ..errors import ModelFileError

__all__ = ["MAX_NPZ_BYTES", "read_npz"]

#: Largest ``.npz`` file read, on disk and unpacked (the sum of its members' declared sizes).
MAX_NPZ_BYTES = 2 * 1024**3

#: Errors numpy and zipfile raise on a damaged archive (truncated, bad CRC, bad header).
_CORRUPT = (OSError, zipfile.BadZipFile, EOFError, KeyError, RuntimeError, NotImplementedError, zlib.error,
            UnicodeDecodeError, ValueError, OverflowError)


def _check_member(zf: zipfile.ZipFile, info: zipfile.ZipInfo, path: Path) -> None:
    """The ``.npy`` header of ``info``: no object data, and no more bytes declared than held."""
    with zf.open(info) as fp:
        version = np.lib.format.read_magic(fp)
        if version == (1, 0):
            shape, _, dtype = np.lib.format.read_array_header_1_0(fp)
        elif version == (2, 0):
            shape, _, dtype = np.lib.format.read_array_header_2_0(fp)
        else:
            raise ModelFileError(f"{path}: {info.filename}: .npy format version {version} is not read")
        header = fp.tell()
    if dtype.hasobject:
        raise ModelFileError(f"{path}: holds pickled objects, which are refused")
    if any(n < 0 for n in shape):
        raise ModelFileError(f"{path}: {info.filename}: corrupt .npy header (shape {shape})")
    need = math.prod(shape) * dtype.itemsize
    if need > info.file_size - header:
        raise ModelFileError(f"{path}: {info.filename} declares {shape} {dtype} ({need} bytes) but holds "
                             f"{info.file_size - header}: truncated or forged")


def read_npz(path, what: str = "model file") -> dict:
    """Every array of an ``.npz`` archive, read with ``allow_pickle=False`` after size checks.

    Parameters
    ----------
    path : str or Path
    what : str
        What the file should be, for the messages (``"model file"``, ``"sector file"``).

    Returns
    -------
    dict of str -> ndarray
        The archive's arrays by name (the member names without ``.npy``).

    Raises
    ------
    ModelFileError
        One line naming the file: missing, not a file, not a zip archive, larger than
        :data:`MAX_NPZ_BYTES` (on disk or unpacked), a member that is not a ``.npy`` array or
        declares more data than it holds, pickled (object) data, truncated or corrupt (a bad
        CRC, a damaged header).
    """
    path = Path(path)
    if not path.exists():
        raise ModelFileError(f"{path}: no such file")
    if not path.is_file():
        raise ModelFileError(f"{path}: not a file")
    if path.stat().st_size > MAX_NPZ_BYTES:
        raise ModelFileError(f"{path}: larger than {MAX_NPZ_BYTES} bytes, refusing to load")
    with open(path, "rb") as f:
        if f.read(4) != b"PK\x03\x04":  # numpy would call any other file pickled
            raise ModelFileError(f"{path}: not an .npz archive (a {what} is numpy's .npz, a zip)")
    arrays: dict = {}
    try:
        with np.load(path, allow_pickle=False) as z:
            infos = z.zip.infolist()
            unpacked = sum(info.file_size for info in infos)
            if unpacked > MAX_NPZ_BYTES:  # a compressed archive may unpack to far more than its size
                raise ModelFileError(f"{path}: unpacks to {unpacked} bytes, more than {MAX_NPZ_BYTES}, "
                                     "refusing to load")
            for info in infos:
                if not info.filename.endswith(".npy"):
                    raise ModelFileError(f"{path}: member {info.filename!r} is not a .npy array: not a {what}")
                _check_member(z.zip, info, path)
            for name in z.files:
                arrays[name] = z[name]
    except ModelFileError:
        raise
    except _CORRUPT as exc:
        text = str(exc).splitlines()[0] if str(exc) else "unreadable"
        if isinstance(exc, ValueError) and "pickle" in text.lower():
            raise ModelFileError(f"{path}: holds pickled objects, which are refused") from None
        raise ModelFileError(f"{path}: corrupt or truncated {what} ({type(exc).__name__}: {text[:200]})") from None
    return arrays

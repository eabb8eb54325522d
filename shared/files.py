"""Files written whole or not at all, and read back checked: HDF5 with checksums, JSON.

A file is written under a temporary name in its own directory
(``.NAME.partial-PID``), flushed to disk, renamed over the target, and the
directory entry flushed too (POSIX: a rename is data of the directory): a
crash at any moment, even SIGKILL or a power cut, leaves the previous file or
the complete new one, never a half-written one. Every HDF5 dataset written
here carries the SHA-256 of its content (:func:`~.checksum.array_digest`) in
its ``sha256`` attribute. The campaign store and the artifact writer both
write through :func:`write_hdf5_atomically`. numpy and h5py only.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from hapticrom.shared.checksum import array_digest
from hapticrom.shared.errors import InputError

PARTIAL_MARK = ".partial-"  # in the name of every file not yet complete


def partial_path(path: Path) -> Path:
    """The temporary name ``path`` is written under before the rename (same directory)."""
    return path.with_name(f".{path.name}{PARTIAL_MARK}{os.getpid()}")


def fsync_directory(directory: Path) -> None:
    """Flush a directory's entries to disk (makes a rename inside it durable)."""
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def replace_durably(tmp: Path, path: Path) -> None:
    """Flush ``tmp`` to disk, rename it to ``path``, flush the directory."""
    with open(tmp, "rb") as f:
        os.fsync(f.fileno())
    os.replace(tmp, path)
    fsync_directory(path.parent)


def write_text_atomically(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file and a durable rename."""
    tmp = partial_path(path)
    try:
        tmp.write_text(text)
        replace_durably(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_hdf5_atomically(
    path: Path,
    fill: Callable[[h5py.File], None],
    check: Callable[[Path], None] | None = None,
    **file_options: Any,
) -> None:
    """Write the HDF5 file ``path``: ``fill(f)`` writes its content into the temporary file,
    ``check(tmp)`` (if given) runs on the closed temporary file before the rename.

    ``file_options`` go to ``h5py.File`` (e.g. ``userblock_size``). On any failure
    nothing is left behind and ``path`` is unchanged; the exception propagates.
    """
    tmp = partial_path(path)
    try:
        with h5py.File(tmp, "w", **file_options) as f:
            fill(f)
        if check is not None:
            check(tmp)
        replace_durably(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_checksummed(group: h5py.Group, name: str, array, attrs: dict | None = None):
    """Create dataset ``name`` in ``group`` holding ``array``, with ``attrs`` and its SHA-256."""
    array = np.asarray(array)
    dset = group.create_dataset(name, data=array)
    for key, value in (attrs or {}).items():
        dset.attrs[key] = value
    dset.attrs["sha256"] = array_digest(array)
    return dset


def read_versioned_json(path: Path, format_name: str, version: int, kind: str) -> dict:
    """The JSON object in ``path`` whose ``format`` is ``format_name`` and ``version`` is
    ``version``; InputError naming the file if it cannot be read, is not JSON, or is
    another format or version. ``kind``: what the file is, for the messages ("manifest")."""
    try:
        data = json.loads(path.read_bytes().decode("utf-8"))
    except OSError as exc:
        raise InputError(f"{path} cannot be read ({exc.strerror or exc})") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{path} is damaged: not valid JSON ({exc})") from None
    if not isinstance(data, dict) or data.get("format") != format_name:
        raise InputError(f"{path} is not a {format_name} {kind}")
    if data.get("version") != version:
        raise InputError(
            f"{path}: {format_name} {kind} version {data.get('version')!r} is not supported "
            f"(this hapticrom reads version {version})"
        )
    return data

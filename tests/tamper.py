"""Tools of an adversary who can edit an artifact and recompute every checksum.

The whole-file envelope and the per-dataset digests detect damage, not intent:
these helpers change a file with h5py and then recompute what the reader
verifies, so a test can reach the reader's value and structure checks.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import h5py
import numpy as np

from hapticrom.shared.checksum import array_digest
from hapticrom.shared.envelope import seal


def copy(src: Path, tmp_path: Path, name: str = "model.h5") -> Path:
    dst = tmp_path / name
    shutil.copyfile(src, dst)
    return dst


def rewrite(path: Path, name: str, change) -> None:
    """Replace dataset ``name`` (e.g. "samples/force") by ``change(values)``, re-digested."""
    with h5py.File(path, "r+") as f:
        old = f[name]
        units = old.attrs["units"]
        values = np.array(old[()])
        new = np.asarray(change(values) if callable(change) else change)
        if new is None:
            new = values
        parent = old.parent
        key = name.rsplit("/", 1)[-1]
        del parent[key]
        dset = parent.create_dataset(key, data=new)
        dset.attrs["units"] = units
        dset.attrs["sha256"] = array_digest(new)
    seal(path)


def mutate(path: Path, edit) -> None:
    """Call ``edit(f)`` on the open file (h5py, r+), then re-seal it."""
    with h5py.File(path, "r+") as f:
        edit(f)
    seal(path)


def set_attribute(path: Path, obj: str, key: str, value) -> None:
    mutate(path, lambda f: f[obj].attrs.__setitem__(key, value))

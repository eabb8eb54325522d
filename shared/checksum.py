"""Checksums of arrays, so a reader can tell a damaged dataset from a valid one.

The digest covers the dtype, the shape and the bytes in C order; two arrays
have the same digest exactly when they are equal element by element (and of
the same dtype and shape).
"""

from __future__ import annotations

import hashlib

import numpy as np

ALGORITHM = "sha256"


def array_digest(array) -> str:
    """Hex SHA-256 of dtype, shape and C-ordered bytes of ``array``."""
    a = np.ascontiguousarray(array)
    h = hashlib.sha256()
    h.update(a.dtype.str.encode())
    h.update(str(a.shape).encode())
    h.update(a.tobytes())
    return h.hexdigest()


def file_digest(path, chunk: int = 1 << 20) -> str:
    """Hex SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()

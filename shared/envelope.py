"""The artifact's integrity envelope: a whole-file digest in the HDF5 user block.

An HDF5 file may begin with a user block that the HDF5 library skips (the
superblock is searched at offsets 0, 512, 1024, ...). The writer reserves
:data:`USERBLOCK` bytes there and, once the HDF5 content is complete, writes a
short ASCII header into them::

    hapticrom-envelope 1
    bytes <size of the whole file>
    sha256 <SHA-256 of every byte after the user block>

followed by zero bytes up to the end of the block. :func:`read_verified` checks
the header, the file size and the digest with plain Python before any HDF5
code sees the file, and returns the verified bytes, which the reader then
parses from memory (never from the path again: what was verified is what is
parsed). A flipped, truncated or appended byte anywhere in the file therefore
never reaches h5py's C code.

The digest detects damage, not intent: anyone can recompute it. A file with a
valid envelope is still checked field by field (see ``artifact_rules``).
numpy-free, h5py-free.
"""

from __future__ import annotations

import hashlib
import os
import re
import stat
from pathlib import Path

from hapticrom.shared.errors import ArtifactError

USERBLOCK = 512
MAGIC = b"hapticrom-envelope 1\n"
# 2 GiB: far above any reduced model (the demo is 33 MB); the reader holds the file in memory.
MAX_BYTES = 1 << 31
_HEADER = re.compile(rb"hapticrom-envelope 1\nbytes ([1-9][0-9]{0,15})\nsha256 ([0-9a-f]{64})\n")
_CHUNK = 1 << 22
_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


def seal(path: str | Path) -> None:
    """Write the envelope header of the HDF5 file at ``path`` (``userblock_size=USERBLOCK``).

    Also what a test uses to re-seal a file it altered on purpose.
    """
    path = Path(path)
    size = path.stat().st_size
    with open(path, "r+b") as fh:
        block = fh.read(USERBLOCK + len(_HDF5_SIGNATURE))
        if block[USERBLOCK:] != _HDF5_SIGNATURE or (
            any(block[:USERBLOCK]) and not block.startswith(MAGIC)
        ):
            raise ArtifactError(f"{path}: not an HDF5 file with a free {USERBLOCK}-byte user block")
        digest = _digest_after_userblock(fh)
        header = MAGIC + b"bytes %d\nsha256 %s\n" % (size, digest.encode())
        fh.seek(0)
        fh.write(header.ljust(USERBLOCK, b"\0"))
        fh.flush()
        os.fsync(fh.fileno())


def _digest_after_userblock(fh) -> str:
    h = hashlib.sha256()
    fh.seek(USERBLOCK)
    while block := fh.read(_CHUNK):
        h.update(block)
    return h.hexdigest()


def read_verified(path: str | Path, max_bytes: int = MAX_BYTES) -> bytes:
    """The bytes of the artifact at ``path`` once its envelope checks out.

    Refuses (``ArtifactError``, naming the problem) anything that is not a
    regular file (a FIFO, a device, a directory), a file larger than
    ``max_bytes``, a missing or malformed header, a size or digest mismatch.
    """
    path = Path(path)
    try:
        info = os.stat(path)
    except FileNotFoundError:
        raise ArtifactError(f"artifact {path} not found") from None
    except OSError as exc:
        raise ArtifactError(f"artifact {path} cannot be read: {exc.strerror}") from None
    if not stat.S_ISREG(info.st_mode):
        raise ArtifactError(f"artifact {path} is not a regular file")
    if info.st_size > max_bytes:
        raise ArtifactError(f"artifact {path} has {info.st_size} bytes, over the {max_bytes} limit")
    try:
        with open(path, "rb") as fh:
            header = fh.read(USERBLOCK)
            _check_header(header, path, info.st_size)  # before reading the rest
            data = header + fh.read(info.st_size - USERBLOCK + 1)  # one more: a file that grew
    except OSError as exc:
        raise ArtifactError(f"artifact {path} cannot be read: {exc.strerror}") from None
    except MemoryError:
        raise ArtifactError(f"artifact {path}: no memory for its {info.st_size} bytes") from None
    _check_envelope(data, path)
    return data


def _check_header(block: bytes, path: Path, size: int) -> None:
    """The user block's header, and the file's size against it."""
    if not block.startswith(MAGIC):
        if block[:8] == _HDF5_SIGNATURE:
            raise ArtifactError(
                f"{path} has no integrity envelope: it was written before artifact format 1.4 "
                "(or is not a hapticrom artifact); re-reduce it with "
                "`hapticrom reduce CAMPAIGN_DIR --out MODEL.h5`"
            )
        raise ArtifactError(f"{path} is not a hapticrom artifact (no envelope header)")
    match = _HEADER.match(block)
    if match is None or len(block) != USERBLOCK or any(block[match.end() :]):
        raise ArtifactError(f"{path}: the envelope header is damaged")
    if int(match.group(1)) != size:
        raise ArtifactError(
            f"{path} has {size} bytes, its envelope says {int(match.group(1))} "
            "(truncated or appended to)"
        )


def _check_envelope(data: bytes, path: Path) -> None:
    """The size read and the digest of everything after the user block."""
    _check_header(data[:USERBLOCK], path, len(data))
    match = _HEADER.match(data)
    if hashlib.sha256(memoryview(data)[USERBLOCK:]).hexdigest() != match.group(2).decode():
        raise ArtifactError(f"{path} fails its whole-file checksum (damaged)")

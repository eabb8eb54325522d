"""Drop the runtime's on-disk numba cache when any of the runtime's sources changed.

numba checks a cached kernel against the source file that defines it, and only that
file. The kernels here call kernels of other modules, which numba compiles into the
caller: a ``proxy.step_position`` cached before ``kernels.py`` changed would go on running
the old ``kernels`` code, reading a state buffer whose layout may have changed (measured:
a stale cache ran a 2.7 us step where the current code takes 0.08 us, and with wrong
offsets it can read past the buffer). A pip upgrade rewrites every file, so this matters
after editing or checking out some of them: on import, the package compares a digest of
all its sources with the one stored beside the cache and, if they differ, deletes the
cache files of this source directory before any kernel is compiled or loaded. The shared
layouts the kernels compile in (``COMPILED_IN``) count as sources.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

STAMP = "hapticrom-sources.sha256"
HERE = Path(__file__).resolve().parent
# shared modules whose constants the kernels compile in (numba freezes a global's value)
COMPILED_IN = (HERE.parent / "shared" / "material_layout.py",)


def sources_digest(directory: Path = HERE, compiled_in: tuple[Path, ...] = COMPILED_IN) -> str:
    """sha256 over the names and contents of the ``*.py`` files of ``directory`` and of
    the ``compiled_in`` files."""
    digest = hashlib.sha256()
    for path in [*sorted(directory.glob("*.py")), *compiled_in]:
        digest.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()


def cache_directory(source: Path = HERE / "kernels.py") -> Path | None:
    """Where numba caches the kernels of ``source``'s directory, found as numba finds it
    (its locators in order: NUMBA_CACHE_DIR, __pycache__, the user's cache); None if numba
    would not cache them or its internals differ from those of numba 0.6x."""
    try:
        from numba.core.caching import CacheImpl

        def probe():  # a locator reads the line a function starts at; any function will do
            pass

        for locator_class in CacheImpl._locator_classes:
            locator = locator_class.from_function(probe, str(source))
            if locator is not None:
                return Path(locator.get_cache_path())
    except (ImportError, AttributeError, TypeError):
        return None
    return None


def drop_if_stale(cache: Path | None = None, directory: Path = HERE) -> bool:
    """Delete the numba cache files (``*.nbi``, ``*.nbc``) in ``cache`` unless the stamp
    there matches the sources of ``directory``; then write the stamp. True if dropped."""
    cache = cache_directory() if cache is None else cache
    if cache is None:
        return False
    digest = sources_digest(directory)
    stamp = cache / STAMP
    try:
        if stamp.read_text() == digest:
            return False
    except OSError:
        pass
    for path in (*cache.glob("*.nbi"), *cache.glob("*.nbc")):
        try:
            path.unlink()
        except OSError:  # another process dropped it first, or a read-only cache
            pass
    try:
        cache.mkdir(parents=True, exist_ok=True)
        temporary = cache / f"{STAMP}.{os.getpid()}"
        temporary.write_text(digest)
        temporary.replace(stamp)
    except OSError:
        pass
    return True

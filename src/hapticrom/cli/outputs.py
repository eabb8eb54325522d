"""Output locations, checked before any expensive work: a mistake is one line, not a lost run."""

from __future__ import annotations

import os
from pathlib import Path

from hapticrom.cli.console import rank
from hapticrom.shared.errors import HapticromError


def check_writable(
    directory: Path, label: str, error: type[HapticromError] = HapticromError
) -> None:
    """``error`` unless a file can be created in ``directory`` (a probe, removed)."""
    probe = directory / f".hapticrom-probe-{rank()}-{os.getpid()}"
    try:
        os.close(os.open(probe, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600))
        probe.unlink()
    except OSError as exc:
        raise error(f"{label}: cannot write in {directory} ({exc.strerror or exc})") from None


def check_out_file(path: str | Path, label: str, make_parents: bool = False) -> Path:
    """An output file: not a directory, in an existing (or creatable) writable directory."""
    out = Path(path)
    if out.is_dir():
        # The example keeps the kind of file asked for (a .msh, .json, ...): a directory named
        # like a file was meant as one.
        example = f"{out.stem}{out.suffix}" if out.suffix else "model.h5"
        raise HapticromError(f"{label} is a directory; give a file name, e.g. {out / example}")
    if make_parents:
        check_ancestor(out.parent, label)
        return out
    if not out.parent.is_dir():
        missing = "is not a directory" if out.parent.exists() else "does not exist"
        raise HapticromError(f"{label}: directory {out.parent} {missing}")
    check_writable(out.parent, label)
    return out


def check_out_dir(path: str | Path, label: str) -> Path:
    """An output directory: an existing one, or one that can be created; writable."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise HapticromError(f"{label} exists and is not a directory")
    check_ancestor(out, label)
    return out


def check_ancestor(path: Path, label: str) -> None:
    """The nearest existing ancestor of ``path`` (or itself) is a writable directory."""
    existing = path
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise HapticromError(f"{label}: {existing} is not a directory")
    check_writable(existing, label)


def check_campaign_dir(path: str | Path, label: str, restart: bool) -> Path:
    """A campaign directory to write: as :func:`check_out_dir`; a manifest it holds is read."""
    out = check_out_dir(path, label)
    from hapticrom.offline.campaign.store import SnapshotStore

    store = SnapshotStore(out)
    if store.manifest_path.exists() and not restart:
        store.manifest()  # InputError if damaged: before any solve
    return out

"""The on-disk snapshot store of a training campaign: crash-safe and rank-independent.

Layout of a campaign directory::

    manifest.json           what this campaign is (its hash), the tool positions
    operators.h5            K0 (canonical CSR, N/mm), the mixed tangent blocks Kuu, Kup,
                            Kpp_diagonal, lumped volumes (mm^3), node coordinates
    solves/position-0007.h5 one file per tool position: the whole load path (displacement
                            and element-wise pressure snapshots, forces, contact nodes)

Every file is written under a temporary name in the same directory, flushed
to disk, then renamed (``hapticrom.shared.files``, as the artifact): a crash
(even SIGKILL) at any moment leaves either the complete file or none, never a
half-written one that reads as valid. Every dataset carries its SHA-256
(``hapticrom.shared.checksum``), verified on read.
All arrays are in the canonical DOF order of :mod:`hapticrom.offline.fe.dofs`, so
campaigns run on different numbers of ranks store the same data.

A rerun of the same campaign in the same directory resumes: positions whose
file exists, passes its checksums and records a converged solve are not solved
again; a damaged file (a bit flip, an unreadable file) or a failed solve is
solved again (:meth:`SnapshotStore.audit`). A directory holding a different
campaign (another configuration or mesh) is refused.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import scipy.sparse

from hapticrom.shared.checksum import array_digest
from hapticrom.shared.errors import InputError
from hapticrom.shared.files import (
    PARTIAL_MARK,
    read_versioned_json,
    write_checksummed,
    write_hdf5_atomically,
    write_text_atomically,
)

FORMAT = "hapticrom-campaign"
VERSION = 2  # 2: pressure snapshots and the mixed tangent blocks
MESH_KEYS = ("file", "sha256")


def write_h5(path: Path, datasets: dict[str, np.ndarray], attrs: dict[str, Any]) -> None:
    """Write datasets (with checksums) and attributes to ``path`` atomically."""

    def fill(f: h5py.File) -> None:
        for key, value in attrs.items():
            f.attrs[key] = value
        for name, array in datasets.items():
            write_checksummed(f, name, array)
        f.attrs["complete"] = True

    write_hdf5_atomically(path, fill)


def read_h5(path: Path) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Read every dataset of ``path`` and verify its checksum; InputError if damaged."""
    try:
        with h5py.File(path, "r") as f:
            if not f.attrs.get("complete", False):
                raise InputError(f"{path} is incomplete")
            attrs = dict(f.attrs)
            data = {}

            def visit(name, obj):
                if isinstance(obj, h5py.Dataset):
                    data[name] = obj[()]
                    if array_digest(data[name]) != obj.attrs.get("sha256"):
                        raise InputError(
                            f"{path}: dataset {name} fails its checksum (damaged file)"
                        )

            f.visititems(visit)
    except InputError:
        raise
    except (OSError, RuntimeError, KeyError, ValueError, TypeError) as exc:
        # h5py reports damaged metadata with any of these, not only OSError
        raise InputError(f"{path} cannot be read as HDF5 ({exc})") from None
    return data, attrs


def _manifest_problem(data: dict) -> str | None:
    """What is wrong with the shape of a manifest's content, or None."""
    if not isinstance(data.get("campaign_hash"), str):
        return "campaign_hash must be a string"
    if not isinstance(data.get("campaign"), dict):
        return "campaign must be an object (the campaign's tables)"
    mesh = data.get("mesh")
    if not isinstance(mesh, dict) or not all(isinstance(mesh.get(k), str) for k in MESH_KEYS):
        return 'mesh must be an object {"file": ..., "sha256": ...}'
    positions = data.get("positions")
    if not isinstance(positions, list) or not positions:
        return "positions must be a non-empty list"
    for i, p in enumerate(positions):
        if not (isinstance(p, dict) and type(p.get("index")) is int and p["index"] == i):
            return f"positions[{i}] must be an object with index {i}"
        for key in ("point", "normal"):
            v = p.get(key)
            ok = isinstance(v, list) and len(v) == 3
            if not ok or not all(type(c) in (int, float) and math.isfinite(c) for c in v):
                return f"positions[{i}].{key} must be three finite numbers"
    return None


def csr_datasets(prefix: str, K: scipy.sparse.csr_matrix) -> dict[str, np.ndarray]:
    """The datasets ``prefix/data``, ``/indices``, ``/indptr``, ``/shape`` of a CSR matrix."""
    return {
        f"{prefix}/data": K.data,
        f"{prefix}/indices": K.indices.astype(np.int64),
        f"{prefix}/indptr": K.indptr.astype(np.int64),
        f"{prefix}/shape": np.asarray(K.shape, dtype=np.int64),
    }


def csr_from(data: dict[str, np.ndarray], prefix: str) -> scipy.sparse.csr_matrix:
    """The CSR matrix stored by :func:`csr_datasets` under ``prefix``."""
    return scipy.sparse.csr_matrix(
        (data[f"{prefix}/data"], data[f"{prefix}/indices"], data[f"{prefix}/indptr"]),
        shape=tuple(data[f"{prefix}/shape"]),
    )


class SnapshotStore:
    """A campaign directory (see the module docstring)."""

    def __init__(self, root: str | Path):
        self.root = Path(root)
        self.solves = self.root / "solves"

    # -- manifest --------------------------------------------------------------
    @property
    def manifest_path(self) -> Path:
        """The campaign's manifest.json."""
        return self.root / "manifest.json"

    def manifest(self) -> dict:
        """The manifest, checked: InputError naming it if unreadable, not JSON or misshapen."""
        path = self.manifest_path
        if not path.is_file():
            raise InputError(f"{self.root} is not a campaign directory (no manifest.json)")
        data = read_versioned_json(path, FORMAT, VERSION, "manifest")
        problem = _manifest_problem(data)
        if problem:
            raise InputError(f"{path} is damaged: {problem}")
        return data

    def open_or_create(self, manifest: dict, restart: bool = False) -> bool:
        """Create the directory for ``manifest``, or check it holds the same campaign.

        Returns True when resuming. Call on one rank only.
        """
        self.solves.mkdir(parents=True, exist_ok=True)
        for stale in self.root.rglob(f".*{PARTIAL_MARK}*"):  # left by a killed run
            stale.unlink()
        if self.manifest_path.is_file() and not restart:
            existing = self.manifest()
            if existing["campaign_hash"] != manifest["campaign_hash"]:
                raise InputError(
                    f"{self.root} holds a different campaign (other configuration or mesh); "
                    "choose another output directory or pass --restart to discard it"
                )
            return True
        if restart:
            for old in self.solves.glob("position-*.h5"):
                old.unlink()
            (self.root / "operators.h5").unlink(missing_ok=True)
        write_text_atomically(self.manifest_path, json.dumps(manifest, indent=2) + "\n")
        return False

    # -- records ---------------------------------------------------------------
    def position_path(self, index: int) -> Path:
        """The record of tool position ``index``."""
        return self.solves / f"position-{index:04d}.h5"

    def completed(self) -> list[int]:
        """Indices of the positions with a complete record (solved or failed)."""
        done = []
        for path in sorted(self.solves.glob("position-*.h5")):
            try:
                with h5py.File(path, "r") as f:
                    if f.attrs.get("complete", False):
                        done.append(int(f.attrs["index"]))
            except OSError:
                continue  # unreadable: treated as not done, solved again
        return done

    def audit(self) -> tuple[list[int], dict[int, str]]:
        """Verify every stored position (all its checksums), for a resume.

        Returns the indices of the positions solved and intact, and for each
        other stored position why it must be solved again: its file is damaged
        or unreadable, or its solve failed in an earlier run. Call on one rank.
        """
        solved, redo = [], {}
        for path in sorted(self.solves.glob("position-*.h5")):
            try:
                index = int(path.stem.removeprefix("position-"))
            except ValueError:
                continue  # not a record of ours
            try:
                _, attrs = read_h5(path)
            except InputError as exc:
                redo[index] = f"stored record is damaged: {exc}"
                continue
            if attrs.get("index") != index:
                held = attrs.get("index")
                redo[index] = f"stored record is damaged: {path} holds position {held}"
            elif attrs.get("status") != "solved":
                reason = attrs.get("message") or attrs.get("status")
                redo[index] = f"failed in an earlier run ({reason})"
            else:
                solved.append(index)
        return solved, redo

    def write_position(self, index: int, datasets: dict, attrs: dict) -> None:
        """Store the record of position ``index`` (atomic, checksummed)."""
        write_h5(self.position_path(index), datasets, {"index": index, **attrs})

    def read_position(self, index: int) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """The record of position ``index``, checksums verified: (datasets, attributes)."""
        return read_h5(self.position_path(index))

    @property
    def operators_path(self) -> Path:
        """The stored operators (operators.h5)."""
        return self.root / "operators.h5"

    def has_operators(self) -> bool:
        """Whether operators.h5 exists (intact or not)."""
        return self.operators_path.is_file()

    def write_operators(self, datasets: dict, attrs: dict) -> None:
        """Store the operators (atomic, checksummed)."""
        write_h5(self.operators_path, datasets, attrs)

    def read_operators(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """The stored operators, checksums verified: (datasets, attributes)."""
        return read_h5(self.operators_path)

"""Mesh generators of hapticrom (all lengths in mm).

Each mesh is written as ``NAME.msh`` (gmsh MSH 4.1 with the physical groups
``tissue``, ``clamped``, ``loadable``, ``free``) plus a ``NAME.json`` sidecar
(see :mod:`hapticrom.meshes.msh`)::

    from hapticrom.meshes import generate
    sidecar = generate("cornea", "meshes/cornea.msh", refinement="coarse", layers=4)

``MESHES`` maps a mesh name to its builder, ``builder(refinement, **params)
-> BuiltMesh``; the builders of the hexahedral meshes are pure numpy, the
liver's calls gmsh's tetrahedral mesher.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from hapticrom.shared.errors import InputError

from .beam import build_beam
from .liver import build_liver
from .msh import REFINEMENTS, BuiltMesh, gmsh_home_guard, read_sidecar, write_msh
from .spherical_cap import build_cornea, build_hemisphere

MESHES: dict[str, Callable[..., BuiltMesh]] = {
    "cornea": build_cornea,
    "beam": build_beam,
    "hemisphere": build_hemisphere,
    "liver": build_liver,
}

__all__ = [
    "MESHES",
    "REFINEMENTS",
    "BuiltMesh",
    "build",
    "generate",
    "gmsh_home_guard",
    "read_sidecar",
    "write_msh",
]


def build(name: str, refinement: str = "default", **params: Any) -> BuiltMesh:
    """Build mesh ``name`` in memory (no files); InputError for bad names or values."""
    if name not in MESHES:
        raise InputError(f"unknown mesh {name!r}; choose one of {', '.join(MESHES)}")
    if refinement not in REFINEMENTS:
        raise InputError(
            f"unknown refinement {refinement!r}; choose one of {', '.join(REFINEMENTS)}"
        )
    return MESHES[name](refinement, **params)


def generate(
    name: str, out: str | Path, refinement: str = "default", incision=None, **params: Any
) -> dict[str, Any]:
    """Write mesh ``name`` to ``out`` (.msh) and its sidecar (.json); return the sidecar.

    ``params`` override the generator's parameters (e.g. ``layers=4``).
    ``incision``: a :class:`~hapticrom.meshes.cut.LimbalArc` meshed explicitly
    (duplicated nodes along the cut faces; the sidecar records it).
    """
    out = Path(out)
    if out.suffix != ".msh":
        raise InputError(f"mesh output must be a .msh file, got {str(out)!r}")
    mesh = build(name, refinement, **params)
    if incision is not None:
        from dataclasses import asdict, replace

        from hapticrom.meshes.cut import cut_mesh, limbal_arc

        mesh, _ = cut_mesh(mesh, limbal_arc(mesh, incision))
        mesh = replace(mesh, params={**mesh.params, "limbal_incision": asdict(incision)})
    sidecar = mesh.sidecar()
    write_msh(out, mesh.nodes, mesh.cells, mesh.facet_groups, sidecar)
    return sidecar

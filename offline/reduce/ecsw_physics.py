"""The artifact's ``hyperreduced`` group (format 2.5; group 1.3 in 2.8): regions of
hyper-reduced physics that the runtime steps online (``online/physics.py``), written from the
trainer's :class:`~hapticrom.offline.reduce.ecsw_model.HyperReducedModel` of each region.

A region is what ``bench/ecsw_tradeoff.py`` measures at one held-out position: a reduced
mixed model on bases Phi (N, n), Psi (cells, n_p) built about a centre, its internal forces
summed over ECSW's sampled elements. The runtime needs, per region: the sampled elements'
reference nodes, weights, basis rows and packed laws (its sums, ``online/hyperreduced.py``);
the constant tangent; the basis at the surface vertices (what it draws); the basis at the
nodes a holder may grip (:class:`GripNodes`: every node of the loadable facets within reach,
the mid-side nodes of P2 too, as the full order's holder holds them); and the reduced load
of a unit force of the tool centred at each loadable vertex within the region's radius
(``tool_loads``: Phi^T g / W, g the campaign's force tool's load, exactly as the full order
spreads it, so a press at a vertex is the full order's load projected); optionally (group
1.2) a check sample, a second ECSW sample of the same bases at a tighter tolerance, and its
constant tangent: the runtime's error indicator (``online/sampling_check.py``); (1.3) a
held region's holder patch and the force patterns it holds it in (``hold_datasets``).

Steps, as a reductor's: :func:`region_arrays` (one region's arrays from its model),
:func:`tool_loads` (the loads at the region's vertices), :func:`physics_group` (the regions
stacked into the group's content), :func:`add_physics` (the group written into an artifact).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hapticrom.online.physics import holder_patch, loadable_vertices
from hapticrom.shared.artifact import read_artifact, with_group, write_artifact
from hapticrom.shared.artifact_rules import CHECK_DATASETS
from hapticrom.shared.errors import InputError

HOLD_STIFFNESS = 1e4  # a holder's penalty, of the stiffest tool's linear stiffness


@dataclass(frozen=True)
class GripNodes:
    """The nodes a holder may grip: every displacement node of the organ's loadable facets
    (vertices, and the edges' mid-side nodes on P2), their canonical indices and positions
    (mm): the candidates of the full order's displacement-controlled tool
    (``ContactPatch.blocks``), which holds those within its radius
    (``ecsw_model.group_nodes(mesh_file, "loadable")``)."""

    nodes: np.ndarray  # (G,) canonical node indices
    points: np.ndarray  # (G, 3) mm

    def within(self, centre, radius) -> np.ndarray:
        """The rows within ``radius`` (mm) of ``centre``."""
        slack = 1e-9 * max(radius, 1.0)  # a node the runtime's patch reaches by rounding
        return np.flatnonzero(np.linalg.norm(self.points - centre, axis=1) <= radius + slack)

    def patch(self, point, radius) -> np.ndarray:
        """The rows a holder at ``point`` grips: the runtime's ``holder_patch`` on them."""
        return holder_patch(self.points, np.arange(len(self.nodes)), point, radius)


@dataclass(frozen=True)
class PhysicsRegion:
    """One region's arrays, as the group stores them (names as ``ARTIFACT.md``'s)."""

    centre: np.ndarray  # (3,) mm
    radius: float  # mm
    element_nodes: np.ndarray  # (S, nodes, 3) mm
    weights: np.ndarray  # (S,)
    basis_rows: np.ndarray  # (S, 3 nodes, n)
    pressure_rows: np.ndarray  # (S, n_p)
    parameters: np.ndarray  # (S, PARAMETER_SIZE)
    constant_tangent: np.ndarray  # (n + n_p, n + n_p)
    surface_basis: np.ndarray  # (3V, n)
    load_vertices: np.ndarray  # (L,) surface vertex indices
    tool_loads: np.ndarray  # (L, 3, n) per N
    hold_stiffness: float  # N/mm
    grip_nodes: np.ndarray  # (G, 3) mm: the grip nodes within reach of the region's holders
    grip_rows: np.ndarray  # (G, 3, n)
    check: dict | None = None  # the error indicator's sample: CHECK_DATASETS' names and arrays
    # a held region's holder (group 1.3): its patch (rows of grip_nodes) and the force
    # patterns it holds the patch in, (P, 3, m) orthonormal over the patch's DOFs
    hold_nodes: np.ndarray | None = None
    hold_reactions: np.ndarray | None = None


def sample_arrays(mesh, model, prefix: str = "") -> dict:
    """A sampled model's datasets, each name ``prefix`` + element_nodes, weights,
    basis_rows, pressure_rows, parameters, constant_tangent."""
    _, _, Phi_e, Psi_e, params, weights = model.sample
    arrays = {
        "element_nodes": np.ascontiguousarray(mesh.X[model.elements]),
        "weights": np.array(weights),
        "basis_rows": np.array(Phi_e),
        "pressure_rows": np.array(Psi_e),
        "parameters": np.array(params),
        "constant_tangent": 0.5 * (model.linear + model.linear.T),  # symmetric up to rounding
    }
    return {prefix + name: a for name, a in arrays.items()}


def region_arrays(mesh, model, Phi, surface, centre, radius, loads, grip: GripNodes,
                  reach: float, check=None, hold=None) -> PhysicsRegion:  # fmt: skip
    """A region about ``centre`` (mm) of tools within ``radius`` (mm): ``model`` (a
    HyperReducedModel on ``mesh``'s elements and the basis ``Phi`` (N, n)), ``surface`` the
    artifact's surface group (vertices, triangles, nodes, groups), ``loads`` a
    ``tool_stiffness.ToolLoads`` (the campaign's force tool), ``grip`` the organ's
    :class:`GripNodes`, of which the region keeps those within ``radius + reach`` (mm:
    the tool's contact radius) of its centre; ``check``: the error indicator's model (a
    second sample on the same bases), or None; ``hold``: a held region's (its holder's
    patch, rows of ``grip``; its hold patterns (3P, m): ``ecsw_regions.hold_patterns``),
    or None."""
    centre = np.asarray(centre, dtype=float)
    near = grip.within(centre, radius + reach)
    hold_nodes = hold_reactions = None
    if hold is not None:
        patch, patterns = hold
        hold_nodes = np.searchsorted(near, patch)  # near rises: rows of the region's grip
        if not np.array_equal(near[np.minimum(hold_nodes, len(near) - 1)], patch):
            raise InputError("a held region's holder grips nodes beyond the region's reach")
        hold_reactions = np.ascontiguousarray(patterns.reshape(len(patch), 3, -1))
    vertices = region_vertices(surface, centre, radius)
    tool_loads_ = tool_loads(Phi, surface["vertices"][vertices], loads)
    return PhysicsRegion(
        centre=centre,
        radius=float(radius),
        **sample_arrays(mesh, model),
        surface_basis=surface_rows(Phi, surface["nodes"]),
        load_vertices=vertices,
        tool_loads=tool_loads_,
        hold_stiffness=hold_stiffness(model, tool_loads_),
        grip_nodes=np.ascontiguousarray(grip.points[near], dtype=float),
        grip_rows=np.ascontiguousarray(Phi.reshape(-1, 3, Phi.shape[1])[grip.nodes[near]]),
        check=None if check is None else sample_arrays(mesh, check, "check_"),
        hold_nodes=hold_nodes,
        hold_reactions=hold_reactions,
    )


def linear_stiffness(model, loads) -> np.ndarray:
    """(k,) N/mm: 1 / (t^T u) for each reduced load t of ``loads`` (k, n) per N, u the
    model's exact linear response to it (its mixed matrices over every element, the
    pressure condensed by the solve): the tool's linear stiffness, where t is a tool's."""
    n = model.n
    K = np.block([[model.L_uu, model.L_up], [model.L_up.T, -model.M]])
    rhs = np.vstack([np.asarray(loads).T, np.zeros((model.n_p, len(loads)))])
    compliance = np.einsum("nk,nk->k", rhs[:n], np.linalg.solve(K, rhs)[:n])
    return 1.0 / compliance


def hold_stiffness(model, loads) -> float:
    """A holder's penalty (N/mm): ``HOLD_STIFFNESS`` times the stiffest linear response
    of a tool of the region (``loads`` (L, 3, n), each direction), so that a held patch
    moves about 1e-4 of what a free one would under the same force."""
    return HOLD_STIFFNESS * float(linear_stiffness(model, loads.reshape(-1, loads.shape[-1])).max())


def region_vertices(surface, centre, radius) -> np.ndarray:
    """The vertices of loadable triangles within ``radius`` of ``centre``: where the
    region's tools may press (refused if none)."""
    loadable = loadable_vertices(surface)
    near = np.linalg.norm(surface["vertices"][loadable] - centre, axis=1) <= radius
    if not near.any():
        raise InputError(f"no loadable surface vertex within {radius} mm of {centre.tolist()}")
    return loadable[near].astype(np.int64)


def surface_rows(Phi, nodes) -> np.ndarray:
    """(3V, n): the basis at the surface vertices (canonical ``nodes``), DOF 3 v + c."""
    n = Phi.shape[1]
    return np.ascontiguousarray(Phi.reshape(-1, 3, n)[np.asarray(nodes)].reshape(-1, n))


def tool_loads(Phi, points, loads) -> np.ndarray:
    """(L, 3, n): Phi^T g / W of a unit force along x, y and z of the tool centred at each
    of ``points`` (``loads.at``: the campaign's traction F w / W, w = (1 - r^2/R^2)^2)."""
    out = np.empty((len(points), 3, Phi.shape[1]))
    for k, point in enumerate(points):
        for axis, push in enumerate(np.eye(3)):
            g, W = loads.at(point, push)
            out[k, axis] = Phi.T @ g / W
    return out


def physics_group(regions: list[PhysicsRegion], cell: str, tolerance: float | None) -> dict:
    """The group's content (datasets and attrs) of ``regions`` (same n, n_p and element
    kind; the penalty the stiffest of theirs)."""
    if not regions:
        raise InputError("no region to write")
    checked = [r.check is not None for r in regions]
    if any(checked) and not all(checked):
        raise InputError("every region or none has a check sample (the error indicator)")
    offsets = [np.cumsum([0] + [len(getattr(r, name)) for r in regions])
               for name in ("weights", "load_vertices", "grip_nodes")]  # fmt: skip

    def stack(name):
        return np.concatenate([getattr(r, name) for r in regions])

    attrs = {"cell": cell, "hold_stiffness": max(r.hold_stiffness for r in regions)}
    if tolerance is not None:
        attrs["tolerance"] = float(tolerance)
    hold = hold_datasets(regions)
    # no basis carries the responses to cupping loads any more (1.1's held regions did: their
    # holders kept the cupping too); a holder other than a held region's keeps its patch's
    # mean and rotation (cupping rows on a basis without their responses stiffen it: README)
    attrs["holder_cupping"] = 0
    check = {}
    if all(checked):
        sizes = [len(r.check["check_weights"]) for r in regions]
        check["check_element_offsets"] = np.cumsum([0] + sizes).astype(np.int64)
        for name in CHECK_DATASETS:
            parts = [r.check[name] for r in regions]
            tangent = name == "check_constant_tangent"  # one a region, the rest stacked
            check[name] = np.array(parts) if tangent else np.concatenate(parts)
    return {
        **check,
        **hold,
        "centres": np.array([r.centre for r in regions]),
        "radii": np.array([r.radius for r in regions]),
        "element_offsets": offsets[0].astype(np.int64),
        "load_offsets": offsets[1].astype(np.int64),
        "grip_offsets": offsets[2].astype(np.int64),
        **{
            name: stack(name)
            for name in (
                "element_nodes",
                "weights",
                "basis_rows",
                "pressure_rows",
                "parameters",
                "load_vertices",
                "tool_loads",
                "grip_nodes",
                "grip_rows",
            )
        },  # fmt: skip
        "constant_tangent": np.array([r.constant_tangent for r in regions]),
        "surface_basis": np.array([r.surface_basis for r in regions]),
        "attrs": attrs,
    }


def hold_datasets(regions: list[PhysicsRegion]) -> dict:
    """The hold datasets (group 1.3) of the regions with a held holder (none: {}), each
    region's patterns padded with zero columns to the widest's, its own count in
    ``hold_ranks``."""
    held = [r for r in regions if r.hold_nodes is not None]
    if not held:
        return {}
    width = max(r.hold_reactions.shape[2] for r in held)
    nodes, reactions, ranks = [], [], []
    for r in regions:
        count = 0 if r.hold_nodes is None else len(r.hold_nodes)
        nodes.append(np.zeros(0, np.int64) if r.hold_nodes is None else r.hold_nodes)
        padded = np.zeros((count, 3, width))
        if count:
            padded[:, :, : r.hold_reactions.shape[2]] = r.hold_reactions
        reactions.append(padded)
        ranks.append(0 if r.hold_nodes is None else r.hold_reactions.shape[2])
    return {
        "hold_offsets": np.cumsum([0] + [len(n) for n in nodes]).astype(np.int64),
        "hold_nodes": np.concatenate(nodes).astype(np.int64),
        "hold_reactions": np.concatenate(reactions),
        "hold_ranks": np.array(ranks, np.int64),
    }


def add_physics(artifact_path, out, regions, cell, tolerance=None) -> Path:
    """Write ``artifact_path``'s artifact with the ``hyperreduced`` group of ``regions`` to
    ``out`` (atomically: the reader checks it before it appears; the source untouched)."""
    artifact = read_artifact(artifact_path)
    group = physics_group(regions, cell, tolerance)
    content, root_attrs = with_group(artifact, "hyperreduced", group)
    write_artifact(out, content, root_attrs)
    return Path(out)

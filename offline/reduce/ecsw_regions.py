"""Regions of hyper-reduced physics built from a solved campaign (issue 18): what
``hapticrom physics`` writes into an artifact's ``hyperreduced`` group.

A region about a centre is the recipe ``bench/ecsw_tradeoff.py`` measured at held-out
positions (README, stops 37-42): full-order solves of the campaign's load path at loadable
surface nodes about the centre (``RegionSolves``: by default three about 0.25 mm and three
about 0.5 mm away, so that every contact within the region has nonlinear snapshots close by;
on a mesh whose nodes lie farther apart, the edges' midpoints too: ``between_nodes``), the
POD of their states and pressures, supremizers (the mixed basis' inf-sup stability), ECSW
trained on the solves' own states, then the region's arrays
(:func:`~hapticrom.offline.reduce.ecsw_physics.region_arrays`). Steps, as a reductor's:
:func:`region_snapshots`, :func:`region_bases`, :func:`region_training`, :func:`region_model`
(the model's sample, and a check sample trained apart at a tighter tolerance: the runtime's
error indicator); :func:`build_regions` runs them for each centre. Serial (one
rank), as the bench.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace

import numpy as np
import scipy.sparse.linalg
from mpi4py import MPI

from hapticrom.meshes.msh import read_surface
from hapticrom.offline.campaign.greedy import near_supports
from hapticrom.offline.campaign.positions import ToolPosition
from hapticrom.offline.campaign.run import solve_position
from hapticrom.offline.fe.organ import load_organ
from hapticrom.offline.reduce.ecsw import ecsw
from hapticrom.offline.reduce.ecsw_model import (
    HyperReducedModel,
    rest_operators,
    rest_solver,
    supremizers,
    training_matrix,
)
from hapticrom.offline.reduce.ecsw_physics import (
    GripNodes,
    PhysicsRegion,
    region_arrays,
    region_vertices,
)
from hapticrom.online.physics import holder_rows
from hapticrom.shared.errors import InputError, SolverError

log = logging.getLogger(__name__)


CHECK_FRACTION = 0.25  # the check sample's default tolerance, of the model's
# a held region's hold patterns: its patch's reactions down to this fraction of the largest
# singular value (the liver's region: 15 of 18; 1e-3 kept 18, the same errors: README, stop 47)
HOLD_PATTERNS = 1e-2


@dataclass(frozen=True)
class RegionRecipe:
    """How a region is built: the solves' distances (mm) and count at each, the modes kept
    (displacement states, pressures; supremizers add one displacement mode a pressure
    mode), ECSW's tolerance, the radius (mm) about a site where tools may press, a pair
    region's second force, a pinch's forces, an oblique region's tangential force and
    linear modes. The defaults are the bench's figures at ECSW 0.004
    (README, stop 42)."""

    distances: tuple[float, ...] = (0.25, 0.5)
    per_distance: int = 3
    state_modes: int = 30
    pressure_modes: int = 20
    tolerance: float = 0.004
    radius: float = 1.0
    second_force: float = 0.5  # a pair region's second tool, of the campaign's force
    lift: float = 0.0  # mm: a held region's holders also lift this far, alone (grasp-and-lift)
    pinch_force: float = 0.014  # N: each of a pinch region's nine forces (thesis §3.4.3)
    oblique: float = 0.5  # an oblique region's tangential force in its solves, of the campaign's
    linear_modes: int = 60  # an oblique region's modes of the tool's linear responses
    # up to this many pressure modes more where the basis carries extra displacement modes (a
    # held region's responses, an oblique region's linear modes): their condensed pressures
    # compete with the solves' for the pressure POD (README, stop 48: the held press at
    # position 30 3.14 -> 2.10 % with every element, 3.33 -> 2.57 % through the product)
    extra_pressure_modes: int = 10
    between_nodes: bool = False  # solves also at the loadable edges' midpoints (a coarse mesh)
    # the error indicator's check sample: ECSW's tolerance, tighter than the model's (None: a
    # quarter of it; 0: no check sample)
    check_tolerance: float | None = None

    def __post_init__(self):
        if self.check_tolerance is None:
            object.__setattr__(self, "check_tolerance", CHECK_FRACTION * self.tolerance)
        if not self.distances or min(self.distances) <= 0:
            raise InputError("a region's solves need positive distances (mm)")
        counts = (self.per_distance, self.state_modes, self.pressure_modes)
        if min(counts) < 1:
            raise InputError("a region needs at least one solve a distance, state mode and "
                             "pressure mode")  # fmt: skip
        if not (type(self.extra_pressure_modes) is int and 0 <= self.extra_pressure_modes <= 1000):
            raise InputError(f"a region's extra pressure modes must lie in 0..1000, got "
                             f"{self.extra_pressure_modes}")  # fmt: skip
        if not 0 <= self.lift <= 10:
            raise InputError(f"a holder's lift must lie in [0, 10] mm, got {self.lift}")
        if not (self.check_tolerance == 0 or 0 < self.check_tolerance < self.tolerance):
            raise InputError(f"the check sample's tolerance must lie in (0, {self.tolerance}) "
                             f"(tighter than the model's), or be 0 for none; got "
                             f"{self.check_tolerance}")  # fmt: skip
        modes = self.linear_modes
        if not (0 < self.oblique <= 10 and type(modes) is int and 1 <= modes <= 1000):
            raise InputError(f"an oblique region's tangential force must lie in (0, 10] of "
                             f"the campaign's and its linear modes in 1..1000, got "
                             f"{self.oblique}, {self.linear_modes}")  # fmt: skip
        if not 0 < self.pinch_force <= 100:
            raise InputError(f"a pinch's force must lie in (0, 100] N, got {self.pinch_force}")
        if not (0 < self.tolerance < 1 and self.radius > 0 and 0 < self.second_force <= 10):
            raise InputError(
                "ECSW's tolerance must lie in (0, 1), the radius be positive and "
                "the second tool's force in (0, 10] of the campaign's"
            )


class RegionSolves:
    """Full-order solves of a campaign's load path at sites of the loadable surface about a
    point (the organ and its surface read once): its nodes, and with ``between_nodes`` the
    midpoints of its edges too (the tool centred between two nodes, its normal their
    normals' mean: solves closer together than a coarse mesh's nodes). A site is an index
    into ``sites``, the nodes first (``nearest`` and ``second_tool`` pick nodes only).
    Subclassed by ``bench/ecsw_tradeoff.py``."""

    def __init__(self, config, distances, per_distance: int, between_nodes: bool = False):
        self.config = config
        # a holder: the campaign's tool under displacement control, held where it is
        self.held = replace(config, load=replace(config.load, mode="displacement", magnitude=0.0))
        self.distances, self.per_distance = tuple(distances), int(per_distance)
        self.surface = read_surface(config.problem.mesh.file, config.load.surface)
        self.sites, self.site_normals = self.surface.nodes, self.surface.normals
        if between_nodes:
            self.sites, self.site_normals = edge_midpoints(self.surface)
        self.organ = load_organ(config.problem.mesh.file, MPI.COMM_SELF)
        # a tip on the clamped rim does not move: no snapshot there (as the greedy campaign)
        self.excluded = near_supports(config, self.sites)

    def nodes(self, point, forbidden=()) -> list[int]:
        """The sites to solve at: per distance d, those whose distance from ``point`` is
        within 25 % of d, the nearest to d first, then each next the farthest from those
        chosen (spread round the point); no site twice, none by the supports, none of
        ``forbidden``."""
        distance = np.linalg.norm(self.sites - point, axis=1)
        chosen: list[int] = []
        for d in self.distances:
            ring = np.flatnonzero(np.abs(distance - d) <= 0.25 * d)
            skip = self.excluded | set(forbidden) | set(chosen)
            ring = np.array([k for k in ring if k not in skip])
            if len(ring) < self.per_distance:
                kind = "nodes" if len(self.sites) == len(self.surface.nodes) else "sites"
                raise InputError(f"{len(ring)} free loadable surface {kind} lie within 25 % of "
                                 f"{d:g} mm of {np.round(point, 4).tolist()}, "
                                 f"{self.per_distance} needed")  # fmt: skip
            picks = [int(ring[np.argmin(np.abs(distance[ring] - d))])]
            while len(picks) < self.per_distance:
                xyz = self.sites[ring][:, None]
                gap = np.linalg.norm(xyz - self.sites[picks][None], axis=2).min(axis=1)
                picks.append(int(ring[np.argmax(gap)]))
            chosen += picks
        return chosen

    def position(self, site) -> ToolPosition:
        """The tool at ``site``; a node's gmsh tag, or -1 for an edge's midpoint."""
        tags = self.surface.node_tags
        tag = int(tags[site]) if site < len(tags) else -1
        return ToolPosition(-1, tuple(self.sites[site]), tuple(self.site_normals[site]), tag,
                            "point")  # fmt: skip

    def solve(self, node, tools=(), config=None) -> dict:
        """The datasets of the campaign's load path at site ``node`` (with further force
        ``tools``; ``config``: another load); a failed solve is refused (its converged part
        would bias the basis silently)."""
        position = self.position(node)
        datasets, attrs = solve_position(config or self.config, position, self.organ,
                                         MPI.COMM_SELF, tools)  # fmt: skip
        if attrs["status"] != "solved":
            raise SolverError(
                f"the full-order solve at surface point "
                f"{np.round(position.point, 4).tolist()} mm failed: {attrs['message']}"
            )
        return datasets

    def nearest(self, point) -> int:
        return int(np.argmin(np.linalg.norm(self.surface.nodes - point, axis=1)))

    def tool(self, node, fraction) -> tuple:
        """A further force tool at surface ``node``: its (point, force) pair, ``fraction``
        of the campaign's force along the campaign's direction there."""
        position = self.position(node)
        force = fraction * self.config.load.magnitude * self.config.load.unit_direction(position)
        return position.point, tuple(float(v) for v in force)

    def pinch(self, site, force) -> tuple[list[tuple], object]:
        """A pinch at ``site`` of nine forces of ``force`` N: its tools (the campaign's tool
        at the site first, then ``pinch_tools``) and the config whose load is the first
        (``solve(site, tools[1:], config)`` solves it)."""
        config = replace(self.config, load=replace(self.config.load, magnitude=force))
        return [self.tool(site, force / self.config.load.magnitude),
                *self.pinch_tools(site, force)], config  # fmt: skip

    def pinch_tools(self, site, force) -> list[tuple]:
        """The further tools of a pinch at ``site`` (the campaign's tool there is its
        first force): the eight free loadable nodes nearest to it, each pressing with
        ``force`` (N) along the campaign's direction there (thesis §3.4.3: nine
        neighbouring nodes, 0.014 N each)."""
        distance = np.linalg.norm(self.surface.nodes - self.sites[site], axis=1)
        distance[[k for k in self.excluded if k < len(distance)]] = np.inf
        if site < len(distance):
            distance[site] = np.inf  # the first tool's own node
        nearest = np.argsort(distance)[:8]
        if len(nearest) < 8 or not np.isfinite(distance[nearest]).all():
            raise InputError(f"a pinch at {np.round(self.sites[site], 4).tolist()} mm needs "
                             "eight free loadable nodes beside it")  # fmt: skip
        return [self.tool(int(n), force / self.config.load.magnitude) for n in nearest]

    def oblique_tool(self, site, azimuth: float, fraction) -> tuple:
        """A tangential force on ``site``'s point, ``fraction`` of the campaign's force
        along the surface at ``azimuth`` (degrees) from the tangent nearest x (nearest y
        where the normal is near x): beside the campaign's tool there, an oblique press
        (``bench/ecsw_tradeoff.py --oblique``: README, stop 40)."""
        normal = np.asarray(self.site_normals[site], float)
        e1 = np.eye(3)[0] - normal[0] * normal
        if np.linalg.norm(e1) < 0.1:
            e1 = np.eye(3)[1] - normal[1] * normal
        e1 /= np.linalg.norm(e1)
        angle = np.radians(azimuth)
        tangent = np.cos(angle) * e1 + np.sin(angle) * np.cross(normal, e1)
        force = fraction * self.config.load.magnitude * tangent
        return self.position(site).point, tuple(float(v) for v in force)

    def second_tool(self, point, distance, fraction) -> tuple[int, tuple]:
        """A second tool ``distance`` mm from ``point`` (the free loadable node nearest to
        that distance, not ``point``'s own): its node and its ``tool``."""
        gap = np.abs(np.linalg.norm(self.surface.nodes - point, axis=1) - distance)
        nodes = len(self.surface.nodes)  # the sites' first (the rest: edge midpoints)
        gap[[k for k in self.excluded if k < nodes] + [self.nearest(point)]] = np.inf
        node = int(np.argmin(gap))
        return node, self.tool(node, fraction)


def edge_midpoints(surface) -> tuple[np.ndarray, np.ndarray]:
    """(points, unit normals) of a surface's nodes followed by the midpoints of its faces'
    edges (each edge once), a midpoint's normal the mean of its two nodes'."""
    faces = surface.faces
    edges = np.sort(np.stack([faces, np.roll(faces, -1, axis=1)], axis=-1).reshape(-1, 2), axis=1)
    a, b = np.unique(edges, axis=0).T
    normals = surface.normals[a] + surface.normals[b]
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    if not (length > 1e-6).all():  # a fold: the two nodes' normals opposite
        k = int(np.argmin(length))
        raise InputError(f"the loadable surface folds over at the edge of nodes "
                         f"{surface.node_tags[a[k]]} and {surface.node_tags[b[k]]}: no normal "
                         "at its midpoint for --between-nodes")  # fmt: skip
    normals /= length
    return (np.vstack([surface.nodes, 0.5 * (surface.nodes[a] + surface.nodes[b])]),
            np.vstack([surface.normals, normals]))  # fmt: skip


def unit_svd(columns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(left singular vectors, singular values) of the columns, each scaled to unit norm
    first (zero columns left out)."""
    norms = np.linalg.norm(columns, axis=0)
    U, s, _ = np.linalg.svd(columns[:, norms > 0] / norms[norms > 0], full_matrices=False)
    return U, s


def pod(columns: np.ndarray) -> np.ndarray:
    """Left singular vectors of the columns, each scaled to unit norm first."""
    return unit_svd(columns)[0]


@dataclass(frozen=True)
class RegionSite:
    """Where a region's tools go: ``kind`` "at" (one site: presses about it), "pinch" (nine
    forces at neighbouring nodes about one site), "oblique" (presses with a tangential
    force about one site), "pair" (two tools pressing at once) or
    "held" (the first presses while a holder grips the second); ``points`` (1 or 2, 3) mm."""

    kind: str
    points: np.ndarray

    def __post_init__(self):
        count = {"at": 1, "pinch": 1, "oblique": 1, "pair": 2, "held": 2}.get(self.kind)
        if count is None or np.shape(self.points) != (count, 3):
            raise InputError(f"a region site is 'at', 'pinch' or 'oblique' one point or "
                             f"'pair' or 'held' two, got {self.kind!r} with shape "
                             f"{np.shape(self.points)}")  # fmt: skip


def region_snapshots(solves: RegionSolves, site: RegionSite, second_force: float = 0.5,
                     lift: float = 0.0, pinch_force: float = 0.014,
                     oblique: float = 0.5) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """(states (N, k), pressures (cells, k)) of the solves about the site's first point;
    for a pair, of pairs: the k-th node about the first pressed with the campaign's force
    while the k-th about the second presses with ``second_force`` of it (never both on one
    node; README stop 39: single presses about each site left the two dents' interaction
    out, 3.4 % against 1.1-1.5 % with pairs); held, the k-th about the first pressed while
    a holder keeps its patch at the k-th about the second in place (``solves.held``), and
    with a ``lift`` (mm) each of those holders also lifts its patch that far against the
    campaign's direction (out of the surface along its normal for "normal"), nothing
    pressing (grasp-and-lift's states); a pinch, at the k-th site about the point the
    campaign's tool and eight more at the nearest nodes, each pressing ``pinch_force`` N
    (``RegionSolves.pinch_tools``); oblique, the campaign's tool at the k-th site of each
    ring with a tangential force of ``oblique`` of its own on the same point at azimuth
    120 k degrees (``RegionSolves.oblique_tool``: three directions about the site)."""
    first = solves.nodes(site.points[0])
    if site.kind == "at":
        solved = [solves.solve(node) for node in first]
    elif site.kind == "oblique":
        rings = solves.per_distance  # three directions in each ring of solves
        solved = [solves.solve(node, tools=[solves.oblique_tool(node, 120.0 * (k % rings % 3),
                                                                oblique)])
                  for k, node in enumerate(first)]  # fmt: skip
    elif site.kind == "pinch":
        pinches = [(node, *solves.pinch(node, pinch_force)) for node in first]
        solved = [solves.solve(node, tools=tools[1:], config=config)
                  for node, tools, config in pinches]  # fmt: skip
    else:
        pairs = zip(first, solves.nodes(site.points[1], forbidden=first), strict=True)
        if site.kind == "pair":
            solved = [solves.solve(a, tools=[solves.tool(b, second_force)]) for a, b in pairs]
        else:
            pairs = list(pairs)
            solved = [solves.solve(b, tools=[solves.tool(a, 1.0)], config=solves.held)
                      for a, b in pairs]  # fmt: skip
            if lift:
                load = replace(solves.held.load, magnitude=-lift)  # against the direction
                lifting = replace(solves.held, load=load)
                solved += [solves.solve(b, config=lifting) for _, b in pairs]
    return (np.vstack([d["displacement"] for d in solved]).T,
            np.vstack([d["pressure"] for d in solved]).T)  # fmt: skip


def patch_motions(points) -> np.ndarray:
    """(P, 3, k): the displacements a holder may give its patch (``points`` (P, 3) mm):
    on three nodes or more, unit translations along x, y, z and unit rotations about them
    (e_a x r_i, r_i about the centroid; k = 6), on one or two each node's unit
    displacements (k = 3P: the runtime holds each)."""
    P = len(points)
    if P < 3:
        return np.eye(3 * P).reshape(P, 3, 3 * P)
    r = points - points.mean(axis=0)
    motions = np.zeros((P, 3, 6))
    for axis, e in enumerate(np.eye(3)):
        motions[:, axis, axis] = 1.0
        motions[:, :, 3 + axis] = np.cross(e, r)
    return motions


def held_patch_responses(operators, grip: GripNodes, point, radius, free,
                         loads) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """(columns (N, k + L), reactions (3P, k + L)): the linear responses at rest with a
    holder's patch (the ``grip`` nodes within ``radius`` (mm) of ``point``: the runtime's
    ``holder_patch``) under displacement control, as the full order's holder holds it: to
    each of its ``patch_motions``, nothing loaded, and to each of ``loads`` (N, L), the
    patch at rest; and the forces (N) the patch's nodes hold the tissue with in each (their
    reactions, node-major). Zero outside the ``free`` rows. A held region's basis carries
    the responses and its holder holds the reactions' patterns (``hold_patterns``): README,
    stop 47, on the liver's grasp-and-lift (7.6 -> 0.9 % in field)."""
    patch = grip.patch(point, radius)
    held = (3 * grip.nodes[patch][:, None] + np.arange(3)).ravel()
    if not np.isin(held, free).all():
        raise InputError(f"a holder at {np.round(point, 4).tolist()} mm grips a supported "
                         "node (the organ's supports hold it): grip farther from them")  # fmt: skip
    motions = patch_motions(grip.points[patch])
    motions = motions.reshape(len(held), -1)
    inner = np.setdiff1d(free, held)
    K = operators.condensed()
    coupling = K[inner][:, held]
    factor = scipy.sparse.linalg.splu(K[inner][:, inner].tocsc())
    columns = np.zeros((K.shape[0], motions.shape[1] + loads.shape[1]))
    columns[held, : motions.shape[1]] = motions
    rhs = np.hstack([-(coupling @ motions), loads[inner]])
    columns[inner] = factor.solve(rhs)
    external = np.hstack([np.zeros_like(motions), loads[held]])
    return columns, np.asarray(K[held] @ columns) - external


def hold_patterns(reactions: np.ndarray, tolerance: float = HOLD_PATTERNS) -> np.ndarray:
    """(3P, m) orthonormal: the left singular vectors of the ``reactions`` (3P, k), each
    column scaled to unit norm first, down to ``tolerance`` of the largest singular value:
    the force patterns a held region's holder keeps its patch still in (the rows it
    holds, ``online/physics.py``)."""
    U, s = unit_svd(reactions)
    return np.ascontiguousarray(U[:, s > tolerance * s[0]])


def linear_modes(operators, loads, points, free, count: int) -> np.ndarray:
    """(N, count): the leading POD modes of the linear responses at rest to a unit force
    of the tool along x, y and z at each of ``points`` (mm; ``loads`` a ``ToolLoads``),
    zero outside the ``free`` rows: what an oblique region's basis needs beside its solves
    (three tangential directions at other nodes do not span a fourth at this one: the
    bench's oblique press 2.9-4.2 % off without them, 1.7-2.5 % with 20; README, stop 40;
    the tangential slip under the tool 8-17 % short with 20, within 1 % with 60 and the
    extra pressure modes, stop 48: a sideways dent is local, so its POD decays slowly)."""
    unit = unit_loads(loads, [(point, push) for point in points for push in np.eye(3)])
    responses = rest_solver(operators, free)(unit)
    modes = pod(responses)[:, :count]
    if modes.shape[1] < count:
        raise InputError(f"{modes.shape[1]} linear responses for {count} linear modes: "
                         "a larger --radius, or fewer --linear-modes")  # fmt: skip
    return modes


MAX_LINEAR_VERTICES = 400  # an oblique region's linear responses are dense: N x 3 each


def oblique_site(surface, point, recipe: RegionRecipe) -> None:
    """Refuse, before any solve, an oblique region whose solves cannot hold three
    directions in each ring (``--solves-per-distance`` under 3) or whose loadable vertices
    within its radius give fewer linear responses than ``recipe.linear_modes`` or more
    than the memory of ``MAX_LINEAR_VERTICES``' (dense columns of the organ's size)."""
    where = f"an oblique region at {np.round(point, 4).tolist()} mm"
    if recipe.per_distance < 3:
        raise InputError(f"{where} needs 3 solves a distance or more (its three tangential "
                         f"directions), got {recipe.per_distance}")  # fmt: skip
    count = len(region_vertices(surface, point, recipe.radius))
    if 3 * count < recipe.linear_modes:
        raise InputError(f"{where} has {count} loadable vertices within its radius "
                         f"({recipe.radius:g} mm): {3 * count} linear responses for "
                         f"{recipe.linear_modes} linear modes (default "
                         f"{RegionRecipe.linear_modes}); a larger --radius or --linear-modes "
                         f"{3 * count} or fewer")  # fmt: skip
    if count > MAX_LINEAR_VERTICES:
        raise InputError(f"{where} has {count} loadable vertices within its radius "
                         f"({recipe.radius:g} mm), more than {MAX_LINEAR_VERTICES} (its linear "
                         "responses are dense): a smaller --radius")  # fmt: skip


def unit_loads(loads, pushes) -> np.ndarray:
    """(N, L): the loads g / W (per N) of the campaign's tool (``loads`` a ``ToolLoads``)
    centred at each point of ``pushes`` ((point mm, unit direction) pairs)."""
    columns = []
    for point, push in pushes:
        g, W = loads.at(point, push)
        columns.append(g / W)
    return np.array(columns).T


def press_loads(solves: RegionSolves, loads, sites) -> np.ndarray:
    """(N, L): ``unit_loads`` of the campaign's tool pressing along the campaign's
    direction at each of ``sites`` (``RegionSolves`` sites)."""
    positions = [solves.position(site) for site in sites]
    return unit_loads(loads, [(p.point, solves.config.load.unit_direction(p))
                              for p in positions])  # fmt: skip


def region_bases(operators, U, P, recipe: RegionRecipe,
                 extra=None) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """(Phi, Psi): ``state_modes`` of the states, the ``extra`` displacement modes kept
    whole (a holder's responses, an oblique region's linear modes) and the supremizers of
    the pressure modes, orthonormalised; the pressure modes: ``pressure_modes`` of the
    pressures, with extra modes up to ``extra_pressure_modes`` more (their condensed
    pressures among the pressures; as many as those columns give, logged if fewer: the
    extra modes' count is known only after the solves)."""
    free = np.flatnonzero(np.abs(U).max(axis=1) > 0)
    if U.shape[1] < recipe.state_modes or P.shape[1] < recipe.pressure_modes:
        raise InputError(f"{U.shape[1]} states for {recipe.state_modes} state and "
                         f"{recipe.pressure_modes} pressure modes")  # fmt: skip
    parts, pressures = [pod(U)[:, : recipe.state_modes]], recipe.pressure_modes
    if extra is not None:
        parts.append(extra)
        P = np.hstack([P, operators.Bt.T @ extra / operators.compliance[:, None]])
        pressures += recipe.extra_pressure_modes
    Psi = pod(P)[:, :pressures]
    if Psi.shape[1] < pressures:
        log.warning("%d pressure modes of %d asked (%d + %d extra): the states and extra modes "
                    "give no more", Psi.shape[1], pressures, recipe.pressure_modes,
                    recipe.extra_pressure_modes)  # fmt: skip
    parts.append(supremizers(operators, Psi, free))
    return np.linalg.qr(np.hstack(parts))[0], Psi


def region_training(mesh, rest, Phi, Psi, U, P) -> np.ndarray:
    """ECSW's training matrix of the bases at the states (U, P) reduced."""
    states = [(Phi.T @ u, Psi.T @ p) for u, p in zip(U.T, P.T, strict=True)]
    return training_matrix(mesh, Phi, Psi, states, rest=rest)[0]


def region_model(mesh, rest, Phi, Psi, G, tolerance) -> HyperReducedModel:
    """The model of ECSW's sample at ``tolerance`` on the training matrix ``G``."""
    sampling = ecsw(G, tolerance=tolerance)
    return HyperReducedModel(mesh, Phi, Psi, sampling.elements, sampling.weights, rest=rest)


def build_regions(config, mesh, rest, surface, grip: GripNodes, loads, sites,
                  recipe: RegionRecipe):  # fmt: skip
    """The :class:`PhysicsRegion` of each of ``sites`` (:class:`RegionSite`; solves as
    ``region_snapshots``; an oblique site's basis also carries ``recipe.linear_modes`` of
    the tool's linear responses at its loadable vertices (``linear_modes``); a held
    site's basis also carries the responses with its holder's
    patch held, ``held_patch_responses`` on the ``grip`` nodes to its moves and the
    region's presses, and its holder holds their reactions' ``hold_patterns``; a two-point
    site's centre is their midpoint, its radius ``recipe.radius`` beyond each), logged as
    it goes."""
    solves = RegionSolves(config, recipe.distances, recipe.per_distance, recipe.between_nodes)
    operators = rest_operators(mesh, rest)
    regions: list[PhysicsRegion] = []
    for k, site in enumerate(sites):
        t0 = time.perf_counter()
        U, P = region_snapshots(solves, site, recipe.second_force, recipe.lift,
                                recipe.pinch_force, recipe.oblique)  # fmt: skip
        extra, hold = None, None
        if site.kind == "oblique":
            free = np.flatnonzero(np.abs(U).max(axis=1) > 0)
            near = region_vertices(surface, site.points[0], recipe.radius)
            extra = linear_modes(operators, loads, surface["vertices"][near], free,
                                 recipe.linear_modes)  # fmt: skip
        if site.kind == "held":
            free = np.flatnonzero(np.abs(U).max(axis=1) > 0)
            presses = press_loads(solves, loads, solves.nodes(site.points[0]))
            extra, reactions = held_patch_responses(operators, grip, site.points[1],
                                                    config.load.contact_radius, free,
                                                    presses)  # fmt: skip
            hold = (grip.patch(site.points[1], config.load.contact_radius),
                    hold_patterns(reactions))  # fmt: skip
        Phi, Psi = region_bases(operators, U, P, recipe, extra)
        G = region_training(mesh, rest, Phi, Psi, U, P)
        model = region_model(mesh, rest, Phi, Psi, G, recipe.tolerance)
        check = None
        if recipe.check_tolerance:
            check = region_model(mesh, rest, Phi, Psi, G, recipe.check_tolerance)
        centre = site.points.mean(axis=0)  # two points' midpoint: tools within radius of each
        radius = recipe.radius + float(np.linalg.norm(site.points[-1] - site.points[0])) / 2
        regions.append(region_arrays(mesh, model, Phi, surface, centre, radius, loads, grip,
                                     config.load.contact_radius, check, hold))  # fmt: skip
        log.info("region %d of %d (%s) at %s mm: %d states, %d + %d modes, %d of %d elements "
                 "(the check sample %d; %.0f s)", k + 1, len(sites), site.kind,
                 np.round(site.points, 3).tolist(), U.shape[1], Phi.shape[1], Psi.shape[1],
                 model.sampled_elements, len(mesh.X), check.sampled_elements if check else 0,
                 time.perf_counter() - t0)  # fmt: skip
    return regions


def physics_from_campaign(model_path, store, sites, recipe: RegionRecipe, out) -> list:
    """The regions of ``sites`` (:class:`RegionSite` each: ``build_regions``)
    built from the solved campaign in ``store`` (a SnapshotStore) and written with
    ``model_path``'s artifact (which must have been reduced from it) to ``out``. The
    campaign must be force-controlled: its tool's load is what the regions' tools press
    with."""
    from hapticrom.offline.reduce.ecsw_model import group_nodes, mesh_elements, rest_tangents
    from hapticrom.offline.reduce.ecsw_physics import add_physics
    from hapticrom.offline.reduce.inputs import campaign_config
    from hapticrom.offline.reduce.tool_stiffness import ToolLoads
    from hapticrom.shared.artifact import read_artifact

    manifest = store.manifest()
    config = campaign_config(store, manifest, None)
    artifact = read_artifact(model_path)
    if artifact.group_attrs["model"]["campaign_hash"] != manifest["campaign_hash"]:
        raise InputError(f"{model_path} was not reduced from the campaign in {store.root} "
                         "(their campaign hashes differ)")  # fmt: skip
    if config.load.mode != "force":
        raise InputError(f"hapticrom physics needs a force-controlled campaign (its tool "
                         f"presses the regions' tools do); {store.root}'s load is "
                         f"'{config.load.mode}'")  # fmt: skip
    states = recipe.per_distance * len(recipe.distances) * config.load.steps
    if states < max(recipe.state_modes, recipe.pressure_modes):
        raise InputError(f"a region's {recipe.per_distance * len(recipe.distances)} solves of "
                         f"{config.load.steps} steps give {states} states, fewer than "
                         f"{recipe.state_modes} state or {recipe.pressure_modes} pressure "
                         "modes: more solves, or fewer modes")  # fmt: skip
    surface = artifact["surface"]
    grip = GripNodes(*group_nodes(config.problem.mesh.file, config.load.surface))
    supported = store.read_operators()[0]["supported_nodes"]
    for site in sites:  # before any solve: each site has loadable surface within the radius
        for point in site.points:
            region_vertices(surface, point, recipe.radius)
        if site.kind == "oblique":
            oblique_site(surface, site.points[0], recipe)
        if site.kind == "held":  # and a holder's site a patch the runtime can hold
            patch = grip.patch(site.points[1], config.load.contact_radius)
            holder_rows(np.zeros((grip.points.size, 1)), grip.points, patch)
            if np.isin(grip.nodes[patch], supported).any():
                raise InputError(f"a holder at {np.round(site.points[1], 4).tolist()} mm "
                                 "grips a supported node (the organ's supports hold it): grip "
                                 "farther from them")  # fmt: skip
    mesh = mesh_elements(config.problem.mesh.file, config.problem.material)
    rest = rest_tangents(mesh)
    regions = build_regions(config, mesh, rest, surface, grip, ToolLoads(config), sites,
                            recipe)  # fmt: skip
    add_physics(model_path, out, regions, mesh.reference.cell, recipe.tolerance)
    return regions

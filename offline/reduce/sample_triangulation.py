"""The samples' neighbourhoods on the organ's surface: a triangulation that follows it.

The runtime blends the three samples of the sample triangle that holds the
contact. On a shallow cap a plane chart of the samples would do; on a curved
or closed organ (a liver's anterior surface wraps around its border, a kidney
is closed) projected triangles fold over and neighbours in a plane are not
neighbours on the organ. So the triangles are taken on the surface itself:
the *restricted Delaunay triangulation* of the samples to the loadable surface,
the dual of their Voronoi cells on it. Three samples form a triangle where
their cells meet on the surface:

1. the loadable surface triangles are subdivided (sub-edges several times
   shorter than the samples' spacing) and every sub-vertex is labelled with
   its nearest sample;
2. every sub-triangle with three different labels proposes that triple;
3. a proposal is kept only if it is a face of the 3-D Delaunay tetrahedrisation
   of the samples (the restricted Delaunay faces are such faces; the faces of
   one tetrahedrisation never cross each other, so discretisation slop where
   four cells nearly meet cannot make two overlapping triangles);
4. triangles whose normal turns from their samples' normals by more than 60 degrees,
   or whose samples' normals turn from each other by more than 80, go (too few
   samples for the curvature there: a hole, which the greedy trainer's ``cover``
   fills); where
   a sample edge would still carry more than two triangles (a surface through a
   Voronoi vertex), the worst-aligned triangles go;
5. each triangle is oriented with its samples' outward normals;
6. where four samples lie on one sphere (symmetric placements), the cells
   may pick one diagonal of their quadrilateral and the tetrahedrisation the
   other, leaving a hole of three or four edges: it is filled (a quadrilateral
   along its shorter diagonal) if the filling faces outward. The border of an
   open patch runs the other way round and would face inward: it stays open.

Pure numpy and scipy, one process.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import Delaunay, QhullError, cKDTree

from hapticrom.shared.errors import InputError

LOADABLE = 1  # the surface group code of loadable triangles (artifact surface/groups)
# Sub-edges of the labelling at most this fraction of the smallest sample spacing, and at
# most this many subdivisions of a surface triangle's edge.
LABEL_EDGE_FRACTION = 0.25
MAX_SUBDIVISIONS = 12
# A kept triangle's normal within 60 degrees of each of its samples' normals (the artifact's
# facing rule, shared/artifact_rules.MIN_NORMAL_DOT: what the runtime's projection along
# blended normals needs), and its samples' normals pairwise within 80 degrees
# (MIN_NEIGHBOUR_NORMAL_DOT). At 60 pairwise, samples ~30 mm apart across the liver's rim
# (curvature radius 20-30 mm) formed no triangle: 34 % of the 4k liver's loadable vertices
# were covered by 24 samples, 68 % at 80 (measured: README "Interpolation on the surface").
MIN_ALIGNMENT = 0.5
MIN_PAIRWISE = 0.17
# Samples whose spread across their best-fit plane is below this fraction of their extent
# are coplanar: their triangulation is the planar Delaunay (qhull cannot tetrahedrise them).
COPLANAR = 1e-9


@dataclass
class SampleTriangulation:
    """The samples' positions (P, 3) mm and outward normals (P, 3), their triangles on the
    surface (S, 3; counter-clockwise seen from outside) and the most central sample (the
    Grassmann reference)."""

    points: np.ndarray
    normals: np.ndarray
    triangles: np.ndarray
    reference: int


def triangulate_samples(points, normals, vertices, triangles, groups) -> SampleTriangulation:
    """The samples' triangulation on the loadable part of a surface mesh (``vertices`` (V, 3),
    ``triangles`` (T, 3), ``groups`` (T,) with 1 = loadable). InputError if it is empty."""
    points = np.asarray(points, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    if len(points) < 3:
        raise InputError("the artifact needs at least 3 tool positions (a triangle) to interpolate")
    loadable = np.asarray(triangles)[np.asarray(groups) == LOADABLE]
    if len(loadable) == 0:
        raise InputError("the surface has no loadable triangle to triangulate the samples on")
    proposed = _proposed_triples(points, np.asarray(vertices, dtype=np.float64), loadable)
    kept = proposed[_delaunay_faces(points, proposed)]
    kept = _aligned(points, normals, kept)
    kept = _manifold(points, normals, kept)
    if len(kept) == 0:
        raise InputError(
            f"the {len(points)} tool positions make no triangle on the loadable surface (are "
            "they spread over it, at least three with neighbouring Voronoi cells?)"
        )
    oriented = _filled(points, normals, _oriented(points, normals, kept))
    return SampleTriangulation(points, normals, oriented.astype(np.int32), central_sample(points))


def central_sample(points: np.ndarray) -> int:
    """The sample nearest the samples' centroid (the Grassmann reference)."""
    return int(np.argmin(np.linalg.norm(points - points.mean(axis=0), axis=1)))


def _proposed_triples(points, vertices, faces) -> np.ndarray:
    """Sorted sample triples (N, 3) whose nearest-sample cells meet in a sub-triangle."""
    spacing = cKDTree(points).query(points, k=2)[0][:, 1].min()
    edges = np.linalg.norm(vertices[faces] - vertices[np.roll(faces, 1, axis=1)], axis=2)
    m = int(np.clip(np.ceil(edges.max() / (LABEL_EDGE_FRACTION * spacing)), 1, MAX_SUBDIVISIONS))
    bary, subtriangles = _subdivision(m)
    corners = vertices[faces]  # (T, 3, 3)
    sub_points = np.einsum("kc,tcx->tkx", bary, corners)  # (T, K, 3)
    labels = cKDTree(points).query(sub_points.reshape(-1, 3))[1].reshape(len(faces), -1)
    triples = labels[:, subtriangles].reshape(-1, 3)  # every sub-triangle's three labels
    distinct = (
        (triples[:, 0] != triples[:, 1])
        & (triples[:, 1] != triples[:, 2])
        & (triples[:, 0] != triples[:, 2])
    )
    return np.unique(np.sort(triples[distinct], axis=1), axis=0)


def _subdivision(m: int):
    """Barycentric points (K, 3) and sub-triangles (m^2, 3) of a triangle cut m times."""
    index = {}
    bary = []
    for i in range(m + 1):
        for j in range(m + 1 - i):
            index[i, j] = len(bary)
            bary.append((m - i - j, i, j))
    tris = []
    for i in range(m):
        for j in range(m - i):
            tris.append((index[i, j], index[i + 1, j], index[i, j + 1]))
            if i + j < m - 1:
                tris.append((index[i + 1, j], index[i + 1, j + 1], index[i, j + 1]))
    return np.array(bary, dtype=np.float64) / m, np.array(tris, dtype=np.int64)


def _delaunay_faces(points, triples) -> np.ndarray:
    """Whether each sorted triple is a face of the samples' Delaunay tetrahedrisation (of
    their planar Delaunay triangulation if they are coplanar)."""
    centred = points - points.mean(axis=0)
    _, s, vt = np.linalg.svd(centred, full_matrices=False)
    try:
        if len(points) < 4 or s[-1] <= COPLANAR * s[0]:
            raise QhullError("coplanar")
        simplices = Delaunay(points).simplices
        faces = np.vstack([np.delete(simplices, k, axis=1) for k in range(4)])
    except QhullError:
        faces = Delaunay(centred @ vt[:2].T).simplices
    faces = np.unique(np.sort(faces, axis=1), axis=0)
    key = _triple_keys(faces, len(points))
    return np.isin(_triple_keys(triples, len(points)), key)


def _triple_keys(triples, n) -> np.ndarray:
    t = np.asarray(triples, dtype=np.int64)
    return (t[:, 0] * n + t[:, 1]) * n + t[:, 2]


def _unit_normals(points, triples) -> np.ndarray:
    a, b, c = (points[triples[:, k]] for k in range(3))
    n = np.cross(b - a, c - a)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def _alignment(points, normals, triples) -> np.ndarray:
    """The smallest |cos| between each triangle's normal and its three samples' normals."""
    n = _unit_normals(points, triples)
    return np.abs(np.einsum("tx,tkx->tk", n, normals[triples])).min(axis=1)


def _aligned(points, normals, triples) -> np.ndarray:
    """The triangles that lie along the surface: their normal within 60 degrees of their
    samples' normals, and those pairwise within 80 degrees (the artifact's rules)."""
    keep = _alignment(points, normals, triples) >= MIN_ALIGNMENT
    return triples[keep & (_pairwise(normals, triples) >= MIN_PAIRWISE)]


def _pairwise(normals, triples) -> np.ndarray:
    """The smallest cosine between two of each triangle's samples' normals."""
    n = normals[triples]  # (T, 3 corners, 3)
    return np.einsum("tix,tjx->tij", n, n).min(axis=(1, 2))


def _manifold(points, normals, triples) -> np.ndarray:
    """At most two triangles per sample edge: the best-aligned ones stay."""
    order = np.argsort(-_alignment(points, normals, triples), kind="stable")
    count: dict[tuple[int, int], int] = {}
    keep = []
    for t in order:
        a, b, c = (int(v) for v in triples[t])
        edges = ((a, b), (b, c), (a, c))
        if all(count.get(e, 0) < 2 for e in edges):
            for e in edges:
                count[e] = count.get(e, 0) + 1
            keep.append(t)
    return triples[np.sort(np.array(keep, dtype=np.int64))]


def _oriented(points, normals, triples) -> np.ndarray:
    """Each triangle counter-clockwise seen from outside (along its samples' normals)."""
    n = np.cross(points[triples[:, 1]] - points[triples[:, 0]],
                 points[triples[:, 2]] - points[triples[:, 0]])  # fmt: skip
    outward = np.einsum("tx,tx->t", n, normals[triples].sum(axis=1)) > 0
    return np.where(outward[:, None], triples, triples[:, [0, 2, 1]])


def _filled(points, normals, triangles) -> np.ndarray:
    """The oriented triangles with every hole of three or four border edges filled."""
    t = np.asarray(triangles, dtype=np.int64)
    directed = np.vstack([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    keys = np.sort(directed, axis=1)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    border = directed[counts[inverse.ravel()] == 1]
    after: dict[int, list[int]] = {}
    for a, b in border:  # a hole runs against its neighbours' edges: b -> a
        after.setdefault(int(b), []).append(int(a))
    fills = []
    for loop in _short_loops(after):
        for candidate in _loop_fillings(points, loop):
            facing = _facing(points, normals, candidate) >= MIN_ALIGNMENT
            if np.all(facing & (_pairwise(normals, candidate) >= MIN_PAIRWISE)):
                fills.extend(candidate.tolist())
                break
    return np.vstack([t, np.array(fills, dtype=np.int64).reshape(-1, 3)])


def _short_loops(after: dict[int, list[int]]) -> list[tuple[int, ...]]:
    """Cycles of 3 or 4 vertices in the border graph, each once (from its smallest vertex)."""
    loops = set()
    for start in after:
        paths = [(start,)]
        for _ in range(4):
            paths = [p + (n,) for p in paths for n in after.get(p[-1], [])]
            for p in paths:
                if p[-1] == start and len(p) in (4, 5) and len(set(p[:-1])) == len(p) - 1:
                    loop = p[:-1]
                    i = loop.index(min(loop))
                    loops.add(loop[i:] + loop[:i])
    return sorted(loops)


def _loop_fillings(points, loop) -> list[np.ndarray]:
    """The triangles filling a loop of 3 or 4 samples, in its order (a quadrilateral: along
    its shorter diagonal first)."""
    if len(loop) == 3:
        return [np.array([loop])]
    a, b, c, d = loop
    by_ac = np.array([[a, b, c], [a, c, d]])
    by_bd = np.array([[a, b, d], [b, c, d]])
    shorter_ac = np.linalg.norm(points[a] - points[c]) <= np.linalg.norm(points[b] - points[d])
    return [by_ac, by_bd] if shorter_ac else [by_bd, by_ac]


def _facing(points, normals, triangles) -> np.ndarray:
    """The smallest cosine between each triangle's normal (as ordered) and its samples'."""
    n = _unit_normals(points, triangles)
    return np.einsum("tx,tkx->tk", n, normals[triangles]).min(axis=1)

"""Interpolation on the surface itself: the samples' triangulation follows a closed organ and
the runtime's weights are continuous on it, checked against an independent algorithm."""

from __future__ import annotations

import numpy as np
import pytest

from hapticrom.offline.reduce.sample_triangulation import triangulate_samples
from hapticrom.online import kernels
from hapticrom.online.reference import _border, _edge_bisection, _fixed_point
from hapticrom.shared.artifact_rules import MIN_NEIGHBOUR_NORMAL_DOT

RADIUS = 10.0  # mm


def icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    """A sphere of RADIUS: vertices (V, 3), outward triangles (T, 3)."""
    t = (1 + 5**0.5) / 2
    v = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t), (0, -1, -t),
         (0, 1, -t), (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]  # fmt: skip
    f = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4),
         (11, 10, 2), (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8),
         (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]  # fmt: skip
    vertices = [np.array(p, dtype=float) / np.linalg.norm(p) for p in v]
    faces = f
    middle: dict[tuple[int, int], int] = {}  # edge -> its midpoint vertex (any level)

    def mid(a, b):
        key = (min(a, b), max(a, b))
        if key not in middle:
            m = vertices[a] + vertices[b]
            vertices.append(m / np.linalg.norm(m))
            middle[key] = len(vertices) - 1
        return middle[key]

    for _ in range(subdivisions):
        faces = [
            tri
            for a, b, c in faces
            for tri in ((a, mid(a, b), mid(c, a)), (b, mid(b, c), mid(a, b)),
                        (c, mid(c, a), mid(b, c)), (mid(a, b), mid(b, c), mid(c, a)))
        ]  # fmt: skip
    return RADIUS * np.array(vertices), np.array(faces, dtype=np.int64)


@pytest.fixture(scope="module")
def closed_organ():
    """A closed organ (a sphere), loadable all over, with 40 samples at surface vertices
    spread by farthest-point sampling."""
    vertices, faces = icosphere(3)
    picked = [0]
    distance = np.linalg.norm(vertices - vertices[0], axis=1)
    for _ in range(39):
        picked.append(int(np.argmax(distance)))
        distance = np.minimum(distance, np.linalg.norm(vertices - vertices[picked[-1]], axis=1))
    points = vertices[picked]
    normals = points / RADIUS
    tri = triangulate_samples(points, normals, vertices, faces, np.ones(len(faces), dtype=int))
    return vertices, points, normals, tri.triangles.astype(np.int64)


def located(p, points, normals, triangles, floors=None):
    """(flag, samples, weights, height) of the runtime's kernel for point p."""
    weights, samples, where, scratch = np.zeros(3), np.zeros(3), np.zeros(2), np.zeros(3)
    planes = kernels.triangle_planes(points, triangles, floors)
    flag = kernels.locate(
        np.asarray(p, dtype=float), np.ravel(points), np.ravel(normals),
        np.ravel(triangles).astype(float), np.ravel(planes),
        np.ravel(kernels.border_edges(triangles)).astype(float),
        weights, samples, where, scratch,
    )  # fmt: skip
    return flag, samples.astype(int), weights, where[1]


def test_the_triangulation_of_a_closed_organ_is_a_closed_outward_surface(closed_organ):
    _, points, normals, triangles = closed_organ
    edges = np.sort(np.vstack([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]]))
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert np.all(counts == 2)  # every sample edge in two triangles: no hole, no fold
    assert len(points) - len(counts) + len(triangles) == 2  # Euler: a sphere
    a, b, c = (points[triangles[:, k]] for k in range(3))
    n = np.cross(b - a, c - a)
    assert np.all(np.einsum("tx,tx->t", n, a + b + c) > 0)  # counter-clockwise from outside
    assert len(kernels.border_edges(triangles)) == 0


def test_every_point_of_a_closed_organ_is_inside_and_weights_agree_with_another_algorithm(
    closed_organ,
):
    """The kernel's Newton against a fixed-point iteration, at random surface points."""
    _, points, normals, triangles = closed_organ
    rng = np.random.default_rng(4)
    for direction in rng.normal(size=(300, 3)):
        p = RADIUS * direction / np.linalg.norm(direction)
        flag, samples, weights, h = located(p, points, normals, triangles)
        assert flag == 0
        assert weights.min() >= -1e-12 and weights.sum() == pytest.approx(1.0, abs=1e-12)
        x, n = points[samples], normals[samples]
        assert np.allclose(weights @ x + h * (weights @ n), p, atol=1e-9)
        u, v, h_ref = _fixed_point(p, x, n)
        assert np.allclose([1 - u - v, u, v], weights, atol=1e-9)
        assert h == pytest.approx(h_ref, abs=1e-9)


def test_weights_are_continuous_around_a_closed_organ(closed_organ):
    """Along a great circle in 0.01 mm steps the sample weights change by O(step): no
    jump where the contact crosses from one sample triangle into the next."""
    _, points, normals, triangles = closed_organ
    theta = np.linspace(0.0, 2 * np.pi, int(2 * np.pi * RADIUS / 0.01))
    axis1, axis2 = np.array([1.0, 0.2, 0.1]), np.array([-0.1, 0.3, 1.0])
    axis1 /= np.linalg.norm(axis1)
    axis2 -= (axis2 @ axis1) * axis1
    axis2 /= np.linalg.norm(axis2)
    previous, crossings, largest = None, 0, 0.0
    for t in theta:
        _, samples, weights, _ = located(
            RADIUS * (np.cos(t) * axis1 + np.sin(t) * axis2), points, normals, triangles
        )
        w = np.zeros(len(points))
        w[samples] = weights
        if previous is not None:
            jump = np.abs(w - previous).sum()
            largest = max(largest, jump)
            crossings += int(set(np.flatnonzero(w)) != set(np.flatnonzero(previous)))
        previous = w
    spacing = np.median(np.linalg.norm(points[triangles[:, 0]] - points[triangles[:, 1]], axis=1))
    assert crossings >= 10  # the path crosses many sample triangles
    assert largest < 10 * 0.01 / spacing  # |dw| ~ step / spacing, never a jump


def test_a_point_beyond_the_border_is_clamped_continuously(closed_organ):
    """An open patch (the samples of one hemisphere): outside it the contact is clamped to
    the border, with the weights of the border edge it meets, continuous across it."""
    vertices, _, _, _ = closed_organ
    cap = vertices[vertices[:, 2] > 0.3 * RADIUS]
    points = cap[np.linspace(0, len(cap) - 1, 25).astype(int)]
    normals = points / RADIUS
    faces = icosphere(3)[1]
    groups = (vertices[faces].mean(axis=1)[:, 2] > 0.2 * RADIUS).astype(int)
    triangles = triangulate_samples(points, normals, vertices, faces, groups).triangles
    triangles = triangles.astype(np.int64)
    border = _border(triangles)
    assert len(border) > 0
    a, b, c = border[0]
    for s in (0.25, 0.5, 0.75):
        on_edge = points[a] + s * (points[b] - points[a])
        outward = np.cross(points[b] - points[a], normals[a] + normals[b])
        outward *= np.sign(outward @ (on_edge - points[c])) / np.linalg.norm(outward)
        inside = located(on_edge - 1e-7 * outward, points, normals, triangles)
        outside = located(on_edge + 0.5 * outward, points, normals, triangles)
        assert inside[0] == 0 and outside[0] == kernels.FLAG_OUTSIDE_REGION
        w_out = dict(zip(outside[1], outside[2], strict=True))
        s_ref = _edge_bisection(on_edge + 0.5 * outward, points[a], points[b], normals[a],
                                normals[b])  # fmt: skip
        assert w_out[b] == pytest.approx(s_ref, abs=1e-9)
        w_in = dict(zip(inside[1], inside[2], strict=True))
        assert w_in.get(b, 0.0) == pytest.approx(s, abs=1e-5)
        assert w_out[b] == pytest.approx(s, abs=0.05)  # 0.5 mm out: about the same point


def test_off_the_surface_of_a_closed_organ_the_nearest_sample_answers(closed_organ):
    """A closed triangulation has no border to clamp to: a point no triangle holds (the
    organ's centre, far away) gets the nearest sample, weight 1, flagged outside."""
    _, points, normals, triangles = closed_organ
    for p in ([0.0, 0.0, 0.0], [0.0, 0.0, 1e6], [3e3, -2e3, 1e3]):
        flag, samples, weights, _ = located(p, points, normals, triangles)
        distance = np.linalg.norm(points - np.array(p), axis=1)
        assert flag == kernels.FLAG_OUTSIDE_REGION
        assert set(samples) <= set(range(len(points)))
        # At the centre every sample is RADIUS away to 2 ulp: four tie in floating point
        # (stop 50), and which one the kernel meets first follows the triangles' order.
        # Any of them is the nearest; far away the nearest is alone (by 1 mm or more).
        assert distance[samples[0]] <= distance.min() * (1 + 4 * np.finfo(float).eps)
        if np.sort(distance)[1] > distance.min() * (1 + 1e-9):
            assert samples[0] == np.argmin(distance)
        assert list(weights) == [1.0, 0.0, 0.0]


def test_every_triangle_meets_the_artifacts_normal_rules_even_with_rough_normals(closed_organ):
    """Samples whose normals turn fast (tilted at random by up to ~70 degrees): every kept
    triangle, hole fillings included, has its samples' normals pairwise within 80 degrees
    and faces along each of them (within 60), as the artifact's rules require (a reduction refused
    at the writer's read-back otherwise)."""
    vertices, points, _, _ = closed_organ
    faces = icosphere(3)[1]
    rng = np.random.default_rng(7)
    for _ in range(5):
        normals = points / RADIUS + rng.normal(scale=0.7, size=points.shape)
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        normals[np.einsum("px,px->p", normals, points) < 0] *= -1  # still outward
        t = triangulate_samples(points, normals, vertices, faces, np.ones(len(faces), int))
        n = normals[t.triangles]
        assert np.einsum("tix,tjx->tij", n, n).min() >= MIN_NEIGHBOUR_NORMAL_DOT
        a, b, c = (points[t.triangles[:, k]] for k in range(3))
        unit = np.cross(b - a, c - a)
        unit /= np.linalg.norm(unit, axis=1, keepdims=True)
        assert np.einsum("tx,tkx->tk", unit, n).min() >= 0.5


def test_a_hole_is_not_filled_across_samples_whose_normals_differ_by_over_80_degrees():
    """A tetrahedron's surface missing its bottom face: the hole is filled when its
    corners' normals agree; not when each faces the filling (55 degrees off it) but they
    differ from each other by ~90 degrees (the artifact would refuse that triangle: the
    liver's 56-sample reduction was, before this rule reached the filling)."""
    from hapticrom.offline.reduce.sample_triangulation import _filled

    points = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.3, 0.3, 1.0]])
    sides = np.array([[0, 1, 3], [1, 2, 3], [2, 0, 3]])  # outward; the bottom (0, 2, 1) missing
    down = np.tile([0.0, 0.0, -1.0], (4, 1))
    down[3] = [0.0, 0.0, 1.0]
    assert len(_filled(points, down, sides)) == 4
    tilt = np.radians(55.0)
    rough = down.copy()
    for k, azimuth in enumerate(np.radians([0.0, 120.0, 240.0])):
        rough[k] = [np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth), -np.cos(tilt)]
    assert len(_filled(points, rough, sides)) == 3


THICKNESS = 2.0  # mm, of the slab below


@pytest.fixture(scope="module")
def slab():
    """A slab 2 mm thick: its top face (z = 0, normal +z) and bottom face (z = -2, normal -z)
    as vertices on a 1 mm grid, and four samples on the top face, two triangles."""
    grid = np.stack(np.meshgrid(np.arange(-10.0, 10.5), np.arange(-10.0, 10.5)), -1).reshape(-1, 2)
    zeros = np.zeros((len(grid), 1))
    vertices = np.vstack([np.hstack([grid, zeros]), np.hstack([grid, zeros - THICKNESS])])
    vertex_normals = np.repeat([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]], len(grid), axis=0)
    points = np.array([[-6.0, -6.0, 0.0], [6.0, -6.0, 0.0], [6.0, 6.0, 0.0], [-6.0, 6.0, 0.0]])
    normals = np.tile([0.0, 0.0, 1.0], (4, 1))
    triangles = np.array([[0, 1, 2], [0, 2, 3]])
    floors = kernels.face_floors(points, normals, triangles, vertices, vertex_normals,
                                 np.zeros((0, 3), dtype=np.int64))  # fmt: skip
    return points, normals, triangles, floors


def test_a_triangles_floor_lies_a_quarter_of_the_way_from_the_opposite_face(slab):
    assert slab[3] == pytest.approx([-0.75 * THICKNESS] * 2, abs=1e-12)


def test_rays_find_the_opposite_face_where_no_vertex_lies_under_a_triangle(slab):
    """The slab's faces as two triangles each, their vertices at the corners only (a mesh
    coarser than the samples): no vertex lies under the sample triangles, the rays down
    their normals meet the bottom face (turned away) and not the top one."""
    points, normals, triangles, floors = slab
    corners = np.array([[-10.0, -10.0], [10.0, -10.0], [10.0, 10.0], [-10.0, 10.0]])
    vertices = np.vstack([np.column_stack([corners, np.zeros(4)]),
                          np.column_stack([corners, np.full(4, -THICKNESS)])])  # fmt: skip
    vertex_normals = np.repeat([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]], 4, axis=0)
    faces = np.array([[0, 1, 2], [0, 2, 3], [4, 6, 5], [4, 7, 6]])  # outward: up, down
    coarse = kernels.face_floors(points, normals, triangles, vertices, vertex_normals, faces)
    np.testing.assert_allclose(coarse, floors, atol=1e-12)
    assert np.all(np.isinf(kernels.face_floors(points, normals, triangles, vertices,
                                               vertex_normals, faces[:2])))  # fmt: skip


def test_a_point_of_the_opposite_face_is_not_in_the_triangle_above_it(slab):
    """The bottom face under the samples is clamped to the border (outside the trained
    region), not given the top face's response 2 mm above it; without the floors it was
    (what the liver showed: a lower-face vertex in an upper triangle at h = -39.8 mm)."""
    points, normals, triangles, floors = slab
    below = [1.0, -2.0, -THICKNESS]
    assert located(below, points, normals, triangles)[0] == 0  # the bound it had
    flag, _, _, _ = located(below, points, normals, triangles, floors)
    assert flag == kernels.FLAG_OUTSIDE_REGION


@pytest.mark.parametrize("height", [-0.7 * THICKNESS, -0.3 * THICKNESS, 0.0, 3.0])
def test_points_above_the_floor_keep_their_weights(slab, height):
    points, normals, triangles, floors = slab
    flag, samples, weights, h = located([1.0, -2.0, height], points, normals, triangles, floors)
    top = located([1.0, -2.0, 0.0], points, normals, triangles)
    assert flag == 0 and h == pytest.approx(height, abs=1e-12)
    assert np.array_equal(samples, top[1]) and np.allclose(weights, top[2], atol=1e-12)


def test_the_reference_locates_with_the_same_floors(slab):
    """The numpy reference (a fixed-point iteration and bisection on the border) answers as
    the kernel on both faces and between them."""
    from types import SimpleNamespace

    from hapticrom.online.reference import barycentric

    points, normals, triangles, floors = slab
    model = SimpleNamespace(sample_points=points, sample_normals=normals,
                            sample_triangles=triangles, sample_floors=floors)  # fmt: skip
    rng = np.random.default_rng(7)
    for x, y, z in np.column_stack([rng.uniform(-5, 5, (60, 2)), rng.uniform(-2, 0.5, 60)]):
        flag, samples, weights, _ = located([x, y, z], points, normals, triangles, floors)
        ref_samples, ref_weights, outside = barycentric(model, [x, y, z])
        assert outside == (flag == kernels.FLAG_OUTSIDE_REGION) == (z < -0.75 * THICKNESS)
        assert np.allclose(np.bincount(samples, weights, 4),
                           np.bincount(ref_samples, ref_weights, 4), atol=1e-9)  # fmt: skip


def test_in_boxes_finds_what_brute_force_finds():
    rng = np.random.default_rng(3)
    lo_items = rng.uniform(-10, 10, (300, 3))
    hi_items = lo_items + rng.uniform(0, 3, (300, 3))
    lo = rng.uniform(-10, 10, (40, 3))
    hi = lo + rng.uniform(0, 6, (40, 3))
    starts, ids = kernels.in_boxes(lo_items, hi_items, lo, hi, "items")
    for t in range(len(lo)):
        meets = np.all((lo_items <= hi[t]) & (hi_items >= lo[t]), axis=1)
        assert sorted(ids[starts[t] : starts[t + 1]].tolist()) == np.flatnonzero(meets).tolist()


def test_a_surface_too_large_for_the_floors_is_refused_by_name(small_artifact, monkeypatch):
    """The floors' work is bounded before it starts (a crafted file of huge overlapping
    triangles would otherwise hold the load for hours): over either budget, the load is
    refused, naming why."""
    import hapticrom.online as online
    from hapticrom.shared.errors import ArtifactError

    monkeypatch.setattr(kernels, "FLOOR_SCAN", 1000)
    with pytest.raises(ValueError, match="would scan 2,018 items, more than the 1,000"):
        kernels.in_boxes(np.zeros((9, 3)), np.ones((9, 3)), np.zeros((2, 3)), np.ones((2, 3)),
                         "items")  # fmt: skip
    with pytest.raises(ArtifactError, match="boxes would scan [0-9,]+ surface vertices"):
        online.load(small_artifact)
    monkeypatch.setattr(kernels, "FLOOR_SCAN", 10**9)
    monkeypatch.setattr(kernels, "FLOOR_WORK", 10)
    with pytest.raises(ArtifactError, match="floors would take [0-9,]+ projections and ray"):
        online.load(small_artifact)


def _layers(z_top, thickness, xs, ys):
    """Vertices (outward normals) and outward faces of a slab whose top is z_top(x) over the
    grid xs x ys (coarse: a few corners), its bottom thickness below."""
    from hapticrom.shared.geometry import vertex_normals

    grid = [(x, y) for y in ys for x in xs]
    top = [(x, y, z_top(x)) for x, y in grid]
    vertices = np.array(top + [(x, y, z - thickness) for x, y, z in top])
    nx, half, faces = len(xs), len(grid), []
    for j in range(len(ys) - 1):
        for i in range(nx - 1):
            a, b, c, d = j * nx + i, j * nx + i + 1, (j + 1) * nx + i + 1, (j + 1) * nx + i
            faces += [(a, b, c), (a, c, d), (half + a, half + c, half + b),
                      (half + a, half + d, half + c)]  # fmt: skip
    faces = np.array(faces)
    return vertices, vertex_normals(vertices, faces), faces


def test_a_deeper_layer_of_the_organ_does_not_lower_the_floor(slab):
    """A second slab 6 mm below the first (a fold of the organ): its top faces the
    triangles' way but lies under their opposite face, and does not count."""
    points, normals, triangles, floors = slab
    v1, n1, f1 = _layers(lambda x: 0.0, THICKNESS, [-10.0, 10.0], [-10.0, 10.0])
    v2, n2, f2 = _layers(lambda x: -8.0, THICKNESS, [-10.0, 0.0, 10.0], [-10.0, 0.0, 10.0])
    folded = kernels.face_floors(points, normals, triangles, np.vstack([v1, v2]),
                                 np.vstack([n1, n2]), np.vstack([f1, f2 + len(v1)]))  # fmt: skip
    np.testing.assert_allclose(folded, floors, atol=1e-12)


def test_a_valley_below_the_chord_with_no_vertex_under_it_stays_in():
    """The top face dips 1.8 mm under the samples' chord between them, the mesh so coarse
    that no vertex lies under the triangles: the rays find where they enter the top face
    there, so its lowest point is in the triangles, and the bottom face is not."""
    valley = lambda x: -3.0 + 0.3 * abs(x)  # noqa: E731 - 0 at |x| = 10, -1.2 at the samples
    vertices, vertex_normals, faces = _layers(valley, THICKNESS, [-10.0, 0.0, 10.0],
                                              [-10.0, 10.0])  # fmt: skip
    points = np.array([[-6.0, -6.0, -1.2], [6.0, -6.0, -1.2], [6.0, 6.0, -1.2], [-6.0, 6.0, -1.2]])
    normals = np.array([[0.3, 0, 1], [-0.3, 0, 1], [-0.3, 0, 1], [0.3, 0, 1]]) / np.hypot(0.3, 1)
    triangles = np.array([[0, 1, 2], [0, 2, 3]])
    floors = kernels.face_floors(points, normals, triangles, vertices, vertex_normals, faces)
    flag, _, _, h = located([0.0, -1.0, -3.0], points, normals, triangles, floors)
    assert flag == 0 and h < -1.5  # the valley's bottom, in
    flag, _, _, _ = located([0.0, -1.0, -3.0 - THICKNESS], points, normals, triangles, floors)
    assert flag == kernels.FLAG_OUTSIDE_REGION  # the bottom face under it, out


def test_the_field_beyond_the_last_knot_never_wraps_its_index():
    """field_depth_weights continues linearly, and at any depth indexes the last segment
    (int() of 1e22 / step would wrap to a negative index)."""
    for depth in (0.5, 1e3, 1e22):
        k, a, b = kernels.field_depth_weights(depth, 0.1, 4)
        assert k == 3 and b == pytest.approx(depth / 0.1 - 3) and a == pytest.approx(1 - b)

"""Hostile inputs for the transported surface (issue 15): the chart built at load and the
numba kernel that reads it.

Artifacts here are written with ``write_artifact``, which reads each file back with
``read_artifact``: every one of them passes the artifact's rules, so whatever happens
next is the runtime's to handle. The attacks that hung the chart's build (a red team's
findings, fixed: the grid's node budget, an O(N) extension, the rasterisation's budget)
now build in process and get no chart; the out-of-bounds question is answered by a Python
mirror of the kernel's index arithmetic, never by letting a kernel read past an array.
"""

from __future__ import annotations

import dataclasses
import subprocess
import sys
import textwrap
import threading

import numpy as np
import pytest
from test_surface_field import dent, lattice, plate, samples_on

from hapticrom.online import load, surface_kernels
from hapticrom.online import surface_chart as surface_chart_module
from hapticrom.online.node_blocks import LANES
from hapticrom.online.surface_chart import SurfaceChart, surface_chart
from hapticrom.shared.artifact import read_artifact, write_artifact
from hapticrom.shared.errors import ArtifactError, InputError, SimulatorBusyError

pytestmark = pytest.mark.serial

UP = np.array([0.0, 0.0, 1.0])


# -- building blocks ---------------------------------------------------------------------
def square_sheet(n: int = 9, width: float = 4.0):
    """A flat square (z = 0, outward +z) of n x n vertices: (V, 3), (T, 3)."""
    return lattice(width / 2, n)


def sample_triangle(edge: float, normal=UP):
    """Three samples on a right triangle of legs ``edge`` (mm) at the origin, one normal."""
    points = np.array([[0.0, 0.0, 0.0], [edge, 0.0, 0.0], [0.0, edge, 0.0]])
    return points, np.tile(normal, (3, 1)), np.array([[0, 1, 2]])


def dip(vertices: np.ndarray, samples: int, depth: float = 0.1) -> np.ndarray:
    """(P, 3V, 1) float32: every sample's one mode, the whole surface ``depth`` mm down."""
    basis = np.zeros((samples, 3 * len(vertices), 1), dtype=np.float32)
    basis[:, 2::3, 0] = -depth
    return basis


def write_model(path, vertices, triangles, points, normals, sample_triangles, basis,
                coefficient=1.0):  # fmt: skip
    """A minimal artifact (stored curves, no POD-ANM, no cutting), written and read back by
    ``write_artifact``: it passes every rule of ``read_artifact``. Each sample's reduced
    coordinates grow linearly to ``coefficient`` at the trained depth (1 mm)."""
    P, n, K = len(points), basis.shape[2], 3
    depth = np.linspace(0.0, 1.0, K)
    content = {
        "model": {
            "attrs": {
                "name": "hostile",
                "mode": "displacement",
                "contact_radius": 0.5,
                "surface_group": "loadable",
                "material": {"law": "neo-hookean"},
                "campaign_hash": "0" * 64,
            }
        },
        "surface": {
            "vertices": np.asarray(vertices, dtype=np.float64),
            "triangles": np.asarray(triangles, dtype=np.int64),
            "nodes": np.arange(len(vertices), dtype=np.int64),
            "groups": np.ones(len(triangles), dtype=np.int64),
        },
        "samples": {
            "points": np.asarray(points, dtype=np.float64),
            "normals": np.asarray(normals, dtype=np.float64),
            "triangles": np.asarray(sample_triangles, dtype=np.int64),
            "indicator": np.zeros(P),
            "depth": depth,
            "force": np.tile(depth, (P, 1)),
            "stiffness": np.ones((P, K)),
            "surface_basis": np.asarray(basis, dtype=np.float32),
            "coefficients": np.tile(coefficient * depth[None, :, None], (P, 1, n)),
            "reduced_stiffness": np.tile(np.eye(n), (P, 1, 1)),
            "contact_rows": np.zeros((P, 3, n)),
            "eigenvalues": np.ones((P, 1)),
        },
    }
    write_artifact(path, content, {"description": "a crafted model (tests)"})
    return path


# -- a Python mirror of transported_surface's index arithmetic ---------------------------
def kernel_offsets(chart: SurfaceChart, samples, weights) -> list[tuple[float, float]]:
    """The whole-node offsets (before the clamp) transported_surface computes for the
    neighbours with a weight: floor(g_j) - floor(x), g_j the samples' places on the grid in
    nodes and x = sum_j w_j g_j."""
    g = chart.sample_grid[np.asarray(samples, dtype=np.int64)]
    x = np.asarray(weights) @ g
    return [tuple(np.floor(g[j]) - np.floor(x)) for j in range(3) if weights[j] != 0.0]


def clamped(chart: SurfaceChart, o: float) -> int:
    limit = float(chart.halo - 1)
    return int(min(max(o, -limit), limit))


def index_violations(chart: SurfaceChart, oa: int, ob: int) -> list[str]:
    """What transported_surface would index outside the grid, or read where no block wrote,
    for one neighbour at the clamped offset (oa, ob) nodes (empty: none)."""
    _, rows, cols = (int(v) for v in chart.shape)
    nodes = int(np.prod(chart.shape))
    reach = (chart.halo - 1) * (cols + 1)  # the largest shift the clamp lets through
    blocks = np.asarray(chart.blocks)
    problems = []
    # sum_blocks: each block's LANES nodes, and the neighbour's modes there moved by the offset
    skipped = blocks[(blocks < reach) | (blocks > nodes - LANES - reach)]
    if len(skipped):
        problems.append(f"sum_blocks skips block {int(skipped[0])} (reach {reach}, {nodes} nodes)")
    moved = blocks + oa * cols + ob
    if len(moved) and (moved.min() < 0 or moved.max() + LANES > nodes):
        problems.append(f"sum_blocks reads modes at nodes [{moved.min()}, {moved.max() + LANES})")
    written = np.zeros(nodes, dtype=bool)
    for g in blocks[(blocks >= 0) & (blocks + LANES <= nodes)]:
        written[g : g + LANES] = True
    # read_nodes: the vertex's cell, a row and a column back where the contact's fraction
    # passes its own, and the cell's three other nodes
    for da in (0, 1):
        for db in (0, 1):
            s = chart.charted_node - da * cols - db
            for node in (s, s + 1, s + cols, s + cols + 1):
                layer = node // (rows * cols)
                same_layer = layer == chart.charted_node // (rows * cols)
                inside = (node >= 0) & (node < nodes) & same_layer
                inside[inside] &= written[node[inside]]
                if not inside.all():
                    problems.append(f"read_nodes reads node {int(node[~inside][0])} unwritten")
    return problems


def extreme_offsets(chart: SurfaceChart) -> list[int]:
    """Offsets (nodes) at and near the clamp's limits and around zero."""
    limit = chart.halo - 1
    return [-limit, -limit + 1, -1, 0, 1, limit - 1, limit]


def plate_chart():
    """The plate of test_surface_field: two sheets, side walls, 49 samples (dents)."""
    vertices, triangles = plate(0.5)
    points, normals, sample_triangles = samples_on(3.0)
    basis = np.stack([dent(vertices, p).reshape(-1, 1) for p in points]).astype(np.float32)
    return surface_chart(vertices, triangles, points, normals, sample_triangles, basis)


def long_edge_chart():
    """A 4 mm sheet under samples 30 mm apart: a halo far wider than the surface."""
    vertices, triangles = square_sheet()
    points, normals, sample_triangles = sample_triangle(30.0)
    return surface_chart(vertices, triangles, points, normals, sample_triangles,
                         dip(vertices, 3))  # fmt: skip


def far_tilted_chart():
    """Samples tilted 17 degrees, 10 m away from the surface in plan view."""
    vertices, triangles = square_sheet(n=13, width=6.0)
    vertices[:, 0] += 1.0e4
    normal = np.array([np.sin(0.3), 0.0, np.cos(0.3)])
    points, normals, sample_triangles = sample_triangle(2.0, normal)
    return surface_chart(vertices, triangles, points, normals, sample_triangles,
                         dip(vertices, 3))  # fmt: skip


# -- defences that hold ------------------------------------------------------------------
@pytest.mark.parametrize("build", [plate_chart, long_edge_chart, far_tilted_chart])
def test_the_clamped_shift_keeps_every_index_inside_the_grid(build):
    """Defence. For every offset the clamp lets through (up to halo - 1 nodes either way),
    every block sum_blocks writes and every block of modes it reads lies in the grid, and
    every node read_nodes reads (whatever the contact's fraction) lies in a block it wrote,
    in the vertex's own layer: the kernel's reads stay in bounds."""
    chart = build()
    assert chart is not None and len(chart.charted) > 0
    for oa in extreme_offsets(chart):
        for ob in extreme_offsets(chart):
            assert index_violations(chart, oa, ob) == [], (oa, ob)


def test_the_mirror_sees_blocks_that_leave_the_grid_or_miss_a_read():
    """The mirror can fail: the plate's chart with a block moved to the grid's last nodes
    (shifted modes would be read past its end) or with a block left out (nodes the
    vertices read that no block writes) is reported, at offset zero too."""
    chart = plate_chart()
    nodes = int(np.prod(chart.shape))
    assert index_violations(chart, 0, 0) == []
    edge = dataclasses.replace(chart, blocks=np.append(chart.blocks, nodes - LANES))
    assert index_violations(edge, 0, 0)
    middle = len(chart.blocks) // 2
    holed = dataclasses.replace(chart, blocks=np.delete(chart.blocks, middle))
    assert any("unwritten" in p for p in index_violations(holed, 0, 0))


@pytest.fixture(scope="module")
def plate_model(tmp_path_factory):
    """The plate (49 samples, one dent mode each) as a loaded artifact (its sweep passed)."""
    vertices, triangles = plate(0.5)
    points, normals, sample_triangles = samples_on(3.0)
    basis = np.stack([dent(vertices, p).reshape(-1, 1) for p in points]).astype(np.float32)
    path = tmp_path_factory.mktemp("plate") / "plate.h5"
    write_model(path, vertices, triangles, points, normals, sample_triangles, basis)
    return load(path, isolate=False)


def render_on_poisoned_scratch(model, sim) -> np.ndarray:
    """The kernel itself, on the simulator's state, with its grid, its neighbours' terms and
    its reads' weights filled with NaN first: the blocks write every node the reads need,
    so a NaN in the result is a read where no block wrote (an independent check of the
    mirror); each term and each read's weights must be found before they are used."""
    chart = model.chart
    coefficients = np.zeros((3, model.num_modes))
    surface_kernels.curves_coefficients(sim._buf, model.coefficients, coefficients)
    grid = np.full((int(np.prod(chart.shape)), 4), np.nan, dtype=np.float32)
    terms = np.full((3, surface_kernels.terms_width(model.num_modes)), np.nan, dtype=np.float32)
    out = np.full_like(model.vertices, np.nan)
    surface_kernels.transported_surface(
        sim._buf, coefficients, chart.node_basis, chart.mode_scale, chart.sample_grid,
        model.sample_normals, chart.shape, chart.blocks, chart.halo, chart.charted,
        chart.charted_node, chart.charted_frac, chart.uncharted, chart.uncharted_basis, grid,
        np.zeros((3, 2), dtype=np.int64), terms,
        np.full((4, len(chart.charted)), np.nan, dtype=np.float32),
        np.zeros(len(chart.charted), dtype=np.int64),
        np.full(3 * len(chart.uncharted), np.nan), out,
    )  # fmt: skip
    return out


HUGE = np.finfo(np.float64).max
CONTACTS = [
    (0.37, -0.81, 0.0),  # inside
    (1.5, 1.5, 0.0),  # a sample
    (3.0, 0.2, 0.0),  # the border
    (3.0 + 1e-12, 3.0, 0.0),  # just beyond a corner
    (40.0, -25.0, 3.0),  # outside, clamped to the border
    (0.2, 0.3, 1.0e5),  # far above
    (0.2, 0.3, -1.0e5),  # far below (through the plate)
    (1.0e12, -1.0e12, 0.0),
    (HUGE, HUGE, HUGE),  # finite, the largest there is
    (HUGE, -HUGE, 0.0),  # makes inf - inf inside locate's projections
    (-HUGE, 5e-324, HUGE),
]


@pytest.mark.parametrize("point", CONTACTS)
def test_every_reachable_contact_shifts_within_the_halo(plate_model, point):
    """Defence. Whatever finite point set_contact gets (inside, on and beyond the border,
    far off the surface, the largest floats), locate's weights are finite, in [0, 1] up to
    round-off and sum to 1, so no offset is NaN and the halo holds every offset without the
    clamp; the indices are in bounds and the rendered surface is finite."""
    model = plate_model
    sim = model.simulator()
    sim.set_contact(np.array(point, dtype=np.float64))
    samples, weights = sim.weights
    assert np.all(np.isfinite(weights)) and abs(weights.sum() - 1.0) < 1e-9
    assert np.all(weights >= -1e-9) and np.all(weights <= 1.0 + 1e-9)
    chart = model.chart
    for oa, ob in kernel_offsets(chart, samples, weights):
        assert max(abs(oa), abs(ob)) <= chart.halo - 2  # the clamp (halo - 1) never engages
        assert index_violations(chart, clamped(chart, oa), clamped(chart, ob)) == []
    sim.step_displacement(-0.5 * np.array(sim.contact_normal))
    out = sim.surface_displacement(np.empty_like(model.vertices))
    assert np.all(np.isfinite(out))
    poisoned = render_on_poisoned_scratch(model, sim)
    assert np.all(np.isfinite(poisoned))  # no node outside the written blocks was read
    np.testing.assert_allclose(poisoned, out, rtol=0, atol=1e-6)


def test_a_second_thread_is_refused_while_a_step_is_inside(plate_model):
    """Defence. While one thread is inside step_displacement (held there by an input whose
    conversion blocks), surface_displacement and set_contact from another thread raise
    SimulatorBusyError and change nothing; once the step is out, the surface renders and
    equals a fresh simulator's at the same state."""
    model = plate_model
    sim = model.simulator()
    point = np.array([0.37, -0.81, 0.0])
    sim.set_contact(point)
    entered, release = threading.Event(), threading.Event()
    push = np.array([0.0, 0.0, -0.4])

    class Blocking:
        def __array__(self, dtype=None, copy=None):
            entered.set()
            release.wait(10.0)
            return push.copy()

    errors = []

    def step():
        try:
            sim.step_displacement(Blocking())
        except Exception as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    worker = threading.Thread(target=step)
    worker.start()
    try:
        assert entered.wait(10.0)
        out = np.full_like(model.vertices, 7.0)
        with pytest.raises(SimulatorBusyError):
            sim.surface_displacement(out)
        assert np.all(out == 7.0)  # nothing written
        with pytest.raises(SimulatorBusyError):
            sim.set_contact(np.array([1.0, 1.0, 0.0]))
    finally:
        release.set()
        worker.join(10.0)
    assert not worker.is_alive() and errors == []
    reference = model.simulator()
    reference.set_contact(point)
    reference.step_displacement(push)
    np.testing.assert_array_equal(
        sim.surface_displacement(np.empty_like(model.vertices)),
        reference.surface_displacement(np.empty_like(model.vertices)),
    )


def test_simulators_sharing_a_model_render_on_parallel_threads(plate_model):
    """Defence. Two simulators on one model render the transported surface on two threads at
    once (the kernel lets the GIL go): each gets exactly what it gets alone."""
    model = plate_model
    contacts = [np.array([0.37, -0.81, 0.0]), np.array([-1.9, 2.2, 0.0])]
    sims, alone = [], []
    for p in contacts:
        sim = model.simulator()
        sim.set_contact(p)
        sim.step_displacement(np.array([0.0, 0.0, -0.6]))
        sims.append(sim)
        alone.append(sim.surface_displacement(np.empty_like(model.vertices)).copy())
    mismatches = []

    def render(k):
        out = np.empty_like(model.vertices)
        for _ in range(100):
            if not np.array_equal(sims[k].surface_displacement(out), alone[k]):
                mismatches.append(k)

    threads = [threading.Thread(target=render, args=(k,)) for k in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60.0)
    assert mismatches == [] and not any(t.is_alive() for t in threads)
    assert not np.allclose(alone[0], alone[1])  # two different dents: the check can fail


def test_samples_facing_all_around_load_with_the_blended_field(tmp_path):
    """Defence. Samples all over a sphere (mean normal near zero): no chart, the model loads,
    the default field is PODI's and asking for the transport is one InputError."""
    from test_surface_interpolation import icosphere

    vertices, triangles = icosphere(2)
    points, sample_triangles = icosphere(1)
    normals = points / np.linalg.norm(points, axis=1)[:, None]
    assert np.linalg.norm(normals.mean(axis=0)) < 0.1
    path = write_model(tmp_path / "sphere.h5", vertices, triangles, points, normals,
                       sample_triangles, dip(vertices, len(points)))  # fmt: skip
    model = load(path, isolate=False)
    assert model.chart is None
    assert model.simulator().interpolation == "podi"
    with pytest.raises(InputError, match="interpolation='podi'"):
        model.simulator("transport")


def test_a_surface_seen_edge_on_has_no_chart(tmp_path):
    """Defence. A wall seen edge-on from the samples (no vertex faces their plan normal):
    no chart, the model loads with the blended field."""
    vertices, triangles = square_sheet()
    vertices = vertices[:, [0, 2, 1]]  # the sheet stood up: normal along y
    points, normals, sample_triangles = sample_triangle(1.0)
    path = write_model(tmp_path / "wall.h5", vertices, triangles, points, normals,
                       sample_triangles, dip(vertices, 3))  # fmt: skip
    model = load(path, isolate=False)
    assert model.chart is None and model.simulator().interpolation == "podi"


# -- findings: each fails until fixed ----------------------------------------------------
def test_a_model_with_many_modes_loads_or_is_refused_in_time(tmp_path):
    """Finding (hang). _spacing coarsens the grid by 1.25 until P n 3 N <= MAX_VALUES, but the
    grid never has fewer than 2 (2 halo + 2)^2 >= 72 nodes: when 3 P n 72 > MAX_VALUES
    (P n > 138,888) no spacing fits and the loop never ends (h grows to inf and stays).
    10,000 samples of 14 modes on a one-triangle surface: a 25 MB file that passes every
    rule, and load() spins in _spacing forever."""
    vertices = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    P, n = 10_000, 14
    rng = np.random.default_rng(3)
    points = np.zeros((P, 3))
    points[:, :2] = rng.uniform(0.0, 1.0, (P, 2))
    points[:3] = vertices
    basis = np.zeros((P, 9, n), dtype=np.float32)
    # in process: a hang would stop at pytest's timeout; the fix returns at once
    chart = surface_chart(vertices, np.array([[0, 1, 2]]), points, np.tile(UP, (P, 1)),
                          np.array([[0, 1, 2]]), basis)  # fmt: skip
    assert chart is None  # no grid holds the modes: the model renders PODI's blend


def test_a_long_sample_edge_does_not_stall_the_chart(tmp_path):
    """Finding (hang). Samples 300 mm apart over a 4 mm surface (nothing else odd): the halo
    makes the grid as large as MAX_VALUES allows (2 x 1100^2 nodes for 3 samples of one
    mode) and almost none of it is covered, so _nearest_covered's breadth-first growth,
    one numpy pass over all nodes per ring, runs ~1100 passes: over a minute (100 mm apart:
    19 s; a single 1 um triangle under samples 1 mm apart: 75 s)."""
    vertices, triangles = square_sheet()
    points, normals, sample_triangles = sample_triangle(300.0)
    chart = surface_chart(vertices, triangles, points, normals, sample_triangles,
                          dip(vertices, 3))  # fmt: skip
    assert chart is None or int(np.prod(chart.shape)) <= surface_chart_module.MAX_NODES


def big_overlapping_sheet(copies: int):
    """A 100 mm square listed ``copies`` times (two triangles each; nothing forbids repeated
    surface triangles), plus 2 copies + 1 separate facing triangles of 1 um that make the
    median edge, hence the grid spacing, tiny: (V, 3), (T, 3)."""
    tiny = 2 * copies + 1
    corner = np.array([[0.0, 0.0, 0.0], [1e-3, 0.0, 0.0], [0.0, 1e-3, 0.0]])
    small = np.concatenate([corner + [2e-3 * k, 0.0, 0.0] for k in range(tiny)])
    square = np.array([[0.0, 0.0, 0.0], [100.0, 0.0, 0.0], [100.0, 100.0, 0.0], [0.0, 100.0, 0.0]])
    vertices = np.vstack([small, square])
    triangles = np.vstack([
        np.arange(3 * tiny).reshape(tiny, 3),
        np.tile([[0, 1, 2], [0, 2, 3]], (copies, 1)) + 3 * tiny,
    ])  # fmt: skip
    return vertices, triangles


def test_overlapping_surface_triangles_do_not_stall_the_rasterisation(tmp_path):
    """Finding (hang). _rasterise visits every node of each charted triangle's bounding box:
    T triangles over the whole grid cost T N. 3,000 repeats of a 100 mm square (2 triangles
    each) and 6,001 1-um triangles for the median edge: 12,001 triangles (a few hundred kB),
    a grid of 2 x 1056^2 nodes, about a minute of rasterisation (1,000 repeats: 17 s)."""
    vertices, triangles = big_overlapping_sheet(3000)
    points, normals, sample_triangles = sample_triangle(1.0)
    chart = surface_chart(vertices, triangles, points, normals, sample_triangles,
                          dip(vertices, 3))  # fmt: skip
    assert chart is None  # the rasterisation's budget: PODI's blend instead


MEMORY_CHILD = """
import resource, sys
import numpy as np
from hapticrom.online.surface_chart import surface_chart
data = np.load(sys.argv[1])
args = [data[k] for k in ("v", "t", "p", "n", "s", "b")]
unit = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
surface_chart(unit, np.array([[0, 1, 2]]), *args[2:5], args[5][:, :9])  # kernels loaded first
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
chart = surface_chart(*args)
after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print((after - before) / 1024.0, chart.node_basis.nbytes / 2**20, int(np.prod(chart.shape)))
"""


def test_the_chart_stays_within_its_memory_budget(tmp_path):
    """Finding (memory). MAX_VALUES bounds the modes on the grid (120 MB of float32) but not
    the nodes: with P n small the grid may have MAX_VALUES / (3 P n) nodes (3.3 million for
    3 samples of one mode) and the build keeps some 170 bytes per node besides (barycentric
    weights, heights, the breadth-first copies, the fit's float64 nodes), so a 13-vertex
    surface (a 100 mm square and three 1 um triangles: 2.2 million nodes) raises the peak
    memory by ~360 MB; each simulator then allocates 36 bytes per node more (80 MB here).
    Budget: the build's peak growth within twice MAX_VALUES' 120 MB."""
    vertices, triangles = big_overlapping_sheet(1)
    points, normals, sample_triangles = sample_triangle(1.0)
    data = tmp_path / "inputs.npz"
    np.savez(data, v=vertices, t=triangles, p=points, n=normals, s=sample_triangles,
             b=dip(vertices, 3))  # fmt: skip
    code = textwrap.dedent(MEMORY_CHILD)
    child = subprocess.run([sys.executable, "-c", code, str(data)], capture_output=True,
                           text=True, timeout=120)  # fmt: skip
    assert child.returncode == 0, child.stderr[-2000:]
    growth, node_basis, nodes = (float(v) for v in child.stdout.split())
    assert node_basis <= 120.0
    assert growth <= 240.0, f"peak +{growth:.0f} MB for {nodes:.0f} nodes"


def test_a_surface_with_no_facing_triangle_is_not_refused_as_unreadable(tmp_path):
    """Finding (wrong refusal). A pleated sheet whose every triangle is steeper than FACING
    but whose ridge vertices face the samples: _spacing takes the median of no edges (NaN),
    math.ceil(NaN) raises ValueError and load() refuses the model with "cannot be set up
    (ValueError: cannot convert float NaN to integer)", naming nothing. No triangle can be
    charted, so the chart should be None (the blended field), like a surface seen edge-on."""
    xs, zs = np.arange(6) * 0.1, np.array([0.0, 1.0, 0.0, 1.0, 0.0, 1.0])
    vertices = np.array([[x, y, z] for x, z in zip(xs, zs, strict=True) for y in (0.0, 1.0)])
    strips = 2 * np.arange(5)[:, None]  # each strip between two ridges: two triangles
    triangles = np.vstack([strips + [0, 2, 3], strips + [0, 3, 1]])
    points, normals, sample_triangles = sample_triangle(1.0)
    path = write_model(tmp_path / "pleat.h5", vertices, triangles, points, normals,
                       sample_triangles, dip(vertices, 3))  # fmt: skip
    try:
        model = load(path, isolate=False)
    except ArtifactError as exc:
        assert "surface/" in str(exc), str(exc)  # a refusal must name the culprit
    else:
        assert model.chart is None


def test_a_chart_with_no_charted_vertex_contracts_inside_the_grid():
    """Finding (index contract, low). A surface whose vertices face the samples but none has
    its cell covered (here a single triangle: no grid cell fits in it) gets a chart with no
    charted vertex. The kernel of the time still contracted a rectangle [ia, ia + 1) x
    [ib, ib + 1) around it: negative slice starts for layer 0 (numba wraps them), and at
    ia = 0, ib = -1 the slice [-1:0], which is empty and then written through (out[0]
    landed on the last node: in the array by luck, not by design). Either no chart (None)
    or nothing read outside the grid (since stop 53: no block, nothing summed)."""
    vertices = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    points, normals, sample_triangles = sample_triangle(1.0)
    chart = surface_chart(vertices, np.array([[0, 1, 2]]), points, normals, sample_triangles,
                          dip(vertices, 3))  # fmt: skip
    if chart is None:
        return
    assert len(chart.charted) == 0
    problems = {p for oa in extreme_offsets(chart) for ob in extreme_offsets(chart)
                for p in index_violations(chart, oa, ob)}  # fmt: skip
    assert not problems, "\n".join(sorted(problems, key=lambda p: "-1:" not in p)[:3])


def test_a_finite_surface_basis_gives_finite_values_on_the_grid():
    """Finding (non-finite values into a fastmath kernel). The back-projection fits the nodes
    in float64 and stores them as float32: a surface basis near float32's range (finite,
    so every rule passes) overflows to inf at a quarter of the nodes. At load the sweep
    then refuses the file as "the model's curves surface is not finite" rather than
    naming samples/surface_basis, and inf reaches transported_surface, compiled with
    fastmath (which assumes no inf or NaN). The chart must hold finite values or refuse."""
    vertices, triangles = plate(0.5)
    points, normals, sample_triangles = samples_on(3.0)
    rng = np.random.default_rng(1)
    big = 0.5 * np.finfo(np.float32).max
    basis = (rng.choice([-1.0, 1.0], size=(len(points), vertices.size, 1)) * big).astype(np.float32)
    assert np.all(np.isfinite(basis))
    try:
        chart = surface_chart(vertices, triangles, points, normals, sample_triangles, basis)
    except ArtifactError as exc:
        assert "surface_basis" in str(exc)
        return
    if chart is not None:  # the nodes are int16 (finite by type): their scales must be
        bad = int(np.count_nonzero(~np.isfinite(chart.mode_scale)))
        assert bad == 0, f"{bad} of {chart.mode_scale.size} mode scales are not finite"


def test_a_tiny_surface_basis_keeps_its_signs_in_16_bits():
    """Finding (review of the 16-bit chart). A mode whose largest value is subnormal in
    float32 (1e-40) had a subnormal float32 scale, the ratio value / scale passed 32767 and
    wrapped in int16: 500 nodes of the plate with the wrong sign. The scale is now taken in
    double precision and the ratio clipped: the tiny chart is the ordinary one times 1e-40,
    to float32's subnormal precision."""
    vertices, triangles = plate(0.5)
    points, normals, sample_triangles = samples_on(3.0)
    basis = np.stack([dent(vertices, p).reshape(-1, 1) for p in points])
    charts = [surface_chart(vertices, triangles, points, normals, sample_triangles,
                            (basis * f).astype(np.float32)) for f in (1.0, 1e-40)]  # fmt: skip
    plain, tiny = (c.node_basis * c.mode_scale[:, :, None, None] for c in charts)
    assert np.all(np.isfinite(charts[1].mode_scale)) and np.all(charts[1].mode_scale > 0)
    largest = np.max(np.abs(plain))
    visible = np.abs(plain) > 1e-3 * largest  # below, a step of 16 bits is zero or not
    assert np.all(np.sign(tiny[visible]) == np.sign(plain[visible]))
    assert np.max(np.abs(tiny * 1e40 - plain)) < 1e-3 * largest  # measured 3e-5


def test_the_crafted_artifacts_pass_the_reader(tmp_path):
    """The overlapping-sheet attack is real: read_artifact accepts a surface that lists one
    triangle several times (every crafted file here goes through write_artifact, which
    reads it back, so each passes the reader's rules)."""
    vertices, triangles = big_overlapping_sheet(3)
    assert len(np.unique(np.sort(triangles, axis=1), axis=0)) < len(triangles)  # repeats
    points, normals, sample_triangles = sample_triangle(1.0)
    path = write_model(tmp_path / "m.h5", vertices, triangles, points, normals,
                       sample_triangles, dip(vertices, 3))  # fmt: skip
    assert read_artifact(path).symbols["T"] == len(triangles)


def test_scratch_of_the_wrong_size_is_not_written_past(plate_model):
    """Finding (review of the blocks, low). Scratch of the old layout ((2, C) weights) or
    coefficients with more modes than the chart (terms sized for the chart) made the kernel
    write past them. Each is now a view into a larger buffer of markers: nothing outside
    the view changes, and the charted vertices render as zero (no weights to read with)."""
    model = plate_model
    sim = model.simulator()
    sim.set_contact(np.array([0.37, -0.81, 0.0]))
    sim.step_displacement(np.array([0.0, 0.0, -0.5]))
    chart, C = model.chart, len(model.chart.charted)
    n = model.num_modes
    own = np.zeros((3, n))
    surface_kernels.curves_coefficients(sim._buf, model.coefficients, own)
    coefficients = np.zeros((3, n + 6))
    coefficients[:, :n] = own
    width = surface_kernels.terms_width(n)
    terms_buffer = np.full((6, width), 7.0, dtype=np.float32)
    weights_buffer = np.full((6, C), 7.0, dtype=np.float32)
    out = np.full_like(model.vertices, np.nan)
    surface_kernels.transported_surface(
        sim._buf, coefficients, chart.node_basis, chart.mode_scale, chart.sample_grid,
        model.sample_normals, chart.shape, chart.blocks, chart.halo, chart.charted,
        chart.charted_node, chart.charted_frac, chart.uncharted, chart.uncharted_basis,
        np.zeros((int(np.prod(chart.shape)), 4), dtype=np.float32),
        np.zeros((3, 2), dtype=np.int64), terms_buffer[:3], weights_buffer[:2],
        np.zeros(C, dtype=np.int64), np.zeros(3 * len(chart.uncharted)), out,
    )  # fmt: skip
    assert np.all(terms_buffer[3:] == 7.0) and np.all(weights_buffer[2:] == 7.0)
    assert np.all(out[chart.charted] == 0.0) and np.all(np.isfinite(out))

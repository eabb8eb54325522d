"""The transported surface field: each neighbour's dent carried to the contact.

On a plate every sample's field is the same dent centred on its own position, so the exact
field at any contact is that dent centred on the contact (an analytic reference): the
transported field must reproduce it, and PODI (the blend of three dents where they were
trained) must not. Then: continuity as the contact slides across sample triangles, exact
read-back at a training position, and the sides of an organ keep the blended field.
"""

from __future__ import annotations

import numpy as np
import pytest

from hapticrom.online import kernels, surface_kernels
from hapticrom.online import surface_chart as surface_chart_module
from hapticrom.online.surface_chart import surface_chart

WIDTH = 12.0  # mm, the plate
SPACING = 0.25  # mm, the surface mesh
SIGMA = 0.6  # mm, the dent's radius
SAMPLE_SPACING = 1.5  # mm


def lattice(half: float, n: int):
    """An n x n square lattice over [-half, half]^2 at z = 0 and its triangles, two per
    square, counter-clockwise seen from +z: (n^2, 3), (2 (n - 1)^2, 3)."""
    x = np.linspace(-half, half, n)
    X, Y = np.meshgrid(x, x, indexing="ij")
    points = np.column_stack([X.ravel(), Y.ravel(), np.zeros(X.size)])
    idx = np.arange(n * n).reshape(n, n)
    a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return points, np.vstack([np.column_stack([a, b, c]), np.column_stack([a, c, d])])


def plate(thickness: float | None = None, spacing: float = SPACING):
    """A square plate's upper surface (z = 0, outward +z) triangulated at SPACING, and with
    ``thickness`` its lower surface (outward -z) and the four side walls, with a ring of
    vertices half way down them: (V, 3), (T, 3)."""
    n = int(round(WIDTH / spacing)) + 1
    top, up = lattice(WIDTH / 2, n)
    idx = np.arange(n * n).reshape(n, n)
    if thickness is None:
        return top, up
    bottom = top - [0.0, 0.0, thickness]
    ring = np.concatenate([idx[:, 0], idx[-1, 1:], idx[-2::-1, -1], idx[0, -2:0:-1]])
    middle = top[ring] - [0.0, 0.0, thickness / 2]
    vertices = np.vstack([top, bottom, middle])
    down = up[:, ::-1] + n * n
    walls = []
    for k in range(len(ring)):
        p, q = ring[k], ring[(k + 1) % len(ring)]
        mp, mq = 2 * n * n + k, 2 * n * n + (k + 1) % len(ring)
        for upper_p, upper_q, lower_p, lower_q in ((p, q, mp, mq), (mp, mq, p + n * n, q + n * n)):
            walls += [(upper_p, lower_p, upper_q), (upper_q, lower_p, lower_q)]
    walls = np.array(walls)
    # orient the walls outward (away from the plate's axis)
    a, b, c = (vertices[walls[:, k]] for k in range(3))
    outward = np.einsum("ij,ij->i", np.cross(b - a, c - a), (a + b + c) / 3)
    walls[outward < 0] = walls[outward < 0][:, ::-1]
    return vertices, np.vstack([up, down, walls])


def dent(vertices: np.ndarray, centre: np.ndarray, radius: float = SIGMA) -> np.ndarray:
    """The analytic dent (V, 3) centred at ``centre``: into the plate, a Gaussian of
    ``radius``; the lower surface follows the upper one."""
    r2 = ((vertices[:, :2] - centre[:2]) ** 2).sum(axis=1)
    field = np.zeros_like(vertices)
    field[:, 2] = -np.exp(-r2 / radius**2)
    return field


def samples_on(extent: float):
    """Samples on a square lattice of SAMPLE_SPACING within +-extent, their normals (+z) and
    a triangulation of the lattice."""
    points, triangles = lattice(extent, int(round(2 * extent / SAMPLE_SPACING)) + 1)
    return points, np.tile([0.0, 0.0, 1.0], (len(points), 1)), triangles.astype(np.int64)


class PlateModel:
    """A model whose sample i has one mode, the dent at its own position, coefficient 1; or
    with ``radii`` one mode a radius, the dents of those radii times ``amplitudes``, and
    ``coefficients`` (n,); ``offset``: the samples moved off the lattice of
    SAMPLE_SPACING."""

    def __init__(self, thickness: float | None = None, spacing: float = SPACING,
                 radii=(SIGMA,), coefficients=(1.0,), offset=(0.0, 0.0, 0.0),
                 amplitudes=None):  # fmt: skip
        self.vertices, self.triangles = plate(thickness, spacing)
        self.points, self.normals, self.sample_triangles = samples_on(3.0)
        self.points = self.points + offset  # the samples moved in plan view (mm)
        amplitudes = np.ones(len(radii)) if amplitudes is None else np.asarray(amplitudes)
        basis = np.stack([
            np.column_stack([a * dent(self.vertices, p, r).reshape(-1)
                             for r, a in zip(radii, amplitudes, strict=True)])
            for p in self.points
        ])  # fmt: skip
        self.basis = basis.astype(np.float32)  # (P, 3V, n)
        self.basis_t = np.ascontiguousarray(self.basis.transpose(0, 2, 1))
        self.chart = surface_chart(self.vertices, self.triangles, self.points, self.normals,
                                   self.sample_triangles, self.basis)  # fmt: skip
        nodes = int(np.prod(self.chart.shape))
        self.grid = np.zeros((nodes, 4), dtype=np.float32)
        self.neighbours = np.zeros((3, 2), dtype=np.int64)
        self.terms = np.zeros((3, surface_kernels.terms_width(len(radii))), dtype=np.float32)
        self.weights = np.zeros((4, len(self.chart.charted)), dtype=np.float32)
        self.cells = np.zeros(len(self.chart.charted), dtype=np.int64)
        self.buf = np.zeros(kernels.buffer_size(2))
        self.coefficients = np.tile(np.asarray(coefficients, dtype=float), (3, 1))
        for a in (self.basis, self.basis_t, *vars(self.chart).values()):
            if isinstance(a, np.ndarray):
                a.flags.writeable = False

    def locate(self, point):
        """Put the contact at ``point``: the runtime's weights, samples and normal."""
        weights, samples = self.buf[kernels.WEIGHTS : kernels.WEIGHTS + 3], np.zeros(3)
        where, scratch = np.zeros(2), np.zeros(3)
        kernels.locate(
            np.asarray(point, dtype=float), np.ravel(self.points), np.ravel(self.normals),
            np.ravel(self.sample_triangles).astype(float),
            np.ravel(kernels.triangle_planes(self.points, self.sample_triangles)),
            np.ravel(kernels.border_edges(self.sample_triangles)).astype(float),
            weights, samples, where, scratch,
        )  # fmt: skip
        self.buf[kernels.SAMPLES : kernels.SAMPLES + 3] = samples
        self.buf[kernels.NORMAL : kernels.NORMAL + 3] = (0.0, 0.0, 1.0)

    def transported(self, point) -> np.ndarray:
        self.locate(point)
        out, c = np.zeros_like(self.vertices), self.chart
        surface_kernels.transported_surface(
            self.buf, self.coefficients, c.node_basis, c.mode_scale, c.sample_grid, self.normals,
            c.shape, c.blocks, c.halo, c.charted, c.charted_node, c.charted_frac, c.uncharted,
            c.uncharted_basis, self.grid, self.neighbours, self.terms, self.weights, self.cells,
            np.zeros(3 * len(c.uncharted)), out,
        )  # fmt: skip
        return out

    def blended(self, point) -> np.ndarray:
        self.locate(point)
        out = np.zeros_like(self.vertices)
        surface_kernels.blended_surface(self.buf, self.coefficients, self.basis_t, out)
        return out


@pytest.fixture(scope="module")
def slab():
    return PlateModel(thickness=0.5)


@pytest.fixture(scope="module")
def fine_slab():
    """The same plate meshed twice as finely: the chart's grid is twice as fine."""
    return PlateModel(thickness=0.5, spacing=SPACING / 2)


def relative(a, b) -> float:
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


@pytest.mark.parametrize("point", [(0.37, -0.81, 0.0), (1.9, 1.1, 0.0), (-0.75, 0.75, 0.0)])
def test_the_dent_is_carried_to_the_contact(slab, fine_slab, point):
    """At untrained contacts the transported field is the dent under the tool, to the
    grid's bilinear interpolation (and the fit's 1e-3): within 3 % with a grid spacing of a
    third of the dent's radius, 1 % with half that. PODI's blend of three trained dents is
    not the dent at all.

    Why 3 % and 4 % under the tool (they were 2 % and 3 %): each neighbour's field lies on
    its own lattice and the three are read at the same place of their cells, so their
    interpolation errors add instead of partly cancelling. Over 200 random contacts of this
    plate the largest errors rose a little (field 2.47 -> 2.62 %, under the tool 3.29 ->
    3.77 %: the old bounds held at these three points, not everywhere), the medians
    doubled and more (0.97 -> 2.0 %, 0.87 -> 3.2 %). On the cornea demo's held-out solves
    the field error is unchanged (2.31 -> 2.30 %), the dent under the tool 0.25 -> 0.53 %."""
    exact = dent(slab.vertices, np.array(point))
    transported, blended = slab.transported(point), slab.blended(point)
    error = relative(transported, exact)
    assert error < 0.03  # h = 0.2 mm against a dent of radius 0.6 mm
    assert relative(blended, exact) > 0.5  # what the transport fixes: the test can fail
    fine = relative(fine_slab.transported(point), dent(fine_slab.vertices, np.array(point)))
    assert fine < 0.01  # (this plate's samples sit on its nodes: every lattice is the grid)
    tool = int(np.argmin(np.linalg.norm(slab.vertices - point, axis=1)))
    assert abs(transported[tool, 2] - exact[tool, 2]) < 0.04  # under the tool: 4 % of the dent
    deepest = int(np.argmin(transported[:, 2]))
    assert np.linalg.norm(slab.vertices[deepest, :2] - slab.vertices[tool, :2]) <= SPACING


def test_shifted_lattices_converge_at_second_order():
    """The samples moved off the grid's nodes (0.037, 0.061 mm), so that every sample's
    modes lie on a lattice moved from the grid on both plates (the fine plate's own samples
    sit on its nodes): at 20 random contacts the field error falls about fourfold when the
    grid is halved (bilinear reads, second order: measured 4.6x at the medians, the largest
    2.0 -> 0.41 % over 63 contacts), and stays within 1 % on the fine plate."""
    offset = np.array([0.037, 0.061, 0.0])
    coarse = PlateModel(thickness=0.5, offset=offset)
    fine = PlateModel(thickness=0.5, spacing=SPACING / 2, offset=offset)
    for model in (coarse, fine):
        fraction = model.chart.sample_grid % 1.0
        assert np.all(np.minimum(fraction, 1.0 - fraction) > 0.1)  # no lattice is the grid
    rng = np.random.default_rng(3)
    points = np.column_stack([rng.uniform(-2.5, 2.5, (20, 2)), np.zeros(20)]) + offset
    errors = np.array([
        [relative(m.transported(p), dent(m.vertices, p)) for m in (coarse, fine)]
        for p in points
    ])  # fmt: skip
    assert errors[:, 1].max() < 0.01
    assert np.median(errors[:, 0]) > 3.0 * np.median(errors[:, 1])


@pytest.mark.parametrize("n", [2, 3, 5, 9])
def test_every_mode_is_carried(n):
    """A sample's modes are summed four at a call (node_blocks.block_modes: fewer padded
    with zero terms, more summed on in the same registers), each in units of its own scale
    (16 bits): with n
    dents of different radii and amplitudes (1 to 1e3, so the scales differ) a sample and
    coefficients of alternating sign, the transported field is the sum of the n dents under
    the tool, within the one-mode plate's 3 %. A mode left out, counted twice or scaled by
    another mode's scale is off by 15 % of the field or more (the test can fail)."""
    radii = np.linspace(SIGMA, 2 * SIGMA, n)
    coefficients = np.array([(-1.0) ** m * (1.0 + 0.5 * m) for m in range(n)])
    amplitudes = np.logspace(0.0, 3.0, n)
    model = PlateModel(thickness=0.5, radii=radii, coefficients=coefficients / amplitudes,
                       amplitudes=amplitudes)  # fmt: skip
    assert np.ptp(np.log10(model.chart.mode_scale)) > 2.0
    point = np.array([0.37, -0.81, 0.0])
    parts = [c * dent(model.vertices, point, r) for r, c in zip(radii, coefficients, strict=True)]
    exact = sum(parts)
    assert relative(model.transported(point), exact) < 0.03
    assert min(np.linalg.norm(q) for q in parts) > 0.15 * np.linalg.norm(exact)


def test_a_training_position_reads_back_its_own_field(slab, monkeypatch):
    """No shift: the grid fitted to the vertices (back-projection) reads back the sample's
    own field, several times closer than the grid of the surface's values alone."""
    point = slab.points[12]
    fitted = relative(slab.transported(point), slab.blended(point))
    monkeypatch.setattr(surface_chart_module, "BACK_PROJECTIONS", 0)
    unfitted_model = PlateModel(thickness=0.5)
    unfitted = relative(unfitted_model.transported(point), unfitted_model.blended(point))
    assert fitted < 5e-3 and fitted < unfitted / 5


def test_the_field_is_continuous_as_the_contact_slides(slab):
    """Along a line across several sample triangles in 0.01 mm steps, no vertex jumps:
    each step changes the field by at most what moving the exact dent 0.01 mm does, times
    a margin for the interpolation."""
    step = 0.01
    path = np.column_stack([np.arange(-2.0, 2.0, step), np.full(400, 0.3), np.zeros(400)])
    slope = np.exp(-0.5) * np.sqrt(2.0) / SIGMA  # the exact dent's steepest slope
    previous = slab.transported(path[0])
    for p in path[1:]:
        field = slab.transported(p)
        assert np.max(np.abs(field - previous)) < 3 * slope * step
        previous = field


def test_the_sides_keep_the_blended_field(slab):
    """Walls (normal across the plan view) are not charted: PODI's values there."""
    walls = np.abs(slab.vertices[:, 2] + 0.25) < 0.2  # strictly between the two surfaces
    assert walls.any() and np.all(np.isin(np.flatnonzero(walls), slab.chart.uncharted))
    point = (0.37, -0.81, 0.0)
    uncharted = slab.chart.uncharted
    np.testing.assert_allclose(
        slab.transported(point)[uncharted], slab.blended(point)[uncharted], atol=1e-6
    )


def test_the_lower_surface_is_carried_too(slab):
    """Both sheets of the plate: the dent on the lower surface moves with the contact, as
    closely as the upper one (the plate's dent is the same on both sheets)."""
    point = np.array([0.37, -0.81, 0.0])
    lower = slab.vertices[:, 2] < -0.4
    upper = slab.vertices[:, 2] > -0.1
    exact, field = dent(slab.vertices, point), slab.transported(point)
    error = relative(field[lower], exact[lower])
    assert error < 0.03
    assert error <= 1.05 * relative(field[upper], exact[upper])


def test_samples_facing_all_around_have_no_chart():
    """A closed organ trained all over: no plan view holds it, so there is no chart, the
    simulator's default field is PODI's and the transport is refused with a clear error."""
    from types import SimpleNamespace

    from test_surface_interpolation import icosphere

    from hapticrom.online.simulator import _check_config
    from hapticrom.shared.errors import InputError

    vertices, faces = icosphere(2)
    points = vertices[::7]
    normals = points / np.linalg.norm(points, axis=1)[:, None]
    basis = np.zeros((len(points), vertices.size, 1), dtype=np.float32)
    triangles = np.array([[0, 1, 2]], dtype=np.int64)
    assert surface_chart(vertices, faces, points, normals, triangles, basis) is None
    model = SimpleNamespace(chart=None, anm=None, grassmann=None)
    with pytest.raises(InputError, match="interpolation='podi'"):
        _check_config(model, "transport", "curves")
    assert _check_config(model, "podi", None) == "curves"


def test_the_grid_is_bounded_whatever_the_mesh(monkeypatch):
    """A fine mesh (or long sample edges) cannot make the chart allocate without bound: the
    grid coarsens until the modes on it fit in MAX_VALUES."""
    vertices, triangles = plate(0.5)
    points, normals, sample_triangles = samples_on(3.0)
    basis = np.stack([dent(vertices, p).reshape(-1, 1) for p in points]).astype(np.float32)
    free = surface_chart(vertices, triangles, points, normals, sample_triangles, basis)
    cap = free.node_basis.size // 4
    monkeypatch.setattr(surface_chart_module, "MAX_VALUES", cap)
    bounded = surface_chart(vertices, triangles, points, normals, sample_triangles, basis)
    assert bounded.node_basis.size <= cap < free.node_basis.size
    assert bounded.spacing > free.spacing

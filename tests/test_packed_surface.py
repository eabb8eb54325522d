"""The surfaces Python renders on the packed arrays (packed_surface.ENTRIES, one call) against
the same kernels called on the model's arrays one by one, and the packing itself."""

from __future__ import annotations

import numpy as np
import pytest

from hapticrom.online import load, packed_surface, surface_kernels
from hapticrom.online.renderer import SurfaceWork


@pytest.fixture(scope="module")
def model(small_artifact):
    return load(small_artifact)


def array_by_array(model, interpolation, response, buf) -> np.ndarray:
    """The surface of the state ``buf``, each kernel given its arrays one by one."""
    m, n = model, model.num_modes
    c, out = np.zeros((3, n)), np.zeros_like(model.vertices)
    if response == "anm":
        surface_kernels.anm_coefficients(buf, m.anm["offsets"], m.anm["coefficients"], c)
    else:
        surface_kernels.curves_coefficients(buf, m.coefficients, c)
    if interpolation == "podi":
        surface_kernels.blended_surface(buf, c, m.surface_basis_t, out)
        return out
    ch = m.chart
    surface_kernels.transported_surface(
        buf, c, ch.node_basis, ch.mode_scale, ch.sample_grid, m.sample_normals, ch.shape,
        ch.blocks, ch.halo, ch.charted, ch.charted_node, ch.charted_frac, ch.uncharted,
        ch.uncharted_basis, np.zeros((int(np.prod(ch.shape)), 4), dtype=np.float32),
        np.zeros((3, 2), dtype=np.int64),
        np.zeros((3, surface_kernels.terms_width(n)), dtype=np.float32),
        np.zeros((4, len(ch.charted)), dtype=np.float32), np.zeros(len(ch.charted), np.int64),
        np.zeros(3 * len(ch.uncharted)), out,
    )  # fmt: skip
    return out


def contacts(model, count: int = 8) -> np.ndarray:
    """Contacts at sample triangles' centroids and between, half of them off the surface."""
    rng = np.random.default_rng(5)
    corners = model.sample_points[model.sample_triangles[rng.integers(len(model.sample_triangles),
                                                                      size=count)]]  # fmt: skip
    weights = rng.dirichlet(np.ones(3), size=count)
    points = np.einsum("pk,pkx->px", weights, corners)
    return points + rng.normal(scale=0.1, size=points.shape) * (np.arange(count) % 2)[:, None]


@pytest.mark.parametrize("interpolation", ["transport", "podi"])
@pytest.mark.parametrize("response", ["anm", "curves"])
def test_one_packed_call_renders_what_the_kernels_render(model, interpolation, response):
    if interpolation == "transport" and model.chart is None:
        pytest.skip("the test artifact has no chart")
    sim = model.simulator(interpolation, response)
    assert sim._work.entry is packed_surface.ENTRIES[interpolation, response]
    out = np.zeros_like(model.vertices)
    for point in contacts(model):
        sim.set_contact(point)
        sim.step_displacement(-0.6 * model.trained_depth * np.asarray(sim.contact_normal))
        sim.surface_displacement(out)
        expected = array_by_array(model, interpolation, response, sim._buf)
        assert np.abs(expected).max() > 0
        np.testing.assert_array_equal(out, expected)


@pytest.mark.parametrize("interpolation", ["transport", "podi", "compliance"])
def test_the_packed_addresses_are_the_works_own_arrays(model, interpolation):
    if interpolation == "transport" and model.chart is None:
        pytest.skip("the test artifact has no chart")
    if interpolation == "compliance" and model.contact_fields is None:
        pytest.skip("the test artifact has no contact fields")
    work = SurfaceWork(model, interpolation, "curves")
    names = packed_surface.SURFACE_ARRAYS
    for i, name in enumerate(names):
        a = work.arrays.get(name)
        if a is None:
            assert work.addresses[i] == 0 and not work.dims[i].any()
            continue
        assert work.addresses[i] == a.ctypes.data, name
        assert tuple(work.dims[i, : a.ndim]) == a.shape and not work.dims[i, a.ndim :].any()
    assert work.arrays["coefficients_out"] is work.coefficients  # scratch: the work's own
    if interpolation == "transport":
        assert work.arrays["chart_grid"] is work.chart_grid
        assert work.arrays["read_weights"] is work.chart_weights
        assert work.arrays["halo"][0] == model.chart.halo
    assert (work.entry is None) == (interpolation == "compliance")


def test_pack_refuses_an_array_that_is_not_c_contiguous():
    with pytest.raises(ValueError, match="C-contiguous"):
        packed_surface.pack({"coefficients": np.zeros((4, 6))[:, ::2]})


def test_a_copied_simulator_renders_from_its_own_arrays(model):
    """deepcopy packs the copy afresh: its addresses are its own arrays', and it renders
    the same surface after the original is gone (copied as they were, the addresses would
    point into the original's freed scratch)."""
    import copy
    import gc

    interpolation = "transport" if model.chart is not None else "podi"
    sim = model.simulator(interpolation, "curves")
    sim.set_contact(model.sample_points[model.sample_triangles[0]].mean(axis=0))
    sim.step_displacement(-0.5 * model.trained_depth * np.asarray(sim.contact_normal))
    expected = sim.surface_displacement(np.zeros_like(model.vertices)).copy()
    twin = copy.deepcopy(sim)
    work = twin._work
    assert work.addresses[0] == work.arrays["coefficients_out"].ctypes.data
    assert work.addresses[0] != sim._work.addresses[0]
    del sim
    gc.collect()
    np.testing.assert_array_equal(twin.surface_displacement(np.zeros_like(expected)), expected)

"""The surfaces Python renders on the packed arrays (packed_surface.ENTRIES, one call) against
the same kernels called on the model's arrays one by one, and the packing itself."""

from __future__ import annotations

import numpy as np
import pytest

from hapticrom.online import load, packed_surface, surface_kernels
from hapticrom.online.renderer import SurfaceWork, surface_of
from hapticrom.shared.errors import ArtifactError, OutputArrayError


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
        packed_surface.pack({"coefficients": np.zeros((2, 4, 6))[:, :, ::2]})


def test_a_copied_work_renders_from_its_own_arrays(model):
    """A SurfaceWork's copy is packed afresh: its addresses are its own arrays', and it
    renders the same surface after the original is gone (copied as they were, the addresses
    would point into the original's freed scratch)."""
    import copy
    import gc

    interpolation = "transport" if model.chart is not None else "podi"
    sim = model.simulator(interpolation, "curves")
    sim.set_contact(model.sample_points[model.sample_triangles[0]].mean(axis=0))
    sim.step_displacement(-0.5 * model.trained_depth * np.asarray(sim.contact_normal))
    expected = sim.surface_displacement(np.zeros_like(model.vertices)).copy()
    work = SurfaceWork(model, interpolation, "curves")
    twin = copy.deepcopy(work)
    assert twin.addresses[0] == twin.arrays["coefficients_out"].ctypes.data
    assert twin.addresses[0] != work.addresses[0]
    del work
    gc.collect()
    out = np.zeros_like(expected)
    surface_of(sim._buf.copy(), twin, out)
    np.testing.assert_array_equal(out, expected)


def test_a_simulator_is_not_copied(model):
    """Its outputs are views into its state buffer and its surface's packed addresses are its
    own: copies would come apart from both, so they are refused with one clear error."""
    import copy
    import pickle

    sim = model.simulator()
    for copier in (copy.copy, copy.deepcopy, pickle.dumps):
        with pytest.raises(TypeError, match="cannot be copied or pickled"):
            copier(sim)


def test_the_renderer_thread_renders_what_the_kernels_render(model):
    interpolation = "transport" if model.chart is not None else "podi"
    sim = model.simulator(interpolation, "curves")
    renderer = sim.renderer()
    out = np.zeros_like(model.vertices)
    for point in contacts(model, 4):
        sim.set_contact(point)
        sim.step_displacement(-0.4 * model.trained_depth * np.asarray(sim.contact_normal))
        renderer.surface(out)
        np.testing.assert_array_equal(out, array_by_array(model, interpolation, "curves", sim._buf))


def test_a_read_only_out_is_refused_by_name(model):
    sim = model.simulator()
    with pytest.raises(OutputArrayError, match="writeable"):
        sim.surface_displacement(model.vertices)  # read only


def test_pack_refuses_an_array_of_another_type_naming_it():
    """A model built by hand skips the load's conversions: the bodies would read a float64
    basis's bytes as float32, so the packing refuses it."""
    with pytest.raises(ArtifactError, match="surface_basis_t must be a 3-d float32 array"):
        packed_surface.pack({"surface_basis_t": np.zeros((2, 3, 6))})
    offsets = np.zeros(5, dtype=np.int64)  # POD-ANM's coefficients are the sections' offsets
    packed_surface.pack({"coefficients": offsets}, "anm")
    with pytest.raises(ArtifactError, match="coefficients must be a 3-d float64"):
        packed_surface.pack({"coefficients": offsets}, "curves")

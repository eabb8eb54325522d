"""The surface grid's vector blocks (online/node_blocks.py) against numpy, and the chart's
blocks (surface_chart.node_blocks) against the nodes the reads need."""

from __future__ import annotations

import numpy as np
import pytest
from numba import njit
from numba.core.errors import TypingError
from test_surface_field import PlateModel

from hapticrom.online.node_blocks import (
    LANES,
    MODES_A_BLOCK,
    ROTATION,
    block_modes,
    block_rotate,
    block_store,
    node_read,
)
from hapticrom.online.surface_chart import node_blocks, nodes_read
from hapticrom.online.surface_kernels import terms_width
from hapticrom.online.vector_tiles import tile
from hapticrom.shared.errors import ArtifactError


@njit
def _sum_block(node_basis, slots, terms, g, grid):
    """grid[g : g + LANES] from the slots (sample, shift) through the intrinsics."""
    P, acc = tile(grid), tile(grid)
    for j in range(slots.shape[0]):
        for k in range(0, node_basis.shape[1], MODES_A_BLOCK):
            block_modes(P, node_basis, slots[j, 0], terms, j, k, g + slots[j, 1], k == 0)
        block_rotate(acc, P, terms, j, j == 0)
    block_store(grid, g, acc)


def _expected_block(node_basis, slots, terms, g):
    n = node_basis.shape[1]
    total = np.zeros((LANES, 3))
    for j, (i, shift) in enumerate(slots):
        planes = node_basis[i, :, :, g + shift : g + shift + LANES].astype(np.float64)
        sums = np.einsum("m,mcb->bc", terms[j, ROTATION : ROTATION + n].astype(np.float64), planes)
        total += sums @ terms[j, :ROTATION].astype(np.float64).reshape(3, 3).T
    return total


@pytest.mark.parametrize("modes", [1, 3, 4, 5, 9])
@pytest.mark.parametrize("neighbours", [1, 3])
def test_a_block_is_the_neighbours_rotated_mode_sums(modes, neighbours):
    """Every mode and every neighbour is summed once, at its shift, rotated by its terms,
    and the block is written (x, y, z, 0) a node; the padding terms past the last mode
    count nothing, though the last mode's plane is read again (NaN-free)."""
    rng = np.random.default_rng(modes * 10 + neighbours)
    nodes = 200
    node_basis = rng.integers(-32767, 32768, size=(5, modes, 3, nodes)).astype(np.int16)
    terms = np.zeros((3, terms_width(modes)), dtype=np.float32)
    terms[:, : ROTATION + modes] = rng.uniform(-1e-3, 1e-3, (3, ROTATION + modes))
    # past the last mode the terms are zero (neighbour_terms writes them so)
    slots = np.array([[4, 17], [0, -9], [2, 40]], dtype=np.int64)[:neighbours]
    grid = np.full((nodes, 4), np.nan, dtype=np.float32)
    g = 60
    _sum_block(node_basis, slots, terms, g, grid)
    expected = _expected_block(node_basis, slots, terms, g)
    np.testing.assert_allclose(grid[g : g + LANES, :3], expected, rtol=2e-5, atol=1e-4)
    assert np.all(grid[g : g + LANES, 3] == 0.0)
    assert np.all(np.isnan(grid[:g])) and np.all(np.isnan(grid[g + LANES :]))  # nothing else


@njit
def _read(grid, cells, columns, weights, vertices, out):
    for k in range(len(cells)):
        node_read(out, vertices[k], grid, cells[k], columns, weights[k, 0], weights[k, 1],
                  weights[k, 2], weights[k, 3])  # fmt: skip


def test_a_node_read_is_the_bilinear_of_four_nodes_into_its_vertex_only():
    rng = np.random.default_rng(7)
    columns, nodes = 13, 13 * 11
    grid = rng.standard_normal((nodes, 4)).astype(np.float32)
    cells = rng.integers(0, nodes - columns - 1, size=50)
    weights = rng.uniform(0, 1, (50, 4)).astype(np.float32)
    vertices = rng.permutation(80)[:50]
    out = np.full((80, 3), np.nan)
    _read(grid, cells, columns, weights, vertices, out)
    corners = np.stack([cells, cells + columns, cells + 1, cells + columns + 1], axis=1)
    expected = np.einsum("kq,kqc->kc", weights, grid[corners, :3])
    np.testing.assert_allclose(out[vertices], expected, rtol=1e-5, atol=1e-6)
    untouched = np.setdiff1d(np.arange(80), vertices)
    assert np.all(np.isnan(out[untouched]))  # each read writes its own row, three values


@njit
def _store_into(grid):
    acc = tile(grid)
    block_store(grid, 0, acc)


@njit
def _read_from(grid, out):
    node_read(out, 0, grid, 0, 1, 1.0, 0.0, 0.0, 0.0)


def test_the_intrinsics_refuse_arrays_they_would_misread():
    """Strided, Fortran-ordered, double or read-only grids and outputs are refused at
    compile time."""
    grid, out = np.zeros((32, 4), dtype=np.float32), np.zeros((4, 3))
    for bad in (grid[::2], np.asfortranarray(grid), grid.astype(np.float64)):
        with pytest.raises(TypingError):
            _read_from(bad, out)
    frozen = out.copy()
    frozen.flags.writeable = False
    for bad in (out[::2], np.asfortranarray(out), out.astype(np.float32), frozen):
        with pytest.raises(TypingError):
            _read_from(grid, bad)
    readonly = grid.copy()
    readonly.flags.writeable = False
    with pytest.raises(TypingError):
        _store_into(readonly)


def test_the_chart_blocks_cover_every_read_and_stay_inside_the_grid():
    """The plate's chart: every node a charted vertex's read can touch lies in a block, and
    every block, moved by the largest shift the clamp lets through, lies in the grid."""
    chart = PlateModel(thickness=0.5).chart
    _, _, columns = (int(v) for v in chart.shape)
    nodes = int(np.prod(chart.shape))
    reach = (chart.halo - 1) * (columns + 1)
    needed = nodes_read(chart.charted_node, columns)
    runs = (chart.blocks[:, None] + np.arange(LANES)).ravel()
    assert np.isin(needed, runs).all()
    assert chart.blocks.min() >= reach and chart.blocks.max() + LANES + reach <= nodes
    assert len(runs) < 1.25 * len(needed) + LANES  # the runs hold few nodes no read needs


def test_a_chart_whose_reads_cannot_fit_runs_is_refused():
    """A grid whose halo leaves no room for a run of LANES nodes around the read nodes is
    refused with ArtifactError (a chart the kernel could not sum), not built."""
    shape = (2, 9, 9)
    charted_node = np.array([4 * 9 + 4], dtype=np.int64)  # the middle of layer 0
    with pytest.raises(ArtifactError, match="runs of"):
        node_blocks(charted_node, shape, halo=5)
    blocks = node_blocks(charted_node, shape, halo=2)
    assert np.isin(nodes_read(charted_node, 9), blocks[:, None] + np.arange(LANES)).all()

"""POD-ANM series computed by groups of ranks, and reused by a re-reduction.

The MPI tests run under ``mpirun -n 2``. A small campaign (coarse hemisphere,
neo-Hookean with an element-wise pressure, force control: the load vector and the
pressure snapshots are part of every series' input) is solved once by rank 0; its
reductions then run on both ranks.

Groups against one group: a series computed on one rank differs from the same series
on two ranks by rounding only (the residual's assembly sums in another order). The
Taylor coefficients of the depth, the force and the reduced coordinates agree to
about 4e-14 of their largest value (measured); 1e-10 leaves room for the reduced
tangent, whose solve at every order carries the rounding into the next. The validity
radius a_max = (tol |y_1| / |y_N|)^(1/(N-1)) comes from the highest coefficient y_N,
the one with the most rounding (it grows like eps 4^N through the Cauchy integrals,
and |y_N| is small): 9e-9 relative measured. What a_max decides is the truncation
error at the section's end, tol (a / a_max)^(N-1), which a relative change d of a_max
moves by (N - 1) d relative: 1e-6 is asked, immaterial against tol = 1e-4. A second
section would start at the first one's a_max and inherit that 1e-8 in its values, so
the campaign is one where one section covers the load (checked).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
from mpi4py import MPI

from hapticrom.offline.campaign.config import CampaignConfig
from hapticrom.offline.campaign.run import run_campaign
from hapticrom.offline.campaign.store import SnapshotStore
from hapticrom.offline.mpi import on_rank_zero
from hapticrom.offline.reduce import anm_reduction
from hapticrom.offline.reduce.anm_reduction import (
    SERIES_FOLDER,
    SeriesInput,
    model_fingerprint,
    sample_series,
    series_groups,
    series_key,
)
from hapticrom.offline.reduce.inputs import OperatorRows, campaign_config, read_samples
from hapticrom.offline.reduce.operators import PODSettings, reduce_samples
from hapticrom.offline.reduce.reduction import reduce_campaign
from hapticrom.shared.errors import InputError, SolverError

SAMPLES = 5  # the pole and a ring of 4 (distinct nodes of the coarse mesh)


def campaign_text(mesh: Path) -> str:
    return f"""
[campaign]
name = "anm-groups"
[mesh]
file = "{mesh}"
[material]
law = "neo-hookean"
E = 2.0
nu = 0.48
[load]
mode = "force"
magnitude = 10.0
contact_radius = 4.0
steps = 4
[positions]
points = [[0.0, 0.0, 0.0]]
[[positions.polar]]
centre = [0.0, 0.0, 0.0]
radius = 8.0
rings = 1
per_ring = {SAMPLES - 1}
include_centre = false
"""


@pytest.fixture(scope="module")
def campaign(mesh_dir, tmp_path_factory) -> Path:
    """The campaign's folder (TOML and ``store``), solved by rank 0 alone; every rank."""
    comm = MPI.COMM_WORLD
    if comm.size != 2:
        pytest.skip("run under mpirun -n 2")
    root = Path(comm.bcast(str(tmp_path_factory.mktemp("anm")) if comm.rank == 0 else None))
    if comm.rank == 0:
        (root / "c.toml").write_text(campaign_text(mesh_dir / "hemisphere-coarse.msh"))
        config = CampaignConfig.from_toml(root / "c.toml")
        run_campaign(config, root / "store", MPI.COMM_SELF, verbose=False)
    comm.barrier()
    return root


@pytest.fixture
def computed(monkeypatch):
    """The samples whose series this rank computed as its group's root (in order)."""
    calls = []
    original = anm_reduction.one_sample_series

    def counting(config, data, setting, comm):
        if comm.rank == 0:
            calls.append(data.index)
        return original(config, data, setting, comm)

    monkeypatch.setattr(anm_reduction, "one_sample_series", counting)
    return calls


def reduce_with(root: Path, out: str, ranks_per_series: int = 1, order: int = 6) -> Path:
    """Reduce the campaign on every rank with these ``[anm]`` keys; the artifact's path."""
    comm = MPI.COMM_WORLD
    anm = f"\n[anm]\nranks_per_series = {ranks_per_series}\norder = {order}\n"
    toml = root / f"{out}.toml"
    if comm.rank == 0:
        toml.write_text(campaign_text(Path(_mesh_of(root))) + anm)
    comm.barrier()
    reduction = CampaignConfig.from_toml(toml)
    reduce_campaign(root / "store", root / f"{out}.h5", comm, verbose=False, reduction=reduction)
    return root / f"{out}.h5"


def _mesh_of(root: Path) -> str:
    return CampaignConfig.from_toml(root / "c.toml").problem.mesh.file


def forget_stored_series(root: Path) -> None:
    comm = MPI.COMM_WORLD
    if comm.rank == 0:
        shutil.rmtree(root / "store" / SERIES_FOLDER, ignore_errors=True)
    comm.barrier()


def total(calls: list) -> int:
    """The series computed by every group together."""
    return MPI.COMM_WORLD.allreduce(len(calls), op=MPI.SUM)


def contents(path: Path) -> dict:
    """Every dataset and attribute of an HDF5 file but its creation time."""
    out = {}
    with h5py.File(path, "r") as f:
        for key, value in f.attrs.items():
            if key != "created":
                out[f"@{key}"] = value

        def visit(name, obj):
            if isinstance(obj, h5py.Dataset):
                out[name] = obj[()]
            for key, value in obj.attrs.items():
                out[f"{name}@{key}"] = value

        f.visititems(visit)
    return out


def assert_identical(a: dict, b: dict, skip: str = "\0") -> None:
    keys = [k for k in a if not k.startswith(skip)]
    assert sorted(keys) == sorted(k for k in b if not k.startswith(skip))
    for key in keys:
        assert np.array_equal(np.asarray(a[key]), np.asarray(b[key])), key


@pytest.mark.mpi
def test_groups_give_the_one_group_series(campaign, computed):
    comm = MPI.COMM_WORLD
    forget_stored_series(campaign)
    one = reduce_with(campaign, "one-group", ranks_per_series=2)
    assert total(computed) == SAMPLES  # one group of both ranks: rank 0 is its root
    forget_stored_series(campaign)
    computed.clear()
    two = reduce_with(campaign, "two-groups", ranks_per_series=1)
    # Round-robin: group 0 (rank 0) computed samples 0, 2, ..., group 1 the others.
    assert sorted(sum(comm.allgather(computed), [])) == list(range(SAMPLES))
    assert computed == list(range(comm.rank, SAMPLES, 2))
    if comm.rank != 0:
        return
    a, b = contents(one), contents(two)
    assert_identical(a, b, skip="anm")  # nothing but the series depends on the groups
    np.testing.assert_array_equal(b["anm/section_offsets"], a["anm/section_offsets"])
    assert np.array_equal(a["anm/section_offsets"], np.arange(SAMPLES + 1))  # one section each
    for name in ("depth", "force", "coefficients"):
        scale = np.abs(a[f"anm/{name}"]).max()
        np.testing.assert_allclose(b[f"anm/{name}"], a[f"anm/{name}"], rtol=0, atol=1e-10 * scale)
    np.testing.assert_allclose(b["anm/a_max"], a["anm/a_max"], rtol=1e-6)


@pytest.mark.mpi
def test_a_reduction_reuses_the_series_it_can(campaign, computed):
    comm = MPI.COMM_WORLD
    forget_stored_series(campaign)
    first = contents(reduce_with(campaign, "first"))
    assert total(computed) == SAMPLES
    computed.clear()
    again = contents(reduce_with(campaign, "again"))
    assert total(computed) == 0
    if comm.rank == 0:
        assert_identical(first, again)
    # A damaged entry (a value changed under its checksum) is computed again, not trusted.
    if comm.rank == 0:
        entry = sorted((campaign / "store" / SERIES_FOLDER).glob("*.h5"))[0]
        with h5py.File(entry, "r+") as f:
            f["coefficients"][0, 0, 0] += 1.0
    comm.barrier()
    computed.clear()
    repaired = contents(reduce_with(campaign, "repaired"))
    assert total(computed) == 1
    if comm.rank == 0:
        assert_identical(first, repaired)
    # Another series order changes every series: nothing is reused.
    computed.clear()
    other = contents(reduce_with(campaign, "order-5", order=5))
    assert total(computed) == SAMPLES
    if comm.rank == 0:
        assert other["anm@order"] == 5
        assert not np.array_equal(other["anm/coefficients"], first["anm/coefficients"])


@pytest.mark.mpi
def test_a_failing_series_fails_every_rank_and_keeps_the_others(campaign, monkeypatch):
    """Sample 1 fails in group 1 (rank 1, its first sample): both ranks raise its error,
    nothing is written, and group 0's series stay stored for the next reduction."""
    original = anm_reduction.one_sample_series

    def failing(config, data, setting, group):
        if data.index == 1:
            raise SolverError("ANM: sample 1 does not converge (injected)")
        return original(config, data, setting, group)

    monkeypatch.setattr(anm_reduction, "one_sample_series", failing)
    forget_stored_series(campaign)
    with pytest.raises(SolverError, match="sample 1 does not converge"):
        reduce_with(campaign, "failing")
    assert not (campaign / "failing.h5").exists()
    stored = list((campaign / "store" / SERIES_FOLDER).glob("*.h5"))
    assert len(stored) == len(range(0, SAMPLES, 2))  # group 0's share: samples 0, 2, ...


@pytest.mark.mpi
def test_a_stored_branch_is_projected_onto_a_new_basis(campaign, computed):
    """Another artifact basis (here each sample's modes reversed and negated: the exact
    change of coordinates c -> -c reversed) reuses every stored branch, projected onto it.

    The projection B^T [g, A] is then summed in canonical order on one rank instead of
    the group's order: rounding of a dot product of bs N terms, ~1e-15 of the largest
    coefficient; 1e-12 asked.
    """
    comm = MPI.COMM_WORLD
    forget_stored_series(campaign)
    store = SnapshotStore(campaign / "store")
    manifest = on_rank_zero(comm, store.manifest)
    config = campaign_config(store, manifest, None)
    samples, layout = read_samples(store, manifest, config, comm)
    ops = OperatorRows(store, layout)
    reduced, _ = reduce_samples(comm, samples, ops, layout.rows, PODSettings.of(config.pod, ops))
    first = sample_series(config, samples, reduced, comm, store_in=store.root)
    assert total(computed) == SAMPLES
    computed.clear()
    for r in reduced:
        r.basis_local = -r.basis_local[:, ::-1]
    again = sample_series(config, samples, reduced, comm, store_in=store.root)
    assert total(computed) == 0
    for a, b in zip(first, again, strict=True):
        for name in ("a_max", "depth", "force"):
            np.testing.assert_array_equal(getattr(b, name), getattr(a, name))
        assert a.coefficients.shape[-1] >= 2  # the reversal moves something
        expected = -a.coefficients[..., ::-1]
        scale = np.abs(expected).max()
        np.testing.assert_allclose(b.coefficients, expected, rtol=0, atol=1e-12 * scale)


class FakeComm:
    def __init__(self, size: int):
        self.size, self.rank = size, 0


def test_a_group_size_that_does_not_divide_the_ranks_is_refused():
    with pytest.raises(InputError, match=r"\[anm\] ranks_per_series = 2 must divide .* \(3\)"):
        series_groups(FakeComm(3), 2)
    assert series_groups(FakeComm(3), 5).count == 1  # at most every rank: one group


@pytest.mark.parametrize("value", ["0", "1.5", "true", '"2"'])  # as written in the TOML
def test_a_hostile_group_size_is_one_line_naming_the_key(mesh_dir, tmp_path, value):
    text = campaign_text(mesh_dir / "hemisphere-coarse.msh")
    (tmp_path / "c.toml").write_text(text + f"\n[anm]\nranks_per_series = {value}\n")
    with pytest.raises(InputError, match=r"\[anm\] ranks_per_series"):
        CampaignConfig.from_toml(tmp_path / "c.toml")


def test_the_key_covers_what_a_branch_reads(mesh_dir, tmp_path):
    """Each input of a branch changes its key; nothing else does."""
    text = campaign_text(mesh_dir / "hemisphere-coarse.msh")
    (tmp_path / "c.toml").write_text(text)
    config = CampaignConfig.from_toml(tmp_path / "c.toml")
    rng = np.random.default_rng(7)
    data = SeriesInput(
        0, rng.random((6, 4)), rng.random((2, 4)), rng.random((6, 1)), rng.random((6, 2))
    )
    base = series_key(model_fingerprint(config), data)
    variants = {
        "material": text.replace("E = 2.0", "E = 2.5"),
        "load": text.replace("magnitude = 10.0", "magnitude = 12.0"),
        "anm order": text + "\n[anm]\norder = 7\n",
        "anm tolerance": text + "\n[anm]\ntolerance = 1e-5\n",
        "truncation": text + "\n[pod]\neigenvalue_ratio = 1e-9\n",
        "quadrature": text.replace("[load]", "[discretisation]\nquadrature_degree = 3\n[load]"),
        "element": text.replace("[load]", '[discretisation]\nelement = "Q1"\n[load]'),
    }
    for what, variant in variants.items():
        (tmp_path / "v.toml").write_text(variant)
        other = CampaignConfig.from_toml(tmp_path / "v.toml")
        assert series_key(model_fingerprint(other), data) != base, what
    for field in ("U", "P", "load"):
        array = getattr(data, field).copy()
        array[-1, -1] = np.nextafter(array[-1, -1], 2.0)  # one unit in the last place
        changed = SeriesInput(**{**data.__dict__, field: array})
        assert series_key(model_fingerprint(config), changed) != base, field
    # The group size, the sample's index and its artifact basis do not change the branch
    # (the basis only the projection, redone when it changes).
    (tmp_path / "v.toml").write_text(text + "\n[anm]\nranks_per_series = 2\n")
    same = CampaignConfig.from_toml(tmp_path / "v.toml")
    moved = SeriesInput(**{**data.__dict__, "index": 3, "basis": rng.random((6, 3))})
    assert series_key(model_fingerprint(same), moved) == base

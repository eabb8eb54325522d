"""Training campaigns: what is stored, crash safety (SIGKILL + resume), K0."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import replace

import h5py
import numpy as np
import pytest
from conftest import campaign_toml

from hapticrom.offline.campaign.positions import ToolPosition
from hapticrom.offline.campaign.run import CampaignConfig, run_campaign
from hapticrom.offline.campaign.store import SnapshotStore, csr_from, read_h5
from hapticrom.offline.config import LoadConfig, ProblemConfig
from hapticrom.offline.fe.dofs import CanonicalOrder
from hapticrom.offline.fe.fullorder import FullOrderModel
from hapticrom.offline.fe.operators import load_vector
from hapticrom.shared.errors import InputError

pytestmark = pytest.mark.serial


def test_campaign_stores_every_position(small_campaign):
    config, store, report = small_campaign
    assert report.positions == 5 and report.solved_now == 5 and report.failed == []
    manifest = store.manifest()
    assert [p["index"] for p in manifest["positions"]] == [0, 1, 2, 3, 4]
    assert store.completed() == [0, 1, 2, 3, 4]
    ops, attrs = store.read_operators()
    n = attrs["num_dofs"]
    for i in range(5):
        data, attrs = store.read_position(i)
        assert attrs["status"] == "solved"
        assert data["displacement"].shape == (4, n)
        np.testing.assert_allclose(data["load_factor"], [0.25, 0.5, 0.75, 1.0])
        # The tool pushes along the inward normal: the force on the tissue points inwards too.
        inward = np.asarray(attrs["direction"])
        assert np.all(data["force"] @ inward > 0)
        # The contact nodes move with the tool, exactly.
        u = data["displacement"][-1].reshape(-1, 3)
        np.testing.assert_allclose(u[data["contact_nodes"]], 0.3 * inward[None, :], atol=1e-12)
        # Supported nodes do not move.
        assert np.abs(u[ops["supported_nodes"]]).max() == 0.0


def test_stored_snapshot_equals_a_direct_solve(small_campaign):
    """Position 1's record is the full-order solution in canonical order."""
    config, store, _ = small_campaign
    data, attrs = store.read_position(1)
    p = store.manifest()["positions"][1]
    position = ToolPosition(1, tuple(p["point"]), tuple(p["normal"]), p["node_tag"], p["source"])
    load = config.load.at(position)
    assert np.allclose(load.displacement, 0.3 * np.asarray(attrs["direction"]))
    model = FullOrderModel(replace(config.problem, load=load), verbose=False)
    result = model.solve()
    u = CanonicalOrder(model.model.V).gather(model.model.u.x.array)
    np.testing.assert_allclose(u, data["displacement"][-1], rtol=0, atol=1e-12)
    np.testing.assert_allclose(result.force, data["force"], rtol=1e-12)


def test_reference_tangent_is_symmetric_and_consistent(small_campaign):
    """The stored K0 is the full model's tangent at u = 0, pressure condensed.

    A force of 1e-6 N keeps the full nonlinear solve in its linear range, so its
    solution u must satisfy K0 u = f on the free DOFs (f: its load vector).
    """
    config, store, _ = small_campaign
    ops, _ = store.read_operators()
    K0 = csr_from(ops, "K0")
    assert abs(K0 - K0.T).max() <= 1e-12 * abs(K0).max()
    load = LoadConfig(mode="force", force=(0.0, 0.0, -1e-6), contact_radius=1.0, steps=1)
    model = FullOrderModel(replace(config.problem, load=load), verbose=False)
    model.solve()
    order = CanonicalOrder(model.model.V)
    u = order.gather(model.model.u.x.array)
    f = load_vector(model.model, order)  # at load factor 1, where the solve ended
    free = np.ones(u.size, dtype=bool)
    free[(3 * ops["supported_nodes"][:, None] + np.arange(3)).ravel()] = False
    residual = (K0 @ u - f)[free]
    assert np.linalg.norm(residual) <= 1e-6 * np.linalg.norm(f)
    assert np.linalg.norm(f) > 0


def test_a_different_campaign_is_refused(small_campaign, mesh_dir, tmp_path):
    _, store, _ = small_campaign
    other = tmp_path / "other.toml"
    other.write_text(campaign_toml(mesh_dir / "cornea-coarse.msh", steps=5))
    with pytest.raises(InputError, match="holds a different campaign"):
        run_campaign(CampaignConfig.from_toml(other), store.root, verbose=False)


def test_a_damaged_record_is_detected(small_campaign, tmp_path):
    _, store, _ = small_campaign
    copy = tmp_path / "position.h5"
    copy.write_bytes(store.position_path(2).read_bytes())
    with h5py.File(copy, "r+") as f:
        f["displacement"][1, 10] += 1e-9  # a silent bit-level change, checksum not updated
    with pytest.raises(InputError, match="fails its checksum"):
        read_h5(copy)


def test_sigkill_and_resume_loses_nothing(small_campaign, mesh_dir, tmp_path):
    """Kill the campaign (SIGKILL) mid-run, twice, rerun: same data as an uninterrupted run."""
    _, reference, _ = small_campaign
    toml = tmp_path / "campaign.toml"
    toml.write_text(campaign_toml(mesh_dir / "cornea-coarse.msh"))
    out = tmp_path / "store"
    command = [sys.executable, "-m", "hapticrom", "campaign", str(toml), "--out", str(out)]
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    for target in (1, 3):  # kill once 1, then 3, records are complete
        proc = subprocess.Popen(
            command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env
        )
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline and proc.poll() is None:
            if len(list((out / "solves").glob("position-*.h5"))) >= target:
                break
            time.sleep(0.02)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        assert proc.returncode == -signal.SIGKILL, "the campaign finished before it was killed"
    done_before = SnapshotStore(out).completed()
    assert 1 <= len(done_before) < 5
    finished = subprocess.run(command, capture_output=True, text=True, env=env, timeout=600)
    assert finished.returncode == 0, finished.stderr
    assert f"{len(done_before)} already stored, resuming" in finished.stdout
    assert not list(out.rglob(".*.partial-*")), "a partial file was left behind"
    store = SnapshotStore(out)
    assert store.completed() == reference.completed()
    for i in reference.completed():
        mine, _ = store.read_position(i)
        ref, _ = reference.read_position(i)
        assert mine.keys() == ref.keys()
        for key in ref:
            np.testing.assert_array_equal(mine[key], ref[key], err_msg=f"position {i} {key}")


def flip_a_bit(path, dataset: str, byte: int = 8) -> None:
    """Flip one bit of ``dataset``'s stored values in the file's bytes (not through h5py)."""
    with h5py.File(path, "r") as f:
        offset = f[dataset].id.get_offset()
    assert offset is not None, "contiguous storage expected"
    with open(path, "r+b") as fh:
        fh.seek(offset + byte)
        value = fh.read(1)[0]
        fh.seek(offset + byte)
        fh.write(bytes([value ^ 0x01]))


@pytest.fixture
def store_copy(small_campaign, tmp_path):
    """A copy of the small campaign's store, to damage."""
    config, store, _ = small_campaign
    copy = tmp_path / "store"
    shutil.copytree(store.root, copy)
    return config, store, SnapshotStore(copy)


def test_damaged_records_are_solved_again_on_resume(store_copy, capsys):
    """A bit flip, a truncated file and damaged operators: detected, redone, nothing else."""
    config, reference, copy = store_copy
    flip_a_bit(copy.position_path(2), "displacement")
    truncated = copy.position_path(4)
    truncated.write_bytes(truncated.read_bytes()[:1000])
    flip_a_bit(copy.operators_path, "volumes")
    untouched = {i: copy.position_path(i).read_bytes() for i in (0, 1, 3)}
    with pytest.raises(InputError, match="fails its checksum"):
        copy.read_position(2)

    report = run_campaign(config, copy.root, verbose=True)
    out = capsys.readouterr().out
    assert report.redone == [2, 4] and report.solved_now == 2 and report.resumed == 3
    assert report.failed == []
    assert "3 already stored, resuming" in out
    assert "position 2: stored record is damaged: " in out and "fails its checksum" in out
    assert "position 4: stored record is damaged: " in out and "solving it again" in out
    assert "stored operators damaged: " in out and "computing them again" in out
    for i in (0, 1, 3):
        assert copy.position_path(i).read_bytes() == untouched[i], f"position {i} rewritten"
    for i in (2, 4):
        mine, attrs = copy.read_position(i)
        ref, _ = reference.read_position(i)
        assert attrs["status"] == "solved" and mine.keys() == ref.keys()
        for key in ref:
            np.testing.assert_array_equal(mine[key], ref[key], err_msg=f"position {i} {key}")
    ops, _ = copy.read_operators()
    np.testing.assert_array_equal(ops["volumes"], reference.read_operators()[0]["volumes"])
    assert copy.audit() == ([0, 1, 2, 3, 4], {})


def test_a_failed_position_is_retried_on_resume(store_copy, capsys):
    config, reference, copy = store_copy
    with h5py.File(copy.position_path(1), "r+") as f:  # as a run whose solve failed records it
        f.attrs["status"] = "failed"
        f.attrs["message"] = "no convergence at load factor 0.5"
    assert copy.audit()[1] == {1: "failed in an earlier run (no convergence at load factor 0.5)"}

    report = run_campaign(config, copy.root, verbose=True)
    out = capsys.readouterr().out
    assert report.redone == [1] and report.solved_now == 1 and report.failed == []
    assert "position 1: failed in an earlier run (no convergence at load factor 0.5); " in out
    assert "stored operators" not in out  # intact: not computed again
    _, attrs = copy.read_position(1)
    assert attrs["status"] == "solved" and attrs["message"] == ""
    np.testing.assert_array_equal(
        copy.read_position(1)[0]["displacement"], reference.read_position(1)[0]["displacement"]
    )


@pytest.mark.parametrize(
    "key, value, message",
    [
        ("steps", 99999999999, "steps must lie in [1, 100000], got 99999999999"),
        ("steps", 0, "steps must lie in [1, 100000], got 0"),
        ("steps", 2.5, "steps must be a finite integer, got 2.5"),
        ("max_step_cuts", -5, "max_step_cuts must lie in [0, 16], got -5"),
        ("max_step_cuts", 17, "max_step_cuts must lie in [0, 16], got 17"),
        ("predictor", "cubic", "predictor must be one of secant, none, got 'cubic'"),
        ("contact_radius", -1.0, "contact_radius must be positive, got -1.0"),
        ("surface", 3, "surface must be the name of a surface group, got 3"),
    ],
)
def test_campaign_and_problem_share_the_load_validator(small_campaign, key, value, message):
    """The same [load] value is refused by a campaign and a problem, with the same words."""
    config, _, _ = small_campaign
    campaign = {**config.raw, "load": {**config.raw["load"], key: value}}
    with pytest.raises(InputError) as from_campaign:
        CampaignConfig.from_dict(campaign, source="c.toml")
    problem = {
        "mesh": config.raw["mesh"],
        "material": config.raw["material"],
        "load": {"mode": "displacement", "displacement": [0.0, 0.0, -0.1], key: value},
    }
    with pytest.raises(InputError) as from_problem:
        ProblemConfig.from_dict(problem, source="c.toml")
    assert str(from_campaign.value) == str(from_problem.value) == f"c.toml: [load] {message}"

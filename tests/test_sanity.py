"""Physics sanity checks (offline/fe/sanity.py), each on a case built to trigger it.

Pure checks on synthetic load paths (the numbers are those of the pinched hemisphere,
examples/hemisphere-svk-pinch.toml at 30 N), real solves on coarse meshes (a few
seconds each), the snapped-position listing, validation before any campaign directory
exists, and (under mpirun -n 2) the distributed measures against serial ones.
"""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from mpi4py import MPI

from hapticrom.offline.fe import sanity
from hapticrom.offline.fe.sanity import StepSanity, campaign_summary, judge, next_finer_level
from hapticrom.offline.fe.solver import StepRecord
from hapticrom.shared.errors import InputError, SolverError

# Fine hemisphere, SVK, 3 N per step (measured): 0.94 -> 4.69 mm between 9 and 12 N.
SNAP_DEPTHS = [0.261, 0.557, 0.938, 4.687, 5.234, 5.948, 6.338, 6.748, 7.182, 7.643]
# Default hemisphere, SVK: smooth, but the stiffness falls to a fifth by 21 N.
SOFT_DEPTHS = [0.255, 0.536, 0.854, 1.231, 1.714, 2.447, 3.671, 4.748, 5.598, 6.424]
# Default hemisphere, neo-Hookean: nothing to flag.
NH_DEPTHS = [0.244, 0.489, 0.734, 0.982, 1.231, 1.483, 1.739, 1.998, 2.263, 2.534]


def path(depths, forces=None, **state) -> list[StepSanity]:
    """A synthetic load path: force control, 3 N per step unless ``forces`` are given."""
    forces = forces if forces is not None else [3.0 * (i + 1) for i in range(len(depths))]
    values = {"j_min": 0.9, "stretch_min": 0.9, "inverted": 0, "u_max": 1.0, **state}
    n = len(depths)
    return [
        StepSanity(i + 1, (i + 1) / n, d, f, where=[0.0, 0.0, 0.0], **values)
        for i, (d, f) in enumerate(zip(depths, forces, strict=True))
    ]


def kinds(report) -> list[str]:
    return [f.kind for f in report.flags]


# -- the load path (pure) ------------------------------------------------------------------
def test_snap_through_is_flagged_with_its_numbers():
    report = judge(path(SNAP_DEPTHS), "svk", "force")
    assert kinds(report) == ["jump"]
    flag = report.flags[0]
    assert flag.step == 4 and flag.value == pytest.approx(9.85, rel=1e-2)
    assert "0.938 to 4.687 mm between 9 and 12 N" in flag.message
    assert 'law = "neo-hookean"' in report.suggestion
    assert report.worst()["jump_ratio"]["step"] == 4


def test_smooth_paths_are_not_flagged():
    assert judge(path(NH_DEPTHS), "neo-hookean", "force").flags == []
    # Stiffening (displacement control of tissue): the force grows faster and faster.
    depths = [0.05 * (i + 1) for i in range(10)]
    forces = [0.01 * (i + 1) ** 2 for i in range(10)]
    assert judge(path(depths, forces), "hgo", "displacement").flags == []


def test_softening_towards_a_limit_point_is_flagged():
    report = judge(path(SOFT_DEPTHS), "svk", "force")
    assert kinds(report) == ["softening"]
    assert report.flags[0].step == 7 and report.flags[0].value == pytest.approx(4.8, rel=1e-2)


def test_limit_point_under_displacement_control():
    depths = [0.1 * (i + 1) for i in range(6)]
    forces = [1.0, 1.8, 2.3, 2.5, 2.4, 2.1]  # past a maximum
    report = judge(path(depths, forces), "neo-hookean", "displacement")
    assert kinds(report) == ["limit-point"]
    assert report.flags[0].step == 5 and "2.5 to 2.4 N" in report.flags[0].message
    assert "displacement control" not in report.suggestion or "smaller load" in report.suggestion


def test_a_failed_solve_after_softening_is_a_limit_point():
    steps = path(SOFT_DEPTHS[:7])
    report = judge(steps, "svk", "force", failure="Newton diverged at load factor 0.75")
    assert kinds(report) == ["limit-point"]
    assert "Newton diverged" in report.flags[0].message


def test_state_flags_and_suggestions():
    steps = path(NH_DEPTHS[:3], j_min=0.95, stretch_min=0.9)
    steps[1] = replace(steps[1], j_min=0.3, stretch_min=0.2)
    steps[2] = replace(steps[2], j_min=-0.1, stretch_min=0.0, inverted=3, tangent_negative=2)
    report = judge(steps, "neo-hookean", "force")
    assert kinds(report) == ["inversion", "compression", "tangent"]
    assert "3 inverted element(s)" in report.flags[0].message
    assert report.flags[1].value == 1.0 and report.flags[1].step == 3
    assert "finer mesh" in report.suggestion and "neo-hookean" not in report.suggestion
    steps[2] = replace(steps[2], j_min=0.4, stretch_min=0.2, inverted=0, tangent_negative=0)
    report = judge(steps, "svk", "force")
    assert kinds(report) == ["volume", "compression"]
    assert "compression 80% at step 2" in report.flags[1].message
    lines = report.warnings("position 3")
    assert lines[-1].startswith("position 3: SVK is unstable in compression")


def test_campaign_summary_layout():
    flagged = judge(path(SNAP_DEPTHS), "svk", "force").summary()
    clean = judge(path(NH_DEPTHS), "svk", "force").summary()
    summary = campaign_summary(
        [(0, [0, 0, 0], clean), (1, [1, 0, 0], flagged), (2, [2, 0, 0], None)], 4
    )
    assert summary["positions"] == 4 and summary["checked"] == 2
    assert [f["position"] for f in summary["flagged"]] == [1]
    assert summary["flagged"][0]["kinds"] == ["jump"]
    assert summary["worst"]["jump_ratio"]["position"] == 1
    assert set(summary["worst"]) >= {"j_min", "compression", "inverted", "u_max"}
    assert "neo-hookean" in summary["suggestion"]
    json.loads(sanity.dumps(summary))  # finite, strict JSON
    assert sanity.summary_lines(summary)[0].startswith("physics sanity: 1 of 2 position(s)")


# -- the measures on a real mesh --------------------------------------------------------------
def beam_model(mesh_dir, **load):
    from hapticrom.offline.config import ProblemConfig
    from hapticrom.offline.fe.fullorder import FullOrderModel

    config = ProblemConfig.from_dict(
        {
            "mesh": {"file": str(mesh_dir / "beam-coarse.msh")},
            "material": {"law": "svk", "E": 1.0, "nu": 0.3},
            "load": {
                "mode": "displacement",
                "displacement": [-28.0, 0.0, 0.0],
                "contact_point": [400.0, 0.0, 0.0],
                "contact_radius": 30.0,
                "steps": 1,
                **load,
            },
            "output": {"xdmf": False},
        }
    )
    return FullOrderModel(config, comm=MPI.COMM_SELF, verbose=False)


@pytest.mark.serial
def test_measures_of_prescribed_deformations(mesh_dir):
    """J, the smallest stretch and inverted cells of u = a x e_x: stretch and J are 1 + a."""
    model = beam_model(mesh_dir)
    monitor, u = model.monitor, model.model.u
    record = StepRecord(1, 1.0, 1, 0, 0.0)
    cells = 40
    for a, j, stretch, inverted in (
        (0.0, 1.0, 1.0, 0),
        (-0.6, 0.4, 0.4, 0),
        (-2.0, -1.0, 0, cells),
    ):
        u.interpolate(lambda x, a=a: np.vstack([a * x[0], 0 * x[1], 0 * x[2]]))
        step = monitor.measure(record, np.zeros(3), np.zeros(3))
        assert step.j_min == pytest.approx(j, abs=1e-12)
        assert step.stretch_min == pytest.approx(stretch, abs=1e-12)
        assert step.inverted == inverted
        assert step.u_max == pytest.approx(abs(a) * 400.0, rel=1e-12)
    report = judge(monitor.steps, "svk", "displacement")
    assert {"inversion", "compression"} <= set(kinds(report))  # J <= 0: not "volume"


@pytest.mark.serial
def test_tangent_loses_definiteness_under_buckling(mesh_dir):
    """A slender SVK column pushed along its axis: the straight state is past Euler's load."""
    model = beam_model(mesh_dir)
    model.monitor.tangent = "every"
    result = model.solve()
    assert result.sanity.steps[0].tangent_negative >= 1
    assert "tangent" in kinds(result.sanity)
    # Pulled instead, the same column is stable.
    model = beam_model(mesh_dir, displacement=[28.0, 0.0, 0.0])
    model.monitor.tangent = "every"
    assert model.solve().sanity.steps[0].tangent_negative == 0


def hemisphere_config(mesh_dir, law: str, force: float, steps: int = 10):
    from hapticrom.offline.config import ProblemConfig

    return ProblemConfig.from_dict(
        {
            "mesh": {"file": str(mesh_dir / "hemisphere-coarse.msh")},
            "material": {"law": law, "E": 2.0, "nu": 0.48},
            "load": {
                "mode": "force",
                "contact_point": [0.0, 0.0, 0.0],
                "contact_radius": 4.0,
                "force": [0.0, 0.0, -force],
                "steps": steps,
            },
            "output": {"xdmf": False},
        }
    )


@pytest.mark.serial
def test_svk_hemisphere_snaps_through_and_inverts(mesh_dir, tmp_path, capsys):
    """The pinched hemisphere of the example on the coarse mesh at 45 N (the coarse mesh is
    stiffer than the default one, which does this at 30 N)."""
    from hapticrom.offline.fe.fullorder import FullOrderModel

    model = FullOrderModel(hemisphere_config(mesh_dir, "svk", 45.0), comm=MPI.COMM_SELF)
    result = model.solve(tmp_path)
    assert kinds(result.sanity) == ["inversion", "compression", "jump"]
    jump = result.sanity.flags[2]
    assert jump.value > sanity.JUMP_FACTOR and jump.step == 8
    out = capsys.readouterr().out
    assert "warning: 4 inverted element(s)" in out and "snap-through" in out
    assert 'try law = "neo-hookean"' in out
    written = json.loads((tmp_path / "sanity.json").read_text())
    assert [f["kind"] for f in written["flags"]] == kinds(result.sanity)
    assert len(written["steps"]) == 10 and written["worst"]["inverted"]["value"] == 4
    # Neo-Hookean at the same load: a dent, no warning.
    model = FullOrderModel(hemisphere_config(mesh_dir, "neo-hookean", 45.0), comm=MPI.COMM_SELF)
    assert model.solve().sanity.flags == []


@pytest.mark.serial
def test_force_control_stopped_by_a_limit_point(mesh_dir):
    from hapticrom.offline.fe.fullorder import FullOrderModel

    config = hemisphere_config(mesh_dir, "svk", 60.0)
    config = replace(config, load=replace(config.load, max_step_cuts=3))
    model = FullOrderModel(config, comm=MPI.COMM_SELF, verbose=False)
    with pytest.raises(SolverError):
        model.solve()
    assert "limit-point" in kinds(model.sanity)


# -- the refinement check ---------------------------------------------------------------------
@pytest.mark.serial
def test_next_finer_level(mesh_dir, tmp_path):
    from hapticrom.meshes import generate

    assert next_finer_level(mesh_dir / "hemisphere-coarse.msh") == (
        "hemisphere",
        "coarse",
        "default",
    )
    generate("hemisphere", tmp_path / "fine.msh", "fine")
    with pytest.raises(sanity.RefinementUnavailable, match="already the finest"):
        next_finer_level(tmp_path / "fine.msh")
    generate("hemisphere", tmp_path / "thick.msh", "coarse", thickness=5.0)
    with pytest.raises(sanity.RefinementUnavailable, match="parameters other than"):
        next_finer_level(tmp_path / "thick.msh")
    info = json.loads((tmp_path / "thick.json").read_text())
    (tmp_path / "thick.json").write_text(json.dumps({**info, "name": "kidney"}))
    with pytest.raises(sanity.RefinementUnavailable, match="not a built-in mesh"):
        next_finer_level(tmp_path / "thick.msh")


@pytest.mark.serial
def test_refinement_check_reports_the_difference(mesh_dir, tmp_path):
    from hapticrom.offline.fe.fullorder import FullOrderModel

    config = hemisphere_config(mesh_dir, "neo-hookean", 10.0, steps=2)
    result = FullOrderModel(config, comm=MPI.COMM_SELF, verbose=False).solve(tmp_path)
    check = sanity.check_refinement(config, result, tmp_path, MPI.COMM_SELF)
    assert check["available"] and (check["level"], check["finer"]) == ("coarse", "default")
    assert check["load_factor"] == 1.0 and check["finer_status"] == "solved"
    d = check["displacement"]
    assert d["relative"] == pytest.approx(
        np.linalg.norm(np.subtract(d["coarse"], d["fine"])) / np.linalg.norm(d["fine"])
    )
    assert 0 < d["relative"] < 1 and check["force"]["relative"] == pytest.approx(0, abs=1e-12)
    assert (tmp_path / "refinement" / "hemisphere-default.msh").is_file()
    assert (tmp_path / "refinement" / "curve.csv").is_file()
    written = json.loads((tmp_path / "sanity.json").read_text())
    assert written["refinement"]["message"] == check["message"]
    assert "coarse -> default hemisphere mesh" in check["message"]


@pytest.mark.serial
def test_campaign_refinement_check(mesh_dir, tmp_path, capsys):
    """`campaign --refinement-check`: position 0 on the next finer mesh, refinement.json."""
    from hapticrom.cli import main
    from hapticrom.offline.campaign.store import SnapshotStore

    toml = write_campaign(tmp_path / "c.toml", mesh_dir / "cornea-coarse.msh", steps=2)
    out = tmp_path / "store"
    assert main(["campaign", str(toml), "--out", str(out), "--refinement-check"]) == 0
    printed = capsys.readouterr().out
    check = json.loads((out / "refinement.json").read_text())
    assert check["message"] in printed and "coarse -> default cornea mesh" in printed
    assert check["available"] and check["finer_status"] == "solved"
    data, _ = SnapshotStore(out).read_position(0)  # the stored position is the coarse side
    assert check["load_factor"] == data["load_factor"][-1] == 1.0
    np.testing.assert_array_equal(check["force"]["coarse"], data["force"][-1])
    np.testing.assert_array_equal(check["displacement"]["coarse"], data["contact_displacement"][-1])
    coarse, fine = check["force"]["coarse"][2], check["force"]["fine"][2]
    assert np.isfinite(fine) and fine < 0 and abs(fine - coarse) > 1e-3 * abs(coarse)
    assert check["force"]["difference"] == pytest.approx(abs(fine - coarse), rel=1e-6)
    assert (out / "refinement" / "cornea-default.msh").is_file()
    assert sorted(p.name for p in (out / "solves").iterdir()) == ["position-0000.h5"]
    assert "refinement" not in json.loads((out / "sanity.json").read_text())

    # A user mesh (a sidecar no built-in generator wrote): the check is not available.
    for suffix in (".msh", ".json"):
        (tmp_path / f"kidney{suffix}").write_bytes(
            (mesh_dir / f"cornea-coarse{suffix}").read_bytes()
        )
    info = json.loads((tmp_path / "kidney.json").read_text())
    (tmp_path / "kidney.json").write_text(json.dumps({**info, "name": "kidney"}))
    toml = write_campaign(tmp_path / "k.toml", tmp_path / "kidney.msh", steps=2)
    assert main(["campaign", str(toml), "--out", str(tmp_path / "k"), "--refinement-check"]) == 0
    printed = capsys.readouterr().out
    assert "refinement check: not available: kidney.msh is not a built-in mesh" in printed
    assert json.loads((tmp_path / "k" / "refinement.json").read_text())["available"] is False
    assert not (tmp_path / "k" / "refinement").exists()

    for command in ("campaign", "train"):
        with pytest.raises(SystemExit):
            main([command, "--help"])
        assert "--refinement-check" in capsys.readouterr().out


# -- campaigns: snapping, validation before the directory, storage -------------------------------
@pytest.mark.serial
def test_snapped_positions_are_listed(mesh_dir):
    from hapticrom.meshes.msh import read_surface
    from hapticrom.offline.campaign.positions import (
        PolarSampler,
        PositionsSpec,
        plan_with_report,
        snap_report_tolerance,
    )

    surface = read_surface(mesh_dir / "hemisphere-coarse.msh")
    ring = PolarSampler((0.0, 0.0, 0.0), 13.0, 1, 8, include_centre=False)
    spec = PositionsSpec(points=[(0.0, 0.0, 0.0), (0.5, 0.3, 0.0)], samplers=[ring])
    positions, text = plan_with_report(surface, spec)
    tolerance = snap_report_tolerance(surface)
    assert positions[0].snap_distance == 0.0 and positions[0].asked == (0.0, 0.0, 0.0)
    moved = [p for p in positions if p.snap_distance > tolerance]
    assert moved and all(p.source == "polar" for p in moved)
    for p in moved:  # each listed with asked and snapped coordinates and the distance
        row = next(
            line for line in text.splitlines() if line.split()[:2] == [str(p.index), "polar"]
        )
        assert float(row.split()[-1]) == pytest.approx(p.snap_distance, abs=1e-3)
    # The second point snaps to the pole again: it is dropped, and that is said.
    assert "asked point(s) dropped" in text and "point (0.5, 0.3, 0)" in text
    assert len({p.node_tag for p in positions}) == len(positions)


def write_campaign(path, mesh, material='law = "hgo"', steps=2, point=(0.0, 0.0, 0.0)):
    path.write_text(
        f"""
[mesh]
file = "{mesh}"
[material]
{material}
[load]
mode = "displacement"
magnitude = 0.2
contact_radius = 0.6
steps = {steps}
[positions]
points = [{list(point)}]
"""
    )
    return path


@pytest.mark.serial
@pytest.mark.parametrize(
    ("material", "mesh", "message"),
    [
        ('law = "svk"\nE = -2.0\nnu = 0.3', "cornea", "E must be positive"),
        ('law = "neo-hookean"\nE = 1.0\nnu = 0.5', "cornea", "nu must lie in"),
        ('law = "hgo"\nfibre_tension_only = true', "cornea", "fibre_tension_only"),
        ('law = "hgo"', "beam", "needs fibre directions"),
    ],
)
def test_mistakes_are_caught_before_any_directory(mesh_dir, tmp_path, material, mesh, message):
    from hapticrom.cli import main
    from hapticrom.offline.campaign.run import CampaignConfig, run_campaign

    point = (400.0, 0.0, 0.0) if mesh == "beam" else (0.0, 0.0, 0.0)
    toml = write_campaign(tmp_path / "c.toml", mesh_dir / f"{mesh}-coarse.msh", material, 2, point)
    out = tmp_path / "store"
    assert main(["campaign", str(toml), "--out", str(out)]) == 2
    assert not out.exists()
    with pytest.raises(InputError, match=message):  # the mesh's fibres: by run_campaign
        run_campaign(CampaignConfig.from_toml(toml), out, comm=MPI.COMM_SELF, verbose=False)
    assert not out.exists()


@pytest.mark.serial
def test_a_rerun_after_a_mistake_needs_no_restart(mesh_dir, tmp_path):
    """A directory whose campaign never solved a position is taken over without --restart."""
    from hapticrom.offline.campaign.positions import ToolPosition
    from hapticrom.offline.campaign.run import CampaignConfig, campaign_manifest, run_campaign
    from hapticrom.offline.campaign.store import SnapshotStore

    mesh = mesh_dir / "cornea-coarse.msh"
    first = CampaignConfig.from_toml(write_campaign(tmp_path / "a.toml", mesh, steps=3))
    store = SnapshotStore(tmp_path / "store")
    position = ToolPosition(0, (0, 0, 0), (0, 0, 1), 1, "point")
    store.open_or_create(campaign_manifest(first, [position]))
    fixed = CampaignConfig.from_toml(write_campaign(tmp_path / "b.toml", mesh, steps=2))
    report = run_campaign(fixed, store.root, comm=MPI.COMM_SELF, verbose=False)
    assert report.solved_now == 1 and report.failed == []
    assert store.manifest()["campaign_hash"] == fixed.campaign_hash()
    assert report.sanity["checked"] == 1
    assert json.loads((store.root / "sanity.json").read_text()) == json.loads(
        sanity.dumps(report.sanity)
    )


@pytest.mark.serial
def test_campaign_stores_sanity_and_the_artifact_summarises_it(small_campaign, small_artifact):
    from hapticrom.shared.artifact import read_artifact

    config, store, report = small_campaign
    data, attrs = store.read_position(1)
    summary = json.loads(attrs["sanity"])
    assert summary["version"] == sanity.VERSION and summary["law"] == "hgo"
    steps = len(data["load_factor"])
    for name in ("j_min", "stretch_min", "inverted", "u_max", "tangent_negative"):
        assert data[f"sanity/{name}"].shape == (steps,)
    assert 0.5 < data["sanity/j_min"].min() <= 1.0 and data["sanity/inverted"].max() == 0
    assert data["sanity/tangent_negative"][-1] == 0  # checked at the last step: stable
    assert report.sanity["checked"] == 5
    artifact = read_artifact(small_artifact)
    stored = artifact.attrs["sanity"]
    assert stored["positions"] == 5 and stored["checked"] == 5
    assert stored["worst"]["j_min"]["value"] == pytest.approx(
        min(store.read_position(i)[0]["sanity/j_min"].min() for i in range(5))
    )
    manifest = store.manifest()
    assert manifest["positions"][0]["asked"] == [0.0, 0.0, 0.0]


# -- parallel -----------------------------------------------------------------------------------
@pytest.mark.mpi
def test_measures_in_parallel_equal_serial(mesh_dir):
    from hapticrom.offline.fe.fullorder import FullOrderModel

    comm = MPI.COMM_WORLD
    if comm.size < 2:
        pytest.skip("run under mpirun -n 2")
    config = hemisphere_config(mesh_dir, "svk", 30.0, steps=4)
    distributed = FullOrderModel(config, comm=comm, verbose=False)
    distributed.monitor.tangent = "every"
    parallel = distributed.solve().sanity.steps
    serial_model = FullOrderModel(config, comm=MPI.COMM_SELF, verbose=False)
    serial_model.monitor.tangent = "every"
    serial = serial_model.solve().sanity.steps
    for p, s in zip(parallel, serial, strict=True):
        for name in ("j_min", "stretch_min", "u_max", "depth"):
            assert getattr(p, name) == pytest.approx(getattr(s, name), rel=1e-9), name
        assert (p.inverted, p.tangent_negative) == (s.inverted, s.tangent_negative)
        # Where: one of the cells symmetric about the axis (ties broken by roundoff).
        rz = [(np.hypot(w[0], w[1]), w[2]) for w in (p.where, s.where)]
        np.testing.assert_allclose(rz[0], rz[1], atol=1e-9)
    assert comm.allgather(parallel[-1].j_min) == [parallel[-1].j_min] * comm.size

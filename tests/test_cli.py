"""The command line: clear one-line errors on bad input, a plain message without the extra."""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

pytestmark = pytest.mark.serial

# Makes the offline stack unimportable in a child interpreter, as on a machine
# that installed only `pip install hapticrom`.
BLOCK_OFFLINE = textwrap.dedent(
    """
    import sys, importlib.abc
    class _Block(importlib.abc.MetaPathFinder):
        BLOCKED = ("dolfinx", "petsc4py", "slepc4py", "mpi4py", "ufl", "basix", "ffcx", "gmsh")
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] in self.BLOCKED:
                raise ModuleNotFoundError(f"No module named {name!r}", name=name)
    sys.meta_path.insert(0, _Block())
    """
)


def run_cli(*args, cwd=None, prelude: str = "") -> subprocess.CompletedProcess:
    code = prelude + "\nimport sys\nfrom hapticrom.cli import main\nsys.exit(main(sys.argv[1:]))\n"
    return subprocess.run(
        [sys.executable, "-c", code, *map(str, args)],
        capture_output=True,
        text=True,
        cwd=cwd,
        env={**os.environ, "PYTHONWARNINGS": "ignore"},
        timeout=600,
    )


def write_config(path: Path, mesh: Path, material: str, load: str) -> Path:
    path.write_text(f'[mesh]\nfile = "{mesh}"\n\n[material]\n{material}\n\n[load]\n{load}\n')
    return path


INDENT = 'mode = "displacement"\ndisplacement = [0.0, 0.0, -0.1]\nsteps = 2'


@pytest.mark.parametrize(
    "material, load, mesh_name, message",
    [
        ('law = "rubber"', INDENT, "cornea-coarse", "unknown material 'rubber'"),
        ('law = "svk"\nE = -2.0\nnu = 0.3', INDENT, "cornea-coarse", "E must be positive"),
        ('law = "hgo"\nC1 = -0.1', INDENT, "cornea-coarse", "C1 must be positive"),
        (
            'law = "hgo"',
            INDENT + "\ncontact_point = [0.0, 0.0, 5.0]",
            "cornea-coarse",
            "off the 'loadable' surface",
        ),
        ('law = "hgo"', INDENT, "no-such-mesh", "not found; generate it with `hapticrom mesh"),
        ('law = "hgo"', 'mode = "push"', "cornea-coarse", "mode must be one of"),
        ('law = "hgo"', INDENT + "\nstep = 3", "cornea-coarse", "unknown key(s) step"),
    ],
)
def test_bad_input_gives_one_clear_line(mesh_dir, tmp_path, material, load, mesh_name, message):
    config = write_config(tmp_path / "bad.toml", mesh_dir / f"{mesh_name}.msh", material, load)
    proc = run_cli("solve", config, "--out", tmp_path / "out")
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("hapticrom: error: ") and message in lines[0], lines[0]
    assert "Traceback" not in proc.stderr


def test_missing_config_file(tmp_path):
    proc = run_cli("solve", tmp_path / "nope.toml", "--out", tmp_path)
    assert proc.returncode == 2 and "configuration file" in proc.stderr


def test_solve_writes_curve_and_takes_petsc_options(mesh_dir, tmp_path):
    """PETSc options reach PETSc; the ones it never used are one warning line at the end."""
    config = write_config(
        tmp_path / "ok.toml", mesh_dir / "cornea-coarse.msh", 'law = "hgo"', INDENT
    )
    proc = run_cli(
        "solve", config, "--out", tmp_path / "out", "-hapticrom_snes_converged_reason",
        "-hapticrom_snes_rtoll", "1e-9", "-snes_rtol", "1e-9",
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    # The PETSc option reached SNES (under the hapticrom_ prefix).
    assert "Nonlinear hapticrom_ solve converged" in proc.stdout
    rows = list(csv.DictReader(open(tmp_path / "out" / "curve.csv")))
    assert len(rows) == 2 and float(rows[-1]["disp_z"]) == pytest.approx(-0.1)
    # The misspelt one and the one without the prefix: one line on stderr, none of PETSc's own
    warnings = [line for line in proc.stderr.splitlines() if "warning" in line]
    assert warnings == [
        "hapticrom: warning: PETSc option(s) never used: -hapticrom_snes_rtoll -snes_rtol "
        "(misspelt? not under the solver's prefix, hapticrom_ by default? for a solver this "
        "command does not create?)"
    ], proc.stderr
    assert "WARNING! There are options you set" not in proc.stdout + proc.stderr


def test_mesh_command_writes_mesh_and_sidecar(tmp_path):
    proc = run_cli("mesh", "beam", "--refinement", "coarse", "--out", tmp_path / "b.msh")
    assert proc.returncode == 0, proc.stderr
    info = json.loads((tmp_path / "b.json").read_text())
    assert info["counts"]["cells"] == 40 and "units mm" in proc.stdout
    proc = run_cli("mesh", "kidney", "--out", tmp_path / "k.msh")
    assert proc.returncode == 2, proc.stderr
    assert "argument name: invalid choice: 'kidney' (choose from 'cornea', 'beam'" in proc.stderr


@pytest.mark.parametrize(
    "command", [["mesh", "cornea"], ["solve", "x.toml", "--out", "o"], ["accuracy", "m.h5"]]
)
def test_offline_commands_say_the_extra_is_missing(tmp_path, command):
    proc = run_cli(*command, cwd=tmp_path, prelude=BLOCK_OFFLINE)
    assert proc.returncode == 3, proc.stderr
    assert "pip install 'hapticrom[offline]'" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_online_runtime_imports_without_the_offline_stack():
    code = BLOCK_OFFLINE + textwrap.dedent(
        """
        import hapticrom, hapticrom.online, hapticrom.shared, hapticrom.shared.units
        import hapticrom.cli
        bad = [m for m in sys.modules if m.split(".")[0] in _Block.BLOCKED]
        assert not bad, bad
        print("ok")
        """
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0 and proc.stdout.strip() == "ok", proc.stderr


def test_the_interpolation_option_offers_what_the_runtime_has():
    """The CLI keeps its own copy (it starts without numba): the same names."""
    from hapticrom.cli.online_commands import INTERPOLATIONS as offered
    from hapticrom.online.model import INTERPOLATIONS

    assert sorted(offered) == sorted(INTERPOLATIONS)


def test_play_and_bench_need_only_the_runtime(small_artifact, tmp_path):
    """The online commands run with the offline stack unimportable."""
    env_prelude = BLOCK_OFFLINE
    proc = run_cli("play", small_artifact, "--seconds", "0.2", cwd=tmp_path, prelude=env_prelude)
    assert proc.returncode == 0, proc.stderr
    assert "achieved" in proc.stdout and "Hz" in proc.stdout
    proc = run_cli("bench", small_artifact, "--steps", "2000", cwd=tmp_path, prelude=env_prelude)
    assert proc.returncode == 0, proc.stderr
    assert "step_displacement" in proc.stdout and "numpy" in proc.stdout


# -- the one-line-error promise: bad numbers, bad files, bad output locations -------------
def main_error(capsys, *args) -> str:
    """Run ``main`` here: exit status 2, one line ``hapticrom...error: ...``, no traceback."""
    from hapticrom.cli import main

    try:
        code = main([str(a) for a in args])
    except SystemExit as exc:  # argparse
        code = exc.code
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert code == 2, err
    assert len(lines) == 1, err
    assert lines[0].startswith("hapticrom") and "error:" in lines[0], err
    assert "Traceback" not in err
    return lines[0]


@pytest.fixture
def no_expensive_work(monkeypatch):
    """The solves and the reduction fail the test if they start."""
    import hapticrom.offline.campaign.run
    import hapticrom.offline.reduce.reduction

    def boom(*args, **kwargs):
        raise AssertionError("expensive work started before the input was checked")

    monkeypatch.setattr(hapticrom.offline.campaign.run, "run_campaign", boom)
    monkeypatch.setattr(hapticrom.offline.reduce.reduction, "reduce_campaign", boom)


def snapshot(directory: Path) -> dict:
    """Every path under ``directory`` with its bytes (files) or None (directories)."""
    return {
        p.relative_to(directory): (p.read_bytes() if p.is_file() else None)
        for p in sorted(directory.rglob("*"))
    }


def campaign_file(mesh_dir: Path, path: Path, **load) -> Path:
    from conftest import campaign_toml

    text = campaign_toml(mesh_dir / "cornea-coarse.msh", steps=load.pop("steps", 4))
    extra = "".join(f"{key} = {value}\n" for key, value in load.items())
    path.write_text(text.replace("[positions]", extra + "[positions]"))
    return path


@pytest.mark.parametrize("command", ["solve", "campaign", "train", "anm"])
def test_a_non_utf8_toml_is_one_line_naming_it(tmp_path, capsys, no_expensive_work, command):
    bad = tmp_path / "latin1.toml"
    bad.write_bytes('[campaign]\nname = "cornée"\n'.encode("latin-1"))
    out = tmp_path / "out"
    line = main_error(capsys, command, bad, "--out", out)
    assert f"{bad}: not valid TOML (not UTF-8 text: byte 0xe9" in line, line
    assert snapshot(tmp_path).keys() == {Path("latin1.toml")}


@pytest.mark.parametrize(
    "load, message",
    [
        ({"steps": 99999999999}, "[load] steps must lie in [1, 100000], got 99999999999"),
        ({"steps": 0}, "[load] steps must lie in [1, 100000], got 0"),
        ({"max_step_cuts": -5}, "[load] max_step_cuts must lie in [0, 16], got -5"),
        ({"max_step_cuts": 17}, "[load] max_step_cuts must lie in [0, 16], got 17"),
    ],
)
def test_campaign_load_is_bounded_like_a_problem(
    mesh_dir, tmp_path, capsys, no_expensive_work, load, message
):
    toml = campaign_file(mesh_dir, tmp_path / "c.toml", **load)
    line = main_error(capsys, "campaign", toml, "--out", tmp_path / "out")
    assert line == f"hapticrom: error: {toml}: {message}"
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    "args, message",
    [
        (["play", "--rate", "0"], "argument --rate: must be above 0 and at most 100000 Hz, got 0"),
        (["play", "--rate", "-5"], "argument --rate: must be above 0"),
        (["play", "--rate", "nan"], "argument --rate: must be above 0"),
        (["play", "--rate", "1e9"], "argument --rate: must be above 0 and at most 100000 Hz"),
        (["play", "--seconds", "1e12"], "argument --seconds: must be above 0 and at most 3600 s"),
        (["play", "--seconds", "0"], "argument --seconds: must be above 0"),
        (["play", "--seconds", "nan"], "argument --seconds: must be above 0"),
        (["play", "--seconds", "inf"], "argument --seconds: must be above 0"),
        (["play", "--seconds", "soon"], "argument --seconds: expected a number, got 'soon'"),
        (["play", "--rate", "1", "--seconds", "0.5"], "is 0 servo ticks; give between 1 and"),
        (["play", "--rate", "1e5", "--seconds", "3600"], "is 360,000,000 servo ticks"),
        (["bench", "--steps", "0"], "argument --steps: must lie in [1, 2,000,000], got 0"),
        (["bench", "--steps", "-3"], "argument --steps: must lie in [1, 2,000,000], got -3"),
        (["bench", "--steps", "99999999999"], "must lie in [1, 2,000,000], got 99,999,999,999"),
        (["report", "--out", "r", "--latency-steps", "0"], "argument --latency-steps: must lie"),
    ],
)
def test_online_numbers_are_bounded(small_artifact, tmp_path, capsys, monkeypatch, args, message):
    monkeypatch.chdir(tmp_path)
    line = main_error(capsys, args[0], small_artifact, *args[1:])
    assert line.startswith(f"hapticrom: error: {args[0]}") and message in line, line
    assert not any(tmp_path.iterdir())


def test_campaign_out_on_a_file(mesh_dir, tmp_path, capsys, no_expensive_work):
    toml = campaign_file(mesh_dir, tmp_path / "c.toml")
    target = tmp_path / "results"
    target.write_text("precious\n")
    line = main_error(capsys, "campaign", toml, "--out", target)
    assert line == f"hapticrom: error: campaign --out {target} exists and is not a directory"
    assert target.read_text() == "precious\n"
    line = main_error(capsys, "campaign", toml, "--out", target / "sub")
    assert f"{target} is not a directory" in line


@pytest.mark.parametrize(
    "content, message",
    [
        (b'{"format": "hapticrom-campaign", "vers', "is damaged: not valid JSON"),
        (b"\xff\xfe{}", "is damaged: not valid JSON"),
        (b"[1, 2]", "is not a hapticrom-campaign manifest"),
        (
            b'{"format": "hapticrom-campaign", "version": 2, "campaign_hash": "x"}',
            "is damaged: campaign must be an object",
        ),
    ],
)
def test_a_corrupt_manifest_is_one_line_naming_it(
    small_campaign, mesh_dir, tmp_path, capsys, no_expensive_work, content, message
):
    _, store, _ = small_campaign
    copy = tmp_path / "store"
    shutil.copytree(store.root, copy)
    (copy / "manifest.json").write_bytes(content)
    before = snapshot(copy)
    toml = campaign_file(mesh_dir, tmp_path / "c.toml")
    for args in (["campaign", toml, "--out", copy], ["reduce", copy, "--out", tmp_path / "m.h5"]):
        line = main_error(capsys, *args)
        assert line.startswith(f"hapticrom: error: {copy / 'manifest.json'} {message}"), line
    assert snapshot(copy) == before and not (tmp_path / "m.h5").exists()


@pytest.fixture
def read_only_dir(tmp_path):
    """A directory nobody can create files in, root included (chattr +i when root)."""
    d = tmp_path / "read-only"
    d.mkdir()
    d.chmod(0o555)
    immutable = False
    if os.geteuid() == 0:
        immutable = subprocess.run(["chattr", "+i", str(d)], capture_output=True).returncode == 0
        if not immutable:
            d.chmod(0o755)
            pytest.skip("running as root and chattr +i is not available")
    try:
        yield d
    finally:
        if immutable:
            subprocess.run(["chattr", "-i", str(d)], check=True)
        d.chmod(0o755)


def test_output_files_are_checked_before_any_work(
    small_campaign, mesh_dir, tmp_path, capsys, no_expensive_work, read_only_dir
):
    _, store, _ = small_campaign
    toml = campaign_file(mesh_dir, tmp_path / "c.toml")
    a_file = tmp_path / "a-file"
    a_file.write_text("")
    under_a_file = a_file / "models" / "model.h5"
    for command in (["reduce", store.root], ["train", toml]):
        line = main_error(capsys, *command, "--out", under_a_file)
        assert line == (
            f"hapticrom: error: {command[0]} --out {under_a_file}: {a_file} is not a directory"
        )
        line = main_error(capsys, *command, "--out", read_only_dir / "model.h5")
        assert f"cannot write in {read_only_dir} (" in line, line
        line = main_error(capsys, *command, "--out", tmp_path)
        assert f"--out {tmp_path} is a directory; give a file name" in line, line
    assert a_file.read_text() == "" and not any(read_only_dir.iterdir())
    assert not (tmp_path / "model.campaign").exists()


def test_report_and_bench_outputs_are_checked_first(small_artifact, tmp_path, capsys):
    target = tmp_path / "report.html"
    target.write_text("old report\n")
    line = main_error(capsys, "report", small_artifact, "--out", target)
    assert line == f"hapticrom: error: report --out {target} exists and is not a directory"
    assert target.read_text() == "old report\n"
    missing = tmp_path / "missing" / "bench.json"
    line = main_error(capsys, "bench", small_artifact, "--json", missing)
    assert f"bench --json {missing}: directory {missing.parent} does not exist" in line
    assert sorted(tmp_path.iterdir()) == [target]


def test_mesh_out_through_a_file(tmp_path, capsys):
    blocker = tmp_path / "meshes"
    blocker.write_text("not a directory\n")
    out = blocker / "sub" / "beam.msh"
    line = main_error(capsys, "mesh", "beam", "--refinement", "coarse", "--out", out)
    assert line == f"hapticrom: error: mesh --out {out}: {blocker} is not a directory"
    assert sorted(tmp_path.iterdir()) == [blocker]


def test_reduce_onto_a_full_disk_leaves_nothing_behind(
    small_campaign, tmp_path, capsys, monkeypatch
):
    """The disk fills while the artifact is written: one line, no .partial file, old file kept."""
    import errno

    import h5py

    _, store, _ = small_campaign
    out = tmp_path / "model.h5"
    out.write_bytes(b"the previous model\n")
    create_dataset = h5py.Group.create_dataset
    calls = []

    def full_disk(self, name, *args, **kwargs):
        if ".partial-" in self.file.filename:
            calls.append(name)
            if len(calls) == 3:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return create_dataset(self, name, *args, **kwargs)

    monkeypatch.setattr(h5py.Group, "create_dataset", full_disk)
    line = main_error(capsys, "reduce", store.root, "--out", out)
    assert len(calls) == 3, "the artifact writer was not reached"
    assert f"cannot write the artifact {out}: No space left on device" in line or (
        f"cannot write {out}: No space left on device" in line
    ), line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model.h5"]
    assert out.read_bytes() == b"the previous model\n"


# -- hapticrom accuracy: bad input is one line, before any solve --------------------------------
@pytest.mark.parametrize(
    "args, message",
    [
        (["--positions", "0"], "argument --positions: must lie in [1, 1,000], got 0"),
        (["--positions", str(10**9)], "must lie in [1, 1,000], got 1,000,000,000"),
        (["--positions", "many"], "argument --positions: expected an integer, got 'many'"),
        (["--seed", "-1"], "argument --seed: must lie in [0, 4,294,967,295], got -1"),
        (["--seed", "1.5"], "argument --seed: expected an integer, got '1.5'"),
        (["--seed", "1", "--softest"], "argument --softest: not allowed with argument --seed"),
        (["--outside", "1", "--seed", "2"], "argument --seed: not allowed with argument --outside"),
        (["--outside", "-1"], "argument --outside: must lie in [0, 4,294,967,295], got -1"),
        (
            ["--anywhere", "1", "--outside", "2"],
            "argument --outside: not allowed with argument --anywhere",
        ),
        (["--anywhere", "x"], "argument --anywhere: expected an integer, got 'x'"),
    ],
)
def test_accuracy_numbers_are_bounded(small_artifact, tmp_path, capsys, monkeypatch, args, message):
    monkeypatch.chdir(tmp_path)
    line = main_error(capsys, "accuracy", small_artifact, *args)
    assert line.startswith("hapticrom: error: accuracy: ") and message in line, line
    assert not any(tmp_path.iterdir())


def test_accuracy_inputs_and_outputs_are_checked_first(
    small_artifact, tmp_path, capsys, no_expensive_work, read_only_dir
):
    missing = tmp_path / "nope.h5"
    line = main_error(capsys, "accuracy", missing)
    assert line == f"hapticrom: error: artifact {missing} not found"
    damaged = tmp_path / "damaged.h5"
    damaged.write_bytes(small_artifact.read_bytes()[:-100])
    line = main_error(capsys, "accuracy", damaged, "--work", tmp_path / "w")
    assert line.startswith(f"hapticrom: error: {damaged} "), line  # the artifact's own check
    out = read_only_dir / "a.json"
    line = main_error(capsys, "accuracy", small_artifact, "--json", out)
    assert f"accuracy --json {out}: cannot write in {read_only_dir} (" in line, line
    out = tmp_path / "missing" / "a.json"
    line = main_error(capsys, "accuracy", small_artifact, "--json", out)
    assert line.endswith(f"accuracy --json {out}: directory {out.parent} does not exist"), line
    blocker = tmp_path / "work"
    blocker.write_text("not a directory\n")
    line = main_error(capsys, "accuracy", small_artifact, "--work", blocker)
    assert line == f"hapticrom: error: accuracy --work {blocker} exists and is not a directory"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["damaged.h5", "read-only", "work"]
    assert not any(read_only_dir.iterdir()) and blocker.read_text() == "not a directory\n"
    assert not small_artifact.with_suffix(".heldout-8").exists()


def test_accuracy_needs_the_mesh_the_model_was_trained_on(
    small_artifact, tmp_path, capsys, no_expensive_work, monkeypatch
):
    """A model whose mesh is gone or changed cannot be checked: one line saying so."""
    import hapticrom.shared.artifact

    read_artifact = hapticrom.shared.artifact.read_artifact
    mesh = tmp_path / "mesh.msh"  # the model's mesh, as seen by the check: a copy to spoil

    def read_with_mesh_here(path, *args, **kwargs):
        artifact = read_artifact(path, *args, **kwargs)
        artifact.group_attrs["model"]["mesh_file"] = str(mesh)
        return artifact

    monkeypatch.setattr(hapticrom.shared.artifact, "read_artifact", read_with_mesh_here)
    work = tmp_path / "w"
    mesh.write_text("")  # present but changed: not the bytes the model was trained on
    line = main_error(capsys, "accuracy", small_artifact, "--work", work)
    assert line == (
        f"hapticrom: error: {mesh} has changed since {small_artifact} was trained on it "
        "(SHA-256 differs): held-out solves on it would not test this model"
    )
    mesh.unlink()
    mesh.mkdir()  # not a file
    line = main_error(capsys, "accuracy", small_artifact, "--work", work)
    assert f"{small_artifact} was trained on {mesh}, which is not found" in line, line
    assert not work.exists()


# -- the front door: unknown options, -v/-q, every option explained ------------------------------
ONLINE_COMMANDS = {
    "play": ["MODEL"],
    "bench": ["MODEL"],
    "report": ["MODEL", "--out", "r"],
    "export": ["MODEL", "--out", "e"],
    "check": ["c.toml"],
}


@pytest.mark.parametrize("command", sorted(ONLINE_COMMANDS))
@pytest.mark.parametrize(
    "typo, message",
    [
        (["-steps", "5"], "unknown option -steps"),
        (
            ["-hapticrom_snes_rtol", "1e-9"],
            "unknown option -hapticrom_snes_rtol; hapticrom {} takes no PETSc options",
        ),  # fmt: skip
        (["--stepz", "5"], "unknown option --stepz"),
        (["-vx"], "unknown option -vx"),
    ],
)
def test_online_commands_refuse_unknown_options(
    small_artifact, tmp_path, capsys, monkeypatch, command, typo, message
):
    """A mistyped option is one line naming it, never silently ignored (nor given to PETSc)."""
    monkeypatch.chdir(tmp_path)
    args = [str(small_artifact) if a == "MODEL" else a for a in ONLINE_COMMANDS[command]]
    line = main_error(capsys, command, *args, *typo)
    assert line.startswith(f"hapticrom: error: {command}: {message.format(command)}"), line
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize(
    "args, message",
    [
        (["bench", "MODEL", "-steps", "5"], "unknown option -steps; did you mean --steps?"),
        (["bench", "MODEL", "--step", "5"], "unknown option --step; did you mean --steps?"),
        (["play", "MODEL", "-free-running"], "did you mean --free-running?"),
        (["report", "MODEL", "-out", "r"], "did you mean --out?"),
        (["bench", "MODEL", "--interpolation", "linear"], "invalid choice: 'linear'"),
        (["bench", "MODEL", "--response", "both"], "invalid choice: 'both'"),
        (["bench", "MODEL", "extra"], "unexpected argument(s): extra"),
        (["solve", "c.toml", "-out", "o"], "unknown option -out; did you mean --out?"),
        (["campaign", "c.toml", "--out", "o", "-snes_monitor", "--restart"],
         "--restart comes after a PETSc option: the command's own options go first"),
        (["solve", "c.toml", "--out", "o", "--", "--outt"], "unknown option --outt"),
        (["train", "c.toml", "--out", "m.h5", "--restat"], "did you mean --restart?"),
        (["mesh", "beam", "-refinement", "coarse"], "did you mean --refinement?"),
        (["mesh", "beam", "--refinement", "medium"], "invalid choice: 'medium'"),
        (["anm", "c.toml", "--out", "o", "--order", "16"], "must lie in [1, 15], got 16"),
        (["anm", "c.toml", "--out", "o", "--quiet", "--verbose"], "not allowed with argument"),
    ],
)  # fmt: skip
def test_mistakes_name_the_option(small_artifact, tmp_path, capsys, monkeypatch, args, message):
    monkeypatch.chdir(tmp_path)
    args = [str(small_artifact) if a == "MODEL" else a for a in args]
    line = main_error(capsys, *args)
    assert message in line, line
    assert not any(tmp_path.iterdir())


def test_every_option_has_help_and_choices_are_declared():
    from hapticrom.cli import build_parser

    parser = build_parser()
    for name, sub in parser.commands.items():
        for action in sub._actions:
            assert action.help, f"hapticrom {name} {action.option_strings or action.dest}"
        text = sub.format_help()  # also checks the %-formats of the help strings
        assert "-v, --verbose" in text and "-q, --quiet" in text
    choices = {
        (name, a.dest): a.choices for name, sub in parser.commands.items() for a in sub._actions
    }
    assert choices["bench", "interpolation"] == ("transport", "compliance", "podi", "grassmann")
    assert choices["bench", "response"] == ("anm", "curves")
    assert choices["mesh", "refinement"] == ("coarse", "default", "fine")
    assert list(choices["mesh", "name"]) == ["cornea", "beam", "hemisphere", "liver", "import"]


def play_output(capsys, *options) -> tuple[str, str]:
    from hapticrom.cli import main

    code = main([*filter(None, options[:1]), "play", *options[1:]])  # a global option first
    assert code == 0
    captured = capsys.readouterr()
    return captured.out, captured.err


def test_quiet_and_verbose(small_artifact, capsys):
    """-q silences the progress and the information, -v adds debug lines; before or after the
    command. The default output is what it always was."""
    fast = [str(small_artifact), "--seconds", "0.05", "--free-running"]
    out, err = play_output(capsys, None, *fast)  # no global option
    assert out.startswith("playing ") and "achieved" in out and err == ""
    for quiet in (["-q", *fast], ["--quiet", *fast], [None, *fast, "-q"]):
        assert play_output(capsys, *quiet) == ("", "")
    out, err = play_output(capsys, "-v", *fast)
    assert "achieved" in out
    assert err.startswith("hapticrom: debug: hapticrom ") and "play: exit status 0" in err
    err = play_output(capsys, None, *fast, "--verbose")[1]
    assert err.startswith("hapticrom: debug: ") and "play: exit status 0" in err


def test_quiet_keeps_results_warnings_and_errors(small_artifact, tmp_path, capsys):
    from hapticrom.cli import main

    assert main(["-q", "bench", str(small_artifact), "--steps", "500"]) == 0
    out = capsys.readouterr().out
    assert "step_displacement" in out and "target" in out  # the result, not progress
    assert main(["-q", "report", str(tmp_path / "nope.h5"), "--out", str(tmp_path / "r")]) == 2
    assert capsys.readouterr().err.startswith("hapticrom: error: artifact ")


def test_unused_petsc_options_are_reported_and_taken_back():
    """In-process (PETSc already running): the options are put in for the command, the unused
    ones named, and all taken out of PETSc's database afterwards."""
    pytest.importorskip("petsc4py")
    from mpi4py import MPI  # noqa: F401
    from petsc4py import PETSc

    from hapticrom.cli.petsc import PetscOptions, parse_options, unused_message

    assert parse_options(["word", "-a_b", "1", "-flag", "-c", "-2.5", "stray"]) == [
        ("a_b", "1"), ("flag", None), ("c", "-2.5"),
    ]  # fmt: skip
    tokens = ["-hapticrom_test_used", "3", "-hapticrom_test_unused", "-options_left", "no"]
    options = PetscOptions(tokens)
    try:
        options.start()
        database = PETSc.Options()
        assert database.getInt("hapticrom_test_used") == 3
        assert options.unused() == ["-hapticrom_test_unused"]  # -options_left: read at exit
        assert "never used: -hapticrom_test_unused (misspelt?" in unused_message(options.unused())
    finally:
        options.take_back()
    assert not any(database.hasName(name) for name in ("hapticrom_test_used", "options_left"))


def fake_module(monkeypatch, name: str, **functions):
    """Stand-in for a module another part of the project provides."""
    import types

    module = types.ModuleType(name)
    module.__dict__.update(functions)
    monkeypatch.setitem(sys.modules, name, module)
    return module


def test_check_is_wired(tmp_path, capsys, monkeypatch):
    from hapticrom.cli import main
    from hapticrom.shared.errors import InputError

    seen = []

    def check_config(path: Path) -> str:
        seen.append(path)
        if path.name == "bad.toml":
            raise InputError(f"{path}: [load] steps must lie in [1, 100000], got 0")
        return f"{path}: problem, hgo on cornea.msh, 10 steps: ok"

    import hapticrom.offline  # noqa: F401 - the parent package is the real one

    fake_module(monkeypatch, "hapticrom.offline.check", check_config=check_config)
    good = tmp_path / "good.toml"
    assert main(["-q", "check", str(good)]) == 0  # the summary is the result: -q keeps it
    assert capsys.readouterr().out == f"{good}: problem, hgo on cornea.msh, 10 steps: ok\n"
    assert seen == [good] and isinstance(seen[0], Path)
    bad = tmp_path / "bad.toml"
    line = main_error(capsys, "check", bad)
    assert line == f"hapticrom: error: {bad}: [load] steps must lie in [1, 100000], got 0"
    assert "takes no PETSc options" in main_error(capsys, "check", good, "-snes_rtol", "1")


def test_export_is_wired(tmp_path, capsys, monkeypatch):
    from hapticrom.cli import main

    calls = []

    def export_model(model: Path, out: Path, *, frames: int = 20, cut: bool = True):
        calls.append((model, out, frames, cut))
        return [out / "surface.vtp", out / "sequence.pvd"]

    fake_module(monkeypatch, "hapticrom.export", export_model=export_model)
    out = tmp_path / "vtk"
    assert main(["export", "m.h5", "--out", str(out)]) == 0
    assert capsys.readouterr().out == f"{out / 'surface.vtp'}\n{out / 'sequence.pvd'}\n"
    assert main(["-q", "export", "m.h5", "--out", str(out), "--frames", "3", "--no-cut"]) == 0
    assert calls == [(Path("m.h5"), out, 20, True), (Path("m.h5"), out, 3, False)]
    capsys.readouterr()
    assert "argument --frames: must lie in [1, 10,000], got 0" in main_error(
        capsys, "export", "m.h5", "--out", out, "--frames", "0"
    )
    blocker = tmp_path / "file"
    blocker.write_text("")
    line = main_error(capsys, "export", "m.h5", "--out", blocker)
    assert line == f"hapticrom: error: export --out {blocker} exists and is not a directory"
    assert len(calls) == 2


def test_train_and_reduce_make_the_model_s_directory(
    small_campaign, mesh_dir, tmp_path, no_expensive_work
):
    """A fresh checkout has no out/: `hapticrom train ... --out out/model.h5` makes it (as
    `mesh --out` does) and goes on to the work."""
    from hapticrom.cli import main

    _, store, _ = small_campaign
    toml = campaign_file(mesh_dir, tmp_path / "c.toml")
    for command in (["reduce", store.root], ["train", toml]):
        out = tmp_path / command[0] / "new" / "model.h5"
        with pytest.raises(AssertionError, match="expensive work started"):
            main([str(a) for a in (*command, "--out", out)])
        assert out.parent.is_dir() and not out.exists()

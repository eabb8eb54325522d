"""The command line: clear one-line errors on bad input, a plain message without the extra."""

from __future__ import annotations

import csv
import json
import os
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
    config = write_config(
        tmp_path / "ok.toml", mesh_dir / "cornea-coarse.msh", 'law = "hgo"', INDENT
    )
    proc = run_cli("solve", config, "--out", tmp_path / "out", "-hapticrom_snes_converged_reason")
    assert proc.returncode == 0, proc.stderr
    # The PETSc option reached SNES (under the hapticrom_ prefix).
    assert "Nonlinear hapticrom_ solve converged" in proc.stdout
    rows = list(csv.DictReader(open(tmp_path / "out" / "curve.csv")))
    assert len(rows) == 2 and float(rows[-1]["disp_z"]) == pytest.approx(-0.1)


def test_mesh_command_writes_mesh_and_sidecar(tmp_path):
    proc = run_cli("mesh", "beam", "--refinement", "coarse", "--out", tmp_path / "b.msh")
    assert proc.returncode == 0, proc.stderr
    info = json.loads((tmp_path / "b.json").read_text())
    assert info["counts"]["cells"] == 40 and "units mm" in proc.stdout
    proc = run_cli("mesh", "kidney", "--out", tmp_path / "k.msh")
    assert proc.returncode == 2 and "unknown mesh 'kidney'" in proc.stderr


@pytest.mark.parametrize("command", [["mesh", "cornea"], ["solve", "x.toml", "--out", "o"]])
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


def test_play_and_bench_need_only_the_runtime(small_artifact, tmp_path):
    """The online commands run with the offline stack unimportable."""
    env_prelude = BLOCK_OFFLINE
    proc = run_cli("play", small_artifact, "--seconds", "0.2", cwd=tmp_path, prelude=env_prelude)
    assert proc.returncode == 0, proc.stderr
    assert "achieved" in proc.stdout and "Hz" in proc.stdout
    proc = run_cli("bench", small_artifact, "--steps", "2000", cwd=tmp_path, prelude=env_prelude)
    assert proc.returncode == 0, proc.stderr
    assert "step_displacement" in proc.stdout and "numpy" in proc.stdout

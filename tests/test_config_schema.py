"""One validator per configuration table: `hapticrom check`, hostile files, the JSON Schemas.

Cheap (seconds): TOML and pydantic only, no mesh and no solve.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import textwrap
import tomllib
from pathlib import Path

import pytest

from hapticrom.offline.check import (
    KINDS,
    check_config,
    config_json_schema,
    config_kind,
    schema_text,
)
from hapticrom.shared.errors import InputError

pytestmark = pytest.mark.serial

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = sorted((ROOT / "examples").glob("*.toml"))


# -- a tiny TOML writer (tables of scalars, arrays and inline tables) ---------------------------
def toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float) and not math.isfinite(value):
        return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k} = {toml_value(v)}" for k, v in value.items()) + "}"
    if isinstance(value, list):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    return json.dumps(value)


def toml_text(data: dict) -> str:
    lines = [f"{k} = {toml_value(v)}" for k, v in data.items() if not isinstance(v, dict)]
    for name, table in data.items():
        if isinstance(table, dict):
            lines += [f"\n[{name}]"] + [f"{k} = {toml_value(v)}" for k, v in table.items()]
    return "\n".join(lines) + "\n"


SOLVE = {
    "mesh": {"file": "organ.msh"},
    "material": {"law": "neo-hookean", "E": 1.0, "nu": 0.4},
    "load": {"mode": "displacement", "displacement": [0.0, 0.0, -0.5], "steps": 4},
    "solver": {"newton": "modified"},
    "output": {"xdmf": False},
}
POLAR = {"centre": [0.0, 0.0, 0.0], "radius": 3.0, "rings": 2, "per_ring": [4, 8]}
CAMPAIGN = {
    "campaign": {"name": "hostile"},
    "mesh": {"file": "organ.msh"},
    "material": {"law": "hgo"},
    "load": {"mode": "force", "magnitude": 0.03, "direction": "normal", "steps": 4},
    "positions": {"points": [[0.0, 0.0, 0.0]], "polar": [POLAR]},
    "pod": {"eigenvalue_ratio": 1e-8},
    "anm": {"order": 6},
    "cutting": {"centre": [1.0, 0.0, 0.0], "radius": 2.0},
}


def edited(base: dict, dotted: str, value) -> dict:
    """``base`` with ``table.key`` set to ``value`` (``DELETE``: removed)."""
    data = json.loads(json.dumps(base))
    *tables, key = dotted.split(".")
    target = data
    for name in tables:
        target = target[name]
    if value is DELETE:
        del target[key]
    else:
        target[key] = value
    return data


DELETE = object()


def test_the_bases_are_valid(tmp_path):
    for name, data in (("s.toml", SOLVE), ("c.toml", CAMPAIGN)):
        path = tmp_path / name
        path.write_text(toml_text(data))
        assert check_config(path).endswith(": OK")


@pytest.mark.parametrize("example", EXAMPLES, ids=lambda p: p.name)
def test_every_example_passes_check(example):
    line = check_config(example)
    kind = config_kind(tomllib.loads(example.read_text()))
    assert line.startswith(f"{example}: {kind}") and line.endswith(": OK"), line
    assert "\n" not in line


def test_the_summary_says_what_the_file_is():
    campaign = ROOT / "examples" / "cornea-campaign.toml"
    assert check_config(campaign) == (
        f"{campaign}: campaign 'cornea-default', 37 positions, hgo, displacement control: OK"
    )
    solve = ROOT / "examples" / "beam-svk.toml"
    assert check_config(solve) == f"{solve}: solve, svk, traction load, 10 steps: OK"


HOSTILE = [
    # (base, table.key, value, words of the one line, besides the file name)
    (SOLVE, "load.stepz", 1, ["[load]", "unknown key(s) stepz", "allowed:"]),
    (SOLVE, "outputs", {"xdmf": True}, ["unknown key(s) outputs"]),
    (SOLVE, "load.steps", "10", ["[load]", "steps must be a finite integer, got '10'"]),
    (SOLVE, "load.steps", True, ["[load]", "steps must be a finite integer, got True"]),
    (SOLVE, "load.steps", 2.0, ["[load]", "steps must be a finite integer, got 2.0"]),
    (SOLVE, "load.steps", 0, ["[load]", "steps must lie in [1, 100000], got 0"]),
    (SOLVE, "load.contact_radius", math.nan, ["[load]", "contact_radius", "finite", "nan"]),
    (SOLVE, "load.contact_radius", math.inf, ["[load]", "contact_radius", "finite", "inf"]),
    (SOLVE, "load.displacement", [0.0, 0.0, -math.inf], ["[load]", "displacement", "three"]),
    (SOLVE, "load.displacement", [0.0, True, 1.0], ["[load]", "displacement", "three"]),
    (SOLVE, "load.force", [0.0, 0.0, 1.0], ["[load]", "force is given but mode is"]),
    (SOLVE, "load.mode", DELETE, ["[load]", "missing mode"]),
    (SOLVE, "load.predictor", "cubic", ["[load]", "predictor must be one of secant, none"]),
    (SOLVE, "load", DELETE, ["missing table [load]"]),
    (SOLVE, "mesh", DELETE, ["missing table [mesh]"]),
    (SOLVE, "mesh.file", DELETE, ["[mesh]", "missing file"]),
    (SOLVE, "mesh.file", 3, ["[mesh]", "file must be", "got 3"]),
    (SOLVE, "material.law", "rubber", ["[material]", "unknown material 'rubber'"]),
    (SOLVE, "material.nu", 0.5, ["[material]", "nu must lie in"]),
    (SOLVE, "material.E", True, ["[material]", "E must be a finite number"]),
    (SOLVE, "output.xdmf", 1, ["[output]", "xdmf must be true or false, got 1"]),
    (SOLVE, "solver.newton", "quasi", ["[solver]", "newton must be one of full, modified"]),
    (SOLVE, "solver.options_prefix", "a b", ["[solver]", "options_prefix"]),
    (SOLVE, "discretisation", {"quadrature_degree": 0}, ["[discretisation]", "positive"]),
    (CAMPAIGN, "load.max_step_cuts", 17, ["[load]", "max_step_cuts must lie in [0, 16], got 17"]),
    (CAMPAIGN, "load.max_step_cuts", -1, ["[load]", "max_step_cuts must lie in [0, 16]"]),
    (CAMPAIGN, "load.max_step_cuts", True, ["[load]", "max_step_cuts must be a finite integer"]),
    (CAMPAIGN, "load.predictor", "cubic", ["[load]", "predictor must be one of secant, none"]),
    (CAMPAIGN, "load.magnitude", DELETE, ["[load]", "missing magnitude"]),
    (CAMPAIGN, "load.magnitude", -0.03, ["[load]", "magnitude must be positive"]),
    (CAMPAIGN, "load.direction", [0.0, 0.0, 0.0], ["[load]", "direction must not be the zero"]),
    (CAMPAIGN, "load.direction", "up", ["[load]", "direction", '"normal"']),
    (CAMPAIGN, "load.contact_point", [0.0, 0.0, 0.0], ["[load]", "unknown key(s) contact_point"]),
    (CAMPAIGN, "campaign.name", 3, ["[campaign]", "name", "got 3"]),
    (CAMPAIGN, "positions", DELETE, ["missing table [positions]"]),
    (CAMPAIGN, "positions.points", "apex", ["[positions]", "points", "list"]),
    (CAMPAIGN, "positions.snap_tolerance", math.nan, ["[positions]", "snap_tolerance", "nan"]),
    (CAMPAIGN, "positions.polar", [{**POLAR, "rings": True}], ["[[positions.polar]] #1", "rings"]),
    (
        CAMPAIGN,
        "positions.polar",
        [{**POLAR, "include_centre": 0}],
        ["[[positions.polar]] #1", "include_centre must be true or false, got 0"],
    ),
    (CAMPAIGN, "positions.polar", [{**POLAR, "per_ring": [4]}], ["per_ring has 1 entries"]),
    (CAMPAIGN, "pod.energy", 1.5, ["[pod]", "energy must lie in (0, 1], got 1.5"]),
    (CAMPAIGN, "pod.method", "qr", ["[pod]", "method must be one of snapshots, svd"]),
    (CAMPAIGN, "pod.max_modes", True, ["[pod]", "max_modes must be a finite integer"]),
    (CAMPAIGN, "anm.enabled", 1, ["[anm]", "enabled must be true or false, got 1"]),
    (CAMPAIGN, "anm.order", 16, ["[anm]", "order must lie in [1, 15], got 16"]),
    (CAMPAIGN, "anm.tolerance", math.inf, ["[anm]", "tolerance", "finite"]),
    (CAMPAIGN, "cutting.radius", math.inf, ["[cutting]", "radius", "finite"]),
    (CAMPAIGN, "cutting.centre", DELETE, ["[cutting]", "missing centre"]),
    (CAMPAIGN, "cutting.patch_layers", 1.5, ["[cutting]", "patch_layers", "integer"]),
    (CAMPAIGN, "material.fibre_tension_only", True, ["[anm]", "fibre_tension_only"]),
    (CAMPAIGN, "output", {"xdmf": True}, ["unknown key(s) output"]),
]


@pytest.mark.parametrize(
    "base, key, value, words",
    HOSTILE,
    # DELETE by name: an object's repr holds its address, which differs between processes
    ids=[f"{case[1]}={'DELETE' if case[2] is DELETE else repr(case[2])}" for case in HOSTILE],
)
def test_a_hostile_file_gives_one_line_naming_the_key(tmp_path, base, key, value, words):
    path = tmp_path / "hostile.toml"
    path.write_text(toml_text(edited(base, key, value)))
    with pytest.raises(InputError) as error:
        check_config(path)
    line = str(error.value)
    assert "\n" not in line and line.startswith(f"{path}: "), line
    for word in words:
        assert word in line, (word, line)


def test_the_commands_read_a_file_as_check_does(tmp_path):
    """check_config and the commands' readers (from_toml) share the models and the words."""
    from hapticrom.offline.campaign.config import CampaignConfig
    from hapticrom.offline.config import ProblemConfig

    for base, reader in ((SOLVE, ProblemConfig), (CAMPAIGN, CampaignConfig)):
        path = tmp_path / "c.toml"
        path.write_text(toml_text(edited(base, "load.steps", 0)))
        with pytest.raises(InputError) as by_check:
            check_config(path)
        with pytest.raises(InputError) as by_command:
            reader.from_toml(path)
        assert str(by_check.value) == str(by_command.value)


def test_not_toml_and_missing_files(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[load\n")
    with pytest.raises(InputError, match="not valid TOML"):
        check_config(bad)
    with pytest.raises(InputError, match="not found"):
        check_config(tmp_path / "nope.toml")


def test_the_kind_comes_from_the_tables():
    assert config_kind(SOLVE) == "solve"
    assert config_kind(CAMPAIGN) == "campaign"
    assert config_kind({"mesh": {}, "positions": {}}) == "campaign"


# -- the JSON Schemas ----------------------------------------------------------------------------
@pytest.mark.parametrize("kind", KINDS)
def test_the_committed_schemas_are_the_generated_ones(kind):
    """Regenerate with: python -m hapticrom.offline.check --write-schemas schemas"""
    committed = ROOT / "schemas" / f"{kind}.schema.json"
    assert committed.read_text(encoding="utf-8") == schema_text(kind), (
        f"{committed} is stale: python -m hapticrom.offline.check --write-schemas schemas"
    )
    assert json.loads(committed.read_text()) == config_json_schema(kind)


def test_an_unknown_kind_is_refused():
    with pytest.raises(ValueError, match="solve, campaign"):
        config_json_schema("mesh")


def resolve(schema: dict, node: dict) -> dict:
    while "$ref" in node:
        node = {**schema["$defs"][node["$ref"].rsplit("/", 1)[1]], **node}
        node.pop("$ref")
    return node


def conforms(schema: dict, node: dict, value, where: str) -> list[str]:
    """A small structural check (no jsonschema here): keys, required keys, types, enums."""
    node = resolve(schema, node)
    if "oneOf" in node or "anyOf" in node:
        branches = node.get("oneOf") or node.get("anyOf")
        base = {k: v for k, v in node.items() if k not in ("oneOf", "anyOf")}
        fits = [b for b in branches if not conforms(schema, {**base, **b}, value, where)]
        return [] if fits else [f"{where}: no branch fits {value!r}"]
    if "enum" in node and value not in node["enum"]:
        return [f"{where}: {value!r} not in {node['enum']}"]
    if "const" in node and value != node["const"]:
        return [f"{where}: {value!r} is not {node['const']!r}"]
    kind = node.get("type")
    types = {"object": dict, "array": list, "string": str, "boolean": bool}
    if kind in types and not isinstance(value, types[kind]):
        return [f"{where}: {value!r} is not {kind}"]
    if kind in ("number", "integer") and (
        isinstance(value, bool) or not isinstance(value, int if kind == "integer" else int | float)
    ):
        return [f"{where}: {value!r} is not {kind}"]
    if kind == "array":
        item = node.get("items", {})
        return [e for i, v in enumerate(value) for e in conforms(schema, item, v, f"{where}[{i}]")]
    if kind != "object":
        return []
    props = node.get("properties", {})
    errors = [f"{where}: missing {key}" for key in node.get("required", []) if key not in value]
    for key, v in value.items():
        if key in props:
            errors += conforms(schema, props[key], v, f"{where}.{key}")
        elif node.get("additionalProperties") is False:
            errors.append(f"{where}: unknown {key}")
    return errors


@pytest.mark.parametrize("example", EXAMPLES, ids=lambda p: p.name)
def test_the_schema_accepts_the_examples(example):
    data = tomllib.loads(example.read_text())
    schema = config_json_schema(config_kind(data))
    assert conforms(schema, schema, data, example.name) == []


@pytest.mark.parametrize(
    "base, key, value",
    [
        (SOLVE, "load.stepz", 1),
        (SOLVE, "load.steps", 2.5),
        (SOLVE, "load.mode", "push"),
        (SOLVE, "material.law", "rubber"),
        (SOLVE, "material.C1", 0.1),  # not a neo-Hookean parameter
        (SOLVE, "mesh", DELETE),
        (CAMPAIGN, "load.direction", "up"),
        (CAMPAIGN, "positions.polar", [{**POLAR, "include_centre": 1}]),
        (CAMPAIGN, "output", {"xdmf": True}),
    ],
)
def test_the_schema_refuses_what_the_models_refuse(base, key, value):
    data = edited(base, key, value)
    schema = config_json_schema(config_kind(data))
    assert conforms(schema, schema, data, "file") != []


def test_check_needs_no_finite_element_stack(tmp_path):
    """check_config runs with DOLFINx, PETSc, SLEPc and gmsh unimportable."""
    code = textwrap.dedent(
        """
        import sys, importlib.abc
        class Block(importlib.abc.MetaPathFinder):
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0] in ("dolfinx", "petsc4py", "slepc4py", "basix", "ffcx",
                                          "gmsh"):
                    raise ModuleNotFoundError(name)
        sys.meta_path.insert(0, Block())
        from hapticrom.offline.check import check_config
        for path in sys.argv[1:]:
            print(check_config(path))
        """
    )
    examples = [str(p) for p in EXAMPLES]
    proc = subprocess.run(
        [sys.executable, "-c", code, *examples],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONWARNINGS": "ignore"},
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    assert len(proc.stdout.splitlines()) == len(examples)

"""``hapticrom check CONFIG``: validate a solve or campaign file (or a ``mesh import`` rules
file), and its JSON Schema.

:func:`check_config` reads a TOML file, tells a solve from a campaign by its
tables and checks it with the same table models the commands use
(:class:`~hapticrom.offline.config.SolveFile`,
:class:`~hapticrom.offline.campaign.config.CampaignFile`): one line either way.
Pure Python, pydantic and numpy (the material laws are UFL, pure Python too): no
DOLFINx, no PETSc, no mesh read. What only the mesh can tell (the element against
its cells, fibres for HGO, positions snapped to its surface) is checked when the
command reads it.

:func:`config_json_schema` is the JSON Schema of either kind of file, generated
from the same models. The committed copies in ``schemas/`` let editors complete and
check the files (e.g. Taplo / Even Better TOML: a first line
``#:schema ../schemas/campaign.schema.json``); ``tests/test_config_schema.py``
asserts they are up to date. Regenerate them, from the repository root, with::

    python -m hapticrom.offline.check --write-schemas schemas
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path
from typing import Any

from hapticrom.offline.campaign.config import CampaignFile
from hapticrom.offline.campaign.positions import asked_count
from hapticrom.offline.config import SolveFile, read_toml
from hapticrom.offline.tables import Table, validate

KINDS: dict[str, type[Table]] = {"solve": SolveFile, "campaign": CampaignFile}
# Tables only a campaign has: any of them makes the file a campaign.
CAMPAIGN_TABLES = ("campaign", "positions", "pod", "anm", "cutting")
SCHEMA_DIALECT = "https://json-schema.org/draft/2020-12/schema"


# A rules file of `hapticrom mesh import` (hapticrom.meshes.import_rules): it has these tables.
RULES_KIND = "mesh-import-rules"
RULES_TABLES = ("clamped", "loadable")


def config_kind(data: dict[str, Any]) -> str:
    """``"mesh-import-rules"`` if the file has ``[clamped]`` or ``[loadable]``, else
    ``"campaign"`` if it has a table only a campaign has, else ``"solve"``."""
    if any(table in data for table in RULES_TABLES):
        return RULES_KIND
    return "campaign" if any(table in data for table in CAMPAIGN_TABLES) else "solve"


def check_config(path: Path) -> str:
    """Validate a solve or campaign TOML (kind detected from its tables); return a one-line summary
    (e.g. "examples/cornea-campaign.toml: campaign 'cornea', 37 positions, hgo, displacement
    control: OK"); raise hapticrom.shared.errors.InputError with one clear line naming the file,
    table and key otherwise."""
    path = Path(path)
    data = read_toml(path)
    kind = config_kind(data)
    if kind == RULES_KIND:
        from hapticrom.meshes.import_rules import RulesFile, summary

        return f"{path}: {RULES_KIND} {summary(validate(RulesFile, data, str(path)))}: OK"
    checked = validate(KINDS[kind], data, str(path))
    if kind == "campaign":
        return f"{path}: {_campaign_summary(checked, path)}: OK"
    return f"{path}: {_solve_summary(checked)}: OK"


def _solve_summary(solve: SolveFile) -> str:
    load = solve.load
    control = "traction load" if load.mode == "traction" else f"{load.mode} control"
    return f"solve, {solve.material.law}, {control}, {load.steps} steps"


def _campaign_summary(campaign: CampaignFile, path: Path) -> str:
    name = campaign.campaign.name or path.stem
    asked, exact = positions_asked(campaign)
    positions = f"{asked} positions" if exact else f"up to {asked} positions"
    greedy = campaign.positions.spec.greedy
    if greedy is not None:
        positions += (
            f" then greedy up to {greedy.max_solves} solves (indicator target "
            f"{100 * greedy.target:g} %)"
        )
    law, mode = campaign.material.law, campaign.load.mode
    return f"campaign '{name}', {positions}, {law}, {mode} control"


def positions_asked(campaign: CampaignFile) -> tuple[int, bool]:
    """How many (initial) tool positions the ``[positions]`` table asks for, and whether
    exactly (:func:`~hapticrom.offline.campaign.positions.asked_count`)."""
    return asked_count(campaign.positions.spec)


def config_json_schema(kind: str) -> dict[str, Any]:
    """The JSON Schema (draft 2020-12) of a ``"solve"`` or ``"campaign"`` configuration file
    (or of a ``"mesh-import-rules"`` file, which has no committed copy in ``schemas/``)."""
    if kind == RULES_KIND:
        from hapticrom.meshes.import_rules import RulesFile

        model = RulesFile
    elif kind in KINDS:
        model = KINDS[kind]
    else:
        raise ValueError(f"kind must be one of {', '.join([*KINDS, RULES_KIND])}, got {kind!r}")
    schema = _tidy(model.model_json_schema())
    return {
        "$schema": SCHEMA_DIALECT,
        **schema,
        "title": f"hapticrom {kind} configuration",
        "description": (
            f"A hapticrom {kind} file (TOML; units mm, N, MPa). Generated from the models "
            "of hapticrom.offline: python -m hapticrom.offline.check --write-schemas schemas"
        ),
    }


def _tidy(node: Any) -> Any:
    """Drop what TOML cannot say (null defaults, the null branch of optional keys), the
    defaults of whole tables, the per-key titles pydantic makes from the key names, and
    the reStructuredText of the docstrings."""
    if isinstance(node, list):
        return [_tidy(item) for item in node]
    if not isinstance(node, dict):
        return node
    node = {
        k: _plain(v) if k == "description" and isinstance(v, str) else _tidy(v)
        for k, v in node.items()
        if not (k == "default" and (v is None or (isinstance(v, dict) and "$ref" in node)))
    }
    branches = node.get("anyOf")
    if branches and {"type": "null"} in branches:
        kept = [b for b in branches if b != {"type": "null"}]
        node.pop("anyOf")
        node = {**kept[0], **node} if len(kept) == 1 else {**node, "anyOf": kept}
    if isinstance(node.get("properties"), dict):
        for prop in node["properties"].values():
            if isinstance(prop, dict):
                prop.pop("title", None)
    return node


def _plain(description: str) -> str:
    """A docstring as plain text: roles and double backquotes gone, lines joined."""
    text = re.sub(r":\w+:`~?([^`]+)`", r"\1", description).replace("``", "`")
    return " ".join(text.split())


def schema_text(kind: str) -> str:
    """The committed form of :func:`config_json_schema`: indented JSON and a newline."""
    return json.dumps(config_json_schema(kind), indent=2, ensure_ascii=False) + "\n"


def write_schemas(directory: Path) -> list[Path]:
    """Write ``solve.schema.json`` and ``campaign.schema.json`` into ``directory``."""
    directory.mkdir(parents=True, exist_ok=True)
    written = []
    for kind in KINDS:
        path = directory / f"{kind}.schema.json"
        path.write_text(schema_text(kind), encoding="utf-8")
        written.append(path)
    return written


def main(argv: list[str] | None = None) -> int:
    """``python -m hapticrom.offline.check [--write-schemas DIR] [CONFIG ...]``."""
    parser = argparse.ArgumentParser(prog="python -m hapticrom.offline.check")
    parser.add_argument("configs", nargs="*", type=Path, help="TOML files to check")
    parser.add_argument("--write-schemas", type=Path, metavar="DIR", help="regenerate schemas")
    args = parser.parse_args(argv)
    if args.write_schemas is not None:
        for path in write_schemas(args.write_schemas):
            print(f"wrote {path}")
    for config in args.configs:
        print(check_config(config))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

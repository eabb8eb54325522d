"""Held-out errors: the JSON of ``hapticrom accuracy --json``, its tables and the targets.

The targets are those of :mod:`hapticrom.shared.accuracy` (the one place they live).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hapticrom.report.content import RESPONSE_LABELS
from hapticrom.shared.accuracy import target, verdict
from hapticrom.shared.errors import HapticromError

ACCURACY_COMMAND = "mpirun -n 2 hapticrom accuracy {model} --json accuracy.json"


@dataclass(frozen=True)
class HeldOutResults:
    """The content of ``hapticrom accuracy --json``: per-combination summary and force rows."""

    summary: dict[str, dict[str, float]]
    responses: list[str]  # names of the ROM force columns of the rows ("podi+curves", ...)
    positions: np.ndarray  # (R,) held-out position index
    points: np.ndarray  # (R, 3) mm
    depths: np.ndarray  # (R,) mm
    fem: np.ndarray  # (R,) N
    rom: np.ndarray  # (R, C) N, one column per response
    field: np.ndarray | None = None  # (R, C) relative L2 surface-field errors (format 2)
    beyond: np.ndarray | None = None  # (R, C) bool: the runtime extrapolated in depth (3)
    outside: frozenset[int] = frozenset()  # positions clamped to the trained region (3)

    @property
    def errors(self) -> np.ndarray:
        """Relative force errors (R, C); NaN where the full-order force is zero."""
        fem = np.where(self.fem > 0, self.fem, np.nan)[:, None]
        return np.abs(self.rom - fem) / fem


# -- held-out accuracy --------------------------------------------------------------------
def read_accuracy(path: str | Path) -> HeldOutResults:
    """Read and check the JSON of ``hapticrom accuracy --json`` (or of the older
    ``bench/accuracy.py --json``, without per-row field errors); a bad file raises, naming it."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise HapticromError(
            f"accuracy file {path} not found; write it with "
            + ACCURACY_COMMAND.format(model="MODEL.h5")
        ) from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise HapticromError(f"accuracy file {path} is not JSON: {exc}") from None
    if not isinstance(data, dict) or not isinstance(data.get("summary"), dict):
        raise HapticromError(f"accuracy file {path} has no 'summary' object")
    rows = data.get("rows")
    if not isinstance(rows, list) or not rows:
        raise HapticromError(f"accuracy file {path} has no 'rows'")
    # One force per combination is appended to each row, in the summary's order: every
    # combination but Grassmann's from version 3 (with the transported field), the PODI
    # ones before.
    if data.get("version", 1) >= 3:
        responses = [name for name in data["summary"] if not name.startswith("grassmann+")]
    else:
        responses = [name for name in data["summary"] if name.startswith("podi+")]
    try:
        table = [
            (
                int(r[0]),
                [float(x) for x in r[1]],
                float(r[2]),
                float(r[3]),
                [float(x) for x in r[4:]],
            )
            for r in rows
        ]
    except (TypeError, ValueError, IndexError) as exc:
        raise HapticromError(f"accuracy file {path}: a row is malformed ({exc})") from None
    if any(len(r[4]) != len(responses) or len(r[1]) != 3 for r in table):
        raise HapticromError(
            f"accuracy file {path}: each row needs [position, [x, y, z], depth, F_FEM] and one "
            "force per combination of the summary but Grassmann's "
            f"({', '.join(responses) or 'none'})"
        )
    return HeldOutResults(
        summary=data["summary"],
        responses=responses,
        positions=np.array([r[0] for r in table]),
        points=np.array([r[1] for r in table]),
        depths=np.array([r[2] for r in table]),
        fem=np.array([r[3] for r in table]),
        rom=np.array([r[4] for r in table]),
        field=_field_errors(path, data.get("field_errors"), len(table), len(responses)),
        beyond=_beyond(path, data.get("beyond_trained_depth"), len(table), len(responses)),
        outside=_outside(path, data.get("outside_trained_region")),
    )


def _beyond(path: Path, beyond, rows: int, columns: int) -> np.ndarray | None:
    """The per-row flags (R, C) of the steps extrapolated in depth, or None (before format 3)."""
    if beyond is None:
        return None
    ok = (
        isinstance(beyond, list)
        and len(beyond) == rows
        and all(
            isinstance(r, list) and len(r) == columns and all(isinstance(b, bool) for b in r)
            for r in beyond
        )
    )
    if not ok:
        raise HapticromError(
            f"accuracy file {path}: 'beyond_trained_depth' must hold one row of {columns} "
            f"booleans per row ({rows})"
        )
    return np.array(beyond, dtype=bool).reshape(rows, columns)


def _outside(path: Path, outside) -> frozenset[int]:
    """The positions the runtime clamped to its trained region (none before format 3)."""
    if outside is None:
        return frozenset()
    if not isinstance(outside, list) or not all(
        isinstance(i, int) and not isinstance(i, bool) for i in outside
    ):
        raise HapticromError(
            f"accuracy file {path}: 'outside_trained_region' must be a list of position indices"
        )
    return frozenset(outside)


def _field_errors(path: Path, field, rows: int, columns: int) -> np.ndarray | None:
    """The per-row field errors (R, C), or None when the file has none (format 1)."""
    if field is None:
        return None
    try:
        array = np.array(field, dtype=float)
    except (TypeError, ValueError) as exc:
        raise HapticromError(f"accuracy file {path}: 'field_errors' is malformed ({exc})") from None
    if array.shape != (rows, columns):
        raise HapticromError(
            f"accuracy file {path}: 'field_errors' must have one row per row and one column per "
            f"PODI combination ({rows} x {columns}), got shape {array.shape}"
        )
    return array


def _error_cells(quantity: str, name: str, error: float) -> tuple[str, str, str]:
    """(error %, target %, verdict) of one quantity, the target from hapticrom.shared.accuracy."""
    limit = target(quantity, name)
    return (
        f"{100 * error:.2f}",
        "" if limit is None else f"{100 * limit:g}",
        verdict(error, limit),
    )


def _number(value) -> float:
    """A summary's error: NaN where the file has null (no step of its kind) or nothing."""
    return np.nan if value is None else float(value)


def accuracy_summary_rows(results: HeldOutResults) -> list[tuple[str, ...]]:
    """(combination, then error, target and verdict of the force and of the surface field)."""
    rows = []
    for name, s in results.summary.items():
        force = _number(s.get("max_force_error"))
        field = _number(s.get("max_field_error"))
        rows.append(
            (name, *_error_cells("force", name, force), *_error_cells("field", name, field))
        )
    return rows


def accuracy_position_rows(results: HeldOutResults) -> list[tuple[str, ...]]:
    """Per held-out position: where, deepest depth and force, worst force error of each
    response, then (when the file has them) worst field error of each response."""
    rows = []
    errors = results.errors
    columns = range(len(results.responses))
    for position in dict.fromkeys(results.positions.tolist()):
        mask = results.positions == position
        deepest = np.flatnonzero(mask)[np.argmax(results.depths[mask])]
        worst = [np.nanmax(errors[mask, c]) for c in columns]
        if results.field is not None:
            worst += [np.nanmax(results.field[mask, c]) for c in columns]
        rows.append(
            (
                str(position),
                *(f"{x:.3f}" for x in results.points[deepest]),
                f"{results.depths[deepest]:.3f}",
                f"{results.fem[deepest]:.5f}",
                *(f"{100 * w:.2f}" for w in worst),
            )
        )
    return rows


def targets_text() -> str:
    """The targets of hapticrom.shared.accuracy in words."""
    parts = []
    for quantity, label in (("force", "force"), ("field", "surface field")):
        limits = {r: f"{100 * target(quantity, f'podi+{r}'):g} %" for r in RESPONSE_LABELS}
        if len(set(limits.values())) == 1:
            parts.append(f"{label} {next(iter(limits.values()))} for every response")
        else:
            by_response = [f"{limit} for {RESPONSE_LABELS[r]}" for r, limit in limits.items()]
            parts.append(f"{label} {' and '.join(by_response)}")
    return "; ".join(parts)

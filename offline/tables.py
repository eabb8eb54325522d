"""Typed TOML tables: one pydantic model per table, one way to report a mistake.

Every table of a configuration file (``[mesh]``, ``[load]``, ``[positions]``...) is
a :class:`Table`: a pydantic model whose keys are typed with the field types
below (:func:`number`, :func:`integer`, :func:`vector`, :func:`choice`,
:func:`boolean`, :func:`text`). The solve configuration
(:mod:`hapticrom.offline.config`), the campaign
(:mod:`hapticrom.offline.campaign.config`) and the positions table
(:mod:`hapticrom.offline.campaign.positions`) share them, so a key means and is
checked the same everywhere, and the JSON Schema of the files
(:mod:`hapticrom.offline.check`) comes from the same models.

The field types validate by hand (``PlainValidator``), not by pydantic's coercion:
a boolean is never a number, an integer is never ``2.0``, NaN and infinities are
refused, and a value keeps the type it was written with (``contact_radius = 1`` is
the integer 1, as before). Each raises :func:`invalid` with what was expected and
what was got; :func:`validate` turns the first error into one :class:`InputError`
line naming the file, the table and the key::

    cornea.toml: [load] steps must lie in [1, 100000], got 0
    cornea.toml: [[positions.polar]] #2 rings must be positive, got -1

Pure Python and pydantic: no DOLFINx, no mesh.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Annotated, Any, ClassVar, get_args, get_origin

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    PlainValidator,
    ValidationError,
    WithJsonSchema,
    create_model,
    model_validator,
)
from pydantic_core import PydanticCustomError

from hapticrom.shared.errors import InputError

_REAL = (int, float, np.integer, np.floating)


def invalid(message: str) -> PydanticCustomError:
    """The error a field type or a table rule raises: ``message`` says what was expected and got.

    The message goes through a placeholder, so braces in a quoted value are kept as they are.
    """
    return PydanticCustomError("hapticrom", "{message}", {"message": message})


# --- field types --------------------------------------------------------------------------


def _is_number(value: Any) -> bool:
    if isinstance(value, bool) or not isinstance(value, _REAL):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:  # an integer beyond any float
        return False


def _interval(gt=None, ge=None, lt=None, le=None) -> str:
    low = f"({gt}" if gt is not None else f"[{ge}" if ge is not None else "(-inf"
    high = f"{lt})" if lt is not None else f"{le}]" if le is not None else "inf)"
    return f"{low}, {high}"


def _bounds_check(value, gt=None, ge=None, lt=None, le=None) -> str | None:
    """What is wrong with ``value`` against the bounds, or None."""
    inside = (
        (gt is None or value > gt)
        and (ge is None or value >= ge)
        and (lt is None or value < lt)
        and (le is None or value <= le)
    )
    if inside:
        return None
    if gt == 0 and ge is lt is le is None:
        return f"must be positive, got {value}"
    if ge == 1 and gt is lt is le is None:
        return f"must be positive, got {value}"
    return f"must lie in {_interval(gt, ge, lt, le)}, got {value}"


def _bounds_schema(gt=None, ge=None, lt=None, le=None) -> dict[str, Any]:
    names = {"exclusiveMinimum": gt, "minimum": ge, "exclusiveMaximum": lt, "maximum": le}
    return {k: v for k, v in names.items() if v is not None}


def number(*, gt=None, ge=None, lt=None, le=None, as_float: bool = False) -> Any:
    """A finite number (an integer is a number; a boolean, NaN or infinity is not) in bounds.

    ``gt=0`` alone reads "must be positive". The value keeps its type unless ``as_float``.
    """

    def check(value: Any) -> Any:
        if not _is_number(value):
            raise invalid(f"must be a finite number, got {value!r}")
        wrong = _bounds_check(value, gt, ge, lt, le)
        if wrong:
            raise invalid(wrong)
        return float(value) if as_float else value

    schema = {"type": "number", **_bounds_schema(gt, ge, lt, le)}
    return Annotated[float, PlainValidator(check), WithJsonSchema(schema)]


def check_integer(value: Any, ge=None, le=None) -> int:
    """An integer in ``[ge, le]`` (:func:`integer`'s check)."""
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise invalid(f"must be a finite integer, got {value!r}")
    wrong = _bounds_check(value, ge=ge, le=le)
    if wrong:
        raise invalid(wrong)
    return int(value)


def integer(*, ge: int | None = None, le: int | None = None) -> Any:
    """An integer (not a boolean, not ``2.0``) in ``[ge, le]``; ``ge=1`` alone reads "positive"."""
    schema = {"type": "integer", **_bounds_schema(ge=ge, le=le)}
    return Annotated[
        int, PlainValidator(lambda v: check_integer(v, ge, le)), WithJsonSchema(schema)
    ]


def check_vector(value: Any, nonzero: bool = False) -> tuple[float, float, float]:
    """Three finite numbers ``[x, y, z]`` as a tuple of floats (:func:`vector`'s check)."""
    if (
        not isinstance(value, list | tuple | np.ndarray)
        or len(value) != 3
        or not all(_is_number(c) for c in value)
    ):
        raise invalid(f"must be three finite numbers [x, y, z], got {_shown(value)}")
    if nonzero and not any(value):
        raise invalid("must not be the zero vector")
    return tuple(float(c) for c in value)


VECTOR_SCHEMA = {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3}


def vector(*, nonzero: bool = False) -> Any:
    """Three finite numbers ``[x, y, z]`` (mm, N or MPa), read as a tuple of floats."""
    return Annotated[
        tuple[float, float, float],
        PlainValidator(lambda v: check_vector(v, nonzero)),
        WithJsonSchema(VECTOR_SCHEMA),
    ]


def choice(options: Sequence[str]) -> Any:
    """One of the strings ``options``."""
    options = tuple(options)

    def check(value: Any) -> str:
        if not isinstance(value, str) or value not in options:
            raise invalid(f"must be one of {', '.join(options)}, got {value!r}")
        return value

    return Annotated[str, PlainValidator(check), WithJsonSchema({"enum": list(options)})]


def _check_boolean(value: Any) -> bool:
    if not isinstance(value, bool):
        raise invalid(f"must be true or false, got {value!r}")
    return value


def boolean() -> Any:
    """``true`` or ``false`` (not 0 or 1, not a string)."""
    return Annotated[bool, PlainValidator(_check_boolean), WithJsonSchema({"type": "boolean"})]


def text(expected: str, accept: Callable[[str], bool] = bool, pattern: str | None = None) -> Any:
    """A string that ``accept`` (default: non-empty); otherwise "must be ``expected``, got ...".

    ``pattern``: the same rule as a JSON Schema regular expression, for editors.
    """

    def check(value: Any) -> str:
        if not isinstance(value, str) or not accept(value):
            raise invalid(f"must be {expected}, got {value!r}")
        return value

    schema = {"type": "string", "minLength": 1} if accept is bool else {"type": "string"}
    if pattern:
        schema["pattern"] = pattern
    return Annotated[str, PlainValidator(check), WithJsonSchema(schema)]


def _shown(value: Any) -> str:
    """``repr`` of a value, a numpy array as a list (what the file said)."""
    return repr(value.tolist() if isinstance(value, np.ndarray) else value)


# --- tables -------------------------------------------------------------------------------


class Table(BaseModel):
    """A TOML table: unknown keys refused (``extra="forbid"``), required keys named when missing.

    ``missing`` gives, per required key, what to write (``'file = "mesh.msh"'``);
    a required sub-table is reported as ``missing table [name]``.
    """

    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)
    missing: ClassVar[dict[str, str]] = {}

    @model_validator(mode="before")
    @classmethod
    def _keys(cls, data: Any) -> Any:
        """A table, with no unknown key and every required key (checked before the values)."""
        if not isinstance(data, dict):
            raise invalid(f"must be a table, got {_shown(data)}")
        if cls.model_config.get("extra") == "forbid":
            unknown = sorted(set(data) - set(cls.model_fields))
            if unknown:
                raise invalid(
                    f"unknown key(s) {', '.join(unknown)}; "
                    f"allowed: {', '.join(sorted(cls.model_fields))}"
                )
        for key, field in cls.model_fields.items():
            if field.is_required() and key not in data:
                if _table_of(field.annotation):
                    raise invalid(f"missing table [{key}]")
                raise invalid(f"missing {cls.missing.get(key, key)}")
        return data


def _table_of(annotation: Any) -> tuple[type[Table], bool] | None:
    """(table model, is an array of tables) if a field holds a table, else None."""
    if isinstance(annotation, type) and issubclass(annotation, Table):
        return annotation, False
    if get_origin(annotation) is Annotated:
        return _table_of(get_args(annotation)[0])
    if get_origin(annotation) is list:
        inner = _table_of(get_args(annotation)[0])
        return (inner[0], True) if inner else None
    for arg in get_args(annotation):  # Optional[Table]
        if arg is not type(None) and _table_of(arg):
            return _table_of(arg)
    return None


def _describe(model: type[Table], error: dict, where: Sequence[str]) -> str:
    """``[table] key message`` of one pydantic error; the tables are told from the keys by the
    models along the error's location."""
    tables, label, key = list(where), "", ""
    loc, cls, i = error["loc"], model, 0
    while i < len(loc):
        field = cls.model_fields.get(loc[i]) if isinstance(loc[i], str) else None
        found = _table_of(field.annotation) if field is not None else None
        at_array = found is not None and found[1] and not isinstance(_at(loc, i + 1), int)
        if found is None or at_array:  # a key (an array of tables as a whole is a key too)
            key = str(loc[i]) + "".join(f"[{part}]" for part in loc[i + 1 :])
            break
        tables.append(loc[i])
        cls, many = found
        if many:
            label = f"[[{'.'.join(tables)}]] #{loc[i + 1] + 1}"
            i += 2
            continue
        label = f"[{'.'.join(tables)}]"
        i += 1
    if not label and tables:
        label = f"[{'.'.join(tables)}]"
    message = error["msg"]
    if error["type"] != "hapticrom":  # pydantic's own words (not expected from the types above)
        message = f"{message[:1].lower()}{message[1:]}, got {_shown(error.get('input'))}"
    return " ".join(part for part in (label, key, message) if part)


def _at(loc: tuple, i: int) -> Any:
    return loc[i] if i < len(loc) else None


def validate[T: Table](
    model: type[T], data: Any, source: str | None = None, where: Sequence[str] = ()
) -> T:
    """``data`` (as from tomllib) checked against ``model``: the one place where pydantic's
    ValidationError becomes an :class:`InputError`.

    One line for the first mistake: ``source: [table] key message``. ``source`` names the
    file (None: no prefix); ``where`` the table ``data`` is (e.g. ``("positions",)``).
    """
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        line = _describe(model, exc.errors()[0], where)
        raise InputError(f"{source}: {line}" if source else line) from None


def check_value(kind: Any, value: Any, key: str) -> Any:
    """One value checked as a field type (e.g. ``number(gt=0)``) outside a file; the error
    names ``key``. For the dataclasses built in code rather than read from a file."""
    if (id(kind), key) not in _SINGLE:  # the kind is kept: its id stays its own
        _SINGLE[id(kind), key] = (kind, create_model("Value", __base__=Table, **{key: (kind, ...)}))
    return getattr(validate(_SINGLE[id(kind), key][1], {key: value}), key)


_SINGLE: dict[tuple[int, str], tuple[Any, type[Table]]] = {}  # check_value's one-key tables


def rule(check: Callable[[], Any]) -> Any:
    """``check()``, an :class:`InputError` it raises becoming :func:`invalid` (for validators
    that call code outside the tables, such as the material laws)."""
    try:
        return check()
    except InputError as exc:
        raise invalid(str(exc)) from None

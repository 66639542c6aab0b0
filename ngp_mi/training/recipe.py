"""Training recipes: TOML tables read into frozen dataclasses, every table, key, type and range checked.

A recipe is a TOML file with one table per part (``[data]``, ``[model]``, ``[train]``, …). Each
table is read by :func:`from_table` into one or more dataclasses (a table may feed several: the
``[specular]`` table holds the stage's data keys and the G_sp^real config); an unknown key, a
missing required key, a value of the wrong type or out of range is an error that names the file,
the table, the key and the value. Command-line overrides (``--set table.key=value``, values in
TOML syntax, bare words as strings) are applied to the tables before that check, so they are
validated like the file; :func:`record` writes what a run used into its folder.
"""

from __future__ import annotations

import dataclasses
import json
import types
import typing
from pathlib import Path
from typing import Any, Iterable, Sequence

import tomllib
import torch

from ngp_mi.atomic import write_json


def read_tables(path: str | Path, overrides: Sequence[str] = (), required: Iterable[str] = (),
                known: Iterable[str] = ()) -> dict[str, dict[str, Any]]:
    """The recipe's tables with ``overrides`` applied; errors name the file (or the override)."""
    path = Path(path)
    try:
        tables = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise ValueError(f"{path}: cannot read the training recipe ({exc})") from None
    known = set(known)
    for override in overrides:
        table, key, value = parse_override(override)
        if table not in known:
            raise ValueError(f"--set {override}: no table [{table}] in this stage's recipes; tables: {sorted(known)}")
        tables.setdefault(table, {})[key] = value
    unknown = set(tables) - known
    if unknown:
        raise ValueError(f"{path}: unknown table(s) {sorted(unknown)}; known: {sorted(known)}")
    for table in required:
        if table not in tables:
            raise ValueError(f"{path}: missing table [{table}]")
    for name, table in tables.items():
        if not isinstance(table, dict):
            raise ValueError(f"{path}: [{name}] must be a table, got {table!r}")
    return tables


def parse_override(text: str) -> tuple[str, str, Any]:
    """``"table.key=value"`` → (table, key, value); the value in TOML syntax, or a bare word (a string)."""
    name, sep, raw = text.partition("=")
    table, dot, key = name.strip().partition(".")
    if not sep or not dot or not table or not key:
        raise ValueError(f"--set {text!r}: expected TABLE.KEY=VALUE, e.g. train.iterations=500")
    try:
        value = tomllib.loads(f"value = {raw.strip()}")["value"]
    except tomllib.TOMLDecodeError:
        value = raw.strip()
    return table, key.strip(), value


def out_override(out: str | Path) -> str:
    """The override that ``--out DIR`` stands for: ``train.out="DIR"``."""
    return f"train.out={json.dumps(str(out))}"  # a JSON string is a TOML basic string


def from_table(tables: dict[str, dict[str, Any]], name: str, path: str | Path, *classes: type) -> tuple[Any, ...]:
    """One instance of each dataclass from the keys of table ``name`` (each key belongs to the first
    class that has it); an absent table is an empty one. Errors name the file, table, key and value."""
    table = tables.get(name, {})
    known = [{f.name for f in dataclasses.fields(c)} for c in classes]
    unknown = set(table) - set().union(*known)
    if unknown:
        raise ValueError(f"{path}: unknown [{name}] field(s) {sorted(unknown)}; known: {sorted(set().union(*known))}")
    out, taken = [], set()
    for cls, names in zip(classes, known):
        hints = typing.get_type_hints(cls)
        values = {}
        for field in dataclasses.fields(cls):
            if field.name in taken or field.name not in table:
                if field.default is dataclasses.MISSING and field.default_factory is dataclasses.MISSING:
                    raise ValueError(f"{path}: missing [{name}] {field.name}")
                continue
            values[field.name] = _typed(table[field.name], hints[field.name], f"{path}: [{name}] {field.name}")
        taken |= names
        try:
            out.append(cls(**values))
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{path}: [{name}] {exc}") from None
    return tuple(out)


_SCALARS = {int: "an integer", float: "a number", bool: "true or false", str: "a string"}


def _typed(value: Any, hint: Any, where: str) -> Any:
    """``value`` checked against a field's type and converted (lists → tuples, integers → floats)."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):  # ``X | None``: TOML has no null, so the value is an X
        return _typed(value, next(a for a in args if a is not type(None)), where)
    if origin is tuple:
        if not isinstance(value, (list, tuple)) or (args[-1] is not Ellipsis and len(value) != len(args)):
            raise ValueError(f"{where} must be a list{'' if args[-1] is Ellipsis else f' of {len(args)}'}, got {value!r}")
        items = args[:1] * len(value) if args[-1] is Ellipsis else args
        return tuple(_typed(v, a, f"{where}[{i}]") for i, (v, a) in enumerate(zip(value, items)))
    if hint in _SCALARS:
        number = isinstance(value, (int, float)) and not isinstance(value, bool)
        ok = number if hint is float else isinstance(value, hint) and (hint is bool or not isinstance(value, bool))
        if not ok:
            raise ValueError(f"{where} must be {_SCALARS[hint]}, got {value!r}")
        return float(value) if hint is float else value
    return value  # other types (nested configs) are their dataclass's to check


def positive(instance: Any, *names: str, minimum: int = 1) -> None:
    """Range check for ``__post_init__``: each named field must be ``>= minimum``."""
    for name in names:
        value = getattr(instance, name)
        if value < minimum:
            raise ValueError(f"{name} must be >= {minimum}, got {value!r}")


def training_device(name: str, local_rank: int = 0) -> torch.device:
    """``auto`` → the process's GPU (``cuda:LOCAL_RANK``) when CUDA works, else the CPU."""
    if name not in ("auto", "cpu", "cuda"):
        raise ValueError(f"[train] device must be 'auto', 'cpu' or 'cuda', got {name!r}")
    if name == "cpu" or (name == "auto" and not torch.cuda.is_available()):
        return torch.device("cpu")
    if not torch.cuda.is_available():
        raise ValueError("[train] device = 'cuda' but torch sees no CUDA device")
    return torch.device("cuda", local_rank % torch.cuda.device_count())


def record(out: Path, path: str | Path, overrides: Sequence[str], tables: dict[str, Any]) -> Path:
    """``out/recipe.json``: the file, the overrides and the tables this run was started with."""
    return write_json(out / "recipe.json", {"file": str(path), "overrides": list(overrides), "tables": tables})

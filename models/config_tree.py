"""Typed configuration trees: frozen dataclasses read from YAML files and dotted overrides.

One way to configure what the plugins run (``bopsurg predict --config FILE --option
refine.depth.weight=8``): a tree of frozen dataclasses whose defaults are the documented
defaults, and a nested mapping laid over them (:func:`bopsurg.options.plugin_options` makes
it from the file and the dotted overrides). Unknown keys and values of the wrong type are
one-line errors naming the key. :func:`to_yaml` writes the resolved tree back, a file that
reproduces it. Structuring and type checks are dacite's.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from collections.abc import Mapping
from typing import Any, Literal, TypeVar

import dacite
import yaml

from bopsurg.errors import BopsurgError

T = TypeVar("T")


def _dataclass_of(tp: Any) -> type[Any] | None:
    """The dataclass in a field type (``X`` or ``X | None``), or None."""
    if isinstance(tp, type) and dataclasses.is_dataclass(tp):
        return tp
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        found = [
            a for a in typing.get_args(tp) if isinstance(a, type) and dataclasses.is_dataclass(a)
        ]
        return found[0] if len(found) == 1 else None
    return None


def _members(tp: Any) -> tuple[Any, ...]:
    """The types a field type admits (``X | None`` -> (X, NoneType))."""
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        return typing.get_args(tp)
    return (tp,)


def _check_keys(cls: type[Any], data: Mapping[str, Any], where: str) -> None:
    """Unknown keys anywhere in ``data`` against the tree of ``cls``, named in full."""
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    for key, value in data.items():
        path = f"{where}{key}"
        if key not in names:
            raise BopsurgError(f"{path}: unknown setting; known here: {', '.join(sorted(names))}")
        sub = _dataclass_of(hints[key])
        if sub is not None and isinstance(value, Mapping):
            _check_keys(sub, value, f"{path}.")
        elif sub is not None:
            raise BopsurgError(f"{path}: is a section, give its keys (e.g. {path}.KEY=VALUE)")
        elif isinstance(value, bool) and float in _members(hints[key]):
            raise BopsurgError(f"{path}: expected a number, got {str(value).lower()}")


def _none_modes(cls: type[Any], data: Mapping[str, Any]) -> dict[str, Any]:
    """``data`` with null read as the mode ``"none"`` where a field's modes (a ``Literal``)
    have one: ``--option refine.depth.mode=none`` parses to null like ``ends.classifier=none``."""
    hints = typing.get_type_hints(cls)
    out = dict(data)
    for key, value in data.items():
        sub = _dataclass_of(hints[key])
        if sub is not None and isinstance(value, Mapping):
            out[key] = _none_modes(sub, value)
        elif value is None and "none" in _literal_modes(hints[key]):
            out[key] = "none"
    return out


def _literal_modes(tp: Any) -> tuple[Any, ...]:
    """The values of a ``Literal`` field type (empty for any other type)."""
    return typing.get_args(tp) if typing.get_origin(tp) is Literal else ()


def _as_float(value: Any) -> Any:
    """ints are floats where a float is asked for (YAML reads ``1`` as an int); bools are not."""
    return float(value) if isinstance(value, int) and not isinstance(value, bool) else value


def from_mapping(cls: type[T], data: Mapping[str, Any], source: str = "config") -> T:
    """The tree ``cls`` with ``data`` laid over its defaults.

    Raises:
        BopsurgError: One line: ``SOURCE: KEY: what is wrong`` for an unknown key, a value of
            the wrong type, or a value a dataclass's own check refuses.
    """
    try:
        _check_keys(cls, data, "")
    except BopsurgError as err:
        raise BopsurgError(f"{source}: {err}") from None
    config = dacite.Config(strict=True, cast=[tuple], type_hooks={float: _as_float})
    try:
        return dacite.from_dict(cls, _none_modes(cls, data), config=config)
    except dacite.DaciteFieldError as err:
        raise BopsurgError(f"{source}: {err.field_path}: {_reason(err)}") from err
    except (dacite.DaciteError, ValueError, TypeError) as err:
        raise BopsurgError(f"{source}: {err}") from err


def _reason(err: dacite.DaciteFieldError) -> str:
    msg = str(err)
    return msg.split(" - ", 1)[1] if " - " in msg else msg


def to_plain(obj: Any) -> Any:
    """A dataclass or nested value as plain YAML/JSON data (tuples become lists), fields in
    their order."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, dict):
        return {k: to_plain(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [to_plain(v) for v in obj]
    return obj


def to_dict(tree: Any) -> dict[str, Any]:
    """A tree (a dataclass) as plain YAML-ready data."""
    out: dict[str, Any] = to_plain(tree)
    return out


def to_yaml(tree: Any) -> str:
    """A tree, or a mapping of trees, as YAML in field order (a valid ``--config`` file)."""
    return str(yaml.safe_dump(to_plain(tree), sort_keys=False, default_flow_style=None))

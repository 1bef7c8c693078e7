"""Plugin options from ``--config FILE`` and ``--option KEY=VALUE``: one nested mapping.

The core knows no plugin's settings; it reads the file (``yaml.safe_load``), lays the dotted
overrides over it (``refine.depth.weight=8`` sets ``{"refine": {"depth": {"weight": 8}}}``),
values parsed as YAML scalars or flow sequences (``0.7``, ``true``, ``[0.9, 1, 1.1]``;
``none`` and ``null`` are null), and hands the mapping to the plugin, which checks it against
its own typed configuration (``bopsurg.models.predict_config`` for ``gdrnet``).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import yaml

from bopsurg.errors import BopsurgError


def parse_value(text: str) -> Any:
    """A dotted override's value: a YAML scalar or flow sequence (``none`` means null)."""
    if text.strip().lower() == "none":
        return None
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError:
        return text


def read_mapping(path: str | Path) -> dict[str, Any]:
    """The mapping in a YAML (or JSON) file; one-line errors naming the file."""
    p = Path(path)
    try:
        data = yaml.safe_load(p.read_text(encoding="utf-8"))
    except OSError as err:
        raise BopsurgError(f"{p}: cannot read ({err.strerror or err})") from err
    except yaml.YAMLError as err:
        raise BopsurgError(f"{p}: not valid YAML ({str(err).splitlines()[0]})") from err
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise BopsurgError(f"{p}: expected a mapping of settings, got {type(data).__name__}")
    return data


def copy_tree(data: Mapping[str, Any]) -> dict[str, Any]:
    """A deep copy of a nested mapping (the leaves shared)."""
    return {k: copy_tree(v) if isinstance(v, Mapping) else v for k, v in data.items()}


def merge(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """``over`` laid over ``base``, section by section."""
    out = copy_tree(base)
    for k, v in over.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), dict):
            out[k] = merge(out[k], v)
        else:
            out[k] = copy_tree(v) if isinstance(v, Mapping) else v
    return out


def nest(pairs: Iterable[tuple[str, Any]], base: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """``base`` (copied) with dotted ``(key, value)`` pairs set in it; later pairs win.

    Raises:
        BopsurgError: A key with an empty part, or one that runs through a value.
    """
    out = copy_tree(base or {})
    for key, value in pairs:
        parts = key.split(".")
        if not all(parts):
            raise BopsurgError(f"option {key!r}: empty part in a dotted key")
        node = out
        for i, part in enumerate(parts[:-1]):
            child = node.setdefault(part, {})
            if not isinstance(child, dict):
                raise BopsurgError(f"option {key!r}: {'.'.join(parts[: i + 1])} is not a section")
            node = child
        node[parts[-1]] = value
    return out


def plugin_options(
    config: str | Path | None, pairs: Iterable[tuple[str, str]], base: Mapping[str, Any] = {}
) -> dict[str, Any]:
    """``base``, then the file ``config``, then the ``KEY=VALUE`` text ``pairs``."""
    data = merge(base, read_mapping(config)) if config is not None else copy_tree(base)
    return nest(((k, parse_value(v)) for k, v in pairs), data)

"""JSON files of BOP datasets, read and written exactly as ``bop_toolkit_lib.inout`` does.

The reference writes a dict as ``{`` newline, one ``  "key": <json.dumps(value, sort_keys=True)>``
line per key (keys sorted as they are, so integer ids sort numerically, then written as
strings), lines separated by ``,``, then ``}`` without a final newline; a list the same way
between ``[`` and ``]``. :func:`save_json` reproduces that byte for byte, so files written by
bopsurg and by the BOP toolkit diff cleanly.
"""

from __future__ import annotations

import gzip
import json
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from bopsurg.atomic import write_bytes
from bopsurg.bop.files import decode_utf8, read_bytes
from bopsurg.errors import DatasetError

_GZIP_MAGIC = b"\x1f\x8b"


def _key_to_int(key: str) -> int | str:
    # Reference semantics: `int(k) if k.lstrip("-").isdigit() else k`. str.isdigit() is also
    # true for digits int() rejects (e.g. superscripts); those keys stay strings.
    if key.lstrip("-").isdigit():
        try:
            return int(key)
        except ValueError:
            return key
    return key


def _keys_to_int_hook(pairs: dict[str, Any]) -> dict[int | str, Any]:
    return {_key_to_int(k): v for k, v in pairs.items()}


def load_json(path: str | Path, *, keys_to_int: bool = False) -> Any:
    """Load a JSON (or gzip-compressed ``.json.gz``) file.

    Python's non-standard ``Infinity``, ``-Infinity`` and ``NaN`` tokens are accepted (BOP error
    files contain them).

    Args:
        path: The file. Gzip is detected from the content, not the suffix.
        keys_to_int: Convert every dict key that looks like an integer (``k.lstrip("-")`` is
            all digits) to ``int``, at every nesting level, as the reference does.

    Returns:
        The decoded content.

    Raises:
        DatasetError: The file is missing, unreadable, not UTF-8 or not valid JSON (the message
            gives the line and column of the syntax error).
    """
    p = Path(path)
    raw = read_bytes(p, DatasetError, expected="a JSON file")
    if raw.startswith(_GZIP_MAGIC):
        try:
            raw = gzip.decompress(raw)
        except (OSError, EOFError, zlib.error) as e:
            raise DatasetError(f"corrupt gzip data ({e})", path=p) from None
    text = decode_utf8(raw, p, DatasetError)
    if not text.strip():
        raise DatasetError("empty file, expected JSON", path=p)
    hook = _keys_to_int_hook if keys_to_int else None
    try:
        return json.loads(text, object_hook=hook)
    except json.JSONDecodeError as e:
        raise DatasetError(
            f"malformed JSON ({e.msg}, column {e.colno})", path=p, line=e.lineno
        ) from None
    except RecursionError:
        raise DatasetError("malformed JSON (nested too deeply)", path=p) from None
    except ValueError as e:  # e.g. an integer literal longer than Python's digit limit
        raise DatasetError(f"malformed JSON ({e})", path=p) from None


def _to_builtin(obj: Any) -> Any:
    # json.dumps `default` hook: numpy scalars and arrays become Python numbers and lists, so
    # callers may pass them; builtin content is serialised exactly as the reference does.
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"Object of type {type(obj).__name__} is not JSON serializable")


def _dumps(value: Any) -> str:
    return json.dumps(value, sort_keys=True, default=_to_builtin)


def _sorted_items(content: dict[Any, Any]) -> list[tuple[Any, Any]]:
    try:
        return sorted(content.items(), key=lambda kv: kv[0])
    except TypeError:
        # Mixed key types (the reference would crash): integers first, then the rest as text.
        return sorted(
            content.items(),
            key=lambda kv: (0, kv[0], "") if isinstance(kv[0], int) else (1, 0, str(kv[0])),
        )


def _block(opening: str, lines: list[str], closing: str) -> str:
    body = ",\n".join(lines) + "\n" if lines else ""
    return f"{opening}\n{body}{closing}"


def dumps_bop(content: Any) -> str:
    """The text :func:`save_json` writes for ``content`` (the reference's layout)."""
    if isinstance(content, dict):
        # json.dumps(str(k), ensure_ascii=False) == '"{}"'.format(k) for every key the
        # reference writes as valid JSON, and escapes the others (quotes, backslashes).
        items = _sorted_items(content)
        lines = [f"  {json.dumps(str(k), ensure_ascii=False)}: {_dumps(v)}" for k, v in items]
        return _block("{", lines, "}")
    if isinstance(content, (list, tuple)):
        return _block("[", [f"  {_dumps(v)}" for v in content], "]")
    return _dumps(content)


def save_json(path: str | Path, content: Any) -> None:
    """Write ``content`` in the reference toolkit's JSON layout, atomically.

    A path ending in ``.gz`` is gzip-compressed (with a zero timestamp, so output is
    reproducible). Numpy scalars and arrays are converted to Python numbers and lists.

    Args:
        path: Destination file; parent folders are created.
        content: A dict (one line per key), a list (one line per element) or any JSON value.
    """
    data = dumps_bop(content).encode("utf-8")
    if str(path).endswith(".gz"):
        data = gzip.compress(data, mtime=0)
    write_bytes(path, data)

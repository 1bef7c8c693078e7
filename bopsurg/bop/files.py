"""Reading a dataset or results file, with the one-line errors every BOP loader gives.

One owner for "missing / a folder / unreadable / not UTF-8" so the JSON, CSV and image
loaders word these problems alike and differ only in the error type and what they expected.
"""

from __future__ import annotations

from pathlib import Path

from bopsurg.errors import InputError


def read_bytes(path: Path, error: type[InputError], *, expected: str, noun: str = "file") -> bytes:
    """The file's bytes.

    Args:
        path: The file.
        error: The :class:`~bopsurg.errors.InputError` subclass to raise (e.g. ``DatasetError``).
        expected: What the file should be, for the folder case, e.g. ``"a JSON file"``.
        noun: What the file is called in the messages, e.g. ``"image"``.

    Raises:
        InputError: (as ``error``) The file is missing, a folder or unreadable.
    """
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise error(f"{noun} not found", path=path) from None
    except IsADirectoryError:
        raise error(f"is a folder, expected {expected}", path=path) from None
    except OSError as e:
        raise error(f"cannot read {noun} ({e.strerror})", path=path) from None


def decode_utf8(raw: bytes, path: Path, error: type[InputError]) -> str:
    """``raw`` as UTF-8 text, a leading byte-order mark dropped (as spreadsheets write it).

    Raises:
        InputError: (as ``error``) The bytes are not UTF-8; the message gives the offset.
    """
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise error(f"not UTF-8 text (byte {e.start})", path=path) from None

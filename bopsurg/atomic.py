"""Atomic file writing: write to a temporary file beside the target, then rename over it.

A reader never sees a half-written file, and a crash leaves either the old file or none.
"""

from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import Iterator
from pathlib import Path

from bopsurg.errors import DatasetError


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path to write; on success it is renamed onto ``path``.

    The temporary file lives in the target's folder (same file system, so ``os.replace`` is
    atomic) and keeps the target's suffix, so writers that pick a format by extension (OpenCV)
    work. On an exception the temporary file is removed and the target is left untouched.

    Args:
        path: Final destination. Parent folders are created.

    Yields:
        The temporary path to write to.
    """
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.with_name(f".{target.stem}.tmp-{os.getpid()}{target.suffix}")
    try:
        yield tmp
        os.replace(tmp, target)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


def check_new_folder(out: str | Path) -> None:
    """Refuse an ``out`` that :func:`atomic_folder` cannot build: one that exists and is not
    an empty folder (call it before the work, so a user mistake costs nothing).

    Raises:
        DatasetError: ``out`` exists and is not an empty folder.
    """
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise DatasetError("already exists and is not empty; choose another --out", path=out)


@contextlib.contextmanager
def atomic_folder(out: str | Path) -> Iterator[Path]:
    """Yield a temporary folder beside ``out``, renamed onto it when the block succeeds and
    removed when it fails, so ``out`` appears complete or not at all.

    Args:
        out: The folder to create; it must not exist or be empty (the caller checks first,
            :func:`check_new_folder`).
    """
    out = Path(out)
    tmp = out.with_name(f".{out.name}.tmp-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        tmp.mkdir(parents=True)
        yield tmp
        if out.is_dir():
            out.rmdir()  # empty
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def write_text(path: str | Path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


def write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def remove_stale_temporaries(folder: str | Path) -> int:
    """Delete temporary files that a killed writer left in ``folder`` (recursively).

    Only call this on a folder no other process is writing to (e.g. a scene folder owned by
    the current unit of work). Returns the number of files removed.
    """
    removed = 0
    root = Path(folder)
    if not root.is_dir():
        return 0
    for tmp in root.rglob(".*.tmp-*"):
        if tmp.is_file():
            tmp.unlink(missing_ok=True)
            removed += 1
    return removed

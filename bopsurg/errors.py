"""Errors bopsurg raises for bad input, each rendered as one line that names file, line and field.

The CLI turns any :class:`BopsurgError` into ``bopsurg: error: <message>`` and exit code 2, so a
user mistake never shows a traceback. Library callers can catch them as :class:`ValueError`.
"""

from __future__ import annotations

from pathlib import Path


class BopsurgError(ValueError):
    """Base class of every error bopsurg raises for bad user input or data."""


class InputError(BopsurgError):
    """Bad input, located as precisely as known: ``path:line: field: reason``.

    Args:
        reason: What is wrong, in words a user can act on.
        path: The file (or folder) concerned, if any.
        field: The field, key or column concerned (e.g. ``"cam_R_m2c"``, ``"R"``), if any.
        line: 1-based line number in a text file (CSV), if any.
    """

    def __init__(
        self,
        reason: str,
        *,
        path: str | Path | None = None,
        field: str | None = None,
        line: int | None = None,
    ) -> None:
        self.reason = reason
        self.path = None if path is None else str(path)
        self.field = field
        self.line = line
        super().__init__(self.message)

    @property
    def message(self) -> str:
        """The one-line message: ``path:line: field: reason`` with absent parts left out."""
        where = self.path or ""
        if self.line is not None:
            where = f"{where}:{self.line}" if where else f"line {self.line}"
        parts = [p for p in (where, self.field) if p]
        text = ": ".join([*parts, self.reason])
        return " ".join(text.split())  # one line, whatever the reason contained

    def __str__(self) -> str:
        return self.message


class DatasetError(InputError):
    """A BOP dataset file is missing, malformed or inconsistent."""


class ResultsError(InputError):
    """A BOP results CSV is malformed or does not fit the dataset."""


class ModelError(InputError):
    """An object model (PLY) or its models_info entry is missing or malformed."""


class ShapeError(InputError):
    """An array given to the API has the wrong shape, dtype or non-finite values."""


class CheckpointError(InputError):
    """A trained-model checkpoint is missing, corrupt or does not fit its model."""

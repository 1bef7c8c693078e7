"""What a command line must print on a user mistake: one line, ``error: ...`` (``bopsurg:
error: ...`` from the ``bopsurg`` command)."""

from __future__ import annotations


def one_line_error(capsys) -> str:
    """The last stderr line captured so far, checked to be the CLI's one-line error."""
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith(("error: ", "bopsurg: error: "))
    return err[-1]

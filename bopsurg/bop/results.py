"""BOP19 pose results CSV: ``scene_id,im_id,obj_id,score,R,t,time``.

One estimate per line with exactly 7 comma-separated fields: integer ids, a float ``score``
(any range), ``R`` = 9 space-separated floats (3x3 rotation, row-major), ``t`` = 3
space-separated floats (mm), ``time`` = wall time in seconds the method took for the whole
image, the same for all estimates of one image (within 0.001 s), ``-1`` if unknown. Line 1 is
skipped if it contains the header string (as the reference ``inout.load_bop_results`` does).

:func:`load_results` parses the whole file vectorised (under 1 s for 100,000 rows on a slow
2-core machine) and only re-reads the lines one by one when the fast path meets a problem, to
report the exact line. Every problem raises :class:`~bopsurg.errors.ResultsError` rendered as
``file:line: field: reason``.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from bopsurg.atomic import write_bytes
from bopsurg.bop.files import decode_utf8, read_bytes
from bopsurg.errors import ResultsError, ShapeError
from bopsurg.geometry import ROTATION_ATOL, is_rotation

if TYPE_CHECKING:  # pandas only for to_dataframe: loading results stays light
    import pandas as pd

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: The header line of a BOP19 results file.
HEADER = "scene_id,im_id,obj_id,score,R,t,time"
#: Largest allowed difference between the times of estimates of one image, s (reference).
TIME_TOLERANCE = 0.001
_ID_FIELDS = ("scene_id", "im_id", "obj_id")
# Lines parsed per vectorised chunk: bounds the memory of the token lists.
_CHUNK_LINES = 16384
# Token layout of one line in the fast path: 17 numbers, 6 "," separators, ";" end of line.
_TOKENS_PER_LINE = 24
_COMMA_POS = (1, 3, 5, 7, 17, 21)
_INT64_MIN, _INT64_MAX = -(2**63), 2**63 - 1


def _ids(value: ArrayLike, name: str) -> I64:
    a = np.asarray(value)
    if a.ndim != 1:
        raise ShapeError(f"expected a 1-D array, got shape {a.shape}", field=name)
    if a.dtype.kind in "iu":
        return a.astype(np.int64)
    f = a.astype(np.float64)
    if not np.all(np.isfinite(f)) or not np.all(f == np.round(f)):
        raise ShapeError("expected integers", field=name)
    return f.astype(np.int64)


def _floats(
    value: ArrayLike, shape: tuple[int, ...], name: str, also: tuple[int, ...] | None = None
) -> F64:
    """``value`` as finite float64 of ``shape``; ``also`` is an accepted alternative shape."""
    a = np.asarray(value, dtype=np.float64)
    if a.shape != shape:
        if also is None or a.shape != also:
            raise ShapeError(f"expected shape {shape}, got {a.shape}", field=name)
        a = a.reshape(shape)
    if not np.all(np.isfinite(a)):
        raise ShapeError("contains NaN or inf", field=name)
    return a


def _times(time: ArrayLike | float, n: int) -> F64:
    """One run time per row from an (n,) array or a single value."""
    try:
        out = np.array(np.broadcast_to(np.asarray(time, dtype=np.float64), n))
    except ValueError:
        raise ShapeError(f"expected shape ({n},), got {np.shape(time)}", field="time") from None
    if not np.all(np.isfinite(out)):
        raise ShapeError("contains NaN or inf", field="time")
    return out


@dataclass(frozen=True, eq=False)
class PoseEstimates:
    """Pose estimates as column arrays (N rows, in file order).

    Attributes:
        scene_id: (N,) int64.
        im_id: (N,) int64.
        obj_id: (N,) int64.
        score: (N,) float64 confidence, any range (higher = more confident).
        R: (N, 3, 3) float64 model-to-camera rotations.
        t: (N, 3) float64 model-to-camera translations, mm.
        time: (N,) float64 run time for the whole image, s; -1 = unknown.
        line: (N,) int64 1-based line of each row in its file (counting the header), -1 for
            rows built in memory.
    """

    scene_id: I64
    im_id: I64
    obj_id: I64
    score: F64
    R: F64
    t: F64
    time: F64
    line: I64

    def __post_init__(self) -> None:
        ids = {k: _ids(getattr(self, k), k) for k in (*_ID_FIELDS, "line")}
        n = len(ids["scene_id"])
        for k, a in ids.items():
            if len(a) != n:
                raise ShapeError(f"length {len(a)} differs from scene_id's {n}", field=k)
            object.__setattr__(self, k, a)
        object.__setattr__(self, "score", _floats(self.score, (n,), "score"))
        object.__setattr__(self, "R", _floats(self.R, (n, 3, 3), "R", also=(n, 9)))
        object.__setattr__(self, "t", _floats(self.t, (n, 3), "t", also=(n, 3, 1)))
        object.__setattr__(self, "time", _floats(self.time, (n,), "time"))

    @classmethod
    def from_arrays(
        cls,
        scene_id: ArrayLike,
        im_id: ArrayLike,
        obj_id: ArrayLike,
        score: ArrayLike,
        R: ArrayLike,
        t: ArrayLike,
        time: ArrayLike | float | None = None,
        *,
        line: ArrayLike | None = None,
    ) -> PoseEstimates:
        """Build estimates from arrays, checking shapes and finiteness.

        Args:
            scene_id: (N,) integers.
            im_id: (N,) integers.
            obj_id: (N,) integers.
            score: (N,) floats.
            R: (N, 3, 3) or (N, 9) row-major rotations.
            t: (N, 3) or (N, 3, 1) translations, mm.
            time: (N,) run times in s (the same for all rows of an image), or one value for
                all rows; None = unknown (-1).
            line: (N,) source line numbers; None = -1.

        Raises:
            ShapeError: Inconsistent lengths, wrong shapes, non-integer ids, NaN or inf.
        """
        n = len(np.atleast_1d(np.asarray(scene_id)))
        times = np.full(n, -1.0) if time is None else _times(time, n)
        lines = np.full(n, -1, dtype=np.int64) if line is None else line
        return cls(scene_id, im_id, obj_id, score, R, t, times, lines)  # type: ignore[arg-type]

    def __len__(self) -> int:
        return len(self.scene_id)

    def subset(self, index: ArrayLike) -> PoseEstimates:
        """The rows selected by a boolean mask or an integer index array (order kept)."""
        idx = np.asarray(index)
        return PoseEstimates(
            *(getattr(self, k)[idx] for k in (*_ID_FIELDS, "score", "R", "t", "time", "line"))
        )

    def images(self) -> set[tuple[int, int]]:
        """The (scene_id, im_id) pairs that have at least one estimate."""
        return set(zip(self.scene_id.tolist(), self.im_id.tolist(), strict=True))

    def to_dataframe(self) -> pd.DataFrame:
        """A DataFrame with columns ``scene_id, im_id, obj_id, score, R0..R8`` (row-major),
        ``t0..t2`` (mm), ``time`` (s), ``line``."""
        import pandas as pd

        cols: dict[str, Any] = {k: getattr(self, k) for k in (*_ID_FIELDS, "score")}
        R = self.R.reshape(-1, 9)
        cols.update({f"R{k}": R[:, k] for k in range(9)})
        cols.update({f"t{k}": self.t[:, k] for k in range(3)})
        cols["time"] = self.time
        cols["line"] = self.line
        return pd.DataFrame(cols)


# --------------------------------------------------------------------------- parsing

_Columns = tuple[I64, I64, I64, F64, F64, F64, F64]


def _parse_fast(chunk: Sequence[str]) -> _Columns | None:
    """Parse lines vectorised; None if anything is off (the slow path then says what)."""
    n = len(chunk)
    tokens = ("\n".join(chunk) + "\n").replace(",", " , ").replace("\n", " ; ").split()
    if len(tokens) != _TOKENS_PER_LINE * n:
        return None
    # Every separator at its place frames each line as 4 + 9 + 3 + 1 numbers.
    if any(set(tokens[p::_TOKENS_PER_LINE]) != {","} for p in _COMMA_POS):
        return None
    if set(tokens[_TOKENS_PER_LINE - 1 :: _TOKENS_PER_LINE]) != {";"}:
        return None
    step = _TOKENS_PER_LINE
    try:
        ids = [np.array(tokens[p::step], dtype=np.int64) for p in (0, 2, 4)]
        score = np.array(tokens[6::step], dtype=np.float64)
        R = np.stack([np.array(tokens[8 + k :: step], dtype=np.float64) for k in range(9)], 1)
        t = np.stack([np.array(tokens[18 + k :: step], dtype=np.float64) for k in range(3)], 1)
        time = np.array(tokens[22::step], dtype=np.float64)
    except (ValueError, OverflowError):
        return None
    return ids[0], ids[1], ids[2], score, R, t, time


def _line_error(reason: str, field: str | None, line: str, lineno: int, path: Path) -> ResultsError:
    # A first line that starts with a word is probably a misspelt header.
    if lineno == 1 and any(c.isalpha() for c in line.split(",")[0]):
        reason += f" (a header line must contain exactly {HEADER!r})"
    return ResultsError(reason, path=path, line=lineno, field=field)


_NUMBER_FIELDS = (
    ("score", 3, 1, "a number"),
    ("R", 4, 9, "9 numbers (3x3 rotation, row-major)"),
    ("t", 5, 3, "3 numbers (translation in mm)"),
)


def _parse_line(line: str, lineno: int, path: Path) -> tuple[Any, ...]:
    """One line with Python's int/float (the reference's semantics); raises at a problem."""
    if not line.strip():
        raise _line_error("empty line", None, line, lineno, path)
    elems = line.split(",")
    if len(elems) != 7:
        reason = f"expected 7 comma-separated fields ({HEADER}), got {len(elems)}"
        raise _line_error(reason, None, line, lineno, path)
    vals: list[Any] = []
    for name, e in zip(_ID_FIELDS, elems[:3], strict=True):
        try:
            v = int(e)
        except ValueError:
            reason = f"expected an integer, got {e.strip()!r}"
            raise _line_error(reason, name, line, lineno, path) from None
        if not _INT64_MIN <= v <= _INT64_MAX:
            raise _line_error(f"id {v} does not fit in 64 bits", name, line, lineno, path)
        vals.append(v)
    for name, col, k, what in _NUMBER_FIELDS:
        parts = elems[col].split()
        if len(parts) != k:
            got = repr(elems[col].strip()) if k == 1 else str(len(parts))
            raise _line_error(f"expected {what}, got {got}", name, line, lineno, path)
        bad = next((x for x in parts if not _is_float(x)), None)
        if bad is not None:
            raise _line_error(f"expected a number, got {bad!r}", name, line, lineno, path)
        nums = [float(x) for x in parts]
        vals.append(nums[0] if k == 1 else nums)
    if not _is_float(elems[6]):
        reason = f"expected a number (seconds), got {elems[6].strip()!r}"
        raise _line_error(reason, "time", line, lineno, path)
    vals.append(float(elems[6]))
    return tuple(vals)


def _parse_slow(chunk: Sequence[str], first_line: int, path: Path) -> _Columns:
    """Parse line by line, raising at the first problem with its line and field."""
    rows = [_parse_line(line, k, path) for k, line in enumerate(chunk, start=first_line)]
    n = len(rows)
    cols = list(zip(*rows, strict=True)) if rows else [()] * 7
    return (
        np.array(cols[0], dtype=np.int64),
        np.array(cols[1], dtype=np.int64),
        np.array(cols[2], dtype=np.int64),
        np.array(cols[3], dtype=np.float64),
        np.array(cols[4], dtype=np.float64).reshape(n, 9),
        np.array(cols[5], dtype=np.float64).reshape(n, 3),
        np.array(cols[6], dtype=np.float64),
    )


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _first(mask: NDArray[np.bool_]) -> int | None:
    idx = np.flatnonzero(mask)
    return int(idx[0]) if len(idx) else None


def _validate(cols: _Columns, lines: I64, path: Path) -> None:
    """Semantic checks; raises for the problem on the earliest line."""
    scene, im, obj, score, R_flat, t, time = cols
    found: list[tuple[int, str, str]] = []  # (row, field, reason)

    finite: dict[str, NDArray[np.bool_]] = {
        "score": np.isfinite(score),
        "R": np.all(np.isfinite(R_flat), axis=1),
        "t": np.all(np.isfinite(t), axis=1),
        "time": np.isfinite(time),
    }
    for name, ok in finite.items():
        row = _first(~ok)
        if row is not None:
            found.append((row, name, "NaN or inf is not allowed"))
    for name, a in zip(_ID_FIELDS, (scene, im, obj), strict=True):
        row = _first(a < 0)
        if row is not None:
            found.append((row, name, f"ids must be non-negative, got {a[row]}"))

    fin_rows = np.flatnonzero(finite["R"])
    R = R_flat[fin_rows].reshape(-1, 3, 3)
    bad = np.flatnonzero(~is_rotation(R)) if len(R) else np.zeros(0, dtype=np.int64)
    if len(bad):
        R_bad = R[bad[0]]
        dev = float(np.abs(R_bad.T @ R_bad - np.eye(3)).max())
        det = float(np.linalg.det(R_bad))
        found.append(
            (
                int(fin_rows[bad[0]]),
                "R",
                f"not a rotation matrix: max |R^T R - I| = {dev:.3g}, det(R) = {det:.6g} "
                f"(tolerance {ROTATION_ATOL:g})",
            )
        )

    if len(scene):
        keys = np.stack([scene, im], axis=1)
        _, first_idx, inv = np.unique(keys, axis=0, return_index=True, return_inverse=True)
        ref_row = first_idx[inv.reshape(-1)]
        with np.errstate(invalid="ignore"):
            diff = np.abs(time - time[ref_row])
        row = _first(diff > TIME_TOLERANCE)
        if row is not None:
            r0 = int(ref_row[row])
            found.append(
                (
                    row,
                    "time",
                    f"{time[row]:g} s differs from {time[r0]:g} s on line {lines[r0]} "
                    f"(scene {scene[row]}, image {im[row]}): all estimates of an image must "
                    f"have the same time (tolerance {TIME_TOLERANCE:g} s)",
                )
            )
    if found:
        row, name, reason = min(found, key=lambda f: f[0])
        raise ResultsError(reason, path=path, line=int(lines[row]), field=name)


def load_results(path: str | Path) -> PoseEstimates:
    """Load and check a BOP19 results CSV.

    Accepts LF or CRLF line endings, with or without a final newline, and the header line or
    none (line 1 is skipped if it contains ``scene_id,im_id,obj_id,score,R,t,time``).

    Args:
        path: The CSV file.

    Returns:
        The estimates in file order, with their line numbers.

    Raises:
        ResultsError: Missing or empty file, no estimates, or a bad line (wrong number of
            fields, non-numeric value, NaN/inf, R without 9 or t without 3 numbers, R not a
            rotation, negative id, a time that differs from the other estimates of the same
            image by more than 0.001 s). The message names the file, line and field.
    """
    p = Path(path)
    text = decode_utf8(read_bytes(p, ResultsError, expected="a CSV file"), p, ResultsError)
    # Universal newlines, as Python's text mode (and so the reference) reads them.
    lines = text.replace("\r\n", "\n").replace("\r", "\n").split("\n")
    if lines[-1] == "":
        lines.pop()
    if not lines:
        raise ResultsError(
            f"no estimates: the file is empty (expected the header {HEADER})", path=p
        )
    first_line = 1
    if HEADER in lines[0]:
        lines = lines[1:]
        first_line = 2
        if not lines:
            raise ResultsError("no estimates: the file has only the header line", path=p)
    parts: list[_Columns] = []
    for start in range(0, len(lines), _CHUNK_LINES):
        chunk = lines[start : start + _CHUNK_LINES]
        cols = _parse_fast(chunk)
        if cols is None:
            cols = _parse_slow(chunk, first_line + start, p)
        parts.append(cols)
    merged: _Columns = tuple(np.concatenate([c[k] for c in parts]) for k in range(7))  # type: ignore[assignment]
    line_no = np.arange(first_line, first_line + len(lines), dtype=np.int64)
    _validate(merged, line_no, p)
    scene, im, obj, score, R_flat, t, time = merged
    return PoseEstimates(scene, im, obj, score, R_flat.reshape(-1, 3, 3), t, time, line_no)


def format_result_row(
    scene_id: int,
    im_id: int,
    obj_id: int,
    score: float,
    R: Sequence[float],
    t: Sequence[float],
    time: float,
) -> str:
    """One line of a BOP19 results CSV (no newline): Python's ``str`` of each value (shortest
    round-trip repr), ``R`` (9 values, row-major) and ``t`` (3 values, mm) space-separated,
    time in s with ``-1`` for unknown."""
    time_text = "-1" if time == -1 else str(float(time))
    return (
        f"{scene_id},{im_id},{obj_id},{score},{' '.join(map(str, R))},"
        f"{' '.join(map(str, t))},{time_text}"
    )


def save_results(
    path: str | Path, est: PoseEstimates, *, time: ArrayLike | float | None = None
) -> None:
    r"""Write estimates as a BOP19 CSV, as the reference ``inout.save_bop_results`` does.

    Values are written with Python's ``str`` (shortest round-trip repr), ``R`` row-major and
    ``t`` in mm space-separated, unknown times as ``-1``, lines joined by ``\n`` without a final
    newline. Written atomically.

    Args:
        path: Destination.
        est: The estimates.
        time: Run times to write instead of ``est.time``: one value for all rows or (N,).
    """
    n = len(est)
    times = est.time if time is None else _times(time, n)
    R = est.R.reshape(n, 9).tolist()
    t = est.t.tolist()
    out = [HEADER]
    for row in zip(
        est.scene_id.tolist(),
        est.im_id.tolist(),
        est.obj_id.tolist(),
        est.score.tolist(),
        R,
        t,
        times.tolist(),
        strict=True,
    ):
        out.append(format_result_row(*row))
    write_bytes(path, "\n".join(out).encode("utf-8"))


def average_time_per_image(est: PoseEstimates) -> float:
    """Average run time per image, as reported by the BOP evaluation.

    Returns:
        -1 if there are no estimates or any time is negative (unknown); otherwise the mean,
        over the images with at least one estimate, of the time of the image's first estimate
        (seconds).
    """
    if len(est) == 0 or np.any(est.time < 0):
        return -1.0
    keys = np.stack([est.scene_id, est.im_id], axis=1)
    _, first_idx = np.unique(keys, axis=0, return_index=True)
    return float(np.mean(est.time[first_idx]))


def _fmt_ids(ids: Iterable[int], limit: int = 10) -> str:
    s = sorted(ids)
    text = ", ".join(str(i) for i in s[:limit])
    return text + (f", ... ({len(s)} in all)" if len(s) > limit else "") if s else "none"


def check_results_against_dataset(
    est: PoseEstimates,
    path: str | Path,
    *,
    images: set[tuple[int, int]],
    obj_ids: set[int],
) -> None:
    """Check that every estimate refers to a known object and an image of the split.

    Args:
        est: Estimates (their ``line`` numbers are used in messages).
        path: The results file, for messages.
        images: The (scene_id, im_id) pairs of the dataset split.
        obj_ids: The object ids of the dataset.

    Raises:
        ResultsError: For the first row (in file order) with an unknown obj_id or image.
    """
    n = len(est)
    if n == 0:
        return
    known_obj = {int(o) for o in obj_ids}
    known_im = {(int(s), int(i)) for s, i in images}
    scenes = {s for s, _ in known_im}
    bad_obj = ~np.isin(est.obj_id, np.fromiter(known_obj, dtype=np.int64, count=len(known_obj)))
    pairs = zip(est.scene_id.tolist(), est.im_id.tolist(), strict=True)
    bad_im = np.fromiter((p not in known_im for p in pairs), dtype=bool, count=n)
    row = _first(bad_obj | bad_im)
    if row is None:
        return
    line = int(est.line[row])
    where = None if line >= 0 else f" (estimate #{row})"
    s, i, o = int(est.scene_id[row]), int(est.im_id[row]), int(est.obj_id[row])
    if bad_im[row] and s not in scenes:
        field, reason = "scene_id", f"scene {s} is not in the dataset split (scenes: "
        reason += f"{_fmt_ids(scenes)})"
    elif bad_im[row]:
        field, reason = "im_id", f"image {i} of scene {s} is not in the dataset split"
    else:
        field, reason = "obj_id", f"unknown obj_id {o} (dataset objects: {_fmt_ids(known_obj)})"
    raise ResultsError(
        reason + (where or ""), path=path, line=line if line >= 0 else None, field=field
    )

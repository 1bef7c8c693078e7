"""Symmetry transformation sets of object models, as the BOP toolkit builds them.

:func:`symmetry_transforms` turns a ``models_info.json`` entry into the arrays ``(R_sym, t_sym)``
that MSSD and MSPD minimise over. The set and its order are those of
``bop_toolkit_lib.misc.get_symmetry_transformations``:

1. discrete list = [identity] + every ``symmetries_discrete`` entry (row-major 4×4, t in mm);
2. each continuous symmetry ``{"axis", "offset"}`` is sampled at ``n = ceil(π / step)`` angles
   ``i · 2π / n`` (i = 0 … n − 1), ``R_i`` by Rodrigues' formula about the normalised axis,
   ``t_i = −R_i · offset + offset``; the samples of all continuous symmetries form one list;
3. with continuous symmetries the result is ``(R_c R_d, R_c t_d + t_c)`` for d in the discrete
   list (outer loop) and c in the continuous list (inner loop); otherwise the discrete list.

The products are evaluated one pair at a time with ``ndarray.dot``, as the reference does, so
the arrays are bit-identical to the reference's (≈ 1 ms for 315 transforms; not a hot path).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from bopsurg.errors import InputError, ShapeError
from bopsurg.geometry import rotation_about_axis

F64 = NDArray[np.float64]

#: ``(R_sym (S, 3, 3), t_sym (S, 3) mm)``, as returned by :func:`symmetry_transforms`.
Symmetries = tuple[F64, F64]

#: The BOP19/BOP24 evaluation scripts' ``max_sym_disc_step`` (→ 315 samples per continuous sym).
DEFAULT_MAX_SYM_DISC_STEP = 0.01


def _float_vector(value: Any, length: int, field: str) -> F64:
    """``value`` as a finite float64 vector of ``length`` entries, or an error naming ``field``."""
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise InputError(f"expected {length} numbers, got {value!r:.60}", field=field) from err
    if a.ndim != 1 or a.shape[0] != length:
        raise ShapeError(f"expected {length} numbers, got shape {a.shape}", field=field)
    if not np.all(np.isfinite(a)):
        raise ShapeError("contains NaN or inf", field=field)
    return a


def _entry_list(model_info: Mapping[str, Any], key: str) -> Sequence[Any]:
    value = model_info.get(key, [])
    if value is None:
        return []
    if isinstance(value, (str, bytes, Mapping)) or not isinstance(value, Sequence):
        raise InputError(f"expected a list, got {type(value).__name__}", field=key)
    return value


def discrete_transforms(model_info: Mapping[str, Any]) -> list[tuple[F64, F64]]:
    """The discrete list: identity first, then each ``symmetries_discrete`` entry.

    Args:
        model_info: One ``models_info.json`` entry.

    Returns:
        List of ``(R (3, 3), t (3, 1) mm)``; ``t`` is a column as in the reference.
    """
    out: list[tuple[F64, F64]] = [(np.eye(3), np.zeros((3, 1)))]
    for i, sym in enumerate(_entry_list(model_info, "symmetries_discrete")):
        m = _float_vector(sym, 16, f"symmetries_discrete[{i}]").reshape(4, 4)
        out.append((m[:3, :3], m[:3, 3].reshape(3, 1)))
    return out


def continuous_transforms(
    model_info: Mapping[str, Any], max_sym_disc_step: float = DEFAULT_MAX_SYM_DISC_STEP
) -> list[tuple[F64, F64]]:
    """The sampled continuous symmetries, all of them concatenated into one list.

    Args:
        model_info: One ``models_info.json`` entry.
        max_sym_disc_step: Largest step, as a fraction of the diameter, that the vertex farthest
            from the axis travels between consecutive samples.

    Returns:
        List of ``(R (3, 3), t (3, 1) mm)``, ``ceil(π / max_sym_disc_step)`` per symmetry.
    """
    step_ok = isinstance(max_sym_disc_step, (int, float)) and not isinstance(
        max_sym_disc_step, bool
    )
    if not step_ok or not math.isfinite(max_sym_disc_step) or max_sym_disc_step <= 0:
        raise InputError(
            f"must be a finite number > 0, got {max_sym_disc_step!r}", field="max_sym_disc_step"
        )
    out: list[tuple[F64, F64]] = []
    for i, sym in enumerate(_entry_list(model_info, "symmetries_continuous")):
        field = f"symmetries_continuous[{i}]"
        if not isinstance(sym, Mapping):
            raise InputError('expected {"axis": [...], "offset": [...]}', field=field)
        for key in ("axis", "offset"):
            if key not in sym:
                raise InputError(f"missing key {key!r}", field=field)
        axis = _float_vector(sym["axis"], 3, f"{field}.axis")
        if not float(np.dot(axis, axis)) > 0.0:
            raise InputError("axis has zero length", field=f"{field}.axis")
        offset = _float_vector(sym["offset"], 3, f"{field}.offset").reshape(3, 1)
        n = int(np.ceil(np.pi / max_sym_disc_step))
        step = 2.0 * np.pi / n
        for k in range(n):
            R = rotation_about_axis(axis, k * step)
            out.append((R, -R.dot(offset) + offset))
    return out


def symmetry_transforms(
    model_info: Mapping[str, Any], max_sym_disc_step: float = DEFAULT_MAX_SYM_DISC_STEP
) -> Symmetries:
    """Symmetry transformations of an object model, in the reference toolkit's set and order.

    Args:
        model_info: One ``models_info.json`` entry; reads the optional keys
            ``symmetries_discrete`` (list of 16 floats: row-major 4×4, t in mm) and
            ``symmetries_continuous`` (list of ``{"axis": [3], "offset": [3] mm}``). Other keys
            are ignored, the bottom row of the 4×4 matrices too.
        max_sym_disc_step: Sampling step of continuous symmetries (fraction of the diameter);
            0.01 gives 315 samples per continuous symmetry.

    Returns:
        ``(R_sym, t_sym)``: (S, 3, 3) float64 rotations and (S, 3) float64 translations in mm,
        ``S = (1 + #discrete) · 315 · #continuous`` (or ``1 + #discrete`` without continuous
        ones). The identity is always first.

    Raises:
        ShapeError: An entry has the wrong number of values or non-finite values.
        InputError: A malformed entry, a zero axis or a step ≤ 0; the message names the field,
            e.g. ``symmetries_discrete[2]``.

    Example:
        >>> R, t = symmetry_transforms({"symmetries_continuous": [
        ...     {"axis": [0, 0, 1], "offset": [0, 0, 0]}]})
        >>> R.shape, t.shape
        ((315, 3, 3), (315, 3))
    """
    if not isinstance(model_info, Mapping):
        raise InputError(f"expected a mapping, got {type(model_info).__name__}", field="model_info")
    disc = discrete_transforms(model_info)
    cont = continuous_transforms(model_info, max_sym_disc_step)
    if cont:
        # Same operations and order as the reference, pair by pair, for bit-identical results.
        combined = [(Rc.dot(Rd), Rc.dot(td) + tc) for Rd, td in disc for Rc, tc in cont]
    else:
        combined = disc
    R_sym = np.stack([R for R, _ in combined]).astype(np.float64, copy=False)
    t_sym = np.stack([t.reshape(3) for _, t in combined]).astype(np.float64, copy=False)
    return R_sym, t_sym


def identity_symmetry() -> Symmetries:
    """The trivial set ``(I (1, 3, 3), 0 (1, 3))`` used when an object has no symmetry."""
    return np.eye(3)[None].copy(), np.zeros((1, 3))


def as_symmetries(syms: Symmetries | Sequence[Mapping[str, ArrayLike]] | None) -> Symmetries:
    """Check a symmetry set; ``None`` is the identity only.

    Args:
        syms: ``(R_sym (S, 3, 3), t_sym (S, 3) or (S, 3, 1))`` as from :func:`symmetry_transforms`,
            or the reference's list of ``{"R": (3, 3), "t": (3, 1)}`` dicts, or ``None``.

    Returns:
        ``(R_sym (S, 3, 3), t_sym (S, 3))`` finite float64 arrays, S ≥ 1.

    Raises:
        ShapeError: Wrong shapes, S = 0, or non-finite values (field ``syms``).
    """
    if syms is None:
        return identity_symmetry()
    if isinstance(syms, (list, tuple)) and syms and isinstance(syms[0], Mapping):
        try:
            R = np.stack([np.asarray(s["R"], dtype=np.float64) for s in syms])
            t = np.stack([np.asarray(s["t"], dtype=np.float64).reshape(-1) for s in syms])
        except (KeyError, ValueError, TypeError) as err:
            raise ShapeError(f"malformed symmetry dicts: {err}", field="syms") from err
    else:
        if not isinstance(syms, (list, tuple)) or len(syms) != 2:
            raise ShapeError("expected (R_sym, t_sym) or a list of {'R', 't'} dicts", field="syms")
        R = np.asarray(syms[0], dtype=np.float64)
        t = np.asarray(syms[1], dtype=np.float64)
    if t.ndim == 3 and t.shape[2:] == (1,):
        t = t[:, :, 0]
    if R.ndim != 3 or R.shape[1:] != (3, 3) or R.shape[0] == 0:
        raise ShapeError(
            f"R_sym: expected shape (S, 3, 3) with S >= 1, got {R.shape}", field="syms"
        )
    if t.shape != (R.shape[0], 3):
        raise ShapeError(f"t_sym: expected shape ({R.shape[0]}, 3), got {t.shape}", field="syms")
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        raise ShapeError("contains NaN or inf", field="syms")
    return R, t

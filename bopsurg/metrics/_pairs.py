"""Input checks shared by the batched pose errors: N (estimate, GT) pose pairs, chunking.

Every argument may be a single pose ((3, 3), (3,), (3, 1)) or a batch ((N, 3, 3), (N, 3));
batches of size 1 broadcast against N (e.g. one GT pose against N estimates). Broadcast
arrays are read-only views (no copies).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from bopsurg.errors import InputError
from bopsurg.geometry import as_intrinsics, as_rotations, as_translations, batch_size

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class PosePairs:
    """N (estimate, GT) pose pairs, all broadcast to the common N.

    Attributes:
        R_est: (N, 3, 3) float64.
        t_est: (N, 3) float64, mm.
        R_gt: (N, 3, 3) float64.
        t_gt: (N, 3) float64, mm.
    """

    R_est: F64
    t_est: F64
    R_gt: F64
    t_gt: F64

    @property
    def n(self) -> int:
        """Number of pairs N."""
        return int(self.R_est.shape[0])


def pose_pairs(R_est: ArrayLike, t_est: ArrayLike, R_gt: ArrayLike, t_gt: ArrayLike) -> PosePairs:
    """Check and broadcast four pose arrays to N pairs.

    Raises:
        ShapeError: A wrong shape, non-finite values or batch sizes that do not broadcast;
            the message names the argument.
    """
    R_e = as_rotations(R_est, "R_est")
    te = as_translations(t_est, "t_est")
    R_g = as_rotations(R_gt, "R_gt")
    tg = as_translations(t_gt, "t_gt")
    n = batch_size(R_e, te, R_g, tg)
    return PosePairs(
        np.broadcast_to(R_e, (n, 3, 3)),
        np.broadcast_to(te, (n, 3)),
        np.broadcast_to(R_g, (n, 3, 3)),
        np.broadcast_to(tg, (n, 3)),
    )


def intrinsics(K: ArrayLike, n: int) -> F64:
    """Camera matrices as float64 (N, 3, 3); a single (3, 3) or a (1, 3, 3) broadcasts."""
    a = np.asarray(K, dtype=np.float64)
    if a.shape == (1, 3, 3):
        a = a[0]
    return as_intrinsics(a, n, "K")


def check_chunk_size(chunk_size: int | None, default: int) -> int:
    """``chunk_size`` or ``default``, checked to be a positive integer."""
    if chunk_size is None:
        return max(1, int(default))
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, (int, np.integer)):
        raise InputError(f"must be a positive int, got {chunk_size!r}", field="chunk_size")
    if chunk_size < 1:
        raise InputError(f"must be >= 1, got {chunk_size}", field="chunk_size")
    return int(chunk_size)


def chunks(n: int, size: int) -> Iterator[slice]:
    """Consecutive slices of at most ``size`` covering ``range(n)``."""
    for start in range(0, n, size):
        yield slice(start, min(n, start + size))

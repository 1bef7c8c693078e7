"""Poses in another needle model's frame: the mapping between two models through their arcs.

A pose is only meaningful in the frame of the model it refers to. An estimator trained on one
needle mesh predicts poses of *that* mesh; a dataset made with another mesh of the same needle
(the AMBF pipeline's ``Needle.ply``, a user's CAD model) has its GT in that mesh's frame. Both
meshes are fitted with :func:`bopsurg.needle.fit_needle`. Their radii may differ a little
(9.97 against 10.18 mm for the AMBF needle), and an estimator reads depth from the needle's
size in the image: a needle k = r_target / r_source times the size at (R, t) looks exactly as
the source needle at (R, t / k) (the scene scaled about the camera centre). So the source
pose is scaled by k about the camera centre, then the rigid transform that lays the scaled
source arc onto the target arc (centres, normals and the arcs' middles coincide, tail-to-tip
direction kept) maps it into the dataset's frame::

    x_target = A (k x_source) + a      (A, a: scaled source arc's middle frame → target's)
    R_target = R_source Aᵀ,  t_target = k t_source − R_target a

Models that are not needles, or needles of different radius (beyond a tolerance), cannot be
matched this way and are refused.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from bopsurg.bop.meshes import ObjectModel
from bopsurg.errors import BopsurgError, ModelError
from bopsurg.estimation import PosePredictions
from bopsurg.needle import NeedleArc, fit_needle

#: Largest relative difference of the two arcs' radii that a rigid mapping may bridge.
RADIUS_RTOL = 0.05
#: Largest difference of the arcs' extents, degrees (a 3/8 vs a 1/2 circle needle is not).
EXTENT_TOL_DEG = 20.0
#: Vertex tolerance under which two models count as the same mesh (no mapping needed), mm.
SAME_MODEL_ATOL = 1e-3


@dataclass(frozen=True)
class FrameMapping:
    """The rigid map from an estimator's model frame to a dataset's: ``x_t = A x_s + a``.

    Attributes:
        obj_id: The object concerned.
        A: (3, 3) rotation.
        a: (3,) translation, mm.
        scale: k = target radius / source radius; translations scale by it (the image of the
            target needle at ``k t`` is the source's at ``t``).
        source: The arc fitted to the estimator's model.
        target: The arc fitted to the dataset's model.
        target_name: Where the dataset's model comes from (its file), for messages.
    """

    obj_id: int
    A: np.ndarray
    a: np.ndarray
    scale: float
    source: NeedleArc
    target: NeedleArc
    target_name: str

    def describe(self) -> str:
        """One line for the user: what was mapped, through what."""
        s, t = self.source, self.target
        return (
            f"obj_id {self.obj_id}: poses mapped from the estimator's needle model into the frame "
            f"of {self.target_name} through the fitted arcs (radius {s.radius:.2f} -> "
            f"{t.radius:.2f} mm: depth x {self.scale:.3f}; arc {s.extent_deg:.1f} -> "
            f"{t.extent_deg:.1f} deg)"
        )

    def map_poses(self, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Poses (R (N, 3, 3), t (N, 3) mm) of the source model → poses of the target model."""
        R_t = np.asarray(R, dtype=np.float64) @ self.A.T
        t_t = self.scale * np.asarray(t, dtype=np.float64) - R_t @ self.a
        return R_t, t_t

    def unmap_poses(self, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The inverse of :meth:`map_poses`: poses of the target model (e.g. a dataset's GT)
        → poses of the source model (the estimator's), R (N, 3, 3), t (N, 3) mm."""
        R_t = np.asarray(R, dtype=np.float64)
        return R_t @ self.A, (np.asarray(t, dtype=np.float64) + R_t @ self.a) / self.scale


def arc_alignment(
    source: NeedleArc,
    target: NeedleArc,
    *,
    radius_rtol: float = RADIUS_RTOL,
    extent_tol_deg: float = EXTENT_TOL_DEG,
    scale: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """The rigid transform ``(A, a)`` with ``x_target = A (scale · x_source) + a`` that lays
    the source arc, scaled about the model origin, onto the target arc (centres, normals and
    arc middles coincide).

    Raises:
        BopsurgError: The radii differ by more than ``radius_rtol`` or the extents by more
            than ``extent_tol_deg``: not the same needle, a rigid map would mislead.
    """
    rel = abs(source.radius - target.radius) / target.radius
    if rel > radius_rtol:
        raise BopsurgError(
            f"needle radii differ by {100 * rel:.1f} % ({source.radius:.2f} vs "
            f"{target.radius:.2f} mm; tolerance {100 * radius_rtol:.0f} %)"
        )
    if abs(source.extent_deg - target.extent_deg) > extent_tol_deg:
        raise BopsurgError(
            f"needle arcs differ: {source.extent_deg:.0f} vs {target.extent_deg:.0f} deg "
            f"(tolerance {extent_tol_deg:.0f} deg)"
        )
    Rs, ts = source.middle_frame()
    Rt, tt = target.middle_frame()
    A = Rt @ Rs.T
    return A, tt - A @ (scale * ts)


def model_mapping(
    obj_id: int,
    source: ObjectModel,
    target: ObjectModel,
    *,
    target_name: str,
    radius_rtol: float = RADIUS_RTOL,
) -> FrameMapping | None:
    """The mapping from ``source`` (the estimator's model) to ``target`` (the dataset's).

    Returns:
        None when both are the same mesh (to ``SAME_MODEL_ATOL``), else the mapping.

    Raises:
        BopsurgError: Either model is not a needle, or the two needles cannot be matched;
            the message names the object and the dataset's model file.
    """
    if source.pts.shape == target.pts.shape and np.allclose(
        source.pts, target.pts, rtol=0.0, atol=SAME_MODEL_ATOL
    ):
        return None
    what = f"cannot map the estimator's poses of obj_id {obj_id} into the frame of {target_name}"
    try:
        s = fit_needle(source, name="the estimator's model")
        t = fit_needle(target, name=target_name)
        k = t.radius / s.radius
        A, a = arc_alignment(s, t, radius_rtol=radius_rtol, scale=k)
    except ModelError as err:
        raise BopsurgError(f"{what}: {err}") from None
    except BopsurgError as err:
        raise BopsurgError(f"{what}: {err}; train the estimator on this model") from None
    return FrameMapping(int(obj_id), A, a, float(k), s, t, target_name)


def map_predictions(pred: PosePredictions, mappings: Mapping[int, FrameMapping]) -> PosePredictions:
    """``pred`` with the poses of every object in ``mappings`` mapped (others unchanged)."""
    if not mappings or len(pred) == 0:
        return pred
    R, t = pred.R.copy(), pred.t.copy()
    for obj_id, m in mappings.items():
        rows = pred.obj_id == obj_id
        if rows.any():
            R[rows], t[rows] = m.map_poses(pred.R[rows], pred.t[rows])
    return PosePredictions(pred.obj_id, pred.score, R, t, pred.bbox)

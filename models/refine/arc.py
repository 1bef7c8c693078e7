"""The needle's geometry as the estimator models it: the arc of its centre line, its wire,
and the poses that share its image (the end-for-end half turn, the tilt mirror).

One home for the needle arc (the mesh itself is :func:`bopsurg.needle.needle_mesh`); the fits
(:mod:`.fit`, :mod:`.depth_fit`, :mod:`.wire3d`) and the end check (:mod:`.ends`) import it.
Units: mm; poses model-to-camera, ``x_cam = R x_model + t``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from bopsurg.bop.dataset import BopDataset
from bopsurg.errors import BopsurgError

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class ArcModel:
    """The needle's centre line: an arc of ``radius`` mm from angle 0 (tail) to ``arc_rad``,
    and its wire: radius ``wire_radius`` mm, tapering to a point over the last ``tip_rad``."""

    radius: float = 10.18
    arc_rad: float = float(np.deg2rad(128.5))
    wire_radius: float = 0.36
    tip_rad: float = float(np.deg2rad(8.5))

    @classmethod
    def from_keypoints(cls, tail: F64, tip: F64) -> ArcModel:
        """The arc of a :func:`bopsurg.needle.needle_mesh` model from its tail and tip (mm).

        The tail-cap centre lies on the centre line at angle 0 and the tip at the arc's end.
        """
        tail, tip = np.asarray(tail, float), np.asarray(tip, float)
        radius = float(np.hypot(tail[0], tail[1]))
        arc = float(np.arctan2(tip[1], tip[0]) % (2 * np.pi))
        if not (radius > 0 and arc > 0):
            raise ValueError(f"keypoints do not describe an arc (tail {tail}, tip {tip})")
        return cls(radius=radius, arc_rad=arc)

    def points(self, n: int) -> F64:
        """(n, 3) centre-line points from tail to tip, mm."""
        s = np.linspace(0.0, self.arc_rad, n)
        return np.stack([self.radius * np.cos(s), self.radius * np.sin(s), np.zeros(n)], axis=1)

    def wire_radii(self, n: int) -> F64:
        """(n,) wire radius at the :meth:`points`, mm (linear taper to 0 at the tip)."""
        s = np.linspace(0.0, self.arc_rad, n)
        taper = np.clip((self.arc_rad - s) / max(self.tip_rad, 1e-9), 0.0, 1.0)
        return self.wire_radius * taper


def dataset_arc(dataset: BopDataset, obj_id: int) -> ArcModel:
    """The arc of needle ``obj_id`` of a dataset, from its ``models_info`` tip and tail
    keypoints.

    Raises:
        BopsurgError: The keypoints are missing or do not describe an arc (one line naming
            models_info.json).
    """
    try:
        kp = dataset.models_info[obj_id]["keypoints"]
        return ArcModel.from_keypoints(kp["tail"], kp["tip"])
    except (KeyError, ValueError) as err:
        raise BopsurgError(
            f"{dataset.models_dir / 'models_info.json'}: obj {obj_id} needs tip and tail "
            f"keypoints ({err})"
        ) from err


def _skew(v: F64) -> F64:
    """(..., 3) → (..., 3, 3) cross-product matrices."""
    z = np.zeros(v.shape[:-1])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return np.stack(
        [np.stack([z, -w, y], -1), np.stack([w, z, -x], -1), np.stack([-y, x, z], -1)], -2
    )


def _exp_so3(w: F64) -> F64:
    """(..., 3) rotation vectors → (..., 3, 3) rotations (Rodrigues)."""
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    Kx = _skew(w)
    small = theta < 1e-12
    th = np.where(small, 1.0, theta)
    a = np.where(small, 1.0, np.sin(th) / th)
    b = np.where(small, 0.5, (1.0 - np.cos(th)) / th**2)
    return np.eye(3) + a * Kx + b * (Kx @ Kx)


def half_turn(arc: ArcModel) -> F64:
    """(3, 3) the half turn S about the arc's bisector (model frame): ``R S`` is the swapped
    pose of ``R`` (the arc's centre is the model origin, so ``t`` stays)."""
    b = np.array([np.cos(arc.arc_rad / 2), np.sin(arc.arc_rad / 2), 0.0])
    return 2.0 * np.outer(b, b) - np.eye(3)


def same_ends(R: F64, t: F64, R_ref: F64, t_ref: F64, arc: ArcModel) -> F64:
    """``R`` or its half turn (the same arc, tip and tail swapped; ``t`` stays): the one
    whose tip lies on the nearer line of sight to the tip of the pose ``(R_ref, t_ref)``.

    A fit of the arc's shape alone (to points, or from a tilt-mirrored start) cannot tell the
    ends apart; this keeps the reference's (the pose head's: the end check judges it after)."""
    tip = arc.points(2)[-1]

    def sight(v: F64) -> F64:
        return v / max(float(np.linalg.norm(v)), 1e-12)

    R_h = R @ half_turn(arc)
    seen = sight(R_ref @ tip + t_ref)
    return R_h if sight(R_h @ tip + t) @ seen > sight(R @ tip + t) @ seen else R


def mirror_pose(R: F64, t: F64) -> F64:
    """The rotation whose arc plane is ``R``'s mirrored through the line of sight to ``t``.

    A circle tilted by +θ or −θ about an axis across the line of sight projects to (almost)
    the same ellipse; this is the other branch of that two-fold ambiguity: the plane normal
    n goes to ``2(n·v)v − n`` (v the unit line of sight), by the smallest rotation.
    """
    v = t / np.linalg.norm(t)
    n = R[:, 2]
    n2 = 2.0 * (n @ v) * v - n
    axis = np.cross(n, n2)
    s, c = np.linalg.norm(axis), float(np.clip(n @ n2, -1.0, 1.0))
    if s < 1e-9:  # normal along the line of sight: the mirror is the pose itself
        return R.copy()
    return _exp_so3(axis / s * np.arctan2(s, c)) @ R

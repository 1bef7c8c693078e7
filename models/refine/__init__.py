"""Refinement of the pose head's needle poses against full-resolution image evidence.

:mod:`.fit` (the exact arc fitted by robust Gauss-Newton / LM, :mod:`.lm`, to foreground
pixels, and to the wire's 3D points when there is a depth image: :mod:`.wire3d`,
:mod:`.depth_fit`; all needles of a call at once, batched torch on the refiner's device),
:mod:`.seghead` (a light full-resolution needle segmenter giving that evidence),
:mod:`.refiner` (the stage the ``gdrnet`` estimator runs: segment, fit, fall back) and
:mod:`.train_seg` and :mod:`.train_ends` (``bopsurg train seg|ends``). Units: mm, px.
"""

from __future__ import annotations

from bopsurg.models.predict_config import FitSettings
from bopsurg.models.refine.arc import ArcModel
from bopsurg.models.refine.fit import Evidence, FitResult, FitResults, refine_pose, refine_poses
from bopsurg.models.refine.refiner import NeedleRefiner, Segmenter
from bopsurg.models.refine.seghead import NeedleSegNet, SegConfig

__all__ = [
    "ArcModel",
    "Evidence",
    "FitResult",
    "FitResults",
    "FitSettings",
    "NeedleRefiner",
    "NeedleSegNet",
    "SegConfig",
    "Segmenter",
    "refine_pose",
    "refine_poses",
]

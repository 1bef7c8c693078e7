"""What a pose estimator provides, and how ``bopsurg predict`` finds one.

An estimator is any object with a :meth:`PoseEstimator.predict` method that takes one RGB image
and its camera matrix (optionally 2D boxes from an external detector) and returns
:class:`PosePredictions`: BOP poses (R row-major model-to-camera, t in mm) with scores. It is
registered under the ``bopsurg.estimators`` entry-point group as a *factory*: a callable
``factory(options: Mapping[str, str]) -> PoseEstimator``. ``bopsurg predict --estimator NAME
--option KEY=VALUE`` passes the options (``device`` and the ``--detector``/``--pose``
checkpoint paths are options too). A third party ships one from its own distribution::

    [project.entry-points."bopsurg.estimators"]
    mynet = "mypkg.estimator:create"

The built-in ``gdrnet`` estimator (a YOLOX-like detector and a GDR-Net-like pose head) lives in
``bopsurg.models``; the core never imports it. Results of methods that are not Python estimators
plug in as files instead: a BOP19 results CSV goes straight to ``bopsurg eval``, and a BOP 2D
detections JSON to ``bopsurg predict --boxes``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from bopsurg.bop.detections import Detections
from bopsurg.bop.meshes import ObjectModel
from bopsurg.errors import BopsurgError, ShapeError
from bopsurg.geometry import as_column, is_rotation

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

__all__ = [
    "Detections",
    "EstimatorFactory",
    "ImageInput",
    "PoseEstimator",
    "PosePredictions",
    "estimator_report",
    "estimator_uses_depth",
    "load_estimator",
    "predict_images",
]


@dataclass(frozen=True, eq=False)
class PosePredictions:
    """Pose estimates in one image.

    Attributes:
        obj_id: (N,) int64 object ids.
        score: (N,) float64 confidences.
        R: (N, 3, 3) float64 model-to-camera rotations (orthonormal, det +1).
        t: (N, 3) float64 model-to-camera translations, mm.
        bbox: (N, 4) float64 ``(x, y, w, h)`` px of the 2D box each pose came from; NaN when
            the estimator used none.
    """

    obj_id: I64
    score: F64
    R: F64
    t: F64
    bbox: F64

    def __post_init__(self) -> None:
        n = len(np.atleast_1d(np.asarray(self.obj_id)))
        object.__setattr__(self, "obj_id", as_column(self.obj_id, (n,), "obj_id", np.int64))
        object.__setattr__(self, "score", as_column(self.score, (n,), "score", np.float64))
        object.__setattr__(self, "R", as_column(self.R, (n, 3, 3), "R", np.float64))
        object.__setattr__(self, "t", as_column(self.t, (n, 3), "t", np.float64))
        bbox = np.asarray(self.bbox, dtype=np.float64)
        if bbox.shape != (n, 4):  # NaN is allowed here (no box), so no finiteness check
            raise ShapeError(f"expected shape {(n, 4)}, got {bbox.shape}", field="bbox")
        object.__setattr__(self, "bbox", bbox)
        if n and not is_rotation(self.R).all():
            raise ShapeError("not a rotation matrix (orthonormal, det +1)", field="R")

    def __len__(self) -> int:
        return len(self.obj_id)

    @classmethod
    def empty(cls) -> PosePredictions:
        """No estimates."""
        return cls(
            np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3, 3)), np.zeros((0, 3)),
            np.zeros((0, 4)),
        )  # fmt: skip


@runtime_checkable
class PoseEstimator(Protocol):
    """A model-based 6D pose estimator for RGB images (BOP units: mm, px).

    Optional: ``object_models`` (obj_id → the :class:`~bopsurg.bop.meshes.ObjectModel` its
    poses refer to, see :func:`estimator_models`), ``report()`` (see
    :func:`estimator_report`), ``uses_depth`` (True: :meth:`predict` also takes
    ``depth=``, see :func:`estimator_uses_depth`) and ``predict_batch(images)`` (a sequence
    of :class:`ImageInput` -> one :class:`PosePredictions` per image, each the same as
    :meth:`predict` gives for that image; see :func:`predict_images`, which loops over
    :meth:`predict` for an estimator without it).
    """

    #: Object ids the estimator can find.
    obj_ids: tuple[int, ...]

    def predict(
        self,
        rgb: NDArray[np.uint8],
        K: F64,
        *,
        obj_ids: tuple[int, ...] | None = None,
        boxes: Detections | None = None,
    ) -> PosePredictions:
        """Estimate the poses of the objects in one image.

        Args:
            rgb: (H, W, 3) uint8 RGB image.
            K: (3, 3) camera matrix, px.
            obj_ids: Only look for these objects (the image's targets); None = all it knows.
            boxes: 2D boxes from an external detector to use instead of its own; None = detect.

        Returns:
            The estimates, any number per object, best first within an object.
        """
        ...


@dataclass(frozen=True, eq=False)
class ImageInput:
    """One image for :func:`predict_images` (the arguments of :meth:`PoseEstimator.predict`).

    Attributes:
        rgb: (H, W, 3) uint8 RGB image.
        K: (3, 3) camera matrix, px.
        obj_ids: Only look for these objects; None = all the estimator knows.
        boxes: 2D boxes from an external detector; None = detect.
        depth: (H, W) depth, mm (0: no reading), for an estimator that ``uses_depth``; None:
            no depth image.
    """

    rgb: NDArray[np.uint8]
    K: F64
    obj_ids: tuple[int, ...] | None = None
    boxes: Detections | None = None
    depth: F64 | None = None


def predict_images(
    estimator: PoseEstimator, images: Sequence[ImageInput], *, depth: bool | None = None
) -> list[PosePredictions]:
    """The estimates of a batch of images, one :class:`PosePredictions` per image, in order.

    Through the estimator's ``predict_batch`` when it has one (it may run its networks on the
    whole batch at once), else :meth:`PoseEstimator.predict` image by image with ``depth=``
    when ``depth`` (default: whether the estimator ``uses_depth``; False: an RGB-only run,
    the keyword is not passed and the images should hold no depth).

    Raises:
        BopsurgError: ``predict_batch`` returned a different number of results.
    """
    batch = getattr(estimator, "predict_batch", None)
    if callable(batch):
        out = list(batch(images))
        if len(out) != len(images):
            raise BopsurgError(
                f"estimator's predict_batch returned {len(out)} results for {len(images)} images"
            )
        return out
    if depth is None:
        depth = estimator_uses_depth(estimator)
    return [
        estimator.predict(
            im.rgb,
            im.K,
            obj_ids=im.obj_ids,
            boxes=im.boxes,
            **({"depth": im.depth} if depth else {}),
        )
        for im in images
    ]


def estimator_models(estimator: object) -> Mapping[int, ObjectModel] | None:
    """The object models an estimator's poses refer to (optional attribute
    ``object_models``: obj_id → :class:`~bopsurg.bop.meshes.ObjectModel`, the meshes it was
    trained on), or None when it does not say.

    ``bopsurg predict`` maps the poses into the dataset's model frame when the dataset's model
    of an object differs (:mod:`bopsurg.model_frames`).
    """
    models = getattr(estimator, "object_models", None)
    if models is None:
        return None
    if not isinstance(models, Mapping) or not all(
        isinstance(m, ObjectModel) for m in models.values()
    ):
        raise BopsurgError("estimator's object_models must map obj_id to an ObjectModel")
    return {int(k): v for k, v in models.items()}


def estimator_uses_depth(estimator: object) -> bool:
    """Whether an estimator takes a depth image (optional attribute ``uses_depth``): then
    ``bopsurg predict`` calls ``predict(..., depth=D)`` with D the image's (H, W) float depth
    in mm (0 where there is no reading), or None for an image without one. RGB methods need
    not say anything."""
    return getattr(estimator, "uses_depth", False) is True


def estimator_report(estimator: object) -> str | None:
    """An estimator's optional one-line account of a finished run (``report()``, e.g. how often
    a decoding path fell back), or None when it offers none."""
    report = getattr(estimator, "report", None)
    return report() if callable(report) else None


def estimator_config(estimator: object) -> Mapping[str, Any] | None:
    """An estimator's optional resolved configuration (``resolved_config()``: every setting it
    runs with, defaults included), written next to the results; None when it offers none."""
    resolved = getattr(estimator, "resolved_config", None)
    return resolved() if callable(resolved) else None


EstimatorFactory = Any  # Callable[[Mapping[str, Any]], PoseEstimator]


def load_estimator(name: str, options: Mapping[str, Any] | None = None) -> PoseEstimator:
    """Build the estimator registered as ``name`` in ``bopsurg.estimators``.

    Args:
        name: Entry-point name (``gdrnet`` is the built-in one).
        options: Passed to the factory: a nested mapping (:mod:`bopsurg.options`, e.g.
            ``{"device": "cpu", "refine": {"segmenter": PATH}}``); which keys are known is
            up to the estimator.

    Raises:
        BopsurgError: No such estimator, it cannot be imported, or it does not provide
            ``predict``.
    """
    from bopsurg.plugins import load_plugin

    factory = load_plugin("estimator", name)
    estimator = factory(dict(options or {}))
    if not isinstance(estimator, PoseEstimator):
        raise BopsurgError(f"estimator {name!r} does not provide obj_ids and predict()")
    return estimator

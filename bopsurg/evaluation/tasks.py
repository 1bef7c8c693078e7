"""Which benchmark tasks ``bopsurg eval`` runs, and the BOP24 step added to an evaluation.

Tasks and the inputs they need:

- ``bop19``: 6D localization (AR), a pose results CSV;
- ``bop24``: 6D detection (AP, BOP 2023-2025), a pose results CSV and the images of
  ``test_targets_bop24.json`` (every image with GT when the file is absent);
- ``coco-bbox``, ``coco-segm``: 2D detection / segmentation (COCO AP via pycocotools), a BOP
  COCO results JSON with boxes / RLE masks, and ``scene_gt_coco.json`` in the scenes.

``all`` (or no ``--task``) runs every task the inputs allow.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

from bopsurg.errors import BopsurgError
from bopsurg.evaluation.options import COCO_TASKS, POSE_TASKS, TASK_CHOICES

if TYPE_CHECKING:  # light at import: the CLI reads the task names before running anything
    from bopsurg.bop.dataset import BopDataset
    from bopsurg.bop.results import PoseEstimates
    from bopsurg.bop.targets import ImageTarget
    from bopsurg.evaluation.bop24 import DetectionEvaluation

__all__ = [
    "COCO_TASKS",
    "POSE_TASKS",
    "TASK_CHOICES",
    "add_detection_scores",
    "detection_evaluation",
    "merge_task_scores",
    "resolve_tasks",
]


def resolve_tasks(
    choice: str | None, results_kind: str = "pose", allowed: Sequence[str] | None = None
) -> tuple[str, ...]:
    """The tasks to run for ``--task choice`` on results of ``results_kind`` (``"pose"`` or
    ``"coco"``); ``allowed`` narrows the kind's tasks to what the results contain.

    ``choice`` is one task name, several joined by commas (``"bop19,bop24"``), or ``"all"``;
    the tasks come back in report order, each once.

    Raises:
        BopsurgError: A task is unknown or does not apply to these results.
    """
    if allowed is None:
        allowed = POSE_TASKS if results_kind == "pose" else COCO_TASKS
    allowed = tuple(allowed)
    chosen = [t.strip() for t in (choice or "all").split(",") if t.strip()]
    unknown = [t for t in chosen if t not in TASK_CHOICES]
    if unknown or not chosen:
        raise BopsurgError(
            f"--task {choice!r}: unknown task {', '.join(unknown) or '(none)'}; "
            f"choose from {', '.join(TASK_CHOICES)} (several joined by commas)"
        )
    if "all" in chosen:
        return allowed
    refused = [t for t in chosen if t not in allowed]
    if refused:
        raise BopsurgError(
            f"--task {','.join(refused)} needs other results: a {results_kind} results file "
            f"allows {', '.join(allowed) or 'no task'}"
        )
    return tuple(t for t in allowed if t in chosen)


def add_detection_scores(
    scores: dict[str, float],
    tasks: Sequence[str],
    dataset: BopDataset,
    estimates: PoseEstimates,
    image_targets: Sequence[ImageTarget] | None = None,
) -> DetectionEvaluation | None:
    """Add the BOP24 keys to ``scores`` when ``bop24`` is a task; drop the BOP19 keys when
    ``bop19`` is not (the pose evaluation computes them anyway for the paper's table)."""
    det = detection_evaluation(tasks, dataset, estimates, image_targets)
    merge_task_scores(scores, tasks, det)
    return det


def detection_evaluation(
    tasks: Sequence[str],
    dataset: BopDataset,
    estimates: PoseEstimates,
    image_targets: Sequence[ImageTarget] | None = None,
) -> DetectionEvaluation | None:
    """The BOP24 evaluation when ``bop24`` is a task, else None."""
    if "bop24" not in tasks:
        return None
    from bopsurg.evaluation.bop24 import evaluate_bop24

    return evaluate_bop24(
        dataset, estimates, image_targets, max_per_image=dataset.max_estimates_per_image
    )


def merge_task_scores(
    scores: dict[str, float], tasks: Sequence[str], det: DetectionEvaluation | None
) -> None:
    """:func:`add_detection_scores` with the BOP24 evaluation done already
    (:func:`detection_evaluation`)."""
    if "bop19" not in tasks:
        for key in [k for k in scores if k.startswith("bop19_")]:
            del scores[key]
    if det is not None:
        scores.update(det.scores)

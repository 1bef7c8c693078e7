"""Choices of the evaluation that the CLI lists before it runs anything.

Kept free of numpy, pandas and the evaluation modules so that ``bopsurg eval --help`` and
``bopsurg compare --help`` stay instant; :mod:`bopsurg.evaluation.tasks` and
:mod:`bopsurg.evaluation.bootstrap` use the same names.
"""

from __future__ import annotations

#: Tasks of a pose results CSV, in report order.
POSE_TASKS = ("bop19", "bop24")
#: Tasks of a BOP COCO results JSON.
COCO_TASKS = ("coco-bbox", "coco-segm")
#: Every task name ``--task`` accepts.
TASK_CHOICES = (*POSE_TASKS, *COCO_TASKS, "all")

#: Resampling units of ``--ci-unit``.
CI_UNITS = ("image", "scene")
#: Replicates by default: stable 2.5 / 97.5 percentiles at about the cost of the evaluation
#: itself on 10,000 images (bench/bench_detection.py).
DEFAULT_REPLICATES = 500

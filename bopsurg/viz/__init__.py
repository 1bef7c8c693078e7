"""Visual error analysis: an evaluation (:func:`log_evaluation`) or a comparison of evaluations
(:func:`log_comparison`) logged to a rerun ``.rrd`` file (``bopsurg[rerun]``).

rerun is imported only inside the functions that log, so ``import bopsurg.viz`` works without
it; calling them without rerun raises :class:`~bopsurg.errors.BopsurgError`.
"""

from __future__ import annotations

from bopsurg.viz.evals import load_eval_folders
from bopsurg.viz.rerun_compare import comparison_frames, log_comparison
from bopsurg.viz.rerun_log import frame_table, log_evaluation, select_image_frames

__all__ = [
    "comparison_frames",
    "frame_table",
    "load_eval_folders",
    "log_comparison",
    "log_evaluation",
    "select_image_frames",
]

"""Visual error analysis: an evaluation logged to a rerun ``.rrd`` file (``bopsurg[rerun]``).

rerun is imported only inside the functions that log, so ``import bopsurg.viz`` works without
it; calling :func:`log_evaluation` without rerun raises :class:`~bopsurg.errors.BopsurgError`.
"""

from __future__ import annotations

from bopsurg.viz.rerun_log import frame_table, log_evaluation, select_image_frames

__all__ = ["frame_table", "log_evaluation", "select_image_frames"]

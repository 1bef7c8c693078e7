"""Stage 4: the needle-end check: a classifier looks at both ends of each refined needle pose
and turns the pose end for end where the tail looks more like a tip than the tip does, by
more than a logit margin (the pose head's own say on which end is the tip)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from bopsurg.models.inference import for_inference
from bopsurg.models.predict_config import EndsSettings
from bopsurg.models.refine.ends import EndJudge, load_judge


class EndStage:
    """The end classifier and its margin.

    Args:
        judge: The loaded classifier (:class:`EndJudge`), with its margin.
    """

    def __init__(self, judge: EndJudge) -> None:
        self.judge = judge

    @classmethod
    def load(cls, path: str | Path, settings: EndsSettings, device: torch.device) -> EndStage:
        """The stage on the ``needle_ends`` checkpoint ``path``."""
        judge = load_judge(path, device, settings.margin)
        for_inference(judge.net, device)
        return cls(judge)

    def __call__(
        self,
        image: torch.Tensor,
        K: np.ndarray,
        R: np.ndarray,
        t: np.ndarray,
        index: np.ndarray | None = None,
    ) -> np.ndarray:
        """The rotations (n, 3, 3), turned end for end where the classifier says so; the
        patches of all n poses in one forward of the classifier.

        Args:
            image: (B, 3, H, W) float RGB in [0, 1].
            K: (3, 3) intrinsics, px, or (n, 3, 3) one per pose.
            R: (n, 3, 3) rotations; t: (n, 3) translations, mm.
            index: (n,) the image of each pose (None: all in image 0).
        """
        # the judge's margin: ``ends.margin``, else the one recorded with the classifier
        R_out: np.ndarray = self.judge(image, K, R, t, index=index)[0]
        return R_out

    def report(self) -> str:
        """What the end check did, for ``bopsurg predict``."""
        st = self.judge.stats
        return (
            f"end check (margin {self.judge.margin:g}) turned {st.swapped} of {st.checked} "
            "needles end for end"
        )

"""Every setting of the ``gdrnet`` prediction path, in one typed tree with one default.

``bopsurg predict --config FILE --option KEY=VALUE`` fills :class:`PredictConfig` (nested
keys: ``refine.depth.weight=8``; see :mod:`bopsurg.models.config_tree`); the resolved tree is
written next to the results as ``RESULTS.config.yaml``. The stages read only their own
section: detect (:class:`DetectSettings`) -> pose head (:class:`HeadSettings`) -> refine
(:class:`RefineSettings`: re-crop, the image fit, the depth fit) -> end check
(:class:`EndsSettings`). Units: mm and px; logits for the end check. Why each default is what
it is, and what it changes on the validation sets, is in MODEL_CARD.md ("Settings").

Weight files: ``shipped`` names the file shipped in ``bopsurg/models/weights``; a path names
your own; ``null`` (``none``) turns the stage off where that is allowed. A missing file is an
error naming it, never a quiet change of method.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from bopsurg.errors import BopsurgError

#: The folder of the model shipped with bopsurg (see MODEL_CARD.md there).
SHIPPED_DIR = Path(__file__).parent / "weights"
#: Weight-file names in :data:`SHIPPED_DIR`, by role.
SHIPPED_FILES = {
    "detector": "detector.pt",
    "pose": "pose.pt",
    "segmenter": "needle_seg.pt",
    "ends": "needle_ends.pt",
}
#: How to get each weight file back (named in the error for a missing one).
HOW_TO_GET = {
    "detector": "bopsurg train detector DATA --out RUN",
    "pose": "bopsurg train pose DATA --out RUN",
    "segmenter": "bopsurg train seg DATA --out RUN --config $(bopsurg recipes --path seg)",
    "ends": "bopsurg train ends DATA --out RUN --config $(bopsurg recipes --path robust_ends)",
}


def weight_file(role: str, value: str) -> Path:
    """The checkpoint a ``detector``/``pose``/``refine.segmenter``/``ends.classifier`` setting
    names (``shipped`` or a path), which must exist.

    Raises:
        BopsurgError: The file is missing (one line naming it and how to get it).
    """
    path = SHIPPED_DIR / SHIPPED_FILES[role] if value == "shipped" else Path(value)
    if not path.is_file():
        hint = "reinstall bopsurg, or " if value == "shipped" else ""
        raise BopsurgError(
            f"{path}: the {role} weights file does not exist ({hint}train it: {HOW_TO_GET[role]})"
        )
    return path


@dataclass(frozen=True)
class DetectSettings:
    """The detector stage.

    Attributes:
        conf: Lowest detection score kept.
        max_per_object: Boxes (hence poses) kept per object and image, best first.
        input_hw: The detector's input (H, W), px, multiples of 32, instead of the one it was
            trained at (null); the network is convolutional.
    """

    conf: float = 0.05
    max_per_object: int = 1
    input_hw: tuple[int, int] | None = None

    def __post_init__(self) -> None:
        if self.max_per_object < 1:
            raise ValueError(f"detect.max_per_object must be >= 1, got {self.max_per_object}")
        if self.input_hw is not None and any(v <= 0 or v % 32 for v in self.input_hw):
            raise ValueError(
                f"detect.input_hw must be positive multiples of 32, got {self.input_hw}"
            )


@dataclass(frozen=True)
class HeadSettings:
    """The pose-head stage.

    Attributes:
        decode: ``direct``: the rotation and SITE (centre, depth) heads; ``pnp``: PnP-RANSAC on
            the dense 2D-3D correspondences (a ROI where PnP finds no solution keeps the
            direct pose).
        zoom: Crop sides, as multiples of the test-time crop (1.5 x the box's longer side),
            whose direct poses are averaged (``[1]``: one crop). The head's depth is biased
            nearly linearly in the crop side; a symmetric set cancels it.
    """

    decode: Literal["direct", "pnp"] = "direct"
    zoom: tuple[float, ...] = (5 / 6, 1.0, 7 / 6)

    def __post_init__(self) -> None:
        if not self.zoom or not all(z > 0 and z < float("inf") for z in self.zoom):
            raise ValueError(f"head.zoom must be positive crop-side multiples, got {self.zoom}")


@dataclass(frozen=True)
class RecropSettings:
    """Re-crops: a needle whose segmenter mask runs past its detection box is run again
    (pose head and segmenter) on the union of the box and the mask's box.

    Attributes:
        growth: Re-crop when the union's longer side is at least this multiple of the box's
            (0: never).
        passes: Most re-crops of one ROI.
    """

    growth: float = 1.1
    passes: int = 3

    def __post_init__(self) -> None:
        if not (self.growth == 0 or self.growth >= 1):
            raise ValueError(f"refine.recrop.growth must be 0 (off) or >= 1, got {self.growth}")
        if self.passes < 0:
            raise ValueError(f"refine.recrop.passes must be >= 0, got {self.passes}")


@dataclass(frozen=True)
class FitSettings:
    """The arc fit to the segmenter's masks (:func:`bopsurg.models.refine.fit.refine_pose`).

    Attributes:
        samples: Centre-line points of the model polyline.
        iterations: Levenberg-Marquardt iterations.
        scale_reverse: Cauchy scale of the mask-pixel-to-wire distances, px.
        scale_forward: Geman-McClure scale of the wire-to-mask distances, px (redescending:
            a part hidden behind an occluder costs a constant and does not pull the arc).
        forward_weight: Weight of the forward term's mean against the reverse term's.
        tube: The wire as a tube of its radius (off: its centre line alone explains the mask).
        scale_outline: Geman-McClure scale of the tube-side residuals, px.
        outline_weight: Weight of the outline term's mean against the reverse term's.
        lambda0: Initial damping, relative to the diagonal.
        mirror_start: Also start from the tilt-mirrored pose (always with depth points).
        prior_deg: Sigma of the Gaussian prior on rotation around the pose head's pose, deg.
        prior_mm: Sigmas of the prior on translation along camera x, y, z, mm.
        prior_weight: The prior's weight against the mean image cost.
        evidence_upsample: The masks' probabilities are resampled this many times finer
            (bilinear) before the threshold, so the outline falls between grid pixels.
        mask_threshold: Foreground threshold on the segmenter's probabilities.
        min_evidence: Fewest mask pixels a fit needs; with fewer the pose is left as it is.
    """

    samples: int = 40
    iterations: int = 12
    scale_reverse: float = 2.0
    scale_forward: float = 1.5
    forward_weight: float = 1.0
    tube: bool = True
    scale_outline: float = 1.0
    outline_weight: float = 1.0
    lambda0: float = 1e-3
    mirror_start: bool = False
    prior_deg: float = 8.0
    prior_mm: tuple[float, float, float] = (1.5, 1.5, 2.5)
    prior_weight: float = 0.05
    evidence_upsample: int = 2
    mask_threshold: float = 0.5
    min_evidence: int = 12


@dataclass(frozen=True)
class PointsFitSettings:
    """The arc fitted to the depth points alone (:func:`bopsurg.models.refine.depth_fit.
    fit_depth`), one more start of the RGB-D fit.

    Attributes:
        scale: Cauchy scale of the point-to-wire distance, mm.
        iterations: Levenberg-Marquardt iterations.
        max_points: Most points used, evenly strided in the order given.
        min_points: Fewer points with depth and this start is not made.
        inlier_mm: A point this near the fitted wire counts as on it, mm.
        min_inliers: Share of the points that must be on the fitted wire, else no start.
        lambda0: Initial damping.
    """

    scale: float = 0.7
    iterations: int = 15
    max_points: int = 600
    min_points: int = 12
    inlier_mm: float = 1.5
    min_inliers: float = 0.5
    lambda0: float = 1e-3


@dataclass(frozen=True)
class DepthSettings:
    """The RGB-D fit: the visible mask's pixels back-projected with the depth image are
    points of the wire's surface, and their distance to the pose's wire joins the fit.

    Attributes:
        mode: ``fit`` (use the depth image when ``bopsurg predict`` gives one) or ``none``.
        weight: Weight of the points' mean cost against the image terms' (px²-like).
        scale_mm: Cauchy scale of the point-to-wire distance, mm.
        max_points: Most points of a needle the fit uses, evenly strided in the mask's scan
            order (the fit to the points alone takes its own ``points.max_points`` of these).
        points: The fit to the points alone (one more start).
    """

    mode: Literal["fit", "none"] = "fit"
    weight: float = 16.0
    scale_mm: float = 0.5
    max_points: int = 600
    points: PointsFitSettings = field(default_factory=PointsFitSettings)


@dataclass(frozen=True)
class RefineSettings:
    """The needle refinement: the segmenter's masks at full resolution, the arc fitted to
    them (and to the depth points with RGB-D).

    Attributes:
        segmenter: The needle segmenter's weights (``shipped``, a path), or null: no
            refinement (the pose head's poses as they are).
        mask: The segmenter's evidence the fit uses: ``full`` (the arc lies on the full,
            amodal mask and explains the visible one), ``visible`` (the visible mask for
            both), ``auto`` (``full`` when the segmenter predicts it).
        recrop: Re-crops of needles that run past their box.
        fit: The image fit.
        depth: The RGB-D fit.
    """

    segmenter: str | None = "shipped"
    mask: Literal["auto", "full", "visible"] = "auto"
    recrop: RecropSettings = field(default_factory=RecropSettings)
    fit: FitSettings = field(default_factory=FitSettings)
    depth: DepthSettings = field(default_factory=DepthSettings)


@dataclass(frozen=True)
class EndsSettings:
    """The needle-end check: a classifier looks at both ends of the refined pose's needle and
    turns the pose end for end where the tail looks more like a tip than the tip does.

    Attributes:
        classifier: Its weights (``shipped``, a path), or null: no end check.
        margin: The logit margin the tail must win by (the pose head's own say on which end
            is the tip); null: the margin recorded with the classifier (its recipe's
            ``margin``, chosen on validation splits: 3 for the shipped one).
    """

    classifier: str | None = "shipped"
    margin: float | None = None

    def __post_init__(self) -> None:
        if self.margin is not None and not abs(self.margin) < float("inf"):
            raise ValueError(f"ends.margin must be a finite logit margin, got {self.margin}")


@dataclass(frozen=True)
class PredictConfig:
    """The whole ``gdrnet`` prediction path.

    Attributes:
        detector: The detector's weights (``shipped``, a path), or null: boxes only from
            ``bopsurg predict --boxes``.
        pose: The pose head's weights (``shipped`` or a path).
        device: Torch device (``auto``: CUDA when available).
        detect: The detector stage.
        head: The pose-head stage.
        refine: The needle refinement.
        ends: The needle-end check.
    """

    detector: str | None = "shipped"
    pose: str = "shipped"
    device: str = "auto"
    detect: DetectSettings = field(default_factory=DetectSettings)
    head: HeadSettings = field(default_factory=HeadSettings)
    refine: RefineSettings = field(default_factory=RefineSettings)
    ends: EndsSettings = field(default_factory=EndsSettings)

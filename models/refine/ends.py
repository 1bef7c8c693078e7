"""Which end of the needle is the tip: a small patch classifier that settles the arc's
two-fold ambiguity.

A needle's arc maps onto itself under the half turn S about its bisector (the line from the
arc's centre through its middle, in its plane): the pose ``R S`` puts the same wire on the
same pixels with tip and tail swapped, and the far side of the arc towards the camera. Its
image differs only at the two ends: the tip is a sharp point, the tail blunt, with the
suture thread leaving it where one is attached. The pose head reads that from a 128 px ROI
of 32×32 maps, and on a phantom it was not trained on it answers with the swap (the paper's
AMBF frames, turned to our tissue's hue: the right arc, 152–177° off; MODEL_CARD.md).

Here each end is looked at on its own, at full resolution, in a frame the pose fixes: a
square patch centred on the end's projection, side a share of the arc's projected radius,
its x axis along the wire's outward tangent (the end at the centre, the wire on the left, what
lies beyond the end on the right). A small CNN gives the logit that the patch shows the tip.
The pose is swapped when its tail patch looks more like a tip than its tip patch, by
``margin``. What the classifier learns is local (the point, the blunt end, the thread), so it
does not depend on the scene's colours or on which face the camera sees (patches are flipped
about their x axis in training: the mirror image of an end is the same end).

Units: px, mm; poses model-to-camera in the estimator's needle frame (:class:`.arc.ArcModel`:
arc centre at the origin, tail at angle 0 on +x, tip at ``arc_rad`` about +z).
"""

from __future__ import annotations

import dataclasses
import itertools
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from numpy.typing import NDArray
from torch import nn

from bopsurg.errors import CheckpointError
from bopsurg.models.checkpoint import config_path, load_checkpoint, load_weights
from bopsurg.models.refine.arc import ArcModel, half_turn

F64 = NDArray[np.float64]

#: Index of each end in the (n, 2, ...) arrays of this module.
TAIL, TIP = 0, 1


@dataclass(frozen=True)
class EndConfig:
    """Patch and network sizes.

    Attributes:
        patch: Patch side, px of the network's input.
        scale: Patch side in image px = ``scale`` × the arc's projected radius at the end
            (f · radius / z): the same share of the needle at every distance.
        width: Channels of the first convolution (then 2×, 4×, 4×).
    """

    patch: int = 32
    scale: float = 0.8
    width: int = 16

    def __post_init__(self) -> None:
        if self.patch < 8 or self.patch % 8:
            raise ValueError(f"patch must be a multiple of 8, >= 8, got {self.patch}")
        if not self.scale > 0 or self.width < 1:
            raise ValueError("scale must be > 0 and width >= 1")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> EndConfig:
        return cls(**d)


def swapped(R: F64, arc: ArcModel) -> F64:
    """Rotations (n, 3, 3) with the needle's tip and tail swapped (same arc in the image)."""
    out: F64 = np.asarray(R, float) @ half_turn(arc)
    return out


def end_frames(K: F64, R: F64, t: F64, arc: ArcModel, cfg: EndConfig) -> tuple[F64, F64, F64]:
    """Image frames of the two ends of poses ``R`` (n, 3, 3), ``t`` (n, 3) mm seen by cameras
    ``K`` (3, 3) px, or (n, 3, 3) one per pose.

    Returns:
        centre (n, 2, 2) px (OpenCV pixel centres), axis (n, 2, 2) unit image direction of the
        wire's outward tangent at each end, side (n, 2) px; end 0 the tail, 1 the tip. Ends
        behind the camera get NaN.
    """
    R, t = np.asarray(R, float), np.asarray(t, float)
    K = np.broadcast_to(np.asarray(K, float), (len(R), 3, 3))
    KT = K.transpose(0, 2, 1)
    a = arc.arc_rad
    ends = arc.radius * np.array([[1.0, 0.0, 0.0], [np.cos(a), np.sin(a), 0.0]])
    out = np.array([[0.0, -1.0, 0.0], [-np.sin(a), np.cos(a), 0.0]])  # outward tangents
    step = 0.1 * arc.radius  # mm along the tangent: a short chord, still in front
    X = np.einsum("nij,kj->nki", R, ends) + t[:, None]  # (n, 2, 3) camera mm
    Y = X + step * np.einsum("nij,kj->nki", R, out)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(X[..., 2:] > 1e-6, X[..., 2:], np.nan)
        zy = np.where(Y[..., 2:] > 1e-6, Y[..., 2:], np.nan)
        uv = (X @ KT)[..., :2] / z
        uv_y = (Y @ KT)[..., :2] / zy
        d = uv_y - uv
        axis = d / np.linalg.norm(d, axis=-1, keepdims=True)
        side = cfg.scale * K[:, :1, 0] * arc.radius / z[..., 0]
    return uv, axis, side


def sample_patches(
    image: torch.Tensor, centre: torch.Tensor, axis: torch.Tensor, side: torch.Tensor, size: int
) -> torch.Tensor:
    """Rotated square patches of one image (1, C, H, W): patch pixel (i, j) sits at image
    ``centre + ((j + ½)/size − ½)·side·axis + ((i + ½)/size − ½)·side·axis⊥`` (axis⊥ the
    axis turned +90° in the image), bilinear, zeros outside. centre, axis (m, 2), side (m,)
    px -> (m, C, size, size)."""
    m = len(centre)
    h, w = image.shape[-2:]
    g = (torch.arange(size, dtype=centre.dtype, device=centre.device) + 0.5) / size - 0.5
    perp = torch.stack([-axis[:, 1], axis[:, 0]], dim=1)
    gx, gy = g[None, None, :, None], g[None, :, None, None]  # (1, 1, S, 1) x; (1, S, 1, 1) y
    s = side[:, None, None, None]
    pos = centre[:, None, None] + s * (gx * axis[:, None, None] + gy * perp[:, None, None])
    norm = torch.stack([(2 * pos[..., 0] + 1) / w - 1, (2 * pos[..., 1] + 1) / h - 1], dim=-1)
    src = image.expand(m, -1, -1, -1) if image.shape[0] == 1 else image
    return F.grid_sample(
        src, norm.to(src.dtype), mode="bilinear", padding_mode="zeros", align_corners=False
    )


def _patches_of(
    image: torch.Tensor,
    centre: torch.Tensor,
    axis: torch.Tensor,
    side: torch.Tensor,
    size: int,
    index: NDArray[np.int64],
) -> torch.Tensor:
    """:func:`sample_patches` of patches on several images (B, C, H, W): patch i on image
    ``index[i]``, each image's patches from a view of it (no copy per patch)."""
    if image.shape[0] == 1:
        return sample_patches(image, centre, axis, side, size)
    out = centre.new_empty((len(centre), image.shape[1], size, size))
    for b in np.unique(index):
        rows = torch.as_tensor(np.flatnonzero(index == b), device=centre.device)
        out[rows] = sample_patches(image[b : b + 1], centre[rows], axis[rows], side[rows], size)
    return out


class EndNet(nn.Module):
    """Patch (B, 3, P, P) in [0, 1] -> logit (B,) that it shows the needle's tip."""

    def __init__(self, cfg: EndConfig) -> None:
        super().__init__()
        w = cfg.width
        chans = [3, w, 2 * w, 4 * w, 4 * w]
        layers: list[nn.Module] = []
        for i, (cin, cout) in enumerate(itertools.pairwise(chans)):
            stride = 1 if i == 0 else 2
            layers += [nn.Conv2d(cin, cout, 3, stride, 1, bias=False), nn.BatchNorm2d(cout)]
            layers.append(nn.ReLU(inplace=True))
        self.body = nn.Sequential(*layers)
        self.head = nn.Linear(chans[-1], 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        # centred on the image's mean: the tissue's brightness is not a cue
        x = x - x.mean(dim=(1, 2, 3), keepdim=True)
        logits: torch.Tensor = self.head(self.body(x).mean(dim=(2, 3)))[:, 0]
        return logits


@dataclass
class EndStats:
    """What the end check did in a run: poses looked at and poses swapped."""

    checked: int = 0
    swapped: int = 0


class EndJudge:
    """A trained :class:`EndNet` and the decision: swap a pose whose tip patch looks less like
    a tip than its tail patch by more than ``margin`` (logits)."""

    def __init__(self, net: EndNet, cfg: EndConfig, arc: ArcModel, margin: float = 0.0) -> None:
        self.net, self.cfg, self.arc, self.margin = net.eval(), cfg, arc, float(margin)
        self.stats = EndStats()

    @torch.inference_mode()
    def logits(
        self, image: torch.Tensor, K: F64, R: F64, t: F64, index: NDArray[np.int64] | None = None
    ) -> F64:
        """(n, 2) tip logits of the tail (column 0) and tip (column 1) patches of the poses;
        NaN for an end that does not project (behind the camera). ``image`` (B, 3, H, W),
        pose i in image ``index[i]`` (None: all in image 0) seen by ``K`` (3, 3) or K[i]."""
        uv, axis, side = end_frames(K, R, t, self.arc, self.cfg)
        n = len(uv)
        ok = np.isfinite(uv).all(-1) & np.isfinite(axis).all(-1) & np.isfinite(side)
        out = np.full((n, 2), np.nan)
        if ok.any():
            dev = image.device
            c = torch.as_tensor(uv[ok], dtype=torch.float32, device=dev)
            a = torch.as_tensor(axis[ok], dtype=torch.float32, device=dev)
            s = torch.as_tensor(side[ok], dtype=torch.float32, device=dev)
            idx = np.zeros(n, np.int64) if index is None else np.asarray(index, np.int64)
            x = _patches_of(image, c, a, s, self.cfg.patch, np.repeat(idx[:, None], 2, 1)[ok])
            out[ok] = self.net(x).double().cpu().numpy()
        return out

    def __call__(
        self,
        image: torch.Tensor,
        K: F64,
        R: F64,
        t: F64,
        margin: float | F64 | None = None,
        index: NDArray[np.int64] | None = None,
    ) -> tuple[F64, NDArray[np.bool_]]:
        """The rotations (n, 3, 3), tip and tail swapped where the patches say so, and which.

        image (B, 3, H, W) float RGB in [0, 1]; K (3, 3) px or (n, 3, 3) per pose; R (n, 3,
        3); t (n, 3) mm; ``margin``: logits, one or (n,) per pose (default: the judge's);
        ``index`` (n,): the image of each pose (None: all in image 0)."""
        R = np.asarray(R, float)
        lg = self.logits(image, K, R, t, index)
        m = self.margin if margin is None else np.asarray(margin, float)
        swap = np.nan_to_num(lg[:, TAIL] - lg[:, TIP], nan=-np.inf) > m
        self.stats.checked += len(R)
        self.stats.swapped += int(swap.sum())
        return np.where(swap[:, None, None], swapped(R, self.arc), R), swap


def load_judge(path: str | Path, device: torch.device, margin: float | None = None) -> EndJudge:
    """The end classifier of a ``needle_ends`` checkpoint (written by :mod:`.train_ends`).

    ``margin`` (logits) overrides the one recorded with the classifier (its ``meta.margin``,
    chosen on validation splits with ``bench/bench_ends.py``; 0 when none is recorded)."""
    state, info = load_checkpoint(path, "needle_ends")
    if margin is None:
        margin = float(info["meta"].get("margin", 0.0))
        if not np.isfinite(margin):  # NaN would silently never swap
            raise CheckpointError(f"{config_path(path)}: meta.margin must be a finite logit margin")
    cfg = EndConfig.from_dict(info["config"])
    net = EndNet(cfg)
    load_weights(net, state, path)
    arc = info["meta"]["arc"]
    return EndJudge(
        net.to(device), cfg, ArcModel(radius=float(arc["radius"]), arc_rad=float(arc["arc_rad"])),
        margin,
    )  # fmt: skip

"""Run an exported ``gdrnet`` pipeline with numpy and onnxruntime: no torch.

The folder ``bopsurg export`` wrote (:mod:`.export`) holds ``detector.onnx`` and one pose head
per object, each with its JSON. :class:`OnnxPipeline` does what the torch estimator
(:mod:`.estimator`) does with its refinement and end check off: letterbox
and detect, keep the best boxes of each object, crop the pose head's square ROIs (1.5 x the
box, at each ``zoom`` multiple), run the head and decode its rotation and SITE outputs
directly into BOP poses (R model-to-camera, t in mm), averaging the zoom crops' poses. The
needle segmenter is exported too, for a caller's own refinement; this runner does not use it.

It is registered as the ``gdrnet-onnx`` estimator (``bopsurg predict --estimator
gdrnet-onnx --option dir=FOLDER``), and ``python -m bopsurg.models.onnx_runtime FOLDER
IMAGE --K fx,fy,cx,cy`` prints the poses of one image. The maths mirrors the torch modules it
names (:mod:`.detector.letterbox`, :mod:`.detector.anchors`, :mod:`.pose.roi`,
:mod:`.pose.encodings`), rewritten in numpy because those import torch.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from bopsurg.errors import BopsurgError
from bopsurg.estimation import Detections, PosePredictions

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
#: Upper bound of the detector's raw log-size (:data:`.detector.anchors.MAX_LOG_SIZE`).
MAX_LOG_SIZE = 10.0


def letterbox(rgb: NDArray[np.uint8], input_hw: Sequence[int], grey: int) -> tuple[F32, float]:
    """(H, W, 3) uint8 → the detector's (1, 3, h, w) float input in [0, 1], image at the
    top-left, the rest ``grey``; and the scale (input px per image px)."""
    h, w = int(input_hw[0]), int(input_hw[1])
    scale = min(h / rgb.shape[0], w / rgb.shape[1])
    nh, nw = round(rgb.shape[0] * scale), round(rgb.shape[1] * scale)
    out = np.full((h, w, 3), grey, np.uint8)
    interp = cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
    out[:nh, :nw] = cv2.resize(rgb, (nw, nh), interpolation=interp)
    return (out.transpose(2, 0, 1)[None].astype(np.float32) / 255).astype(np.float32), scale


def anchors(input_hw: Sequence[int], strides: Sequence[int]) -> tuple[F32, F32]:
    """Grid cells (A, 2) (column, row) and their strides (A,), px, in the detector's order."""
    grids, strs = [], []
    for s in strides:
        rows, cols = np.meshgrid(
            np.arange(input_hw[0] // s), np.arange(input_hw[1] // s), indexing="ij"
        )
        grids.append(np.stack([cols.ravel(), rows.ravel()], axis=1))
        strs.append(np.full(rows.size, float(s)))
    return np.concatenate(grids).astype(np.float32), np.concatenate(strs).astype(np.float32)


def nms(boxes: F64, scores: F64, iou_thr: float) -> NDArray[np.int64]:
    """Greedy NMS of (N, 4) xyxy boxes: indices kept, by decreasing score (stable)."""
    order = np.argsort(-scores, kind="stable")
    b = boxes[order]
    area = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    lo = np.maximum(b[:, None, :2], b[None, :, :2])
    hi = np.minimum(b[:, None, 2:], b[None, :, 2:])
    inter = np.prod(np.clip(hi - lo, 0, None), axis=2)
    over = inter / (area[:, None] + area[None, :] - inter) > iou_thr
    suppressed = np.zeros(len(b), bool)
    keep = []
    for i in range(len(b)):  # greedy: each kept box suppresses the later ones it overlaps
        if not suppressed[i]:
            keep.append(i)
            suppressed |= over[i]
    return order[np.array(keep, np.int64)]


def decode_detections(
    raw: F32, meta: Mapping[str, Any], conf: float, input_hw: Sequence[int]
) -> F64:
    """One image's raw predictions (A, 5 + C) → (k, 6) x1, y1, x2, y2 (input px, clipped),
    score, class index, by decreasing score (the steps of :meth:`YoloxDetector.detect`)."""
    grid, strides = anchors(input_hw, meta["strides"])
    raw = raw.astype(np.float32)
    xy = (raw[:, :2] + grid) * strides[:, None]
    wh = np.exp(np.minimum(raw[:, 2:4], MAX_LOG_SIZE)) * strides[:, None]
    prob = 1 / (1 + np.exp(-raw[:, 4:].astype(np.float64)))
    cls_id = prob[:, 1:].argmax(axis=1)
    score = prob[:, 0] * prob[np.arange(len(prob)), 1 + cls_id]
    keep = np.flatnonzero(score >= conf)
    det = meta["detect"]
    if len(keep) > det["pre_nms_top_k"]:
        keep = keep[np.argsort(-score[keep], kind="stable")[: det["pre_nms_top_k"]]]
    boxes = np.concatenate([xy - wh / 2, xy + wh / 2], axis=1)[keep].astype(np.float64)
    h, w = input_hw
    boxes = np.minimum(np.maximum(boxes, 0), [w, h, w, h])
    if len(keep) == 0:
        return np.zeros((0, 6))
    span = boxes.max() - boxes.min() + 1  # class-aware: shift each class apart
    kept = nms(boxes + (cls_id[keep] * span)[:, None], score[keep], det["nms_iou"])
    kept = kept[: det["max_det"]]
    return np.concatenate([boxes[kept], score[keep][kept, None], cls_id[keep][kept, None]], 1)


def crop(image: F32, centre: F64, side: F64, size: int) -> F32:
    """Bilinear square crops (n, 3, size, size) of a (3, H, W) float image, zeros outside:
    output pixel u samples ``centre + (u − size/2) · side/size`` (as :func:`.pose.roi.crop`)."""
    _, H, W = image.shape
    u = np.arange(size) - size / 2
    x = centre[:, 0, None] + u[None] * (side / size)[:, None]  # (n, S) per column
    y = centre[:, 1, None] + u[None] * (side / size)[:, None]  # (n, S) per row
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    fx, fy = (x - x0).astype(np.float32), (y - y0).astype(np.float32)
    out = np.zeros((len(centre), image.shape[0], size, size), np.float32)
    for dy, wy in ((0, 1 - fy), (1, fy)):
        for dx, wx in ((0, 1 - fx), (1, fx)):
            xi, yi = x0 + dx, y0 + dy
            ok = ((xi >= 0) & (xi < W))[:, None, :] & ((yi >= 0) & (yi < H))[:, :, None]
            px = image[:, np.clip(yi, 0, H - 1)[:, :, None], np.clip(xi, 0, W - 1)[:, None, :]]
            weight = wy[:, :, None] * wx[:, None, :] * ok  # (n, S, S)
            out += np.moveaxis(px, 0, 1) * weight[:, None]
    return out


def roi_coord_2d(centre: F64, side: F64, size: int, image_hw: Sequence[int]) -> F32:
    """(n, 2, size, size) image-normalised ``((x + ½)/W, (y + ½)/H)`` of the ROI pixels."""
    u = np.arange(size) - size / 2
    x = centre[:, 0, None] + u[None] * (side / size)[:, None]
    y = centre[:, 1, None] + u[None] * (side / size)[:, None]
    n = len(centre)
    cx = np.broadcast_to(((x + 0.5) / image_hw[1])[:, None, :], (n, size, size))
    cy = np.broadcast_to(((y + 0.5) / image_hw[0])[:, :, None], (n, size, size))
    return np.stack([cx, cy], axis=1).astype(np.float32)


def _unit(v: F64) -> F64:
    return np.asarray(v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12))


def rotation_from_rot6d(x: F64) -> F64:
    """(n, 6) codes → (n, 3, 3) rotations by Gram-Schmidt (columns b1, b2, b3)."""
    b1 = _unit(x[:, :3])
    b3 = _unit(np.cross(b1, x[:, 3:]))
    return np.stack([b1, np.cross(b3, b1), b3], axis=2)


def ray_rotation(t: F64) -> F64:
    """(n, 3, 3) rotations turning the optical axis onto the ray of ``t`` (allo → ego)."""
    d = _unit(t)
    dx, dy, c = d[:, 0], d[:, 1], d[:, 2]
    z = np.zeros_like(c)
    vx = np.stack([np.stack([z, z, dx], 1), np.stack([z, z, dy], 1), np.stack([-dx, -dy, z], 1)], 1)
    regular = c > -1.0 + 1e-6
    denom = np.where(regular, 1.0 + c, 1.0)
    R = np.eye(3) + vx + vx @ vx / denom[:, None, None]
    return np.where(regular[:, None, None], R, np.diag([1.0, -1.0, -1.0]))


def site_decode(site: F64, K: F64, centre: F64, wh: F64, side: F64, meta: Mapping[str, Any]) -> F64:
    """(n, 3) SITE → t (n, 3) mm: the projected centre ``δ_xy · wh + c`` at depth
    ``δz · z_unit_mm · roi_out / side``."""
    o = site[:, :2] * wh + centre
    tz = site[:, 2] * meta["z_unit_mm"] * (meta["roi_out"] / side)
    ray = np.linalg.solve(K, np.concatenate([o, np.ones((len(o), 1))], 1)[:, :, None])[:, :, 0]
    return np.asarray(ray / ray[:, 2:3] * tz[:, None])


def nearest_rotation(m: F64) -> F64:
    """Proper rotations nearest to (n, 3, 3) matrices (SVD, reflection flipped)."""
    U, _, Vh = np.linalg.svd(m)
    d = np.sign(np.linalg.det(U @ Vh))
    U = np.concatenate([U[..., :2], U[..., 2:] * d[:, None, None]], axis=-1)
    return np.asarray(U @ Vh)


#: The newest metadata format this runner reads (:data:`.export.META_FORMAT`).
META_FORMAT = 1


def _read_meta(path: Path) -> dict[str, Any] | None:
    """An export's metadata, or None for a JSON file that is not one (no ``onnx`` key)."""
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise BopsurgError(f"{path}: not a readable JSON file ({err})") from err
    if not isinstance(meta, dict) or "onnx" not in meta:
        return None
    if not isinstance(meta.get("format"), int) or meta["format"] > META_FORMAT:
        raise BopsurgError(
            f"{path}: format: expected an export of format <= {META_FORMAT}, got "
            f"{meta.get('format')!r} (a newer bopsurg wrote it)"
        )
    return meta | {"_dir": path.parent}


class OnnxPipeline:
    """An exported detector + pose heads; implements :class:`bopsurg.estimation.PoseEstimator`.

    Args:
        folder: What ``bopsurg export`` wrote (``*.onnx`` with their ``*.json``).
        conf: Minimum detection score kept (default: the one recorded at export).
        max_per_object: Boxes (hence poses) kept per object and image, best first.
        zoom: Crop sides as multiples of the 1.5 x box crop whose poses are averaged
            (default: the estimator's, recorded at export; ``(1.0,)`` is one crop).
        providers: onnxruntime execution providers.
        threads: onnxruntime's intra-op threads (default: its own choice).
    """

    def __init__(
        self,
        folder: str | Path,
        *,
        conf: float | None = None,
        max_per_object: int = 1,
        zoom: Sequence[float] | None = None,
        providers: Sequence[str] = ("CPUExecutionProvider",),
        threads: int | None = None,
    ) -> None:
        try:
            import onnxruntime as ort
        except ImportError as err:
            raise BopsurgError(
                "gdrnet-onnx needs onnxruntime: pip install 'bopsurg[onnx]'"
            ) from err
        folder = Path(folder)
        metas = [m for p in sorted(folder.glob("*.json")) if (m := _read_meta(p)) is not None]
        found = {m.get("kind") for m in metas}
        if "detector" not in found or "pose" not in found:
            raise BopsurgError(f"{folder}: no exported detector and pose head (run bopsurg export)")

        options = ort.SessionOptions()
        if threads is not None:
            options.intra_op_num_threads = threads

        def session(m: dict[str, Any]) -> Any:
            path = str(m["_dir"] / m["onnx"])
            return ort.InferenceSession(path, options, providers=list(providers))

        self.det_meta = next(m for m in metas if m["kind"] == "detector")
        self.detector = session(self.det_meta)
        heads = [m for m in metas if m.get("kind") == "pose"]
        self.heads = {int(m["obj_id"]): (m, session(m)) for m in heads}
        if len(self.heads) < len(heads):
            raise BopsurgError(f"{folder}: two exported pose heads are for the same obj_id")
        self.obj_ids = tuple(sorted(self.heads))
        self.conf = float(self.det_meta["detect"]["conf"] if conf is None else conf)
        self.max_per_object = max_per_object
        self.zoom = None if zoom is None else tuple(float(z) for z in zoom)

    def detect(self, rgb: NDArray[np.uint8]) -> Detections:
        """Boxes (BOP xywh, px) of the exported detector in one (H, W, 3) uint8 image."""
        m = self.det_meta
        x, scale = letterbox(rgb, m["input_hw"], m["letterbox"]["pad_grey"])
        (raw,) = self.detector.run(["raw"], {"images": x})
        det = decode_detections(raw[0], m, self.conf, m["input_hw"])
        xyxy = det[:, :4] / scale
        classes = np.asarray(m["classes"], np.int64)
        return Detections(classes[det[:, 5].astype(np.int64)], det[:, 4], np.concatenate(
            [xyxy[:, :2], xyxy[:, 2:] - xyxy[:, :2]], axis=1))  # fmt: skip

    def head_poses(self, obj_id: int, image: F32, K: F64, box_xywh: F64) -> tuple[F64, F64]:
        """Direct poses R (n, 3, 3), t (n, 3) mm of one object's boxes (n, 4) (x, y, w, h)
        in pixel-centre px, on ``image`` (3, H, W) float in [0, 1]."""
        meta, sess = self.heads[obj_id]
        zoom = np.asarray(self.zoom or meta["zoom"], np.float64)
        hw = image.shape[1:]
        n, k = len(box_xywh), len(zoom)
        side = np.clip(meta["dzi_pad"] * box_xywh[:, 2:].max(axis=1), 1.0, max(hw))
        sides = np.clip(side[:, None] * zoom, 1.0, max(hw)).reshape(-1)
        centres = np.repeat(box_xywh[:, :2] + 0.5 * box_xywh[:, 2:], k, axis=0)
        # the torch path runs these in float32: keep that precision for the same crops
        sides = sides.astype(np.float32).astype(np.float64)
        centres = centres.astype(np.float32).astype(np.float64)
        feed = {
            "roi_img": crop(image, centres, sides, meta["roi_in"]),
            "roi_coord2d": roi_coord_2d(centres, sides, meta["roi_out"], hw),
        }
        rot6d, site = sess.run(["rot6d", "site"], feed)
        wh = np.repeat(box_xywh[:, 2:], k, axis=0)
        t = site_decode(site.astype(np.float64), np.asarray(K, float), centres, wh, sides, meta)
        R = ray_rotation(t) @ rotation_from_rot6d(rot6d.astype(np.float64))
        return nearest_rotation(R.reshape(n, k, 3, 3).mean(1)), t.reshape(n, k, 3).mean(1)

    def predict(
        self,
        rgb: NDArray[np.uint8],
        K: F64,
        *,
        obj_ids: tuple[int, ...] | None = None,
        boxes: Detections | None = None,
    ) -> PosePredictions:
        """Poses of the objects in one image (see :class:`bopsurg.estimation.PoseEstimator`)."""
        wanted = tuple(o for o in (obj_ids or self.obj_ids) if o in self.heads)
        found = self.detect(rgb) if boxes is None and wanted else boxes or Detections.empty()
        keep: list[int] = []
        for o in wanted:
            rows = np.flatnonzero(found.obj_id == o)
            keep.extend(rows[np.argsort(-found.score[rows], kind="stable")][: self.max_per_object])
        found = found.subset(np.array(keep, np.int64))
        if len(found) == 0:
            return PosePredictions.empty()
        image = rgb.transpose(2, 0, 1).astype(np.float32) / np.float32(255)
        R_out, t_out = np.zeros((len(found), 3, 3)), np.zeros((len(found), 3))
        for obj in np.unique(found.obj_id):
            rows = np.flatnonzero(found.obj_id == obj)
            box = found.bbox[rows] - np.array([0.5, 0.5, 0.0, 0.0])  # pixel-centre convention
            R_out[rows], t_out[rows] = self.head_poses(int(obj), image, K, box)
        return PosePredictions(found.obj_id, found.score, R_out, t_out, found.bbox)


@dataclass(frozen=True)
class OnnxConfig:
    """The ``gdrnet-onnx`` estimator's settings (``bopsurg predict --option KEY=VALUE``).

    Attributes:
        dir: The export folder (``bopsurg export --out``).
        conf: Lowest detection score kept (null: the export's).
        max_per_object: Boxes (hence poses) kept per object and image, best first.
        zoom: Crop sides as multiples of the 1.5 x box crop, poses averaged (null: the
            export's).
        device: Accepted for ``bopsurg predict --device``; onnxruntime runs on the CPU.
    """

    dir: str = ""
    conf: float | None = None
    max_per_object: int = 1
    zoom: tuple[float, ...] | None = None
    device: str = "auto"


def create(options: Mapping[str, Any]) -> OnnxPipeline:
    """The ``gdrnet-onnx`` factory for ``bopsurg predict`` (settings: :class:`OnnxConfig`)."""
    from bopsurg.models.config_tree import from_mapping

    cfg = from_mapping(OnnxConfig, options, "gdrnet-onnx")
    if not cfg.dir:
        raise BopsurgError("gdrnet-onnx: pass the export folder: --option dir=FOLDER")
    return OnnxPipeline(cfg.dir, conf=cfg.conf, max_per_object=cfg.max_per_object, zoom=cfg.zoom)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m bopsurg.models.onnx_runtime FOLDER IMAGE --K fx,fy,cx,cy``: one image's
    poses as BOP CSV rows (scene 0, image 0, time -1)."""
    p = argparse.ArgumentParser(
        prog="python -m bopsurg.models.onnx_runtime", description=main.__doc__
    )
    p.add_argument("folder", help="what bopsurg export wrote")
    p.add_argument("image", help="RGB image (png, jpg)")
    p.add_argument("--K", required=True, help="fx,fy,cx,cy in px")
    p.add_argument("--zoom", default=None, help="crop multiples, e.g. 1 (default: the export's)")
    args = p.parse_args(argv)
    try:
        fx, fy, cx, cy = (float(v) for v in args.K.split(","))
        from bopsurg.bop.images import load_rgb

        zoom = {"zoom": [float(z) for z in args.zoom.split(",")]} if args.zoom else {}
        pred = create({"dir": args.folder, **zoom}).predict(
            load_rgb(args.image), np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
        )
    except (BopsurgError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)  # noqa: T201
        return 2
    print("scene_id,im_id,obj_id,score,R,t,time")  # noqa: T201
    for i in range(len(pred)):
        R = " ".join(f"{v:.8f}" for v in pred.R[i].ravel())
        t = " ".join(f"{v:.6f}" for v in pred.t[i])
        print(f"0,0,{pred.obj_id[i]},{pred.score[i]:.6f},{R},{t},-1")  # noqa: T201
    return 0


if __name__ == "__main__":
    sys.exit(main())

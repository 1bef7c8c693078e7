"""Log an evaluation to a rerun recording (``.rrd``) for visual error analysis.

Layout of the recording (entity paths; ``frame`` is a sequence timeline, one step per image
that has GT or estimates, in ``(scene_id, im_id)`` order):

- ``world``: the camera frame (RDF, mm; the camera sits at the origin).
- ``world/camera``: :class:`rerun.Pinhole` (K, resolution), per image frame.
- ``world/camera/rgb``: the image, JPEG-encoded (:class:`rerun.EncodedImage`).
- ``world/camera/gt_silhouette`` (blue) and ``world/camera/est_silhouette`` (green):
  :class:`rerun.SegmentationImage` overlays as in the paper's Fig. 3; the estimated silhouette
  fills the model's triangles projected at each estimated pose, the GT one is the union of the
  ``mask_visib`` masks (or the same projection at the GT poses where a mask is missing).
- ``world/gt/obj_{obj_id:06d}`` (blue) and ``world/est/obj_{obj_id:06d}`` (green): the model
  meshes (mm) at the GT and estimated poses.
- ``metrics/{re,te,mssd,mspd}`` (the registered metrics with ``in_rerun``,
  :mod:`bopsurg.metrics.registry`) and ``metrics/visib_fract``: per-frame errors (deg, mm, mm,
  px, fraction); ``metrics/worst_rank``: 1..N on the N frames with the largest MSSD.
- ``frame_info/{scene_id,im_id}``: the ids of each frame.
- ``world/camera/boxes``: the 2D boxes the estimates came from (``--detections``), labelled
  with object id and score.
- ``histograms/{re,te,mssd}`` (the metrics of the paper's table; :class:`rerun.BarChart`,
  interactive), ``histograms/{re,te,mssd}_plot`` (the paper's Fig. 4: the histogram drawn as
  an image with the median marked by a red line) and ``histograms/medians`` (text).
- ``report/summary`` (the paper's table, markdown) and ``report/worst`` (the worst frames).

The per-frame value of a metric is the largest over the frame's matched estimates (the one an
error analysis wants to see); with one object instance per image it is that estimate's value
in errors.csv. Frames without a matched estimate have no metric values.

Cost: scalars go for every frame in one columnar call each (:func:`rerun.send_columns`);
images, silhouettes and meshes, the costly part (~10 ms a frame), only for the frames chosen
by :func:`select_image_frames`: all frames up to :data:`DEFAULT_IMAGE_FRAMES`, else the
:data:`DEFAULT_IMAGE_FRAMES` worst (largest MSSD) plus as many spread uniformly over the rest.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
import pandas as pd

from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.detections import Detections
from bopsurg.bop.images import load_mask, load_rgb
from bopsurg.bop.results import PoseEstimates
from bopsurg.errors import BopsurgError
from bopsurg.evaluation.summary import format_table
from bopsurg.metrics.registry import rerun_metrics, table_metrics
from bopsurg.silhouette import is_closed, project_silhouette

if TYPE_CHECKING:
    from bopsurg.evaluation.runner import Evaluation

log = logging.getLogger(__name__)

#: Frames with images when ``max_frames`` is None: all up to this many, else this many worst
#: frames plus this many spread uniformly over the others. Images cost ~4 ms a frame (JPEG,
#: two silhouettes, mesh poses) while scalars for 10,000 frames cost ~0.3 s, so 200 images
#: keep the recording cheaper than the evaluation it shows.
DEFAULT_IMAGE_FRAMES = 100
#: Silhouette colours (RGB): GT blue, estimate green, as in the paper's Fig. 3.
GT_COLOR = (40, 90, 255)
EST_COLOR = (0, 220, 0)
#: Detector boxes (RGB).
BOX_COLOR = (255, 200, 0)
JPEG_QUALITY = 85
HIST_BINS = 30


def _import_rerun() -> Any:
    try:
        import rerun as rr
    except ImportError as err:
        raise BopsurgError("rerun-sdk is not installed; pip install bopsurg[rerun]") from err
    return rr


def frame_table(errors: pd.DataFrame, gt_rows: pd.DataFrame) -> pd.DataFrame:
    """One row per image with GT or estimates, in ``(scene_id, im_id)`` order.

    Args:
        errors: errors.csv rows (:attr:`Evaluation.errors`).
        gt_rows: Per-GT rows (:attr:`Evaluation.gt_rows`).

    Returns:
        Columns ``frame`` (0..n-1), ``scene_id``, ``im_id``, ``n_gt``, ``n_est`` and per metric
        of :func:`~bopsurg.metrics.registry.rerun_metrics` plus ``visib_fract`` the largest
        value over the frame's matched estimates (NaN when none is matched): RE deg, TE/MSSD
        mm, MSPD px.
    """
    key = ["scene_id", "im_id"]
    ids = pd.concat([errors[key], gt_rows[key]]).drop_duplicates()
    frames = ids.sort_values(key).reset_index(drop=True).astype(np.int64)
    frames.insert(0, "frame", np.arange(len(frames), dtype=np.int64))
    frames = frames.merge(gt_rows.groupby(key).size().rename("n_gt"), on=key, how="left")
    frames = frames.merge(errors.groupby(key).size().rename("n_est"), on=key, how="left")
    matched = errors[errors["gt_id"] >= 0]
    names = [m.name for m in rerun_metrics()]
    cols = [c for c in (*names, "visib_fract") if c in matched]
    frames = frames.merge(matched.groupby(key)[cols].max(), on=key, how="left")
    frames[["n_gt", "n_est"]] = frames[["n_gt", "n_est"]].fillna(0).astype(np.int64)
    return frames


def select_image_frames(mssd: np.ndarray, max_frames: int | None = None) -> np.ndarray:
    """The frames that get images (see the module docstring).

    Args:
        mssd: (F,) per-frame MSSD, mm (NaN = no matched estimate, ranked last).
        max_frames: At most this many frames: half the worst (largest MSSD), the rest spread
            uniformly over the others. None: all when F ≤ :data:`DEFAULT_IMAGE_FRAMES`, else
            that many worst plus that many uniform.

    Returns:
        Sorted frame indices.
    """
    n = len(mssd)
    if max_frames is None:
        budget = n if n <= DEFAULT_IMAGE_FRAMES else 2 * DEFAULT_IMAGE_FRAMES
    else:
        budget = max(0, int(max_frames))
    if budget >= n:
        return np.arange(n)
    n_worst = budget // 2 if max_frames is not None else DEFAULT_IMAGE_FRAMES
    order = np.argsort(-np.nan_to_num(np.asarray(mssd, float), nan=-np.inf), kind="stable")
    worst = order[:n_worst]
    rest = np.setdiff1d(np.arange(n), worst)
    n_uniform = min(budget - n_worst, len(rest))
    uniform = (
        rest[np.linspace(0, len(rest) - 1, n_uniform).round().astype(int)] if n_uniform else []
    )
    return np.union1d(worst, uniform).astype(np.int64)


def _blueprint(rrb: Any) -> Any:
    hists = [m.name for m in table_metrics()]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial2DView(name="image", origin="world/camera"),
                rrb.Spatial3DView(name="3D", origin="world"),
            ),
            rrb.Vertical(
                rrb.TimeSeriesView(name="errors", origin="metrics"),
                rrb.Tabs(
                    *(
                        rrb.Spatial2DView(
                            name=f"{n.upper()} histogram", origin=f"histograms/{n}_plot"
                        )
                        for n in hists
                    ),
                    *(
                        rrb.BarChartView(name=f"{n.upper()} bars", origin=f"histograms/{n}")
                        for n in hists
                    ),
                ),
                rrb.Tabs(
                    rrb.TextDocumentView(name="worst frames", origin="report/worst"),
                    rrb.TextDocumentView(name="summary", origin="report/summary"),
                    rrb.TextDocumentView(name="medians", origin="histograms/medians"),
                ),
            ),
            column_shares=[3, 2],
        ),
        collapse_panels=True,
    )


def log_evaluation(
    dataset: BopDataset,
    estimates: PoseEstimates,
    evaluation: Evaluation,
    path: str | Path,
    *,
    max_frames: int | None = None,
    worst: int = 20,
    detections: Mapping[tuple[int, int], Detections] | None = None,
) -> Path:
    """Write an evaluation as a rerun recording, headless (no viewer is started).

    Args:
        dataset: The evaluated dataset (images, masks, cameras, GT poses, models).
        estimates: The evaluated estimates (poses: R, t mm).
        evaluation: :func:`bopsurg.evaluation.runner.evaluate`'s result.
        path: The ``.rrd`` file to write (parent folders are created).
        max_frames: At most this many frames get images, silhouettes and meshes (see
            :func:`select_image_frames`); scalars go for all frames.
        worst: Length of the "worst frames" list (largest per-frame MSSD, mm).
        detections: 2D boxes per ``(scene_id, im_id)`` (e.g. ``bopsurg predict
            --detections-out``), drawn on the images.

    Returns:
        The written path. Open it with ``rerun FILE.rrd``.

    Raises:
        BopsurgError: rerun-sdk is not installed.
    """
    rr = _import_rerun()
    import rerun.blueprint as rrb

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    frames = frame_table(evaluation.errors, evaluation.gt_rows)
    n = len(frames)
    rec = rr.RecordingStream("bopsurg_eval", recording_id=None)
    rec.save(path, default_blueprint=_blueprint(rrb))
    try:
        _log_static(rr, rec, frames, evaluation, worst)
        _log_scalars(rr, rec, frames, worst)
        chosen = select_image_frames(frames["mssd"].to_numpy(float), max_frames)
        _log_images(rr, rec, dataset, estimates, frames.iloc[chosen], detections or {})
        log.info("rerun: %d frames, %d with images -> %s", n, len(chosen), path)
    finally:
        rec.flush()
        rec.disconnect()
    return path


def _worst_frames(frames: pd.DataFrame, worst: int) -> pd.DataFrame:
    ranked = frames[np.isfinite(frames["mssd"].to_numpy(float))]
    return ranked.sort_values("mssd", ascending=False, kind="stable").head(max(0, worst))


def histogram_figure(
    counts: np.ndarray,
    edges: np.ndarray,
    median: float,
    label: str,
    size: tuple[int, int] = (360, 560),
) -> np.ndarray:
    """The paper's Fig. 4 panel as an RGB image: bars, x ticks, the median as a red line.

    Args:
        counts: (B,) bin counts.
        edges: (B + 1,) bin edges (the metric's unit).
        median: Where to draw the median line.
        label: x-axis label, e.g. ``"RE [deg]"``.
        size: (height, width) px.

    Returns:
        (H, W, 3) uint8 image, white background.
    """
    h, w = size
    img = np.full((h, w, 3), 255, np.uint8)
    left, right, top, bottom = 40, 12, 28, 46
    x0, x1, y0, y1 = left, w - right, top, h - bottom
    lo, hi = float(edges[0]), float(edges[-1])
    span = hi - lo if hi > lo else 1.0

    def x_of(v: float) -> int:
        return round(x0 + (v - lo) / span * (x1 - x0))

    peak = max(int(counts.max()), 1)
    for c, a, b in zip(counts, edges[:-1], edges[1:], strict=True):
        top_px = round(y1 - float(c) / peak * (y1 - y0))
        cv2.rectangle(img, (x_of(a), top_px), (max(x_of(a), x_of(b) - 1), y1), (90, 120, 200), -1)
    cv2.line(img, (x0, y1), (x1, y1), (0, 0, 0), 1)
    cv2.line(img, (x0, y0), (x0, y1), (0, 0, 0), 1)
    font = cv2.FONT_HERSHEY_SIMPLEX
    for v in np.linspace(lo, hi, 5):
        cv2.line(img, (x_of(v), y1), (x_of(v), y1 + 4), (0, 0, 0), 1)
        cv2.putText(img, f"{v:.3g}", (x_of(v) - 14, y1 + 17), font, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, str(peak), (4, y0 + 5), font, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(
        img, label, (x0 + (x1 - x0) // 2 - 30, h - 8), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA
    )
    xm = x_of(median)
    cv2.line(img, (xm, y0), (xm, y1), (220, 0, 0), 2)
    cv2.putText(
        img, f"median {median:.2f}", (min(xm + 4, w - 110), y0 - 8), font, 0.45, (220, 0, 0), 1,
        cv2.LINE_AA,
    )  # fmt: skip
    return img


def _log_static(rr: Any, rec: Any, frames: pd.DataFrame, ev: Evaluation, worst: int) -> None:
    rec.log("world", rr.ViewCoordinates.RDF, static=True)
    for name, color in (("gt_silhouette", GT_COLOR), ("est_silhouette", EST_COLOR)):
        rec.log(
            f"world/camera/{name}",
            rr.AnnotationContext([(1, name.split("_")[0], color)]),
            static=True,
        )
    # the instances of the paper's table (visib_fract >= min_visib), so the medians agree
    min_visib = ev.summary.get("min_visib", 0.0)
    assert isinstance(min_visib, int | float)
    matched = ev.errors[(ev.errors["gt_id"] >= 0) & (ev.errors["visib_fract"] >= min_visib)]
    lines = [f"# Medians (matched estimates, visib_fract >= {min_visib:g}, as the table)", ""]
    for m in table_metrics():
        name, heading = m.name, m.heading()
        values = matched[name].to_numpy(float) if name in matched else np.array([])
        values = values[np.isfinite(values)]
        if len(values) == 0:
            lines.append(f"- {name.upper()}: no values")
            continue
        counts, edges = np.histogram(values, bins=HIST_BINS)
        median = float(np.median(values))
        rec.log(
            f"histograms/{name}",
            rr.BarChart(
                counts,
                abscissa=(edges[:-1] + edges[1:]) / 2,
                widths=np.diff(edges).astype(np.float32),
            ),
            static=True,
        )
        rec.log(
            f"histograms/{name}_plot",
            rr.Image(histogram_figure(counts, edges, median, heading)),
            static=True,
        )
        lines.append(
            f"- {heading}: median {median:.2f} (bin "
            f"{int(np.searchsorted(edges, median, side='right')) - 1} of {HIST_BINS}, "
            f"{edges[0]:.2f}..{edges[-1]:.2f})"
        )
    rec.log(
        "histograms/medians",
        rr.TextDocument("\n".join(lines), media_type=rr.MediaType.MARKDOWN),
        static=True,
    )
    table = format_table(ev.summary, ev.scores)
    rec.log(
        "report/summary",
        rr.TextDocument(f"# Evaluation\n\n```\n{table}\n```\n", media_type=rr.MediaType.MARKDOWN),
        static=True,
    )
    top = _worst_frames(frames, worst)
    rows = [
        f"# {len(top)} worst frames (largest MSSD)",
        "",
        "Jump there on the `frame` timeline; `metrics/worst_rank` marks them.",
        "",
        "| rank | frame | scene | image | MSSD [mm] | RE [deg] | TE [mm] | visib |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for rank, r in enumerate(top.itertuples(index=False), start=1):
        rows.append(
            f"| {rank} | {r.frame} | {r.scene_id} | {r.im_id} | {r.mssd:.2f} | "
            f"{getattr(r, 're', np.nan):.2f} | {getattr(r, 'te', np.nan):.2f} | "
            f"{getattr(r, 'visib_fract', np.nan):.2f} |"
        )
    rec.log(
        "report/worst",
        rr.TextDocument("\n".join(rows), media_type=rr.MediaType.MARKDOWN),
        static=True,
    )


def _send(rr: Any, rec: Any, entity: str, frame: np.ndarray, values: np.ndarray) -> None:
    ok = np.isfinite(values)
    if not ok.any():
        return
    rec.send_columns(
        entity,
        indexes=[rr.TimeColumn("frame", sequence=frame[ok])],
        columns=rr.Scalars.columns(scalars=values[ok].astype(np.float64)),
    )


def _log_scalars(rr: Any, rec: Any, frames: pd.DataFrame, worst: int) -> None:
    frame = frames["frame"].to_numpy(np.int64)
    for name in (*(m.name for m in rerun_metrics()), "visib_fract"):
        if name in frames:
            _send(rr, rec, f"metrics/{name}", frame, frames[name].to_numpy(float))
    for name in ("scene_id", "im_id"):
        _send(rr, rec, f"frame_info/{name}", frame, frames[name].to_numpy(float))
    top = _worst_frames(frames, worst)
    if len(top):
        order = np.argsort(top["frame"].to_numpy())
        _send(
            rr,
            rec,
            "metrics/worst_rank",
            top["frame"].to_numpy(np.int64)[order],
            np.arange(1, len(top) + 1, dtype=float)[order],
        )
        rec.log(
            "metrics/worst_rank", rr.SeriesPoints(markers="cross", marker_sizes=6.0), static=True
        )


class _Meshes:
    """Object models loaded on first use; each mesh is logged once (static, model frame, mm)
    under ``world/gt`` and ``world/est``, and frames then only move its instances."""

    def __init__(self, rr: Any, rec: Any, dataset: BopDataset) -> None:
        self.rr, self.rec, self.dataset = rr, rec, dataset
        self.models: dict[int, Any] = {}
        self.closed: dict[int, bool] = {}

    def __call__(self, obj_id: int) -> Any:
        if obj_id not in self.models:
            mdl = self.models[obj_id] = self.dataset.model(obj_id)
            self.closed[obj_id] = is_closed(mdl.faces)
            for kind, color in (("gt", GT_COLOR), ("est", EST_COLOR)):
                self.rec.log(
                    f"world/{kind}/obj_{obj_id:06d}",
                    self.rr.Mesh3D(
                        vertex_positions=mdl.pts,
                        triangle_indices=mdl.faces,
                        albedo_factor=[*color, 255],
                    ),
                    static=True,
                )
        return self.models[obj_id]

    def silhouette(
        self, obj_id: int, K: np.ndarray, R: np.ndarray, t: np.ndarray, shape: tuple[int, int]
    ) -> np.ndarray:
        """(H, W) bool: the model's projected triangles at pose (R, t mm) under K."""
        mdl = self(obj_id)
        return project_silhouette(mdl.pts, mdl.faces, K, R, t, shape, closed=self.closed[obj_id])


Poses = dict[int, list[tuple[np.ndarray, np.ndarray]]]


def _log_camera(rr: Any, rec: Any, dataset: BopDataset, s: int, im: int) -> tuple[int, int]:
    """The pinhole and the JPEG-encoded image of one frame; returns the image's (h, w) px."""
    scene = dataset.scene(s)
    try:
        rgb = load_rgb(scene.rgb_path(im))
    except (OSError, BopsurgError):
        rgb = None
    if rgb is not None:
        h, w = rgb.shape[:2]
    else:
        w, h = dataset.image_size(s)
    rec.log(
        "world/camera",
        rr.Pinhole(
            image_from_camera=scene.camera[im].K,
            resolution=[w, h],
            camera_xyz=rr.ViewCoordinates.RDF,
        ),
    )
    if rgb is not None:
        ok, jpg = cv2.imencode(
            ".jpg",
            cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR),
            [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY],
        )
        if ok:
            rec.log(
                "world/camera/rgb",
                rr.EncodedImage(contents=jpg.tobytes(), media_type="image/jpeg"),
            )
    return h, w


def _gt_silhouette(
    dataset: BopDataset, meshes: _Meshes, s: int, im: int, shape: tuple[int, int], poses: Poses
) -> np.ndarray:
    """Union of the frame's ``mask_visib`` masks (the projected model where one is missing);
    appends each GT pose in front of the camera to ``poses``."""
    scene = dataset.scene(s)
    K = scene.camera[im].K
    mask = np.zeros(shape, np.uint8)
    for gt_id, g in enumerate(scene.gt.get(im, [])):
        if g.t[2] <= 0:
            continue
        poses.setdefault(g.obj_id, []).append((g.R, g.t))
        mpath = scene.mask_visib_path(im, gt_id)
        if mpath.is_file():
            m = load_mask(mpath)
            if m.shape == mask.shape:
                mask[m] = 1
                continue
        mask |= meshes.silhouette(g.obj_id, K, g.R, g.t, shape)
    return mask


def _log_boxes(rr: Any, rec: Any, det: Detections) -> None:
    labels = [f"obj {o} {sc:.2f}" for o, sc in zip(det.obj_id, det.score, strict=True)]
    rec.log(
        "world/camera/boxes",
        rr.Boxes2D(
            array=det.bbox,
            array_format=rr.Box2DFormat.XYWH,
            labels=labels,
            colors=[BOX_COLOR] * len(det),
            draw_order=3.0,
        ),
    )


def _log_instances(rr: Any, rec: Any, meshes: _Meshes, kind: str, poses: Poses) -> None:
    """Move the instances of each object's mesh under ``world/{kind}`` to this frame's poses."""
    for o, p in poses.items():
        meshes(o)
        entity = f"world/{kind}/obj_{o:06d}"
        if p:
            pose = rr.InstancePoses3D(
                translations=np.array([pt for _, pt in p], float),
                mat3x3=np.array([pR for pR, _ in p], float),
            )
        else:  # no instance in this frame: one instance scaled to nothing
            pose = rr.InstancePoses3D(translations=[[0.0, 0.0, 0.0]], scales=[[0.0] * 3])
        rec.log(entity, pose)


def _log_images(
    rr: Any,
    rec: Any,
    dataset: BopDataset,
    est: PoseEstimates,
    frames: pd.DataFrame,
    detections: Mapping[tuple[int, int], Detections],
) -> None:
    obj_ids = sorted({int(o) for o in est.obj_id} | set(dataset.obj_ids))
    est_key = pd.DataFrame({"scene_id": est.scene_id, "im_id": est.im_id})
    est_groups = est_key.groupby(["scene_id", "im_id"]).indices
    meshes = _Meshes(rr, rec, dataset)
    for r in frames.itertuples(index=False):
        s, im = int(r.scene_id), int(r.im_id)
        rec.set_time("frame", sequence=int(r.frame))
        shape = _log_camera(rr, rec, dataset, s, im)
        K = dataset.scene(s).camera[im].K
        gt_poses: Poses = {o: [] for o in obj_ids}
        est_poses: Poses = {o: [] for o in obj_ids}
        gt_mask = _gt_silhouette(dataset, meshes, s, im, shape, gt_poses)
        est_mask = np.zeros(shape, np.uint8)
        for e in est_groups.get((s, im), []):
            o = int(est.obj_id[e])
            est_poses.setdefault(o, []).append((est.R[e], est.t[e]))
            est_mask |= meshes.silhouette(o, K, est.R[e], est.t[e], shape)
        for name, mask, order in (("gt", gt_mask, 1.0), ("est", est_mask, 2.0)):
            rec.log(
                f"world/camera/{name}_silhouette",
                rr.SegmentationImage(mask, opacity=0.45, draw_order=order),
            )
        if detections:
            _log_boxes(rr, rec, detections.get((s, im), Detections.empty()))
        _log_instances(rr, rec, meshes, "gt", gt_poses)
        _log_instances(rr, rec, meshes, "est", est_poses)

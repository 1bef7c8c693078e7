"""BOP19 6D-localization scores: recall per threshold and average recall (AR).

Reproduces ``scripts/eval_bop19_pose.py`` → ``eval_calc_errors.py`` → ``eval_calc_scores.py``
of the reference toolkit (``visib_gt_min = -1``, ``n_top = -1``, targets from
``test_targets_bop19.json``):

- only (scene, image, object) triples listed as targets are evaluated; per triple the
  ``inst_count`` best-scored estimates are kept (stable score order);
- per image, the ``inst_count`` most visible GT instances of each target object are valid;
- errors are normalised before thresholding: MSSD by the object diameter, MSPD by
  ``640 / image width``; MSSD is +inf where ``‖t_est − t_gt‖ ≥ diameter`` (the reference's
  sphere pre-check), VSD is 1 where the bounding-sphere projections do not overlap;
- greedy matching (:mod:`bopsurg.evaluation.matching`) with strict thresholds, redone per
  threshold; recall = matched valid GTs / valid GTs, micro-averaged over the dataset;
- AR_MSSD, AR_MSPD = mean of 10 recalls; AR_VSD = mean of 10 τ × 10 θ recalls;
  AR = (AR_VSD + AR_MSSD + AR_MSPD) / 3 when VSD is available.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import cast

import numpy as np
import pandas as pd
from numpy.typing import NDArray
from tqdm import tqdm

from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.images import image_size, load_depth_window
from bopsurg.bop.meshes import ObjectModel
from bopsurg.bop.results import PoseEstimates
from bopsurg.bop.targets import Target
from bopsurg.errors import DatasetError
from bopsurg.evaluation.matching import greedy_match, valid_gts_localization
from bopsurg.evaluation.pair_errors import ModelCache, candidate_pairs, pair_errors
from bopsurg.evaluation.tables import GtTable, estimates_frame, rank_within_groups
from bopsurg.metrics.vsd import vsd_in_window
from bopsurg.plugins import DepthRenderer

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: Correctness thresholds exactly as the reference builds them (floats included).
MSSD_THRESHOLDS: tuple[float, ...] = tuple(float(x) for x in np.arange(0.05, 0.51, 0.05))
MSPD_THRESHOLDS: tuple[float, ...] = tuple(float(x) for x in np.arange(5, 51, 5))
VSD_THRESHOLDS: tuple[float, ...] = MSSD_THRESHOLDS
VSD_TAUS: tuple[float, ...] = tuple(float(x) for x in np.arange(0.05, 0.51, 0.05))
VSD_DELTA_MM = 15.0


@dataclass(frozen=True)
class PairTable:
    """Candidate (estimate, GT) pairs of the kept estimates, ordered by estimate then gt_id.

    Attributes:
        est_rank: (P,) score rank of the estimate within its (scene, image, object) target.
        est_index: (P,) row of the estimate in the results.
        gt_index: (P,) row of the GT in the :class:`~bopsurg.evaluation.tables.GtTable`.
    """

    est_rank: NDArray[np.int64]
    est_index: NDArray[np.int64]
    gt_index: NDArray[np.int64]


@dataclass
class RecallCurve:
    """Recall at each threshold of one error type, and its mean (the AR)."""

    error_type: str
    thresholds: list[float]
    recalls: list[float]
    tp_counts: list[int]
    targets_count: int
    taus: list[float] | None = None
    extra: dict[str, object] = field(default_factory=dict)
    #: Per image with valid GTs, what the bootstrap intervals resample: (M, 2) scene_id,
    #: im_id; (M,) valid GTs; (T, M) matched valid GTs at each threshold (recall order).
    image_ids: NDArray[np.int64] | None = None
    image_targets: NDArray[np.int64] | None = None
    image_hits: NDArray[np.int64] | None = None

    @property
    def average_recall(self) -> float:
        """Mean of the recalls (0 when there are no thresholds)."""
        return float(np.mean(self.recalls)) if self.recalls else 0.0


def recall_curve(
    pairs: PairTable,
    errors: F64,
    valid_gt: NDArray[np.bool_],
    thresholds: tuple[float, ...],
    error_type: str,
    gt_images: NDArray[np.int64] | None = None,
) -> RecallCurve:
    """Recall at each threshold for normalised pair errors.

    Args:
        pairs: The candidate pairs.
        errors: (P,) normalised errors of the pairs, or (T, P) for VSD (one row per τ, the
            recall list is then τ-major, θ-minor like the reference's folders).
        valid_gt: (G,) valid GT instances.
        thresholds: Correctness thresholds θ.
        error_type: Name, e.g. ``"mssd"``.
        gt_images: (G, 2) scene_id, im_id of each GT: also count hits per image (for the
            bootstrap intervals of the AR).
    """
    errs = np.atleast_2d(np.asarray(errors, dtype=np.float64))
    targets = int(np.count_nonzero(valid_gt))
    recalls: list[float] = []
    tps: list[int] = []
    hit_rows: list[NDArray[np.bool_]] = []
    for row in errs:
        for th in thresholds:
            matched = greedy_match(
                pairs.est_rank, pairs.est_index, pairs.gt_index, row, th, valid_gt
            )
            tp = int(np.count_nonzero(matched[valid_gt] >= 0))
            tps.append(tp)
            recalls.append(tp / float(targets) if targets > 0 else 0.0)
            hit_rows.append(matched[valid_gt] >= 0)
    curve = RecallCurve(error_type, list(thresholds), recalls, tps, targets)
    if gt_images is not None:
        ids, inv = np.unique(gt_images[valid_gt], axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        curve.image_ids = ids.astype(np.int64).reshape(-1, 2)
        curve.image_targets = np.bincount(inv, minlength=len(ids)).astype(np.int64)
        curve.image_hits = np.array(
            [np.bincount(inv, weights=h, minlength=len(ids)) for h in hit_rows], dtype=np.int64
        ).reshape(len(hit_rows), len(ids))
    return curve


def merge_image_counts(merged: RecallCurve, parts: Sequence[RecallCurve]) -> None:
    """Give ``merged`` the per-image counts of ``parts`` (curves of disjoint scenes), in image
    order, so that the bootstrap draws the same replicates however the scenes were split."""
    if not parts or any(p.image_ids is None for p in parts):
        return
    ids = np.concatenate([p.image_ids for p in parts if p.image_ids is not None])
    order = np.lexsort((ids[:, 1], ids[:, 0]))
    merged.image_ids = ids[order]
    merged.image_targets = np.concatenate(
        [p.image_targets for p in parts if p.image_targets is not None]
    )[order]
    merged.image_hits = np.concatenate(
        [p.image_hits for p in parts if p.image_hits is not None], axis=1
    )[:, order]


def normalise_mssd(mssd: F64, te: F64, diameter: F64) -> F64:
    """MSSD / diameter with the reference's +inf where ``‖t_est − t_gt‖ ≥ diameter``."""
    out = mssd / diameter
    return np.where(te < diameter, out, np.inf)


def normalise_mspd(mspd: F64, im_width: NDArray[np.int64]) -> F64:
    """MSPD scaled to a 640 px wide image, as the reference (``640 / W × e``)."""
    factor = 640.0 / im_width.astype(np.float64)
    return factor * mspd


def sphere_projections_overlap(t_est: F64, t_gt: F64, radius: F64) -> NDArray[np.bool_]:
    """The reference's approximate overlap test of the bounding-sphere projections (VSD).

    Args:
        t_est, t_gt: (P, 3) translations, mm.
        radius: (P,) sphere radius (diameter / 2), mm.
    """
    ze, zg = t_est[:, 2], t_gt[:, 2]
    nonzero = (ze != 0) & (zg != 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        pe = t_est[:, :2] / ze[:, None]
        pg = t_gt[:, :2] / zg[:, None]
        dist = np.linalg.norm(pe - pg, axis=1)
        thresh = radius * (1.0 / ze + 1.0 / zg)
    result: NDArray[np.bool_] = nonzero & (dist < thresh)
    return result


@dataclass(frozen=True)
class VsdInputs:
    """What VSD needs besides the poses.

    Attributes:
        dataset: The dataset (depth images, cameras, models).
        renderer: Renders model depth at a pose.
        delta: Visibility tolerance δ, mm.
        progress: Show a progress bar over images.
    """

    dataset: BopDataset
    renderer: DepthRenderer
    delta: float = VSD_DELTA_MM
    progress: bool = False


def _target_frame(targets: Sequence[Target]) -> pd.DataFrame:
    """Targets as columns, one row per (scene, image, object); the last entry wins."""
    return pd.DataFrame(
        {
            "scene_id": [t.scene_id for t in targets],
            "im_id": [t.im_id for t in targets],
            "obj_id": [t.obj_id for t in targets],
            "inst_count": [t.inst_count for t in targets],
        },
        dtype=np.int64,
    ).drop_duplicates(["scene_id", "im_id", "obj_id"], keep="last")


def valid_gts(gt: GtTable, targets: pd.DataFrame) -> NDArray[np.bool_]:
    """(G,) the valid GT instances: in target images, of target objects, the ``inst_count``
    most visible per (scene, image, object)."""
    gdf = gt.frame().merge(targets, on=["scene_id", "im_id", "obj_id"], how="left")
    gdf = gdf.sort_values("g").reset_index(drop=True)
    inst = gdf["inst_count"].fillna(0).to_numpy(dtype=np.int64)
    grp = gdf.groupby(["scene_id", "im_id", "obj_id"], sort=False).ngroup().to_numpy()
    return valid_gts_localization(grp, gt.visib_fract, inst)


def kept_pairs(est: PoseEstimates, gt: GtTable, targets: pd.DataFrame) -> PairTable:
    """Candidate pairs of the kept estimates: targets only, the ``inst_count`` best-scored per
    (scene, image, object)."""
    est_df = estimates_frame(est).merge(targets, on=["scene_id", "im_id", "obj_id"], how="inner")
    est_df = est_df.sort_values("e").reset_index(drop=True)
    rank, _ = rank_within_groups(
        est_df[["scene_id", "im_id", "obj_id"]], est_df["score"].to_numpy()
    )
    est_df["rank"] = rank
    est_df = est_df[est_df["rank"] < est_df["inst_count"]]
    pairs_df = candidate_pairs(est_df.drop(columns="inst_count"), gt)
    return PairTable(
        est_rank=pairs_df["rank"].to_numpy(np.int64),
        est_index=pairs_df["e"].to_numpy(np.int64),
        gt_index=pairs_df["g"].to_numpy(np.int64),
    )


def recall_curves(
    est: PoseEstimates,
    gt: GtTable,
    targets: Sequence[Target],
    models: ModelCache,
    *,
    pair_mssd: pd.DataFrame,
    vsd_inputs: VsdInputs | None = None,
) -> dict[str, RecallCurve]:
    """BOP19 recall curves (MSSD, MSPD, and VSD with ``vsd_inputs``) under the reference's rules.

    Args:
        est: The estimates.
        gt: The GT table.
        targets: The BOP19 targets.
        models: Model points, symmetries and diameters.
        pair_mssd: MSSD (mm) of candidate pairs already computed (columns ``e``, ``g``,
            ``mssd``); every kept pair must be among them.
        vsd_inputs: Depth renderer and dataset for VSD; None: no VSD curve.
    """
    tdf = _target_frame(targets)
    valid = valid_gts(gt, tdf)
    pairs = kept_pairs(est, gt, tdf)
    e_idx, g_idx = pairs.est_index, pairs.gt_index
    errs = pair_errors(est, gt, e_idx, g_idx, models, ("te", "mspd"))
    known = pd.Series(
        pair_mssd["mssd"].to_numpy(), index=pd.MultiIndex.from_frame(pair_mssd[["e", "g"]])
    )
    errs["mssd"] = known.reindex(pd.MultiIndex.from_arrays([e_idx, g_idx])).to_numpy()
    diam = models.diameters(gt.obj_id[g_idx])
    ims = np.stack([gt.scene_id, gt.im_id], axis=1).astype(np.int64)
    mssd = normalise_mssd(errs["mssd"], errs["te"], diam)
    mspd = normalise_mspd(errs["mspd"], gt.im_width[g_idx])
    curves = {
        "mssd": recall_curve(pairs, mssd, valid, MSSD_THRESHOLDS, "mssd", ims),
        "mspd": recall_curve(pairs, mspd, valid, MSPD_THRESHOLDS, "mspd", ims),
    }
    if vsd_inputs is not None:
        errors = vsd_errors(est, gt, e_idx, g_idx, diam, vsd_inputs)
        curve = recall_curve(pairs, errors, valid, VSD_THRESHOLDS, "vsd", ims)
        curve.taus = list(VSD_TAUS)
        curve.extra["delta_mm"] = vsd_inputs.delta
        curves["vsd"] = curve
    return curves


#: A model's depth in a window of the image (mm) and the window's top-left (row, column);
#: None when the model is not seen.
WindowDepth = tuple[F64, tuple[int, int]] | None
WindowRenderer = Callable[[ObjectModel, F64, F64, F64, int, int], WindowDepth]


def window_renderer(renderer: DepthRenderer) -> WindowRenderer:
    """The renderer's ``render_depth_window`` when it has one, else its whole-image
    ``render_depth`` cut to the bounding box of the model's pixels."""
    windowed = getattr(renderer, "render_depth_window", None)
    if callable(windowed):
        return cast(WindowRenderer, windowed)

    def render(model: ObjectModel, R: F64, t: F64, K: F64, width: int, height: int) -> WindowDepth:
        depth = np.asarray(renderer.render_depth(model, R, t, K, width, height))
        rows = np.flatnonzero((depth > 0).any(axis=1))
        if rows.size == 0:
            return None
        cols = np.flatnonzero((depth > 0).any(axis=0))
        r0, r1, c0, c1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
        return depth[r0:r1, c0:c1], (r0, c0)

    return render


def _span(windows: Sequence[WindowDepth]) -> tuple[int, int, int, int] | None:
    """(row0, row1, col0, col1), ends exclusive, of the box around the windows; None if none."""
    seen = [w for w in windows if w is not None]
    if not seen:
        return None
    r0 = min(o[0] for _, o in seen)
    c0 = min(o[1] for _, o in seen)
    r1 = max(o[0] + d.shape[0] for d, o in seen)
    c1 = max(o[1] + d.shape[1] for d, o in seen)
    return r0, r1, c0, c1


def _pasted(win: WindowDepth, box: tuple[int, int, int, int]) -> F64:
    """A model's window depth on the box (0 outside the window)."""
    r0, r1, c0, c1 = box
    out = np.zeros((r1 - r0, c1 - c0))
    if win is not None:
        depth, (wr, wc) = win
        out[wr - r0 : wr - r0 + depth.shape[0], wc - c0 : wc - c0 + depth.shape[1]] = depth
    return out


def vsd_errors(
    est: PoseEstimates, gt: GtTable, e_idx: I64, g_idx: I64, diameter: F64, inputs: VsdInputs
) -> F64:
    """VSD errors (τ × P) of the pairs, 1 where the sphere projections do not overlap.

    Pairs are rendered image by image, each GT pose once, each model only in the window it
    covers; of the image's depth only the box around those windows is decoded, in a second
    thread while the next image renders (decoding releases the GIL).

    Raises:
        DatasetError: An image without ``depth_scale``.
    """
    taus = np.asarray(VSD_TAUS)
    out = np.ones((taus.size, e_idx.shape[0]))
    overlap = sphere_projections_overlap(est.t[e_idx], gt.t[g_idx], 0.5 * diameter)
    todo = np.flatnonzero(overlap)
    scene_of, im_of = gt.scene_id[g_idx[todo]], gt.im_id[g_idx[todo]]
    order = np.lexsort((im_of, scene_of))  # pairs grouped by image, images in order
    starts = np.flatnonzero(np.r_[True, np.diff(scene_of[order]) != 0]
                            | np.r_[True, np.diff(im_of[order]) != 0])  # fmt: skip
    render = window_renderer(inputs.renderer)
    groups = np.split(todo[order], starts[1:])
    pairs = _Pairs(est, gt, e_idx, g_idx)
    with ThreadPoolExecutor(max_workers=1) as decoder:
        previous: _ImageRenders | None = None
        # no bar object without a bar: tqdm's lock would import multiprocessing
        bar = tqdm(groups, desc="VSD", unit="img") if inputs.progress else groups
        for group in bar:
            current = _render_image(group, pairs, inputs, render, decoder)
            if previous is not None:
                _score_image(out, previous, pairs, diameter, inputs.delta)
            previous = current
        if previous is not None:
            _score_image(out, previous, pairs, diameter, inputs.delta)
    return out


@dataclass(frozen=True)
class _Pairs:
    """The poses of the pairs: estimate ``e_idx[p]`` with GT ``g_idx[p]``."""

    est: PoseEstimates
    gt: GtTable
    e_idx: I64
    g_idx: I64


@dataclass(frozen=True)
class _ImageRenders:
    """One image's rendered pairs and its depth box, being decoded (None: nothing rendered)."""

    group: I64
    K: F64
    est_win: list[WindowDepth]
    gt_win: dict[int, WindowDepth]
    span: tuple[int, int, int, int] | None
    depth: Future[NDArray[np.float32]] | None
    depth_scale: float


def _render_image(
    group: I64,
    pairs: _Pairs,
    inputs: VsdInputs,
    render: WindowRenderer,
    decoder: ThreadPoolExecutor,
) -> _ImageRenders:
    """Render the pairs ``group`` (all in one image) and start decoding its depth box."""
    dataset, est, gt = inputs.dataset, pairs.est, pairs.gt
    first = int(pairs.g_idx[group[0]])
    scene_id, im_id = int(gt.scene_id[first]), int(gt.im_id[first])
    scene = dataset.scene(scene_id)
    cam = scene.camera[im_id]
    if cam.depth_scale is None:
        raise DatasetError(
            "depth_scale is missing (needed for VSD)",
            path=scene.scene_dir / "scene_camera.json",
            field=f"{im_id}/depth_scale",
        )
    depth_path = scene.depth_path(im_id)
    w, h = image_size(depth_path)
    gt_win: dict[int, WindowDepth] = {}
    est_win: list[WindowDepth] = []
    for p in group.tolist():  # one render per pose: the renderer's unit of work
        g, e = int(pairs.g_idx[p]), int(pairs.e_idx[p])
        model = dataset.model(int(gt.obj_id[g]))
        if g not in gt_win:
            gt_win[g] = render(model, gt.R[g], gt.t[g], cam.K, w, h)
        est_win.append(render(model, est.R[e], est.t[e], cam.K, w, h))
    span = _span([*gt_win.values(), *est_win])
    depth = None
    if span is not None:
        depth = decoder.submit(load_depth_window, depth_path, span[:2], span[2:])
    return _ImageRenders(group, cam.K, est_win, gt_win, span, depth, cam.depth_scale)


def _score_image(
    out: F64, image: _ImageRenders, pairs: _Pairs, diameter: F64, delta: float
) -> None:
    """VSD of one image's rendered pairs into their columns of ``out``."""
    if image.span is None or image.depth is None:  # no model pixel: every error stays 1
        return
    r0, _, c0, _ = image.span
    depth = image.depth.result() * image.depth_scale
    taus = np.asarray(VSD_TAUS)
    for p, e_w in zip(image.group.tolist(), image.est_win, strict=True):
        g_w = image.gt_win[int(pairs.g_idx[p])]
        box = _span([e_w, g_w])
        if box is None:
            continue
        test = depth[box[0] - r0 : box[1] - r0, box[2] - c0 : box[3] - c0]
        out[:, p] = vsd_in_window(test, _pasted(e_w, box), _pasted(g_w, box), image.K,
                                  (box[0], box[2]), delta, taus,
                                  diameter=float(diameter[p]))  # fmt: skip

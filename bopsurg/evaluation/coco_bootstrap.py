"""Bootstrap confidence intervals of the COCO 2D scores, and paired comparisons.

pycocotools' ``COCOeval.evaluate`` matches each image on its own (per category, area range
and IoU threshold); ``accumulate`` then ranks the detections of all images and interpolates
precision at 101 recall points. The matching does not depend on which other images are in
the test set, so a resampled test set is the same matches under image weights: the ranked
TP flags of every (category, area range, IoU threshold) are kept once
(:class:`CocoSamples`, from ``COCOeval.evalImgs``), and each replicate re-weights them with
:func:`bopsurg.evaluation.bootstrap.weighted_ap`, as the BOP24 scores are.

- AP: per (category, IoU threshold), ignored detections (``dtIgnore``: matched to a crowd /
  out-of-area GT, or out-of-area and unmatched) dropped, target count = the weighted number of
  non-ignored GTs; the mean over categories with targets and thresholds, as ``summarize``;
- AR: the recall after the last detection (``maxDets`` per image) likewise.

With unit weights the scores are ``COCOeval.stats`` (to rounding: pycocotools adds
``np.spacing(1)`` to its precision denominator). A resampled set equals pycocotools run on
the set with every image copied as often as drawn, as long as no two different detections
tie in score (copies of one detection are then adjacent in the ranking).
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from bopsurg.atomic import atomic_path
from bopsurg.errors import BopsurgError, InputError
from bopsurg.evaluation.bootstrap import (
    _BLOCK,
    F64,
    I64,
    Comparison,
    paired_comparisons,
    percentile_interval,
    resample_weights,
    resampling_units,
    weighted_ap,
)
from bopsurg.evaluation.options import DEFAULT_REPLICATES

#: File in an evaluation folder holding the COCO samples (``bopsurg compare``).
COCO_SAMPLES_FILENAME = "bootstrap_coco.npz"
#: Area ranges of ``COCOeval.params`` in order (all, small, medium, large).
AREAS = ("all", "small", "medium", "large")
#: ``COCOeval.params.maxDets``.
MAX_DETS = (1, 10, 100)
#: (area index, max detections) of the kept rankings: every area at 100 detections (AP,
#: AR_small/medium/large, AR100), all areas at 1 and 10 (AR1, AR10).
RUNS = ((0, 100), (1, 100), (2, 100), (3, 100), (0, 1), (0, 10))


@dataclass
class CocoSamples:
    """The ranked per-image matches the COCO scores of one evaluation are computed from.

    Attributes:
        images: (I, 2) ``(scene_id, im_id)`` of the evaluated images, in COCO image-id order.
        iou_thresholds: (T,) IoU thresholds of the matching.
        run_prefix, run_cat, run_area, run_maxdet: (R,) of each kept ranking: the index of its
            key prefix in ``prefixes``, its category id, area index (:data:`AREAS`) and
            detections per image.
        prefixes: Key prefixes (``bbox``, ``bbox_modal``, ``segm``).
        gt_counts: (R, I) non-ignored GTs per image of each ranking.
        est_image: Concatenated ranked detections of every ranking: image index of each.
        est_tp: (T, N) matched to a GT at each threshold.
        est_ignored: (T, N) ignored at each threshold.
        offsets: (R + 1,) start of each ranking in the concatenation, plus the end.
    """

    images: I64
    iou_thresholds: F64
    prefixes: list[str]
    run_prefix: I64
    run_cat: I64
    run_area: I64
    run_maxdet: I64
    gt_counts: I64
    est_image: I64
    est_tp: NDArray[np.bool_]
    est_ignored: NDArray[np.bool_]
    offsets: I64

    @classmethod
    def from_cocoevals(
        cls, evals: Sequence[tuple[str, Any]], images: Sequence[tuple[int, int]]
    ) -> CocoSamples:
        """Collect the samples of evaluated ``COCOeval`` objects (``evaluate()`` has run).

        Args:
            evals: ``(key prefix, COCOeval)`` pairs, all on the same images.
            images: ``(scene_id, im_id)`` of each COCO image id in ``params.imgIds`` order.
        """
        n_img = len(images)
        runs: list[tuple[int, int, int, int]] = []
        counts: list[I64] = []
        est_img: list[I64] = []
        est_tp: list[NDArray[np.bool_]] = []
        est_ig: list[NDArray[np.bool_]] = []
        thresholds = np.zeros(0)
        for p, (_, ev) in enumerate(evals):
            params = ev.params
            thresholds = np.asarray(params.iouThrs, dtype=np.float64)
            n_t = len(thresholds)
            area_names = list(getattr(params, "areaRngLbl", AREAS))
            if tuple(area_names) != AREAS or tuple(params.maxDets) != MAX_DETS:
                raise BopsurgError("COCO bootstrap: unexpected COCOeval area ranges or maxDets")
            n_area = len(area_names)
            for k, cat in enumerate(params.catIds):
                for a, max_det in RUNS:
                    base = (k * n_area + a) * n_img
                    gt = np.zeros(n_img, dtype=np.int64)
                    scores, imgs, tps, igs = [], [], [], []
                    for i in range(n_img):
                        e = ev.evalImgs[base + i]
                        if e is None:
                            continue
                        gt[i] = int(np.count_nonzero(np.asarray(e["gtIgnore"]) == 0))
                        s = np.asarray(e["dtScores"][:max_det], dtype=np.float64)
                        scores.append(s)
                        imgs.append(np.full(s.size, i, dtype=np.int64))
                        tps.append(np.asarray(e["dtMatches"])[:, :max_det].reshape(n_t, -1) > 0)
                        igs.append(np.asarray(e["dtIgnore"])[:, :max_det].reshape(n_t, -1) > 0)
                    s_all = np.concatenate([np.zeros(0), *scores])
                    order = np.argsort(-s_all, kind="mergesort")  # accumulate()'s ranking
                    est_img.append(np.concatenate([np.zeros(0, np.int64), *imgs])[order])
                    empty = np.zeros((n_t, 0), dtype=bool)
                    est_tp.append(np.concatenate([empty, *tps], axis=1)[:, order])
                    est_ig.append(np.concatenate([empty, *igs], axis=1)[:, order])
                    runs.append((p, int(cat), a, max_det))
                    counts.append(gt)
        run = np.array(runs, dtype=np.int64).reshape(-1, 4)
        n_t = len(thresholds)
        return cls(
            images=np.asarray(images, dtype=np.int64).reshape(-1, 2),
            iou_thresholds=thresholds,
            prefixes=[prefix for prefix, _ in evals],
            run_prefix=run[:, 0],
            run_cat=run[:, 1],
            run_area=run[:, 2],
            run_maxdet=run[:, 3],
            gt_counts=np.array(counts, dtype=np.int64).reshape(len(runs), n_img),
            est_image=np.concatenate([np.zeros(0, np.int64), *est_img]),
            est_tp=np.concatenate([np.zeros((n_t, 0), bool), *est_tp], axis=1),
            est_ignored=np.concatenate([np.zeros((n_t, 0), bool), *est_ig], axis=1),
            offsets=np.r_[0, np.cumsum([len(x) for x in est_img])].astype(np.int64),
        )

    def save(self, path: str | Path) -> None:
        """Write the samples (npz, atomically)."""
        fields = {k: v for k, v in vars(self).items() if k != "prefixes"}
        with atomic_path(path) as tmp, open(tmp, "wb") as f:
            np.savez_compressed(f, prefixes=np.array(self.prefixes, dtype=str), **fields)

    @classmethod
    def load(cls, path: str | Path) -> CocoSamples:
        """Read samples written by :meth:`save`.

        Raises:
            InputError: Missing or unreadable file.
        """
        try:
            with np.load(path, allow_pickle=False) as z:
                fields = {k: z[k] for k in z.files}
            fields["prefixes"] = [str(p) for p in fields["prefixes"]]
            fields["images"] = fields["images"].reshape(-1, 2)
            return cls(**fields)
        except FileNotFoundError:
            raise InputError(f"{path}: missing (evaluate a COCO results JSON)") from None
        except (OSError, KeyError, ValueError, TypeError) as exc:
            raise InputError(
                f"{path}: not COCO bootstrap samples of bopsurg eval ({exc})"
            ) from None


def replicate_scores(samples: CocoSamples, weights: F64) -> dict[str, F64]:
    """The ``bop22_coco_<prefix>_<stat>`` scores under each row of image weights, (B,) each
    (NaN where COCO reports -1: no category with targets)."""
    b = weights.shape[0]
    n_t = len(samples.iou_thresholds)
    total = weights @ samples.gt_counts.T.astype(np.float64)  # (B, R)
    ap = np.full((len(samples.run_prefix), b, n_t), np.nan)
    rec = np.full((len(samples.run_prefix), b, n_t), np.nan)
    # Bootstrap counts are small integers: float32 holds them (and their sums below 2**24)
    # exactly and halves the memory traffic of the gathers; other weights stay float64.
    compact = weights.astype(np.float32)
    if np.array_equal(compact, weights) and weights.sum(axis=1).max(initial=0) < 2**24:
        weights = compact  # type: ignore[assignment]
    for r in range(len(samples.run_prefix)):
        if not samples.gt_counts[r].any():
            continue  # no targets in any replicate (e.g. no large object): NaN, as -1 in COCO
        lo, hi = samples.offsets[r], samples.offsets[r + 1]
        img = samples.est_image[lo:hi]
        need_ap = samples.run_maxdet[r] == MAX_DETS[-1]
        done: dict[bytes, int] = {}  # thresholds with the same matches share their scores
        for t in range(n_t):
            keep = ~samples.est_ignored[t, lo:hi]
            tp = samples.est_tp[t, lo:hi][keep]
            same = done.setdefault(np.packbits(np.r_[keep, tp]).tobytes(), t)
            if same != t:
                ap[r, :, t], rec[r, :, t] = ap[r, :, same], rec[r, :, same]
                continue
            step = max(1, _BLOCK // max(int(keep.sum()), 1))
            for s in range(0, b, step):  # replicate batches bound the memory
                w = weights[s : s + step][:, img[keep]]
                tot = total[s : s + step, r]
                with np.errstate(invalid="ignore", divide="ignore"):
                    found = (w @ tp.astype(w.dtype)).astype(np.float64)
                    rec[r, s : s + step, t] = np.where(tot > 0, found / tot, np.nan)
                if need_ap:
                    ap[r, s : s + step, t] = weighted_ap(w, tp, tot)
    out: dict[str, F64] = {}
    iou = samples.iou_thresholds
    t50, t75 = np.flatnonzero(iou == 0.5), np.flatnonzero(iou == 0.75)
    for p, prefix in enumerate(samples.prefixes):

        def pick(area: int, max_det: int, values: F64, p: int = p) -> F64:
            sel = (
                (samples.run_prefix == p)
                & (samples.run_area == area)
                & (samples.run_maxdet == max_det)
            )
            picked: F64 = values[sel]  # (K, B, T)
            return picked

        stats = {
            "AP": pick(0, 100, ap),
            "AP50": pick(0, 100, ap)[:, :, t50],
            "AP75": pick(0, 100, ap)[:, :, t75],
            "AP_small": pick(1, 100, ap),
            "AP_medium": pick(2, 100, ap),
            "AP_large": pick(3, 100, ap),
            "AR1": pick(0, 1, rec),
            "AR10": pick(0, 10, rec),
            "AR100": pick(0, 100, rec),
            "AR_small": pick(1, 100, rec),
            "AR_medium": pick(2, 100, rec),
            "AR_large": pick(3, 100, rec),
        }
        with warnings.catch_warnings():  # a replicate without targets: NaN, no warning
            warnings.simplefilter("ignore", RuntimeWarning)
            for name, v in stats.items():
                mean = np.nanmean(v.transpose(1, 0, 2).reshape(b, -1), axis=1) if v.size else None
                out[f"bop22_coco_{prefix}_{name}"] = (
                    mean if mean is not None else np.full(b, np.nan)
                )
    return out


def confidence_intervals(
    samples: CocoSamples, replicates: int, seed: int = 0, unit: str = "image"
) -> dict[str, tuple[float, float]]:
    """95 % bootstrap interval of each COCO score (resampling images or scenes)."""
    weights = resample_weights(resampling_units(samples.images, unit), replicates, seed)
    return {k: percentile_interval(v) for k, v in replicate_scores(samples, weights).items()}


def compare_coco(
    a: CocoSamples,
    b: CocoSamples,
    replicates: int = DEFAULT_REPLICATES,
    seed: int = 0,
    unit: str = "image",
) -> dict[str, Comparison]:
    """Paired bootstrap comparison of the COCO scores of two evaluations of the same images
    (the keys both have).

    Raises:
        BopsurgError: The evaluations are not on the same images.
    """
    if a.images.shape != b.images.shape or not np.array_equal(a.images, b.images):
        raise BopsurgError(
            f"the COCO evaluations are on different images ({len(a.images)} vs "
            f"{len(b.images)}): compare needs the same dataset split and targets"
        )
    ones = np.ones((1, len(a.images)))
    weights = resample_weights(resampling_units(a.images, unit), replicates, seed)
    full_a, full_b = replicate_scores(a, ones), replicate_scores(b, ones)
    rep_a, rep_b = replicate_scores(a, weights), replicate_scores(b, weights)
    common = [k for k in full_a if k in full_b]
    return paired_comparisons(
        {k: full_a[k] for k in common},
        {k: full_b[k] for k in common},
        {k: rep_a[k] for k in common},
        {k: rep_b[k] for k in common},
    )

"""Bootstrap confidence intervals of the BOP24/BOP25 detection scores, and paired comparisons.

A score is recomputed on resampled test sets: the target images (or whole scenes, with
``unit="scene"``) are drawn with replacement, each replicate is a weight per image (how
often it was drawn). Weights enter the AP computation directly, so all replicates are
evaluated at once with numpy (no Python loop over replicates or estimates):

- an estimate of an image drawn w times counts w times: the running TP and detection counts
  along the ranking become weighted cumulative sums (copies of an estimate are adjacent in
  the ranking, and the 101-point interpolated precision only sees the last of a run of TPs
  and the first of a run of FPs, so the weighted sums give exactly the resampled AP);
- an object's target count is the weighted sum of its per-image counts; an object without
  targets in a replicate is left out of that replicate's mean, as the reference does.

With every weight 1 the scores are those of :func:`bopsurg.evaluation.bop24.evaluate_bop24`
exactly. The 95 % interval is the 2.5 / 97.5 percentile of the replicates. Two methods
evaluated on the same images are compared on the *same* replicates (paired bootstrap): the
interval of the difference and a two-sided p-value ``2 · min(P(Δ* ≤ 0), P(Δ* ≥ 0))``.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from bopsurg.atomic import atomic_path
from bopsurg.errors import BopsurgError, InputError
from bopsurg.evaluation.bop19 import RecallCurve
from bopsurg.evaluation.bop24 import RECALL_POINTS, DetectionEvaluation, score_keys
from bopsurg.evaluation.options import CI_UNITS, DEFAULT_REPLICATES

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: File in an evaluation folder holding what the bootstrap needs (``bopsurg compare``).
SAMPLES_FILENAME = "bootstrap_bop24.npz"
#: Elements of one (replicates x estimates) block; bounds the memory of a replicate batch.
_BLOCK = 1 << 22
#: Elements of one (replicates x rankings x length) block of :func:`weighted_ap_runs`: small
#: blocks reuse the same memory, where large fresh arrays cost more in page faults than in
#: arithmetic.
_RUNS_BLOCK = 1 << 16


@dataclass
class DetectionSamples:
    """What the BOP24 scores are computed from, per target image.

    Attributes:
        images: (I, 2) ``(scene_id, im_id)`` of the target images.
        targets: (I, O) targets (GT with ``visib_fract ≥ 0.1``) per image and object.
        error_types: Error types, each with its thresholds.
        est_image: Concatenated ranked estimates of every (error type, object, threshold),
            in that nested order: target-image index of each.
        est_tp: Their TP flags.
        offsets: Start of each (error type, object, threshold) run in ``est_image``, plus
            the end.
        obj_ids: (O,) the object of each column of ``targets``, ascending (None in files
            written before it was stored).
    """

    images: I64
    targets: I64
    error_types: dict[str, list[float]]
    est_image: I64
    est_tp: NDArray[np.bool_]
    offsets: I64
    obj_ids: I64 | None = None

    @classmethod
    def from_evaluation(cls, det: DetectionEvaluation) -> DetectionSamples:
        """Collect the samples of an evaluation."""
        inputs = det.inputs
        objs = sorted({o for c in det.curves.values() for o in c.obj_ids})
        col = {o: k for k, o in enumerate(objs)}
        targets = np.zeros((len(inputs.images), len(objs)), dtype=np.int64)
        g = np.flatnonzero(inputs.is_target)
        obj_col = np.array([col[int(o)] for o in inputs.gt.obj_id[g]], dtype=np.int64)
        np.add.at(targets, (inputs.gt_im_pos[g], obj_col), 1)
        runs = [r for c in det.curves.values() for r in c.ranked]
        lengths = [len(img) for img, _ in runs]
        empty_i, empty_b = np.zeros(0, np.int64), np.zeros(0, bool)
        return cls(
            images=inputs.images,
            targets=targets,
            error_types={n: list(c.thresholds) for n, c in det.curves.items()},
            est_image=np.concatenate([empty_i, *(img for img, _ in runs)]),
            est_tp=np.concatenate([empty_b, *(tp for _, tp in runs)]),
            offsets=np.r_[0, np.cumsum(lengths)].astype(np.int64),
            obj_ids=np.array(objs, dtype=np.int64),
        )

    def save(self, path: str | Path) -> None:
        """Write the samples (npz, atomically)."""
        names = np.array(list(self.error_types))
        thresholds = np.array([self.error_types[n] for n in names], dtype=np.float64)
        extra: dict[str, Any] = {} if self.obj_ids is None else {"obj_ids": self.obj_ids}
        with atomic_path(path) as tmp, open(tmp, "wb") as f:
            np.savez_compressed(
                f,
                images=self.images,
                targets=self.targets,
                error_names=names,
                thresholds=thresholds,
                est_image=self.est_image,
                est_tp=self.est_tp,
                offsets=self.offsets,
                **extra,
            )

    @classmethod
    def load(cls, path: str | Path) -> DetectionSamples:
        """Read samples written by :meth:`save`.

        Raises:
            InputError: Missing or unreadable file.
        """
        try:
            with np.load(path, allow_pickle=False) as z:
                names = [str(n) for n in z["error_names"]]
                return cls(
                    images=z["images"].reshape(-1, 2),
                    targets=z["targets"],
                    error_types={n: z["thresholds"][i].tolist() for i, n in enumerate(names)},
                    est_image=z["est_image"],
                    est_tp=z["est_tp"],
                    offsets=z["offsets"],
                    obj_ids=z["obj_ids"] if "obj_ids" in z.files else None,
                )
        except FileNotFoundError:
            raise InputError(
                f"{path}: missing (evaluate with 'bopsurg eval --task bop24')"
            ) from None
        except (OSError, KeyError, ValueError) as exc:
            raise InputError(f"{path}: not bootstrap samples of bopsurg eval ({exc})") from None


def resample_weights(units: I64, replicates: int, seed: int) -> F64:
    """(replicates, I) bootstrap weights of the images.

    Args:
        units: (I,) resampling unit of each image (0 … U-1; the image itself, or its scene).
        replicates: Number of bootstrap replicates.
        seed: Seed of the generator (same seed, same replicates).
    """
    n_units = int(units.max()) + 1 if units.size else 0
    rng = np.random.default_rng(seed)
    counts = rng.multinomial(n_units, np.full(n_units, 1.0 / max(n_units, 1)), size=replicates)
    return counts[:, units].astype(np.float64)


def resampling_units(images: I64, unit: str) -> I64:
    """Unit index of each image: itself (``"image"``) or its scene (``"scene"``)."""
    if unit not in CI_UNITS:
        raise BopsurgError(f"--ci-unit: expected one of {', '.join(CI_UNITS)}, got {unit!r}")
    if unit == "image":
        return np.arange(len(images), dtype=np.int64)
    return np.unique(images[:, 0], return_inverse=True)[1].astype(np.int64).reshape(-1)


def weighted_ap(weights: F64, tp: NDArray[np.bool_], total: F64) -> F64:
    """101-point interpolated AP of one ranking under each row of weights.

    Args:
        weights: (B, N) weight of each ranked estimate in each replicate (float32 is exact
            for bootstrap counts and halves the memory traffic; sums are taken in float64).
        tp: (N,) TP flags in ranking order.
        total: (B,) weighted target count (AP is NaN where 0).

    Returns:
        (B,) APs, as :func:`bopsurg.evaluation.bop24.interpolated_ap` with unit weights.
    """
    b = weights.shape[0]
    ap = np.zeros(b)
    hits = np.flatnonzero(tp)
    if hits.size:
        # Only TP points matter: an FP point has the recall of the point before it and no
        # more precision, so it never raises an interpolated precision. Precision at a TP
        # counts every estimate up to it: sums of the weights between consecutive TPs.
        starts = np.r_[0, hits[:-1] + 1]
        segments = np.add.reduceat(weights[:, : hits[-1] + 1], starts, axis=1)
        n_cum = np.cumsum(segments, axis=1).astype(np.float64, copy=False)
        tp_cum = np.cumsum(weights[:, hits], axis=1).astype(np.float64, copy=False)
        pre = np.divide(tp_cum, n_cum, out=np.zeros_like(tp_cum), where=n_cum > 0)
        best_after = np.maximum.accumulate(pre[:, ::-1], axis=1)[:, ::-1]
        first = _first_reaching(tp_cum, total)
        k = hits.size
        interp = np.take_along_axis(best_after, np.minimum(first, k - 1), axis=1)
        ap = np.where(first < k, interp, 0.0).mean(axis=1)
    return np.where(total > 0, ap, np.nan)


def _first_reaching(tp_cum: F64, total: F64) -> I64:
    """(B, 101) index of the first point (column of ``tp_cum``) with recall
    ``tp_cum / total ≥ r`` per recall point r (the number of columns where none), exactly as
    comparing the float recalls.

    Weighted TP counts are whole numbers, so each recall point becomes the smallest count k
    with ``k / total ≥ r`` (in floats, as the recalls are computed), and all rows are searched
    at once in one sorted integer array (row b offset by b · span, span above every count).
    """
    b, n = tp_cum.shape
    safe = np.where(total > 0, total, 1.0)[:, None]
    k = np.ceil(RECALL_POINTS[None, :] * safe) - 1  # the smallest k is k, k + 1 or k + 2
    for _ in range(2):
        k = np.where(k / safe >= RECALL_POINTS[None, :], k, k + 1)
    k = np.where((k - 1) / safe >= RECALL_POINTS[None, :], k - 1, k)  # ceil rounded up
    k = np.maximum(k, 0)
    span = np.int64(max(n, int(safe.max())) + 2)
    rows = np.arange(b, dtype=np.int64)[:, None] * span
    keys = (np.minimum(tp_cum, span - 1).astype(np.int64) + rows).ravel()
    query = (np.minimum(k, span - 1).astype(np.int64) + rows).ravel()
    first = np.searchsorted(keys, query, side="left").reshape(b, -1) - rows // span * n
    out: I64 = first.astype(np.int64)
    return out


def weighted_ap_runs(weights: F64, runs: list[tuple[I64, NDArray[np.bool_]]], total: F64) -> F64:
    """:func:`weighted_ap` of several rankings at once (the same numbers, bit for bit).

    Args:
        weights: (B, I) weight of each image in each replicate.
        runs: R rankings: (image index of each ranked estimate, its TP flag).
        total: (B, R) weighted target count of each ranking's object.

    Returns:
        (B, R) APs.

    The rankings are padded to one length with an image of weight 0 and no TP; every
    position is a point whose precision counts only at a TP (elsewhere 0): a point that is
    not a TP never raises an interpolated precision (see :func:`weighted_ap`), and maxima
    are exact, so the APs equal those of the TP points alone. The first point reaching each
    recall point is counted rather than searched: the recall points at or below each
    point's recall (a search in the 101 of them), histogrammed per ranking and summed.
    """
    b, n_runs = total.shape
    length = max((len(img) for img, _ in runs), default=0)
    if n_runs == 0 or length == 0:
        return np.where(total > 0, 0.0, np.nan)
    img = np.full((n_runs, length), weights.shape[1], dtype=np.int64)  # the padding image
    tp = np.zeros((n_runs, length), dtype=bool)
    for r, (im, flags) in enumerate(runs):
        img[r, : len(im)] = im
        tp[r, : len(im)] = flags
    padded = np.concatenate([weights, np.zeros((b, 1), dtype=weights.dtype)], axis=1)
    safe = np.where(total > 0, total, 1.0)
    n_points = RECALL_POINTS.size
    ap = np.empty((b, n_runs))
    step = max(1, _RUNS_BLOCK // (n_runs * length))
    for s in range(0, b, step):  # replicate batches bound the memory
        w = padded[s : s + step][:, img]  # (b', R, L)
        n_cum = np.cumsum(w, axis=2).astype(np.float64, copy=False)
        tp_cum = np.cumsum(np.where(tp, w, 0), axis=2).astype(np.float64, copy=False)
        pre = np.divide(tp_cum, n_cum, out=np.zeros_like(tp_cum), where=(n_cum > 0) & tp)
        reversed_best = np.maximum.accumulate(pre[..., ::-1], axis=2)  # best_after, reversed
        # first[i]: the points whose recall is below recall point i (recalls are sorted)
        below = np.searchsorted(RECALL_POINTS, tp_cum / safe[s : s + step, :, None], "right")
        rows = np.arange(below.shape[0] * n_runs).reshape(-1, n_runs, 1) * (n_points + 1)
        hist = np.bincount((below + rows).ravel(), minlength=rows.size * (n_points + 1))
        first = np.cumsum(hist.reshape(-1, n_runs, n_points + 1)[..., :n_points], axis=2)
        at = length - 1 - np.minimum(first, length - 1)
        interp = np.take_along_axis(reversed_best, at, axis=2)
        ap[s : s + step] = np.where(first < length, interp, 0.0).mean(axis=2)
    return np.where(total > 0, ap, np.nan)


def replicate_scores(samples: DetectionSamples, weights: F64) -> dict[str, F64]:
    """The BOP24/BOP25 scores (reference keys) under each row of image weights: (B,) each."""
    b = weights.shape[0]
    total = weights @ samples.targets  # (B, O)
    n_obj = samples.targets.shape[1]
    runs: list[tuple[I64, NDArray[np.bool_]]] = []
    run_obj: list[int] = []
    for thresholds in samples.error_types.values():  # runs: error type, object, threshold
        for k in range(n_obj):
            for _ in thresholds:
                lo, hi = samples.offsets[len(runs)], samples.offsets[len(runs) + 1]
                runs.append((samples.est_image[lo:hi], samples.est_tp[lo:hi]))
                run_obj.append(k)
    ap_runs = weighted_ap_runs(weights, runs, total[:, run_obj])
    mean_ap: dict[str, F64] = {}
    run = 0
    for name, thresholds in samples.error_types.items():
        n_th = len(thresholds)
        ap = np.ascontiguousarray(ap_runs[:, run : run + n_obj * n_th]).reshape(b, n_obj, n_th)
        run += n_obj * n_th
        per_obj = ap.mean(axis=2)
        with warnings.catch_warnings():  # a replicate without targets: NaN, no warning
            warnings.simplefilter("ignore", RuntimeWarning)
            mean_ap[name] = np.nanmean(per_obj, axis=1) if n_obj else np.full(b, np.nan)
    return score_keys(mean_ap)


def percentile_interval(replicates: F64) -> tuple[float, float]:
    """The 95 % percentile interval of replicates (NaN replicates left out)."""
    ok = replicates[np.isfinite(replicates)]
    if ok.size == 0:
        return float("nan"), float("nan")
    lo, hi = np.percentile(ok, [2.5, 97.5])
    return float(lo), float(hi)


def confidence_intervals(
    samples: DetectionSamples, replicates: int, seed: int = 0, unit: str = "image"
) -> dict[str, tuple[float, float]]:
    """95 % bootstrap interval of each BOP24/BOP25 score."""
    weights = resample_weights(resampling_units(samples.images, unit), replicates, seed)
    reps = replicate_scores(samples, weights)
    return {k: percentile_interval(v) for k, v in reps.items()}


def bop19_replicates(curves: dict[str, RecallCurve], weights: F64) -> dict[str, F64]:
    """The BOP19 scores under each row of image weights (B, M): ``bop19_average_recall_{name}``
    per curve and, with VSD, ``bop19_average_recall``; (B,) each.

    A recall is a ratio of sums over images (matched valid GTs / valid GTs), so a replicate
    re-weights both sums; unit weights give the reported scores exactly. ``weights``' columns
    are the images of the curves' ``image_ids`` (the same for every curve: the valid GTs).
    """
    out: dict[str, F64] = {}
    for name, c in curves.items():
        if c.image_hits is None or c.image_targets is None:
            raise BopsurgError(f"the {name} recall curve has no per-image counts")
        total = weights @ c.image_targets.astype(np.float64)  # (B,)
        with np.errstate(invalid="ignore", divide="ignore"):
            recalls = (weights @ c.image_hits.T.astype(np.float64)) / total[:, None]  # (B, T)
        recalls = np.where(total[:, None] > 0, recalls, 0.0)  # as the scorer: 0 without targets
        out[f"bop19_average_recall_{name}"] = recalls.mean(axis=1)
    if all(f"bop19_average_recall_{n}" in out for n in ("vsd", "mssd", "mspd")):
        out["bop19_average_recall"] = np.mean(
            [out[f"bop19_average_recall_{n}"] for n in ("vsd", "mssd", "mspd")], axis=0
        )
    return out


def bop19_intervals(
    curves: dict[str, RecallCurve], replicates: int, seed: int = 0, unit: str = "image"
) -> dict[str, tuple[float, float]]:
    """95 % bootstrap interval of each BOP19 average recall (resampling images or scenes)."""
    first = next(iter(curves.values()), None)
    if first is None or first.image_ids is None:
        return {}
    weights = resample_weights(resampling_units(first.image_ids, unit), replicates, seed)
    return {k: percentile_interval(v) for k, v in bop19_replicates(curves, weights).items()}


#: File in an evaluation folder with the BOP19 per-image counts (``bopsurg compare``).
BOP19_SAMPLES_FILENAME = "bootstrap_bop19.npz"


def save_bop19_counts(path: Path, curves: dict[str, RecallCurve]) -> None:
    """Write the curves' per-image counts (atomically) for :func:`compare_bop19`."""
    arrays: dict[str, Any] = {}
    for name, c in curves.items():
        if c.image_ids is None or c.image_targets is None or c.image_hits is None:
            return
        arrays |= {"image_ids": c.image_ids, "image_targets": c.image_targets}
        arrays[f"hits_{name}"] = c.image_hits
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez_compressed(f, **arrays)


def load_bop19_counts(path: Path) -> dict[str, RecallCurve] | None:
    """The per-image counts :func:`save_bop19_counts` wrote, as curves; None without the file.

    Raises:
        InputError: The file is not such an archive.
    """
    if not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            ids, targets = z["image_ids"], z["image_targets"]
            hits = {k[5:]: z[k] for k in z.files if k.startswith("hits_")}
    except (OSError, ValueError, KeyError) as err:
        raise InputError(f"not a bopsurg BOP19 bootstrap archive ({err})", path=path) from None
    curves = {}
    for name, h in hits.items():
        c = RecallCurve(name, [], [], [], int(targets.sum()))
        c.image_ids, c.image_targets, c.image_hits = ids, targets, h
        curves[name] = c
    return curves


def compare_bop19(
    a: dict[str, RecallCurve],
    b: dict[str, RecallCurve],
    replicates: int = DEFAULT_REPLICATES,
    seed: int = 0,
    unit: str = "image",
) -> dict[str, Comparison]:
    """Paired bootstrap comparison of the BOP19 ARs of two evaluations of the same targets.

    Raises:
        BopsurgError: The evaluations are not on the same images with valid GTs.
    """
    ids_a, ids_b = next(iter(a.values())).image_ids, next(iter(b.values())).image_ids
    if ids_a is None or ids_b is None or not np.array_equal(ids_a, ids_b):
        raise BopsurgError(
            "the evaluations' BOP19 targets are on different images: compare needs the same "
            "dataset split and targets"
        )
    common = {k: a[k] for k in a if k in b}
    ones = np.ones((1, len(ids_a)))
    weights = resample_weights(resampling_units(ids_a, unit), replicates, seed)
    b_common = {k: b[k] for k in common}
    return paired_comparisons(
        bop19_replicates(common, ones),
        bop19_replicates(b_common, ones),
        bop19_replicates(common, weights),
        bop19_replicates(b_common, weights),
    )


@dataclass
class Comparison:
    """Paired comparison of one score between two evaluations (B minus A).

    Attributes:
        a, b: The scores on the full test set.
        diff: ``b - a``.
        ci: 95 % interval of the difference.
        p_value: Two-sided paired bootstrap p-value of "no difference".
    """

    a: float
    b: float
    diff: float
    ci: tuple[float, float]
    p_value: float


def compare_samples(
    a: DetectionSamples,
    b: DetectionSamples,
    replicates: int = DEFAULT_REPLICATES,
    seed: int = 0,
    unit: str = "image",
) -> dict[str, Comparison]:
    """Paired bootstrap comparison of two evaluations of the same target images.

    Raises:
        BopsurgError: The evaluations are not on the same images.
    """
    if a.images.shape != b.images.shape or not np.array_equal(a.images, b.images):
        raise BopsurgError(
            f"the evaluations are on different target images ({len(a.images)} vs "
            f"{len(b.images)}): compare needs the same dataset split and targets"
        )
    ones = np.ones((1, len(a.images)))
    full_a, full_b = replicate_scores(a, ones), replicate_scores(b, ones)
    weights = resample_weights(resampling_units(a.images, unit), replicates, seed)
    rep_a, rep_b = replicate_scores(a, weights), replicate_scores(b, weights)
    return paired_comparisons(full_a, full_b, rep_a, rep_b)


def paired_comparisons(
    full_a: dict[str, F64], full_b: dict[str, F64], rep_a: dict[str, F64], rep_b: dict[str, F64]
) -> dict[str, Comparison]:
    """Comparisons from the full-set values ((1,) each) and the replicates drawn with the
    same weights for both ((B,) each)."""
    out = {}
    for key in full_a:
        d = rep_b[key] - rep_a[key]
        d = d[np.isfinite(d)]
        p = 2 * min(np.mean(d <= 0), np.mean(d >= 0)) if d.size else float("nan")
        va, vb = float(full_a[key][0]), float(full_b[key][0])
        out[key] = Comparison(va, vb, vb - va, percentile_interval(d), float(min(1.0, p)))
    return out


def json_strict(value: Any) -> Any:
    """``value`` for strict JSON: tuples as lists, NaN as None (a score without targets, an
    interval without finite replicates)."""
    if isinstance(value, dict):
        return {k: json_strict(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_strict(v) for v in value]
    if isinstance(value, float) and np.isnan(value):
        return None
    return value

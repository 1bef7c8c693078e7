"""``bopsurg eval``: from a BOP dataset and a results CSV to errors, the paper's table and AR.

Two matchings are made, each for its purpose:

1. **Per-instance errors** (``errors.csv``, the paper's table): within each image and object,
   estimates in decreasing score order take the not-yet-matched GT instance with the smallest
   MSSD, with no threshold, over all GT instances (whatever their visibility). Each estimate
   gets at most one GT and each GT at most one estimate; estimates left over are written with
   ``gt_id = -1`` and empty errors; GT instances left over are "missed". The table then
   describes the GT instances with ``visib_fract ≥ --min-visib``.
2. **BOP19 scores** (``scores.json``): exactly the reference toolkit's rule
   (:mod:`bopsurg.evaluation.bop19`).

Errors in ``errors.csv`` are the plain metric values (no +inf shortcut); the reference's
shortcut only enters the BOP scores, where it decides nothing that the threshold would not.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from tqdm import tqdm

from bopsurg import metrics
from bopsurg.atomic import atomic_path, write_text
from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.images import load_depth
from bopsurg.bop.results import PoseEstimates, average_time_per_image
from bopsurg.bop.targets import Target
from bopsurg.errors import BopsurgError, DatasetError
from bopsurg.evaluation import bop19
from bopsurg.evaluation.ambiguity import ambiguity_splits, instance_ambiguity
from bopsurg.evaluation.matching import greedy_match, valid_gts_localization
from bopsurg.evaluation.summary import paper_summary
from bopsurg.evaluation.tables import GtTable, estimates_frame, load_gt_table, rank_within_groups
from bopsurg.executors import Executor
from bopsurg.plugins import DepthRenderer, load_plugin

log = logging.getLogger(__name__)

#: Per-instance metrics of errors.csv; ADD-S (``adi``) is the costly one (a k-d tree query
#: per model vertex and estimate).
INSTANCE_METRICS = ("re", "te", "mssd", "mspd", "add", "adi")

#: Columns of errors.csv, in order.
ERROR_COLUMNS = (
    "scene_id", "im_id", "obj_id", "gt_id", "score", "visib_fract",
    "re", "te", "mssd", "mspd", "add", "adi",
    "tip_visible", "tail_visible", "view_angle_deg",
)  # fmt: skip


@dataclass
class Evaluation:
    """Everything ``bopsurg eval`` computes.

    Attributes:
        errors: errors.csv rows (one per estimate; ``gt_id = -1`` when unmatched).
        gt_rows: One row per GT instance of the split with its matched estimate's errors.
        summary: The paper's table and extra scores
            (:func:`~bopsurg.evaluation.summary.paper_summary`).
        scores: BOP19 scores under the reference toolkit's key names.
        curves: Recall curves per BOP error type.
    """

    errors: pd.DataFrame
    gt_rows: pd.DataFrame
    summary: dict[str, object]
    scores: dict[str, float]
    curves: dict[str, bop19.RecallCurve]


class _ModelCache:
    """Model points, symmetry sets and diameters per object, loaded once."""

    def __init__(self, dataset: BopDataset, max_sym_disc_step: float) -> None:
        self.dataset = dataset
        self.step = max_sym_disc_step
        self._syms: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def pts(self, obj_id: int) -> np.ndarray:
        return self.dataset.model(obj_id).pts

    def syms(self, obj_id: int) -> tuple[np.ndarray, np.ndarray]:
        if obj_id not in self._syms:
            self._syms[obj_id] = metrics.symmetry_transforms(
                self.dataset.models_info[obj_id], self.step
            )
        return self._syms[obj_id]

    def diameter(self, obj_id: int) -> float:
        return float(self.dataset.models_info[obj_id]["diameter"])

    def diameters(self, obj_ids: np.ndarray) -> np.ndarray:
        """Diameter (mm) of each object id in ``obj_ids``, looked up once per distinct id."""
        ids, inverse = np.unique(obj_ids, return_inverse=True)
        return np.array([self.diameter(int(o)) for o in ids], dtype=np.float64)[inverse]


def _pair_errors(
    est: PoseEstimates,
    gt: GtTable,
    e_idx: np.ndarray,
    g_idx: np.ndarray,
    models: _ModelCache,
    which: Sequence[str],
) -> dict[str, np.ndarray]:
    """Metric values for pairs (estimate e_idx[i], GT g_idx[i]), batched per object."""
    out = {name: np.full(e_idx.shape[0], np.nan) for name in which}
    obj = gt.obj_id[g_idx]
    for obj_id in np.unique(obj):
        sel = np.flatnonzero(obj == obj_id)
        Re, te_ = est.R[e_idx[sel]], est.t[e_idx[sel]]
        Rg, tg = gt.R[g_idx[sel]], gt.t[g_idx[sel]]
        oid = int(obj_id)
        for name in which:
            if name == "re":
                v = metrics.re(Re, Rg)
            elif name == "te":
                v = metrics.te(te_, tg)
            elif name == "mssd":
                v = metrics.mssd(Re, te_, Rg, tg, models.pts(oid), models.syms(oid))
            elif name == "mspd":
                K = gt.K[g_idx[sel]]
                v = metrics.mspd(Re, te_, Rg, tg, K, models.pts(oid), models.syms(oid))
            elif name == "add":
                v = metrics.add(Re, te_, Rg, tg, models.pts(oid))
            elif name == "adi":
                v = metrics.adi(Re, te_, Rg, tg, models.pts(oid))
            else:  # pragma: no cover - guarded by callers
                raise ValueError(name)
            out[name][sel] = v
    return out


def _candidate_pairs(est_df: pd.DataFrame, gt: GtTable) -> pd.DataFrame:
    """All (estimate, GT) pairs of the same object in the same image, by estimate then gt_id."""
    pairs = est_df.merge(gt.frame(), on=["scene_id", "im_id", "obj_id"], how="inner")
    return pairs.sort_values(["e", "gt_id"], kind="stable").reset_index(drop=True)


def _instance_matching(
    est: PoseEstimates, gt: GtTable, models: _ModelCache, which: Sequence[str]
) -> tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame]:
    """Matching 1 (see the module docstring): errors.csv rows, per-GT rows, and the MSSD of
    every candidate pair (columns e, g, mssd) for the BOP scores to reuse."""
    est_df = estimates_frame(est)
    rank, _ = rank_within_groups(est_df[["scene_id", "im_id", "obj_id"]], est.score)
    est_df["rank"] = rank
    pairs = _candidate_pairs(est_df, gt)
    e_idx = pairs["e"].to_numpy()
    g_idx = pairs["g"].to_numpy()
    mssd_all = _pair_errors(est, gt, e_idx, g_idx, models, ("mssd",))["mssd"]
    matched_by = greedy_match(
        pairs["rank"].to_numpy(), e_idx, g_idx, mssd_all, np.inf, np.ones(len(gt), dtype=bool)
    )
    gt_ok = np.flatnonzero(matched_by >= 0)
    p = matched_by[gt_ok]
    m_e, m_g = e_idx[p], g_idx[p]
    rest = [m for m in which if m != "mssd"]
    errs = _pair_errors(est, gt, m_e, m_g, models, rest)
    errs["mssd"] = mssd_all[p]  # always computed: it decides the matching

    n_est = len(est)
    gt_of_est = np.full(n_est, -1, dtype=np.int64)
    gt_of_est[m_e] = m_g
    rows = pd.DataFrame(
        {
            "scene_id": est.scene_id,
            "im_id": est.im_id,
            "obj_id": est.obj_id,
            "gt_id": np.where(gt_of_est >= 0, gt.gt_id[np.maximum(gt_of_est, 0)], -1),
            "score": est.score,
            "visib_fract": np.where(
                gt_of_est >= 0, gt.visib_fract[np.maximum(gt_of_est, 0)], np.nan
            ),
        }
    )
    for name in INSTANCE_METRICS:
        col = np.full(n_est, np.nan)
        if name in errs:
            col[m_e] = errs[name]
        rows[name] = col
    rows = rows.sort_values(["scene_id", "im_id", "obj_id", "gt_id"], kind="stable")

    gt_rows = gt.frame().drop(columns="g")
    gt_rows["visib_fract"] = gt.visib_fract
    gt_rows["diameter"] = models.diameters(gt.obj_id)
    gt_rows["est_row"] = -1
    gt_rows.loc[m_g, "est_row"] = m_e
    for name in INSTANCE_METRICS:
        col = np.full(len(gt), np.nan)
        if name in errs:
            col[m_g] = errs[name]
        gt_rows[name] = col
    pair_mssd = pd.DataFrame({"e": e_idx, "g": g_idx, "mssd": mssd_all})
    return rows.reset_index(drop=True), gt_rows, pair_mssd


def _bop19(
    est: PoseEstimates,
    gt: GtTable,
    targets: Sequence[Target],
    models: _ModelCache,
    dataset: BopDataset,
    renderer: DepthRenderer | None,
    vsd_delta: float,
    progress: bool,
    pair_mssd: pd.DataFrame,
) -> dict[str, bop19.RecallCurve]:
    """Matching 2: BOP19 recall curves under the reference toolkit's rules."""
    tdf = pd.DataFrame(
        {
            "scene_id": [t.scene_id for t in targets],
            "im_id": [t.im_id for t in targets],
            "obj_id": [t.obj_id for t in targets],
            "inst_count": [t.inst_count for t in targets],
        },
        dtype=np.int64,
    ).drop_duplicates(["scene_id", "im_id", "obj_id"], keep="last")
    # Valid GT instances: in target images, of target objects, the inst_count most visible.
    gdf = gt.frame().merge(tdf, on=["scene_id", "im_id", "obj_id"], how="left")
    gdf = gdf.sort_values("g").reset_index(drop=True)
    inst = gdf["inst_count"].fillna(0).to_numpy(dtype=np.int64)
    grp = gdf.groupby(["scene_id", "im_id", "obj_id"], sort=False).ngroup().to_numpy()
    valid = valid_gts_localization(grp, gt.visib_fract, inst)

    # Kept estimates: targets only, the inst_count best per (scene, image, object).
    est_df = estimates_frame(est).merge(tdf, on=["scene_id", "im_id", "obj_id"], how="inner")
    est_df = est_df.sort_values("e").reset_index(drop=True)
    rank, _ = rank_within_groups(
        est_df[["scene_id", "im_id", "obj_id"]], est_df["score"].to_numpy()
    )
    est_df["rank"] = rank
    est_df = est_df[est_df["rank"] < est_df["inst_count"]]
    pairs_df = _candidate_pairs(est_df.drop(columns="inst_count"), gt)
    pairs = bop19.PairTable(
        est_rank=pairs_df["rank"].to_numpy(np.int64),
        est_index=pairs_df["e"].to_numpy(np.int64),
        gt_index=pairs_df["g"].to_numpy(np.int64),
    )
    e_idx, g_idx = pairs.est_index, pairs.gt_index
    errs = _pair_errors(est, gt, e_idx, g_idx, models, ("te", "mspd"))
    # Every BOP pair is also a candidate pair of the instance matching: reuse its MSSD.
    known = pd.Series(
        pair_mssd["mssd"].to_numpy(), index=pd.MultiIndex.from_frame(pair_mssd[["e", "g"]])
    )
    errs["mssd"] = known.reindex(pd.MultiIndex.from_arrays([e_idx, g_idx])).to_numpy()
    diam = models.diameters(gt.obj_id[g_idx])
    curves = {
        "mssd": bop19.recall_curve(
            pairs,
            bop19.normalise_mssd(errs["mssd"], errs["te"], diam),
            valid,
            bop19.MSSD_THRESHOLDS,
            "mssd",
        ),
        "mspd": bop19.recall_curve(
            pairs,
            bop19.normalise_mspd(errs["mspd"], gt.im_width[g_idx]),
            valid,
            bop19.MSPD_THRESHOLDS,
            "mspd",
        ),
    }
    if renderer is not None:
        vsd = _vsd_errors(est, gt, e_idx, g_idx, diam, dataset, renderer, vsd_delta, progress)
        curve = bop19.recall_curve(pairs, vsd, valid, bop19.VSD_THRESHOLDS, "vsd")
        curve.taus = list(bop19.VSD_TAUS)
        curve.extra["delta_mm"] = vsd_delta
        curves["vsd"] = curve

    return curves


def _vsd_errors(
    est: PoseEstimates,
    gt: GtTable,
    e_idx: np.ndarray,
    g_idx: np.ndarray,
    diameter: np.ndarray,
    dataset: BopDataset,
    renderer: DepthRenderer,
    delta: float,
    progress: bool,
) -> np.ndarray:
    """VSD errors (τ × P) of the pairs, rendering both poses with the renderer plugin."""
    taus = np.asarray(bop19.VSD_TAUS)
    out = np.ones((taus.size, e_idx.shape[0]))
    overlap = bop19.sphere_projections_overlap(est.t[e_idx], gt.t[g_idx], 0.5 * diameter)
    todo = np.flatnonzero(overlap)
    images = pd.DataFrame({"s": gt.scene_id[g_idx[todo]], "i": gt.im_id[g_idx[todo]], "p": todo})
    groups = images.groupby(["s", "i"], sort=True)
    for (scene_id, im_id), grp in tqdm(
        groups, total=groups.ngroups, desc="VSD", unit="img", disable=not progress
    ):
        scene = dataset.scene(int(scene_id))
        cam = scene.camera[int(im_id)]
        if cam.depth_scale is None:
            raise DatasetError(
                "depth_scale is missing (needed for VSD)",
                path=scene.scene_dir / "scene_camera.json",
                field=f"{im_id}/depth_scale",
            )
        depth = load_depth(scene.depth_path(int(im_id))) * cam.depth_scale
        h, w = depth.shape
        gt_cache: dict[int, np.ndarray] = {}
        for p in grp["p"].to_numpy():
            g, e = int(g_idx[p]), int(e_idx[p])
            model = dataset.model(int(gt.obj_id[g]))
            if g not in gt_cache:
                gt_cache[g] = renderer.render_depth(model, gt.R[g], gt.t[g], cam.K, w, h)
            d_est = renderer.render_depth(model, est.R[e], est.t[e], cam.K, w, h)
            out[:, p] = metrics.vsd(
                depth, d_est, gt_cache[g], cam.K, delta, taus, diameter=float(diameter[p])
            )
    return out


def evaluate(
    dataset: BopDataset,
    estimates: PoseEstimates,
    *,
    targets: Sequence[Target] | None = None,
    min_visib: float = 0.3,
    renderer: DepthRenderer | None = None,
    vsd_delta: float = bop19.VSD_DELTA_MM,
    max_sym_disc_step: float = 0.01,
    instance_metrics: Sequence[str] = INSTANCE_METRICS,
    scene_ids: Sequence[int] | None = None,
    progress: bool = False,
) -> Evaluation:
    """Evaluate pose estimates on a BOP dataset split.

    Args:
        dataset: The dataset (its split holds the GT).
        estimates: Results, e.g. from :func:`bopsurg.bop.load_results`. They must already be
            checked against the dataset (:func:`bopsurg.bop.check_results_against_dataset`).
        targets: BOP19 targets; default: the dataset's ``test_targets_bop19.json``.
        min_visib: Visibility threshold of the paper's table.
        renderer: A depth renderer for VSD; without one AR_VSD and the overall AR are absent.
        vsd_delta: VSD visibility tolerance δ, mm.
        max_sym_disc_step: Discretisation of continuous symmetries (BOP: 0.01).
        instance_metrics: Metrics of errors.csv (subset of :data:`INSTANCE_METRICS`; MSSD is
            always computed since it decides the matching; left-out columns stay empty).
        scene_ids: Evaluate only these scenes (their GT, estimates and targets).
        progress: Show progress bars.

    Returns:
        The :class:`Evaluation`.
    """
    unknown = set(instance_metrics) - set(INSTANCE_METRICS)
    if unknown:
        raise BopsurgError(
            f"unknown metric(s) {sorted(unknown)}; choose from {', '.join(INSTANCE_METRICS)}"
        )
    models = _ModelCache(dataset, max_sym_disc_step)
    gt = load_gt_table(dataset, scene_ids)
    if targets is None:
        targets = dataset.targets()
    if scene_ids is not None:
        keep = set(scene_ids)
        targets = [t for t in targets if t.scene_id in keep]
        estimates = estimates.subset(np.isin(estimates.scene_id, sorted(keep)))
    errors, gt_rows, pair_mssd = _instance_matching(estimates, gt, models, instance_metrics)
    amb = instance_ambiguity(dataset, gt_rows, gt.R, gt.t, gt.K)
    gt_rows = gt_rows.join(amb)
    # errors.csv rows carry the ambiguity of the GT they were matched to
    key = ["scene_id", "im_id", "obj_id", "gt_id"]
    errors = errors.merge(gt_rows[[*key, *amb.columns]], on=key, how="left")
    curves = _bop19(
        estimates, gt, targets, models, dataset, renderer, vsd_delta, progress, pair_mssd
    )
    return _assemble(errors, gt_rows, curves, estimates, min_visib)


def _assemble(
    errors: pd.DataFrame,
    gt_rows: pd.DataFrame,
    curves: dict[str, bop19.RecallCurve],
    estimates: PoseEstimates,
    min_visib: float,
) -> Evaluation:
    """Scores and summary from the per-instance rows and the recall curves."""
    scores: dict[str, float] = {}
    for name in ("vsd", "mssd", "mspd"):
        if name in curves:
            scores[f"bop19_average_recall_{name}"] = curves[name].average_recall
    if "vsd" in curves:
        scores["bop19_average_recall"] = float(
            np.mean([scores[f"bop19_average_recall_{n}"] for n in ("vsd", "mssd", "mspd")])
        )
    scores["bop19_average_time_per_image"] = average_time_per_image(estimates)
    summary = paper_summary(gt_rows, min_visib=min_visib)
    summary["splits"] = ambiguity_splits(gt_rows[gt_rows["visib_fract"] >= min_visib])
    summary["estimates"] = len(estimates)
    summary["unmatched_estimates"] = int((errors["gt_id"] < 0).sum())
    return Evaluation(errors, gt_rows, summary, scores, curves)


@dataclass(frozen=True)
class EvalUnit:
    """A group of scenes evaluated on its own (a unit for :mod:`bopsurg.executors`)."""

    root: str
    split: str
    split_type: str | None
    scene_ids: tuple[int, ...]
    estimates: PoseEstimates
    targets: tuple[Target, ...] | None
    options: dict


def _eval_unit(unit: EvalUnit, report: Callable[[int], None]) -> Evaluation:
    dataset = BopDataset(unit.root, unit.split, split_type=unit.split_type)
    opts = dict(unit.options)
    renderer_name = opts.pop("renderer_name", None)
    renderer = load_plugin("renderer", renderer_name)() if renderer_name else None
    result = evaluate(
        dataset,
        unit.estimates,
        targets=unit.targets,
        scene_ids=unit.scene_ids,
        renderer=renderer,
        **opts,
    )
    report(len(unit.scene_ids))
    return result


def evaluate_distributed(
    dataset: BopDataset,
    estimates: PoseEstimates,
    *,
    executor: Executor,
    targets: Sequence[Target] | None = None,
    renderer_name: str | None = None,
    scenes_per_unit: int = 1,
    progress: bool = False,
    **options: object,
) -> Evaluation:
    """:func:`evaluate`, split into groups of scenes run by ``executor``, then merged.

    Matching is per image and recall is micro-averaged (Σ TP / Σ targets), so the merged
    result equals :func:`evaluate`'s, number for number. Renderers do not travel between
    processes: VSD workers load the renderer plugin ``renderer_name`` themselves.
    """
    if scenes_per_unit < 1:
        raise BopsurgError("scenes_per_unit must be >= 1")
    all_targets = list(targets) if targets is not None else dataset.targets()
    ids = dataset.scene_ids
    groups = [tuple(ids[i : i + scenes_per_unit]) for i in range(0, len(ids), scenes_per_unit)]
    units = []
    for g in groups:
        keep = np.isin(estimates.scene_id, g)
        units.append(
            EvalUnit(
                root=str(dataset.root),
                split=dataset.split,
                split_type=dataset.split_type,
                scene_ids=g,
                estimates=estimates.subset(keep),
                targets=tuple(t for t in all_targets if t.scene_id in set(g)),
                options={**options, "renderer_name": renderer_name},
            )
        )
    with tqdm(total=len(ids), unit="scene", desc="eval", disable=not progress) as bar:
        parts: list[Evaluation] = executor.map(_eval_unit, units, on_progress=bar.update)
    curves: dict[str, bop19.RecallCurve] = {}
    for name in parts[0].curves if parts else ():
        first = parts[0].curves[name]
        tps = np.sum([p.curves[name].tp_counts for p in parts], axis=0).tolist()
        targets_count = int(sum(p.curves[name].targets_count for p in parts))
        recalls = [tp / float(targets_count) if targets_count > 0 else 0.0 for tp in tps]
        curves[name] = bop19.RecallCurve(
            name,
            first.thresholds,
            recalls,
            [int(t) for t in tps],
            targets_count,
            first.taus,
            first.extra,
        )
    errors = pd.concat([p.errors for p in parts], ignore_index=True)
    gt_rows = pd.concat([p.gt_rows for p in parts], ignore_index=True)
    min_visib = float(options.get("min_visib", 0.3))  # type: ignore[arg-type]
    return _assemble(errors, gt_rows, curves, estimates, min_visib)


def _json_safe(value: object) -> object:
    """NaN/inf become null, so the files are standard JSON that every parser reads."""
    if isinstance(value, float):
        return value if np.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    return value


def write_evaluation(result: Evaluation, out_dir: str | Path, *, meta: dict | None = None) -> None:
    """Write ``errors.csv``, ``summary.json`` and ``scores.json`` into ``out_dir`` atomically."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    with atomic_path(out / "errors.csv") as tmp:
        result.errors.loc[:, list(ERROR_COLUMNS)].to_csv(tmp, index=False, float_format="%.9g")
    summary = {**(meta or {}), **result.summary}
    text = json.dumps(_json_safe(summary), indent=2, allow_nan=False)
    write_text(out / "summary.json", text + "\n")
    details = {
        name: {
            "thresholds": c.thresholds,
            "taus": c.taus,
            "recalls": c.recalls,
            "tp_counts": c.tp_counts,
            "targets_count": c.targets_count,
            **c.extra,
        }
        for name, c in result.curves.items()
    }
    scores = {**result.scores, "details": details}
    write_text(
        out / "scores.json", json.dumps(_json_safe(scores), indent=2, allow_nan=False) + "\n"
    )

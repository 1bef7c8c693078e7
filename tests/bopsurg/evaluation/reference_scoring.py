"""A sequential, dict-based re-statement of the reference toolkit's BOP19 scoring.

Written from the rules of ``eval_calc_errors.py``, ``eval_calc_scores.py``,
``pose_matching.match_poses`` and ``score.calc_localization_scores`` (thodan/bop_toolkit,
localization mode, ``n_top = -1``, ``visib_gt_min = -1``), one image and one estimate at a
time, as the oracle for the vectorised implementation in :mod:`bopsurg.evaluation`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass


@dataclass
class Gt:
    obj_id: int
    visib_fract: float
    pose: object


@dataclass
class Est:
    scene_id: int
    im_id: int
    obj_id: int
    score: float
    pose: object


def calc_errors(
    gts: dict[tuple[int, int], list[Gt]],
    targets: Sequence[dict],
    ests: Sequence[Est],
    error_fn: Callable[[Est, Gt], float],
) -> list[dict]:
    """Per-estimate errors w.r.t. every GT of its object, as eval_calc_errors.py."""
    targets_org: dict[int, dict[int, dict[int, dict]]] = {}
    for t in targets:
        targets_org.setdefault(t["scene_id"], {}).setdefault(t["im_id"], {})[t["obj_id"]] = t
    ests_org: dict[int, dict[int, dict[int, list[Est]]]] = {}
    for e in ests:
        ests_org.setdefault(e.scene_id, {}).setdefault(e.im_id, {}).setdefault(e.obj_id, []).append(
            e
        )
    out = []
    for scene_id, scene_targets in targets_org.items():
        for im_id, im_targets in scene_targets.items():
            for obj_id, target in im_targets.items():
                obj_ests = ests_org.get(scene_id, {}).get(im_id, {}).get(obj_id, [])
                ranked = sorted(enumerate(obj_ests), key=lambda x: x[1].score, reverse=True)
                ranked = ranked[slice(0, target["inst_count"])]
                for est_id, est in ranked:
                    errs = {}
                    for gt_id, gt in enumerate(gts[(scene_id, im_id)]):
                        if gt.obj_id == obj_id:
                            errs[gt_id] = error_fn(est, gt)
                    out.append(
                        {"scene_id": scene_id, "im_id": im_id, "obj_id": obj_id,
                         "est_id": est_id, "score": est.score, "errors": errs}
                    )  # fmt: skip
    return out


def match_poses(errs: list[dict], threshold: float, valid: list[bool]) -> list[dict]:
    """pose_matching.match_poses for a one-element error."""
    errs_sorted = sorted(errs, key=lambda e: e["score"], reverse=True)
    matches = []
    gt_matched: list[int] = []
    for e in errs_sorted:
        best_gt_id = -1
        best_error = threshold
        for gt_id, error in e["errors"].items():
            if valid[gt_id] and gt_id not in gt_matched and error < best_error:
                best_gt_id = gt_id
                best_error = error
        if best_gt_id >= 0:
            gt_matched.append(best_gt_id)
            matches.append({"est_id": e["est_id"], "gt_id": best_gt_id})
    return matches


def recall(
    gts: dict[tuple[int, int], list[Gt]],
    targets: Sequence[dict],
    errs: list[dict],
    threshold: float,
    normalise: Callable[[dict, int, float], float] = lambda e, gt_id, v: v,
) -> float:
    """Recall for one threshold, as eval_calc_scores.py + calc_localization_scores."""
    targets_org: dict[tuple[int, int], dict[int, dict]] = {}
    for t in targets:
        targets_org.setdefault((t["scene_id"], t["im_id"]), {})[t["obj_id"]] = t
    tars = tps = 0
    for (scene_id, im_id), im_targets in targets_org.items():
        im_gts = gts[(scene_id, im_id)]
        order = sorted(range(len(im_gts)), key=lambda g: im_gts[g].visib_fract, reverse=True)
        to_add = {obj_id: t["inst_count"] for obj_id, t in im_targets.items()}
        valid = [False] * len(im_gts)
        for gt_id in order:
            obj_id = im_gts[gt_id].obj_id
            if to_add.get(obj_id, 0) > 0:
                valid[gt_id] = True
                to_add[obj_id] -= 1
        tars += sum(valid)
        im_errs = [e for e in errs if (e["scene_id"], e["im_id"]) == (scene_id, im_id)]
        for obj_id in {g.obj_id for g in im_gts}:
            obj_errs = []
            for e in im_errs:
                if e["obj_id"] == obj_id:
                    normed = {g: normalise(e, g, v) for g, v in e["errors"].items()}
                    obj_errs.append({**e, "errors": normed})
            for m in match_poses(obj_errs, threshold, valid):
                if valid[m["gt_id"]]:
                    tps += 1
    return tps / float(tars) if tars else 0.0

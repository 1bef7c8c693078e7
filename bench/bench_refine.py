r"""Bench: the needle refinement, before/after, on the same held-out test split.

One pass over the split runs the ``gdrnet`` estimator without refinement (the "before"
poses: detector + pose head, direct decoding), then the refinement stage on the same image,
boxes and poses (the "after" poses: ``GdrNetEstimator.refine_needles``, what the estimator's
``refine=fit`` runs, re-crops included, ``--option recrop=0`` turns them off; skipped with
``--segmenter none``), and optionally the stage again with the GT masks as
evidence (``--oracle``: the fit's ceiling; the full or the visible masks, as ``--mask``
says). Each set is written as a BOP results CSV and scored by ``bopsurg eval``; it prints
the paper's table, AR_MSSD / AR_MSPD, the median translation error per camera axis and the
CPU time per 640x480 image (network, refinement), 2 threads.

    python bench/bench_refine.py DATASET --out bench/out/refine --segmenter SEG.pt \
        [--oracle] [--stride 1] [--fit prior_weight=0.3] [--from-gt] [--oracle-boxes]
        [--option zoom=1]

A dataset whose needle model is not the estimator's (an imported ``bopsurg import
ambf-yaml``) is measured in its own frame, as ``bopsurg predict`` maps it
(:mod:`bopsurg.model_frames`): the stages run in the estimator's frame (a GT start mapped
into it) and every pose is mapped back before it is scored.

SEG.pt comes from ``python -m bopsurg.models.refine.train_seg TRAIN_DATASET --out RUN``.

DATASET needs a test split from episodes and viewpoints never used in training (the model
card's recipe: bags seeds 101..102, ``generate --split test --replays 16 --period 2 --seed 1``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np
import torch

from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.detections import gt_detections
from bopsurg.bop.images import load_mask, load_rgb
from bopsurg.bop.results import PoseEstimates, save_results
from bopsurg.cli.main import main as bopsurg
from bopsurg.estimation import load_estimator
from bopsurg.evaluation.summary import format_table
from bopsurg.models.estimator import REFINE_FIT, SHIPPED
from bopsurg.models.pose.roi import crop
from bopsurg.models.refine import ArcModel, FitSettings, NeedleRefiner, Segmenter
from bopsurg.prediction import dataset_mappings

PAPER = {"re": 7.74, "te": 1.49, "mssd": 1.43}
#: Evidence grid side (px) of the oracle stage when no segmenter sets it.
ORACLE_GRID = 192


def gt_mask_evidence(mask: np.ndarray, full: np.ndarray | None = None):
    """An evidence source that crops GT masks like the segmenter crops the image: the visible
    ``mask``, or it and the ``full`` mask (as a full-mask segmenter gives them)."""
    planes = [mask] if full is None else [mask, full]
    m = torch.from_numpy(np.stack(planes).astype(np.float32))[None]

    def evidence(image, centre, side, size):
        index = torch.zeros(len(centre), dtype=torch.long)
        prob = crop(m, centre, side, size, "bilinear", index=index).numpy()
        return prob if full is not None else prob[:, 0]

    return evidence


def fit_settings(pairs: list[str]) -> FitSettings:
    """The estimator's fit (:data:`REFINE_FIT`) with ``KEY=VALUE`` overrides (ints, floats,
    0/1 flags, comma tuples)."""
    base = REFINE_FIT
    kw: dict = {}
    for pair in pairs:
        key, _, value = pair.partition("=")
        if not hasattr(base, key):
            raise SystemExit(f"--fit: unknown FitSettings knob {key!r}")
        current = getattr(base, key)
        if isinstance(current, tuple):
            kw[key] = tuple(float(v) for v in value.split(","))
        else:
            kw[key] = type(current)(float(value))
    return dataclasses.replace(base, **kw)


def axis_medians(ds: BopDataset, est: PoseEstimates, min_visib: float) -> tuple[list[float], float]:
    """Median |dx|, |dy|, |dz| (camera frame, mm) against the first GT of each image with
    visib_fract >= min_visib (one needle per image), and the median signed relative depth
    error (t_z,est − t_z,gt) / t_z,gt: a bias of the depth, not only its spread."""
    d, rel = [], []
    for s, i, t in zip(est.scene_id, est.im_id, est.t, strict=True):
        scene = ds.scene(int(s))
        if scene.gt_info[int(i)][0].visib_fract >= min_visib:
            t_gt = scene.gt[int(i)][0].t
            d.append(np.abs(t - t_gt))
            rel.append((t[2] - t_gt[2]) / t_gt[2])
    return [float(v) for v in np.median(np.array(d), axis=0)], float(np.median(rel))


def evaluate(data: Path, results: Path, out: Path) -> tuple[dict, dict]:
    args = ["-q", "eval", str(data), str(results), "--out", str(out)]
    code = bopsurg([*args, "--metrics", "re,te,mssd,mspd", "--no-progress"])
    if code:
        raise SystemExit(f"bopsurg eval failed with exit code {code}")
    return (
        json.loads((out / "summary.json").read_text()),
        json.loads((out / "scores.json").read_text()),
    )


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("dataset", type=Path, help="BOP dataset root with a test split")
    ap.add_argument("--out", type=Path, required=True, help="output folder")
    ap.add_argument("--detector", default=None, help="default: the shipped one")
    ap.add_argument("--pose", default=None, help="default: the shipped one")
    ap.add_argument(
        "--segmenter",
        default=str(SHIPPED / "needle_seg.pt"),
        help="segmenter checkpoint, or 'none' (then only 'before' and '--oracle' are scored)",
    )
    ap.add_argument(
        "--mask",
        choices=["full", "visible"],
        default=None,
        help="the segmenter's evidence the fit uses, and the GT masks of --oracle: full (the "
        "full and the visible mask; the default when the segmenter predicts the full mask) "
        "or visible",
    )
    ap.add_argument("--oracle", action="store_true", help="also refine against GT masks")
    ap.add_argument("--stride", type=int, default=1, help="every n-th image (quick looks)")
    ap.add_argument(
        "--from-gt",
        action="store_true",
        help="start the refinement stages from the GT pose instead of the network's; with "
        "--fit prior_weight=0 this measures how far the evidence alone moves a perfect pose "
        "(what the fit can pin down at best)",
    )
    ap.add_argument(
        "--oracle-boxes",
        action="store_true",
        help="the GT visible boxes instead of the detector's (the stages measured without "
        "the detector's misses)",
    )
    ap.add_argument(
        "--fit",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a FitSettings knob (numbers; repeatable), e.g. --fit prior_weight=0.05",
    )
    ap.add_argument(
        "--option",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a gdrnet option of the network stage (repeatable), e.g. --option zoom=1",
    )
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    args.out.mkdir(parents=True, exist_ok=True)
    ds = BopDataset(args.dataset, "test")
    opts = {"refine": "none", "device": "cpu"}
    opts |= {k: v for k, v in (("detector", args.detector), ("pose", args.pose)) if v}
    opts |= dict(pair.partition("=")[::2] for pair in args.option)
    est = load_estimator("gdrnet", opts)
    head = est.heads[1]
    settings = fit_settings(args.fit)
    refiner = None
    if args.segmenter != "none":
        seg = Segmenter(args.segmenter, torch.device("cpu"), args.mask)
        refiner = NeedleRefiner.for_segmenter(seg, settings)
    oracle_mask = args.mask or (seg.mask if refiner is not None else "visible")
    mapping = dataset_mappings(ds, est).get(1)  # None: the dataset's needle is the estimator's
    if mapping is None:
        info = ds.models_info[1]["keypoints"]
        arc = ArcModel.from_keypoints(info["tail"], info["tip"])
    elif refiner is not None:
        print(mapping.describe())
        arc = seg.arc  # the stages run in the estimator's frame
    else:
        raise SystemExit("a dataset with another needle model needs --segmenter (its arc)")
    boxes = gt_detections(ds) if args.oracle_boxes else {}
    oracle = NeedleRefiner(
        gt_mask_evidence(np.zeros((1, 1), bool)),
        arc,
        ORACLE_GRID,
        settings=settings,
        whole=refiner is not None and refiner.whole,  # framed as the segmenter frames
    )

    names = ["before"] + (["after"] if refiner else []) + (["oracle"] if args.oracle else [])
    rows: dict[str, list] = {n: [] for n in names}
    net_ms: list[float] = []
    ref_ms: list[float] = []
    oracle_ms: list[float] = []
    keys = [(s, i) for s in ds.scene_ids for i in ds.scene(s).im_ids][:: args.stride]
    for s, i in keys:
        scene = ds.scene(s)
        rgb, K = load_rgb(scene.rgb_path(i)), scene.camera[i].K
        t0 = time.perf_counter()
        found = boxes.get((s, i)) if args.oracle_boxes else None
        if args.oracle_boxes and found is None:
            continue  # nothing of the needle visible: no box to run on
        pred = est.predict(rgb, K, boxes=found)
        t1 = time.perf_counter()
        if len(pred) == 0:
            continue
        image = torch.from_numpy(rgb).permute(2, 0, 1)[None].float() / 255
        b = torch.as_tensor(pred.bbox, dtype=torch.float32)
        box = torch.cat([b[:, :2] - 0.5, b[:, 2:]], dim=1)  # as the estimator crops
        net_ms.append(1000 * (t1 - t0))
        poses = {"before": (pred.R, pred.t)}
        R0, t0 = pred.R, pred.t
        if args.from_gt:  # one needle per image: its first GT
            g = scene.gt[i][0]
            R0, t0 = np.repeat(g.R[None], len(pred), 0), np.repeat(g.t[None], len(pred), 0)
            if mapping is not None:
                R0, t0 = mapping.unmap_poses(R0, t0)
        # the estimator's refinement stage (re-crops included, not from a GT start)
        recrop = 0.0 if args.from_gt else None
        if refiner is not None:
            t2 = time.perf_counter()
            poses["after"] = est.refine_needles(head, image, K, box, R0, t0, refiner, recrop)[:2]
            ref_ms.append(1000 * (time.perf_counter() - t2))
        if args.oracle:
            visible = load_mask(scene.mask_visib_path(i, 0))
            full = load_mask(scene.mask_path(i, 0)) if oracle_mask == "full" else None
            oracle.evidence = gt_mask_evidence(visible, full)
            t2 = time.perf_counter()
            poses["oracle"] = est.refine_needles(head, image, K, box, R0, t0, oracle, recrop)[:2]
            oracle_ms.append(1000 * (time.perf_counter() - t2))
        for name, (Rn, tn) in poses.items():
            if mapping is not None:  # scored in the dataset's frame
                Rn, tn = mapping.map_poses(Rn, tn)
            for k in range(len(pred)):
                rows[name].append((s, i, int(pred.obj_id[k]), float(pred.score[k]), Rn[k], tn[k]))

    report: dict = {"images": len(keys), "stride": args.stride, "fit": vars(settings)}
    report["mask"] = oracle_mask
    table = []
    for name in names:
        r = rows[name]
        est_n = PoseEstimates(
            scene_id=np.array([x[0] for x in r]),
            im_id=np.array([x[1] for x in r]),
            obj_id=np.array([x[2] for x in r]),
            score=np.array([x[3] for x in r]),
            R=np.array([x[4] for x in r]),
            t=np.array([x[5] for x in r]),
            time=np.full(len(r), -1.0),
            line=np.full(len(r), -1),
        )
        path = args.out / f"results_{name}.csv"
        save_results(path, est_n)
        summary, scores = evaluate(args.dataset, path, args.out / f"eval_{name}")
        axes, depth_bias = axis_medians(ds, est_n, summary["min_visib"])
        report[name] = {
            "summary": summary, "scores": scores, "axes_mm": axes, "depth_bias": depth_bias
        }  # fmt: skip
        print(f"\n== {name} ==\n{format_table(summary, scores)}")
        print("median |dx|, |dy|, |dz| (camera frame, mm): " + ", ".join(f"{v:.2f}" for v in axes))
        print(f"median signed depth error (t_z est - gt) / t_z gt: {100 * depth_bias:+.1f} %")
        tb = summary["table"]
        table.append(
            f"| {name} | {tb['re']['median']:.2f} | {tb['te']['median']:.2f} | "
            f"{tb['mssd']['median']:.2f} | {scores['bop19_average_recall_mssd']:.3f} | "
            f"{scores['bop19_average_recall_mspd']:.3f} | "
            + " / ".join(f"{v:.2f}" for v in axes)
            + " |"
        )
    report["net_ms"] = {"median": float(np.median(net_ms)), "p90": float(np.percentile(net_ms, 90))}
    fit = ref_ms or oracle_ms  # the fit's time (the segmenter's included when there is one)
    report["refine_ms"] = {"median": float(np.median(fit)), "p90": float(np.percentile(fit, 90))}
    stage = refiner or oracle
    report["refine_stats"] = vars(stage.stats)
    print(
        "\n| | median RE [deg] | median TE [mm] | median MSSD [mm] | AR_MSSD | AR_MSPD "
        "| |dx| / |dy| / |dz| [mm] |"
    )
    print("|---|---|---|---|---|---|---|")
    print("\n".join(table))
    print(f"| paper (GDRNPP) | {PAPER['re']} | {PAPER['te']} | {PAPER['mssd']} | | | |")
    print(
        f"\nCPU time per 640x480 image ({args.threads} threads): network median "
        f"{report['net_ms']['median']:.1f} ms (p90 {report['net_ms']['p90']:.1f}); refinement "
        f"median {report['refine_ms']['median']:.1f} ms (p90 {report['refine_ms']['p90']:.1f}); "
        f"refined {stage.stats.refined}, kept {stage.stats.kept}"
    )
    (args.out / "bench_refine.json").write_text(json.dumps(report, indent=2, default=str) + "\n")


if __name__ == "__main__":
    main()

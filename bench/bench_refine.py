r"""Bench: the needle refinement, before/after, on the same held-out test split.

One pass over the split runs the ``gdrnet`` estimator without refinement (the "before"
poses: detector + pose head), then the refinement stage (:class:`bopsurg.models.stages.refine.
RefineStage`, re-crops included) on the same image, boxes and poses (the "after" poses;
skipped with ``--segmenter none``), and optionally the stage again with the GT masks as
evidence (``--oracle``: the fit's ceiling; the full or the visible masks, as
``refine.mask`` says). RGB only. Each set is written as a BOP results CSV and scored by
``bopsurg eval``; it prints the paper's table, AR_MSSD / AR_MSPD, the median translation
error per camera axis and the CPU time per 640x480 image (network, refinement).

    python bench/bench_refine.py DATASET [--split test] --out bench/out/refine \
        [--segmenter SEG.pt] [--oracle] [--stride 1] [--from-gt] [--oracle-boxes] \
        [--option refine.fit.prior_weight=0.3] [--option head.zoom=[1]]

``--option`` takes any setting of ``bopsurg predict``'s configuration (dotted keys).

A dataset whose needle model is not the estimator's (an imported ``bopsurg import
ambf-yaml``) is measured in its own frame, as ``bopsurg predict`` maps it
(:mod:`bopsurg.model_frames`): the stages run in the estimator's frame (a GT start mapped
into it) and every pose is mapped back before it is scored.

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
from bopsurg.cli.inputs import key_value
from bopsurg.cli.main import main as bopsurg
from bopsurg.evaluation.summary import format_table
from bopsurg.model_frames import FrameMapping
from bopsurg.models.config_tree import from_mapping
from bopsurg.models.estimator import GdrNetEstimator
from bopsurg.models.pose.roi import crop
from bopsurg.models.predict_config import PredictConfig, weight_file
from bopsurg.models.refine import ArcModel, NeedleRefiner, Segmenter
from bopsurg.models.stages.head import HeadPoses
from bopsurg.models.stages.refine import RefineStage
from bopsurg.options import plugin_options
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


def evaluate(data: Path, split: str, results: Path, out: Path) -> tuple[dict, dict]:
    args = ["-q", "eval", str(data), str(results), "--split", split, "--out", str(out)]
    code = bopsurg([*args, "--metrics", "re,te,mssd,mspd", "--no-progress"])
    if code:
        raise SystemExit(f"bopsurg eval failed with exit code {code}")
    return (
        json.loads((out / "summary.json").read_text()),
        json.loads((out / "scores.json").read_text()),
    )


def parse_args() -> argparse.Namespace:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("dataset", type=Path, help="BOP dataset root with a held-out split")
    ap.add_argument("--split", default="test", help="the split measured (default: test)")
    ap.add_argument("--out", type=Path, required=True, help="output folder")
    ap.add_argument(
        "--segmenter",
        default="shipped",
        help="segmenter checkpoint ('shipped': the one shipped), or 'none' (then only "
        "'before' and '--oracle' are scored)",
    )
    ap.add_argument("--oracle", action="store_true", help="also refine against GT masks")
    ap.add_argument("--stride", type=int, default=1, help="every n-th image (quick looks)")
    ap.add_argument(
        "--from-gt",
        action="store_true",
        help="start the refinement stages from the GT pose instead of the network's; with "
        "--option refine.fit.prior_weight=0 this measures how far the evidence alone moves "
        "a perfect pose (what the fit can pin down at best)",
    )
    ap.add_argument(
        "--oracle-boxes",
        action="store_true",
        help="the GT visible boxes instead of the detector's (the stages measured without "
        "the detector's misses)",
    )
    ap.add_argument(
        "--option",
        type=key_value,
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a setting of the prediction config (repeatable), e.g. --option head.zoom=[1]",
    )
    ap.add_argument("--threads", type=int, default=2)
    return ap.parse_args()


@dataclasses.dataclass
class Setup:
    """The estimator without refinement, the stages to compare, and the dataset's frame."""

    est: GdrNetEstimator
    stages: dict[str, RefineStage]
    mapping: FrameMapping | None
    oracle_mask: str


def setup(args: argparse.Namespace, ds: BopDataset) -> Setup:
    """The network-only estimator, the segmenter's stage ("after") and the GT-mask stage
    ("oracle"), as ``args`` ask."""
    cfg = from_mapping(PredictConfig, plugin_options(None, args.option, {"device": "cpu"}))
    net_only = dataclasses.replace(
        cfg,
        refine=dataclasses.replace(cfg.refine, segmenter=None),
        ends=dataclasses.replace(cfg.ends, classifier=None),
    )
    est = GdrNetEstimator(net_only)
    stages: dict[str, RefineStage] = {}
    seg = None
    if args.segmenter != "none":
        seg = Segmenter(weight_file("segmenter", args.segmenter), est.device, cfg.refine.mask)
        refiner = NeedleRefiner.for_segmenter(seg, cfg.refine.fit, cfg.refine.depth)
        stages["after"] = RefineStage(refiner, cfg.refine.recrop)
    oracle_mask = seg.mask if seg is not None else cfg.refine.mask.replace("auto", "visible")
    mapping = dataset_mappings(ds, est).get(1)  # None: the dataset's needle is the estimator's
    if mapping is None:
        info = ds.models_info[1]["keypoints"]
        arc = ArcModel.from_keypoints(info["tail"], info["tip"])
    elif seg is not None:
        print(mapping.describe())
        arc = seg.arc  # the stages run in the estimator's frame
    else:
        raise SystemExit("a dataset with another needle model needs --segmenter (its arc)")
    if args.oracle:
        oracle = NeedleRefiner(
            gt_mask_evidence(np.zeros((1, 1), bool)),
            arc,
            ORACLE_GRID,
            fit=cfg.refine.fit,
            depth=cfg.refine.depth,
            whole=seg is not None and seg.cfg.frame == "whole",  # framed as the segmenter frames
        )
        stages["oracle"] = RefineStage(oracle, cfg.refine.recrop)
    return Setup(est, stages, mapping, oracle_mask)


Row = tuple[int, int, int, float, np.ndarray, np.ndarray]


def run_split(args: argparse.Namespace, ds: BopDataset, st: Setup) -> tuple[dict, dict, int]:
    """Every image's poses per set ("before" and the stages), the ms each part took, and the
    number of images."""
    rows: dict[str, list[Row]] = {n: [] for n in ["before", *st.stages]}
    ms: dict[str, list[float]] = {n: [] for n in ["net", *st.stages]}
    boxes = gt_detections(ds) if args.oracle_boxes else {}
    keys = [(s, i) for s in ds.scene_ids for i in ds.scene(s).im_ids][:: args.stride]
    for s, i in keys:
        scene = ds.scene(s)
        rgb, K = load_rgb(scene.rgb_path(i)), scene.camera[i].K
        found = boxes.get((s, i)) if args.oracle_boxes else None
        if args.oracle_boxes and found is None:
            continue  # nothing of the needle visible: no box to run on
        t0 = time.perf_counter()
        pred = st.est.predict(rgb, K, boxes=found)
        ms["net"].append(1000 * (time.perf_counter() - t0))
        if len(pred) == 0:
            continue
        poses = {"before": (pred.R, pred.t)}
        poses |= stage_poses(args, st, scene, i, rgb, K, pred, ms)
        for name, (Rn, tn) in poses.items():
            if st.mapping is not None:  # scored in the dataset's frame
                Rn, tn = st.mapping.map_poses(Rn, tn)
            for k in range(len(pred)):
                rows[name].append((s, i, int(pred.obj_id[k]), float(pred.score[k]), Rn[k], tn[k]))
    return rows, ms, len(keys)


def stage_poses(args, st: Setup, scene, i: int, rgb, K, pred, ms) -> dict:
    """The poses of each refinement stage from the network's (or the GT) poses of ``pred``."""
    image = torch.from_numpy(rgb).permute(2, 0, 1)[None].float() / 255
    K_t = torch.as_tensor(K, dtype=torch.float32)
    b = torch.as_tensor(pred.bbox, dtype=torch.float32)
    box = torch.cat([b[:, :2] - 0.5, b[:, 2:]], dim=1)  # as the estimator crops
    R0, t0 = pred.R, pred.t
    if args.from_gt:  # one needle per image: its first GT
        g = scene.gt[i][0]
        R0, t0 = np.repeat(g.R[None], len(pred), 0), np.repeat(g.t[None], len(pred), 0)
        if st.mapping is not None:
            R0, t0 = st.mapping.unmap_poses(R0, t0)
    # re-crops re-run the pose head (not from a GT start)
    head = None if args.from_gt else (lambda g, _rows: st.est.head(image, K_t, g))
    out = {}
    for name, stage in st.stages.items():
        if name == "oracle":
            visible = load_mask(scene.mask_visib_path(i, 0))
            full = load_mask(scene.mask_path(i, 0)) if st.oracle_mask == "full" else None
            stage.refiner.evidence = gt_mask_evidence(visible, full)
        t = time.perf_counter()
        ref = stage(image, K, box, HeadPoses(R0, t0), head=head)
        ms[name].append(1000 * (time.perf_counter() - t))
        out[name] = (ref.R, ref.t)
    return out


def score(args: argparse.Namespace, ds: BopDataset, name: str, r: list[Row]) -> tuple[dict, str]:
    """``bopsurg eval`` of one set: its report entry and its row of the printed table."""
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
    summary, scores = evaluate(args.dataset, args.split, path, args.out / f"eval_{name}")
    axes, depth_bias = axis_medians(ds, est_n, summary["min_visib"])
    print(f"\n== {name} ==\n{format_table(summary, scores)}")
    print("median |dx|, |dy|, |dz| (camera frame, mm): " + ", ".join(f"{v:.2f}" for v in axes))
    print(f"median signed depth error (t_z est - gt) / t_z gt: {100 * depth_bias:+.1f} %")
    tb = summary["table"]
    row = (
        f"| {name} | {tb['re']['median']:.2f} | {tb['te']['median']:.2f} | "
        f"{tb['mssd']['median']:.2f} | {scores['bop19_average_recall_mssd']:.3f} | "
        f"{scores['bop19_average_recall_mspd']:.3f} | "
        + " / ".join(f"{v:.2f}" for v in axes)
        + " |"
    )
    entry = {"summary": summary, "scores": scores, "axes_mm": axes, "depth_bias": depth_bias}
    return entry, row


def main() -> None:
    args = parse_args()
    torch.set_num_threads(args.threads)
    args.out.mkdir(parents=True, exist_ok=True)
    ds = BopDataset(args.dataset, args.split)
    st = setup(args, ds)
    rows, ms, n_images = run_split(args, ds, st)
    report: dict = {"images": n_images, "stride": args.stride, "options": args.option}
    report["config"] = st.est.resolved_config()
    table = []
    for name, r in rows.items():
        report[name], row = score(args, ds, name, r)
        table.append(row)
    for part, values in ms.items():
        if values:
            report[f"{part}_ms"] = {
                "median": float(np.median(values)),
                "p90": float(np.percentile(values, 90)),
            }
    report["stats"] = {n: vars(s.stats) for n, s in st.stages.items()}
    print(
        "\n| | median RE [deg] | median TE [mm] | median MSSD [mm] | AR_MSSD | AR_MSPD "
        "| |dx| / |dy| / |dz| [mm] |"
    )
    print("|---|---|---|---|---|---|---|")
    print("\n".join(table))
    print(f"| paper (GDRNPP) | {PAPER['re']} | {PAPER['te']} | {PAPER['mssd']} | | | |")
    times = ", ".join(
        f"{part} median {v['median']:.1f} ms (p90 {v['p90']:.1f})"
        for part, v in ((p, report.get(f"{p}_ms")) for p in ms)
        if v
    )
    print(f"\nCPU time per 640x480 image ({args.threads} threads): {times}")
    for name, stage in st.stages.items():
        print(f"{name}: {stage.report()}")
    (args.out / "bench_refine.json").write_text(json.dumps(report, indent=2, default=str) + "\n")


if __name__ == "__main__":
    main()

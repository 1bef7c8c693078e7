r"""Bench: the needle-end check (tip/tail) of the gdrnet estimator, at several margins.

The end check (`bopsurg.models.refine.ends`) turns a needle pose end for end when the patch at
its tail looks more like a tip than the patch at its tip, by a margin (logits). A swap that
turns a right pose is a new error of 180 deg; one that turns a flipped pose mends it. This
runs, as a user would:

  1. bopsurg predict DATA --option ends.classifier=none   (the pose without the check)
  2. bopsurg predict DATA --option ends.classifier=CKPT --option ends.margin=M   for each M
  3. bopsurg eval of each

and prints, per run: the paper's medians, the mean RE, the share of needles with RE > 90 deg
(tip and tail swapped), AR_MSSD, and how many poses the check turned: in all, how many of them
it mended (RE > 90 deg before, below after) and how many it broke (below before, above after).
A classifier fit to be on by default breaks none on held-out splits of our renderer at its
margin and mends the flips where they occur (the mirrored split of bench_faces.py, the
paper's AMBF frames of bench_transfer.py: give their folders as DATA).

Step 2 is one pass of the classifier by default: the check is the last stage and changes
nothing but the turned rotations, so the classifier judges each pose of step 1's results
(which hold the poses to the last bit) once, on its decoded image, and each margin's results
follow from that one say (``--predict-each``: a whole predict per margin, as above; needed
where the dataset's needle model is mapped to the estimator's, or a --predict-option sets
``ends.*``). The two agree up to roundoff (the classifier's on a
batch of other poses, predict's own from run to run: on the demo's data, margins 0 and 3,
the same table and turned poses, rotations within 5e-10); a say within roundoff of a margin
may fall the other way.

    python bench/bench_ends.py DATA --split test --ends runs/ends/needle_ends.pt \
        --out runs/bench_ends [--margins 0,1,2,3] [--oracle-boxes] [--predict-option K=V]
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import torch
from benchlib import (
    FLIP_DEG,
    evaluate,
    fresh_dir,
    oracle_boxes,
    predict_eval,
    predict_options,
    split_bench_parser,
    table_needles,
)

from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.images import load_rgb
from bopsurg.bop.results import PoseEstimates, load_results, save_results
from bopsurg.cli.inputs import key_value
from bopsurg.estimation import load_estimator
from bopsurg.models.inference import for_inference
from bopsurg.models.refine.ends import TAIL, TIP, EndJudge, load_judge, swapped
from bopsurg.options import plugin_options
from bopsurg.prediction import dataset_mappings

#: Estimate-row keys that pair the rows of two runs on the same boxes.
KEYS = ("scene_id", "im_id", "obj_id")


def turned(base: PoseEstimates, path: Path) -> np.ndarray:
    """Which estimates of results file ``path`` are those of ``base`` turned by more than
    90 deg (the end check's half turn is 180 deg); the two runs must hold the same rows."""
    other = load_results(path)
    same = len(base) == len(other) and all(
        np.array_equal(getattr(base, k), getattr(other, k)) for k in KEYS
    )
    if not same:
        raise SystemExit(f"{path}: its estimates are not the rows of the run without the check")
    cos = (np.einsum("nij,nij->n", base.R, other.R) - 1.0) / 2.0  # cos of the relative angle
    return cos < np.cos(np.radians(FLIP_DEG))


def end_says(data: Path, split: str, est: PoseEstimates, judge: EndJudge) -> np.ndarray:
    """Per estimate (N,): the classifier's tail logit less its tip logit at the estimate's
    pose (NaN where an end does not project), each image's poses in one pass, on the image
    as ``bopsurg predict`` decodes it."""
    dev = next(judge.net.parameters()).device
    ds = BopDataset(data, split)
    say = np.full(len(est), np.nan)
    keys = np.stack([est.scene_id, est.im_id], 1)
    for scene_id, im_id in np.unique(keys, axis=0).tolist():
        rows = np.flatnonzero((keys[:, 0] == scene_id) & (keys[:, 1] == im_id))
        scene = ds.scene(scene_id)
        rgb = torch.from_numpy(load_rgb(scene.rgb_path(im_id))[None]).to(dev)
        image = rgb.permute(0, 3, 1, 2).float() / 255
        lg = judge.logits(image, scene.camera[im_id].K, est.R[rows], est.t[rows])
        say[rows] = lg[:, TAIL] - lg[:, TIP]
    return say


def one_pass_refused(data: Path, split: str, options: list[str]) -> str | None:
    """Why the margins cannot follow from one pass of the classifier, or None."""
    touched = [o for o in options if o.startswith("ends.")]
    if touched:
        return f"--predict-option {touched[0]} changes the end check"
    # the estimator of the runs (its pose head says which model its poses refer to), without
    # the stages that model does not depend on
    light = {
        "device": "cpu",
        "detector": None,
        "refine": {"segmenter": None},
        "ends": {"classifier": None},
    }
    est = load_estimator("gdrnet", plugin_options(None, map(key_value, options), light))
    if dataset_mappings(BopDataset(data, split), est):
        return "the dataset's needle model is mapped to the estimator's"
    return None


def main() -> None:
    ap = split_bench_parser(__doc__, "BOP dataset root", "pose=runs/pose/pose.pt")
    ap.add_argument("--ends", type=Path, required=True, help="needle_ends.pt checkpoint")
    ap.add_argument("--margins", default="0,1,2,3", help="comma-separated logit margins")
    ap.add_argument(
        "--oracle-boxes", action="store_true", help="the GT visible boxes, not the detector's"
    )
    ap.add_argument(
        "--predict-each", action="store_true",
        help="a whole bopsurg predict per margin (default: one pass of the classifier)",
    )  # fmt: skip
    args = ap.parse_args()
    if not args.ends.is_file():
        raise SystemExit(f"--ends {args.ends}: no such checkpoint")
    try:
        margins = [float(m) for m in args.margins.split(",")]
    except ValueError:
        raise SystemExit(f"--margins {args.margins!r}: give numbers, e.g. 0,1,2,3") from None
    out = fresh_dir(args.out)
    extra = predict_options(args.predict_option)
    if args.oracle_boxes:
        extra += ["--boxes", str(oracle_boxes(args.data, args.split, out / "oracle_boxes.json"))]
    runs = {"ends=none": ["--option", "ends.classifier=none"]}
    for m in margins:
        runs[f"margin {m:g}"] = [
            "--option", f"ends.classifier={args.ends}", "--option", f"ends.margin={m}"
        ]  # fmt: skip

    why = "--predict-each" if args.predict_each else None
    why = why or one_pass_refused(args.data, args.split, args.predict_option)
    report: dict = {
        "data": str(args.data), "split": args.split, "ends": str(args.ends),
        "options": args.predict_option, "oracle_boxes": args.oracle_boxes, "runs": {},
        "margins_by": why or "one pass of the classifier",
    }  # fmt: skip
    base: PoseEstimates | None = None
    head = f"{'':<12}{'N':>5}{'RE med':>8}{'TE med':>8}{'MSSD med':>9}{'RE mean':>8}"
    lines = [f"\n{head}{f'RE>{FLIP_DEG:g}':>8}{'AR_MSSD':>9}{'turned':>8}{'mended':>8}{'broke':>7}"]
    say: np.ndarray | None = None
    for i, (name, opts) in enumerate(runs.items()):
        if i == 0 or why is not None:
            ev, errs, t = predict_eval(
                args.data, args.split, out, str(i), args.device, [*extra, *opts]
            )
        else:  # this margin's results from the classifier's one say per pose
            assert base is not None
            if say is None:
                judge = load_judge(args.ends, torch.device(args.device))
                for_inference(judge.net, torch.device(args.device))
                say = end_says(args.data, args.split, base, judge)
            turn = np.nan_to_num(say, nan=-np.inf) > margins[i - 1]
            R = np.where(turn[:, None, None], swapped(base.R, judge.arc), base.R)
            save_results(out / f"results_{i}.csv", dataclasses.replace(base, R=R))
            ev = evaluate(args.data, out / f"results_{i}.csv", out / f"eval_{i}", split=args.split)
            errs, t = ev.pop("errors"), None
        flip = table_needles(ev, errs).set_index([*KEYS, "gt_id"]).re > FLIP_DEG
        if base is None:  # the run without the check: what the others are compared with
            base, base_flip = load_results(out / "results_0.csv"), flip
            n_turned = mended = broke = 0
        else:
            n_turned = int(turned(base, out / f"results_{i}.csv").sum())
            before = base_flip.reindex(flip.index, fill_value=False)
            mended, broke = int((before & ~flip).sum()), int((~before & flip).sum())
        tab, ar = ev["summary"]["table"], ev["scores"]["bop19_average_recall_mssd"]
        report["runs"][name] = {
            **ev, "flipped": float(flip.mean()), "turned": n_turned, "mended": mended,
            "broke": broke, "predict_s": t,
        }  # fmt: skip
        lines.append(
            f"{name:<12}{tab['te']['n']:>5}{tab['re']['median']:>8.2f}{tab['te']['median']:>8.2f}"
            f"{tab['mssd']['median']:>9.2f}{tab['re']['mean']:>8.2f}{flip.mean():>8.1%}"
            f"{ar:>9.3f}{n_turned:>8}{mended:>8}{broke:>7}"
        )
    print("\n".join(lines))
    print("turned: estimates of all visibilities; mended/broke: needles of the table")
    print("margins: " + (f"a predict each ({why})" if why else "one pass of the classifier"))
    (out / "bench_ends.json").write_text(json.dumps(report, indent=2, default=str) + "\n")


if __name__ == "__main__":
    main()

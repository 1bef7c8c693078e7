"""Bench: a model on both faces of the needle (a split and its mirror image).

A suturing needle's arc looks alike from its two faces with tip and tail swapped; which face
the camera sees is the sign of n.v (arc normal against the line of sight). Recorded episodes
nearly always show one (model card: n.v > 0.5 in 3 of 2,937 training needles) and the
paper's AMBF frames show the other. The mirror image of a held-out split (`bopsurg.mirror`:
columns about c_x, poses R -> F R M, t -> F t) is the same scenes showing the other face, so
this measures what a model does with that face without any data but ours:

  1. mirror DATA's split into OUT/mirrored (masks and gt_info annotated again)
  2. bopsurg predict + bopsurg eval on the split and on its mirror image
  3. print the paper's table for both, the share of needles with RE > 90 deg (tip and tail
     swapped) and what a model that knew both faces would show: the same numbers twice.

    python bench/bench_faces.py DATA --split test --out runs/faces [--predict-option KEY=VALUE]
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

from benchlib import FLIP_DEG, add_predict_option, evaluate, predict_options, run

from bopsurg.mirror import mirror_split


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("data", type=Path, help="BOP dataset root with a held-out split")
    ap.add_argument("--split", default="test")
    ap.add_argument("--out", type=Path, required=True, help="work folder (rewritten)")
    ap.add_argument("--device", default="cpu")
    add_predict_option(ap, "pose=runs/pose/pose.pt")
    args = ap.parse_args()
    out = args.out
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    mirrored = out / "mirrored"
    rep = mirror_split(args.data, mirrored, args.split, progress=False)
    print(f"mirrored {rep.images} images, {rep.instances} instances -> {mirrored}")

    options = predict_options(args.predict_option)
    report: dict = {"data": str(args.data), "split": args.split, "options": args.predict_option}
    faces = (
        ("source", "the split's face", args.data),
        ("mirrored", "the other face (mirrored)", mirrored),
    )
    head = f"{'':<28}{'N':>5}{'RE med':>8}{'TE med':>8}{'MSSD med':>9}{'TE mean':>8}"
    lines = [f"\n{head}{f'RE>{FLIP_DEG:g}':>8}{'AR_MSSD':>9}"]
    for key, label, data in faces:
        results = out / f"results_{key}.csv"
        t = run(
            ["predict", str(data), "--split", args.split, "--out", str(results),
             "--device", args.device, "--no-progress", *options], quiet=True,
        )  # fmt: skip
        ev = evaluate(data, results, out / f"eval_{key}", split=args.split)
        errs = ev.pop("errors")
        kept = errs.visib_fract >= ev["summary"]["min_visib"]  # the GT the table counts
        flipped = float((errs[kept].re > FLIP_DEG).mean())
        report[key] = {**ev, "flipped": flipped, "predict_s": t}
        tab, ar = ev["summary"]["table"], ev["scores"]["bop19_average_recall_mssd"]
        lines.append(
            f"{label:<28}{tab['te']['n']:>5}{tab['re']['median']:>8.2f}{tab['te']['median']:>8.2f}"
            f"{tab['mssd']['median']:>9.2f}{tab['te']['mean']:>8.2f}{flipped:>8.1%}{ar:>9.3f}"
        )
    print("\n".join(lines))
    (out / "bench_faces.json").write_text(json.dumps(report, indent=2, default=str) + "\n")


if __name__ == "__main__":
    main()

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

import json

from benchlib import (
    FLIP_DEG,
    fresh_dir,
    predict_eval,
    predict_options,
    split_bench_parser,
    table_needles,
)

from bopsurg.mirror import mirror_split


def main() -> None:
    ap = split_bench_parser(
        __doc__, "BOP dataset root with a held-out split", "pose=runs/pose/pose.pt"
    )
    args = ap.parse_args()
    out = fresh_dir(args.out)
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
        ev, errs, t = predict_eval(data, args.split, out, key, args.device, options)
        flipped = float((table_needles(ev, errs).re > FLIP_DEG).mean())
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

"""Bench: the needle-end check (tip/tail) of the gdrnet estimator, at several margins.

The end check (`bopsurg.models.refine.ends`) turns a needle pose end for end when the patch at
its tail looks more like a tip than the patch at its tip, by a margin (logits). A swap that
turns a right pose is a new error of 180 deg; one that turns a flipped pose mends it. This
runs, as a user would:

  1. bopsurg predict DATA --option ends=none          (the pose without the check)
  2. bopsurg predict DATA --option ends=CKPT --option ends_margin=M   for each M in --margins
  3. bopsurg eval of each

and prints, per run: the paper's medians, the mean RE, the share of needles with RE > 90 deg
(tip and tail swapped), AR_MSSD, and how many poses the check turned: in all, how many of them
it mended (RE > 90 deg before, below after) and how many it broke (below before, above after).
A classifier fit to be on by default breaks none on held-out splits of our renderer at its
margin and mends the flips where they occur (the mirrored split of bench_faces.py, the
paper's AMBF frames of bench_transfer.py: give their folders as DATA).

    python bench/bench_ends.py DATA --split test --ends runs/ends/needle_ends.pt \
        --out runs/bench_ends [--margins 0,1,2,3] [--oracle-boxes] [--predict-option K=V]
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import numpy as np
from benchlib import FLIP_DEG, add_predict_option, evaluate, oracle_boxes, predict_options, run

from bopsurg.bop.results import load_results

#: Estimate-row keys that pair the rows of two runs on the same boxes.
KEYS = ("scene_id", "im_id", "obj_id")


def turned(a: Path, b: Path) -> np.ndarray:
    """Which estimates of results file ``b`` are those of ``a`` turned by more than 90 deg
    (the end check's half turn is 180 deg); the two runs must hold the same rows."""
    ra, rb = load_results(a), load_results(b)
    same = len(ra) == len(rb) and all(np.array_equal(getattr(ra, k), getattr(rb, k)) for k in KEYS)
    if not same:
        raise SystemExit(f"{b}: its estimates are not the rows of {a}; cannot pair them")
    cos = (np.einsum("nij,nij->n", ra.R, rb.R) - 1.0) / 2.0  # cos of the relative angle
    return cos < np.cos(np.radians(FLIP_DEG))


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("data", type=Path, help="BOP dataset root")
    ap.add_argument("--split", default="test")
    ap.add_argument("--ends", type=Path, required=True, help="needle_ends.pt checkpoint")
    ap.add_argument("--margins", default="0,1,2,3", help="comma-separated logit margins")
    ap.add_argument("--out", type=Path, required=True, help="work folder (rewritten)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument(
        "--oracle-boxes", action="store_true", help="the GT visible boxes, not the detector's"
    )
    add_predict_option(ap, "pose=runs/pose/pose.pt")
    args = ap.parse_args()
    if not args.ends.is_file():
        raise SystemExit(f"--ends {args.ends}: no such checkpoint")
    try:
        margins = [float(m) for m in args.margins.split(",")]
    except ValueError:
        raise SystemExit(f"--margins {args.margins!r}: give numbers, e.g. 0,1,2,3") from None
    out = args.out
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    extra = predict_options(args.predict_option)
    if args.oracle_boxes:
        extra += ["--boxes", str(oracle_boxes(args.data, args.split, out / "oracle_boxes.json"))]
    runs = {"ends=none": ["--option", "ends=none"]}
    for m in margins:
        runs[f"margin {m:g}"] = ["--option", f"ends={args.ends}", "--option", f"ends_margin={m}"]

    report: dict = {
        "data": str(args.data), "split": args.split, "ends": str(args.ends),
        "options": args.predict_option, "oracle_boxes": args.oracle_boxes, "runs": {},
    }  # fmt: skip
    base_flip = None
    head = f"{'':<12}{'N':>5}{'RE med':>8}{'TE med':>8}{'MSSD med':>9}{'RE mean':>8}"
    lines = [f"\n{head}{f'RE>{FLIP_DEG:g}':>8}{'AR_MSSD':>9}{'turned':>8}{'mended':>8}{'broke':>7}"]
    for i, (name, opts) in enumerate(runs.items()):
        results = out / f"results_{i}.csv"
        t = run(
            ["predict", str(args.data), "--split", args.split, "--out", str(results),
             "--device", args.device, "--no-progress", *extra, *opts], quiet=True,
        )  # fmt: skip
        ev = evaluate(args.data, results, out / f"eval_{i}", split=args.split)
        errs = ev.pop("errors")
        kept = errs[(errs.visib_fract >= ev["summary"]["min_visib"]) & (errs.gt_id >= 0)]
        flip = kept.set_index([*KEYS, "gt_id"]).re > FLIP_DEG
        if base_flip is None:
            base_flip, n_turned, mended, broke = flip, 0, 0, 0
        else:
            n_turned = int(turned(out / "results_0.csv", results).sum())
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
    (out / "bench_ends.json").write_text(json.dumps(report, indent=2, default=str) + "\n")


if __name__ == "__main__":
    main()

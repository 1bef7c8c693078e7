"""Bench: the shipped model on frames of the paper's own AMBF pipeline (transfer).

Steps, each a `bopsurg` command as a user of the paper's pipeline would run them:

  1. bopsurg import ambf-yaml SRC --out OUT/data --model SRC/Needle.ply
     (the pipeline's YAML layout: RGB, 1 mm depth, GT poses in the frame of its Needle.ply)
  2. bopsurg predict OUT/data --out OUT/results.csv   (the shipped detector + pose head; its
     poses are mapped from bopsurg's needle frame into Needle.ply's through the fitted arcs)
  3. bopsurg eval OUT/data OUT/results.csv --out OUT/eval

then the same prediction with oracle boxes (the GT visible boxes) instead of the detector's,
to tell detection failures from pose failures. Prints the paper's table for both, the error of
every frame and the camera-to-needle distances, and writes OUT/bench_transfer.json.

    python bench/bench_transfer.py --src /work/shared/data/ambf_scene1 --out runs/transfer

SRC is not part of bopsurg (development data of the team; never train on it).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pandas as pd
from benchlib import (
    add_predict_option,
    fresh_dir,
    oracle_boxes,
    predict_eval,
    predict_options,
    run,
    table_needles,
)

from bopsurg.bop.dataset import BopDataset
from bopsurg.evaluation.summary import format_table

#: The paper's GDRNPP on its own AMBF test set: label, median RE (deg), TE and MSSD (mm).
PAPER_AMBF = ("paper: GDRNPP on its own AMBF test set", 7.74, 1.49, 1.43)
#: The errors of the paper's table (errors.csv columns).
ERRORS = ("re", "te", "mssd")


def _strict_medians(ev: dict, errors: pd.DataFrame) -> dict:
    """Medians of RE, TE and MSSD over every GT needle of the table, a missed one counted as
    an infinite error (the eval's table counts the found ones only), and 'found/all'."""
    found = table_needles(ev, errors)
    n_gt = int(ev["summary"]["gt_instances"])
    misses = np.full(n_gt - len(found), np.inf)
    out = {k: float(np.median(np.r_[found[k].to_numpy(float), misses])) for k in ERRORS}
    return {**out, "found": f"{len(found)}/{n_gt}"}


def import_ambf(src: Path, model: Path, data: Path) -> float:
    """``bopsurg import ambf-yaml`` of SRC into ``data`` (then ``bopsurg check``); returns
    the import's wall time in s."""
    seconds = run(
        ["import", "ambf-yaml", str(src), "--out", str(data), "--model", str(model),
         "--no-progress"]
    )  # fmt: skip
    run(["check", str(data)])
    return seconds


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--src", required=True, help="the AMBF pipeline's YAML-layout folder")
    ap.add_argument("--model", default=None, help="its needle PLY (default: SRC/Needle.ply)")
    ap.add_argument("--out", required=True, help="work folder (rewritten)")
    ap.add_argument("--device", default="cpu")
    add_predict_option(ap, "head.decode=pnp")
    args = ap.parse_args()
    src, out = Path(args.src), Path(args.out)
    model = Path(args.model) if args.model else src / "Needle.ply"
    data = out / "data"
    fresh_dir(out)
    report: dict = {"src": str(src), "model": str(model)}

    report["import_s"] = import_ambf(src, model, data)
    ds = BopDataset(data, "test")
    gts = {(s, i): g for s in ds.scene_ids for i, g in ds.scene(s).gt.items()}
    depth = np.array([g[0].t[2] for g in gts.values()])
    print(f"needle depth t_z: {depth.min():.1f}-{depth.max():.1f} mm over {len(gts)} frames")

    options = predict_options(args.predict_option)
    boxes = oracle_boxes(data, "test", out / "oracle_boxes.json")
    runs = {
        "shipped model": [],
        "shipped pose head on oracle GT visible boxes": ["--boxes", str(boxes)],
    }
    for i, (name, extra) in enumerate(runs.items()):
        ev, errs, t = predict_eval(data, "test", out, str(i), args.device, [*options, *extra])
        report[name] = {**ev, "predict_s": t, "strict": _strict_medians(ev, errs)}
        print(f"\n== {name} ==\n{format_table(ev['summary'], ev['scores'])}")
        print(f"\n{'frame':>6}{'t_z mm':>9}{'RE deg':>9}{'TE mm':>8}{'MSSD mm':>9}")
        for _, row in errs.sort_values("im_id").iterrows():
            z = gts[(int(row.scene_id), int(row.im_id))][0].t[2]
            print(f"{int(row.im_id):>6}{z:>9.1f}{row.re:>9.2f}{row.te:>8.2f}{row.mssd:>9.2f}")
    print(f"\n{'':<46}{'med RE':>8}{'med TE':>8}{'med MSSD':>9}{'AR_MSSD':>9}{'found':>7}")
    for name in runs:
        t, sc = report[name]["summary"]["table"], report[name]["scores"]
        print(
            f"{name:<46}{t['re']['median']:>8.2f}{t['te']['median']:>8.2f}"
            f"{t['mssd']['median']:>9.2f}{sc['bop19_average_recall_mssd']:>9.3f}"
            f"{report[name]['strict']['found']:>7}"
        )
        if report[name]["summary"]["missed"]:
            m = report[name]["strict"]
            label = "  the same, a missed needle counted as failed"
            print(f"{label:<46}{m['re']:>8.2f}{m['te']:>8.2f}{m['mssd']:>9.2f}")
    print(f"{PAPER_AMBF[0]:<46}{PAPER_AMBF[1]:>8.2f}{PAPER_AMBF[2]:>8.2f}{PAPER_AMBF[3]:>9.2f}")
    (out / "bench_transfer.json").write_text(json.dumps(report, indent=2, default=str) + "\n")


if __name__ == "__main__":
    main()

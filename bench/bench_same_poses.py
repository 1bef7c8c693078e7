"""Bench: are two results files the same poses? (a refactor against the code before it)

Pairs the estimates of two BOP19 results CSVs in file order (their scene_id, im_id and obj_id
must agree) and prints how many there are, how many differ at all, the largest element-wise
differences of R and t (mm) and the largest rotation angle between paired poses (deg); then
the median angle and translation between them and how many turned by over 1 and 90 deg (how
far a setting moves the poses, e.g. fewer fit iterations against the default).

    python bench/bench_same_poses.py OLD.csv NEW.csv
"""

from __future__ import annotations

import argparse

import numpy as np

from bopsurg import metrics
from bopsurg.bop.results import load_results


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("a", help="results CSV (e.g. the code before)")
    ap.add_argument("b", help="results CSV (e.g. the code after)")
    args = ap.parse_args()
    a, b = load_results(args.a), load_results(args.b)
    keys_a = list(zip(a.scene_id.tolist(), a.im_id.tolist(), a.obj_id.tolist(), strict=True))
    keys_b = list(zip(b.scene_id.tolist(), b.im_id.tolist(), b.obj_id.tolist(), strict=True))
    if keys_a != keys_b:
        raise SystemExit(f"{args.a} and {args.b} hold estimates of different images or objects")
    d_R = np.abs(a.R - b.R).max(axis=(1, 2))
    d_t = np.abs(a.t - b.t).max(axis=1)
    changed = (d_R > 0) | (d_t > 0)
    angle = metrics.re(a.R, b.R) if len(a) else np.zeros(0)
    shift = np.linalg.norm(a.t - b.t, axis=1)
    print(
        f"{len(a)} paired estimates, {int(changed.sum())} differ; "
        f"max |dR| {d_R.max(initial=0.0):.3g}, max |dt| {d_t.max(initial=0.0):.3g} mm, "
        f"max angle {angle.max(initial=0.0):.3g} deg"
    )
    if len(a):  # how far a setting moves poses (e.g. fewer iterations against more)
        print(
            f"median angle {np.median(angle):.3g} deg, median |t_a - t_b| "
            f"{np.median(shift):.3g} mm; over 1 deg: {int((angle > 1).sum())}, over 90 deg: "
            f"{int((angle > 90).sum())}"
        )


if __name__ == "__main__":
    main()

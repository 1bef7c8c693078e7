"""Bench: which views of the needle a split holds, to compare training data with a target.

A circle's image leaves its tilt two-fold ambiguous (the plane tilted towards or away from
the camera projects to the same ellipse): a pose head settles it from appearance it learned
on the views it was trained on. For every GT needle of each split (visib_fract >= 0.3) this
prints the view angle (0 = edge-on, 90 = face-on, as ``bopsurg eval``'s ``view_angle_deg``)
and the image direction of the plane normal's camera-facing side, in eight 45° sectors
(0° = image +x, 90° = image down): the two tilts differ by 180° there. A sector that a target
split fills and the training splits leave empty is a view the head has never seen.

    python bench/bench_viewpoints.py DATA:SPLIT [DATA:SPLIT ...] [--every 5]

e.g. ``data:train_def5 data:train_orbit ambf:test`` (an imported ``bopsurg import
ambf-yaml`` dataset is a split like any other).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd

from bopsurg.bop.dataset import BopDataset
from bopsurg.evaluation.ambiguity import view_angle_deg

#: Needles the paper's table counts.
MIN_VISIB = 0.3
SECTORS = 8


def views(data: Path, split: str, every: int, obj_id: int = 1) -> pd.DataFrame:
    """View angle and the camera-facing normal's image direction (deg) of every ``every``-th
    scene's GT needles with visib_fract >= :data:`MIN_VISIB`."""
    ds = BopDataset(data, split)
    normal = np.asarray(ds.models_info[obj_id].get("plane_normal", (0.0, 0.0, 1.0)), float)
    R, t = [], []
    for scene_id in ds.scene_ids[::every]:
        scene = ds.scene(scene_id)
        info = scene.gt_info or {}
        for im_id, poses in scene.gt.items():
            for k, g in enumerate(poses):
                visib = info[im_id][k].visib_fract if im_id in info else 1.0
                if g.obj_id == obj_id and visib >= MIN_VISIB:
                    R.append(g.R)
                    t.append(g.t)
    if not R:
        return pd.DataFrame({"view_deg": [], "direction_deg": []})
    Rs, ts = np.array(R), np.array(t)
    n = np.einsum("nij,j->ni", Rs, normal)
    n *= -np.sign(np.einsum("ni,ni->n", n, ts))[:, None]  # the side that faces the camera
    return pd.DataFrame(
        {
            "view_deg": view_angle_deg(Rs, ts, normal),
            "direction_deg": np.degrees(np.arctan2(n[:, 1], n[:, 0])) % 360.0,
        }
    )


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("splits", nargs="+", help="DATA:SPLIT, e.g. data:train_def5")
    ap.add_argument("--every", type=int, default=5, help="every n-th scene (1: all)")
    args = ap.parse_args()
    edges = np.arange(SECTORS + 1) * 360.0 / SECTORS
    rows = {}
    for spec in args.splits:
        data, _, split = spec.rpartition(":")
        v = views(Path(data), split, args.every)
        share = np.histogram(v.direction_deg, bins=edges)[0] / max(len(v), 1)
        rows[spec] = {
            "N": len(v),
            "view p25": v.view_deg.quantile(0.25),
            "view med": v.view_deg.median(),
            "view p75": v.view_deg.quantile(0.75),
            **{
                f"{int(a)}-{int(b)}": s
                for a, b, s in zip(edges[:-1], edges[1:], share, strict=True)
            },
        }
    table = pd.DataFrame(rows).T
    table["N"] = table["N"].astype(int)
    print("view angle (deg, 0 = edge-on) and share of needles whose camera-facing normal points")
    print("into each image sector (deg, 0 = image +x, 90 = image down):\n")
    print(table.to_string(float_format=lambda x: f"{x:.2f}"))


if __name__ == "__main__":
    main()

"""BOP19's valid GTs and kept pairs in plain numpy equal the pandas implementation they
replaced (kept here, verbatim in substance, as the reference), on seeded random cases with
duplicate targets, estimates outside the targets, score ties, several instances per object
and missing visibilities."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from bopsurg.bop.results import PoseEstimates
from bopsurg.bop.targets import Target
from bopsurg.evaluation.bop19_pairs import TargetTable, kept_pairs, kept_pairs_of_targets, valid_gts
from bopsurg.evaluation.matching import valid_gts_localization
from bopsurg.evaluation.pair_errors import candidate_pairs
from bopsurg.evaluation.tables import GtTable, estimates_frame, rank_within_groups


def _pandas_targets(targets):
    return pd.DataFrame(
        {
            "scene_id": [t.scene_id for t in targets],
            "im_id": [t.im_id for t in targets],
            "obj_id": [t.obj_id for t in targets],
            "inst_count": [t.inst_count for t in targets],
        },
        dtype=np.int64,
    ).drop_duplicates(["scene_id", "im_id", "obj_id"], keep="last")


def _pandas_valid_gts(gt, tdf):
    gdf = gt.frame().merge(tdf, on=["scene_id", "im_id", "obj_id"], how="left")
    gdf = gdf.sort_values("g").reset_index(drop=True)
    inst = gdf["inst_count"].fillna(0).to_numpy(dtype=np.int64)
    grp = gdf.groupby(["scene_id", "im_id", "obj_id"], sort=False).ngroup().to_numpy()
    return valid_gts_localization(grp, gt.visib_fract, inst)


def _pandas_kept_pairs(est, gt, tdf):
    est_df = estimates_frame(est).merge(tdf, on=["scene_id", "im_id", "obj_id"], how="inner")
    est_df = est_df.sort_values("e").reset_index(drop=True)
    rank, _ = rank_within_groups(
        est_df[["scene_id", "im_id", "obj_id"]], est_df["score"].to_numpy()
    )
    est_df["rank"] = rank
    est_df = est_df[est_df["rank"] < est_df["inst_count"]]
    pairs_df = candidate_pairs(est_df.drop(columns="inst_count"), gt)
    return (
        pairs_df["rank"].to_numpy(np.int64),
        pairs_df["e"].to_numpy(np.int64),
        pairs_df["g"].to_numpy(np.int64),
    )


def _case(seed):
    """GT of a few scenes/images/objects (1-3 instances each), estimates with tied scores,
    targets with duplicates, missing triples and triples without GT."""
    rng = np.random.default_rng(seed)
    rows = []
    for scene in (1, 2, 7):
        for im in rng.choice(50, size=rng.integers(1, 6), replace=False):
            gt_id = 0
            for obj in rng.choice([1, 2, 5], size=rng.integers(1, 4), replace=False):
                for _ in range(rng.integers(1, 4)):
                    rows.append((scene, int(im), gt_id, int(obj)))
                    gt_id += 1
    order = rng.permutation(len(rows))  # the table's row order is not the triples' order
    ids = np.array(rows, dtype=np.int64)[order]
    g = len(ids)
    visib = rng.choice([0.1, 0.5, 0.9, np.nan], size=g)
    gt = GtTable(
        scene_id=ids[:, 0], im_id=ids[:, 1], gt_id=ids[:, 2], obj_id=ids[:, 3],
        R=np.tile(np.eye(3), (g, 1, 1)), t=np.zeros((g, 3)),
        K=np.tile(np.eye(3), (g, 1, 1)), visib_fract=visib,
        im_width=np.full(g, 640, dtype=np.int64), images=frozenset(),
    )  # fmt: skip
    n = 3 * g
    pick = rng.integers(0, g, size=n)
    other_obj = rng.random(n) < 0.1  # an object without GT in that image
    est = PoseEstimates(
        scene_id=ids[pick, 0], im_id=ids[pick, 1],
        obj_id=np.where(other_obj, 9, ids[pick, 3]),
        score=rng.choice([0.2, 0.5, 0.7], size=n), R=np.tile(np.eye(3), (n, 1, 1)),
        t=np.zeros((n, 3)), time=np.full(n, -1.0), line=np.full(n, -1, dtype=np.int64),
    )  # fmt: skip
    targets = []
    for s, i, _, o in rows:
        if rng.random() < 0.8:
            targets.append(Target(s, i, o, int(rng.integers(0, 4))))
    targets += [Target(s, i, o, int(rng.integers(1, 3))) for s, i, o in
                {(t.scene_id, t.im_id, t.obj_id) for t in targets[::3]}]  # fmt: skip
    targets.append(Target(3, 0, 1, 1))  # a target without GT or estimates
    return est, gt, [targets[k] for k in rng.permutation(len(targets))]


@pytest.mark.parametrize("seed", range(12))
def test_numpy_kept_pairs_and_valid_gts_equal_the_pandas_ones(seed):
    est, gt, targets = _case(seed)
    tdf = _pandas_targets(targets)
    table = TargetTable.of(targets)
    want_rank, want_e, want_g = _pandas_kept_pairs(est, gt, tdf)
    got = kept_pairs(est, gt, table)
    assert want_e.size > 0  # the case exercises what it claims to
    np.testing.assert_array_equal(got.est_rank, want_rank)
    np.testing.assert_array_equal(got.est_index, want_e)
    np.testing.assert_array_equal(got.gt_index, want_g)
    want_valid = _pandas_valid_gts(gt, tdf)
    assert 0 < want_valid.sum() < len(gt)
    np.testing.assert_array_equal(valid_gts(gt, table), want_valid)
    kept = kept_pairs_of_targets(est, gt, targets, lambda obj: obj * 10.0)
    np.testing.assert_array_equal(kept.diameter, gt.obj_id[want_g] * 10.0)


def test_no_targets_no_pairs():
    est, gt, _ = _case(0)
    kept = kept_pairs_of_targets(est, gt, [], lambda obj: obj * 1.0)
    assert kept.pairs.est_index.size == 0
    assert not kept.valid.any()

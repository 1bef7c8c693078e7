"""The numpy tables of the evaluation (bopsurg.evaluation.columns) against what pandas does
with the same rows: the CSV text byte for byte, groups, lookups and joins (seeded cases)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from bopsurg.evaluation.columns import (
    csv_text,
    group_labels,
    join_pairs,
    match_rows,
    pick,
    take,
)


def _floats(rng: np.random.Generator, n: int) -> np.ndarray:
    x = rng.normal(0, 10.0 ** rng.integers(-12, 12, n), n)
    special = rng.integers(0, 8, n)
    x[special == 0] = np.nan
    x[special == 1] = np.inf
    x[special == 2] = -np.inf
    x[special == 3] = -0.0
    x[special == 4] = np.round(x[special == 4])  # whole numbers: "3", not "3.0"
    return x


@pytest.mark.parametrize("seed", range(20))
def test_csv_text_is_what_pandas_writes(seed, tmp_path):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(0, 40))
    cols = {
        "scene_id": rng.integers(0, 3, n),
        "gt_id": rng.integers(-1, 2**40, n),
        "score": _floats(rng, n),
        "re": _floats(rng, n),
        "tip_visible": rng.choice([0.0, 1.0, np.nan], n),
    }
    path = tmp_path / "errors.csv"
    pd.DataFrame(cols).to_csv(path, index=False, float_format="%.9g")
    assert csv_text(cols, float_format="%.9g") == path.read_text()


@pytest.mark.parametrize("seed", range(10))
def test_groups_lookups_and_joins_are_pandas(seed):
    rng = np.random.default_rng(seed)
    n, m = int(rng.integers(0, 60)), int(rng.integers(0, 30))
    left = {"s": rng.integers(0, 3, n), "i": rng.integers(0, 4, n), "e": np.arange(n)}
    right_all = {"s": rng.integers(0, 3, m), "i": rng.integers(0, 4, m), "k": rng.permutation(m)}
    ldf, rdf = pd.DataFrame(left), pd.DataFrame(right_all)

    expected = ldf.groupby(["s", "i"], sort=True).ngroup().to_numpy()
    np.testing.assert_array_equal(group_labels(left["s"], left["i"]), expected)

    pairs = ldf.merge(rdf.assign(r=np.arange(m)), on=["s", "i"], how="inner")
    pairs = pairs.sort_values(["e", "k"], kind="stable")
    li, ri = join_pairs((left["s"], left["i"]), (right_all["s"], right_all["i"]), right_all["k"])
    np.testing.assert_array_equal(li, pairs["e"].to_numpy())
    np.testing.assert_array_equal(ri, pairs["r"].to_numpy())

    distinct = rdf.drop_duplicates(["s", "i"]).reset_index(drop=True)
    right = {c: distinct[c].to_numpy() for c in distinct.columns}
    found = match_rows((left["s"], left["i"]), (right["s"], right["i"]))
    merged = ldf.merge(distinct.assign(r=np.arange(len(distinct))), on=["s", "i"], how="left")
    np.testing.assert_array_equal(found, merged["r"].fillna(-1).to_numpy(np.int64))
    values = rng.normal(size=len(distinct))
    np.testing.assert_array_equal(
        pick(values, found), merged["r"].map(dict(enumerate(values))).to_numpy(np.float64)
    )
    assert take(left, left["s"] == 1)["e"].tolist() == ldf.loc[ldf["s"] == 1, "e"].tolist()


def test_pick_of_nothing_is_the_fill():
    assert np.isnan(pick(np.zeros(0), np.array([-1, -1]))).all()

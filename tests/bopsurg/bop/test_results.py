"""BOP19 results CSV: round trips, the reference layout, and one test per kind of bad input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bopsurg.bop import (
    PoseEstimates,
    average_time_per_image,
    check_results_against_dataset,
    load_results,
    save_results,
)
from bopsurg.bop.results import HEADER
from bopsurg.errors import ResultsError, ShapeError

R_ID = "1 0 0 0 1 0 0 0 1"
GOOD = [
    f"1,0,5,0.9,{R_ID},10 20 500,0.25",
    f"1,0,6,0.5,{R_ID},0 0 400,0.25",
    f"1,3,5,0.7,{R_ID},1.5 -2 300,0.5",
]


def write(tmp_path: Path, lines: list[str], *, header: bool = True, end: str = "\n") -> Path:
    path = tmp_path / "method_lmo-test.csv"
    rows = ([HEADER] if header else []) + lines
    path.write_bytes((end.join(rows) + end).encode())
    return path


def random_estimates(n: int, seed: int = 0) -> PoseEstimates:
    rng = np.random.default_rng(seed)
    im = np.arange(n) // 10
    return PoseEstimates.from_arrays(
        scene_id=im // 100,
        im_id=im % 100,
        obj_id=rng.integers(1, 20, n),
        score=rng.random(n),
        R=Rotation.random(n, random_state=seed).as_matrix(),
        t=rng.normal(size=(n, 3)) * 100,
        time=im * 0.01 + 0.5,
    )


def test_save_matches_reference_layout(tmp_path: Path) -> None:
    est = PoseEstimates.from_arrays(
        [1, 1],
        [0, 3],
        [5, 6],
        [0.9, 1.0],
        [np.eye(3)] * 2,
        [[10, 20, 500.5], [0, 0, 1]],
        [0.25, -1],
    )
    path = tmp_path / "r.csv"
    save_results(path, est)
    eye = "1.0 0.0 0.0 0.0 1.0 0.0 0.0 0.0 1.0"
    assert path.read_text() == (
        f"{HEADER}\n1,0,5,0.9,{eye},10.0 20.0 500.5,0.25\n1,3,6,1.0,{eye},0.0 0.0 1.0,-1"
    )
    save_results(path, est, time=-1)  # time unknown: written as the reference's default -1
    assert [x.rsplit(",", 1)[1] for x in path.read_text().splitlines()[1:]] == ["-1", "-1"]


def test_round_trip_is_exact(tmp_path: Path) -> None:
    est = random_estimates(200)
    save_results(tmp_path / "r.csv", est)
    back = load_results(tmp_path / "r.csv")
    for name in ("scene_id", "im_id", "obj_id", "score", "R", "t", "time"):
        np.testing.assert_array_equal(getattr(back, name), getattr(est, name))
    np.testing.assert_array_equal(back.line, np.arange(2, 202))
    assert len(back) == 200


@pytest.mark.parametrize("end", ["\n", "\r\n"])
@pytest.mark.parametrize("trailing", [True, False])
@pytest.mark.parametrize("header", [True, False])
def test_line_endings_and_header(tmp_path: Path, end: str, trailing: bool, header: bool) -> None:
    path = write(tmp_path, GOOD, header=header, end=end)
    if not trailing:
        path.write_bytes(path.read_bytes()[: -len(end)])
    est = load_results(path)
    assert len(est) == 3
    np.testing.assert_array_equal(est.obj_id, [5, 6, 5])
    np.testing.assert_array_equal(est.t[2], [1.5, -2, 300])
    np.testing.assert_array_equal(est.line, np.arange(3) + (2 if header else 1))
    np.testing.assert_array_equal(est.R[0], np.eye(3))


def test_average_time_per_image() -> None:
    est = PoseEstimates.from_arrays(
        [1, 1, 1],
        [0, 0, 3],
        [5, 6, 5],
        [1, 1, 1],
        [np.eye(3)] * 3,
        np.zeros((3, 3)),
        [0.2, 0.2, 0.5],
    )
    assert average_time_per_image(est) == pytest.approx(0.35)
    unknown = PoseEstimates.from_arrays([1], [0], [5], [1], [np.eye(3)], [[0, 0, 0]])
    assert average_time_per_image(unknown) == -1


def test_dataframe_and_subset() -> None:
    est = random_estimates(20)
    df = est.to_dataframe()
    assert list(df.columns[:4]) == ["scene_id", "im_id", "obj_id", "score"]
    np.testing.assert_array_equal(df[[f"R{k}" for k in range(9)]].to_numpy(), est.R.reshape(-1, 9))
    np.testing.assert_array_equal(df[["t0", "t1", "t2"]].to_numpy(), est.t)
    sub = est.subset(est.obj_id == est.obj_id[0])
    assert len(sub) == int(np.sum(est.obj_id == est.obj_id[0]))


def test_from_arrays_validates_shapes() -> None:
    with pytest.raises(ShapeError, match="length"):
        PoseEstimates.from_arrays([1, 2], [0], [5, 5], [1, 1], [np.eye(3)] * 2, np.zeros((2, 3)))
    with pytest.raises(ShapeError, match="shape"):
        PoseEstimates.from_arrays([1], [0], [5], [1], np.eye(2)[None], np.zeros((1, 3)))
    with pytest.raises(ShapeError, match="NaN"):
        PoseEstimates.from_arrays([1], [0], [5], [np.nan], [np.eye(3)], np.zeros((1, 3)))
    est = PoseEstimates.from_arrays(
        [1], [0], [5], [1], np.eye(3).reshape(1, 9), np.zeros((1, 3, 1))
    )
    assert est.R.shape == (1, 3, 3)
    assert est.line.tolist() == [-1]


BAD = [
    # (name, bad line, field, reason)
    ("columns", f"1,0,5,0.9,{R_ID},0 0 1", None, "expected 7 comma-separated fields"),
    ("columns_extra", f"1,0,5,0.9,{R_ID},0 0 1,0.25,7", None, "got 8"),
    ("non_numeric", f"1,zero,5,0.9,{R_ID},0 0 1,0.25", "im_id", "expected an integer, got 'zero'"),
    ("non_numeric_score", f"1,0,5,high,{R_ID},0 0 1,0.25", "score", "expected a number"),
    ("non_numeric_t", f"1,0,5,0.9,{R_ID},0 x 1,0.25", "t", "expected a number, got 'x'"),
    ("nan", f"1,0,5,nan,{R_ID},0 0 1,0.25", "score", "NaN or inf"),
    ("inf", f"1,0,5,0.9,{R_ID},0 0 inf,0.25", "t", "NaN or inf"),
    ("not_rotation", "1,0,5,0.9,1 0 0 0 2 0 0 0 1,0 0 1,0.25", "R", "not a rotation matrix"),
    ("R_8", "1,0,5,0.9,1 0 0 0 1 0 0 0,0 0 1,0.25", "R", "expected 9 numbers"),
    ("t_4", f"1,0,5,0.9,{R_ID},0 0 1 1,0.25", "t", "expected 3 numbers"),
    ("negative_id", f"1,0,-5,0.9,{R_ID},0 0 1,0.25", "obj_id", "non-negative"),
    ("empty_line", "", None, "empty line"),
]


@pytest.mark.parametrize(("name", "line", "field", "reason"), BAD, ids=[b[0] for b in BAD])
def test_bad_line(tmp_path: Path, name: str, line: str, field: str | None, reason: str) -> None:
    # The bad line is the 3rd estimate: line 4 of the file (the header is line 1).
    path = write(tmp_path, [GOOD[0], GOOD[1], line, GOOD[2]])
    with pytest.raises(ResultsError, match=reason) as e:
        load_results(path)
    assert e.value.line == 4
    assert e.value.field == field
    prefix = f"{path}:4: {field}: " if field else f"{path}:4: "
    assert str(e.value).startswith(prefix)
    assert "\n" not in str(e.value)


def test_rotation_message_says_deviation(tmp_path: Path) -> None:
    path = write(tmp_path, [GOOD[0], "1,0,5,0.9,1 0 0 0 1 0 0 0 1.01,0 0 1,0.25"])
    with pytest.raises(ResultsError, match=r"max \|R\^T R - I\| = 0.0201") as e:
        load_results(path)
    assert e.value.line == 3


def test_inconsistent_times(tmp_path: Path) -> None:
    lines = [GOOD[0], GOOD[2], f"1,0,7,0.5,{R_ID},0 0 400,0.2515"]
    path = write(tmp_path, [*lines, f"1,0,8,0.5,{R_ID},0 0 400,0.2505"])
    with pytest.raises(ResultsError, match=r"differs from 0\.25 s on line 2") as e:
        load_results(path)
    assert (e.value.line, e.value.field) == (4, "time")
    # Within 0.001 s of the image's first estimate is fine (the reference's check).
    path = write(tmp_path, [GOOD[0], GOOD[2], f"1,0,7,0.5,{R_ID},0 0 400,0.2509"])
    assert len(load_results(path)) == 3


def test_header_hint_on_bad_first_line(tmp_path: Path) -> None:
    path = tmp_path / "r.csv"
    path.write_text("scene,im,obj,score,R,t,time\n" + GOOD[0])
    with pytest.raises(ResultsError, match="header line must contain exactly") as e:
        load_results(path)
    assert (e.value.line, e.value.field) == (1, "scene_id")


def test_empty_header_only_and_missing(tmp_path: Path) -> None:
    path = tmp_path / "r.csv"
    path.write_text("")
    with pytest.raises(ResultsError, match="no estimates") as e:
        load_results(path)
    assert str(e.value).startswith(str(path))
    path.write_text(HEADER + "\n")
    with pytest.raises(ResultsError, match=r"no estimates.*only the header") as e:
        load_results(path)
    assert str(e.value).startswith(str(path))
    with pytest.raises(ResultsError, match="file not found") as e:
        load_results(tmp_path / "none.csv")
    assert str(tmp_path / "none.csv") in str(e.value)


def test_unknown_obj_id_and_image(tmp_path: Path) -> None:
    path = write(tmp_path, GOOD)
    est = load_results(path)
    images = {(1, 0), (1, 3)}
    check_results_against_dataset(est, path, images=images, obj_ids={5, 6})
    with pytest.raises(ResultsError, match="unknown obj_id 6") as e:
        check_results_against_dataset(est, path, images=images, obj_ids={5})
    assert (e.value.line, e.value.field) == (3, "obj_id")
    assert str(e.value).startswith(f"{path}:3: obj_id: ")
    with pytest.raises(ResultsError, match="image 3 of scene 1 is not in the dataset") as e:
        check_results_against_dataset(est, path, images={(1, 0)}, obj_ids={5, 6})
    assert (e.value.line, e.value.field) == (4, "im_id")
    with pytest.raises(ResultsError, match="scene 1 is not in the dataset split") as e:
        check_results_against_dataset(est, path, images={(2, 0)}, obj_ids={5, 6})
    assert (e.value.line, e.value.field) == (2, "scene_id")


def test_100k_rows(tmp_path: Path) -> None:
    est = random_estimates(100_000)
    path = tmp_path / "big.csv"
    save_results(path, est)
    back = load_results(path)
    assert len(back) == 100_000
    np.testing.assert_array_equal(back.R, est.R)
    assert back.line[-1] == 100_001


def test_bad_line_in_large_file_is_located(tmp_path: Path) -> None:
    est = random_estimates(20_000)  # more than one parsing chunk
    path = tmp_path / "big.csv"
    save_results(path, est)
    lines = path.read_text().split("\n")
    lines[18_000] = lines[18_000].replace(",", ";", 1)
    path.write_text("\n".join(lines))
    with pytest.raises(ResultsError, match="got 6") as e:
        load_results(path)
    assert e.value.line == 18_001

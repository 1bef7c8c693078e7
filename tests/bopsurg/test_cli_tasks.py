"""``bopsurg eval --task``: every task alone and combined, on a pose CSV and on a COCO results
JSON, plain or gzip-compressed (``.json.gz``, as BOP challenge submissions ship)."""

from __future__ import annotations

import gzip
import json
import shutil

import numpy as np
import pytest

from bopsurg.bop.detections import save_detections
from bopsurg.bop.images import load_mask
from bopsurg.bop.jsonio import save_json
from bopsurg.cli.main import main
from bopsurg.estimation import Detections
from bopsurg.evaluation.coco_eval import is_coco_results
from bopsurg.example import ExampleSpec, write_example_dataset

BOP19_KEY = "bop19_average_recall_mssd"
BOP24_KEY = "bop24_mAP"


@pytest.fixture(scope="module")
def example(tmp_path_factory):
    return write_example_dataset(
        tmp_path_factory.mktemp("tasks"), ExampleSpec(seed=3, scenes=1, images_per_scene=5)
    )


def _eval(example, out, *extra: str) -> int:
    args = ["eval", str(example.root), str(example.results), "--out", str(out)]
    return main([*args, "--bootstrap", "20", "--renderer", "none", *extra])


@pytest.mark.parametrize(
    ("task", "bop19", "bop24"),
    [
        ("bop19", True, False),
        ("bop24", False, True),
        ("all", True, True),
        ("bop19,bop24", True, True),
        ("bop24,bop19", True, True),
        (" bop24 , bop24 ", False, True),
    ],
)
def test_every_pose_task_alone_and_combined(example, tmp_path, capsys, task, bop19, bop24):
    out = tmp_path / "out"
    assert _eval(example, out, "--task", task) == 0
    printed = capsys.readouterr()
    assert "Traceback" not in printed.err
    scores = json.loads((out / "scores.json").read_text())
    assert (BOP19_KEY in scores) is bop19
    assert (BOP24_KEY in scores) is bop24
    # the intervals cover exactly the scores that were computed
    assert (BOP19_KEY in scores["ci95"]) is bop19
    assert (BOP24_KEY in scores["ci95"]) is bop24
    assert (BOP19_KEY in printed.out) is bop19
    assert (out / "bootstrap_bop19.npz").is_file() is bop19
    assert (out / "bootstrap_bop24.npz").is_file() is bop24
    assert (out / "errors.csv").is_file()  # the paper's table whatever the task


def test_a_task_run_leaves_no_samples_of_an_earlier_run(example, tmp_path):
    out = tmp_path / "out"
    assert _eval(example, out, "--task", "all") == 0
    assert (out / "bootstrap_bop24.npz").is_file()
    assert _eval(example, out, "--task", "bop19") == 0
    assert not (out / "bootstrap_bop24.npz").exists()  # compare would read stale rankings
    assert _eval(example, out, "--task", "bop24") == 0
    assert not (out / "bootstrap_bop19.npz").exists()


@pytest.mark.parametrize("task", ["coco-bbox", "coco-segm", "coco-bbox,bop19"])
def test_a_task_the_pose_results_do_not_allow_is_one_line_exit_2(example, tmp_path, capsys, task):
    assert _eval(example, tmp_path / "out", "--task", task) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "Traceback" not in err
    assert "needs other results" in err


def test_an_unknown_task_is_a_usage_error(example, tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        _eval(example, tmp_path / "out", "--task", "bop19,bogus")
    assert exc.value.code == 2
    assert "unknown task(s) 'bogus'" in capsys.readouterr().err


def test_detections_of_the_rerun_option_may_be_gzip_compressed(example, tmp_path):
    boxes = {(1, 0): Detections(np.array([1]), np.array([0.9]), np.array([[10.0, 10, 20, 20]]))}
    for name in ("det.json", "det.json.gz"):
        save_detections(tmp_path / name, boxes)
        assert (
            _eval(example, tmp_path / name.replace(".", "_"), "--detections", str(tmp_path / name))
            == 0
        )
    assert (tmp_path / "det.json.gz").read_bytes()[:2] == b"\x1f\x8b"


# --- a BOP COCO results JSON: the 2D tasks -------------------------------------------------


@pytest.fixture
def squares(tmp_path):
    """Two annotated squares (scene_gt_coco.json) and a detector's boxes and masks for them."""
    pytest.importorskip("pycocotools")
    from bopsurg.bop.coco import mask_to_rle
    from tests.bopsurg.bop.test_coco import _two_squares

    sdir = _two_squares(tmp_path / "data")
    masks = [load_mask(sdir / "mask_visib" / f"000000_00000{k}.png") for k in (0, 1)]
    boxes = ([25, 19, 10, 10], [30, 19, 10, 10])
    results = [
        {"scene_id": 1, "image_id": 0, "category_id": 1, "score": s, "bbox": b, "time": 0.5,
         "segmentation": mask_to_rle(m)}
        for s, b, m in zip((0.9, 0.8), boxes, masks, strict=True)
    ]  # fmt: skip
    return tmp_path / "data", results


@pytest.mark.parametrize("suffix", [".json", ".json.gz"])
@pytest.mark.parametrize(
    ("task", "bbox", "segm"),
    [
        ("coco-bbox", True, False),
        ("coco-segm", False, True),
        ("coco-bbox,coco-segm", True, True),
        ("all", True, True),
    ],
)
def test_every_coco_task_on_plain_and_gzip_results(squares, tmp_path, suffix, task, bbox, segm):
    root, results = squares
    path = tmp_path / f"results{suffix}"
    save_json(path, results)
    assert (path.read_bytes()[:2] == b"\x1f\x8b") is (suffix == ".json.gz")
    assert is_coco_results(path)
    out = tmp_path / "out"
    assert main(["eval", str(root), str(path), "--out", str(out), "--task", task]) == 0
    scores = json.loads((out / "scores.json").read_text())
    assert ("bop22_coco_bbox_AP" in scores) is bbox
    assert ("bop22_coco_segm_AP" in scores) is segm
    if bbox:
        assert scores["bop22_coco_bbox_AP"] == pytest.approx(1.0)  # the GT's own boxes
    if segm:
        assert scores["bop22_coco_segm_AP"] == pytest.approx(1.0)  # the GT's own masks


@pytest.mark.parametrize("task", ["bop19", "bop24", "bop19,coco-bbox"])
def test_a_pose_task_on_gzip_coco_results_is_one_line_exit_2(squares, tmp_path, capsys, task):
    root, results = squares
    path = tmp_path / "results.json.gz"
    save_json(path, results)
    assert main(["eval", str(root), str(path), "--out", str(tmp_path / "o"), "--task", task]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "needs other results: a coco results file" in err


def test_content_not_suffix_decides_the_kind(tmp_path, example):
    gz_csv = tmp_path / "results.csv.json.gz"  # a pose CSV compressed: still not COCO
    with gzip.open(gz_csv, "wb") as f:
        f.write(example.results.read_bytes())
    assert not is_coco_results(gz_csv)
    bom = tmp_path / "bom.json"
    bom.write_bytes(b"\xef\xbb\xbf [ ]")
    assert is_coco_results(bom)
    corrupt = tmp_path / "corrupt.json.gz"
    corrupt.write_bytes(b"\x1f\x8b not gzip")
    assert not is_coco_results(corrupt)  # load_results then says what is wrong with it
    shutil.copy(example.results, tmp_path / "plain.json")
    assert not is_coco_results(tmp_path / "plain.json")

"""Estimator interface, BOP detections JSON and `bopsurg predict` with a plugin estimator."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from bopsurg import plugins
from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.detections import gt_detections, load_detections, save_detections
from bopsurg.bop.images import load_depth, load_rgb, save_depth
from bopsurg.bop.results import load_results
from bopsurg.cli.main import main
from bopsurg.errors import BopsurgError, ResultsError, ShapeError
from bopsurg.estimation import (
    Detections,
    ImageInput,
    PoseEstimator,
    PosePredictions,
    predict_images,
)
from bopsurg.example import ExampleSpec, write_example_dataset
from bopsurg.prediction import image_targets, predict_dataset


@pytest.fixture(scope="module")
def example(tmp_path_factory):
    return write_example_dataset(
        tmp_path_factory.mktemp("example"), ExampleSpec(scenes=2, images_per_scene=4)
    )


class GtEstimator:
    """Returns the GT pose shifted by 1 mm in x, one estimate per GT instance (a test oracle
    that reads the dataset it is run on); counts its calls."""

    obj_ids = (1,)

    def __init__(self, dataset: BopDataset, fail_after: int | None = None) -> None:
        self.dataset = dataset
        self.calls = 0
        self.fail_after = fail_after
        self.lookup = {
            (s, i): gts for s in dataset.scene_ids for i, gts in dataset.scene(s).gt.items()
        }

    def predict(self, rgb, K, *, obj_ids=None, boxes=None):
        if self.fail_after is not None and self.calls >= self.fail_after:
            raise KeyboardInterrupt  # a kill in the middle of the run
        self.calls += 1
        assert rgb.dtype == np.uint8
        assert rgb.ndim == 3
        assert K.shape == (3, 3)
        gts = next(g for k, g in self.lookup.items() if np.array_equal(self._rgb(k), rgb))
        if boxes is not None:
            gts = gts[: len(boxes)]
        n = len(gts)
        if n == 0:
            return PosePredictions.empty()
        return PosePredictions(
            np.array([g.obj_id for g in gts]),
            np.linspace(1, 0.5, n),
            np.stack([g.R for g in gts]).reshape(n, 3, 3),
            np.stack([g.t + np.array([1.0, 0, 0]) for g in gts]).reshape(n, 3),
            np.tile([10.0, 20.0, 30.0, 40.0], (n, 1)),
        )

    def _rgb(self, key):
        from bopsurg.bop.images import load_rgb

        return load_rgb(self.dataset.scene(key[0]).rgb_path(key[1]))


def test_estimator_protocol_and_prediction_checks():
    assert isinstance(GtEstimator.__new__(GtEstimator), PoseEstimator)
    with pytest.raises(ShapeError, match="R"):
        PosePredictions([1], [1.0], np.ones((1, 3, 3)), np.zeros((1, 3)), np.zeros((1, 4)))
    with pytest.raises(ShapeError, match="t"):
        PosePredictions([1], [1.0], np.eye(3)[None], np.full((1, 3), np.nan), np.zeros((1, 4)))
    with pytest.raises(ShapeError, match="bbox"):
        Detections([1, 2], [1.0, 0.5], np.zeros((1, 4)))
    assert len(PosePredictions.empty()) == 0
    assert len(Detections.empty()) == 0


def test_detections_json_round_trip_and_errors(tmp_path):
    dets = {
        (1, 3): Detections([1, 1], [0.9, 0.2], [[1.5, 2, 30, 40], [5, 6, 7, 8]]),
        (2, 0): Detections([2], [0.5], [[0, 0, 10, 10]]),
    }
    path = tmp_path / "det.json"
    save_detections(path, dets, {(1, 3): 0.25})
    back, times = load_detections(path)
    assert set(back) == set(dets)
    np.testing.assert_array_equal(back[(1, 3)].bbox, dets[(1, 3)].bbox)
    np.testing.assert_array_equal(back[(1, 3)].score, [0.9, 0.2])
    assert times == {(1, 3): 0.25, (2, 0): -1.0}
    entries = json.loads(path.read_text())
    assert set(entries[0]) == {"scene_id", "image_id", "category_id", "score", "bbox", "time"}
    entries[1]["bbox"] = [1, 2, 3]
    path.write_text(json.dumps(entries))
    with pytest.raises(ResultsError, match=r"det\.json: 1/bbox"):
        load_detections(path)
    entries[1]["bbox"] = [1, 2, 0, 3]
    path.write_text(json.dumps(entries))
    with pytest.raises(ResultsError, match="positive"):
        load_detections(path)


def test_gt_detections_are_the_visible_boxes_in_pixel_spans(example):
    ds = BopDataset(example.root, example.split)
    boxes = gt_detections(ds)
    n = 0
    for s in ds.scene_ids:
        scene = ds.scene(s)
        for im_id, infos in scene.gt_info.items():
            visible = [
                (g, i) for g, i in zip(scene.gt[im_id], infos, strict=True) if i.px_count_visib
            ]
            n += len(visible)
            if not visible:
                assert (s, im_id) not in boxes
                continue
            det = boxes[(s, im_id)]
            assert det.obj_id.tolist() == [g.obj_id for g, _ in visible]
            assert det.score.tolist() == [1.0] * len(visible)
            x, y, w, h = visible[0][1].bbox_visib  # BOP: w = x_max - x_min
            assert det.bbox[0].tolist() == [x, y, w + 1, h + 1]
    assert n == sum(len(d) for d in boxes.values()) > 0


def test_predict_dataset_writes_timed_results_and_resumes_after_a_kill(example, tmp_path):
    ds = BopDataset(example.root, "test")
    targets = image_targets(ds, (1,))
    out = tmp_path / "res.csv"
    with pytest.raises(KeyboardInterrupt):
        predict_dataset(ds, GtEstimator(ds, fail_after=3), out, progress=False)
    assert not out.exists()
    partial = out.with_name("res.csv.partial")
    # A kill can also tear the last line: append half a row.
    partial.write_text(partial.read_text() + "1,5,1,0.3,1 0 0")
    resumed = GtEstimator(ds)
    run = predict_dataset(ds, resumed, out, detections_out=tmp_path / "d.json", progress=False)
    assert resumed.calls == len(targets) - 3
    assert not partial.exists()
    est = load_results(out)
    assert len(est) == run.estimates.__len__() > 0
    assert run.images == len(targets)
    assert (est.time > 0).all()
    one_image = (est.scene_id == est.scene_id[0]) & (est.im_id == est.im_id[0])
    assert len(set(est.time[one_image])) == 1  # BOP: one time per image
    fresh = tmp_path / "fresh.csv"
    predict_dataset(ds, GtEstimator(ds), fresh, progress=False)
    clean = load_results(fresh)
    np.testing.assert_array_equal(clean.t, est.t)
    dets, _ = load_detections(tmp_path / "d.json")
    assert sum(len(d) for d in dets.values()) == len(est)


class BlindEstimator:
    obj_ids = (1,)

    def predict(self, rgb, K, *, obj_ids=None, boxes=None):
        return PosePredictions.empty()


def test_an_estimator_that_finds_nothing_gives_a_header_only_csv(example, tmp_path):
    ds = BopDataset(example.root, "test")
    out = tmp_path / "none.csv"
    run = predict_dataset(ds, BlindEstimator(), out, progress=False)
    assert len(run.estimates) == 0
    assert run.images == len(image_targets(ds, (1,)))
    assert out.read_text().strip() == "scene_id,im_id,obj_id,score,R,t,time"
    # eval refuses a header-only file with a one-line reason rather than scoring it 0
    assert main(["eval", str(example.root), str(out), "--out", str(tmp_path / "e")]) == 2


def test_predict_cli_with_a_plugin_estimator_and_external_boxes(
    example, tmp_path, capsys, monkeypatch
):
    ds = BopDataset(example.root, "test")
    seen = {}

    def factory(options):
        seen.update(options)
        return GtEstimator(ds)

    real = plugins.load_plugin
    monkeypatch.setattr(
        plugins,
        "load_plugin",
        lambda kind, name=None: factory if name == "oracle" else real(kind, name),
    )
    boxes = tmp_path / "boxes.json"
    save_detections(boxes, {(1, 0): Detections([1], [0.8], [[1, 2, 3, 4]])})
    out = tmp_path / "r.csv"
    config = tmp_path / "settings.yaml"
    config.write_text("k: from-file\nsection: {a: 1, b: 2}\n")
    args = ["predict", str(example.root), "--out", str(out), "--estimator", "oracle"]
    args += ["--config", str(config), "--option", "section.b=[1, 2.5]", "--option", "k=v"]
    code = main([*args, "--boxes", str(boxes), "--no-progress"])
    assert code == 0
    # the file, then the dotted options (YAML values), then the flags' defaults
    expected = {"device": "auto", "k": "v", "section": {"a": 1, "b": [1, 2.5]}}
    assert seen == expected
    # an estimator without resolved_config(): the options it got are what made the results
    written = tmp_path / "r.config.yaml"
    assert yaml.safe_load(written.read_text()) == expected
    assert "settings: " in capsys.readouterr().out
    assert main([*args[:6], "--config", str(written), "--boxes", str(boxes), "--no-progress"]) == 0
    assert seen == expected  # the written file reproduces the run
    est = load_results(out)
    # Images without an external box get no estimate.
    assert set(zip(est.scene_id.tolist(), est.im_id.tolist(), strict=True)) == {(1, 0)}
    assert "next: bopsurg eval" in capsys.readouterr().out
    assert main(["eval", str(example.root), str(out), "--out", str(tmp_path / "e")]) == 0


def test_predict_cli_errors_are_one_line(example, tmp_path, capsys):
    out = tmp_path / "r.csv"
    assert main(["predict", str(example.root), "--out", str(out), "--estimator", "nope"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("bopsurg: error:")
    assert "nope" in err
    assert "\n" not in err
    bad = tmp_path / "b.json"
    bad.write_text("[{]")
    args = ["predict", str(example.root), "--out", str(out), "--boxes", str(bad)]
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert str(bad) in err
    assert "\n" not in err


class DepthEstimator:
    """Uses depth (``uses_depth``); keeps what each call was given."""

    obj_ids = (1,)
    uses_depth = True

    def __init__(self) -> None:
        self.calls: list[dict] = []

    def predict(self, rgb, K, *, obj_ids=None, boxes=None, **kw):
        self.calls.append(kw)
        return PosePredictions.empty()


def with_depth(ds: BopDataset, seed: int = 0) -> BopDataset:
    """``ds`` with a random depth image (stored values, uint16) beside every RGB image."""
    rng = np.random.default_rng(seed)
    for s in ds.scene_ids:
        scene = ds.scene(s)
        for im_id in scene.camera:
            shape = load_rgb(scene.rgb_path(im_id)).shape[:2]
            save_depth(scene.depth_path(im_id), rng.integers(0, 3000, shape))
    return ds


def test_an_estimator_that_uses_depth_gets_it_in_mm_unless_rgb_only(tmp_path):
    ex = write_example_dataset(tmp_path / "d", ExampleSpec(scenes=1, images_per_scene=3))
    ds = with_depth(BopDataset(ex.root, "test"))
    est = DepthEstimator()
    run = predict_dataset(ds, est, tmp_path / "r.csv", progress=False)
    keys = list(image_targets(ds, est.obj_ids))
    assert run.depth_images == len(est.calls) == len(keys) == 3
    for (s, im_id), kw in zip(keys, est.calls, strict=True):
        scene = ds.scene(s)
        mm = (
            load_depth(scene.depth_path(im_id)).astype(np.float64) * scene.camera[im_id].depth_scale
        )
        assert mm.std() > 0
        np.testing.assert_allclose(kw["depth"], mm, rtol=1e-12)
    # an image without a depth file: the estimator is told so with None
    ds.scene(keys[0][0]).depth_path(keys[0][1]).unlink()
    est = DepthEstimator()
    run = predict_dataset(ds, est, tmp_path / "r2.csv", progress=False)
    assert est.calls[0] == {"depth": None}
    assert run.depth_images == 2
    # RGB only: not even the keyword (an RGB estimator's predict() need not take it)
    est = DepthEstimator()
    run = predict_dataset(ds, est, tmp_path / "r3.csv", progress=False, depth=False)
    assert est.calls == [{}] * 3
    assert run.depth_images == 0


class BatchCounter(GtEstimator):
    """:class:`GtEstimator` with ``predict_batch``: records the size of every batch."""

    def __init__(self, dataset: BopDataset, fail_after: int | None = None) -> None:
        super().__init__(dataset, fail_after)
        self.batches: list[int] = []

    def predict_batch(self, images):
        self.batches.append(len(images))
        return [self.predict(im.rgb, im.K, obj_ids=im.obj_ids, boxes=im.boxes) for im in images]


def test_batches_give_the_same_results_resume_and_share_their_time(example, tmp_path):
    ds = BopDataset(example.root, "test")
    n = len(image_targets(ds, (1,)))
    one = predict_dataset(ds, GtEstimator(ds), tmp_path / "one.csv", progress=False)
    # killed in the second batch of 3: the first batch is done, the second lost
    with pytest.raises(KeyboardInterrupt):
        predict_dataset(ds, BatchCounter(ds, 4), tmp_path / "b.csv", batch_size=3, progress=False)
    resumed = BatchCounter(ds)
    run = predict_dataset(ds, resumed, tmp_path / "b.csv", batch_size=3, progress=False)
    left = n - 3
    assert resumed.batches == [3] * (left // 3) + ([left % 3] if left % 3 else [])
    assert run.images == n
    a, b = load_results(tmp_path / "one.csv"), load_results(tmp_path / "b.csv")
    np.testing.assert_array_equal(a.R, b.R)
    np.testing.assert_array_equal(a.t, b.t)
    assert len(a) == len(one.estimates)
    # the images of one batch share its time; a --max-images cut ends in a short batch
    cut = BatchCounter(ds)
    run = predict_dataset(ds, cut, tmp_path / "c.csv", batch_size=4, max_images=5, progress=False)
    assert cut.batches == [4, 1]
    assert run.images == 5
    c = load_results(tmp_path / "c.csv")
    keys = zip(c.scene_id.tolist(), c.im_id.tolist(), strict=True)
    per_image = dict(zip(keys, c.time.tolist(), strict=True))
    assert (c.time > 0).all()
    assert len(set(list(per_image.values())[:4])) == 1  # the first batch's images
    with pytest.raises(BopsurgError, match="batch size"):
        predict_dataset(ds, GtEstimator(ds), tmp_path / "d.csv", batch_size=0)


def test_predict_images_loops_over_predict_without_predict_batch():
    rgb = np.zeros((4, 5, 3), np.uint8)
    images = [ImageInput(rgb, np.eye(3), depth=np.ones((4, 5))), ImageInput(rgb, np.eye(3))]
    est = DepthEstimator()
    assert len(predict_images(est, images)) == 2
    np.testing.assert_array_equal(est.calls[0]["depth"], np.ones((4, 5)))
    assert est.calls[1] == {"depth": None}
    est = DepthEstimator()
    predict_images(est, images, depth=False)  # an RGB-only run: not even the keyword
    assert est.calls == [{}, {}]

    class Short:
        obj_ids = (1,)

        def predict(self, rgb, K, *, obj_ids=None, boxes=None):
            return PosePredictions.empty()

        def predict_batch(self, images):
            return []

    with pytest.raises(BopsurgError, match="returned 0 results for 2 images"):
        predict_images(Short(), images)


def test_predict_cli_refuses_a_batch_size_below_one(example, tmp_path, capsys):
    args = ["predict", str(example.root), "--out", str(tmp_path / "r.csv"), "--batch-size", "0"]
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert "--batch-size" in err
    assert "\n" not in err

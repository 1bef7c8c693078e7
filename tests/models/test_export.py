"""bopsurg export: ONNX models that compute what torch computes, and the torch-free runner
(numpy + onnxruntime) that gives the torch estimator's network-only poses."""

from __future__ import annotations

import importlib.util
import json
import shutil
import subprocess
import sys

import cv2
import numpy as np
import pytest

from bopsurg import metrics
from bopsurg.cli.main import main
from bopsurg.errors import BopsurgError
from bopsurg.estimation import Detections, load_estimator

torch = pytest.importorskip("torch")
ort = pytest.importorskip("onnxruntime")

from bopsurg.models import export  # noqa: E402
from bopsurg.models.onnx_runtime import OnnxPipeline, crop, nms  # noqa: E402
from bopsurg.models.pose.roi import crop as torch_crop  # noqa: E402
from bopsurg.models.predict_config import SHIPPED_DIR as SHIPPED  # noqa: E402

pytestmark = [
    pytest.mark.usefixtures("one_thread"),
    pytest.mark.skipif(not (SHIPPED / "pose.pt").exists(), reason="no shipped model"),
]
K = np.array([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]])
LOADERS = {
    "detector": export.load_detector,
    "pose": export.load_pose_head,
    "needle_seg": export.load_segmenter,
}


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    out = tmp_path_factory.mktemp("onnx")
    assert main(["export", "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def image():
    """Grey noise with a bright arc: the shipped detector boxes it (and a few noise blobs at
    a low threshold, which exercise NMS and the per-object selection)."""
    rng = np.random.default_rng(7)
    rgb = rng.integers(80, 130, (480, 640, 3)).astype(np.uint8)
    cv2.ellipse(rgb, (300, 250), (60, 60), 0, 20, 250, (200, 200, 210), 4)
    return rgb


def test_the_command_writes_each_model_with_its_metadata(exported, capsys):
    names = sorted(p.name for p in exported.iterdir())
    assert names == [
        f"{n}.{e}" for n in ("detector", "needle_seg", "pose") for e in ("json", "onnx")
    ]
    det = json.loads((exported / "detector.json").read_text())
    assert det["kind"] == "detector"
    assert det["classes"] == [1]
    assert det["input_hw"] == [384, 512]
    assert det["letterbox"]["pad_grey"] == 114
    assert det["dynamic_axes"]["images"] == {"0": "batch", "2": "height", "3": "width"}
    pose = json.loads((exported / "pose.json").read_text())
    assert pose["obj_id"] == 1
    assert pose["roi_in"] == 128
    assert pose["roi_out"] == 32
    assert pose["normaliser"]["xyz_scale_mm"] == pytest.approx(16.9312, abs=1e-3)
    assert pose["zoom"] == pytest.approx([5 / 6, 1.0, 7 / 6])
    seg = json.loads((exported / "needle_seg.json").read_text())
    assert seg["arc"]["radius_mm"] == pytest.approx(10.18)
    assert seg["channels"] == 2
    for meta in (det, pose, seg):
        assert len(meta["source"]["sha256"]) == 64
        assert meta["opset"] == export.DEFAULT_OPSET


@pytest.mark.parametrize("kind", ["detector", "pose", "needle_seg"])
@pytest.mark.parametrize("batch", [1, 4])
def test_onnxruntime_outputs_equal_torch_outputs(exported, kind, batch):
    item = LOADERS[kind](SHIPPED / f"{kind}.pt")
    sess = ort.InferenceSession(str(exported / f"{kind}.onnx"))
    inputs = item.inputs(batch)
    got = sess.run(None, {n: x.numpy() for n, x in zip(item.input_names, inputs, strict=True)})
    want = export.torch_outputs(item, inputs)
    assert [o.name for o in sess.get_outputs()] == item.output_names
    for g, w in zip(got, want, strict=True):
        assert g.shape == w.shape
        assert w.shape[0] == batch
        np.testing.assert_allclose(g, w, rtol=0, atol=1e-4)
        assert np.abs(w).max() > 1e-2  # not two zero tensors


def test_the_detector_takes_another_input_size(exported):
    item = export.load_detector(SHIPPED / "detector.pt")
    x = torch.rand((1, 3, 480, 640), generator=torch.Generator().manual_seed(3))
    (got,) = ort.InferenceSession(str(exported / "detector.onnx")).run(None, {"images": x.numpy()})
    (want,) = export.torch_outputs(item, (x,))
    assert got.shape == want.shape == (1, 60 * 80 + 30 * 40 + 15 * 20, 6)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-4)


def test_the_export_is_deterministic(exported):
    item = export.load_segmenter(SHIPPED / "needle_seg.pt")
    assert export.onnx_bytes(item) == (exported / "needle_seg.onnx").read_bytes()


def test_numpy_crop_and_nms_match_the_torch_ones():
    rng = np.random.default_rng(1)
    img = rng.random((3, 50, 70)).astype(np.float32)
    centre = np.array([[10.3, 20.7], [68.0, 1.0], [35.5, 25.0]])  # one runs off the image
    side = np.array([17.2, 40.0, 90.0])
    want = torch_crop(
        torch.from_numpy(img)[None].expand(3, -1, -1, -1),
        torch.from_numpy(centre).float(),
        torch.from_numpy(side).float(),
        16,
    ).numpy()
    np.testing.assert_allclose(crop(img, centre, side, 16), want, atol=1e-5)
    boxes = np.array([[0, 0, 10, 10], [1, 1, 10, 10], [20, 20, 30, 30], [0, 0, 9, 10.0]])
    # 1 overlaps 0 (IoU .81) and goes; 3 overlaps 0 (IoU .9) and goes; 2 is alone
    assert nms(boxes, np.array([0.9, 0.8, 0.7, 0.95]), 0.65).tolist() == [3, 2]


@pytest.mark.parametrize("zoom", [[1.0], None])
def test_the_runner_gives_the_torch_estimators_network_only_poses(exported, image, zoom):
    opts = {"device": "cpu", "refine": {"segmenter": None}, "ends": {"classifier": None}}
    opts |= {"detect": {"conf": 0.001, "max_per_object": 3}}
    opts |= {"head": {"zoom": zoom}} if zoom else {}
    est = load_estimator("gdrnet", opts)
    onnx_opts = {"dir": str(exported), "conf": 0.001, "max_per_object": 3}
    runner = load_estimator("gdrnet-onnx", onnx_opts | ({"zoom": zoom} if zoom else {}))
    assert runner.obj_ids == (1,)
    want, got = est.predict(image, K), runner.predict(image, K)
    assert len(want) == 3
    np.testing.assert_array_equal(got.obj_id, want.obj_id)
    np.testing.assert_allclose(got.score, want.score, atol=1e-5)
    np.testing.assert_allclose(got.bbox, want.bbox, atol=1e-3)  # px
    # float32 rounding (crops, network) moves poses by ~0.01 deg and ~1e-3 mm at t_z ~ 40 mm
    assert metrics.re(got.R, want.R).max() < 0.05  # deg
    np.testing.assert_allclose(got.t, want.t, atol=5e-3)  # mm
    # external boxes go straight to the pose head
    xywh = np.array([[250, 180, 110, 90.0], [10, 20, 30, 40.0]])
    boxes = Detections(np.array([1, 1]), np.array([0.9, 0.5]), xywh)
    want, got = est.predict(image, K, boxes=boxes), runner.predict(image, K, boxes=boxes)
    assert len(got) == 2
    assert metrics.re(got.R, want.R).max() < 0.05
    np.testing.assert_allclose(got.t, want.t, atol=5e-3)
    assert len(runner.predict(image, K, obj_ids=(7,))) == 0


def test_the_runner_needs_no_torch(exported, image, tmp_path):
    png = tmp_path / "im.png"
    cv2.imwrite(str(png), image[..., ::-1])
    code = (
        "import sys; from bopsurg.models.onnx_runtime import main; rc = main(sys.argv[1:]); "
        "assert 'torch' not in sys.modules, 'torch was imported'; sys.exit(rc)"
    )
    args = [str(exported), str(png), "--K", "600,600,320,240", "--zoom", "1"]
    run = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    lines = run.stdout.strip().splitlines()
    assert lines[0] == "scene_id,im_id,obj_id,score,R,t,time"
    assert len(lines) == 2  # one needle: the best box
    fields = lines[1].split(",")
    assert fields[2] == "1"
    assert len(fields[4].split()) == 9
    assert len(fields[5].split()) == 3


def test_bad_inputs_are_one_line_errors(exported, tmp_path, capsys):
    with pytest.raises(BopsurgError, match="pass the export folder"):
        load_estimator("gdrnet-onnx", {})
    with pytest.raises(BopsurgError, match="refine: unknown setting"):
        load_estimator("gdrnet-onnx", {"dir": str(exported), "refine": "fit"})
    with pytest.raises(BopsurgError, match="zoom"):
        load_estimator("gdrnet-onnx", {"dir": str(exported), "zoom": "x"})
    with pytest.raises(BopsurgError, match="no exported detector"):
        OnnxPipeline(tmp_path)
    (tmp_path / "pose.json").write_text("{not json")
    with pytest.raises(BopsurgError, match=r"pose\.json: not a readable JSON"):
        OnnxPipeline(tmp_path)
    (tmp_path / "pose.json").write_text('{"format": 9, "kind": "pose", "onnx": "pose.onnx"}')
    with pytest.raises(BopsurgError, match=r"pose\.json: format: expected an export of format"):
        OnnxPipeline(tmp_path)
    twice = tmp_path / "twice"
    twice.mkdir()
    for name in ("detector", "pose"):
        (twice / f"{name}.onnx").symlink_to(exported / f"{name}.onnx")
        shutil.copy(exported / f"{name}.json", twice)
    shutil.copy(exported / "pose.json", twice / "pose_copy.json")
    with pytest.raises(BopsurgError, match="two exported pose heads are for the same obj_id"):
        OnnxPipeline(twice)
    with pytest.raises(BopsurgError, match="holds a 'detector' model, expected 'pose'"):
        export.load_pose_head(SHIPPED / "detector.pt")
    with pytest.raises(BopsurgError, match="exporter must be one of"):
        export.onnx_bytes(export.load_segmenter(SHIPPED / "needle_seg.pt"), exporter="jit")
    if importlib.util.find_spec("onnxscript") is None:
        with pytest.raises(BopsurgError, match="exporter=dynamo needs onnxscript"):
            export.onnx_bytes(export.load_segmenter(SHIPPED / "needle_seg.pt"), exporter="dynamo")
    out = tmp_path / "none"
    assert main(["export", "--out", str(out), "--detector", "none", "--pose", "none",
                 "--segmenter", "none"]) != 0  # fmt: skip
    assert "nothing to export" in capsys.readouterr().err


@pytest.mark.slow
@pytest.mark.skipif(importlib.util.find_spec("onnxscript") is None, reason="needs onnxscript")
def test_the_dynamo_exporter_agrees_too(tmp_path):
    item = export.load_segmenter(SHIPPED / "needle_seg.pt")
    path = export.write_export(item, tmp_path, source=SHIPPED / "needle_seg.pt", exporter="dynamo")
    assert export.max_difference(path, item, batch=3) < export.CHECK_ATOL

"""Poses mapped between two needle models through their fitted arcs, in `bopsurg predict`."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.images import load_depth, load_rgb
from bopsurg.bop.meshes import ObjectModel, load_ply, save_ply
from bopsurg.bop.results import load_results
from bopsurg.errors import BopsurgError
from bopsurg.estimation import PosePredictions, estimator_models
from bopsurg.example import ExampleSpec, write_example_dataset
from bopsurg.geometry import project_pts, transform_pts
from bopsurg.model_frames import map_predictions, model_mapping
from bopsurg.needle import NeedleSpec, needle_mesh
from bopsurg.prediction import predict_dataset
from tests.bopsurg.test_prediction import DepthEstimator, with_depth

#: The dataset's needle = bopsurg's needle moved by (Q, q): x_dataset = Q x_ours + q.
Q = Rotation.from_euler("xyz", [180.0, 0.0, 183.0], degrees=True).as_matrix()
q = np.array([0.4, -0.3, 0.2])


def _moved(model: ObjectModel) -> ObjectModel:
    return ObjectModel(model.pts @ Q.T + q, model.faces)


def _poses(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    t = rng.uniform(-20, 20, (n, 3)) + np.array([0.0, 0.0, 80.0])
    return Rotation.random(n, random_state=rng).as_matrix(), t


def test_mapped_poses_put_the_dataset_model_where_the_estimator_saw_its_own():
    ours = needle_mesh()
    theirs = _moved(ours)
    m = model_mapping(1, ours, theirs, target_name="theirs.ply")
    assert m is not None
    np.testing.assert_allclose(m.A, Q, atol=1e-6)
    assert m.a == pytest.approx(q, abs=1e-4)
    R, t = _poses(5)
    R2, t2 = m.map_poses(R, t)
    seen = transform_pts(ours.pts, R, t)
    mapped = transform_pts(theirs.pts, R2, t2)
    assert np.abs(mapped - seen).max() < 1e-4  # mm: the same surface in the camera
    R3, t3 = m.unmap_poses(R2, t2)  # and back: the estimator's poses again
    np.testing.assert_allclose(R3, R, atol=1e-12)
    np.testing.assert_allclose(t3, t, atol=1e-9)
    assert "theirs.ply" in m.describe()
    assert "\n" not in m.describe()


#: A pinhole camera (px) for the image-space checks.
K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])


def _project(R, t, pts):
    return project_pts(pts, np.broadcast_to(K, (len(R), 3, 3)), R, t)


def test_a_smaller_needle_is_mapped_to_the_pose_that_gives_the_same_image():
    """A needle 2 % smaller in every dimension at (R, t) looks exactly like ours at
    (R, t / 0.98): the estimator, which reads depth from our needle's size, answers the
    latter, and the mapping must give the former (a rigid map would leave it 2 % too far)."""
    ours = needle_mesh()
    k = 0.98
    spec = NeedleSpec(arc_radius=10.18 * k, wire_diameter=0.72 * k)
    theirs = _moved(needle_mesh(spec))
    m = model_mapping(1, ours, theirs, target_name="theirs.ply")
    assert m.scale == pytest.approx(k, rel=1e-6)
    assert "depth x 0.980" in m.describe()
    R, t = _poses(4, seed=2)
    R2, t2 = m.map_poses(R, t)
    seen, mapped = _project(R, t, ours.pts), _project(R2, t2, theirs.pts)
    assert np.abs(mapped - seen).max() < 1e-3  # px: the same image, vertex for vertex
    # ... and in the camera the mapped needle is theirs where the camera saw it
    X = transform_pts(ours.pts, R, t)
    Y = transform_pts(theirs.pts, R2, t2)
    assert np.abs(Y - k * X).max() < 1e-4
    R3, t3 = m.unmap_poses(R2, t2)
    np.testing.assert_allclose(R3, R, atol=1e-12)
    np.testing.assert_allclose(t3, t, atol=1e-9)


def test_a_slightly_different_needle_maps_within_its_shape_difference():
    """Another mesh of about the same needle (radius +2 %, 2 deg shorter, other tessellation,
    the wire as thick as ours): in the image it lies on ours to within its shape difference."""
    ours = needle_mesh()
    spec = NeedleSpec(arc_radius=10.38, body_deg=118.0, rings=64, sides=10)
    theirs = _moved(needle_mesh(spec))
    m = model_mapping(1, ours, theirs, target_name="theirs.ply")
    assert m.scale == pytest.approx(10.38 / 10.18, rel=1e-3)
    R, t = _poses(3, seed=1)
    R2, t2 = m.map_poses(R, t)
    seen, mapped = _project(R, t, ours.pts), _project(R2, t2, theirs.pts)
    d = np.linalg.norm(mapped[:, :, None] - seen[:, None], axis=3).min(axis=2)  # px
    assert np.median(d) < 0.5
    assert d.max() < 2.0


def test_same_model_needs_no_mapping_and_unmatched_models_are_refused(tmp_path):
    ours = needle_mesh()
    assert model_mapping(1, ours, needle_mesh(), target_name="x.ply") is None
    save_ply(tmp_path / "ours.ply", ours)  # float32 in the file, as every generated dataset
    assert model_mapping(1, ours, load_ply(tmp_path / "ours.ply"), target_name="x.ply") is None
    with pytest.raises(BopsurgError, match=r"x\.ply.*radii differ.*train the estimator"):
        model_mapping(1, ours, needle_mesh(NeedleSpec(arc_radius=6.0)), target_name="x.ply")
    box = trimesh.creation.box(extents=(10, 10, 10))
    with pytest.raises(BopsurgError, match=r"obj_id 1 into the frame of x\.ply.*not a needle"):
        model_mapping(1, ours, ObjectModel(box.vertices, box.faces), target_name="x.ply")


def test_map_predictions_touches_only_the_mapped_object():
    ours = needle_mesh()
    m = model_mapping(1, ours, _moved(ours), target_name="t.ply")
    R, t = _poses(2)
    pred = PosePredictions([1, 2], [0.9, 0.8], R, t, np.zeros((2, 4)))
    out = map_predictions(pred, {1: m})
    R1, t1 = m.map_poses(R[:1], t[:1])
    assert out.R[0] == pytest.approx(R1[0])
    assert out.t[0] == pytest.approx(t1[0])
    assert out.R[1] == pytest.approx(R[1])
    assert out.t[1] == pytest.approx(t[1])


class OwnFrameEstimator:
    """Declares bopsurg's needle as its model and returns the GT pose *of that model*
    (the dataset's GT re-expressed through the known (Q, q)), as a trained estimator would."""

    obj_ids = (1,)

    def __init__(self, dataset: BopDataset) -> None:
        self.object_models = {1: needle_mesh()}
        self.calls = 0
        self.by_image = {}  # image bytes -> its GT
        for s in dataset.scene_ids:
            scene = dataset.scene(s)
            for im_id, gts in scene.gt.items():
                self.by_image[load_rgb(scene.rgb_path(im_id)).tobytes()] = (s, im_id, gts[0])

    def predict(self, rgb, K, *, obj_ids=None, boxes=None):
        gt = self.by_image[rgb.tobytes()][2]
        self.calls += 1
        R_ours = gt.R @ Q  # x_cam = R (Q x_ours + q) + t
        t_ours = gt.R @ q + gt.t
        return PosePredictions([1], [1.0], R_ours[None], t_ours[None], np.zeros((1, 4)))


@pytest.fixture
def moved_dataset(tmp_path):
    ex = write_example_dataset(tmp_path, ExampleSpec(scenes=1, images_per_scene=3))
    ds = BopDataset(ex.root, "test")
    save_ply(ds.model_path(1), _moved(needle_mesh()))  # the dataset's own model frame
    return BopDataset(ex.root, "test")


def test_predict_maps_into_the_dataset_frame_and_says_so(moved_dataset, tmp_path, caplog):
    est = OwnFrameEstimator(moved_dataset)
    assert estimator_models(est) is not None
    with caplog.at_level(logging.INFO, logger="bopsurg.prediction"):
        run = predict_dataset(moved_dataset, est, tmp_path / "r.csv", progress=False)
    said = [r.getMessage() for r in caplog.records if "mapped" in r.getMessage()]
    assert len(said) == 1
    assert "obj_000001.ply" in said[0]
    assert len(run.mappings) == 1
    res = load_results(tmp_path / "r.csv")
    gt = {(s, i): g for s, i, g in est.by_image.values()}
    assert len(res) == est.calls > 0
    for k in range(len(res)):
        g = gt[(int(res.scene_id[k]), int(res.im_id[k]))]
        assert res.R[k] == pytest.approx(g.R, abs=1e-5)
        assert res.t[k] == pytest.approx(g.t, abs=1e-3)


def test_predict_refuses_before_any_image_when_models_do_not_match(moved_dataset, tmp_path):
    save_ply(moved_dataset.model_path(1), needle_mesh(NeedleSpec(arc_radius=7.0)))
    ds = BopDataset(moved_dataset.root, "test")
    est = OwnFrameEstimator(ds)
    with pytest.raises(BopsurgError, match="radii differ"):
        predict_dataset(ds, est, tmp_path / "r.csv", progress=False)
    assert est.calls == 0
    assert not (tmp_path / "r.csv").exists()


def test_estimator_without_declared_models_is_not_mapped(moved_dataset, tmp_path):
    est = OwnFrameEstimator(moved_dataset)
    del est.object_models
    run = predict_dataset(moved_dataset, est, tmp_path / "r.csv", progress=False)
    assert run.mappings == ()
    res = load_results(tmp_path / "r.csv")
    g = {(s, i): g for s, i, g in est.by_image.values()}[(int(res.scene_id[0]), int(res.im_id[0]))]
    assert res.R[0] == pytest.approx(g.R @ Q, abs=1e-6)


class DepthProbe(DepthEstimator):
    """A depth-using estimator that declares bopsurg's needle as its model."""

    def __init__(self) -> None:
        super().__init__()
        self.object_models = {1: needle_mesh()}


def test_depth_reaches_the_estimator_at_its_own_needle_scale(tmp_path):
    """The mapping's scaling, for depth: a dataset needle k times ours at (R, t) is seen by
    the estimator as ours at (R, t / k), so the depth it gets is the dataset's divided by k
    (a depth fit of our needle then lands on the pose that the mapping scales back)."""
    ex = write_example_dataset(tmp_path / "d", ExampleSpec(scenes=1, images_per_scene=2))
    ds = with_depth(BopDataset(ex.root, "test"))
    k = 0.98
    small = needle_mesh()
    save_ply(ds.model_path(1), ObjectModel(k * small.pts, small.faces))
    ds = BopDataset(ex.root, "test")
    est = DepthProbe()
    run = predict_dataset(ds, est, tmp_path / "r.csv", progress=False)
    assert run.mappings[0].scale == pytest.approx(k, rel=1e-3)
    assert run.depth_images == len(est.calls) == 2
    scene = ds.scene(ds.scene_ids[0])
    for im_id, kw in zip(sorted(scene.camera), est.calls, strict=True):
        got = kw["depth"]
        stored = (
            load_depth(scene.depth_path(im_id)).astype(np.float64) * scene.camera[im_id].depth_scale
        )
        assert got is not None
        np.testing.assert_allclose(got, stored / run.mappings[0].scale, rtol=1e-12)

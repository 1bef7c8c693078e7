"""The batched needle fit against the per-ROI numpy fit it replaced: reference outputs of that
fit on a small rendered scene (:mod:`tests.models.refine_scene`, ``data/refine_reference.json``,
captured from it once) with and without depth and the full mask, and the batch's own contract.

Tolerance: the same float64 arithmetic in another order differs by roundoff, which can tip
one discrete decision of the fit: a problem's convergence test (its cost fell by less than
``rtol`` = 1e-6 of itself) may stop it one Levenberg-Marquardt step earlier or later. Such a
step lowers the cost C by less than rtol·C, and the data's Gauss-Newton Hessian is positive
semi-definite on top of the prior's diag(w/σ²), so it moves each pose coordinate by less than
σ·sqrt(2·rtol·C/w): with the default prior (σ 8°, 2.5 mm, w 0.05) and C of order 1, 0.05° and
0.016 mm. The fixtures' differences sit far below that (roundoff, or one tipped test:
1.3e-4° and 3e-6 mm), so the tests hold them to 1e-3° and 1e-4 mm."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from bopsurg import metrics

torch = pytest.importorskip("torch")

from bopsurg.models.pose.roi import crop  # noqa: E402
from bopsurg.models.predict_config import DepthSettings  # noqa: E402
from bopsurg.models.refine.refiner import NeedleRefiner  # noqa: E402
from tests.models.refine_scene import ARC, K, scene, variants  # noqa: E402

REFERENCE = json.loads((Path(__file__).parent / "data" / "refine_reference.json").read_text())
ROT_TOL_DEG = 1e-3
T_TOL_MM = 1e-4
GRID = 96


@pytest.fixture(scope="module")
def the_scene():
    return scene()


def _source(*planes: np.ndarray):
    """Crops of full-image masks as the segmenter crops the image ((n, S, S) or (n, 2, S, S))."""
    m = torch.from_numpy(np.stack(planes).astype(np.float32))[None]

    def evidence(image, centre, side, size):
        index = torch.zeros(len(centre), dtype=torch.long)
        prob = crop(m, centre, side, size, "bilinear", index=index).numpy()
        return prob if len(planes) > 1 else prob[:, 0]

    return evidence


def _refiner(sc, name: str, device: str = "cpu"):
    fit, dep, _, two = variants()[name]
    planes = (sc.visible, sc.full) if two else (sc.visible,)
    refiner = NeedleRefiner(_source(*planes), ARC, GRID, fit=fit, depth=dep, device=device)
    masks = refiner.observe(None, K, torch.as_tensor(sc.boxes, dtype=torch.float32), sc.R0, sc.t0)
    return refiner, masks


def _assert_matches(res, name: str) -> None:
    ref = REFERENCE[name]
    np.testing.assert_array_equal(res.changed, ref["changed"])
    assert metrics.re(res.R, np.array(ref["R"])).max() <= ROT_TOL_DEG
    assert np.abs(res.t - np.array(ref["t"])).max() <= T_TOL_MM


@pytest.mark.parametrize("name", list(variants()))
def test_the_batched_fit_gives_the_per_roi_fits_poses(the_scene, name):
    refiner, masks = _refiner(the_scene, name)
    use_depth = variants()[name][2]
    res = refiner.fit(masks, K, the_scene.R0, the_scene.t0, the_scene.depth if use_depth else None)
    assert res.R.shape == (4, 3, 3)
    assert not res.changed[3]  # the empty corner keeps its start
    _assert_matches(res, name)


@pytest.mark.parametrize("name", ["rgbd", "rgbd_full"])
def test_the_default_cap_on_depth_points_stays_near_the_fit_on_all(the_scene, name):
    """With its default ``max_points`` the RGB-D fit reads a strided subset of each mask's
    points (the scene's needles have up to several times more): the same decisions, and poses
    within a tenth of a degree and a hundredth of a mm of the fit on every point."""
    fit, dep, _, two = variants()[name]
    capped = dataclasses.replace(dep, max_points=DepthSettings().max_points)
    planes = (the_scene.visible, the_scene.full) if two else (the_scene.visible,)
    refiner = NeedleRefiner(_source(*planes), ARC, GRID, fit=fit, depth=capped)
    sc = the_scene
    masks = refiner.observe(None, K, torch.as_tensor(sc.boxes, dtype=torch.float32), sc.R0, sc.t0)
    res = refiner.fit(masks, K, sc.R0, sc.t0, sc.depth)
    ref = REFERENCE[name]
    np.testing.assert_array_equal(res.changed, ref["changed"])
    assert metrics.re(res.R, np.array(ref["R"])).max() <= 0.1
    assert np.abs(res.t - np.array(ref["t"])).max() <= 0.01


def test_per_roi_intrinsics_and_depth(the_scene):
    """One call with a K and a depth entry (or None: RGB) per ROI gives what one call per
    ROI gave (the reference ``mixed``)."""
    refiner, masks = _refiner(the_scene, "rgbd")
    Ks = np.repeat(K[None], 4, 0)
    Ks[1, 0, 2] += 3.0
    depth = [the_scene.depth, None, the_scene.depth, the_scene.depth]
    _assert_matches(refiner.fit(masks, Ks, the_scene.R0, the_scene.t0, depth), "mixed")
    with pytest.raises(ValueError, match="3 entries for 4 ROIs"):
        refiner.fit(masks, K, the_scene.R0, the_scene.t0, depth[:3])


def test_a_batch_equals_its_rois_fitted_alone(the_scene):
    """Each ROI's problem stops on its own: fitting ROIs together or one by one (in another
    order) gives the same poses to roundoff."""
    refiner, masks = _refiner(the_scene, "rgbd")
    sc = the_scene
    together = refiner.fit(masks, K, sc.R0, sc.t0, sc.depth)
    for i in (2, 0, 1):
        alone = refiner.fit(
            masks.subset(np.array([i])), K, sc.R0[i : i + 1], sc.t0[i : i + 1], sc.depth
        )
        np.testing.assert_allclose(alone.R[0], together.R[i], atol=1e-9)
        np.testing.assert_allclose(alone.t[0], together.t[i], atol=1e-9)
        assert alone.changed[0] == together.changed[i]


@pytest.mark.parametrize("name", ["rgb", "rgbd"])
def test_a_fit_under_two_torch_threads_gives_the_poses_of_one(the_scene, name):
    """With two torch threads (the budget ``bopsurg predict`` gives) the fits still run on
    the calling thread with one intra-op thread (:func:`bopsurg.models.refine.lm.fit_threads`):
    the same poses and decisions as one thread, and the caller's thread count restored."""
    refiner, masks = _refiner(the_scene, name)
    depth = the_scene.depth if variants()[name][2] else None
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = refiner.fit(masks, K, the_scene.R0, the_scene.t0, depth)
        torch.set_num_threads(2)
        two = refiner.fit(masks, K, the_scene.R0, the_scene.t0, depth)
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
    np.testing.assert_allclose(two.R, one.R, atol=1e-9)
    np.testing.assert_allclose(two.t, one.t, atol=1e-9)
    np.testing.assert_array_equal(two.changed, one.changed)


def test_no_roi_gives_no_pose(the_scene):
    refiner, masks = _refiner(the_scene, "rgbd")
    none = np.zeros(0, np.int64)
    res = refiner.fit(masks.subset(none), K, np.zeros((0, 3, 3)), np.zeros((0, 3)), the_scene.depth)
    assert res.R.shape == (0, 3, 3)
    assert res.changed.shape == (0,)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_the_fit_on_cuda_gives_the_cpu_poses(the_scene):
    refiner, masks = _refiner(the_scene, "rgbd", device="cuda")
    _assert_matches(refiner.fit(masks, K, the_scene.R0, the_scene.t0, the_scene.depth), "rgbd")

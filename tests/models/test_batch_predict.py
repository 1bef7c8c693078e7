"""Networks loaded for inference (BatchNorm folded, channels-last) give the outputs of the
trained ones, and ``gdrnet`` over batches of images gives the poses of single images."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.images import load_rgb, save_depth
from bopsurg.bop.results import load_results
from bopsurg.estimation import load_estimator
from bopsurg.example import ExampleSpec, write_example_dataset
from bopsurg.prediction import predict_dataset

torch = pytest.importorskip("torch")

from torch import nn  # noqa: E402

from bopsurg.models.checkpoint import load_checkpoint, load_weights  # noqa: E402
from bopsurg.models.detector import DetectorConfig, YoloxDetector  # noqa: E402
from bopsurg.models.inference import fold_batchnorm, for_inference  # noqa: E402
from bopsurg.models.pose.config import PoseConfig  # noqa: E402
from bopsurg.models.pose.network import GdrPoseNet  # noqa: E402
from bopsurg.models.predict_config import SHIPPED_DIR  # noqa: E402
from bopsurg.models.refine.ends import EndConfig, EndNet  # noqa: E402
from bopsurg.models.refine.seghead import NeedleSegNet, SegConfig  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")
CPU = torch.device("cpu")


def _shipped(kind: str, file: str, build):
    state, info = load_checkpoint(SHIPPED_DIR / file, kind)
    net = build(info["config"])
    load_weights(net, state, SHIPPED_DIR / file)
    return net.eval()


def _rel(a, b) -> float:
    if isinstance(a, dict):
        return max(_rel(a[k], b[k]) for k in a)
    return float((a - b).abs().max() / a.abs().max())


def _randomise_norms(net: nn.Module, gen: torch.Generator) -> nn.Module:
    """Running statistics and affine parameters far from the identity (a fresh net's BN is
    nearly one, so folding it would prove little)."""
    for m in net.modules():
        if isinstance(m, nn.BatchNorm2d):
            c = m.num_features
            m.running_mean.copy_(torch.randn(c, generator=gen))
            m.running_var.copy_(torch.rand(c, generator=gen) + 0.2)
            m.weight.data.copy_(torch.randn(c, generator=gen))
            m.bias.data.copy_(torch.randn(c, generator=gen))
    return net.eval()


def test_folded_networks_give_the_outputs_of_the_trained_ones():
    gen = torch.Generator().manual_seed(0)
    pose_bn = _randomise_norms(GdrPoseNet(PoseConfig(norm="bn")), gen)
    cases = [
        (
            _shipped(
                "detector", "detector.pt", lambda c: YoloxDetector(DetectorConfig.from_dict(c))
            ),
            (torch.rand(2, 3, 384, 512, generator=gen),),
            74,
        ),
        (
            _shipped("needle_seg", "needle_seg.pt", lambda c: NeedleSegNet(SegConfig.from_dict(c))),
            (torch.rand(3, 3, 160, 160, generator=gen),),
            14,
        ),
        (
            _shipped("needle_ends", "needle_ends.pt", lambda c: EndNet(EndConfig.from_dict(c))),
            (torch.rand(4, 3, 32, 32, generator=gen),),
            4,
        ),
        (pose_bn, (torch.rand(2, 3, 128, 128, generator=gen), torch.rand(2, 2, 32, 32)), None),
    ]
    for net, inputs, expected in cases:
        fast = for_inference(copy.deepcopy(net), CPU)
        norms = sum(isinstance(m, nn.BatchNorm2d) for m in fast.modules())
        assert norms == 0, type(net).__name__  # every BatchNorm of these nets follows a conv
        if expected is not None:
            assert sum(isinstance(m, nn.BatchNorm2d) for m in net.modules()) == expected
        with torch.inference_mode():
            assert _rel(net(*inputs), fast(*inputs)) < 1e-4, type(net).__name__


def test_only_norms_right_after_a_convolution_fold():
    gen = torch.Generator().manual_seed(1)

    class Skip(nn.Module):  # the conv's output is used besides the norm: not foldable
        def __init__(self) -> None:
            super().__init__()
            self.conv, self.bn = nn.Conv2d(3, 3, 3, padding=1), nn.BatchNorm2d(3)

        def forward(self, x):
            y = self.conv(x)
            return self.bn(y) + y

    net = _randomise_norms(nn.Sequential(Skip(), nn.ReLU(), nn.BatchNorm2d(3)), gen)
    assert fold_batchnorm(net) == 0  # the Sequential's norm follows a ReLU
    gn = GdrPoseNet(PoseConfig(norm="gn")).eval()
    assert fold_batchnorm(gn) == 0  # GroupNorm depends on its input
    train = nn.Sequential(nn.Conv2d(3, 3, 1), nn.BatchNorm2d(3)).train()
    assert fold_batchnorm(train) == 0  # training mode: the norm uses the batch's statistics


@pytest.fixture(scope="module")
def needles(tmp_path_factory):
    """Six images of the embedded example with a depth image each (a plane at 80-120 mm)."""
    root = tmp_path_factory.mktemp("batch")
    ex = write_example_dataset(root, ExampleSpec(scenes=2, images_per_scene=3, seed=3))
    ds = BopDataset(ex.root, "test")
    rng = np.random.default_rng(3)
    for s in ds.scene_ids:
        scene = ds.scene(s)
        for im_id in scene.camera:
            h, w = load_rgb(scene.rgb_path(im_id)).shape[:2]
            depth = rng.uniform(80, 120) + 20 * np.linspace(0, 1, w)[None].repeat(h, 0)
            save_depth(scene.depth_path(im_id), depth / scene.camera[im_id].depth_scale)
    return BopDataset(ex.root, "test")


def test_batches_give_the_poses_of_single_images(needles, tmp_path):
    """The default gdrnet (detector, pose head, re-crops, RGB-D fit, end check) at batch 1
    and at batch 4 (a full and a short batch): the same estimates, poses within float noise
    (the networks' convolutions round differently at other batch sizes)."""
    opts = {"device": "cpu", "detect": {"conf": 0.0}}
    runs = []
    for size in (1, 4):
        est = load_estimator("gdrnet", opts)
        out = tmp_path / f"b{size}.csv"
        run = predict_dataset(needles, est, out, batch_size=size, progress=False)
        assert run.depth_images == 6
        runs.append((load_results(out), est.report()))
    (a, report_a), (b, report_b) = runs
    assert len(a) >= 6
    np.testing.assert_array_equal(a.obj_id, b.obj_id)
    np.testing.assert_array_equal(a.im_id, b.im_id)
    np.testing.assert_allclose(a.score, b.score, rtol=1e-5)
    # the fit stops within its tolerance of the same optimum: float noise grows to ~1e-5 mm
    assert np.abs(a.t - b.t).max() < 1e-4, np.abs(a.t - b.t).max()  # mm
    assert np.abs(a.R - b.R).max() < 1e-5
    assert report_a == report_b  # the same refinements, re-crops and end turns

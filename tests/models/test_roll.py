"""The roll augmentation shows the scene from a camera turned about its optical axis, exactly
(pixels, pose, coordinates, box)."""

from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from bopsurg.bop.dataset import BopDataset  # noqa: E402
from bopsurg.example import ExampleSpec, write_example_dataset  # noqa: E402
from bopsurg.models.data import load_pose_set  # noqa: E402
from bopsurg.models.roll import roll_batch  # noqa: E402
from tests.models.plane_depth import train_pose_runs, write_plane_depth  # noqa: E402
from tests.models.test_mirror import _reprojection_px  # noqa: E402


@pytest.fixture(scope="module")
def batch():
    """Every needle of a small example split (depth: a plane at the needle), one batch."""
    import tempfile

    with tempfile.TemporaryDirectory() as root:
        ex = write_example_dataset(root, ExampleSpec(seed=4, scenes=2, images_per_scene=4))
        ds = BopDataset(ex.root, ex.split)
        write_plane_depth(ds)
        data = load_pose_set(ds, [1, 2], 1, context=128, cache_mb=0)
        n = len(data)
        yield data.collate([data[i] for i in range(n)], list(range(n)))


def _angles(n: int) -> torch.Tensor:
    """Turns of every size and sign, one sample left as it is."""
    angle = torch.linspace(-math.pi, math.pi, n)
    angle[n // 2] = 0.0
    return angle


def _project(K: torch.Tensor, p: torch.Tensor) -> np.ndarray:
    uv = torch.einsum("bij,bj->bi", K.double(), p.double())
    return (uv[:, :2] / uv[:, 2:]).numpy()


def test_the_turned_samples_show_their_pixels_where_their_pose_puts_them(batch):
    assert len(batch.idx) >= 6
    before = _reprojection_px(batch)
    assert before.max() < 0.51  # nearest image pixel's point, as cut
    angle = _angles(len(batch.idx))
    r = roll_batch(batch, angle)
    # resampled nearest once more: a context pixel reads a point at most 0.71 context px
    # (0.71 / a image px) from where it sits, and the turn makes the per-axis error of a
    # pixel up to sqrt(2) larger; a wrong pose or centre would be pixels off
    slack = 0.71 / batch.ctx[:, 0].numpy() + 1e-3
    after = _reprojection_px(r)
    assert np.all(after <= math.sqrt(2) * before + slack)
    assert np.all(after[angle.abs() > 0.3] > 0.0)  # and they did move
    keep = angle == 0
    for name in ("rgb", "mask", "xyz", "ctx", "bbox", "R", "t"):
        assert torch.equal(getattr(r, name)[keep], getattr(batch, name)[keep])


def test_the_pose_turns_about_the_optical_axis_and_the_image_about_the_principal_point(batch):
    angle = _angles(len(batch.idx))
    r = roll_batch(batch, angle)
    np.testing.assert_allclose(torch.linalg.det(r.R.double()).numpy(), 1.0, atol=1e-5)
    np.testing.assert_allclose(r.t.norm(dim=1).numpy(), batch.t.norm(dim=1).numpy(), rtol=1e-6)
    np.testing.assert_allclose(r.t[:, 2].numpy(), batch.t[:, 2].numpy(), atol=1e-4)  # depth kept
    # the model origin's image turns by the angle about the principal point (f_x = f_y here)
    pp = batch.K[:, :2, 2].double().numpy()
    d0, d1 = _project(batch.K, batch.t) - pp, _project(r.K, r.t) - pp
    turned = np.arctan2(d1[:, 1], d1[:, 0]) - np.arctan2(d0[:, 1], d0[:, 0])
    np.testing.assert_allclose(np.angle(np.exp(1j * (turned - angle.numpy()))), 0.0, atol=1e-5)
    # the turned box is the turned mask's (an unturned one stays the data's integer box)
    C = batch.rgb.shape[-1]
    for k in np.nonzero(angle.numpy())[0]:
        rows, cols = np.nonzero(r.mask[k].numpy())
        a, cx, cy = (float(v) for v in r.ctx[k])
        x, y, w, h = (float(v) for v in r.bbox[k])
        u, v = (cols - C / 2) / a + cx, (rows - C / 2) / a + cy
        np.testing.assert_allclose([u.min(), v.min()], [x, y], atol=1e-3)
        np.testing.assert_allclose([u.max(), v.max()], [x + w - 1, y + h - 1], atol=1e-3)
    # turned back, the pose is the first one
    back = roll_batch(r, -angle)
    np.testing.assert_allclose(back.R.numpy(), batch.R.numpy(), atol=1e-5)
    np.testing.assert_allclose(back.t.numpy(), batch.t.numpy(), atol=1e-3)
    np.testing.assert_allclose(back.ctx.numpy(), batch.ctx.numpy(), atol=1e-3)


def test_anisotropic_pixels_turn_as_the_camera_does(batch):
    """f_x != f_y: the image turns by ``S Rot S^-1``, not by the angle, and every pixel still
    lands where the turned pose puts it."""
    import dataclasses

    K = batch.K.clone()
    K[:, 0, 0] *= 1.25  # the same pixels seen through wider pixels: stretch the data along x
    stretched = dataclasses.replace(batch, K=K)
    angle = _angles(len(batch.idx))
    r = roll_batch(stretched, angle)
    pp = K[:, :2, 2].double().numpy()
    d0, d1 = _project(K, stretched.t) - pp, _project(K, r.t) - pp
    S = np.diag([float(K[0, 0, 0]), float(K[0, 1, 1])])
    for k, th in enumerate(angle.numpy()):
        A = S @ np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]]) @ np.linalg.inv(S)
        np.testing.assert_allclose(d1[k], A @ d0[k], atol=1e-3)


def test_a_run_with_turned_samples_is_configured_recorded_and_deterministic(tmp_path):
    base = "{epochs: 1, batch_size: 4, val_every: 1, roll: %s, roll_deg: 90}"
    weights, written = train_pose_runs(
        tmp_path, {"a": base % 0.5, "b": base % 0.5, "off": base % 0.0}
    )
    assert [written[n]["roll"] for n in ("a", "b", "off")] == [0.5, 0.5, 0.0]
    assert written["a"]["roll_deg"] == 90
    assert all(torch.equal(weights["a"][k], weights["b"][k]) for k in weights["a"])
    assert any(not torch.equal(weights["a"][k], weights["off"][k]) for k in weights["a"])

"""The mirror augmentation shows the needle's other face, exactly (pixels, pose, coordinates)."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from bopsurg.bop.dataset import BopDataset  # noqa: E402
from bopsurg.example import ExampleSpec, write_example_dataset  # noqa: E402
from bopsurg.mirror import PlaneReflection, object_reflection  # noqa: E402
from bopsurg.models.data import load_pose_set  # noqa: E402
from bopsurg.models.mirror import mirror_batch  # noqa: E402
from tests.models.plane_depth import train_pose_runs, write_plane_depth  # noqa: E402


@pytest.fixture(scope="module")
def example(tmp_path_factory):
    """Every needle of a small example split (depth: a plane at the needle), one batch, and
    the needle's reflection through its plane (from its mesh and models_info)."""
    root = tmp_path_factory.mktemp("mirror")
    ex = write_example_dataset(root, ExampleSpec(seed=4, scenes=2, images_per_scene=4))
    ds = BopDataset(ex.root, ex.split)
    write_plane_depth(ds)
    data = load_pose_set(ds, [1, 2], 1, context=128, cache_mb=0)
    n = len(data)
    return data.collate([data[i] for i in range(n)], list(range(n))), object_reflection(ds, 1)


@pytest.fixture(scope="module")
def batch(example):
    return example[0]


@pytest.fixture(scope="module")
def reflection(example):
    return example[1]


def _reprojection_px(b) -> np.ndarray:
    """Per sample, the largest distance (px) between a visible context pixel's image position
    and the projection of its object coordinates at the sample's pose."""
    C = b.rgb.shape[-1]
    out = []
    for k in range(len(b.idx)):
        i, j = np.nonzero(b.mask[k].numpy())
        a, c0x, c0y = (float(v) for v in b.ctx[k])
        img = np.stack([(j - C / 2) / a + c0x, (i - C / 2) / a + c0y], 1)
        X = b.xyz[k].float().numpy()[:, i, j].T
        cam = X @ b.R[k].double().numpy().T + b.t[k].double().numpy()
        uv = cam @ b.K[k].double().numpy().T
        out.append(np.abs(uv[:, :2] / uv[:, 2:] - img).max())
    return np.array(out)


def test_the_mirrored_samples_show_their_pixels_where_their_pose_puts_them(batch, reflection):
    assert len(batch.idx) >= 4
    # the data's own consistency: the coordinates are sampled nearest, so a context pixel
    # holds its nearest image pixel's point, up to half an image pixel away
    before = _reprojection_px(batch)
    assert before.max() < 0.51
    flip = torch.arange(len(batch.idx)) % 2 == 0
    m = mirror_batch(batch, flip, reflection)
    # mirrored exactly: every pixel keeps its error, mirrored (one context pixel off, 1/a
    # image px, would add about a pixel)
    np.testing.assert_allclose(_reprojection_px(m), before, atol=1e-3)
    # the flipped ones moved: their image columns mirrored about c_x
    assert not torch.equal(m.rgb[flip], batch.rgb[flip])
    assert torch.equal(m.rgb[~flip], batch.rgb[~flip])
    assert torch.equal(m.R[~flip], batch.R[~flip])


def test_the_mirror_shows_the_other_face_with_a_proper_rotation(batch, reflection):
    # bopsurg's needle: the plane z = 0 through the model origin
    np.testing.assert_allclose(reflection.M, np.diag([1.0, 1.0, -1.0]), atol=1e-12)
    np.testing.assert_allclose(reflection.d, 0.0, atol=1e-9)
    flip = torch.ones(len(batch.idx), dtype=torch.bool)
    m = mirror_batch(batch, flip, reflection)
    det = torch.linalg.det(m.R.double())
    np.testing.assert_allclose(det.numpy(), 1.0, atol=1e-5)
    n, n2 = batch.R[:, :, 2].double(), m.R[:, :, 2].double()  # the arc normals (model +Z)
    v = batch.t.double() / batch.t.double().norm(dim=1, keepdim=True)
    v2 = m.t.double() / m.t.double().norm(dim=1, keepdim=True)
    np.testing.assert_allclose((n2 * v2).sum(1).numpy(), -(n * v).sum(1).numpy(), atol=1e-5)
    # the visible box mirrors with the pixels: its column span is the mask's
    C = batch.rgb.shape[-1]
    for k in range(len(m.idx)):
        cols = np.nonzero(m.mask[k].numpy().any(0))[0]
        a, c0x = float(m.ctx[k, 0]), float(m.ctx[k, 1])
        left = (cols.min() - C / 2) / a + c0x
        assert abs(left - float(m.bbox[k, 0])) < 1.0 / a + 1e-3
    back = mirror_batch(m, flip, reflection)  # twice is the identity
    for name in ("rgb", "mask", "xyz"):
        assert torch.equal(getattr(back, name), getattr(batch, name))
    for name in ("ctx", "bbox", "R", "t"):
        np.testing.assert_allclose(
            getattr(back, name).numpy(), getattr(batch, name).numpy(), atol=1e-4
        )


def test_a_needle_whose_plane_is_off_its_model_origin_mirrors_to_the_same_poses(batch, reflection):
    """The same samples in a model frame shifted by o: the plane is z = o_z, so the reflection
    moves points by d = (0, 0, 2 o_z). Mirrored there, every pixel still lands where the pose
    puts it, and the poses are the first frame's mirrored poses moved by o (dropping R d from
    the translation would put them 2 o_z mm off)."""
    import dataclasses

    o = torch.tensor([0.3, -0.2, 2.5])
    shifted = dataclasses.replace(
        batch,
        xyz=torch.where(batch.mask[:, None], batch.xyz.float() + o[:, None, None], 0.0).half(),
        t=batch.t - batch.R @ o,
    )
    plane = PlaneReflection(reflection.M, reflection.M @ -o.double().numpy() + o.double().numpy())
    np.testing.assert_allclose(plane.d, [0.0, 0.0, 5.0], atol=1e-12)
    flip = torch.arange(len(batch.idx)) % 2 == 1
    m, ms = mirror_batch(batch, flip, reflection), mirror_batch(shifted, flip, plane)
    # (float16 coordinates, rounded again after the shift and the mirror: ~0.01 px)
    np.testing.assert_allclose(_reprojection_px(ms), _reprojection_px(shifted), atol=0.01)
    np.testing.assert_allclose(ms.R.numpy(), m.R.numpy(), atol=1e-6)
    np.testing.assert_allclose(ms.t.numpy(), (m.t - m.R @ o).numpy(), atol=1e-4)


def test_a_run_with_mirrored_samples_is_configured_recorded_and_deterministic(tmp_path):
    base = "{epochs: 1, batch_size: 4, val_every: 1, mirror: %s}"
    weights, written = train_pose_runs(
        tmp_path, {"a": base % 0.5, "b": base % 0.5, "off": base % 0.0}
    )
    assert [written[n]["mirror"] for n in ("a", "b", "off")] == [0.5, 0.5, 0.0]
    assert all(torch.equal(weights["a"][k], weights["b"][k]) for k in weights["a"])
    assert any(not torch.equal(weights["a"][k], weights["off"][k]) for k in weights["a"])


def test_mirror_splits_picks_the_samples_of_the_named_splits_and_refuses_others(tmp_path):
    import shutil

    from bopsurg.errors import BopsurgError
    from bopsurg.models.data import SCENE_ID_STRIDE, open_split
    from bopsurg.models.train_pose import _mirrorable

    ex = write_example_dataset(tmp_path, ExampleSpec(seed=4, scenes=2, images_per_scene=2))
    write_plane_depth(BopDataset(ex.root, ex.split))
    shutil.copytree(ex.root / ex.split, ex.root / "wide")
    union = open_split(ex.root, f"{ex.split},wide")
    ids = [1, 2, SCENE_ID_STRIDE + 1, SCENE_ID_STRIDE + 2]
    data = load_pose_set(union, ids, 1, context=128, cache_mb=0, progress=False)
    in_wide = np.array([r.scene_id >= SCENE_ID_STRIDE for r in data.records])
    assert 0 < in_wide.sum() < len(data)
    assert _mirrorable(data, union, ()) is None  # every split may mirror
    assert np.array_equal(_mirrorable(data, union, ("wide",)).numpy(), in_wide)
    assert np.array_equal(_mirrorable(data, union, (ex.split,)).numpy(), ~in_wide)
    with pytest.raises(BopsurgError, match="mirror_splits: train_wide not among"):
        _mirrorable(data, union, ("train_wide",))

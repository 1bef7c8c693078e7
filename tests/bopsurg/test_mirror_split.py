"""`bopsurg.mirror`: a split's mirror image shows the needle's other face, exactly."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bopsurg.ambf_import import ambf_needle, import_ambf_yaml
from bopsurg.bop.check import check_dataset
from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.images import load_rgb
from bopsurg.bop.jsonio import load_json, save_json
from bopsurg.bop.meshes import ObjectModel, save_ply
from bopsurg.errors import DatasetError, ModelError
from bopsurg.mirror import mirror_split, plane_reflection
from bopsurg.needle import fit_needle
from tests.bopsurg.test_ambf_import import K, SilhouetteRenderer, write_ambf_yaml


@pytest.fixture
def source(tmp_path):
    """Three needles (AMBF needle model, own frame) over a phantom, depth in 1 mm units."""
    model = ambf_needle()
    save_ply(tmp_path / "Needle.ply", model)
    src = write_ambf_yaml(tmp_path / "scene1", model)
    out = tmp_path / "data"
    renderer = SilhouetteRenderer()
    import_ambf_yaml(src, out, model=tmp_path / "Needle.ply", renderer=renderer, progress=False)
    return out


def _mirror(src, out, **kw):
    return mirror_split(src, out, "test", renderer=SilhouetteRenderer(), progress=False, **kw)


def _project(pts, R, t):
    uv = (pts @ R.T + t) @ K.T
    return uv[:, :2] / uv[:, 2:]


def test_the_mirror_shows_every_model_point_where_the_mirror_puts_it(source, tmp_path):
    rep = _mirror(source, tmp_path / "m")
    assert (rep.images, rep.instances) == (3, 3)
    assert check_dataset(tmp_path / "m") == []
    a, b = BopDataset(source, "test").scene(1), BopDataset(tmp_path / "m", "test").scene(1)
    model = BopDataset(source, "test").model(1)
    arc = fit_needle(model)
    for im_id, (g,) in a.gt.items():
        (m,) = b.gt[im_id]
        assert np.linalg.det(m.R) == pytest.approx(1.0)
        assert np.allclose(m.R @ m.R.T, np.eye(3))
        # the model's points, mapped onto themselves by its plane reflection, land on the
        # mirrored pixels u' = 2 c_x - u of the points they mirror
        S = plane_reflection(model, arc.normal)
        src_uv = _project(model.pts, g.R, g.t)
        dst_uv = _project(model.pts @ S.M.T + S.d, m.R, m.t)
        np.testing.assert_allclose(dst_uv[:, 0], 2 * K[0, 2] - src_uv[:, 0], atol=1e-9)
        np.testing.assert_allclose(dst_uv[:, 1], src_uv[:, 1], atol=1e-9)
        # the other face: the arc normal turns from the camera to it, or the other way
        view, mview = arc.center @ g.R.T + g.t, arc.center @ m.R.T + m.t
        face = np.sign((g.R @ arc.normal) @ view)
        assert np.sign((m.R @ arc.normal) @ mview) == -face != 0
        assert np.linalg.norm(mview) == pytest.approx(np.linalg.norm(view))
        # pixels: column u' of the mirror is column 2 c_x - u' of the source
        src_rgb, dst_rgb = load_rgb(a.rgb_path(im_id)), load_rgb(b.rgb_path(im_id))
        cols = int(2 * K[0, 2]) - np.arange(1, src_rgb.shape[1])
        assert np.array_equal(dst_rgb[:, 1:], src_rgb[:, cols])
        assert not dst_rgb[:, 0].any()  # its mirror lies outside the image
        # the masks come out as before (the needles lie inside the image; the stand-in
        # rasteriser's tie rule at pixel centres is not mirror-exact, so a pixel or two)
        ia, ib = a.gt_info[im_id][0], b.gt_info[im_id][0]
        assert ib.visib_fract == pytest.approx(ia.visib_fract, abs=0.02)
        assert ib.px_count_visib == pytest.approx(ia.px_count_visib, rel=0.05)
        x, y, w, h = ia.bbox_visib
        assert ib.bbox_visib == pytest.approx((2 * K[0, 2] - x - w, y, w, h), abs=1)


def test_mirroring_twice_gives_back_the_poses(source, tmp_path):
    _mirror(source, tmp_path / "m")
    _mirror(tmp_path / "m", tmp_path / "mm")
    a, c = BopDataset(source, "test").scene(1), BopDataset(tmp_path / "mm", "test").scene(1)
    for im_id, (g,) in a.gt.items():
        (back,) = c.gt[im_id]
        np.testing.assert_allclose(back.R, g.R, atol=1e-12)
        np.testing.assert_allclose(back.t, g.t, atol=1e-9)
    assert load_json(tmp_path / "mm" / "bopsurg_mirror.json")["source"].endswith("m")


def test_bad_input_gets_one_clear_error_and_leaves_nothing(source, tmp_path):
    out = tmp_path / "m"
    (out / "x").mkdir(parents=True)
    with pytest.raises(DatasetError, match="not empty"):
        _mirror(source, out)
    # a principal point between pixel centres and edges: the mirror would resample
    cam = source / "test" / "000001" / "scene_camera.json"
    saved = load_json(cam)
    edited = {
        k: {**v, "cam_K": [*v["cam_K"][:2], 80.25, *v["cam_K"][3:]]} for k, v in saved.items()
    }
    save_json(cam, edited)
    with pytest.raises(DatasetError, match="2 c_x to be an integer"):
        _mirror(source, tmp_path / "m2")
    save_json(cam, saved)
    # an object that is not its own mirror image, or without the plane
    info_path = source / "models" / "models_info.json"
    info = load_json(info_path)
    save_json(info_path, {"1": {k: v for k, v in info["1"].items() if k != "plane_normal"}})
    with pytest.raises(DatasetError, match="no plane_normal"):
        _mirror(source, tmp_path / "m3")
    save_json(info_path, {"1": {**info["1"], "plane_normal": [1.0, 0.0, 0.0]}})
    with pytest.raises(ModelError, match="not its own mirror image"):
        _mirror(source, tmp_path / "m4")
    leftovers = [p.name for p in tmp_path.iterdir() if p.name.startswith((".m", "m2", "m3", "m4"))]
    assert leftovers == []


def test_a_model_with_a_bent_tip_is_not_its_own_mirror_image():
    model = ambf_needle()
    pts = model.pts.copy()
    tip = np.argmax(pts[:, 1])
    pts[tip, 2] += 0.3  # one vertex out of the plane's symmetry
    with pytest.raises(ModelError, match="not its own mirror image"):
        plane_reflection(ObjectModel(pts, model.faces), [0, 0, 1])
    S = plane_reflection(model, [0, 0, 2.0])  # any length of normal
    assert np.allclose(S.M, np.diag([1.0, 1.0, -1.0]))
    assert np.allclose(S.d, 0.0, atol=1e-9)


def test_a_plane_off_the_origin_mirrors_exactly():
    """A needle lifted 1 mm off its model origin: d = 2 (n . c) n enters the translation."""
    model = ambf_needle()
    lifted = ObjectModel(model.pts + np.array([0.0, 0.0, 1.0]), model.faces)
    S = plane_reflection(lifted, [0, 0, 1])
    np.testing.assert_allclose(S.d, [0.0, 0.0, 2.0], atol=1e-9)
    R = Rotation.from_euler("xyz", [20, -35, 50], degrees=True).as_matrix()
    t = np.array([3.0, -2.0, 55.0])
    Rm, tm = S.pose(R, t)
    uv, uvm = _project(lifted.pts, R, t), _project(lifted.pts @ S.M.T + S.d, Rm, tm)
    np.testing.assert_allclose(uvm, np.c_[2 * K[0, 2] - uv[:, 0], uv[:, 1]], atol=1e-9)

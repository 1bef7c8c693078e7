"""`bopsurg import`: the AMBF pipeline's YAML layout and its BOP folders with obj_id 0.

The fixtures are built here by code in the pipeline's layout (YAML strings of numbers, PNGs,
a needle PLY in a frame of its own); a stand-in depth renderer fills the needle's silhouette.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bopsurg import plugins
from bopsurg.ambf_import import ambf_needle, import_ambf_yaml, import_bop_renumbered
from bopsurg.bop.check import check_dataset
from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.images import load_depth, save_depth, save_rgb
from bopsurg.bop.jsonio import load_json, save_json
from bopsurg.bop.meshes import ObjectModel, load_models_info, save_ply
from bopsurg.bop.scene import load_scene_gt
from bopsurg.cli.main import main
from bopsurg.errors import DatasetError, ModelError
from bopsurg.needle import fit_needle
from bopsurg.silhouette import project_silhouette

W, H = 160, 120
K = np.array([[88.0, 0.0, 80.0], [0.0, 88.0, 60.0], [0.0, 0.0, 1.0]])
KEYS = ("00000", "00010", "00020")


class SilhouetteRenderer:
    """Depth t_z over the model's filled silhouette (enough for masks of a thin needle)."""

    def render_depth(self, model, R, t, K, width, height):
        sil = project_silhouette(model.pts, model.faces, K, R, t, (height, width))
        return np.where(sil, t[2], 0.0)


def _poses() -> list[tuple[np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(3)
    out = []
    for _ in KEYS:
        R = Rotation.from_euler("xyz", rng.uniform(-40, 40, 3), degrees=True).as_matrix()
        out.append((R, np.array([*rng.uniform(-4, 4, 2), rng.uniform(45, 60)])))
    return out


def _fmt(values) -> str:
    return ",".join(f"{v: .8f}" for v in np.ravel(values))  # padded, as the pipeline writes


def write_ambf_yaml(root, model: ObjectModel, *, depth=True):
    """A folder of the pipeline's YAML layout: 3 frames, needle poses in ``model``'s frame."""
    (root / "raw_img").mkdir(parents=True)
    (root / "intrinsic.yaml").write_text(f"intrinsic: '{_fmt(K)}'\n")
    lines = []
    rng = np.random.default_rng(0)
    for key, (R, t) in zip(KEYS, _poses(), strict=True):
        lines += [f"'{key}':", f"  rot_model2cam: {_fmt(R)}", f"  t_model2cam: '{_fmt(t)}'", ""]
        save_rgb(root / "raw_img" / f"{key}.png", rng.integers(0, 255, (H, W, 3), dtype=np.uint8))
        if depth:
            sil = project_silhouette(model.pts, model.faces, K, R, t, (H, W))
            d = np.where(sil, np.round(t[2]), 90.0)  # 1 mm units; a phantom at 90 mm
            save_depth(root / "depth_img" / f"{key}.png", d)
    (root / "extrinsic.yaml").write_text("\n".join(lines))
    return root


@pytest.fixture
def their_needle(tmp_path):
    model = ambf_needle()
    path = tmp_path / "Needle.ply"
    save_ply(path, model)
    return path, model


def _import(src, out, model, **kw):
    return import_ambf_yaml(
        src, out, model=model, renderer=SilhouetteRenderer(), progress=False, **kw
    )


def test_import_gives_a_dataset_that_check_accepts(tmp_path, their_needle):
    ply, model = their_needle
    src = write_ambf_yaml(tmp_path / "scene1", model)
    out = tmp_path / "data"
    rep = _import(src, out, ply)
    assert rep.images == 3
    assert rep.with_depth
    assert check_dataset(out) == []
    ds = BopDataset(out, "test")
    scene = ds.scene(1)
    assert sorted(scene.gt) == [0, 10, 20]  # image ids are the frame numbers
    for (R, t), im_id in zip(_poses(), (0, 10, 20), strict=True):
        (gt,) = scene.gt[im_id]
        assert gt.obj_id == 1
        np.testing.assert_allclose(gt.R, R, atol=1e-8)
        assert gt.t == pytest.approx(t, abs=1e-7)
        np.testing.assert_allclose(scene.camera[im_id].K, K)
        assert scene.camera[im_id].depth_scale == 1.0
        assert load_depth(scene.depth_path(im_id)).max() == 90.0
    # Every needle pixel is in front of the phantom: visible.
    assert all(i[0].visib_fract == pytest.approx(1.0, abs=0.02) for i in scene.gt_info.values())
    assert rep.visib_fract == [i[0].visib_fract for _, i in sorted(scene.gt_info.items())]
    assert ds.model(1).pts == pytest.approx(model.pts, abs=1e-5)  # the user's frame, kept
    info = load_models_info(out / "models" / "models_info.json")[1]
    arc = fit_needle(model)
    assert info["keypoints"]["tip"] == pytest.approx(arc.tip.tolist(), abs=1e-4)
    assert info["plane_normal"] == pytest.approx(arc.normal.tolist(), abs=1e-6)
    assert (out / "test_targets_bop19.json").is_file()
    record = json.loads((out / "bopsurg_import.json").read_text())
    assert record["frames"] == {"00000": 0, "00010": 10, "00020": 20}
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_import_without_depth_and_with_the_built_in_needle(tmp_path):
    src = write_ambf_yaml(tmp_path / "s", ambf_needle(), depth=False)
    out = tmp_path / "data"
    rep = _import(src, out, None)
    assert not rep.with_depth
    assert check_dataset(out) == []
    assert not (out / "test" / "000001" / "depth").exists()


def _edit(path, old, new):
    path.write_text(path.read_text().replace(old, new, 1))


def _scale_first_rotation(src):
    lines = (src / "extrinsic.yaml").read_text().splitlines()
    key, values = lines[1].split(":")
    lines[1] = f"{key}: {_fmt(2 * np.array([float(v) for v in values.split(',')]))}"
    (src / "extrinsic.yaml").write_text("\n".join(lines))


@pytest.mark.parametrize(
    ("breakage", "match"),
    [
        (lambda s: (s / "intrinsic.yaml").unlink(), r"intrinsic\.yaml: file not found"),
        (lambda s: _edit(s / "intrinsic.yaml", "88.0", "eighty"), "intrinsic: expected 9"),
        (lambda s: _edit(s / "extrinsic.yaml", "'00010':", "'00010': ["), "not valid YAML"),
        (lambda s: _edit(s / "extrinsic.yaml", "'00010':", "00010:"), "quoted frame number"),
        (
            lambda s: _edit(s / "extrinsic.yaml", "  t_model2cam", "  t_m2c"),
            "00000/t_model2cam: missing",
        ),
        (_scale_first_rotation, "not a rotation"),
        (lambda s: (s / "raw_img" / "00010.png").unlink(), "frame 00010 .* has no image"),
        (lambda s: (s / "depth_img" / "00020.png").unlink(), "has no depth image"),
        (
            lambda s: shutil.copy(s / "raw_img" / "00000.png", s / "raw_img" / "00030.png"),
            "have no pose",
        ),
        (lambda s: (s / "depth_img" / "00010.png").write_bytes(b"garbage"), "cannot decode"),
        (
            lambda s: save_rgb(s / "raw_img" / "00020.png", np.zeros((10, 10, 3), np.uint8)),
            "size 10x10",
        ),
    ],
    ids=[
        "no-intrinsic",
        "bad-number",
        "bad-yaml",
        "octal-key",
        "missing-t",
        "not-rotation",
        "missing-image",
        "missing-depth",
        "unposed-image",
        "corrupt-depth",
        "other-size",
    ],
)
def test_bad_or_partial_input_is_one_line_and_writes_nothing(
    tmp_path, their_needle, breakage, match
):
    ply, model = their_needle
    src = write_ambf_yaml(tmp_path / "s", model)
    breakage(src)
    out = tmp_path / "data"
    with pytest.raises(DatasetError, match=match) as err:
        _import(src, out, ply)
    assert "\n" not in str(err.value)
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["Needle.ply", "s"]


def test_a_model_that_is_not_a_needle_is_refused(tmp_path, their_needle):
    src = write_ambf_yaml(tmp_path / "s", their_needle[1])
    box = tmp_path / "box.ply"
    g = np.array([[x, y, z] for x in (0, 9) for y in (0, 9) for z in (0, 9)], float)
    save_ply(box, ObjectModel(np.concatenate([g, g + 0.5]), np.zeros((0, 3))))
    with pytest.raises(ModelError, match=r"box\.ply: not a needle"):
        _import(src, tmp_path / "data", box)
    assert not (tmp_path / "data").exists()


def test_failure_while_writing_leaves_nothing(tmp_path, their_needle):
    class Broken:
        def render_depth(self, *a):
            raise RuntimeError("renderer died")

    src = write_ambf_yaml(tmp_path / "s", their_needle[1])
    with pytest.raises(RuntimeError):
        import_ambf_yaml(
            src, tmp_path / "data", model=their_needle[0], renderer=Broken(), progress=False
        )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["Needle.ply", "s"]


def test_out_must_be_new(tmp_path, their_needle):
    src = write_ambf_yaml(tmp_path / "s", their_needle[1])
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "x").write_text("keep me")
    with pytest.raises(DatasetError, match="not empty"):
        _import(src, tmp_path / "data", their_needle[0])
    assert (tmp_path / "data" / "x").read_text() == "keep me"


def _use_silhouette_renderer(monkeypatch):
    real = plugins.load_plugin
    monkeypatch.setattr(
        plugins,
        "load_plugin",
        lambda kind, name=None: SilhouetteRenderer if kind == "renderer" else real(kind, name),
    )


def test_cli_import_then_check(tmp_path, their_needle, capsys, monkeypatch):
    _use_silhouette_renderer(monkeypatch)
    src = write_ambf_yaml(tmp_path / "s", their_needle[1])
    out = tmp_path / "data"
    args = ["import", "ambf-yaml", str(src), "--out", str(out), "--model", str(their_needle[0])]
    assert main([*args, "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert "3 images" in text
    assert "next: bopsurg check" in text
    assert main(["check", str(out)]) == 0
    assert main([*args, "--no-progress"]) == 2  # out exists now
    assert "not empty" in capsys.readouterr().err


# --------------------------------------------------------------------------- obj_id 0


def _zero_based(tmp_path, monkeypatch):
    """A BOP dataset as the pipeline's BOP writer makes it: the needle is obj_id 0."""
    src = write_ambf_yaml(tmp_path / "s", ambf_needle())
    ok = tmp_path / "ok"
    _import(src, ok, None)
    zero = tmp_path / "zero"
    shutil.copytree(ok, zero)
    (zero / "models" / "obj_000001.ply").rename(zero / "models" / "obj_000000.ply")
    info = load_json(zero / "models" / "models_info.json", keys_to_int=True)
    save_json(zero / "models" / "models_info.json", {0: info[1]})
    gt_path = zero / "test" / "000001" / "scene_gt.json"
    gt = load_json(gt_path, keys_to_int=True)
    save_json(gt_path, {k: [{**g, "obj_id": 0} for g in v] for k, v in gt.items()})
    targets = load_json(zero / "test_targets_bop19.json")
    save_json(zero / "test_targets_bop19.json", [{**t, "obj_id": 0} for t in targets])
    coco_path = zero / "test" / "000001" / "scene_gt_coco.json"
    coco = load_json(coco_path)
    coco["annotations"] = [{**a, "category_id": 0} for a in coco["annotations"]]
    coco["categories"] = [{**c, "id": 0, "name": "0"} for c in coco["categories"]]
    save_json(coco_path, coco)
    return ok, zero


def test_check_names_obj_id_zero_first_and_how_to_fix_it(tmp_path, monkeypatch):
    _, zero = _zero_based(tmp_path, monkeypatch)
    problems = check_dataset(zero)
    assert problems
    first = str(problems[0])
    assert "obj_id 0" in first
    assert f"bopsurg import bop {zero} --out" in first
    assert "--obj-id-offset 1" in first
    assert len(check_dataset(zero, max_problems=1)) == 1


def test_renumbering_gives_the_dataset_with_ids_from_1(tmp_path, monkeypatch):
    ok, zero = _zero_based(tmp_path, monkeypatch)
    out = tmp_path / "fixed"
    rep = import_bop_renumbered(zero, out, obj_id_offset=1, progress=False)
    assert rep.obj_ids == {0: 1}
    assert check_dataset(out) == []
    assert load_scene_gt(out / "test" / "000001" / "scene_gt.json") == load_scene_gt(
        ok / "test" / "000001" / "scene_gt.json"
    )
    assert (out / "models" / "obj_000001.ply").read_bytes() == (
        ok / "models" / "obj_000001.ply"
    ).read_bytes()
    assert not (out / "models" / "obj_000000.ply").exists()
    coco = "test/000001/scene_gt_coco.json"
    assert load_json(out / coco) == load_json(ok / coco)  # 2D GT renumbered too
    bop24 = "test_targets_bop24.json"  # per-image targets name no object: copied
    assert load_json(out / bop24) == load_json(ok / bop24)
    with pytest.raises(DatasetError, match="below 1"):
        import_bop_renumbered(zero, tmp_path / "bad", obj_id_offset=0, progress=False)
    assert not (tmp_path / "bad").exists()


def test_renumbering_annotates_scenes_without_gt_info(tmp_path, monkeypatch):
    _use_silhouette_renderer(monkeypatch)
    _, zero = _zero_based(tmp_path, monkeypatch)
    scene = zero / "test" / "000001"
    (scene / "scene_gt_info.json").unlink()
    shutil.rmtree(scene / "mask")
    shutil.rmtree(scene / "mask_visib")
    out = tmp_path / "fixed"
    code = main(["import", "bop", str(zero), "--out", str(out), "--no-progress"])
    assert code == 0
    assert check_dataset(out) == []

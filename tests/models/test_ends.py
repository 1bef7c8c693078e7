"""The needle-end check: the half turn that swaps tip and tail keeps the arc on its pixels, the
patches sit where their frames say, the judge swaps only what its classifier says, its
trainer is seeded and learns ends it can see, and the estimator switches it."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from bopsurg.errors import BopsurgError
from bopsurg.needle import needle_mesh

torch = pytest.importorskip("torch")

from bopsurg.example import ExampleSpec, write_example_dataset  # noqa: E402
from bopsurg.models.checkpoint import load_checkpoint, save_checkpoint  # noqa: E402
from bopsurg.models.estimator import create  # noqa: E402
from bopsurg.models.predict_config import EndsSettings  # noqa: E402
from bopsurg.models.refine.arc import ArcModel  # noqa: E402
from bopsurg.models.refine.ends import (  # noqa: E402
    TAIL,
    TIP,
    EndConfig,
    EndJudge,
    EndNet,
    end_frames,
    half_turn,
    load_judge,
    sample_patches,
    swapped,
)
from tests.models.cli_errors import one_line_error  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")

K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
#: Options of an estimator without detector, refinement or end check.
BARE = {
    "detector": None,
    "device": "cpu",
    "refine": {"segmenter": None},
    "ends": {"classifier": None},
}
MODEL = needle_mesh()
ARC = ArcModel.from_keypoints(MODEL.pts[0], MODEL.pts[-1])


def _poses(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    R = Rotation.random(n, random_state=seed).as_matrix()
    t = np.stack([rng.uniform(-10, 10, n), rng.uniform(-10, 10, n), rng.uniform(50, 90, n)], 1)
    return R, t


def _project(R: np.ndarray, t: np.ndarray, X: np.ndarray) -> np.ndarray:
    cam = np.einsum("nij,kj->nki", R, X) + t[:, None]
    uv = cam @ K.T
    return uv[..., :2] / uv[..., 2:]


def test_the_half_turn_keeps_the_arc_on_its_pixels_and_swaps_its_ends():
    R, t = _poses(20)
    S = half_turn(ARC)
    np.testing.assert_allclose(S @ S, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(S), 1.0, atol=1e-12)
    R2 = swapped(R, ARC)
    np.testing.assert_allclose(np.linalg.det(R2), 1.0, atol=1e-12)
    line = ARC.points(101)  # tail to tip
    a, b = _project(R, t, line), _project(R2, t, line)
    np.testing.assert_allclose(b, a[:, ::-1], atol=1e-9)  # same pixels, run the other way
    cfg = EndConfig()
    uv, axis, side = end_frames(K, R, t, ARC, cfg)
    uv2, axis2, side2 = end_frames(K, R2, t, ARC, cfg)
    np.testing.assert_allclose(uv2[:, [TIP, TAIL]], uv, atol=1e-9)
    np.testing.assert_allclose(axis2[:, [TIP, TAIL]], axis, atol=1e-9)
    np.testing.assert_allclose(side2[:, [TIP, TAIL]], side, atol=1e-9)


def test_end_frames_sit_on_the_ends_and_point_out_of_the_arc():
    R, t = _poses(20, seed=1)
    uv, axis, side = end_frames(K, R, t, ARC, EndConfig(scale=0.8))
    line = _project(R, t, ARC.points(201))
    np.testing.assert_allclose(uv[:, TAIL], line[:, 0], atol=1e-9)
    np.testing.assert_allclose(uv[:, TIP], line[:, -1], atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(axis, axis=-1), 1.0, atol=1e-12)
    # outward: the arc's neighbouring points lie behind each end (where the arc is not seen
    # edge-on: there the image tangent is ill-defined)
    inward_tail = line[:, 5] - line[:, 0]
    inward_tip = line[:, -6] - line[:, -1]
    long = (np.linalg.norm(inward_tail, axis=1) > 1.0) & (np.linalg.norm(inward_tip, axis=1) > 1.0)
    assert long.sum() >= 10
    assert ((axis[:, TAIL] * inward_tail).sum(1)[long] < 0).all()
    assert ((axis[:, TIP] * inward_tip).sum(1)[long] < 0).all()
    z = (np.einsum("nij,j->ni", R, MODEL.pts[0]) + t)[:, 2]
    np.testing.assert_allclose(side[:, TAIL], 0.8 * K[0, 0] * ARC.radius / z, rtol=1e-3)
    # an end behind the camera has no frame
    uv_b, _, _ = end_frames(K, R[:1], t[:1] * np.array([1, 1, -1]), ARC, EndConfig())
    assert np.isnan(uv_b).all()


def test_patches_sample_the_image_where_their_frame_says():
    h, w = 120, 160
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    image = torch.from_numpy(np.stack([xs, ys, xs + ys]))[None]  # pixel coordinates
    centre = torch.tensor([[80.0, 60.0], [70.0, 50.0]])
    axis = torch.tensor([[1.0, 0.0], [0.0, 1.0]])  # along +x; along +y (turned +90 degrees)
    side = torch.tensor([16.0, 8.0])
    p = sample_patches(image, centre, axis, side, 8).numpy()
    g = (np.arange(8) + 0.5) / 8 - 0.5
    # patch 0: x runs along the patch's columns, y along its rows
    np.testing.assert_allclose(p[0, 0], np.broadcast_to(80 + 16 * g, (8, 8)), atol=1e-4)
    np.testing.assert_allclose(p[0, 1], np.broadcast_to((60 + 16 * g)[:, None], (8, 8)), atol=1e-4)
    # patch 1: its x axis is the image's +y, its y axis the image's -x
    np.testing.assert_allclose(p[1, 1], np.broadcast_to(50 + 8 * g, (8, 8)), atol=1e-4)
    np.testing.assert_allclose(p[1, 0], np.broadcast_to((70 - 8 * g)[:, None], (8, 8)), atol=1e-4)


def test_the_trainers_window_cut_is_the_test_time_cut():
    """Training cuts each patch from the window it covers; test time from the whole image."""
    from bopsurg.models.refine.train_ends import _cut

    rgb = (np.random.default_rng(0).random((120, 160, 3)) * 255).astype(np.uint8)
    image = torch.from_numpy(rgb).permute(2, 0, 1)[None].float()
    for c, a in (
        ([3.3, 5.9], [0.6, 0.8]),
        ([80.2, 60.7], [-1.0, 0.0]),
        ([158.0, 117.5], [0.0, 1.0]),
    ):
        full = (
            sample_patches(image, torch.tensor([c]), torch.tensor([a]), torch.tensor([30.0]), 24)[0]
            .round()
            .clamp(0, 255)
        )
        cut = torch.from_numpy(_cut(rgb, np.array(c), np.array(a), 30.0, 24)).float()
        assert (full - cut).abs().max() <= 1.0  # float rounding at a half


class _Bright(EndNet):
    """A stand-in classifier: the tip is the brighter patch (logit = mean intensity - 0.5)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x.mean(dim=(1, 2, 3)) - 0.5


def _frame_with_a_bright_tip(R: np.ndarray, t: np.ndarray) -> torch.Tensor:
    image = torch.zeros(1, 3, 480, 640)
    uv, _, side = end_frames(K, R[None], t[None], ARC, EndConfig())
    u, v = uv[0, TIP]
    r = int(0.4 * side[0, TIP])
    image[..., round(v) - r : round(v) + r, round(u) - r : round(u) + r] = 1.0
    return image


def test_the_judge_turns_only_the_poses_whose_tail_looks_like_the_tip():
    cfg = EndConfig()
    judge = EndJudge(_Bright(cfg), cfg, ARC)
    R = np.eye(3)[None].repeat(3, 0)
    t = np.array([[0.0, 0.0, 70.0]] * 3)
    image = _frame_with_a_bright_tip(R[0], t[0])
    wrong = swapped(R[:1], ARC)
    poses = np.concatenate([R[:1], wrong, R[:1]])
    t_in = t.copy()
    t_in[2, 2] = -70.0  # behind the camera: nothing to look at, left as it is
    out, swap = judge(image, K, poses, t_in)
    assert swap.tolist() == [False, True, False]
    np.testing.assert_allclose(out[0], R[0])
    np.testing.assert_allclose(out[1], R[0], atol=1e-12)  # turned back
    np.testing.assert_allclose(out[2], poses[2])
    assert np.isfinite(out).all()
    assert (judge.stats.checked, judge.stats.swapped) == (3, 1)
    again, _ = EndJudge(_Bright(cfg), cfg, ARC)(image, K, poses, t_in)
    assert np.array_equal(again, out)  # deterministic
    # a margin the logits do not reach keeps every pose
    kept, swap = EndJudge(_Bright(cfg), cfg, ARC, margin=10.0)(image, K, poses, t_in)
    assert not swap.any()
    np.testing.assert_array_equal(kept, poses)
    # a margin per pose (the estimator's 0 where the head was lost): only that pose may turn
    _, swap = EndJudge(_Bright(cfg), cfg, ARC, margin=10.0)(
        image, K, poses, t_in, np.array([10.0, 0.0, 0.0])
    )
    assert swap.tolist() == [False, True, False]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("ends")
    ds = write_example_dataset(root, ExampleSpec(seed=4, scenes=3, images_per_scene=3))
    shutil.copytree(ds.root / "test", ds.root / "train")
    return ds.root


def _train(dataset, out, *extra: str) -> int:
    from bopsurg.cli.main import main

    args = ["train", "ends", str(dataset), "--out", str(out), "--epochs", "1", "--batch-size", "8"]
    tiny = ["--set", "recipe.steps_per_epoch=4", "--set", "ends.patch=16"]
    return main([*args, *tiny, "--no-progress", *extra])


def test_the_trainer_is_seeded_records_its_run_and_loads(dataset, tmp_path):
    assert _train(dataset, tmp_path / "a") == 0
    assert _train(dataset, tmp_path / "b") == 0
    assert _train(dataset, tmp_path / "c", "--seed", "1") == 0
    a, info = load_checkpoint(tmp_path / "a" / "needle_ends.pt", "needle_ends")
    b, _ = load_checkpoint(tmp_path / "b" / "needle_ends.pt", "needle_ends")
    c, _ = load_checkpoint(tmp_path / "c" / "needle_ends.pt", "needle_ends")
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not all(torch.equal(a[k], c[k]) for k in a)
    assert info["config"]["patch"] == 16
    assert info["meta"]["ends"] > 0
    assert 0.0 <= info["meta"]["validation"]["val_accuracy"] <= 1.0
    judge = load_judge(tmp_path / "a" / "needle_ends.pt", torch.device("cpu"))
    assert judge.arc.radius == pytest.approx(ARC.radius, rel=1e-6)
    assert judge.margin == 0.0  # none chosen


def test_the_margin_chosen_for_a_classifier_travels_with_it(dataset, tmp_path):
    assert _train(dataset, tmp_path / "m", "--set", "recipe.margin=2.5") == 0
    path = tmp_path / "m" / "needle_ends.pt"
    assert load_checkpoint(path, "needle_ends")[1]["meta"]["margin"] == 2.5
    assert load_judge(path, torch.device("cpu")).margin == 2.5
    assert load_judge(path, torch.device("cpu"), margin=1.0).margin == 1.0
    # the estimator runs a classifier at the margin chosen for it, unless ends.margin is set
    opts = {**BARE, "ends": {"classifier": str(path)}}
    assert EndsSettings().margin is None
    assert create(opts).ends.judge.margin == 2.5
    assert create({**opts, "ends": {"classifier": str(path), "margin": 0}}).ends.judge.margin == 0
    info = load_checkpoint(path, "needle_ends")[1]
    save_checkpoint(
        path, load_checkpoint(path, "needle_ends")[0], kind="needle_ends",
        config=info["config"], meta={**info["meta"], "margin": float("nan")},
    )  # fmt: skip
    with pytest.raises(BopsurgError, match=r"meta\.margin"):
        load_judge(path, torch.device("cpu"))


def test_the_seen_ends_are_labelled_tip_and_tail(dataset):
    from bopsurg.bop.dataset import BopDataset
    from bopsurg.models.refine.arc import dataset_arc
    from bopsurg.models.refine.train_ends import collect_ends

    ds = BopDataset(dataset, "train")
    arc = dataset_arc(ds, 1)
    x, y = collect_ends(ds, ds.scene_ids, 1, arc, EndConfig(patch=16), progress=False)
    assert x.dtype == torch.uint8
    assert x.shape[1:] == (3, 32, 32)
    assert set(y.tolist()) == {0.0, 0.5, 1.0}  # tails, hidden ends, tips
    _, seen_y = collect_ends(
        ds, ds.scene_ids, 1, arc, EndConfig(patch=16), unseen=False, progress=False
    )
    assert set(seen_y.tolist()) == {0.0, 1.0}
    assert len(seen_y) == int((y != 0.5).sum())


def test_trainer_errors_are_one_line(dataset, tmp_path, capsys):
    assert _train(dataset, tmp_path / "x", "--split", "nope") == 2
    err = one_line_error(capsys)
    assert "nope" in err
    assert _train(dataset, tmp_path / "y", "--set", "recipe.margin=nan") == 2
    assert "margin must be a finite logit margin" in one_line_error(capsys)
    assert not (tmp_path / "y").exists()


def test_estimator_options_switch_the_end_check(dataset, tmp_path):
    assert _train(dataset, tmp_path / "e") == 0
    path = tmp_path / "e" / "needle_ends.pt"
    on = create({**BARE, "ends": {"classifier": str(path)}})
    assert on.ends is not None
    off = create(BARE)
    assert off.ends is None
    with pytest.raises(BopsurgError, match="does not exist"):
        create({**BARE, "ends": {"classifier": str(tmp_path / "no.pt")}})
    with pytest.raises(BopsurgError, match=r"ends\.margin"):
        create({**BARE, "ends": {"margin": "x"}})
    with pytest.raises(BopsurgError, match="finite"):
        create({**BARE, "ends": {"margin": float("nan")}})
    # a classifier of another needle than the refinement's segmenter is refused
    cfg = EndConfig(patch=16, width=2)
    other = tmp_path / "other.pt"
    meta = {"arc": {"radius": 5.0, "arc_rad": ARC.arc_rad}}
    save_checkpoint(
        other, EndNet(cfg).state_dict(), kind="needle_ends", config=cfg.to_dict(), meta=meta
    )
    fit = {**BARE, "refine": {"segmenter": "shipped"}}
    with pytest.raises(BopsurgError, match="trained for another needle"):
        create({**fit, "ends": {"classifier": str(other)}})
    assert create({**fit, "ends": {"classifier": str(path)}}).ends is not None


def test_a_checkpoint_of_another_kind_is_refused(tmp_path):
    cfg = EndConfig(patch=16, width=2)
    path = tmp_path / "x.pt"
    save_checkpoint(path, EndNet(cfg).state_dict(), kind="needle_seg", config=cfg.to_dict())
    with pytest.raises(BopsurgError):
        load_judge(path, torch.device("cpu"))


@pytest.mark.parametrize(("margin", "turned"), [(10.0, False), (0.0, True)])
def test_the_end_stage_turns_a_pose_whose_tail_wins_by_its_margin(margin, turned):
    """The margin is the pose head's say on which end is the tip: a bright tail turns the
    pose at margin 0, not at a margin above the classifier's say."""
    from bopsurg.models.stages.ends import EndStage

    cfg = EndConfig()
    stage = EndStage(EndJudge(_Bright(cfg), cfg, ARC, margin=margin))
    R, t = np.eye(3)[None], np.array([[0.0, 0.0, 70.0]])
    wrong = swapped(R, ARC)
    image = _frame_with_a_bright_tip(R[0], t[0])
    out = stage(image, K, wrong, t)
    np.testing.assert_allclose(out[0], R[0] if turned else wrong[0], atol=1e-12)
    assert stage.judge.stats.swapped == int(turned)
    assert ("turned 1 of 1" in stage.report()) == turned

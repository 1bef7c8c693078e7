"""The YOLOX-like detector: shapes, sizes, box ops, SimOTA, losses, training, augmentation, EMA."""

from __future__ import annotations

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from bopsurg.models.detector import (  # noqa: E402
    DetectorConfig,
    YoloxDetector,
    box_iou,
    letterbox_params,
    nms,
)
from bopsurg.models.detector.anchors import make_anchors  # noqa: E402
from bopsurg.models.detector.assign import (  # noqa: E402
    dynamic_k_matching,
    simota_assign,
    simota_assign_batch,
)
from bopsurg.models.detector.augment import (  # noqa: E402
    hsv_jitter,
    hsv_to_rgb,
    random_affine,
    random_flip,
    rgb_to_hsv,
)
from bopsurg.models.detector.boxes import batched_nms, xyxy_to_cxcywh  # noqa: E402
from bopsurg.models.detector.letterbox import (  # noqa: E402
    PAD_GREY,
    PAD_VALUE,
    image_to_input_boxes,
    input_to_image_boxes,
    letterbox,
)
from bopsurg.models.ema import ModelEMA  # noqa: E402

TEST_HW = (64, 96)


@pytest.fixture(autouse=True)
def _one_thread():
    """One intra-op thread: the tiny models gain nothing from more, and on a shared CPU other
    jobs slow multi-threaded runs down by an order of magnitude."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def n_anchors(hw: tuple[int, int]) -> int:
    return sum((hw[0] // s) * (hw[1] // s) for s in (8, 16, 32))


def n_params(model: torch.nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def synthetic_batch(seed: int, n: int = 4) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """White rectangles (one per image) on dark noise, at the test input size."""
    g = torch.Generator().manual_seed(seed)
    h, w = TEST_HW
    images = torch.rand(n, 3, h, w, generator=g) * 0.5
    targets = []
    for i in range(n):
        bw, bh = (
            int(torch.randint(16, 40, (1,), generator=g)),
            int(torch.randint(12, 30, (1,), generator=g)),
        )
        x1, y1 = (
            int(torch.randint(0, w - bw, (1,), generator=g)),
            int(torch.randint(0, h - bh, (1,), generator=g)),
        )
        images[i, :, y1 : y1 + bh, x1 : x1 + bw] = 1.0
        targets.append(torch.tensor([[0.0, x1, y1, x1 + bw, y1 + bh]]))
    return images, targets


# --------------------------------------------------------------------------------- config
def test_config_json_round_trip_and_validation():
    cfg = DetectorConfig.preset("s", num_classes=3)
    assert cfg.input_hw == (480, 640)
    assert cfg.width == 0.5
    assert DetectorConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    assert DetectorConfig() == DetectorConfig.preset("cpu")
    with pytest.raises(ValueError, match="bogus"):
        DetectorConfig.from_dict({**cfg.to_dict(), "bogus": 1})
    with pytest.raises(ValueError, match="multiples of 32"):
        DetectorConfig(input_hw=(240, 320))
    with pytest.raises(ValueError, match="unknown detector preset"):
        DetectorConfig.preset("huge")


# -------------------------------------------------------------------------------- network
@pytest.mark.parametrize(("hw", "num_classes"), [(TEST_HW, 1), ((64, 64), 3), ((96, 64), 2)])
def test_forward_and_decode_shapes(hw, num_classes):
    model = YoloxDetector(DetectorConfig.preset("test", num_classes=num_classes)).eval()
    with torch.no_grad():
        raw = model(torch.rand(2, 3, *hw))
    assert raw.shape == (2, n_anchors(hw), 5 + num_classes)
    dec = model.decode(raw)
    assert dec.shape == (2, n_anchors(hw), 5 + num_classes)
    assert torch.all(dec[..., 2:4] > dec[..., :2])
    assert torch.all((dec[..., 4:] >= 0) & (dec[..., 4:] <= 1))


def test_decode_of_zero_raw_is_a_stride_sized_box_at_each_cell_corner():
    model = YoloxDetector(DetectorConfig.preset("test"))
    raw = torch.zeros(1, n_anchors(TEST_HW), 6)
    dec = model.decode(raw, input_hw=TEST_HW)[0]
    # first anchor: level stride 8, cell (0, 0); second: cell (j=1, i=0); last: stride 32
    assert torch.allclose(dec[0, :4], torch.tensor([-4.0, -4.0, 4.0, 4.0]))
    assert torch.allclose(dec[1, :4], torch.tensor([4.0, -4.0, 12.0, 4.0]))
    assert torch.allclose(dec[-1, :4], torch.tensor([64.0 - 16, 32.0 - 16, 64.0 + 16, 32.0 + 16]))
    assert torch.allclose(dec[:, 4:], torch.full_like(dec[:, 4:], 0.5))
    # grids are cached per input size and device
    assert model.anchors(TEST_HW, raw.device)[0] is model.anchors(TEST_HW, raw.device)[0]


def test_training_step_after_inference_mode_detection():
    model = YoloxDetector(DetectorConfig.preset("test"))
    images, targets = synthetic_batch(seed=1, n=2)
    with torch.inference_mode():
        model.detect(images)  # fills the anchor cache
    model.loss(model(images), targets, use_l1=True)["total"].backward()


def test_parameter_counts_match_yolox_nano_and_plain():
    plain = n_params(YoloxDetector(DetectorConfig.preset("cpu")))
    depthwise = n_params(YoloxDetector(DetectorConfig.preset("cpu", depthwise=True)))
    assert 2.0e6 < plain < 2.5e6  # 2.24 M
    assert 0.8e6 < depthwise < 1.0e6  # 0.90 M, YOLOX-nano's README figure (0.91 M)


# ---------------------------------------------------------------------------------- boxes
def test_box_iou_hand_worked_values():
    a = torch.tensor([[0.0, 0, 2, 2], [0, 0, 4, 2]])
    b = torch.tensor([[1.0, 1, 3, 3], [0, 0, 2, 2], [5, 5, 6, 6]])
    expected = torch.tensor([[1 / 7, 1.0, 0.0], [0.2, 0.5, 0.0]])
    assert torch.allclose(box_iou(a, b), expected)


def _reference_nms(boxes, scores, thr):
    order = sorted(range(len(boxes)), key=lambda i: -float(scores[i]))
    keep = []
    for i in order:
        if all(float(box_iou(boxes[i : i + 1], boxes[k : k + 1])) <= thr for k in keep):
            keep.append(i)
    return keep


@pytest.mark.parametrize("thr", [0.3, 0.5, 0.7])
def test_nms_equals_reference_loop(thr):
    g = torch.Generator().manual_seed(7)
    xy = torch.rand(60, 2, generator=g) * 50
    boxes = torch.cat((xy, xy + 5 + torch.rand(60, 2, generator=g) * 20), dim=1)
    scores = torch.rand(60, generator=g)
    keep = nms(boxes, scores, thr)
    assert keep.tolist() == _reference_nms(boxes, scores, thr)
    assert len(keep) < 60


def test_batched_nms_keeps_overlapping_boxes_of_other_classes():
    boxes = torch.tensor([[-5.0, 0, 10, 10], [-5.0, 0, 10, 10], [-4.0, 0, 10, 10]])
    scores = torch.tensor([0.9, 0.8, 0.7])
    assert batched_nms(boxes, scores, torch.tensor([0, 1, 0]), 0.5).tolist() == [0, 1]
    assert nms(boxes, scores, 0.5).tolist() == [0]
    assert nms(torch.zeros(0, 4), torch.zeros(0), 0.5).shape == (0,)


@pytest.mark.parametrize(
    ("src", "expected"), [((480, 640), (0.5, 0, 16)), ((375, 500), (0.64, 0, 16))]
)
def test_letterbox_params_and_box_round_trip(src, expected):
    scale, pad_x, pad_y = letterbox_params(src, (256, 320))
    assert scale == pytest.approx(expected[0])
    assert (pad_x, pad_y) == expected[1:]
    boxes = torch.tensor([[10.0, 20, 200, 300], [0, 0, src[1], src[0]]])
    back = input_to_image_boxes(image_to_input_boxes(boxes, scale), scale, src)
    assert torch.allclose(back, boxes, atol=1e-4)
    image = np.random.default_rng(0).integers(0, 255, (*src, 3), dtype=np.uint8)
    boxed, s = letterbox(image, (256, 320))
    assert boxed.shape == (256, 320, 3)
    assert s == scale
    assert np.all(boxed[256 - pad_y :] == PAD_GREY)
    assert np.all(boxed[:, 320 - pad_x :] == PAD_GREY)
    assert np.any(boxed[: 256 - pad_y, : 320 - pad_x] != PAD_GREY)  # the image fills the rest


# --------------------------------------------------------------------------------- SimOTA
def test_simota_gives_every_gt_a_positive_and_each_anchor_one_gt():
    model = YoloxDetector(DetectorConfig.preset("test"))
    grid, strides = model.anchors(TEST_HW, "cpu")
    centers = (grid + 0.5) * strides[:, None]
    g = torch.Generator().manual_seed(3)
    a = len(grid)
    raw = torch.randn(a, 6, generator=g) * 0.5
    pred = torch.cat((centers + raw[:, :2] * 4, strides[:, None].expand(a, 2) * 2), dim=1)
    gt = xyxy_to_cxcywh(torch.tensor([[4.0, 4, 30, 28], [50, 10, 90, 60], [30, 30, 50, 50]]))
    out = simota_assign(
        pred, raw[:, 4], raw[:, 5:], centers, strides, gt, torch.zeros(3, dtype=torch.long)
    )
    assert out.num_fg >= 3
    assert torch.equal(out.gt_index >= 0, out.fg_mask)
    assert set(out.gt_index[out.fg_mask].tolist()) == {0, 1, 2}
    assert torch.all(out.iou[out.fg_mask] > 0)
    assert torch.all(out.iou[~out.fg_mask] == 0)


def test_dynamic_k_matching_gives_shared_anchors_to_the_cheaper_gt():
    cost = torch.tensor([[1.0, 2.0, 9.0, 9.0], [3.0, 1.0, 2.0, 9.0]])
    ious = torch.tensor([[0.9, 0.9, 0.0, 0.0], [0.9, 0.9, 0.9, 0.0]])  # dynamic_k = 1 and 2
    matching = dynamic_k_matching(cost, ious)
    assert matching.sum(dim=0).le(1).all()
    assert matching.tolist() == [[True, False, False, False], [False, True, True, False]]
    # both GTs want anchor 0: it goes to GT 0 (cost 1 < 3)
    m2 = dynamic_k_matching(torch.tensor([[1.0, 5.0], [3.0, 4.0]]), torch.full((2, 2), 0.6))
    assert m2.tolist() == [[True, False], [False, False]]


# ---------------------------------------------------------------------------------- losses
def test_loss_on_an_empty_image_is_finite_and_only_objectness():
    model = YoloxDetector(DetectorConfig.preset("test"))
    raw = model(torch.rand(2, 3, *TEST_HW))
    losses = model.loss(raw, [torch.zeros(0, 5), torch.zeros(0, 5)], use_l1=True)
    assert all(torch.isfinite(v) for v in losses.values())
    assert losses["obj"] > 0
    assert losses["num_fg"] == 0
    assert losses["iou"] == 0
    assert losses["cls"] == 0
    assert losses["l1"] == 0
    losses["total"].backward()


def test_loss_keys_with_l1():
    model = YoloxDetector(DetectorConfig.preset("test", num_classes=2))
    raw = model(torch.rand(2, 3, *TEST_HW))
    targets = [torch.tensor([[1.0, 10, 10, 40, 30], [0, 50, 20, 90, 60]]), torch.zeros(0, 5)]
    losses = model.loss(raw, targets, use_l1=True)
    assert set(losses) == {"iou", "obj", "cls", "l1", "total", "num_fg"}
    assert losses["num_fg"] >= 2
    assert losses["l1"] > 0
    parts = losses["iou"] + losses["obj"] + losses["cls"] + losses["l1"]
    assert torch.allclose(losses["total"], parts)


def _recalibrate_batchnorm(model: torch.nn.Module, images: torch.Tensor) -> None:
    """Running BN statistics = the batch's (momentum 0.03 needs ~100 steps to converge)."""
    for m in model.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.reset_running_stats()
            m.momentum = None  # cumulative average
    with torch.no_grad():
        model.train()(images)


def test_training_reduces_the_loss_and_then_detects_the_boxes():
    torch.manual_seed(0)
    images, targets = synthetic_batch(seed=0)
    model = YoloxDetector(DetectorConfig.preset("test"))
    opt = torch.optim.Adam(model.parameters(), lr=5e-3)
    history = []
    for _ in range(50):
        losses = model.loss(model(images), targets)
        opt.zero_grad()
        losses["total"].backward()
        opt.step()
        history.append(float(losses["total"].detach()))
    first, last = sum(history[:3]) / 3, sum(history[-5:]) / 5
    assert last < 0.5 * first, history

    _recalibrate_batchnorm(model, images)
    dets = model.detect(images, conf_thr=0.01)
    assert model.training  # detect() restores the mode
    hits = 0
    for d, t in zip(dets, targets, strict=True):
        assert d.shape[1] == 6
        assert torch.all(d[:-1, 4] >= d[1:, 4])
        hits += bool(len(d)) and float(box_iou(d[:1, :4], t[:, 1:])[0, 0]) > 0.5
    assert hits >= 3, dets


# ---------------------------------------------------------------------------- augmentation
def _rect_batch(gen: torch.Generator, n: int = 6) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """Filled white rectangles on black, strictly inside the image; boxes in input px."""
    h, w = TEST_HW
    images = torch.zeros(n, 3, h, w)
    boxes = []
    for i in range(n):
        x1, y1 = (
            int(torch.randint(2, 50, (1,), generator=gen)),
            int(torch.randint(2, 30, (1,), generator=gen)),
        )
        x2, y2 = (
            x1 + int(torch.randint(8, 40, (1,), generator=gen)),
            y1 + int(torch.randint(8, 28, (1,), generator=gen)),
        )
        x2, y2 = min(x2, w - 2), min(y2, h - 2)
        images[i, :, y1:y2, x1:x2] = 1.0
        boxes.append(torch.tensor([[float(i % 2), x1, y1, x2, y2]]))
    return images, boxes


def _mask_bbox(mask: torch.Tensor) -> torch.Tensor:
    ys, xs = mask.nonzero(as_tuple=True)
    return torch.tensor([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], dtype=torch.float32)


def test_flip_twice_is_identity_and_boxes_follow_the_pixels():
    gen = torch.Generator().manual_seed(1)
    images, boxes = _rect_batch(gen)
    once, boxes1 = random_flip(images, boxes, torch.Generator().manual_seed(5), p=1.0)
    for img, b in zip(once, boxes1, strict=True):
        assert torch.equal(_mask_bbox(img[0] > 0.5), b[0, 1:])
    twice, boxes2 = random_flip(once, boxes1, torch.Generator().manual_seed(5), p=1.0)
    assert torch.equal(twice, images)
    assert all(torch.equal(a, b) for a, b in zip(boxes2, boxes, strict=True))


def test_affine_moves_boxes_with_the_pixels():
    gen = torch.Generator().manual_seed(2)
    images, boxes = _rect_batch(gen, n=8)
    out, new_boxes = random_affine(images, boxes, torch.Generator().manual_seed(11), translate=0.2)
    assert out.shape == images.shape
    kept = 0
    for img, old, new in zip(out, boxes, new_boxes, strict=True):
        assert new.shape[1] == 5
        if len(new):
            kept += 1
            assert new[0, 0] == old[0, 0]  # class kept
            # the fill (114/255) and the black background are below 0.5, the rectangle above
            assert torch.allclose(_mask_bbox(img[0] > 0.5), new[0, 1:], atol=2.0)
    assert kept >= 4
    # same generator seed -> same result
    again, _ = random_affine(images, boxes, torch.Generator().manual_seed(11), translate=0.2)
    assert torch.equal(out, again)


def test_affine_fills_borders_and_drops_boxes_pushed_out():
    images = torch.zeros(1, 3, *TEST_HW)
    boxes = [torch.tensor([[0.0, 0, 0, 10, 10], [0.0, 40, 20, 60, 40]])]
    # zoom out by 0.5 about the centre: the border is filled, both boxes stay (shrunk)
    out, nb = random_affine(
        images, boxes, torch.Generator().manual_seed(0), scale=(0.5, 0.5), translate=0.0
    )
    assert torch.allclose(out[0, :, 0, 0], torch.full((3,), PAD_VALUE))
    assert torch.allclose(nb[0][:, 1:], torch.tensor([[24.0, 16, 29, 21], [44, 26, 54, 36]]))
    # zoom in by 3: the corner box leaves the image and is dropped
    _, nb = random_affine(
        images, boxes, torch.Generator().manual_seed(0), scale=(3.0, 3.0), translate=0.0
    )
    assert len(nb[0]) == 1


def test_hsv_conversion_round_trip_and_jitter():
    g = torch.Generator().manual_seed(4)
    images = torch.rand(3, 3, 16, 24, generator=g)
    assert torch.allclose(hsv_to_rgb(rgb_to_hsv(images)), images, atol=1e-5)
    assert torch.equal(
        hsv_jitter(images, torch.Generator().manual_seed(0), 0, 0, 0),
        hsv_to_rgb(rgb_to_hsv(images)),
    )
    out = hsv_jitter(images, torch.Generator().manual_seed(0))
    assert out.shape == images.shape
    assert out.min() >= 0
    assert out.max() <= 1
    assert not torch.allclose(out, images, atol=1e-3)


def test_hsv_jitter_spins_the_whole_hue_circle_for_its_share_only():
    """``whole``: that share of the images gets any hue, the rest keep ``h``'s small shift;
    0 draws nothing more, so older recipes see the same colours."""
    red = torch.zeros(2000, 3, 2, 2)
    red[:, 0] = 1.0
    # whole = 0 takes the three draws of the old jitter (hue, saturation, value) and no more;
    # any share takes more, so the runs after it see other numbers
    for whole, more in ((0.0, False), (0.3, True)):
        used, old = torch.Generator().manual_seed(1), torch.Generator().manual_seed(1)
        hsv_jitter(red, used, whole=whole)
        for _ in range(3):
            torch.rand(len(red), generator=old)
        assert torch.equal(torch.rand(8, generator=used), torch.rand(8, generator=old)) != more
    hue = rgb_to_hsv(hsv_jitter(red, torch.Generator().manual_seed(1), 0.0, 0, 0, 0.3))
    turn = torch.minimum(hue[:, 0, 0, 0], 1 - hue[:, 0, 0, 0])  # distance from red, turns
    spun = turn > 1e-4
    assert 0.25 < spun.float().mean() < 0.35
    counts = torch.histc(hue[spun, 0, 0, 0], bins=4, min=0, max=1)
    assert counts.min() > 0.15 * spun.sum()  # every quarter of the circle


# --------------------------------------------------------------------------------------- EMA
def test_ema_lies_between_and_round_trips():
    torch.manual_seed(0)
    model = torch.nn.Sequential(torch.nn.Linear(4, 3), torch.nn.BatchNorm1d(3))
    ema = ModelEMA(model, decay=0.9, tau=1.0)
    old = [p.detach().clone() for p in ema.ema.parameters()]
    with torch.no_grad():
        for p in model.parameters():
            p.add_(1.0)
    ema.update(model)
    d = 0.9 * (1 - torch.exp(torch.tensor(-1.0)))
    for o, e, new in zip(old, ema.ema.parameters(), model.parameters(), strict=True):
        assert torch.all(e > torch.minimum(o, new))
        assert torch.all(e < torch.maximum(o, new))
        assert torch.allclose(e, d * o + (1 - d) * new)
    assert not ema.ema.training
    assert not any(p.requires_grad for p in ema.ema.parameters())

    other = ModelEMA(torch.nn.Sequential(torch.nn.Linear(4, 3), torch.nn.BatchNorm1d(3)))
    other.load_state_dict(ema.state_dict())
    assert other.updates == 1
    assert other.decay == 0.9
    assert other.tau == 1.0
    for a, b in zip(other.ema.state_dict().values(), ema.ema.state_dict().values(), strict=True):
        assert torch.equal(a, b)


# -------------------------------------------------------------------------------------- CUDA
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_forward_loss_detect_and_augment_on_cuda():
    device = torch.device("cuda")
    model = YoloxDetector(DetectorConfig.preset("test")).to(device)
    images, targets = synthetic_batch(seed=0)
    images, targets = images.to(device), [t.to(device) for t in targets]
    gen = torch.Generator().manual_seed(0)
    images = hsv_jitter(images, gen)
    images, targets = random_flip(images, targets, gen)
    images, targets = random_affine(images, targets, gen)
    assert images.device.type == "cuda"
    assert all(t.device.type == "cuda" for t in targets)
    losses = model.loss(model(images), targets, use_l1=True)
    losses["total"].backward()
    assert torch.isfinite(losses["total"])
    dets = model.detect(images)
    assert len(dets) == 4
    assert all(d.device.type == "cuda" for d in dets)
    ema = ModelEMA(model)
    ema.update(model)


def test_the_batched_simota_assigns_each_image_as_the_per_image_one():
    """64 images of 0-3 GTs (padded), random predictions: the batched assignment is the
    per-image one, image by image (positives, matched GT, IoU)."""
    grid, strides = make_anchors((256, 320), (8, 16, 32), torch.device("cpu"))
    centers = (grid + 0.5) * strides[:, None]
    g = torch.Generator().manual_seed(0)
    B, A, C = 64, len(grid), 3
    size = torch.tensor([320.0, 256.0])
    pred = torch.cat(
        [torch.rand(B, A, 2, generator=g) * size, 5 + 60 * torch.rand(B, A, 2, generator=g)], -1
    )
    obj, cls = torch.randn(B, A, generator=g), torch.randn(B, A, C, generator=g)
    n = torch.randint(0, 4, (B,), generator=g)
    G = int(n.max())
    gt = torch.cat(
        [torch.rand(B, G, 2, generator=g) * size, 4 + 80 * torch.rand(B, G, 2, generator=g)], -1
    )
    gt_cls = torch.randint(0, C, (B, G), generator=g)
    batch = simota_assign_batch(
        pred, obj, cls, centers, strides, gt, gt_cls, torch.arange(G) < n[:, None]
    )
    assert int(batch.fg_mask.sum()) > 0
    for b in range(B):
        one = simota_assign(pred[b], obj[b], cls[b], centers, strides, gt[b, : n[b]],
                            gt_cls[b, : n[b]])  # fmt: skip
        assert torch.equal(one.fg_mask, batch.fg_mask[b])
        assert torch.equal(one.gt_index, batch.gt_index[b])
        torch.testing.assert_close(one.iou, batch.iou[b])
    none = simota_assign_batch(
        pred, obj, cls, centers, strides, gt[:, :0], gt_cls[:, :0], torch.zeros(B, 0, dtype=bool)
    )
    assert not none.fg_mask.any()

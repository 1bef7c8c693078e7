"""Training-time photometric augmentations (models/photometric.py): each op does what it says,
draws only from its sample's seed, and keeps images in [0, 1] with their dtype."""

from __future__ import annotations

import math

import pytest

torch = pytest.importorskip("torch")
cv2 = pytest.importorskip("cv2")

from bopsurg.models.photometric import (  # noqa: E402
    PhotometricConfig,
    augment_batch,
    augment_one,
    batch_seeds,
    gaussian_blur,
    jpeg_round_trip,
    sample_seed,
)

ON = {"blur_p": 1.0, "noise_p": 1.0, "gamma_p": 1.0, "colour_p": 1.0, "jpeg_p": 1.0}


def _images(n: int = 3, h: int = 24, w: int = 32) -> torch.Tensor:
    gen = torch.Generator().manual_seed(7)
    return torch.rand((n, 3, h, w), generator=gen)


def _only(op: str, **ranges: object) -> PhotometricConfig:
    return PhotometricConfig(**{f"{op}_p": 1.0, **ranges})  # type: ignore[arg-type]


def test_off_by_default_and_the_same_tensor_comes_back():
    imgs = _images()
    assert not PhotometricConfig().active
    assert augment_batch(imgs, PhotometricConfig(), [1, 2, 3]) is imgs


def test_same_seed_same_tensor_other_seed_other_tensor():
    cfg = PhotometricConfig.from_dict({"preset": "domain", **ON})
    imgs = _images()
    a = augment_batch(imgs, cfg, [11, 12, 13])
    b = augment_batch(imgs.clone(), cfg, [11, 12, 13])
    torch.testing.assert_close(a, b, rtol=0, atol=0)
    c = augment_batch(imgs, cfg, [11, 12, 14])
    torch.testing.assert_close(a[:2], c[:2], rtol=0, atol=0)  # per sample, not per batch
    assert not torch.equal(a[2], c[2])


def test_a_sample_does_not_depend_on_its_batch():
    cfg = PhotometricConfig(**ON)
    imgs = _images()
    alone = augment_batch(imgs[1:2], cfg, [5])
    together = augment_batch(imgs, cfg, [4, 5, 6])
    torch.testing.assert_close(alone[0], together[1], rtol=0, atol=0)


def test_sample_seeds_differ_by_seed_epoch_and_index():
    seeds = {sample_seed(s, e, i) for s in range(3) for e in range(3) for i in range(20)}
    assert len(seeds) == 180
    assert batch_seeds(0, 1, torch.tensor([3, 4])) == [sample_seed(0, 1, 3), sample_seed(0, 1, 4)]
    assert sample_seed(0, 0, 0) == sample_seed(0, 0, 0)


def test_gamma_maps_a_half_to_a_half_to_the_power_g():
    img = torch.full((3, 8, 8), 0.5)
    for g in (0.6, 1.0, 1.8):
        out = augment_one(img, _only("gamma", gamma=(g, g)), torch.Generator().manual_seed(1))
        torch.testing.assert_close(out, torch.full_like(img, 0.5**g))


def test_gamma_is_drawn_log_uniformly_within_its_range():
    img = torch.full((3, 2, 2), 0.5)
    cfg = _only("gamma", gamma=(0.5, 2.0))
    gs = [
        math.log(float(augment_one(img, cfg, torch.Generator().manual_seed(s))[0, 0, 0]))
        / math.log(0.5)
        for s in range(200)
    ]
    assert min(gs) >= 0.5
    assert max(gs) <= 2.0
    assert sum(g < 1 for g in gs) == pytest.approx(100, abs=25)  # log-uniform: median 1


def test_blur_equals_opencv_gaussian_and_keeps_a_flat_image():
    img = _images(1, 32, 40)[0]
    sigma = 1.3
    ours = gaussian_blur(img, sigma)
    r = math.ceil(3 * sigma)
    ref = cv2.GaussianBlur(
        img.permute(1, 2, 0).numpy(),
        (2 * r + 1, 2 * r + 1),
        sigma,
        borderType=cv2.BORDER_REFLECT_101,
    )
    torch.testing.assert_close(ours, torch.from_numpy(ref).permute(2, 0, 1), atol=1e-5, rtol=0)
    flat = torch.full((3, 16, 16), 0.3)
    torch.testing.assert_close(gaussian_blur(flat, 1.0), flat)
    out = augment_one(img, _only("blur", blur_sigma=(1.0, 1.0)), torch.Generator().manual_seed(0))
    assert out.std() < img.std()


def test_noise_has_the_drawn_standard_deviation():
    img = torch.full((3, 64, 64), 0.5)
    out = augment_one(img, _only("noise", noise_std=(0.05, 0.05)), torch.Generator().manual_seed(3))
    assert float((out - img).std()) == pytest.approx(0.05, rel=0.05)
    assert float((out - img).mean()) == pytest.approx(0.0, abs=0.005)


def test_colour_applies_contrast_brightness_and_channel_gain():
    img = _images(1)[0] * 0.5 + 0.25
    cfg = _only("colour", brightness=0.0, contrast=(1.5, 1.5), channel_gain=0.0)
    out = augment_one(img, cfg, torch.Generator().manual_seed(0))
    m = img.mean()
    torch.testing.assert_close(out, ((img - m) * 1.5 + m).clamp(0, 1))
    cfg = _only("colour", brightness=0.0, contrast=(1.0, 1.0), channel_gain=0.2)
    out = augment_one(img, cfg, torch.Generator().manual_seed(0))
    gains = (out / img).flatten(1)
    assert torch.allclose(gains.min(1).values, gains.max(1).values, atol=1e-5)  # one per channel
    assert ((gains[:, 0] >= 0.8 - 1e-6) & (gains[:, 0] <= 1.2 + 1e-6)).all()


def test_jpeg_changes_the_image_less_at_higher_quality():
    img = _images(1, 32, 32)[0]
    low, high = jpeg_round_trip(img, 10), jpeg_round_trip(img, 95)
    assert (low - img).abs().mean() > (high - img).abs().mean() > 0
    assert high.dtype == img.dtype
    assert high.shape == img.shape


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_every_op_keeps_range_shape_and_dtype(dtype):
    cfg = PhotometricConfig(
        **ON, noise_std=(0.3, 0.3), brightness=0.5, contrast=(2.0, 2.0), gamma=(0.3, 3.0)
    )
    imgs = _images().to(dtype)
    out = augment_batch(imgs, cfg, [1, 2, 3])
    assert out.shape == imgs.shape
    assert out.dtype == dtype
    assert float(out.min()) >= 0.0
    assert float(out.max()) <= 1.0
    assert not torch.equal(out, imgs)


def test_switching_one_op_off_leaves_the_others_draws_alone():
    img = torch.full((3, 8, 8), 0.5)
    gamma_only = _only("gamma")
    with_noise_off_but_blur = PhotometricConfig(gamma_p=1.0, blur_p=1.0, blur_sigma=(0.0, 0.0))
    a = augment_one(img, gamma_only, torch.Generator().manual_seed(9))
    b = augment_one(img, with_noise_off_but_blur, torch.Generator().manual_seed(9))
    torch.testing.assert_close(a, b)  # a zero blur changes nothing, and gamma drew the same g


def test_config_validation_presets_and_round_trip():
    with pytest.raises(ValueError, match="gamma"):
        PhotometricConfig(gamma=(2.0, 1.0))
    with pytest.raises(ValueError, match="blur_p"):
        PhotometricConfig(blur_p=1.5)
    with pytest.raises(ValueError, match="unknown augment key"):
        PhotometricConfig.from_dict({"sharpen_p": 0.5})
    with pytest.raises(ValueError, match="unknown augment preset"):
        PhotometricConfig.from_dict({"preset": "heavy"})
    domain = PhotometricConfig.from_dict({"preset": "domain", "jpeg_p": 0.9})
    assert domain.active
    assert domain.jpeg_p == 0.9
    assert domain.blur_p == 0.3
    assert PhotometricConfig.from_dict(domain.to_dict()) == domain

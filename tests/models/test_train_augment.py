"""The batched photometric augmentation (``augment_batch``: every operation on the whole batch
at once, as a GPU trainer needs) against the per-sample reference (``augment_one``): the same
draws give the same images, up to float rounding; the JPEG round trip exactly."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")

from bopsurg.models.photometric import (  # noqa: E402
    PhotometricConfig,
    augment_batch,
    augment_one,
    sample_seed,
)


def _images(n: int, hw=(24, 20), seed=0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    base = torch.rand((n, 3, *hw), generator=g)
    return (base + torch.linspace(0, 0.5, hw[1])).clamp(0, 1)  # some structure to blur


def _one_at_a_time(images, cfg, seeds):
    return torch.stack(
        [
            augment_one(im, cfg, torch.Generator().manual_seed(s))
            for im, s in zip(images, seeds, strict=True)
        ]
    )


@pytest.mark.parametrize(
    "values",
    [
        {"blur_p": 0.5, "noise_p": 0.5, "gamma_p": 0.5, "colour_p": 0.5},
        {"blur_p": 1.0, "noise_p": 1.0, "gamma_p": 1.0, "colour_p": 1.0},
        {"blur_p": 1.0, "blur_sigma": (0.0, 9.0)},  # sigma 0 (none) .. wider than the image
        {"colour_p": 1.0, "brightness": 0.3, "channel_gain": 0.4, "contrast": (0.5, 1.5)},
    ],
    ids=["half", "all", "blur widths", "colour"],
)
def test_the_batch_equals_each_image_augmented_alone(values):
    cfg = PhotometricConfig(**values)
    seeds = [sample_seed(3, 1, i) for i in range(16)]
    images = _images(16)
    batched = augment_batch(images, cfg, seeds)
    torch.testing.assert_close(batched, _one_at_a_time(images, cfg, seeds), rtol=0, atol=2e-6)
    assert not torch.equal(batched, images)


def test_jpeg_round_trips_are_the_reference_ones_exactly():
    cfg = PhotometricConfig(jpeg_p=0.5, jpeg_quality=(20, 95))
    seeds = [sample_seed(0, 0, i) for i in range(12)]
    images = _images(12, (32, 40), seed=2)
    batched = augment_batch(images, cfg, seeds)
    assert torch.equal(batched, _one_at_a_time(images, cfg, seeds))
    changed = (batched != images).flatten(1).any(1)
    assert 0 < int(changed.sum()) < 12  # about half fired


def test_the_domain_set_keeps_its_shares_over_many_samples():
    """Distribution: over 2,000 samples each operation fires at its probability."""
    cfg = PhotometricConfig(**PhotometricConfig.preset_values("domain"))
    images = torch.full((2000, 3, 4, 4), 0.5)
    out = augment_batch(images, cfg, [sample_seed(1, 0, i) for i in range(2000)])
    changed = float((out != images).flatten(1).any(1).float().mean())
    # P(nothing fires) = 0.7 * 0.7 * 0.5 * 0.5 * 0.7 (blur of a flat image changes nothing)
    assert changed == pytest.approx(1 - 0.7 * 0.5 * 0.5 * 0.7, abs=0.03)

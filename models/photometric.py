"""Training-time image augmentations (blur, noise, gamma, colour, JPEG), seeded per sample.

Plain torch + OpenCV (no torchvision, imgaug or albumentations). Each operation runs with its
own probability and draws its strength from a configurable range; every draw of a sample comes
from a CPU ``torch.Generator`` seeded by :func:`sample_seed` ``(seed, epoch, index)``, so an
augmented sample depends only on those three numbers: not on the batch it lands in, the
loader's worker count, or whether the run was resumed.

Order (a camera's): optical blur -> sensor noise -> colour (brightness, contrast, per-channel
gain) -> gamma -> JPEG compression. Images are (3, H, W) or (B, 3, H, W) float in [0, 1] and
stay so (clipped after each operation); they come back on their device and dtype.

Every operation is off by default (probability 0), so the shipped recipe trains as before;
:meth:`PhotometricConfig.preset` ``"domain"`` is the documented set for sim-to-real training.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

_RANGES = ("blur_sigma", "noise_std", "gamma", "contrast", "jpeg_quality")


@dataclass(frozen=True)
class PhotometricConfig:
    """Probabilities (0..1) and ranges of the photometric augmentations.

    Attributes:
        blur_p: Probability of a Gaussian blur.
        blur_sigma: Its standard deviation, px of the augmented image, drawn U(lo, hi).
        noise_p: Probability of additive Gaussian noise (independent per pixel and channel).
        noise_std: Its standard deviation in intensity units (image in [0, 1]), U(lo, hi).
        gamma_p: Probability of a gamma change ``x -> x ** g``.
        gamma: The exponent g, drawn log-uniformly in [lo, hi].
        colour_p: Probability of a colour change ``x -> (x - m) * c + m + b`` then a gain per
            channel, with m the image's mean intensity.
        brightness: b ~ U(-brightness, brightness), intensity units.
        contrast: c ~ U(lo, hi).
        channel_gain: each channel times U(1 - channel_gain, 1 + channel_gain).
        jpeg_p: Probability of a JPEG encode/decode round trip (OpenCV).
        jpeg_quality: Its quality, an integer drawn in [lo, hi] (0..100).
    """

    blur_p: float = 0.0
    blur_sigma: tuple[float, float] = (0.5, 1.5)
    noise_p: float = 0.0
    noise_std: tuple[float, float] = (0.005, 0.03)
    gamma_p: float = 0.0
    gamma: tuple[float, float] = (0.7, 1.5)
    colour_p: float = 0.0
    brightness: float = 0.1
    contrast: tuple[float, float] = (0.8, 1.2)
    channel_gain: float = 0.1
    jpeg_p: float = 0.0
    jpeg_quality: tuple[int, int] = (30, 90)

    PRESETS: ClassVar[dict[str, dict[str, Any]]] = {
        "off": {},
        # sim-to-real: what separates a rendered frame from an endoscope's (defocus, sensor
        # noise, auto-exposure and white balance, a compressed video stream)
        "domain": {"blur_p": 0.3, "noise_p": 0.3, "gamma_p": 0.5, "colour_p": 0.5, "jpeg_p": 0.3},
    }

    def __post_init__(self) -> None:
        for name in _RANGES:
            value = getattr(self, name)
            if len(value) != 2 or value[0] > value[1]:
                raise ValueError(f"{name} must be a range [lo, hi] with lo <= hi, got {value}")
            cast = int if name == "jpeg_quality" else float
            object.__setattr__(self, name, (cast(value[0]), cast(value[1])))
        for f in dataclasses.fields(self):
            if f.name.endswith("_p") and not 0.0 <= getattr(self, f.name) <= 1.0:
                raise ValueError(f"{f.name} must be a probability in [0, 1]")
        if self.blur_sigma[0] < 0 or self.noise_std[0] < 0 or self.gamma[0] <= 0:
            raise ValueError("blur_sigma and noise_std must be >= 0, gamma > 0")
        if not 0 <= self.jpeg_quality[0] <= self.jpeg_quality[1] <= 100:
            raise ValueError(f"jpeg_quality must lie in [0, 100], got {self.jpeg_quality}")

    @property
    def active(self) -> bool:
        """Whether any operation can fire."""
        return any(
            getattr(self, f.name) > 0 for f in dataclasses.fields(self) if f.name[-2:] == "_p"
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON/YAML-safe dict (ranges as lists)."""
        return {
            f.name: list(v) if isinstance(v := getattr(self, f.name), tuple) else v
            for f in dataclasses.fields(self)
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> PhotometricConfig:
        """Inverse of :meth:`to_dict`; a ``preset`` key starts from that preset. Unknown keys
        raise ``ValueError`` naming them."""
        d = dict(d)
        base = cls.preset_values(str(d.pop("preset", "off")))
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"unknown augment key(s): {', '.join(unknown)}")
        return cls(**{**base, **d})

    @classmethod
    def preset_values(cls, name: str) -> dict[str, Any]:
        """The field values of preset ``name`` ("off" or "domain")."""
        if name not in cls.PRESETS:
            raise ValueError(f"unknown augment preset {name!r}; choose from {sorted(cls.PRESETS)}")
        return dict(cls.PRESETS[name])


def sample_seed(seed: int, epoch: int, index: int) -> int:
    """The seed of one sample's augmentation: a 63-bit hash of (run seed, epoch, sample
    index) (NumPy's ``SeedSequence``, stable across platforms and versions)."""
    state = np.random.SeedSequence([seed, epoch, index, 0x9E3779B9]).generate_state(2, np.uint32)
    return int((int(state[0]) << 31) ^ int(state[1])) & ((1 << 63) - 1)


def _u(gen: torch.Generator, lo: float = 0.0, hi: float = 1.0) -> float:
    return lo + (hi - lo) * float(torch.rand((), generator=gen))


def gaussian_blur(image: Tensor, sigma: float) -> Tensor:
    """(3, H, W) image blurred by a separable Gaussian of ``sigma`` px (kernel 2·ceil(3σ)+1,
    reflected borders); sigma <= 0 returns the image."""
    if sigma <= 0:
        return image
    r = max(1, math.ceil(3 * sigma))
    r = min(r, (min(image.shape[-2:]) - 1))  # reflect padding needs r < side
    if r < 1:
        return image
    x = torch.arange(-r, r + 1, dtype=image.dtype, device=image.device)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    k = k / k.sum()
    img = image[None]
    img = F.pad(img, (r, r, 0, 0), mode="reflect")
    img = F.conv2d(img, k.view(1, 1, 1, -1).expand(3, 1, 1, -1), groups=3)
    img = F.pad(img, (0, 0, r, r), mode="reflect")
    img = F.conv2d(img, k.view(1, 1, -1, 1).expand(3, 1, -1, 1), groups=3)
    return img[0]


def jpeg_round_trip(image: Tensor, quality: int) -> Tensor:
    """(3, H, W) RGB in [0, 1] encoded as JPEG at ``quality`` (0..100) and decoded (OpenCV,
    on the CPU), back on the image's device and dtype."""
    rgb = (image.detach().clamp(0, 1) * 255).round().byte().permute(1, 2, 0).cpu().numpy()
    ok, buf = cv2.imencode(".jpg", rgb[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:  # pragma: no cover - OpenCV always encodes a uint8 RGB image
        raise RuntimeError("cv2.imencode failed")
    bgr = cv2.imdecode(buf, cv2.IMREAD_COLOR)
    if bgr is None:  # pragma: no cover - a buffer OpenCV just encoded
        raise RuntimeError("cv2.imdecode failed")
    out = torch.from_numpy(np.ascontiguousarray(bgr[..., ::-1])).permute(2, 0, 1)
    return out.to(image.device, image.dtype) / 255


def augment_one(image: Tensor, cfg: PhotometricConfig, gen: torch.Generator) -> Tensor:
    """One (3, H, W) image in [0, 1], augmented with draws from ``gen`` (a CPU generator).

    Each operation draws its coin and its parameters whether or not it fires, so turning one
    operation on or off does not change the draws of the others (only the noise field is
    drawn when the noise fires)."""
    out = image
    blur, sigma = _u(gen), _u(gen, *cfg.blur_sigma)
    noise, std = _u(gen), _u(gen, *cfg.noise_std)
    colour, b = _u(gen), _u(gen, -cfg.brightness, cfg.brightness)
    c = _u(gen, *cfg.contrast)
    gains = [_u(gen, 1 - cfg.channel_gain, 1 + cfg.channel_gain) for _ in range(3)]
    gam = _u(gen)
    g = math.exp(_u(gen, math.log(cfg.gamma[0]), math.log(cfg.gamma[1])))
    jpeg, quality = (
        _u(gen),
        cfg.jpeg_quality[0] + int(_u(gen) * (cfg.jpeg_quality[1] - cfg.jpeg_quality[0] + 1)),
    )
    quality = min(quality, cfg.jpeg_quality[1])
    if blur < cfg.blur_p:
        out = gaussian_blur(out, sigma)
    if noise < cfg.noise_p:
        field = torch.randn(out.shape, generator=gen, dtype=torch.float32)
        out = (out + std * field.to(out)).clamp(0, 1)
    if colour < cfg.colour_p:
        mean = out.mean()
        gain = torch.tensor(gains, dtype=out.dtype, device=out.device).view(3, 1, 1)
        out = (((out - mean) * c + mean + b) * gain).clamp(0, 1)
    if gam < cfg.gamma_p:
        out = out.clamp(0, 1) ** g
    if jpeg < cfg.jpeg_p:
        out = jpeg_round_trip(out, quality)
    return out


#: Uniform draws per sample, in :func:`augment_one`'s order: blur coin, sigma, noise coin,
#: std, colour coin, brightness, contrast, three channel gains, gamma coin, gamma, JPEG coin,
#: quality.
_DRAWS = 14


def augment_batch(images: Tensor, cfg: PhotometricConfig, seeds: Sequence[int] | Tensor) -> Tensor:
    """(B, 3, H, W) images in [0, 1], each augmented with its own generator seeded by
    ``seeds[i]`` (see :func:`sample_seed`); a new tensor, same device and dtype. With no
    operation active the images are returned unchanged (the same tensor).

    What :func:`augment_one` does to each image, with the same draws, run on the whole batch
    on its device (the draws, and the JPEG round trips, stay on the CPU): equal to it up to
    float rounding."""
    if not cfg.active:
        return images
    seeds = [int(s) for s in seeds]
    if len(seeds) != images.shape[0]:
        raise ValueError(f"{images.shape[0]} images but {len(seeds)} seeds")
    with torch.autocast(images.device.type, enabled=False):  # the images' dtype throughout
        return _augment(images, cfg, seeds)


def _augment(images: Tensor, cfg: PhotometricConfig, seeds: list[int]) -> Tensor:
    """:func:`augment_batch` of an active ``cfg``."""
    u, fields = _batch_draws(cfg, seeds, tuple(images.shape[1:]))
    v = _parameters(cfg, u)
    out = images.clone()
    fire = {k: torch.nonzero(u[:, c] < p).flatten() for k, c, p in (
        ("blur", 0, cfg.blur_p), ("noise", 2, cfg.noise_p), ("colour", 4, cfg.colour_p),
        ("gamma", 10, cfg.gamma_p), ("jpeg", 12, cfg.jpeg_p))}  # fmt: skip
    dev, dt = images.device, images.dtype
    if len(sel := fire["blur"]):
        out[sel] = _blur_batch(out[sel], v["sigma"][sel])
    if len(sel := fire["noise"]):
        field = torch.stack([fields[int(k)] for k in sel]).to(dev, dt)
        out[sel] = (out[sel] + v["std"][sel].to(dev, dt).view(-1, 1, 1, 1) * field).clamp(0, 1)
    if len(sel := fire["colour"]):
        x = out[sel]
        mean = x.mean((1, 2, 3), keepdim=True)
        c, b = (v[n][sel].to(dev, dt).view(-1, 1, 1, 1) for n in ("contrast", "brightness"))
        gain = v["gains"][sel].to(dev, dt).view(-1, 3, 1, 1)
        out[sel] = (((x - mean) * c + mean + b) * gain).clamp(0, 1)
    if len(sel := fire["gamma"]):
        out[sel] = out[sel].clamp(0, 1) ** v["gamma"][sel].to(dev, dt).view(-1, 1, 1, 1)
    for k in fire["jpeg"].tolist():  # no JPEG codec in torch: OpenCV, per image
        out[k] = jpeg_round_trip(out[k], int(v["quality"][k]))
    return out


def _batch_draws(
    cfg: PhotometricConfig, seeds: list[int], shape: tuple[int, ...]
) -> tuple[Tensor, dict[int, Tensor]]:
    """(B, 14) uniform draws of each sample's generator and, where the noise fires, its
    noise field (the next draws of that generator, as :func:`augment_one` makes them)."""
    u = torch.empty(len(seeds), _DRAWS, dtype=torch.float32)
    fields: dict[int, Tensor] = {}
    for k, s in enumerate(seeds):
        gen = torch.Generator().manual_seed(s)
        u[k] = torch.rand(_DRAWS, generator=gen)  # the same stream as one draw at a time
        if float(u[k, 2]) < cfg.noise_p:
            fields[k] = torch.randn(shape, generator=gen, dtype=torch.float32)
    return u, fields


def _parameters(cfg: PhotometricConfig, u: Tensor) -> dict[str, Tensor]:
    """Each sample's strengths from its draws ``u`` (B, 14), in float64 as :func:`_u`."""
    d = u.double()

    def lerp(col: int, lo: float, hi: float) -> Tensor:
        return lo + (hi - lo) * d[:, col]

    q_lo, q_hi = cfg.jpeg_quality
    gains = torch.stack(
        [lerp(c, 1 - cfg.channel_gain, 1 + cfg.channel_gain) for c in (7, 8, 9)], dim=1
    )
    log_gamma = lerp(11, math.log(cfg.gamma[0]), math.log(cfg.gamma[1]))
    return {
        "sigma": lerp(1, *cfg.blur_sigma),
        "std": lerp(3, *cfg.noise_std),
        "brightness": lerp(5, -cfg.brightness, cfg.brightness),
        "contrast": lerp(6, *cfg.contrast),
        "gains": gains,
        "gamma": torch.exp(log_gamma),
        "quality": (q_lo + (d[:, 13] * (q_hi - q_lo + 1)).floor()).clamp(max=q_hi),
    }


def _blur_batch(images: Tensor, sigma: Tensor) -> Tensor:
    """(n, 3, H, W) images, each blurred as :func:`gaussian_blur` with its own ``sigma``
    (n,): one grouped convolution per axis, the kernels zero-padded to the widest."""
    n, C, H, W = images.shape
    r = torch.ceil(3 * sigma).clamp(min=1).clamp(max=min(H, W) - 1)
    r = torch.where(sigma > 0, r, torch.zeros_like(r)).long()
    R = int(r.max())
    if R < 1:
        return images
    x = torch.arange(-R, R + 1, dtype=images.dtype, device=images.device)
    s = sigma.to(images.device, images.dtype).clamp(min=1e-12)[:, None]
    k = torch.exp(-0.5 * (x[None] / s) ** 2) * (x[None].abs() <= r.to(images.device)[:, None])
    k = k / k.sum(1, keepdim=True)
    k = torch.where(r.to(images.device)[:, None] > 0, k, (x[None] == 0).to(k))  # sigma <= 0
    kc = k.repeat_interleave(C, dim=0)  # (n*C, 2R+1)
    img = F.pad(images.reshape(1, n * C, H, W), (R, R, 0, 0), mode="reflect")
    img = F.conv2d(img, kc.view(n * C, 1, 1, -1), groups=n * C)
    img = F.pad(img, (0, 0, R, R), mode="reflect")
    img = F.conv2d(img, kc.view(n * C, 1, -1, 1), groups=n * C)
    return img.reshape(n, C, H, W)


def batch_seeds(seed: int, epoch: int, indices: Sequence[int] | Tensor) -> list[int]:
    """:func:`sample_seed` of each sample index of a batch."""
    return [sample_seed(seed, epoch, int(i)) for i in indices]

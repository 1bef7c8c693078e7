"""A trained network made cheaper for inference, with the same outputs up to float rounding.

:func:`for_inference` puts a loaded network in eval mode on its device, folds its BatchNorms
into the convolutions before them (:func:`fold_batchnorm`) and, on a CPU, stores its weights
channels-last (oneDNN's convolutions run faster on that layout; ``bench/bench_predict_speed.py``
measures the whole path). Nothing is retrained or resized.

In eval mode a BatchNorm2d is a fixed per-channel affine map, so a convolution followed by it
is one convolution with scaled weights and a bias: the same outputs up to float rounding, one
pass over the feature map less. Which pairs may be folded is known from the structure alone
where it is unambiguous: a convolution followed by a BatchNorm2d in an ``nn.Sequential``
(its order is its forward), and the ``(conv, norm)`` attribute pairs a module lists in its
class attribute ``FOLDS`` (its forward applies that norm to that convolution's output and
uses the output nowhere else). Norms of other kinds (GroupNorm) are left alone.
"""

from __future__ import annotations

import itertools

import torch
from torch import nn
from torch.nn.utils.fusion import fuse_conv_bn_eval

_CONVS = (nn.Conv2d, nn.ConvTranspose2d)


def _fused(conv: nn.Module, norm: nn.Module) -> nn.Module | None:
    """The convolution with ``norm`` folded in, or None where the pair cannot be folded."""
    if not isinstance(conv, _CONVS) or not isinstance(norm, nn.BatchNorm2d):
        return None
    if conv.training or norm.training or not norm.track_running_stats:
        return None
    return fuse_conv_bn_eval(conv, norm, transpose=isinstance(conv, nn.ConvTranspose2d))


def fold_batchnorm(net: nn.Module) -> int:
    """Fold every BatchNorm2d of an eval-mode ``net`` into the convolution before it (see the
    module's doc), in place: the convolution gets the folded weights and bias, the norm
    becomes an ``nn.Identity``. Returns how many were folded (0 for a net in training mode).
    """
    if net.training:
        return 0
    folded = 0
    for module in list(net.modules()):
        pairs: list[tuple[str, str]] = list(getattr(module, "FOLDS", ()))
        if isinstance(module, nn.Sequential):
            names = [name for name, _ in module.named_children()]
            pairs += list(itertools.pairwise(names))
        for conv_name, norm_name in pairs:
            conv, norm = getattr(module, conv_name), getattr(module, norm_name)
            fused = _fused(conv, norm)
            if fused is not None:
                setattr(module, conv_name, fused)
                setattr(module, norm_name, nn.Identity())
                folded += 1
    return folded


def for_inference(net: nn.Module, device: torch.device) -> nn.Module:
    """``net`` (in place) on ``device`` in eval mode, its BatchNorms folded, channels-last
    on a CPU; returned for chaining."""
    net.to(device).eval()
    fold_batchnorm(net)
    if device.type == "cpu":
        net.to(memory_format=torch.channels_last)  # type: ignore[call-overload]
    return net

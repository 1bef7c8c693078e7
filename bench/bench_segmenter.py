"""Bench: the needle segmenter's arithmetic and time per ROI, by layout.

For the shipped segmenter's layout and the same layout at other widths (``--widths``), and
ROI sides (``--rois``): the convolutions' GFLOP per ROI (2 × multiply-adds, counted from the
layers' outputs), the parameters, and the ms per ROI of a forward pass as ``bopsurg predict``
runs it on a CPU (BatchNorms folded, channels-last, one intra-op thread, batches of
``--batch`` ROIs), the layouts in turn over ``--rounds`` (fastest round), and the GFLOP/s that
makes. Random weights: the time of a layout does not depend on them.

    python bench/bench_segmenter.py [--widths 8 6 4] [--rois 160] [--rounds 10]
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import torch
from bench_metrics import machine

from bopsurg.models.checkpoint import load_checkpoint
from bopsurg.models.inference import for_inference
from bopsurg.models.predict_config import weight_file
from bopsurg.models.refine.seghead import NeedleSegNet, SegConfig


def gflop_per_roi(net: NeedleSegNet) -> float:
    """2 × the multiply-adds of the convolutions of one forward pass of one ROI, in GFLOP."""
    macs = 0

    def count(m: torch.nn.Module, _: object, out: torch.Tensor) -> None:
        nonlocal macs
        assert isinstance(m, torch.nn.Conv2d)
        per_output = m.in_channels // m.groups * m.kernel_size[0] * m.kernel_size[1]
        macs += out.numel() * per_output

    convs = [m for m in net.modules() if isinstance(m, torch.nn.Conv2d)]
    hooks = [m.register_forward_hook(count) for m in convs]
    with torch.inference_mode():
        net(torch.zeros(1, 3, net.cfg.roi, net.cfg.roi))
    for h in hooks:
        h.remove()
    return 2.0 * macs / 1e9


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--widths", type=int, nargs="+", help="default: the shipped one's, 6, 4")
    ap.add_argument("--rois", type=int, nargs="+", help="ROI sides, px (default: the shipped)")
    ap.add_argument("--batch", type=int, default=1, help="ROIs per forward pass")
    ap.add_argument("--rounds", type=int, default=10)
    args = ap.parse_args()
    torch.set_num_threads(1)
    _, info = load_checkpoint(weight_file("segmenter", "shipped"), "needle_seg")
    shipped = SegConfig.from_dict(info["config"])
    widths = args.widths or sorted({shipped.width, 6, 4}, reverse=True)
    rois = args.rois or [shipped.roi]
    layouts = [dataclasses.replace(shipped, width=w, roi=r) for r in rois for w in widths]
    torch.manual_seed(0)
    nets = [for_inference(NeedleSegNet(c), torch.device("cpu")) for c in layouts]
    plain = [NeedleSegNet(c).eval() for c in layouts]  # as trained: BatchNorms unfolded
    flops = [gflop_per_roi(net) for net in plain]
    params = [sum(p.numel() for p in net.parameters()) for net in plain]
    inputs = [
        torch.rand(args.batch, 3, c.roi, c.roi).contiguous(memory_format=torch.channels_last)
        for c in layouts
    ]
    best = [float("inf")] * len(layouts)
    with torch.inference_mode():
        for net, x in zip(nets, inputs, strict=True):
            net(x)  # warm-up
        for _ in range(args.rounds):
            for i, (net, x) in enumerate(zip(nets, inputs, strict=True)):
                start = time.perf_counter()
                net(x)
                best[i] = min(best[i], (time.perf_counter() - start) / args.batch)
    print(f"machine: {machine()}; torch {torch.__version__}, 1 thread")
    print(f"shipped layout: {shipped}")
    print(f"{'width':>5} {'ROI':>4} {'GFLOP/ROI':>10} {'params':>8} {'ms/ROI':>7} "
          f"{'vs shipped':>10} {'GFLOP/s':>8}")  # fmt: skip
    ref = {r: best[i] for i, c in enumerate(layouts) for r in [c.roi] if c.width == shipped.width}
    for c, f, ms, n in zip(layouts, flops, best, params, strict=True):
        share = f"{ms / ref[c.roi]:.0%}" if c.roi in ref else "-"
        print(f"{c.width:5d} {c.roi:4d} {f:10.3f} {n:8d} {1e3 * ms:7.2f} {share:>10} {f / ms:8.1f}")


if __name__ == "__main__":
    main()

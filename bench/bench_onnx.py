"""Bench: the exported pipeline (numpy + onnxruntime) against the torch estimator, per image.

Exports the shipped models into a temporary folder, then times ``predict`` of the torch
``gdrnet`` estimator with its refinement and end check off and of the
``gdrnet-onnx`` runner on the same seeded 640x480 images (a drawn needle on noise), best of
``--repeat`` runs each, on the CPU with ``--threads`` threads for both, and prints the ratio
and the largest pose difference.

    python bench/bench_onnx.py [--images 10] [--repeat 3] [--threads 1] [--zoom 1]
"""

from __future__ import annotations

import argparse
import tempfile
import time

import cv2
import numpy as np
import torch

from bopsurg import metrics
from bopsurg.cli.main import main as bopsurg
from bopsurg.estimation import load_estimator
from bopsurg.models.onnx_runtime import OnnxPipeline


def images(n: int) -> list[np.ndarray]:
    rng = np.random.default_rng(0)
    out = []
    for _ in range(n):
        rgb = rng.integers(70, 140, (480, 640, 3)).astype(np.uint8)
        centre = (int(rng.integers(150, 490)), int(rng.integers(120, 360)))
        start = int(rng.integers(0, 360))
        cv2.ellipse(rgb, centre, (50, 50), 0, start, start + 230, (205, 205, 215), 4)
        out.append(rgb)
    return out


def best_time(fn, repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--images", type=int, default=10)
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--zoom", default=None, help="crop multiples, e.g. 1 (default: the shipped)")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    K = np.array([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]])
    ims = images(args.images)
    zooms = [float(z) for z in args.zoom.split(",")] if args.zoom else None
    head = {"head": {"zoom": zooms}} if zooms else {}
    bare = {"device": "cpu", "refine": {"segmenter": None}, "ends": {"classifier": None}}
    est = load_estimator("gdrnet", bare | head)
    with tempfile.TemporaryDirectory() as tmp:
        assert bopsurg(["export", "--out", tmp, "--segmenter", "none"]) == 0
        runner = OnnxPipeline(tmp, zoom=zooms, threads=args.threads)
        t_torch = best_time(lambda: [est.predict(im, K) for im in ims], args.repeat)
        t_onnx = best_time(lambda: [runner.predict(im, K) for im in ims], args.repeat)
        a = [est.predict(im, K) for im in ims]
        b = [runner.predict(im, K) for im in ims]
    n_poses = sum(len(x) for x in a)
    re = max((metrics.re(x.R, y.R).max() for x, y in zip(a, b, strict=True) if len(x)), default=0)
    te = max((np.abs(x.t - y.t).max() for x, y in zip(a, b, strict=True) if len(x)), default=0)
    n = len(ims)
    print(f"{n} images, {n_poses} poses, {args.threads} thread(s), zoom {args.zoom or 'shipped'}")
    print(f"torch estimator (network only): {1000 * t_torch / n:7.1f} ms/image")
    print(f"onnxruntime + numpy runner:     {1000 * t_onnx / n:7.1f} ms/image")
    print(f"ratio torch / onnx:             {t_torch / t_onnx:7.2f}")
    print(f"largest difference: rotation {re:.4f} deg, translation {te:.4f} mm")


if __name__ == "__main__":
    main()

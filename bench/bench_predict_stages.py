"""Bench: where ``bopsurg predict``'s time per image goes, stage by stage (the default model).

On a BOP split, the ``gdrnet`` estimator's ``predict_batch`` on decoded images (decoding
excluded, as in ``bopsurg predict``'s own timing), RGB and RGB-D, after one warm-up batch.
Each stage is timed by the CPU time of the calling thread (steady on a machine shared with
other jobs) and printed in ms per image: the detector, the pose head (its first pass and the
re-crops' passes together), the segmenter (first masks and re-crops), the evidence's
preparation (distance transforms), the fit to the depth points alone, the RGB(-D) fit, and
the end check. The stages nest: ``refine stage`` holds the segmenter, ``refiner.fit`` and the
re-crops' pose-head passes; ``refiner.fit`` holds the evidence and both fits. Keep the
default ``--threads 1``: with more, the refinement runs its parts on worker threads
(``models/refine/workers.py``), whose time the calling thread's clock does not see.

    python bench/bench_predict_stages.py TEST_SPLIT --images 48 --batch-size 8 \
        [--predict-option KEY=VALUE ...]

``--predict-option`` (repeatable) sets the estimator's options as ``bopsurg predict --option``
does: the cost of a candidate setting, stage by stage.

``bench/bench_predict_speed.py`` times whole configurations against the networks alone.
"""

from __future__ import annotations

import argparse
import functools
import time
from collections.abc import Callable
from typing import Any

import torch
from bench_metrics import machine
from benchlib import add_predict_option, decoded_images

from bopsurg.bop.dataset import BopDataset
from bopsurg.cli.inputs import key_value
from bopsurg.estimation import load_estimator
from bopsurg.models.refine import fit, refiner
from bopsurg.models.stages import detect, ends, head, refine
from bopsurg.options import plugin_options

#: label -> (object, attribute): the callables timed.
STAGES: dict[str, tuple[Any, str]] = {
    "detector": (detect.DetectStage, "batch"),
    "pose head (all passes)": (head.HeadStage, "__call__"),
    "refine stage": (refine.RefineStage, "__call__"),
    "  segmenter": (refine.RefineStage, "_observe"),
    "  refiner.fit": (refiner.NeedleRefiner, "fit"),
    "    evidence": (fit.Evidence, "from_mask"),
    "    fit to the depth points": (refiner, "fit_depths"),
    "    RGB(-D) fit": (refiner, "refine_poses"),
    "end check": (ends.EndStage, "__call__"),
}


def instrument(spent: dict[str, float]) -> None:
    """Wrap each stage so that its thread CPU time adds up in ``spent`` (s)."""
    for label, (owner, name) in STAGES.items():
        inner: Callable[..., Any] = getattr(owner, name)  # a class method comes bound

        def timed(*a: Any, _f: Callable[..., Any] = inner, _k: str = label, **kw: Any) -> Any:
            start = time.thread_time()
            try:
                return _f(*a, **kw)
            finally:
                spent[_k] = spent.get(_k, 0.0) + time.thread_time() - start

        wrapped = functools.wraps(inner)(timed)
        bound = isinstance(vars(owner).get(name), classmethod)  # a module's names are plain
        setattr(owner, name, staticmethod(wrapped) if bound else wrapped)


def run(
    ds: BopDataset,
    rgbd: bool,
    images: int,
    batch: int,
    spent: dict[str, float],
    options: dict[str, Any],
) -> tuple[float, int]:
    """ms per image of the whole ``predict_batch`` over (at most) ``images`` images after one
    warm-up batch, and how many were timed; ``spent`` holds the stages' seconds over them.
    ``options``: the estimator's, over its defaults."""
    est = load_estimator("gdrnet", {**options, "device": "cpu"})
    mapped, decoded = decoded_images(ds, est, batch + images, rgbd)
    mapped.predict_batch(decoded[:batch])
    spent.clear()
    start = time.thread_time()
    for i in range(batch, len(decoded), batch):
        mapped.predict_batch(decoded[i : i + batch])
    timed = max(1, len(decoded) - batch)
    return 1000.0 * (time.thread_time() - start) / timed, timed


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset", help="BOP dataset root (e.g. /work/exp/s38/testsplit)")
    ap.add_argument("--split", default="test")
    ap.add_argument("--images", type=int, default=48, help="images timed per mode")
    ap.add_argument("--batch-size", type=int, default=8)
    ap.add_argument(
        "--threads", type=int, default=1, help="torch threads (default 1; see the docstring)"
    )
    add_predict_option(ap, "refine.depth.points.iterations=8")
    args = ap.parse_args()
    options = plugin_options(None, [key_value(o) for o in args.predict_option])
    torch.set_num_threads(args.threads)
    ds = BopDataset(args.dataset, args.split)
    spent: dict[str, float] = {}
    instrument(spent)
    print(f"machine: {machine()}; torch {torch.__version__}, {torch.get_num_threads()} threads")
    print(f"batch {args.batch_size}, {args.images} images after one warm-up batch, CPU time")
    if args.predict_option:
        print("options: " + " ".join(args.predict_option))
    for mode, rgbd in (("RGB", False), ("RGB-D", True)):
        total, timed = run(ds, rgbd, args.images, args.batch_size, spent, options)
        print(f"{mode}: {total:.1f} ms/image over {timed} images")
        for label in STAGES:
            print(f"  {label:30s} {1000.0 * spent.get(label, 0.0) / timed:7.1f}")


if __name__ == "__main__":
    main()

"""Bench: what the second core could do while a batch's fits run (``bopsurg predict``, RGB-D).

The needle fits run on the calling thread with one intra-op thread (their ops are small:
``models/refine/workers.py``), so on a 2-core CPU one core idles while they run. This bench
measures the ways of filling it, each against the same work done one part after the other,
in one process on the same captured inputs (one pass of the default estimator over a split,
batches of ``--batch-size``), batch by batch, the two ways in turn, over ``--rounds``; it
prints ms per image of each way from each batch's fastest round (and its median round) and
the saving:

1. ``networks``: a batch's detector and pose head (the estimator without its refinement and
   end check) on one and on two torch threads: how well the networks already use both cores.
2. ``fits in two halves``: each batch's fit (:meth:`NeedleRefiner.fit`, the evidence and both
   fits) as two halves of its ROIs on two threads, against one call for all of them.
3. ``segmenter beside the fits``: the next batch's segmenter pass on a second thread (one
   intra-op thread) while this batch's fits run (a pipeline over batches), against the pass
   on both cores (its images in two groups, as the stage runs it) and then the fits.
4. ``evidence beside the depth fit``: each batch's distance transforms (the fit's evidence,
   cv2) on a second thread while the fit to the depth points runs, against one after the
   other (the points are back-projected beforehand, untimed).
5. ``networks beside the fits``: the next batch's networks (two threads) while this batch's
   fits run on a second thread, against one after the other.

    python bench/bench_refine_overlap.py TEST_SPLIT --images 48 --batch-size 8 --rounds 5

On a shared machine the fastest rounds are the figure to trust (a spike of the machine spoils
one batch's time, not a whole pass); the saving that matters is per image against the
networks' time (``bench/bench_predict_speed.py``).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any, NamedTuple

import numpy as np
import torch
from bench_metrics import machine
from benchlib import decoded_images

from bopsurg import prediction
from bopsurg.bop.dataset import BopDataset
from bopsurg.estimation import ImageInput, load_estimator
from bopsurg.models.refine import refiner as refine_mod
from bopsurg.models.refine.depth_fit import fit_depths
from bopsurg.models.stages.refine import RefineStage


class FitCall(NamedTuple):
    """The arguments of one :meth:`NeedleRefiner.fit` call."""

    refiner: refine_mod.NeedleRefiner
    masks: refine_mod.RoiMasks
    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    depth: Any


class ObserveCall(NamedTuple):
    """The arguments of a batch's first segmenter pass (:meth:`RefineStage._observe`)."""

    stage: RefineStage
    args: tuple[Any, ...]


def capture(images: list[list[ImageInput]], est: Any) -> tuple[list[FitCall], list[ObserveCall]]:
    """Each batch's fit call and first segmenter pass, from one pass of ``est``."""
    fits: list[FitCall] = []
    passes: list[ObserveCall] = []
    fit, observe = refine_mod.NeedleRefiner.fit, RefineStage._observe

    def fit_spy(self: Any, masks: Any, K: Any, R: Any, t: Any, depth: Any = None) -> Any:
        fits.append(FitCall(self, masks, np.array(K), R.copy(), t.copy(), depth))
        return fit(self, masks, K, R, t, depth)

    def observe_spy(self: Any, *args: Any) -> Any:
        if len(passes) < len(fits) + 1:  # the batch's first pass (re-crops come after it)
            passes.append(ObserveCall(self, tuple(args)))
        return observe(self, *args)

    refine_mod.NeedleRefiner.fit = fit_spy  # type: ignore[method-assign]
    RefineStage._observe = observe_spy  # type: ignore[method-assign]
    try:
        for batch in images:
            est.predict_batch(batch)
    finally:
        refine_mod.NeedleRefiner.fit = fit  # type: ignore[method-assign]
        RefineStage._observe = observe  # type: ignore[method-assign]
    return fits, passes


def run_fit(call: FitCall, rows: np.ndarray | None = None) -> Any:
    """The fit call, or of its ROIs ``rows`` alone."""
    if rows is None:
        return call.refiner.fit(call.masks, call.K, call.R, call.t, call.depth)
    depth = call.depth if call.depth is None else [call.depth[i] for i in rows]
    return call.refiner.fit(
        call.masks.subset(rows), call.K[rows], call.R[rows], call.t[rows], depth
    )


def one_thread(fn: Callable[[], Any]) -> Callable[[], Any]:
    """``fn`` run with one torch intra-op thread (on a pool thread: its own count)."""

    def inner() -> Any:
        torch.set_num_threads(1)
        return fn()

    return inner


class DepthWork(NamedTuple):
    """A batch's evidence work (per ROI) and its fit to the depth points, split apart."""

    evidence: Callable[[], Any]
    depth_fit: Callable[[], Any]


def depth_work(call: FitCall) -> DepthWork:
    """The two parts of a fit call that need not wait for each other: the distance transforms
    of every ROI, and the fit to the depth points (their points back-projected here)."""
    ref, n = call.refiner, len(call.R)
    depths = call.depth if isinstance(call.depth, list) else [call.depth] * n
    grids = [ref._evidence(call.masks, i) for i in range(n)]
    points = [ref.roi_points(*g, d, K) for g, d, K in zip(grids, depths, call.K, strict=True)]

    def evidence() -> Any:
        return [ref._evidence(call.masks, i) for i in range(n)]

    def depth_fit() -> Any:
        return fit_depths(call.R, call.t, points, ref.arc, ref.depth.points, ref.device)

    return DepthWork(evidence, depth_fit)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset", help="BOP dataset root with depth images (a test split)")
    ap.add_argument("--split", default="test")
    ap.add_argument("--images", type=int, default=48, help="images, after a warm-up batch")
    ap.add_argument("--batch-size", type=int, default=8)
    ap.add_argument("--rounds", type=int, default=5)
    args = ap.parse_args()
    torch.set_num_threads(2)
    ds = BopDataset(args.dataset, args.split)
    est = load_estimator("gdrnet", {"device": "cpu"})
    nets = load_estimator(
        "gdrnet", {"device": "cpu", "refine": {"segmenter": None}, "ends": {"classifier": None}}
    )
    mapped, decoded = decoded_images(ds, est, args.batch_size + args.images, depth=True)
    mapped_nets = prediction._Mapped(nets, mapped.mappings, False)
    b = args.batch_size
    batches = [decoded[i : i + b] for i in range(0, len(decoded), b)]
    mapped.predict_batch(batches[0])  # warm-up
    mapped_nets.predict_batch(batches[0])
    batches = batches[1:]
    fits, passes = capture(batches, mapped)
    if len(fits) != len(batches) or len(passes) != len(batches):
        raise SystemExit("every batch needs a needle ROI (a split with needles in each image)")
    n_images = sum(len(x) for x in batches)
    works = [depth_work(f) for f in fits]
    pool = ThreadPoolExecutor(1, "bench-beside")

    def beside(background: Callable[[], Any], here: Callable[[], Any]) -> None:
        future = pool.submit(background)
        here()
        future.result()

    def networks(threads: int) -> Callable[[int], None]:
        def go(k: int) -> None:
            torch.set_num_threads(threads)
            mapped_nets.predict_batch(batches[k])
            torch.set_num_threads(2)

        return go

    def fits_whole(k: int) -> None:
        run_fit(fits[k])

    def fits_halves(k: int) -> None:
        f = fits[k]
        a, c = np.array_split(np.arange(len(f.R)), 2)
        beside(one_thread(lambda: run_fit(f, a)), lambda: run_fit(f, c))

    def segmenter_pass(k: int) -> Callable[[], Any]:
        """The first segmenter pass of the batch after k (the first batch's after the last)."""
        p = passes[(k + 1) % len(passes)]
        return lambda: p.stage._observe(*p.args)

    def segment_then_fit(k: int) -> None:
        segmenter_pass(k)()
        run_fit(fits[k])

    def segment_beside_fit(k: int) -> None:
        beside(one_thread(segmenter_pass(k)), lambda: run_fit(fits[k]))

    def evidence_then_depth(k: int) -> None:
        works[k].evidence()
        works[k].depth_fit()

    def evidence_beside_depth(k: int) -> None:
        beside(works[k].evidence, works[k].depth_fit)

    def next_networks(k: int) -> Callable[[], Any]:
        nxt = batches[(k + 1) % len(batches)]
        return lambda: mapped_nets.predict_batch(nxt)

    def nets_then_fit(k: int) -> None:
        next_networks(k)()
        run_fit(fits[k])

    def nets_beside_fit(k: int) -> None:
        beside(one_thread(lambda: run_fit(fits[k])), next_networks(k))

    pairs: dict[str, tuple[Callable[[int], None], Callable[[int], None], str, str]] = {
        "networks": (networks(1), networks(2), "1 thread", "2 threads"),
        "fits in two halves": (fits_whole, fits_halves, "one call", "two halves"),
        "segmenter beside the fits": (segment_then_fit, segment_beside_fit, "in turn", "beside"),
        "evidence beside the depth fit": (
            evidence_then_depth, evidence_beside_depth, "in turn", "beside"
        ),
        "networks beside the fits": (nets_then_fit, nets_beside_fit, "in turn", "beside"),
    }  # fmt: skip
    # per batch and round: a spike of the machine spoils one batch's time, not a whole pass
    times: dict[tuple[str, int], np.ndarray] = {
        (name, j): np.zeros((args.rounds, len(batches))) for name in pairs for j in (0, 1)
    }
    with torch.inference_mode():
        for r in range(args.rounds):
            for name, pair in pairs.items():
                for k in range(len(batches)):
                    for j in (0, 1):
                        start = time.perf_counter()
                        pair[j](k)
                        times[name, j][r, k] = time.perf_counter() - start
    pool.shutdown()
    print(f"machine: {machine()}; torch {torch.__version__}, 2 threads")
    print(
        f"RGB-D, batch {b}, {n_images} images, {args.rounds} rounds: ms per image, each "
        "batch's fastest round (its median round)"
    )
    for name, (_, _, a, c) in pairs.items():
        lo = [1e3 * times[name, j].min(0).sum() / n_images for j in (0, 1)]
        med = [1e3 * np.median(times[name, j], 0).sum() / n_images for j in (0, 1)]
        print(
            f"  {name:30s} {a} {lo[0]:6.1f} ({med[0]:6.1f})   {c} {lo[1]:6.1f} ({med[1]:6.1f})"
            f"   saves {lo[0] - lo[1]:5.1f} ms/image"
        )


if __name__ == "__main__":
    main()

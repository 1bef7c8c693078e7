"""Bench: `bopsurg annotate` instances per second at 640×480, 1 and 2 worker processes.

Generates a seeded dataset (needle + the six instrument parts annotated, so 7 instances per
image), deletes its masks and scene_gt_info, and times annotate with 1 and 2 workers
(rendering each instance on the 3× canvas, visibility against the depth images, masks and
gt_info written). Checks the result equals the generator's own annotation.

    python bench/bench_annotate.py [--replays 2] [--duration 10]
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

from bopsurg.annotate import annotate_dataset
from bopsurg.bop.dataset import BopDataset
from bopsurg.generators.bags import write_bag
from bopsurg.generators.generate import generate_dataset
from bopsurg.generators.replay import GenerateSettings
from bopsurg.generators.trajectory import synthesize_suturing


def strip(root: Path) -> None:
    for scene_dir in (root / "test").iterdir():
        if scene_dir.is_dir():
            (scene_dir / "scene_gt_info.json").unlink()
            shutil.rmtree(scene_dir / "mask")
            shutil.rmtree(scene_dir / "mask_visib")


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--replays", type=int, default=2)
    ap.add_argument("--duration", type=float, default=10.0)
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="bopsurg-bench-"))
    try:
        bag = work / "a.bag"
        write_bag(bag, synthesize_suturing(seed=0, duration=args.duration))
        src = work / "src"
        settings = GenerateSettings(
            replays=args.replays, min_visib=0.0, backend_config={"annotate_instruments": True}
        )
        generate_dataset([bag], src, settings=settings, workers=2, progress=False)
        reference = BopDataset(src, "test")
        n_inst = sum(len(g) for s in reference.iter_scenes() for g in s.gt.values())
        n_img = sum(len(s.gt) for s in reference.iter_scenes())
        print(f"{n_img} images, {n_inst} GT instances, 640x480")
        for workers in (1, 2):
            ds = work / f"ds{workers}"
            shutil.copytree(src, ds)
            strip(ds)
            t0 = time.perf_counter()
            annotate_dataset(ds, "test", delta=settings.delta_mm, workers=workers, progress=False)
            dt = time.perf_counter() - t0
            same = all(
                BopDataset(ds, "test").scene(s).gt_info == reference.scene(s).gt_info
                for s in reference.scene_ids
            )
            print(
                f"  annotate, {workers} worker(s): {n_inst / dt:6.1f} instances/s "
                f"({n_img / dt:5.1f} images/s, {dt:.1f} s); equals the generator's: {same}"
            )
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()

r"""Bench: two sets of results compared on several held-out splits pooled into one.

One validation split of a few hundred needles cannot tell a small change from the luck of
its episodes: two detectors of equal quality move many needles both ways, and a split may
say "worse" where another says "better" (the model card, "The detector at 512x384
(shipped)"). This pools splits drawn the same way from other episodes (VAL1 and VAL2 of the
card) into one test set and compares the two results on it, paired:

  1. OUT/data: a BOP dataset whose test split links every scene of each given split (not
     copied), renumbered 1, 2, ... in the order given (OUT/data/pooled_scenes.json says
     which scene came from where), their models and camera (which must be the same in every
     split), and their test targets;
  2. each result CSV renumbered the same way and pooled: OUT/base.csv, OUT/other.csv;
  3. ``bopsurg eval`` of both, then ``bopsurg compare`` (paired bootstrap by image), printed
     and written to OUT/compare.

    python bench/bench_pooled.py --out runs/pooled --bootstrap 2000 \
        --set val1 results/base_val1.csv results/new_val1.csv \
        --set val2 results/base_val2.csv results/new_val2.csv
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import shutil
import sys
from pathlib import Path

import numpy as np
from benchlib import run

from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.results import PoseEstimates, load_results, save_results

#: Test-target files carried over when every split has them.
TARGETS = ("test_targets_bop19.json", "test_targets_bop24.json")
#: The columns of a results file that are pooled.
POSE_FIELDS = ("scene_id", "im_id", "obj_id", "score", "R", "t", "time")


def _digest(root: Path) -> str:
    """Checksum of a dataset's models folder and camera.json (what must agree to pool)."""
    h = hashlib.sha256()
    for f in [*sorted((root / "models").glob("*")), root / "camera.json"]:
        h.update(f.name.encode())
        h.update(f.read_bytes())
    return h.hexdigest()


def pool_datasets(roots: list[Path], out: Path, split: str = "test") -> list[dict[int, int]]:
    """Link the ``split`` scenes of every dataset into ``out`` (renumbered 1, 2, ... in order);
    returns, per dataset, its scene id -> the pooled one."""
    first = _digest(roots[0])
    for r in roots[1:]:
        if _digest(r) != first:
            raise SystemExit(f"{r}: models/ or camera.json differ from {roots[0]}'s; cannot pool")
    shutil.rmtree(out, ignore_errors=True)
    (out / split).mkdir(parents=True)
    shutil.copytree(roots[0] / "models", out / "models")
    shutil.copy(roots[0] / "camera.json", out / "camera.json")
    maps: list[dict[int, int]] = []
    record = []
    for r in roots:
        ids = BopDataset(r, split).scene_ids
        m = {s: len(record) + 1 + k for k, s in enumerate(ids)}
        for s, new in m.items():
            (out / split / f"{new:06d}").symlink_to((r / split / f"{s:06d}").resolve())
            record.append({"pooled": new, "dataset": str(r.resolve()), "scene_id": s})
        maps.append(m)
    for name in TARGETS:
        if all((r / name).is_file() for r in roots):
            rows = [
                {**t, "scene_id": m[int(t["scene_id"])]}
                for r, m in zip(roots, maps, strict=True)
                for t in json.loads((r / name).read_text())
            ]
            (out / name).write_text(json.dumps(rows))
    (out / "pooled_scenes.json").write_text(json.dumps(record, indent=1) + "\n")
    return maps


def pool_results(csvs: list[Path], maps: list[dict[int, int]], out: Path) -> None:
    """One BOP results CSV of several, their scene ids renumbered by ``maps`` (read and written
    as ``bopsurg`` does: a malformed file gets its one-line error, values round-trip)."""
    parts = []
    for path, m in zip(csvs, maps, strict=True):
        est = load_results(path)
        unknown = sorted(set(est.scene_id.tolist()) - set(m))
        if unknown:
            raise SystemExit(f"{path}: scene_id {unknown[0]} is not in its dataset")
        lut = np.zeros(max(m) + 1, np.int64)
        lut[list(m)] = list(m.values())
        parts.append(dataclasses.replace(est, scene_id=lut[est.scene_id]))
    cols = {k: np.concatenate([getattr(e, k) for e in parts]) for k in POSE_FIELDS}
    save_results(out, PoseEstimates.from_arrays(**cols))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "--set",
        nargs=3,
        action="append",
        required=True,
        metavar=("DATA", "BASE_CSV", "OTHER_CSV"),
        help="a dataset and the two results on its test split (repeat for each split)",
    )
    ap.add_argument("--out", type=Path, required=True, help="output folder")
    ap.add_argument("--bootstrap", type=int, default=2000, help="paired replicates (2000)")
    args = ap.parse_args(argv)
    if len(args.set) < 2:
        ap.error("give at least two --set (one split needs no pooling: bopsurg compare)")
    for data, *csvs in args.set:
        for f, what in ((Path(data) / "test", "a test split"), *((Path(c), "") for c in csvs)):
            if not f.exists():
                ap.error(f"{f}: not found" + (f" ({data} needs {what})" if what else ""))
    roots = [Path(s[0]) for s in args.set]
    maps = pool_datasets(roots, args.out / "data")
    evals = []
    for k, name in ((1, "base"), (2, "other")):
        csv = args.out / f"{name}.csv"
        pool_results([Path(s[k]) for s in args.set], maps, csv)
        ev = args.out / f"eval_{name}"
        shutil.rmtree(ev, ignore_errors=True)
        argv = ["eval", str(args.out / "data"), str(csv), "--out", str(ev), "--no-progress"]
        run(argv, quiet=True)
        evals.append(str(ev))
    n = sum(len(m) for m in maps)
    print(f"pooled {len(roots)} splits ({n} scenes) -> {args.out / 'data'}")
    cmp = args.out / "compare"
    run(["compare", *evals, "--out", str(cmp), "--bootstrap", str(args.bootstrap)])
    return 0


if __name__ == "__main__":
    sys.exit(main())

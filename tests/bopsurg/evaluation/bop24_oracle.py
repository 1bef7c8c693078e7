r"""Inputs of the BOP24 equality test, and the script that asks the reference toolkit for its
numbers on them.

The datasets are the synthetic ones of ``conftest.build_synthetic`` (two objects, one with a
continuous symmetry; 1-3 instances per image, some below 10 % visibility; missing, duplicate
and tied estimates; estimates of absent objects), plus a crowded image (more than 100
estimates) so that the per-image cap matters, and targets listed in a shuffled order (the
order decides how tied scores rank).

Regenerate ``data/bop24_reference.json`` with a checkout of thodan/bop_toolkit and a Python
environment that runs it (numpy < 2, scipy, pypng, imageio, tqdm)::

    python -m tests.bopsurg.evaluation.bop24_oracle --toolkit /path/to/bop_toolkit \
        --python /path/to/toolkit-venv/bin/python

The toolkit only evaluates datasets it knows by name; the data are laid out as ``lm``
(15 objects, 640 x 480 px) with copies of the cylinder for the objects we do not use.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.jsonio import load_json
from bopsurg.bop.meshes import load_models_info, save_models_info
from bopsurg.bop.results import PoseEstimates, save_results
from bopsurg.bop.targets import ImageTarget, enumerate_image_targets, save_image_targets
from tests.bopsurg.evaluation.conftest import build_synthetic

SEEDS = (0, 1, 2)
FIXTURE = Path(__file__).parent / "data" / "bop24_reference.json"


def _crowd(ds: BopDataset, est: PoseEstimates, rng: np.random.Generator) -> PoseEstimates:
    """120 extra estimates in the first image: near and far poses of its first instance, with
    tied scores around those of the real ones, so the 100-per-image cap cuts through ties."""
    scene_id = ds.scene_ids[0]
    im_id = min(ds.scene(scene_id).gt)
    gt = ds.scene(scene_id).gt[im_id][0]
    n = 120
    rot = Rotation.from_rotvec(rng.normal(size=(n, 3)) * np.deg2rad(3.0)).as_matrix()
    extra = PoseEstimates.from_arrays(
        scene_id=np.full(n, scene_id, dtype=np.int64),
        im_id=np.full(n, im_id, dtype=np.int64),
        obj_id=np.full(n, gt.obj_id, dtype=np.int64),
        score=rng.choice([0.6, 0.7, 0.75], size=n),
        R=rot @ gt.R,
        t=gt.t + rng.normal(size=(n, 3)) * rng.choice([0.5, 3.0, 40.0], size=(n, 1)),
        time=np.full(n, 0.1),
    )
    return PoseEstimates.from_arrays(
        scene_id=np.r_[est.scene_id, extra.scene_id],
        im_id=np.r_[est.im_id, extra.im_id],
        obj_id=np.r_[est.obj_id, extra.obj_id],
        score=np.r_[est.score, extra.score],
        R=np.concatenate([est.R, extra.R]),
        t=np.concatenate([est.t, extra.t]),
        time=np.r_[est.time, extra.time],
    )


def build_case(root: Path, seed: int) -> tuple[BopDataset, PoseEstimates, list[ImageTarget]]:
    """The dataset (split ``test``), results CSV ``root/synth_lm-test.csv`` and BOP24 targets
    (also written to ``root/test_targets_bop24.json``) of one seed."""
    synth = build_synthetic(root, seed=seed, n_scenes=2, n_images=8)
    ds = BopDataset(root, "test")
    rng = np.random.default_rng(1000 + seed)
    est = _crowd(ds, synth.est, rng)
    save_results(root / "synth_lm-test.csv", est)
    targets = enumerate_image_targets({s.scene_id: s.gt for s in ds.iter_scenes()})
    targets = [targets[i] for i in rng.permutation(len(targets))]
    save_image_targets(root / "test_targets_bop24.json", targets)
    return ds, est, targets


def _as_lm(root: Path, bop_path: Path) -> None:
    """Lay the synthetic dataset out as the toolkit's ``lm`` (objects 1..15)."""
    lm = bop_path / "lm"
    models = lm / "models_eval"
    models.mkdir(parents=True)
    info = load_models_info(root / "models" / "models_info.json")
    for obj_id in range(1, 16):
        src = obj_id if obj_id in info else 2
        shutil.copy(root / "models" / f"obj_{src:06d}.ply", models / f"obj_{obj_id:06d}.ply")
        info[obj_id] = info[src]
    save_models_info(models / "models_info.json", info)
    shutil.copytree(root / "test", lm / "test")
    shutil.copy(root / "test_targets_bop24.json", lm / "test_targets_bop24.json")


def run_toolkit(root: Path, toolkit: Path, python: Path, work: Path) -> dict:
    """Run ``scripts/eval_bop24_pose.py`` on the case in ``root``; its ``scores_bop24.json``."""
    bop_path, results, eval_path = work / "bop", work / "results", work / "eval"
    _as_lm(root, bop_path)
    results.mkdir()
    eval_path.mkdir()
    shutil.copy(root / "synth_lm-test.csv", results / "synth_lm-test.csv")
    env = {
        **os.environ,
        "PYTHONPATH": str(toolkit),
        "BOP_PATH": str(bop_path),
        "BOP_RESULTS_PATH": str(results),
        "BOP_EVAL_PATH": str(eval_path),
        "PATH": f"{python.parent}{os.pathsep}{os.environ['PATH']}",
    }
    cmd = [
        str(python),
        str(toolkit / "scripts" / "eval_bop24_pose.py"),
        "--result_filenames=synth_lm-test.csv",
        "--num_workers=1",
    ]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if proc.returncode != 0 or not (eval_path / "synth_lm-test" / "scores_bop24.json").exists():
        raise RuntimeError(f"the toolkit failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    scores = load_json(eval_path / "synth_lm-test" / "scores_bop24.json")
    per_object = {}
    for sub in sorted((eval_path / "synth_lm-test").glob("error=*")):
        for f in sorted(sub.glob("scores_th=*.json")):
            per_object[f"{sub.name}/{f.stem}"] = load_json(f)["scores"]
    return {"scores": scores, "per_object_ap": per_object}


def run_oracle(
    argv: list[str] | None,
    description: str,
    fixture: Path,
    seeds: tuple[int, ...],
    case: Callable[[int, Path, Path, Path], dict],
) -> int:
    """Command line of an oracle script: ``case(seed, work_dir, toolkit, python)`` gives the
    toolkit's numbers of one seed; all seeds are written to ``fixture`` with the commit."""
    p = argparse.ArgumentParser(description=description)
    p.add_argument("--toolkit", type=Path, required=True, help="thodan/bop_toolkit checkout")
    p.add_argument("--python", type=Path, required=True, help="python that runs the toolkit")
    p.add_argument("--commit", default="", help="the toolkit's commit, if not a git checkout")
    args = p.parse_args(argv)
    commit = subprocess.run(
        ["git", "-C", str(args.toolkit), "rev-parse", "HEAD"], capture_output=True, text=True
    ).stdout.strip()
    out: dict = {"toolkit_commit": commit or args.commit or "unknown", "cases": {}}
    for seed in seeds:
        with tempfile.TemporaryDirectory() as tmp:
            out["cases"][str(seed)] = case(seed, Path(tmp), args.toolkit, args.python)
        print(f"seed {seed}: {out['cases'][str(seed)]}")
    fixture.parent.mkdir(exist_ok=True)
    fixture.write_text(json.dumps(out, indent=1, sort_keys=True) + "\n")
    print(f"wrote {fixture}")
    return 0


def _case(seed: int, work: Path, toolkit: Path, python: Path) -> dict:
    build_case(work / "ds", seed)
    return run_toolkit(work / "ds", toolkit, python, work)


def main(argv: list[str] | None = None) -> int:
    return run_oracle(argv, __doc__.split("\n\n")[0], FIXTURE, SEEDS, _case)


if __name__ == "__main__":
    sys.exit(main())

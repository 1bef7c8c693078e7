r"""Inputs of the COCO equality test, and the script that asks the reference toolkit for its
numbers on them (``scripts/eval_bop22_coco.py``: bbox amodal, bbox modal, segm).

Each case: two scenes of 640 x 480 images with sparse image ids, 1-5 rectangular instances
of three objects per image (several of one object; small, medium and large; occluding each
other in depth order: half covers, so visible boxes differ from amodal ones; some
hidden); results with jittered boxes and
masks, duplicates, misses, false positives of absent objects, tied scores, results of
images that are not targets, and segmentations as compressed RLE (as submissions have them).
The targets list the images scene-interleaved so that the merging order matters.

Regenerate ``data/coco_reference.json`` with a checkout of thodan/bop_toolkit and a Python
environment that runs it with pycocotools::

    python -m tests.bopsurg.evaluation.coco_oracle --toolkit /path/to/bop_toolkit \
        --python /path/to/toolkit-venv/bin/python
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np

from bopsurg.bop.coco import (
    SCENE_GT_COCO,
    mask_bbox,
    rle_bbox,
    rle_to_mask,
    write_detection_annotations,
)
from bopsurg.bop.dataset import BopDataset, save_camera_json
from bopsurg.bop.images import save_mask
from bopsurg.bop.jsonio import load_json, save_json
from bopsurg.bop.meshes import save_models_info
from bopsurg.bop.scene import (
    CameraInfo,
    GtInfo,
    GtPose,
    save_scene_camera,
    save_scene_gt,
    save_scene_gt_info,
)
from bopsurg.bop.targets import ImageTarget, save_image_targets
from bopsurg.example import DEFAULT_K
from tests.bopsurg.evaluation.bop24_oracle import run_oracle

SEEDS = (0, 1)
FIXTURE = Path(__file__).parent / "data" / "coco_reference.json"
RESULTS = "synth_lm-test.json"
W, H = 640, 480
#: (ann_type, bbox_type) runs of the reference script and our key prefix for each.
RUNS = {"bbox": ("bbox", "amodal"), "bbox_modal": ("bbox", "modal"), "segm": ("segm", "amodal")}


def _rect(rng: np.random.Generator) -> tuple[int, int, int, int]:
    side = rng.choice([12, 50, 140])  # COCO small / medium / large
    w, h = (int(v) for v in np.maximum(4, rng.normal(side, side / 4, 2)))
    x, y = int(rng.integers(-w // 3, W - w // 2)), int(rng.integers(-h // 3, H - h // 2))
    return x, y, w, h


def build_case(root: Path, seed: int) -> tuple[BopDataset, list[dict[str, Any]]]:
    """Write the dataset (split ``test``) and return its COCO results."""
    rng = np.random.default_rng(seed)
    save_camera_json(root, DEFAULT_K, W, H)
    save_models_info(
        root / "models" / "models_info.json", {o: {"diameter": 10.0} for o in (1, 2, 3)}
    )
    targets = []
    for scene_id in (1, 2):
        sdir = root / "test" / f"{scene_id:06d}"
        gts, infos = {}, {}
        for im_id in sorted(rng.choice(12, size=4, replace=False).tolist()):
            n = int(rng.integers(1, 6))
            objs = rng.choice([1, 1, 2, 3], size=n)
            depth = rng.permutation(n)  # 0 = nearest
            full = np.zeros((n, H, W), bool)
            prev = None
            for k in range(n):
                x, y, w, h = _rect(rng)
                if prev is not None and rng.random() < 0.6:  # over the right half of the last
                    px, py, pw, ph = prev
                    x, y, w, h = px + pw // 2, py - ph // 4, max(w, pw), ph + ph // 2
                prev = (x, y, w, h)
                full[k, max(y, 0) : y + h, max(x, 0) : x + w] = True
            gts[im_id], infos[im_id] = [], []
            for k in range(n):
                nearer = full[depth < depth[k]].any(axis=0)
                visib = full[k] & ~nearer
                save_mask(sdir / "mask" / f"{im_id:06d}_{k:06d}.png", full[k])
                save_mask(sdir / "mask_visib" / f"{im_id:06d}_{k:06d}.png", visib)
                n_all, n_vis = int(full[k].sum()), int(visib.sum())
                box = tuple(mask_bbox(full[k])) if n_all else (-1, -1, -1, -1)
                vbox = tuple(mask_bbox(visib)) if n_vis else (-1, -1, -1, -1)
                vf = n_vis / n_all if n_all else 0.0
                infos[im_id].append(GtInfo(box, vbox, n_all, n_all, n_vis, vf))
                gts[im_id].append(
                    GtPose(int(objs[k]), np.eye(3), np.array([0, 0, 100.0 + depth[k]]))
                )
        save_scene_gt(sdir / "scene_gt.json", gts)
        save_scene_gt_info(sdir / "scene_gt_info.json", infos)
        save_scene_camera(sdir / "scene_camera.json", {i: CameraInfo(K=DEFAULT_K) for i in gts})
        targets += [ImageTarget(scene_id, i) for i in list(gts)[:3]]  # the 4th is no target
    order = rng.permutation(len(targets))
    save_image_targets(root / "test_targets_bop24.json", [targets[i] for i in order])
    ds = BopDataset(root, "test")
    write_detection_annotations(ds, keep_targets=True)
    return ds, _results(ds, rng)


def _results(ds: BopDataset, rng: np.random.Generator) -> list[dict[str, Any]]:
    from pycocotools import mask as mask_utils

    def rle(m: np.ndarray) -> dict[str, Any]:
        r = mask_utils.encode(np.asfortranarray(m.astype(np.uint8)))
        return {"counts": r["counts"].decode("ascii"), "size": [int(v) for v in r["size"]]}

    out = []
    for scene in ds.iter_scenes():
        coco = load_json(scene.scene_dir / SCENE_GT_COCO)
        for ann in coco["annotations"]:
            if rng.random() < 0.15:
                continue  # a miss
            x, y, w, h = ann["bbox"]
            for _ in range(1 + int(rng.random() < 0.2)):  # sometimes a duplicate
                jitter = rng.normal(0, 0.08, 4) * [w, h, w, h]
                box = [float(x + jitter[0]), float(y + jitter[1]), float(max(1, w + jitter[2])),
                       float(max(1, h + jitter[3]))]  # fmt: skip
                vis = np.zeros((H, W), bool)
                ys, xs = np.nonzero(rle_to_mask(ann["segmentation"]))
                shift = rng.integers(-3, 4, 2)
                vis[np.clip(ys + shift[0], 0, H - 1), np.clip(xs + shift[1], 0, W - 1)] = True
                out.append(
                    {
                        "scene_id": scene.scene_id,
                        "image_id": ann["image_id"],
                        "category_id": ann["category_id"],
                        "score": float(rng.choice([0.5, 0.7, 0.9, rng.random()])),
                        "bbox": box,
                        "segmentation": rle(vis),
                        "time": 0.2,
                    }
                )
        for im in coco["images"]:  # a false positive of object 3 per image, often absent
            m = np.zeros((H, W), bool)
            x, y, w, h = _rect(rng)
            m[max(y, 0) : y + h, max(x, 0) : x + w] = True
            out.append(
                {
                    "scene_id": scene.scene_id,
                    "image_id": im["id"],
                    "category_id": 3,
                    "score": float(rng.random() * 0.6),
                    "bbox": [float(v) for v in mask_bbox(m)],
                    "segmentation": rle(m),
                    "time": 0.2,
                }
            )
    return out


#: The script passes an in-memory dict to ``COCO()``: the toolkit pins a cocoapi fork that
#: accepts one, PyPI's pycocotools reads only a path. This shim builds the index from the
#: dict and runs the script unchanged.
_SHIM = """
import runpy, sys
from pycocotools import coco
_init = coco.COCO.__init__
def _dict_init(self, annotation_file=None):
    if isinstance(annotation_file, dict):
        _init(self)
        self.dataset = annotation_file
        self.createIndex()
    else:
        _init(self, annotation_file)
coco.COCO.__init__ = _dict_init
sys.argv = sys.argv[1:]
runpy.run_path(sys.argv[0], run_name="__main__")
"""


def run_toolkit(root: Path, results: list, toolkit: Path, python: Path, work: Path) -> dict:
    """Run ``scripts/eval_bop22_coco.py`` three times on the case; scores per run."""
    bop, res_dir, eval_dir = work / "bop", work / "results", work / "eval"
    lm = bop / "lm"
    shutil.copytree(root / "test", lm / "test")
    shutil.copy(root / "test_targets_bop24.json", lm / "test_targets_bop24.json")
    (lm / "models_eval").mkdir(parents=True)
    for scene in sorted((lm / "test").iterdir()):  # the modal variant the script reads
        coco = load_json(scene / SCENE_GT_COCO)
        for a in coco["annotations"]:
            a["bbox"] = rle_bbox(a["segmentation"])
        save_json(scene / "scene_gt_coco_modal.json", coco)
    res_dir.mkdir()
    eval_dir.mkdir()
    (res_dir / RESULTS).write_text(json.dumps(results))
    env = {
        **os.environ,
        "PYTHONPATH": str(toolkit),
        "BOP_PATH": str(bop),
        "BOP_RESULTS_PATH": str(res_dir),
        "BOP_EVAL_PATH": str(eval_dir),
    }
    out = {}
    for key, (ann_type, bbox_type) in RUNS.items():
        cmd = [str(python), "-c", _SHIM, str(toolkit / "scripts" / "eval_bop22_coco.py"),
               f"--result_filenames={RESULTS}", f"--results_path={res_dir}",
               f"--eval_path={eval_dir}", "--targets_filename=test_targets_bop24.json",
               f"--ann_type={ann_type}", f"--bbox_type={bbox_type}"]  # fmt: skip
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
        name = f"scores_bop22_coco_{ann_type}" + ("_modal" if key == "bbox_modal" else "")
        path = eval_dir / RESULTS.removesuffix(".json") / f"{name}.json"
        if proc.returncode != 0 or not path.exists():
            raise RuntimeError(f"the toolkit failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
        out[key] = load_json(path)
    return out


def _case(seed: int, work: Path, toolkit: Path, python: Path) -> dict:
    _, results = build_case(work / "ds", seed)
    return run_toolkit(work / "ds", results, toolkit, python, work)


def main(argv: list[str] | None = None) -> int:
    return run_oracle(argv, __doc__.split("\n\n")[0], FIXTURE, SEEDS, _case)


if __name__ == "__main__":
    sys.exit(main())

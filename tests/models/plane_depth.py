"""Depth images for the example dataset (it has none): a plane at each needle's depth, so the
pose head's object coordinates can be computed from them."""

from __future__ import annotations

import numpy as np

from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.images import save_depth


def write_plane_depth(ds: BopDataset, shape: tuple[int, int] = (480, 640)) -> None:
    """Write ``depth/IM.png`` (depth_scale 0.1 mm) into every scene of ``ds``: the GT needle's
    depth, or 100 mm in an image without a needle."""
    for scene in ds.iter_scenes():
        for im_id in scene.im_ids:
            z = scene.gt[im_id][0].t[2] if scene.gt.get(im_id) else 100.0
            path = scene.depth_path(im_id)
            path.parent.mkdir(parents=True, exist_ok=True)
            save_depth(path, np.full(shape, z / 0.1))


def train_pose_runs(root, recipes: dict[str, str]) -> tuple[dict[str, dict], dict[str, dict]]:
    """Train the test preset's pose head for one epoch on a small example split (plane depth)
    once per ``recipes`` entry (name -> the YAML flow mapping of its ``recipe`` section);
    returns each run's weights and the recipe it wrote into its config.yaml."""
    import yaml

    from bopsurg.cli.main import main
    from bopsurg.example import ExampleSpec, write_example_dataset
    from bopsurg.models.checkpoint import load_tensors

    ex = write_example_dataset(root / "d", ExampleSpec(seed=1, scenes=2, images_per_scene=4))
    write_plane_depth(BopDataset(ex.root, ex.split))
    weights, written = {}, {}
    for name, recipe in recipes.items():
        cfg = root / f"{name}.yaml"
        cfg.write_text(f"preset: test\nrecipe: {recipe}\n")
        out = root / name
        args = ["train", "pose", str(ex.root), "--split", ex.split, "--out", str(out)]
        assert main([*args, "--config", str(cfg), "--no-progress", "--threads", "1"]) == 0
        weights[name] = load_tensors(out / "pose.pt")
        written[name] = yaml.safe_load((out / "config.yaml").read_text())["recipe"]
    return weights, written

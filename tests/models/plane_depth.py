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

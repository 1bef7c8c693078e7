"""VSD of BOP19's kept pairs, image by image: render the models' windows, decode the depth box.

A :class:`VsdJob` holds everything VSD needs as plain arrays, paths and meshes (no dataset
object, no pandas), so that it can run in this process or in the VSD worker process
(:mod:`bopsurg.evaluation.vsd_worker`) while the rest of the evaluation proceeds. Pairs are
rendered image by image, each GT pose once, each model only in the window it covers; of the
image's depth only the box around those windows is decoded, in a second thread while the next
image renders (decoding releases the GIL).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, cast

import numpy as np
from numpy.typing import NDArray

from bopsurg.bop.images import image_size, load_depth_window
from bopsurg.bop.meshes import ObjectModel
from bopsurg.metrics.vsd import vsd_in_window

if TYPE_CHECKING:  # (the worker process loads no entry points)
    from bopsurg.plugins import DepthRenderer

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: The τ values of BOP19's VSD (the rows of :func:`vsd_errors`' result), as the reference.
VSD_TAUS: tuple[float, ...] = tuple(float(x) for x in np.arange(0.05, 0.51, 0.05))

#: A model's depth in a window of the image (mm) and the window's top-left (row, column);
#: None when the model is not seen.
WindowDepth = tuple[F64, tuple[int, int]] | None
WindowRenderer = Callable[[ObjectModel, F64, F64, F64, int, int], WindowDepth]


@dataclass(frozen=True)
class VsdImage:
    """One test image with pairs to render.

    Attributes:
        depth_path: Its depth PNG.
        K: (3, 3) intrinsics, px.
        depth_scale: mm per depth unit.
        pairs: Columns of the job's pairs in this image, in rendering order.
    """

    depth_path: Path
    K: F64
    depth_scale: float
    pairs: I64


@dataclass(frozen=True)
class VsdJob:
    """The VSD errors to compute: P pairs (estimate pose, GT pose) of one model each.

    Attributes:
        images: The images whose pairs are rendered, in order; pairs in none of them (the
            bounding-sphere projections do not overlap) keep error 1.
        models: The meshes by object id (mm).
        obj_id: (P,) object of each pair.
        gt_key: (P,) identifies the GT instance of each pair: its render is shared.
        R_est, t_est, R_gt, t_gt: (P, 3, 3) and (P, 3) poses, mm.
        diameter: (P,) object diameters, mm.
        delta: Visibility tolerance δ, mm.
    """

    images: tuple[VsdImage, ...]
    models: dict[int, ObjectModel]
    obj_id: I64
    gt_key: I64
    R_est: F64
    t_est: F64
    R_gt: F64
    t_gt: F64
    diameter: F64
    delta: float

    @property
    def n_pairs(self) -> int:
        """P."""
        return int(self.obj_id.shape[0])


class ImageClaims:
    """A job's images shared out between two processes without a lock.

    One process takes images from the front, the other from the back, each by creating the
    image's file in a common folder: ``O_EXCL`` lets exactly one creation succeed. Each stops
    at the first image the other has taken, so every image is taken exactly once, and the
    faster process takes more (the VSD worker, busy from the start, and the caller, free only
    once the rest of the evaluation is done).
    """

    def __init__(self, folder: str | os.PathLike[str], n_images: int) -> None:
        self.folder = Path(folder)
        self.n_images = n_images

    def _take(self, index: int) -> bool:
        try:
            fd = os.open(self.folder / str(index), os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            return False
        os.close(fd)
        return True

    def from_front(self) -> Iterator[int]:
        """Image indices 0, 1, ... until one is taken already."""
        for i in range(self.n_images):
            if not self._take(i):
                return
            yield i

    def from_back(self) -> Iterator[int]:
        """Image indices n − 1, n − 2, ... until one is taken already."""
        for i in reversed(range(self.n_images)):
            if not self._take(i):
                return
            yield i


def window_renderer(renderer: DepthRenderer) -> WindowRenderer:
    """The renderer's ``render_depth_window`` when it has one, else its whole-image
    ``render_depth`` cut to the bounding box of the model's pixels."""
    windowed = getattr(renderer, "render_depth_window", None)
    if callable(windowed):
        return cast(WindowRenderer, windowed)

    def render(model: ObjectModel, R: F64, t: F64, K: F64, width: int, height: int) -> WindowDepth:
        depth = np.asarray(renderer.render_depth(model, R, t, K, width, height))
        rows = np.flatnonzero((depth > 0).any(axis=1))
        if rows.size == 0:
            return None
        cols = np.flatnonzero((depth > 0).any(axis=0))
        r0, r1, c0, c1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
        return depth[r0:r1, c0:c1], (r0, c0)

    return render


def vsd_errors(
    job: VsdJob, render: WindowRenderer, images: Iterable[VsdImage] | None = None
) -> F64:
    """VSD errors (τ × P) of the job's pairs, 1 for the pairs of no image.

    Args:
        job: The pairs, images and models.
        render: The renderer's window function (:func:`window_renderer`).
        images: The images to go through (default: all of the job's), e.g. wrapped in a
            progress bar.
    """
    out = np.ones((len(VSD_TAUS), job.n_pairs))
    with ThreadPoolExecutor(max_workers=1) as decoder:
        previous: _ImageRenders | None = None
        for image in job.images if images is None else images:
            current = _render_image(image, job, render, decoder)
            if previous is not None:
                _score_image(out, previous, job)
            previous = current
        if previous is not None:
            _score_image(out, previous, job)
    return out


def _span(windows: Sequence[WindowDepth]) -> tuple[int, int, int, int] | None:
    """(row0, row1, col0, col1), ends exclusive, of the box around the windows; None if none."""
    seen = [w for w in windows if w is not None]
    if not seen:
        return None
    r0 = min(o[0] for _, o in seen)
    c0 = min(o[1] for _, o in seen)
    r1 = max(o[0] + d.shape[0] for d, o in seen)
    c1 = max(o[1] + d.shape[1] for d, o in seen)
    return r0, r1, c0, c1


def _pasted(win: WindowDepth, box: tuple[int, int, int, int]) -> F64:
    """A model's window depth on the box (0 outside the window)."""
    r0, r1, c0, c1 = box
    out = np.zeros((r1 - r0, c1 - c0))
    if win is not None:
        depth, (wr, wc) = win
        out[wr - r0 : wr - r0 + depth.shape[0], wc - c0 : wc - c0 + depth.shape[1]] = depth
    return out


@dataclass(frozen=True)
class _ImageRenders:
    """One image's rendered pairs and its depth box, being decoded (None: nothing rendered)."""

    image: VsdImage
    est_win: list[WindowDepth]
    gt_win: dict[int, WindowDepth]
    span: tuple[int, int, int, int] | None
    depth: Future[NDArray[np.float32]] | None


def _render_image(
    image: VsdImage, job: VsdJob, render: WindowRenderer, decoder: ThreadPoolExecutor
) -> _ImageRenders:
    """Render the image's pairs and start decoding its depth box."""
    w, h = image_size(image.depth_path)
    gt_win: dict[int, WindowDepth] = {}
    est_win: list[WindowDepth] = []
    for p in image.pairs.tolist():  # one render per pose: the renderer's unit of work
        g = int(job.gt_key[p])
        model = job.models[int(job.obj_id[p])]
        if g not in gt_win:
            gt_win[g] = render(model, job.R_gt[p], job.t_gt[p], image.K, w, h)
        est_win.append(render(model, job.R_est[p], job.t_est[p], image.K, w, h))
    span = _span([*gt_win.values(), *est_win])
    depth = None
    if span is not None:
        depth = decoder.submit(load_depth_window, image.depth_path, span[:2], span[2:])
    return _ImageRenders(image, est_win, gt_win, span, depth)


def _score_image(out: F64, renders: _ImageRenders, job: VsdJob) -> None:
    """VSD of one image's rendered pairs into their columns of ``out``."""
    if renders.span is None or renders.depth is None:  # no model pixel: every error stays 1
        return
    image = renders.image
    r0, _, c0, _ = renders.span
    depth = renders.depth.result() * image.depth_scale
    taus = np.asarray(VSD_TAUS)
    for p, e_w in zip(image.pairs.tolist(), renders.est_win, strict=True):
        g_w = renders.gt_win[int(job.gt_key[p])]
        box = _span([e_w, g_w])
        if box is None:
            continue
        test = depth[box[0] - r0 : box[1] - r0, box[2] - c0 : box[3] - c0]
        out[:, p] = vsd_in_window(test, _pasted(e_w, box), _pasted(g_w, box), image.K,
                                  (box[0], box[2]), job.delta, taus,
                                  diameter=float(job.diameter[p]))  # fmt: skip

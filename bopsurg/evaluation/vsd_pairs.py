"""VSD of BOP19's kept pairs: the job (:mod:`bopsurg.evaluation.vsd_images`) and where it runs.

``bopsurg eval`` starts VSD first (:func:`start_vsd_early`): on a worker process
(:mod:`bopsurg.evaluation.vsd_worker`) it renders while this process loads and runs the rest of
the evaluation; without one it runs here when its errors are asked for. No pandas here, so
that starting VSD waits for nothing else.
"""

from __future__ import annotations

import logging
import shutil
import tempfile
import time
import weakref
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.registry import VSD_DELTA_MM
from bopsurg.bop.results import PoseEstimates
from bopsurg.bop.targets import Target
from bopsurg.errors import DatasetError
from bopsurg.evaluation.bop19_pairs import KeptPairs, kept_pairs_of_targets
from bopsurg.evaluation.pair_errors import ModelCache
from bopsurg.evaluation.tables import GtTable, load_gt_table
from bopsurg.evaluation.vsd_images import ImageClaims, VsdImage, VsdJob, window_renderer
from bopsurg.evaluation.vsd_images import vsd_errors as job_vsd_errors
from bopsurg.evaluation.vsd_worker import VsdWorker, VsdWorkerError
from bopsurg.plugins import DepthRenderer

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


def sphere_projections_overlap(t_est: F64, t_gt: F64, radius: F64) -> NDArray[np.bool_]:
    """The reference's approximate overlap test of the bounding-sphere projections (VSD).

    Args:
        t_est, t_gt: (P, 3) translations, mm.
        radius: (P,) sphere radius (diameter / 2), mm.
    """
    ze, zg = t_est[:, 2], t_gt[:, 2]
    nonzero = (ze != 0) & (zg != 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        pe = t_est[:, :2] / ze[:, None]
        pg = t_gt[:, :2] / zg[:, None]
        dist = np.linalg.norm(pe - pg, axis=1)
        thresh = radius * (1.0 / ze + 1.0 / zg)
    result: NDArray[np.bool_] = nonzero & (dist < thresh)
    return result


@dataclass(frozen=True)
class VsdInputs:
    """What VSD needs besides the poses.

    Attributes:
        dataset: The dataset (depth images, cameras, models).
        renderer: Renders model depth at a pose.
        delta: Visibility tolerance δ, mm.
        progress: Show a progress bar over images.
        worker: A VSD worker process that renders with the same renderer plugin (it takes
            one job); None: VSD runs in this process.
    """

    dataset: BopDataset
    renderer: DepthRenderer
    delta: float = VSD_DELTA_MM
    progress: bool = False
    worker: VsdWorker | None = None


def vsd_job(
    est: PoseEstimates, gt: GtTable, e_idx: I64, g_idx: I64, diameter: F64, inputs: VsdInputs
) -> VsdJob:
    """The VSD of the pairs as a :class:`~bopsurg.evaluation.vsd_images.VsdJob`: the pairs
    whose bounding-sphere projections overlap, grouped by image (images in order).

    Raises:
        DatasetError: An image without ``depth_scale``.
    """
    dataset = inputs.dataset
    overlap = sphere_projections_overlap(est.t[e_idx], gt.t[g_idx], 0.5 * diameter)
    todo = np.flatnonzero(overlap)
    scene_of, im_of = gt.scene_id[g_idx[todo]], gt.im_id[g_idx[todo]]
    order = np.lexsort((im_of, scene_of))  # pairs grouped by image, images in order
    starts = np.flatnonzero(np.r_[True, np.diff(scene_of[order]) != 0]
                            | np.r_[True, np.diff(im_of[order]) != 0])  # fmt: skip
    images = []
    for group in np.split(todo[order], starts[1:]) if todo.size else ():
        first = int(g_idx[group[0]])
        scene_id, im_id = int(gt.scene_id[first]), int(gt.im_id[first])
        scene = dataset.scene(scene_id)
        cam = scene.camera[im_id]
        if cam.depth_scale is None:
            raise DatasetError(
                "depth_scale is missing (needed for VSD)",
                path=scene.scene_dir / "scene_camera.json",
                field=f"{im_id}/depth_scale",
            )
        images.append(VsdImage(scene.depth_path(im_id), cam.K, cam.depth_scale, group))
    obj_id = gt.obj_id[g_idx].astype(np.int64)
    return VsdJob(
        images=tuple(images),
        models={int(o): dataset.model(int(o)) for o in np.unique(obj_id[todo])},
        obj_id=obj_id,
        gt_key=np.asarray(g_idx, dtype=np.int64),
        R_est=est.R[e_idx],
        t_est=est.t[e_idx],
        R_gt=gt.R[g_idx],
        t_gt=gt.t[g_idx],
        diameter=np.asarray(diameter, dtype=np.float64),
        delta=inputs.delta,
    )


class PendingVsd:
    """VSD errors of a job being computed by the VSD worker process, or computed in this
    process when asked for (no worker, or the worker failed).

    With a worker, the images are shared out
    (:class:`~bopsurg.evaluation.vsd_images.ImageClaims`): the worker takes them from the
    front from the start; this process, once it asks for the errors, renders from the back
    until the two meet rather than wait. Every image's errors are the same whoever renders
    it. With a progress bar the worker renders them all (one bar over all images).
    """

    def __init__(self, job: VsdJob, inputs: VsdInputs) -> None:
        self._job = job
        self._inputs = inputs
        self._worker = inputs.worker
        self._claims: str | None = None
        self._remove_claims: weakref.finalize[Any, Any] | None = None
        if self._worker is not None:
            if not inputs.progress and len(job.images) > 1:
                self._claims = tempfile.mkdtemp(prefix="bopsurg-vsd-")
                # called by result(), or with this object if the evaluation stops before
                self._remove_claims = weakref.finalize(
                    self, shutil.rmtree, self._claims, ignore_errors=True
                )
            self._worker.submit(job, progress=inputs.progress, claims=self._claims)

    def result(self) -> F64:
        """(τ, P) VSD errors, 1 where the bounding-sphere projections do not overlap."""
        if self._worker is not None:
            worker, self._worker = self._worker, None
            try:
                return self._shared(worker, self._claims)
            except VsdWorkerError as err:
                log.debug("%s; computing VSD in this process", err)
            finally:
                if self._remove_claims is not None:
                    self._remove_claims()
        # no bar object without a bar: tqdm's lock would import multiprocessing
        images: Iterable[VsdImage] = self._job.images
        if self._inputs.progress:
            images = tqdm(self._job.images, desc="VSD", unit="img")
        return job_vsd_errors(self._job, window_renderer(self._inputs.renderer), images)

    def _shared(self, worker: VsdWorker, claims: str | None) -> F64:
        """The worker's errors, and this process's of the images it takes from the back."""
        if claims is None:
            return worker.result()
        job = self._job
        taken: list[int] = []

        def from_back() -> Iterator[VsdImage]:
            for i in ImageClaims(claims, len(job.images)).from_back():
                taken.append(i)
                yield job.images[i]

        render = window_renderer(self._inputs.renderer)
        start = time.perf_counter()
        try:
            here = job_vsd_errors(job, render, from_back())
        except Exception as err:  # e.g. a bad depth image: raised again in image order below
            worker.close()
            raise VsdWorkerError(f"VSD failed here ({err})") from err
        rendered = time.perf_counter()
        try:
            errors = worker.result()
            log.debug(
                "VSD: %d of %d images rendered here in %.3f s, the rest by the worker; "
                "then %.3f s waiting for it", len(taken), len(job.images),
                rendered - start, time.perf_counter() - rendered,
            )  # fmt: skip
        except VsdWorkerError as err:  # the images it did not take render here
            log.debug("%s; computing the rest of VSD in this process", err)
            mine = set(taken)
            rest = [image for i, image in enumerate(job.images) if i not in mine]
            errors = job_vsd_errors(job, render, rest)
        if taken:
            cols = np.concatenate([job.images[i].pairs for i in taken])
            errors[:, cols] = here[:, cols]
        return errors


def start_vsd(est: PoseEstimates, gt: GtTable, kept: KeptPairs, inputs: VsdInputs) -> PendingVsd:
    """Start the VSD of the kept pairs (in the worker process of ``inputs``, if any)."""
    pairs = kept.pairs
    return PendingVsd(
        vsd_job(est, gt, pairs.est_index, pairs.gt_index, kept.diameter, inputs), inputs
    )


def vsd_errors(
    est: PoseEstimates, gt: GtTable, e_idx: I64, g_idx: I64, diameter: F64, inputs: VsdInputs
) -> F64:
    """VSD errors (τ × P) of the pairs, 1 where the sphere projections do not overlap
    (:mod:`bopsurg.evaluation.vsd_images`).

    Raises:
        DatasetError: An image without ``depth_scale``.
    """
    return PendingVsd(vsd_job(est, gt, e_idx, g_idx, diameter, inputs), inputs).result()


@dataclass(frozen=True)
class StartedVsd:
    """VSD of a dataset's BOP19 pairs, started before the rest of the evaluation
    (:func:`start_vsd_early`), with the GT table and the pairs it was started on.

    Attributes:
        gt: The GT table of the whole split.
        kept: The BOP19 targets' kept pairs and valid GTs.
        inputs: Dataset, renderer, δ.
        errors: The VSD errors of ``kept.pairs``, pending.
    """

    gt: GtTable
    kept: KeptPairs
    inputs: VsdInputs
    errors: PendingVsd


def start_vsd_early(
    est: PoseEstimates, targets: Sequence[Target], models: ModelCache, inputs: VsdInputs
) -> StartedVsd:
    """Load the GT, find the BOP19 targets' kept pairs and start their VSD.

    Args:
        est: The estimates (checked against ``inputs.dataset``).
        targets: The BOP19 targets.
        models: The dataset's models (the pairs' diameters).
        inputs: Dataset, renderer, δ and the worker process, if any.
    """
    gt = load_gt_table(inputs.dataset)
    kept = kept_pairs_of_targets(est, gt, targets, models.diameters)
    return StartedVsd(gt, kept, inputs, start_vsd(est, gt, kept, inputs))

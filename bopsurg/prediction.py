"""Run a pose estimator over the images of a BOP split and write a BOP19 results CSV.

When the estimator declares the models it was trained on (``object_models``) and the
dataset's model of an object differs, the poses are mapped into the dataset's model frame
through the two fitted needle arcs (:mod:`bopsurg.model_frames`), or the run is refused
before any image when the models cannot be matched.

An estimator that declares ``uses_depth`` also gets each image's depth image in mm (stored
value × ``depth_scale``; 0 where there is no reading) unless the run is RGB-only. Where the
poses are mapped into a dataset model k times the size of the estimator's, the depth is
divided by k: the estimator sees the scene scaled to its own needle, as it sees the image.

Images go to the estimator in batches (``batch_size``; a thread decodes the next batch
meanwhile). Each batch is timed from the moment its pixels are in memory to the moment its
poses are (image decoding excluded, as BOP asks), and each of its images gets the batch's
time divided by its number of images in the CSV's ``time`` column. Progress is appended to
``RESULTS.partial`` after every batch, so a killed run resumes where it stopped; the final
CSV appears atomically at the end.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from bopsurg.atomic import write_text
from bopsurg.bop.dataset import BopDataset, BopScene
from bopsurg.bop.detections import Detections, save_detections
from bopsurg.bop.images import load_depth, load_rgb
from bopsurg.bop.results import (
    HEADER,
    PoseEstimates,
    format_result_row,
    load_results,
    save_results,
)
from bopsurg.errors import BopsurgError, ResultsError
from bopsurg.estimation import (
    ImageInput,
    PoseEstimator,
    PosePredictions,
    estimator_models,
    estimator_uses_depth,
    predict_images,
)
from bopsurg.model_frames import FrameMapping, map_predictions, model_mapping

log = logging.getLogger(__name__)

ImageKey = tuple[int, int]


@dataclass(frozen=True)
class PredictionRun:
    """What :func:`predict_dataset` did.

    Attributes:
        estimates: All estimates, in (scene_id, im_id) order.
        detections: The 2D box behind each estimate, per image.
        images: Number of images processed (resumed ones included).
        mean_time: Mean run time per image, s (resumed images included).
        mappings: The objects whose poses were mapped into the dataset's model frame.
        depth_images: Images whose depth the estimator was given (resumed ones excluded); 0
            for an RGB-only run.
    """

    estimates: PoseEstimates
    detections: dict[ImageKey, Detections]
    images: int
    mean_time: float
    mappings: tuple[FrameMapping, ...] = ()
    depth_images: int = 0


def dataset_mappings(dataset: BopDataset, estimator: PoseEstimator) -> dict[int, FrameMapping]:
    """Mappings from the estimator's models to the dataset's, for the objects where they differ.

    Empty when the estimator does not declare its models (``object_models``).

    Raises:
        BopsurgError: A model pair cannot be matched (see
            :func:`bopsurg.model_frames.model_mapping`).
    """
    models = estimator_models(estimator)
    if not models:
        return {}
    out = {}
    for obj_id, source in sorted(models.items()):
        if obj_id not in dataset.obj_ids:
            continue
        target = dataset.model(obj_id)
        m = model_mapping(obj_id, source, target, target_name=str(dataset.model_path(obj_id)))
        if m is not None:
            out[obj_id] = m
    return out


def depth_divisor(mappings: Mapping[int, FrameMapping]) -> float:
    """What to divide a depth image by so that it shows the scene at the estimator's scale:
    the mappings' common ``scale`` (1 without mappings).

    Raises:
        BopsurgError: The mapped objects are scaled differently (one depth image cannot show
            the scene at two scales).
    """
    scales = sorted({m.scale for m in mappings.values()})
    if len(scales) > 1:
        raise BopsurgError(
            f"the dataset's models are {scales} times the estimator's: one depth image cannot "
            "match them all; run RGB-only (bopsurg predict --no-depth)"
        )
    return scales[0] if scales else 1.0


def _load_depth_mm(scene: BopScene, im_id: int, divisor: float) -> np.ndarray | None:
    """An image's depth in mm divided by ``divisor``, or None when it has none."""
    scale = scene.camera[im_id].depth_scale
    path = scene.depth_path(im_id)
    if scale is None or not path.is_file():
        return None
    return load_depth(path).astype(np.float64) * (scale / divisor)


def image_targets(dataset: BopDataset, known: Iterable[int]) -> dict[ImageKey, tuple[int, ...]]:
    """The objects to look for in each image of the split.

    From the test targets file when the dataset has one (only its listed images, as BOP
    evaluates), else every image of the split with all objects ``known`` to the estimator.
    """
    known = tuple(sorted(set(known)))
    path = dataset.root / "test_targets_bop19.json"
    if path.is_file():
        out: dict[ImageKey, set[int]] = {}
        for tg in dataset.targets():
            if tg.scene_id in dataset.scene_ids:
                out.setdefault((tg.scene_id, tg.im_id), set()).add(tg.obj_id)
        if out:
            return {k: tuple(sorted(v)) for k, v in sorted(out.items())}
    return {
        (s, i): known for s in dataset.scene_ids for i in sorted(dataset.scene(s).camera)
    }  # fmt: skip


def _format_row(scene: int, im: int, pred: PosePredictions, k: int, secs: float) -> str:
    return format_result_row(
        scene, im, int(pred.obj_id[k]), float(pred.score[k]), pred.R[k].reshape(9).tolist(),
        pred.t[k].tolist(), secs,
    )  # fmt: skip


def _bbox_line(scene: int, im: int, pred: PosePredictions, k: int) -> str:
    return f"# box {scene},{im},{' '.join(map(str, pred.bbox[k].tolist()))}"


def _read_partial(path: Path) -> tuple[list[str], dict[ImageKey, float]]:
    """Complete lines of an interrupted run and the images they finished.

    An image counts as done once its ``# done scene,im,seconds`` marker is written, so a kill in the
    middle of an image only loses that image. A torn last line is dropped.
    """
    if not path.is_file():
        return [], {}
    text = path.read_text(encoding="utf-8")
    lines = text.split("\n")
    if not text.endswith("\n"):
        lines = lines[:-1]  # torn last line
    keep: list[str] = []
    pending: list[str] = []
    done: dict[ImageKey, float] = {}
    for line in lines:
        if line.startswith("# done "):
            s, i, secs = line[len("# done ") :].split(",")
            done[(int(s), int(i))] = float(secs)
            keep.extend(pending)
            keep.append(line)
            pending = []
        elif line:
            pending.append(line)
    return keep, done


def _no_estimates() -> PoseEstimates:
    empty = np.zeros(0, np.int64)
    return PoseEstimates.from_arrays(
        empty, empty, empty, np.zeros(0), np.zeros((0, 3, 3)), np.zeros((0, 3))
    )


def _partial_to_outputs(
    lines: list[str], path: Path
) -> tuple[PoseEstimates, dict[ImageKey, Detections]]:
    rows = [ln for ln in lines if not ln.startswith("#")]
    boxes: dict[ImageKey, list[tuple[float, ...]]] = {}
    for ln in lines:
        if ln.startswith("# box "):
            s, i, b = ln[len("# box ") :].split(",")
            boxes.setdefault((int(s), int(i)), []).append(tuple(map(float, b.split())))
    tmp = path.with_name(path.name + ".csv")
    tmp.write_text("\n".join([HEADER, *rows]), encoding="utf-8")
    try:
        est = load_results(tmp) if rows else _no_estimates()
    finally:
        tmp.unlink()
    dets: dict[ImageKey, Detections] = {}
    for key, bs in boxes.items():
        sel = (est.scene_id == key[0]) & (est.im_id == key[1])
        xywh = np.array(bs, dtype=np.float64).reshape(-1, 4)
        valid = np.isfinite(xywh).all(axis=1)
        dets[key] = Detections(est.obj_id[sel][valid], est.score[sel][valid], xywh[valid])
    return est, dets


def run_config_path(results: str | Path) -> Path:
    """Where the settings of a results file are written: ``RESULTS.config.yaml`` beside it
    (``results.csv`` -> ``results.config.yaml``)."""
    p = Path(results)
    return p.with_name(f"{p.stem}.config.yaml")


def save_run_config(results: str | Path, estimator: str, config: Mapping[str, Any]) -> Path:
    """Write the settings a results file is made with (atomically): a YAML mapping that
    ``bopsurg predict --estimator ESTIMATOR --config FILE`` takes back; returns its path."""
    import yaml

    path = run_config_path(results)
    header = f"# bopsurg predict --estimator {estimator}: the settings of {Path(results).name}\n"
    write_text(path, header + yaml.safe_dump(dict(config), sort_keys=False))
    return path


class _Mapped:
    """An estimator whose poses come mapped into the dataset's model frames."""

    def __init__(
        self, estimator: PoseEstimator, mappings: Mapping[int, FrameMapping], depth: bool
    ) -> None:
        self.estimator, self.mappings, self.obj_ids = estimator, mappings, estimator.obj_ids
        self.depth = depth  # pass depth= (False: an RGB-only run)

    def predict(self, rgb: Any, K: Any, **kw: Any) -> PosePredictions:
        return self.predict_batch([ImageInput(rgb, K, **kw)])[0]

    def predict_batch(self, images: Sequence[ImageInput]) -> list[PosePredictions]:
        out = []
        for pred in predict_images(self.estimator, images, depth=self.depth):
            if not isinstance(pred, PosePredictions):
                raise BopsurgError(
                    f"estimator returned {type(pred).__name__}, expected PosePredictions"
                )
            out.append(map_predictions(pred, self.mappings))
        return out


def _load_image(
    dataset: BopDataset,
    key: ImageKey,
    obj_ids: tuple[int, ...],
    boxes: Detections | None,
    depth_divisor: float | None,
) -> ImageInput:
    """One image decoded, with its camera, targets, boxes and (``depth_divisor`` not None)
    its depth in mm divided by ``depth_divisor``."""
    scene_id, im_id = key
    scene = dataset.scene(scene_id)
    depth = None if depth_divisor is None else _load_depth_mm(scene, im_id, depth_divisor)
    return ImageInput(load_rgb(scene.rgb_path(im_id)), scene.camera[im_id].K, obj_ids, boxes, depth)


def _image_lines(key: ImageKey, pred: PosePredictions, secs: float) -> list[str]:
    """An image's result and detection lines, then its ``# done`` marker."""
    chunk = []
    for k in range(len(pred)):
        chunk.append(_format_row(key[0], key[1], pred, k, secs))
        chunk.append(_bbox_line(key[0], key[1], pred, k))
    return [*chunk, f"# done {key[0]},{key[1]},{secs}"]


def _batches(keys: list[ImageKey], size: int) -> list[list[ImageKey]]:
    return [keys[i : i + size] for i in range(0, len(keys), size)]


def _load_all(load: Callable[[ImageKey], ImageInput], keys: list[ImageKey]) -> list[ImageInput]:
    return [load(k) for k in keys]


def _decoded_batches(
    batches: list[list[ImageKey]], load: Callable[[ImageKey], ImageInput]
) -> Iterator[tuple[list[ImageKey], list[ImageInput]]]:
    """Each batch with its images decoded; a thread decodes the next batch while the caller
    works on this one (decoding is not part of an image's time, and overlaps with it)."""
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="decode") as pool:
        ahead = [pool.submit(_load_all, load, b) for b in batches[:1]]
        for i, batch in enumerate(batches):
            images = ahead.pop().result()
            ahead += [pool.submit(_load_all, load, b) for b in batches[i + 1 : i + 2]]
            yield batch, images


def _predict_batch(
    estimator: _Mapped, keys: list[ImageKey], images: list[ImageInput]
) -> tuple[list[str], float]:
    """A batch's result, detection and ``# done`` lines, and its time per image (s)."""
    t0 = time.perf_counter()
    preds = estimator.predict_batch(images)
    secs = (time.perf_counter() - t0) / len(keys)  # the batch's time, shared by its images
    return [
        ln for key, p in zip(keys, preds, strict=True) for ln in _image_lines(key, p, secs)
    ], secs


def predict_dataset(
    dataset: BopDataset,
    estimator: PoseEstimator,
    out: str | Path,
    *,
    boxes: Mapping[ImageKey, Detections] | None = None,
    detections_out: str | Path | None = None,
    max_images: int | None = None,
    progress: bool = True,
    depth: bool = True,
    batch_size: int = 1,
) -> PredictionRun:
    """Estimate poses in every target image of ``dataset`` and write the results CSV.

    Args:
        dataset: The split to run on.
        estimator: Any :class:`~bopsurg.estimation.PoseEstimator`.
        out: Results CSV (BOP19: ``scene_id,im_id,obj_id,score,R,t,time``).
        boxes: External 2D boxes per image (see :mod:`bopsurg.bop.detections`); an image
            without an entry gets an empty Detections (so no estimates).
        detections_out: Also write the 2D box of every estimate as BOP detections JSON.
        max_images: Stop after this many images (a quick look); None = all.
        progress: Show a progress bar.
        depth: Give an estimator that uses depth (``uses_depth``) each image's depth image;
            False: RGB only.
        batch_size: Images per call of the estimator (``predict_batch``, see
            :func:`bopsurg.estimation.predict_images`); each image's time is the batch's time
            divided by its images.

    Raises:
        BopsurgError: ``batch_size`` < 1, the estimator returned something that is not a
            PosePredictions, its models cannot be matched to the dataset's, or a bad image /
            dataset file (named).
    """
    if batch_size < 1:
        raise BopsurgError(f"batch size must be >= 1, got {batch_size}")
    mappings = dataset_mappings(dataset, estimator)
    for mapping in mappings.values():
        log.info("%s", mapping.describe())
    use_depth = depth and estimator_uses_depth(estimator)
    mapped = _Mapped(estimator, mappings, use_depth)
    divisor, depth_images = (depth_divisor(mappings) if use_depth else None), 0
    out = Path(out)
    partial = out.with_name(out.name + ".partial")
    lines, done = _read_partial(partial)
    if done:
        log.info("resuming: %d images already done in %s", len(done), partial)
    todo = image_targets(dataset, mapped.obj_ids)
    keys = list(todo)[: max_images if max_images is not None else None]

    def load(key: ImageKey) -> ImageInput:
        img_boxes = None if boxes is None else boxes.get(key, Detections.empty())
        return _load_image(dataset, key, todo[key], img_boxes, divisor)

    partial.parent.mkdir(parents=True, exist_ok=True)
    bar = tqdm(total=len(keys), desc="predict", unit="img", disable=not progress)
    bar.update(sum(k in done for k in keys))
    with partial.open("w", encoding="utf-8") as fh, bar:
        # Rewrite what survived (drops a torn tail), then append batch by batch.
        fh.write("".join(ln + "\n" for ln in lines))
        fh.flush()
        batches = _batches([k for k in keys if k not in done], batch_size)
        for batch, images in _decoded_batches(batches, load):
            chunk, secs = _predict_batch(mapped, batch, images)
            depth_images += sum(im.depth is not None for im in images)
            done.update(dict.fromkeys(batch, secs))
            fh.write("".join(c + "\n" for c in chunk))
            fh.flush()
            lines.extend(chunk)
            bar.update(len(batch))
    try:
        est, dets = _partial_to_outputs(lines, partial)
    except ResultsError as err:  # only a foreign or hand-edited partial file gets here
        raise BopsurgError(f"{partial}: unreadable progress file ({err}); delete it") from err
    save_results(out, est)
    if detections_out is not None:
        save_detections(detections_out, dets, done)
    partial.unlink()
    mean_time = float(np.mean(list(done.values()))) if done else float("nan")
    return PredictionRun(est, dets, len(done), mean_time, tuple(mappings.values()), depth_images)

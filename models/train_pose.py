"""Train the GDR-Net-like pose head on the GT instances of a BOP split.

Per batch, from the context crops of :class:`~bopsurg.models.data.PoseSet` (read from disk per
batch): dynamic zoom-in (DZI) around the visible box, ROI image (bilinear, ``roi_in``), visible
mask and object coordinates (nearest, ``roi_out``), the soft mask (covered fraction per cell),
normalised coordinates and FPS surface regions computed on the fly, colour jitter, the optional
photometric augmentations of ``recipe.augment`` (blur, noise, gamma, colour, JPEG; off by
default) on the ROI image, SITE and allocentric targets; the GDR-Net losses of
:func:`~bopsurg.models.pose.losses.gdr_losses`. Recipe (as GDR-Net's): AdamW, quadratic
warm-up, flat then cosine from 72 % of the steps, EMA of the weights, run by the shared epoch
loop :func:`~bopsurg.models.training.fit`. Validation decodes poses with test-time crops around
the GT visible boxes and reports the median RE / TE / MSSD with bopsurg's own metrics.
"""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bopsurg import metrics
from bopsurg.bop.dataset import BopDataset
from bopsurg.errors import BopsurgError
from bopsurg.geometry import rotation_about_axis
from bopsurg.mirror import PlaneReflection, object_reflection
from bopsurg.models import training
from bopsurg.models.data import (
    SCENE_ID_STRIDE,
    BatchReader,
    PoseBatch,
    PoseSet,
    load_pose_set,
)
from bopsurg.models.detector.augment import hsv_jitter
from bopsurg.models.mirror import mirror_batch
from bopsurg.models.photometric import PhotometricConfig, augment_batch, batch_seeds
from bopsurg.models.pose.config import TRAINING_ONLY, PoseConfig
from bopsurg.models.pose.decode import pose_from_output
from bopsurg.models.pose.encodings import SiteRoi, ego_to_allo, rot6d_from_matrix, site_encode
from bopsurg.models.pose.losses import gdr_losses
from bopsurg.models.pose.network import GdrPoseNet
from bopsurg.models.pose.roi import crop, dzi_boxes, roi_coord_2d
from bopsurg.models.pose.targets import XyzNormaliser, farthest_point_sampling, xyz_to_region
from bopsurg.models.roll import roll_batch
from bopsurg.models.run_config import LoaderConfig, resolved, write_config

log = logging.getLogger(__name__)

#: Model points for the point-matching loss (GDR-Net uses 3000).
PM_POINTS = 3000


@dataclass(frozen=True)
class PoseRecipe:
    """Training hyper-parameters (recorded in the checkpoint)."""

    epochs: int = 40
    batch_size: int = 32
    lr: float = 1e-3
    weight_decay: float = 1e-2
    warmup_epochs: float = 1.0
    anneal_from: float = 0.72
    min_visib: float = 0.1
    hsv: tuple[float, float, float] = (0.015, 0.5, 0.4)
    #: Share of the samples whose hue turns by any amount (the whole colour circle) instead
    #: of ``hsv[0]``: tissue of other colours without losing how ours looks.
    hue_whole: float = 0.0
    val_every: int = 5
    symmetric: bool = False
    augment: PhotometricConfig = field(default_factory=PhotometricConfig)
    #: Share of the samples shown mirrored (:func:`bopsurg.models.mirror.mirror_batch`: the
    #: needle's other face, exactly); 0 draws nothing, so older recipes train as before.
    mirror: float = 0.0
    #: The splits (names of a comma-separated ``--split``) whose samples may be mirrored;
    #: empty = all. Mirroring only the splits that carry a cue to the face (a suture thread
    #: at the tail: ``--domain wide``) keeps what the others teach about their usual face.
    mirror_splits: tuple[str, ...] = ()
    #: Share of the samples seen by a camera turned about its optical axis
    #: (:func:`bopsurg.models.roll.roll_batch`: the needle in other image orientations,
    #: exactly), by an angle uniform in ±``roll_deg``; 0 draws nothing, so older recipes train
    #: as before.
    roll: float = 0.0
    roll_deg: float = 180.0
    #: Exported checkpoint (``NAME.pt``, same kind and config) the network starts from, to
    #: fine-tune it on new data; "" = random initialisation.
    init: str = ""
    #: ``fp32``, or ``bf16``: steps under ``torch.autocast`` in bfloat16 (a GPU's fast path;
    #: :attr:`~bopsurg.models.training.Schedule.precision`).
    precision: str = "fp32"
    #: Steps per epoch; 0: one pass over the training samples. More than a pass draws
    #: from consecutive shuffles (a small split trained for a fixed number of steps).
    steps_per_epoch: int = 0

    def __post_init__(self) -> None:
        if self.steps_per_epoch < 0:
            raise ValueError(f"steps_per_epoch must be >= 0, got {self.steps_per_epoch}")
        if self.precision not in training.PRECISIONS:
            raise ValueError(f"precision must be fp32 or bf16, got {self.precision!r}")
        for name in ("mirror", "hue_whole", "roll"):
            share = getattr(self, name)
            if not 0.0 <= share <= 1.0:
                raise ValueError(f"{name} is a share of the samples, in [0, 1], got {share}")
        if not 0.0 <= self.roll_deg <= 180.0:
            raise ValueError(f"roll_deg is the largest turn, in [0, 180] deg, got {self.roll_deg}")

    def schedule(self) -> training.Schedule:
        """What the epoch loop reads; the cosine starts at ``anneal_from`` (GDR-Net)."""
        return training.Schedule(
            self.epochs, self.batch_size, self.lr, self.weight_decay, self.warmup_epochs,
            self.anneal_from, self.val_every, self.steps_per_epoch, self.precision,
        )  # fmt: skip


@dataclass(frozen=True)
class ObjectGeometry:
    """What the pose head needs to know about its object (all mm, model frame)."""

    obj_id: int
    normaliser: XyzNormaliser
    fps: torch.Tensor  # (R, 3) region centres
    points: torch.Tensor  # (P, 3) PM-loss points
    sym_rotations: torch.Tensor | None  # (S, 3, 3)
    diameter: float

    def to_meta(self) -> dict[str, Any]:
        """The JSON part the estimator needs at test time."""
        return {
            "obj_id": self.obj_id,
            "xyz_centre": self.normaliser.centre.tolist(),
            "xyz_scale": float(self.normaliser.scale),
            "fps": self.fps.tolist(),
            "diameter": self.diameter,
            "symmetries": None if self.sym_rotations is None else self.sym_rotations.tolist(),
        }


def needle_symmetry(info: dict[str, Any]) -> torch.Tensor:
    """The proper 2-fold symmetry of a circular-arc needle (tip and tail swapped): 180 deg
    about the in-plane axis through the circle centre (model origin) and the arc midpoint,
    from ``models_info`` keypoints ``tip``/``tail`` and ``plane_normal``."""
    kp = info.get("keypoints") or {}
    if "tip" not in kp or "tail" not in kp:
        raise ValueError("models_info has no tip/tail keypoints to derive the needle symmetry")
    tip, tail = (np.asarray(kp[k], float) for k in ("tip", "tail"))
    axis = tip / np.linalg.norm(tip) + tail / np.linalg.norm(tail)
    return torch.tensor(rotation_about_axis(axis, np.pi)[None], dtype=torch.float32)


def object_geometry(
    dataset: BopDataset, obj_id: int, cfg: PoseConfig, symmetric: bool
) -> ObjectGeometry:
    """Normaliser, FPS regions, PM points and symmetries of ``obj_id`` from the dataset."""
    model = dataset.model(obj_id)
    info = dataset.models_info.get(obj_id, {})
    v = torch.from_numpy(model.pts).float()
    gen = torch.Generator().manual_seed(obj_id)
    idx = torch.randperm(len(v), generator=gen)[:PM_POINTS]
    syms = None
    if symmetric:
        table = metrics.symmetry_transforms(info, max_sym_disc_step=0.01)
        R_s = torch.tensor(np.asarray(table[0]), dtype=torch.float32)
        R_s = R_s[1:] if len(R_s) > 1 else needle_symmetry(info)  # drop the identity
        syms = R_s
    return ObjectGeometry(
        obj_id,
        XyzNormaliser.from_vertices(v),
        farthest_point_sampling(v, cfg.num_regions),
        v[idx],
        syms,
        float(info.get("diameter", float(torch.cdist(v, v).max()))),
    )


def roi_batch(
    data: PoseBatch,
    cfg: PoseConfig,
    geo: ObjectGeometry,
    device: torch.device,
    gen: torch.Generator | None,
    hsv: tuple[float, float, float] = (0.015, 0.5, 0.4),
    augment: PhotometricConfig | None = None,
    seeds: list[int] | None = None,
    hue_whole: float = 0.0,
) -> tuple[torch.Tensor, torch.Tensor, dict[str, torch.Tensor]]:
    """Network inputs and loss targets of a batch of instances; train-time jitter when
    ``gen`` is given (DZI; HSV colour, amplitudes ``hsv``, the whole hue circle for a share
    ``hue_whole``; then the photometric ``augment`` seeded per sample by ``seeds``),
    test-time crops when None."""
    H, W = (int(v) for v in data.image_hw[0])
    box = data.bbox.to(device)
    box_xywh = torch.cat([box[:, :2] - 0.5, box[:, 2:]], dim=1)  # pixel-centre convention
    centre, side = dzi_boxes(box_xywh, gen, cfg, (H, W))
    a, c0 = data.ctx[:, 0].to(device), data.ctx[:, 1:].to(device)
    C = data.rgb.shape[-1]
    c_centre, c_side = (centre - c0) * a[:, None] + C / 2, side * a  # in the context crop
    rgb = data.rgb.to(device, non_blocking=True).float() / 255
    roi_img = crop(rgb, c_centre, c_side, cfg.roi_in, "bilinear")
    if gen is not None:
        roi_img = hsv_jitter(roi_img, gen, *hsv, whole=hue_whole)
        if augment is not None and seeds is not None:
            roi_img = augment_batch(roi_img, augment, seeds)
    mask_full = data.mask[:, None].to(device, non_blocking=True).float()
    mask = crop(mask_full, c_centre, c_side, cfg.roi_out, "nearest")
    soft = None  # the covered fraction of each map cell (4×4 nearest samples), for BCE only
    if cfg.mask_loss == "bce":
        soft = crop(mask_full, c_centre, c_side, 4 * cfg.roi_out, "nearest")
        soft = torch.nn.functional.avg_pool2d(soft, 4)
    xyz = data.xyz.to(device, non_blocking=True).float()
    xyz = crop(xyz, c_centre, c_side, cfg.roi_out, "nearest")
    fg = mask[:, 0] > 0.5
    xyz_hw = xyz.permute(0, 2, 3, 1)
    region = xyz_to_region(xyz_hw, fg, geo.fps.to(device))
    xyz_n = geo.normaliser.normalise(xyz_hw).permute(0, 3, 1, 2) * fg[:, None]
    K, R, t = data.K.to(device), data.R.to(device), data.t.to(device)
    wh = box_xywh[:, 2:]
    coord2d = roi_coord_2d(centre, side, cfg.roi_out, (H, W))
    target = {
        "mask_visib": fg[:, None].float(),
        "xyz": xyz_n,
        "region": region,
        "R": R,
        "t": t,
        "site": site_encode(t, SiteRoi(K, centre, wh, side, cfg.roi_out, cfg.z_unit_mm)),
        "rot6d_allo": rot6d_from_matrix(ego_to_allo(R, t)),
        "K": K,
        "centre": centre,
        "wh": wh,
        "side": side,
    }
    if soft is not None:
        target["mask_soft"] = soft
    return roi_img, coord2d, target


@torch.no_grad()
def validate(
    model: torch.nn.Module,
    data: PoseSet,
    cfg: PoseConfig,
    geo: ObjectGeometry,
    device: torch.device,
) -> dict[str, float]:
    """Median RE (deg), TE (mm), MSSD (mm) on test-time crops around the GT visible boxes."""
    if len(data) == 0:
        return {}
    model.eval()
    R_all, t_all = [], []
    for batch in BatchReader(data, data.collate).all(64):
        roi_img, coord2d, tg = roi_batch(batch, cfg, geo, device, None)
        out = model(roi_img, coord2d)
        R, t = pose_from_output(out, tg["K"], tg["centre"], tg["wh"], tg["side"], cfg)
        R_all.append(R.double().cpu())
        t_all.append(t.double().cpu())
    R_e, t_e = torch.cat(R_all).numpy(), torch.cat(t_all).numpy()
    R_g, t_g = data.R.double().numpy(), data.t.double().numpy()
    pts = geo.points.double().numpy()
    syms = None
    if geo.sym_rotations is not None:
        S = geo.sym_rotations.double().numpy()
        syms = (np.concatenate([np.eye(3)[None], S]), np.zeros((len(S) + 1, 3)))
    return {
        "re_median": float(np.median(metrics.re(R_e, R_g))),
        "te_median": float(np.median(metrics.te(t_e, t_g))),
        "mssd_median": float(np.median(metrics.mssd(R_e, t_e, R_g, t_g, pts, syms))),
    }


def train_pose(
    dataset: str | Path,
    out: str | Path,
    *,
    split: str = "train",
    val_split: str | None = None,
    obj_id: int | None = None,
    preset: str = "cpu",
    recipe: PoseRecipe | None = None,
    seed: int = 0,
    device: str = "auto",
    restart: bool = False,
    progress: bool = True,
    max_instances: int | None = None,
    config: PoseConfig | None = None,
    loader: LoaderConfig | None = None,
) -> Path:
    """Train (or resume) a pose-head run in ``out``; returns the exported ``pose.pt``.

    Args:
        dataset: BOP dataset root.
        out: Run folder (created; resumed when it holds a run with the same settings).
        split: Training split.
        val_split: Validation split; None = hold out one scene in 10 of ``split`` (seeded).
        obj_id: Object to train for; None = the dataset's first object.
        preset: :meth:`PoseConfig.preset` name (``cpu``, ``paper``, ``test``).
        recipe: Hyper-parameters (default :class:`PoseRecipe`).
        seed: Seed of every random choice.
        device: ``auto``, ``cpu``, ``cuda`` ...
        restart: Discard a previous run in ``out``.
        progress: Show progress bars.
        max_instances: Use only the first N training instances (smoke tests).
        config: The network's config (default: the preset's); ``recipe.symmetric`` or
            ``config.symmetric`` sets both.
        loader: How instances are read (workers, cache); does not change the result.
    """
    recipe, loader = recipe or PoseRecipe(), loader or LoaderConfig()
    dev = training.resolve_device(device)
    preset_cfg = PoseConfig.preset(preset)
    cfg = preset_cfg if config is None else config
    if recipe.symmetric or cfg.symmetric:
        cfg, recipe = replace(cfg, symmetric=True), replace(recipe, symmetric=True)
    splits = training.open_splits(dataset, split, val_split)
    ds = splits.train
    obj_id = ds.obj_ids[0] if obj_id is None else obj_id
    settings = training.RunSettings(
        "pose", str(Path(dataset).resolve()), split, preset, seed, asdict(recipe),
        {"val_split": val_split, "obj_id": obj_id, "max_instances": max_instances},
        cfg.to_dict(),
    )  # fmt: skip
    legacy_cfg = replace(preset_cfg, symmetric=cfg.symmetric)  # runs before config files
    legacy = {"model": legacy_cfg.to_dict(), "recipe": LEGACY_RECIPE}
    run, state = training.open_run(out, settings, restart=restart, legacy=legacy)
    weights = Path(out) / "pose.pt"
    if training.finished(run, state, weights):
        return weights
    write_config(out, resolved("pose", preset, seed, cfg, recipe, loader))
    geo = object_geometry(ds, obj_id, cfg, recipe.symmetric)
    train, val = (
        load_pose_set(
            split_ds, ids, obj_id, min_visib=min_visib,
            cache_mb=loader.cache_mb, cache_items=loader.cache_items, shared=loader.shared_cache,
        )
        for split_ds, ids, min_visib in (
            (ds, splits.train_ids, recipe.min_visib), (splits.val, splits.val_ids, 0.3)
        )
    )  # fmt: skip
    if max_instances is not None:
        train = train.head(max_instances)
    log.info("pose: %d train instances, %d validation instances", len(train), len(val))
    model = _network(cfg, recipe.init if state is None else "", geo).to(dev)
    export = training.Export(weights, "pose", cfg.to_dict(), geo.to_meta())
    step = _step_fn(model, cfg, geo, recipe, dev, seed, *_mirror(train, ds, obj_id, recipe))
    path: Path = training.fit(
        model, run, state, recipe.schedule(), n_train=len(train), step=step,
        validate=lambda ema: validate(ema, val, cfg, geo, dev), export=export,
        device=dev, progress=progress,
        load=BatchReader(
            train, train.collate, loader.num_workers, dev.type == "cuda", device=dev
        ),
    )  # fmt: skip
    return path


#: Recipe settings that runs written by an older bopsurg lack, at the value they had then.
LEGACY_RECIPE = {
    "augment": asdict(PhotometricConfig()),
    "precision": "fp32",
    "steps_per_epoch": 0,
    "init": "",
    "mirror": 0.0,
    "mirror_splits": [],
    "hue_whole": 0.0,
    "roll": 0.0,
    "roll_deg": 180.0,
}


def _network(cfg: PoseConfig, init: str, geo: ObjectGeometry) -> GdrPoseNet:
    """A fresh pose head (seeded by the caller), or, with ``init``, that checkpoint's."""
    model = GdrPoseNet(cfg)
    if init:
        training.init_weights(model, init, "pose", cfg.to_dict(), geo.to_meta(), TRAINING_ONLY)
    return model


def _mirror(
    train: PoseSet, ds: BopDataset, obj_id: int, recipe: PoseRecipe
) -> tuple[torch.Tensor | None, PlaneReflection | None]:
    """Which samples may be mirrored (:func:`_mirrorable`) and the object's reflection (its
    symmetry through its plane, from its mesh, checked: what a mirror shows; None without
    ``recipe.mirror``)."""
    reflection = object_reflection(ds, obj_id) if recipe.mirror > 0 else None
    return _mirrorable(train, ds, recipe.mirror_splits), reflection


def _mirrorable(
    train: PoseSet, dataset: BopDataset, splits: tuple[str, ...]
) -> torch.Tensor | None:
    """(N,) bool: which training samples lie in ``splits`` (None: every split may mirror).

    Raises:
        BopsurgError: A split in ``splits`` is not one of the training splits.
    """
    if not splits:
        return None
    names = dataset.split.split(",")  # the k-th split's scenes are k * SCENE_ID_STRIDE + s
    unknown = sorted(set(splits) - set(names))
    if unknown:
        raise BopsurgError(
            f"recipe.mirror_splits: {', '.join(unknown)} not among the training splits "
            f"({dataset.split})"
        )
    k = np.array([r.scene_id // SCENE_ID_STRIDE for r in train.records], dtype=np.int64)
    chosen = np.array([n in splits for n in names])
    return torch.from_numpy(chosen[k])


def _step_fn(
    model: GdrPoseNet,
    cfg: PoseConfig,
    geo: ObjectGeometry,
    recipe: PoseRecipe,
    dev: torch.device,
    seed: int,
    mirrorable: torch.Tensor | None = None,
    reflection: PlaneReflection | None = None,
) -> training.StepFn:
    """The pose head's training step: jittered ROIs of a batch, the GDR-Net losses."""
    points = geo.points.to(dev)
    syms = None if geo.sym_rotations is None else geo.sym_rotations.to(dev)

    def step(batch: PoseBatch, gen: torch.Generator, epoch: int) -> dict[str, torch.Tensor]:
        if recipe.mirror > 0:  # drawn from the run's generator: resumable and deterministic
            u = torch.rand(len(batch.idx), generator=gen, device=gen.device)
            flip = (u < recipe.mirror).cpu()
            if mirrorable is not None:
                flip &= mirrorable[batch.idx]
            assert reflection is not None  # made by train_pose whenever recipe.mirror > 0
            batch = mirror_batch(batch, flip, reflection)
        if recipe.roll > 0:  # after the mirror: both are exact, so either order is
            u, v = torch.rand(2, len(batch.idx), generator=gen, device=gen.device).cpu()
            turn = torch.where(u < recipe.roll, (2 * v - 1) * math.radians(recipe.roll_deg), 0.0)
            batch = roll_batch(batch, turn)
        seeds = batch_seeds(seed, epoch, batch.idx)
        roi_img, coord2d, target = roi_batch(
            batch, cfg, geo, dev, gen, recipe.hsv, recipe.augment, seeds, recipe.hue_whole
        )
        out = {k: v.float() for k, v in model(roi_img, coord2d).items()}  # losses in fp32
        losses: dict[str, torch.Tensor] = gdr_losses(out, target, points, cfg, syms)
        return losses

    return step

"""Per-scene annotation files: ``scene_camera.json``, ``scene_gt.json``, ``scene_gt_info.json``.

Each file maps an image id (written as a string key, ``"0"``, ``"12"``) to the entries of that
image. Poses map model to camera (``x_cam = R @ x_model + t``); ``R`` is stored as 9 floats
row-major, ``t`` as 3 floats in mm; ``cam_K`` as 9 floats row-major in px; depth in mm is the
stored depth value times ``depth_scale``. The ``gt_id`` of an instance is its index in the
image's list in ``scene_gt.json``, and ``scene_gt_info.json`` lists the instances in the same
order.

Loaders check types, shapes and finiteness and raise :class:`~bopsurg.errors.DatasetError`
naming the file and the field (``"12/cam_K"``, ``"12/0/cam_R_m2c"`` = image 12, gt_id 0). They
accept everything the reference ``bop_toolkit_lib.inout`` accepts, in particular rotations that
are not exactly orthonormal (:func:`~bopsurg.bop.check.check_dataset` reports those). Savers
write the reference layout via :func:`~bopsurg.bop.jsonio.save_json`.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from bopsurg.bop._validate import (
    Issues,
    get_dict,
    get_float,
    get_floats,
    get_int,
    get_list,
    id_key,
    trusted,
)
from bopsurg.bop.jsonio import load_json, save_json
from bopsurg.errors import ShapeError

F64 = NDArray[np.float64]

#: Keys of a scene_camera.json entry that :class:`CameraInfo` holds in named fields.
CAMERA_KEYS = ("cam_K", "depth_scale", "cam_R_w2c", "cam_t_w2c")
#: Keys of a scene_gt.json entry that :class:`GtPose` holds in named fields.
GT_KEYS = ("obj_id", "cam_R_m2c", "cam_t_m2c")
#: Keys of a scene_gt_info.json entry (all required).
GT_INFO_KEYS = (
    "bbox_obj",
    "bbox_visib",
    "px_count_all",
    "px_count_valid",
    "px_count_visib",
    "visib_fract",
)


def _matrix(value: ArrayLike, shape: tuple[int, ...], name: str) -> F64:
    """``value`` as a finite float64 array of ``shape``; the flat form (9 for 3x3) and (3, 1)
    for (3,) are accepted too."""
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ShapeError(f"expected numbers of shape {shape}", field=name) from None
    size = int(np.prod(shape))
    if a.shape not in (shape, (size,), (size, 1)):
        raise ShapeError(f"expected shape {shape}, got {a.shape}", field=name)
    a = a.reshape(shape)
    if not np.all(np.isfinite(a)):
        raise ShapeError("contains NaN or inf", field=name)
    return a


def _same(a: Any, b: Any) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return bool(np.array_equal(a, b))


@dataclass(frozen=True, eq=False)
class CameraInfo:
    """The camera of one image (a ``scene_camera.json`` entry).

    Attributes:
        K: (3, 3) float64 intrinsic matrix, px.
        depth_scale: Depth in mm = stored depth value × ``depth_scale``; None if absent.
        R_w2c: (3, 3) float64 world-to-camera rotation, or None.
        t_w2c: (3,) float64 world-to-camera translation in mm, or None.
        extra: Other keys of the entry (``view_level``, ``elev``, ``mode``, BOP24
            ``cam_model`` ...), kept as loaded and written back unchanged.
    """

    K: F64
    depth_scale: float | None = None
    R_w2c: F64 | None = None
    t_w2c: F64 | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "K", _matrix(self.K, (3, 3), "K"))
        if self.depth_scale is not None:
            object.__setattr__(self, "depth_scale", float(self.depth_scale))
        if self.R_w2c is not None:
            object.__setattr__(self, "R_w2c", _matrix(self.R_w2c, (3, 3), "R_w2c"))
        if self.t_w2c is not None:
            object.__setattr__(self, "t_w2c", _matrix(self.t_w2c, (3,), "t_w2c"))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, CameraInfo):
            return NotImplemented
        return (
            _same(self.K, other.K)
            and self.depth_scale == other.depth_scale
            and _same(self.R_w2c, other.R_w2c)
            and _same(self.t_w2c, other.t_w2c)
            and self.extra == other.extra
        )

    __hash__ = None  # type: ignore[assignment]  # holds arrays


@dataclass(frozen=True, eq=False)
class GtPose:
    """One ground-truth instance (a ``scene_gt.json`` entry).

    Attributes:
        obj_id: Object id (the model ``obj_{obj_id:06d}.ply``).
        R: (3, 3) float64 model-to-camera rotation.
        t: (3,) float64 model-to-camera translation, mm. Placeholders for fully occluded
            instances may have ``t = (-1, -1, -1)``.
        extra: Other keys of the entry, written back unchanged.
    """

    obj_id: int
    R: F64
    t: F64
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "obj_id", int(self.obj_id))
        object.__setattr__(self, "R", _matrix(self.R, (3, 3), "R"))
        object.__setattr__(self, "t", _matrix(self.t, (3,), "t"))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, GtPose):
            return NotImplemented
        return (
            self.obj_id == other.obj_id
            and _same(self.R, other.R)
            and _same(self.t, other.t)
            and self.extra == other.extra
        )

    __hash__ = None  # type: ignore[assignment]  # holds arrays


Box = tuple[int, int, int, int]

#: The box of an instance with nothing visible.
EMPTY_BBOX: Box = (-1, -1, -1, -1)


def _bbox(value: Sequence[int], name: str) -> Box:
    box = [int(v) for v in value]
    if len(box) != 4:
        raise ShapeError(f"expected 4 integers (x, y, w, h), got {len(box)}", field=name)
    return (box[0], box[1], box[2], box[3])


def bbox_from_mask(mask: ArrayLike, offset: tuple[int, int] = (0, 0)) -> Box:
    """BOP bounding box ``(x, y, w, h)`` px of the nonzero pixels, ``w = x_max − x_min``.

    Args:
        mask: (H, W) mask.
        offset: (x, y) subtracted from pixel coordinates (e.g. for a canvas larger than the
            image).

    Returns:
        The box, or :data:`EMPTY_BBOX` for an empty mask.
    """
    m = np.asarray(mask, dtype=bool)
    rows = np.flatnonzero(m.any(axis=1))
    if rows.size == 0:
        return EMPTY_BBOX
    cols = np.flatnonzero(m.any(axis=0))
    x0, x1 = int(cols[0]) - offset[0], int(cols[-1]) - offset[0]
    y0, y1 = int(rows[0]) - offset[1], int(rows[-1]) - offset[1]
    return (x0, y0, x1 - x0, y1 - y0)


@dataclass(frozen=True)
class GtInfo:
    """Visibility meta data of one ground-truth instance (a ``scene_gt_info.json`` entry).

    Attributes:
        bbox_obj: (x, y, w, h) px of the full (amodal) silhouette, may extend beyond the
            image; ``w = x_max - x_min`` (no +1). ``(-1, -1, -1, -1)`` when not visible.
        bbox_visib: (x, y, w, h) px of the visible mask, ``(-1, -1, -1, -1)`` when empty.
        px_count_all: Pixels of the full silhouette, including the part outside the image.
        px_count_valid: Silhouette pixels inside the image with a depth measurement.
        px_count_visib: Pixels of the visible mask.
        visib_fract: ``px_count_visib / px_count_all`` (0 when ``px_count_all == 0``).
        extra: Other keys of the entry, written back unchanged.
    """

    bbox_obj: tuple[int, int, int, int]
    bbox_visib: tuple[int, int, int, int]
    px_count_all: int
    px_count_valid: int
    px_count_visib: int
    visib_fract: float
    extra: dict[str, Any] = field(default_factory=dict, hash=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "bbox_obj", _bbox(self.bbox_obj, "bbox_obj"))
        object.__setattr__(self, "bbox_visib", _bbox(self.bbox_visib, "bbox_visib"))
        for name in ("px_count_all", "px_count_valid", "px_count_visib"):
            object.__setattr__(self, name, int(getattr(self, name)))
        object.__setattr__(self, "visib_fract", float(self.visib_fract))


# --------------------------------------------------------------------------- parsing


def _top_level(content: Any, issues: Issues, what: str) -> list[tuple[int, Any]]:
    """The (image id, value) pairs of a scene file, sorted by id; bad keys reported."""
    top = get_dict(content, None, issues, f"a mapping from image id to {what}")
    if top is None:
        return []
    out = []
    for key, value in top.items():
        im_id = id_key(key, str(key), issues)
        if im_id is not None:
            out.append((im_id, value))
    return sorted(out, key=lambda kv: kv[0])


def parse_camera_entry(entry: Any, where: str, issues: Issues) -> CameraInfo | None:
    """One ``scene_camera.json`` entry (``where`` = image id, for messages)."""
    d = get_dict(entry, where, issues, "camera parameters")
    if d is None:
        return None
    n_before = len(issues)
    extra = {k: copy.deepcopy(v) for k, v in d.items() if k not in CAMERA_KEYS}
    K = None
    if "cam_K" in d:
        if "cam_model" in d:
            issues("only one of cam_K and cam_model may be given", f"{where}/cam_K")
        K = get_floats(d["cam_K"], 9, f"{where}/cam_K", issues, what=" (3x3 row-major)")
    elif "cam_model" in d:
        # BOP24 H3 format: projection_params start with fx, fy, cx, cy; K is their pinhole
        # part (distortion stays in extra["cam_model"]).
        model = get_dict(d["cam_model"], f"{where}/cam_model", issues, "a camera model")
        params = None if model is None else model.get("projection_params")
        if isinstance(params, list) and len(params) >= 4:
            p = get_floats(params[:4], 4, f"{where}/cam_model/projection_params", issues)
            if p is not None:
                K = np.array([[p[0], 0.0, p[2]], [0.0, p[1], p[3]], [0.0, 0.0, 1.0]])
        elif model is not None:
            issues("expected at least 4 numbers (fx, fy, cx, cy)", f"{where}/cam_model")
    else:
        issues("missing (the 9 intrinsic values, row-major)", f"{where}/cam_K")
    depth_scale = None
    if "depth_scale" in d:
        depth_scale = get_float(d["depth_scale"], f"{where}/depth_scale", issues)
    R = t = None
    if "cam_R_w2c" in d:
        R = get_floats(d["cam_R_w2c"], 9, f"{where}/cam_R_w2c", issues, what=" (row-major)")
    if "cam_t_w2c" in d:
        t = get_floats(d["cam_t_w2c"], 3, f"{where}/cam_t_w2c", issues, what=" (mm)")
    if len(issues) > n_before or K is None:
        return None
    return CameraInfo(K=K, depth_scale=depth_scale, R_w2c=R, t_w2c=t, extra=extra)


def parse_scene_camera(content: Any, issues: Issues) -> dict[int, CameraInfo | None]:
    """Validate decoded ``scene_camera.json`` content; bad entries are None (collect mode)."""
    return {
        im_id: parse_camera_entry(entry, str(im_id), issues)
        for im_id, entry in _top_level(content, issues, "camera parameters")
    }


def parse_gt_entry(entry: Any, where: str, issues: Issues) -> GtPose | None:
    """One ``scene_gt.json`` instance (``where`` = ``"im_id/gt_id"``)."""
    d = get_dict(entry, where, issues, "a GT instance")
    if d is None:
        return None
    n_before = len(issues)
    obj_id = R = t = None
    for key in GT_KEYS:
        if key not in d:
            issues("missing", f"{where}/{key}")
    if "obj_id" in d:
        obj_id = get_int(d["obj_id"], f"{where}/obj_id", issues, minimum=0)
    if "cam_R_m2c" in d:
        R = get_floats(d["cam_R_m2c"], 9, f"{where}/cam_R_m2c", issues, what=" (row-major)")
    if "cam_t_m2c" in d:
        t = get_floats(d["cam_t_m2c"], 3, f"{where}/cam_t_m2c", issues, what=" (mm)")
    if len(issues) > n_before or obj_id is None or R is None or t is None:
        return None
    extra = {k: copy.deepcopy(v) for k, v in d.items() if k not in GT_KEYS}
    return trusted(GtPose, obj_id=obj_id, R=R.reshape(3, 3), t=t, extra=extra)


def parse_scene_gt(content: Any, issues: Issues) -> dict[int, list[GtPose | None]]:
    """Validate decoded ``scene_gt.json`` content; bad instances are None (collect mode)."""
    out: dict[int, list[GtPose | None]] = {}
    for im_id, value in _top_level(content, issues, "lists of GT instances"):
        items = get_list(value, str(im_id), issues, "a list of GT instances")
        if items is not None:
            out[im_id] = [parse_gt_entry(e, f"{im_id}/{i}", issues) for i, e in enumerate(items)]
    return out


def _get_bbox(value: Any, field_: str, issues: Issues) -> tuple[int, int, int, int] | None:
    if not isinstance(value, list) or len(value) != 4:
        got = f"{len(value)} values" if isinstance(value, list) else repr(value)[:40]
        issues(f"expected 4 integers (x, y, w, h), got {got}", field_)
        return None
    vals = [get_int(v, field_, issues) for v in value]
    if any(v is None for v in vals):
        return None
    return tuple(vals)  # type: ignore[return-value]


def parse_gt_info_entry(entry: Any, where: str, issues: Issues) -> GtInfo | None:
    """One ``scene_gt_info.json`` instance (``where`` = ``"im_id/gt_id"``)."""
    d = get_dict(entry, where, issues, "GT meta information")
    if d is None:
        return None
    n_before = len(issues)
    for key in GT_INFO_KEYS:
        if key not in d:
            issues("missing", f"{where}/{key}")
    if len(issues) > n_before:
        return None
    bbox_obj = _get_bbox(d["bbox_obj"], f"{where}/bbox_obj", issues)
    bbox_visib = _get_bbox(d["bbox_visib"], f"{where}/bbox_visib", issues)
    counts = [
        get_int(d[k], f"{where}/{k}", issues, minimum=0)
        for k in ("px_count_all", "px_count_valid", "px_count_visib")
    ]
    visib_fract = get_float(d["visib_fract"], f"{where}/visib_fract", issues)
    if len(issues) > n_before:
        return None
    extra = {k: copy.deepcopy(v) for k, v in d.items() if k not in GT_INFO_KEYS}
    return trusted(
        GtInfo,
        bbox_obj=bbox_obj,
        bbox_visib=bbox_visib,
        px_count_all=counts[0],
        px_count_valid=counts[1],
        px_count_visib=counts[2],
        visib_fract=visib_fract,
        extra=extra,
    )


def parse_scene_gt_info(content: Any, issues: Issues) -> dict[int, list[GtInfo | None]]:
    """Validate decoded ``scene_gt_info.json`` content; bad instances are None (collect mode)."""
    out: dict[int, list[GtInfo | None]] = {}
    for im_id, value in _top_level(content, issues, "lists of GT meta information"):
        items = get_list(value, str(im_id), issues, "a list of GT meta information")
        if items is not None:
            out[im_id] = [
                parse_gt_info_entry(e, f"{im_id}/{i}", issues) for i, e in enumerate(items)
            ]
    return out


# --------------------------------------------------------------------------- load / save


def load_scene_camera(path: str | Path) -> dict[int, CameraInfo]:
    """Load ``scene_camera.json``.

    Args:
        path: The file.

    Returns:
        Image id → camera, sorted by image id.

    Raises:
        DatasetError: Missing or malformed file, or an entry with a missing/ill-shaped or
            non-finite field (``field`` names it, e.g. ``"12/cam_K"``).
    """
    cams = parse_scene_camera(load_json(path, keys_to_int=True), Issues(path))
    return {k: v for k, v in cams.items() if v is not None}


def load_scene_gt(path: str | Path) -> dict[int, list[GtPose]]:
    """Load ``scene_gt.json``.

    Args:
        path: The file.

    Returns:
        Image id → GT instances in gt_id order, sorted by image id.

    Raises:
        DatasetError: Missing or malformed file or entry (``field`` e.g. ``"12/0/cam_R_m2c"``).
    """
    gts = parse_scene_gt(load_json(path, keys_to_int=True), Issues(path))
    return {k: [g for g in v if g is not None] for k, v in gts.items()}


def load_scene_gt_info(path: str | Path) -> dict[int, list[GtInfo]]:
    """Load ``scene_gt_info.json``.

    Args:
        path: The file.

    Returns:
        Image id → meta information of the GT instances in gt_id order.

    Raises:
        DatasetError: Missing or malformed file or entry (``field`` e.g. ``"3/1/visib_fract"``).
    """
    infos = parse_scene_gt_info(load_json(path, keys_to_int=True), Issues(path))
    return {k: [g for g in v if g is not None] for k, v in infos.items()}


def camera_to_json(cam: CameraInfo) -> dict[str, Any]:
    """The ``scene_camera.json`` entry of ``cam`` (flat lists, as the reference writes)."""
    entry: dict[str, Any] = copy.deepcopy(cam.extra)
    # A BOP24 camera (cam_model) must not also get cam_K: the reference rejects both.
    if "cam_model" not in entry:
        entry["cam_K"] = cam.K.flatten().tolist()
    if cam.depth_scale is not None:
        entry["depth_scale"] = float(cam.depth_scale)
    if cam.R_w2c is not None:
        entry["cam_R_w2c"] = cam.R_w2c.flatten().tolist()
    if cam.t_w2c is not None:
        entry["cam_t_w2c"] = cam.t_w2c.flatten().tolist()
    return entry


def gt_to_json(gt: GtPose) -> dict[str, Any]:
    """The ``scene_gt.json`` entry of ``gt``."""
    entry: dict[str, Any] = copy.deepcopy(gt.extra)
    entry["obj_id"] = int(gt.obj_id)
    entry["cam_R_m2c"] = gt.R.flatten().tolist()
    entry["cam_t_m2c"] = gt.t.flatten().tolist()
    return entry


def gt_info_to_json(info: GtInfo) -> dict[str, Any]:
    """The ``scene_gt_info.json`` entry of ``info``."""
    entry: dict[str, Any] = copy.deepcopy(info.extra)
    entry.update(
        bbox_obj=[int(v) for v in info.bbox_obj],
        bbox_visib=[int(v) for v in info.bbox_visib],
        px_count_all=int(info.px_count_all),
        px_count_valid=int(info.px_count_valid),
        px_count_visib=int(info.px_count_visib),
        visib_fract=float(info.visib_fract),
    )
    return entry


def save_scene_camera(path: str | Path, cams: Mapping[int, CameraInfo]) -> None:
    """Write ``scene_camera.json`` in the reference layout (atomic).

    Args:
        path: Destination file.
        cams: Image id → camera.
    """
    save_json(path, {int(k): camera_to_json(v) for k, v in cams.items()})


def save_scene_gt(path: str | Path, gts: Mapping[int, Sequence[GtPose]]) -> None:
    """Write ``scene_gt.json`` in the reference layout (atomic).

    Args:
        path: Destination file.
        gts: Image id → GT instances in gt_id order.
    """
    save_json(path, {int(k): [gt_to_json(g) for g in v] for k, v in gts.items()})


def save_scene_gt_info(path: str | Path, infos: Mapping[int, Sequence[GtInfo]]) -> None:
    """Write ``scene_gt_info.json`` in the reference layout (atomic).

    Args:
        path: Destination file.
        infos: Image id → meta information in gt_id order.
    """
    save_json(path, {int(k): [gt_info_to_json(g) for g in v] for k, v in infos.items()})

"""Defaults of the standard BOP datasets, so their folders evaluate and check without flags.

The reference toolkit keeps these in a hard-coded table (``bop_toolkit_lib/dataset_params.py``)
and the evaluation scripts; here each dataset is one :class:`DatasetSpec`, looked up by the
dataset folder's name (``lmo``, ``tless`` ...) or by name (``--dataset NAME``). A folder
whose name is not registered keeps bopsurg's generic behaviour (its own ``camera.json``, the
size of its images, δ = 15 mm).

What a spec holds:

* the image size (width, height) px per split type and sensor stream: the MSPD threshold
  scale ``W / 640`` and the size ``bopsurg check`` expects;
* the split type used when the split is named without one (T-LESS and HB ``test`` →
  ``test_primesense``), and the dataset-level camera file (``camera_primesense.json``,
  ``camera_uw.json``, else ``camera.json``);
* VSD: whether the reference evaluates it (the BOP19 datasets; not the BOP24 industrial and
  HOT3D ones), δ (5 mm for ITODD, 15 mm otherwise) and τ (0.05 ... 0.5 × diameter);
* the sensor streams of multi-stream layouts (HOT3D, IPD, XYZ-IBD, ITODD-MV): per scene,
  ``scene_camera_{stream}.json``, ``scene_gt_{stream}.json``, ``scene_gt_info_{stream}.json``,
  ``mask_visib_{stream}/`` and the stream's image folders; the evaluated stream is the first
  of :attr:`DatasetSpec.streams` a scene has files of (HOT3D: ``rgb`` for Aria scenes,
  ``gray1`` for Quest 3 ones);
* the targets files the dataset ships (``test_targets_bop19.json`` for BOP19 localization,
  ``test_targets_bop24.json`` for BOP24 detection) and the estimates per image the BOP24
  evaluation keeps (100; 200 for XYZ-IBD).

Depth: every layout stores 16-bit depth images (ITODD: ``.tif``) with depth in mm = stored
value × the image's ``depth_scale`` in ``scene_camera*.json``, which differs between datasets
(e.g. 1.0 for LM-O, 0.1 for T-LESS and YCB-V): never assume one. HOT3D has no depth images.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

#: VSD misalignment tolerances τ, fractions of the object diameter (the reference's
#: ``np.arange(0.05, 0.51, 0.05)``, same floats).
VSD_TAUS: tuple[float, ...] = tuple(0.05 + 0.05 * k for k in range(10))
#: VSD visibility tolerance δ of every dataset but ITODD, mm.
VSD_DELTA_MM = 15.0
TARGETS_BOP19 = "test_targets_bop19.json"
TARGETS_BOP24 = "test_targets_bop24.json"
BOP19_AND_BOP24 = (TARGETS_BOP19, TARGETS_BOP24)

Size = tuple[int, int]


@dataclass(frozen=True)
class Stream:
    """One sensor stream of a multi-stream scene layout.

    Attributes:
        name: The suffix of its annotation files: ``scene_gt_{name}.json``,
            ``scene_camera_{name}.json``, ``scene_gt_info_{name}.json``, ``mask_{name}/``,
            ``mask_visib_{name}/``.
        images: Its image folders, tried in order (``rgb_photoneo``; HOT3D: ``rgb``).
        depth: Its depth folder, or None when the stream has no depth.
        size: Its image size (width, height), px.
    """

    name: str
    images: tuple[str, ...]
    depth: str | None
    size: Size


@dataclass(frozen=True)
class DatasetSpec:
    """Per-dataset defaults of a standard BOP dataset (see the module docs).

    Attributes:
        name: The dataset's short name, as its folder is called (``lmo``, ``tless``).
        title: Its full name.
        size: Image size (width, height) px of its test images.
        sizes: Sizes of other split types (``{"kinect": (1920, 1080)}``), or of one split's
            type (``{"train_primesense": (400, 400)}``, which comes first).
        split_types: The split type used for a split named without one (``{"test":
            "primesense"}``), applied when that folder exists.
        camera_files: The dataset-level camera file per split type (``None``: the default).
        vsd: Whether the reference evaluates VSD on it.
        vsd_delta_mm: VSD visibility tolerance δ, mm.
        vsd_taus: VSD misalignment tolerances τ, fractions of the diameter.
        streams: Evaluated sensor streams of a multi-stream layout, in preference order.
        targets: The targets files it ships (BOP19 and/or BOP24).
        max_estimates_per_image: Estimates per image the BOP24 evaluation keeps.
        gray: Its images are grey (``gray/`` folders).
    """

    name: str
    title: str
    size: Size
    sizes: Mapping[str, Size] = field(default_factory=dict)
    split_types: Mapping[str, str] = field(default_factory=dict)
    camera_files: Mapping[str | None, str] = field(default_factory=dict)
    vsd: bool = True
    vsd_delta_mm: float = VSD_DELTA_MM
    vsd_taus: tuple[float, ...] = VSD_TAUS
    streams: tuple[Stream, ...] = ()
    targets: tuple[str, ...] = BOP19_AND_BOP24
    max_estimates_per_image: int = 100
    gray: bool = False

    def split_type(self, split: str, split_type: str | None, root: Path) -> str | None:
        """The split type to use: ``split_type`` if given, else this dataset's default for
        ``split`` when the folder ``root/{split}_{type}`` exists (and ``root/split`` does
        not), else None."""
        if split_type is not None:
            return split_type
        default = self.split_types.get(split)
        if default and not (root / split).is_dir() and (root / f"{split}_{default}").is_dir():
            return default
        return None

    def image_size(
        self, split_type: str | None = None, stream: str | None = None, split: str = "test"
    ) -> Size:
        """Image size (width, height) px of a split, split type and stream (default: test's)."""
        for s in self.streams:
            if s.name == stream:
                return s.size
        if split_type is None:
            return self.size
        for key in (f"{split}_{split_type}", split_type):
            if key in self.sizes:
                return self.sizes[key]
        return self.size

    def camera_file(self, split_type: str | None = None) -> str:
        """The dataset-level camera file name for a split type."""
        return self.camera_files.get(split_type, self.camera_files.get(None, "camera.json"))

    def stream(self, name: str) -> Stream:
        """The stream called ``name``.

        Raises:
            KeyError: No such stream (the message lists them).
        """
        for s in self.streams:
            if s.name == name:
                return s
        raise KeyError(f"{self.name} has no stream {name!r}; streams: {self.stream_names}")

    @property
    def stream_names(self) -> list[str]:
        """Names of the streams, in preference order."""
        return [s.name for s in self.streams]


_VGA = (640, 480)
_DATASETS = (
    DatasetSpec("lm", "LineMOD", _VGA),
    DatasetSpec("lmo", "LineMOD-Occluded", _VGA),
    DatasetSpec(
        "tless", "T-LESS", (720, 540),
        sizes={"primesense": (720, 540), "kinect": (720, 540), "canon": (2560, 1920),
               "pbr": (720, 540), "train_render_reconst": (1280, 1024),
               "train_primesense": (400, 400), "train_kinect": (400, 400),
               "train_canon": (1900, 1900), "train_synthetless": (400, 400)},
        split_types={"test": "primesense", "train": "primesense"},
        camera_files={None: "camera_primesense.json", "primesense": "camera_primesense.json",
                      "kinect": "camera_kinect.json", "canon": "camera_canon.json"},
    ),
    DatasetSpec("tudl", "TU Dresden Light", _VGA, split_types={"train": "render"}),
    DatasetSpec("icbin", "IC-BIN (Doumanoglou et al.)", _VGA),
    DatasetSpec("itodd", "MVTec ITODD", (1280, 960), vsd_delta_mm=5.0, gray=True),
    DatasetSpec(
        "hb", "HomebrewedDB", _VGA, sizes={"kinect": (1920, 1080)},
        split_types={"test": "primesense", "val": "primesense"},
        camera_files={None: "camera_primesense.json", "primesense": "camera_primesense.json",
                      "kinect": "camera_kinect.json"},
    ),
    DatasetSpec(
        "ycbv", "YCB-Video", _VGA, split_types={"train": "real"},
        camera_files={None: "camera_uw.json", "synt": "camera_cmu.json"},
    ),
    DatasetSpec("hope", "HOPE", (1920, 1080)),
    DatasetSpec("hopev2", "HOPE v2 (BOP-H3)", (1920, 1080), targets=(TARGETS_BOP24,)),
    DatasetSpec("handal", "HANDAL (BOP-H3)", (1920, 1440), targets=(TARGETS_BOP24,)),
    DatasetSpec(
        "hot3d", "HOT3D (BOP-H3)", (1408, 1408), vsd=False, targets=(TARGETS_BOP24,),
        streams=(Stream("rgb", ("rgb",), None, (1408, 1408)),  # Aria
                 Stream("gray1", ("gray1",), None, (1280, 1024))),  # Quest 3
    ),
    DatasetSpec(
        "ipd", "Intel Industrial Plenoptic Dataset (BOP24)", (2064, 1544), vsd=False,
        sizes={"pbr": (2400, 2400)}, targets=(TARGETS_BOP24,),
        streams=(Stream("photoneo", ("rgb_photoneo",), "depth_photoneo", (2064, 1544)),),
    ),
    DatasetSpec(
        "xyzibd", "XYZ-IBD (BOP24)", (1440, 1080), vsd=False, targets=(TARGETS_BOP24,),
        max_estimates_per_image=200, gray=True,
        streams=(Stream("xyz", ("gray_xyz",), "depth_xyz", (1440, 1080)),),
    ),
    DatasetSpec(
        "itoddmv", "MVTec ITODD multi-view (BOP24)", (1280, 960), vsd=False, gray=True,
        targets=(TARGETS_BOP24,),
        streams=(Stream("3dlong", ("gray_3dlong",), "depth_3dlong", (1280, 960)),),
    ),
)  # fmt: skip

#: ``--dataset`` names that mean "not a standard dataset": generic behaviour.
CUSTOM = ("none", "custom")
#: The registry: dataset name → spec.
DATASETS: dict[str, DatasetSpec] = {d.name: d for d in _DATASETS}


def dataset_spec(name: str) -> DatasetSpec:
    """The spec of a registered dataset (name case-insensitive).

    Raises:
        KeyError: Not registered (the message lists the names).
    """
    try:
        return DATASETS[name.strip().lower()]
    except KeyError:
        raise KeyError(f"unknown BOP dataset {name!r}; known: {', '.join(DATASETS)}") from None


def recognise(root: str | Path, name: str | None = None) -> DatasetSpec | None:
    """The spec of a dataset folder: ``name`` if given (``--dataset``; ``none`` or ``custom``:
    None), else the one its folder name (case-insensitive) matches, else None (a custom
    dataset).

    Raises:
        KeyError: ``name`` is given but not registered.
    """
    if name:
        return None if name.strip().lower() in CUSTOM else dataset_spec(name)
    return DATASETS.get(Path(root).resolve().name.lower())

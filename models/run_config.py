"""A training run's full configuration: read from a YAML/JSON file, resolved, written back.

One file configures one run of ``bopsurg train detector|pose|seg|ends --config FILE``::

    preset: cpu          # the model preset the model section starts from
    seed: 0
    pose:                # PoseConfig fields (a detector run: 'detector:' with DetectorConfig's;
                         # 'seg:' SegConfig's, 'ends:' EndConfig's)
      z_unit_mm: 100
      roi_in: 160
    recipe:              # PoseRecipe / DetectorRecipe fields: epochs, lr, batch_size, hsv ...
      epochs: 40
      lr: 1.0e-3
    augment:             # photometric augmentations (models/photometric.py)
      preset: domain     # start from a named set ('off' is the default), then override
      jpeg_p: 0.5
    loader:              # how samples are read; does not change the result
      num_workers: 1
      cache_mb: 4096     # decoded samples kept in memory, MiB per set and process (0: none)
    data:                # the splits it trains and validates on, as record + generate
      splits: {train_a: {domain: wide, bags: [501], replays: 24, seed: 51}, ...}
      train: [train_a]   # the default --split
      val: [val_a]       # the default --val-split (bopsurg.data_spec; made by 'bopsurg data')

Every section and key is optional (defaults: the preset's). Unknown keys are errors naming the
file and the key. Command-line flags override the file, and ``--set SECTION.KEY=VALUE``
(:func:`apply_overrides`) any single field. The resolved configuration (every
field, explicit) is written into the run folder as ``config.yaml``: it is a valid ``--config``
file that reproduces the run.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import yaml

from bopsurg.data_spec import DataSpec, missing_splits, parse_data_spec
from bopsurg.errors import BopsurgError
from bopsurg.models.config_tree import to_plain, to_yaml
from bopsurg.models.photometric import PhotometricConfig
from bopsurg.options import nest, read_mapping

#: The model sections: each names the model a run trains (one per run).
MODEL_SECTIONS = ("detector", "pose", "seg", "ends")
SECTIONS = ("preset", "seed", *MODEL_SECTIONS, "recipe", "augment", "loader", "data")
D = TypeVar("D")


@dataclass(frozen=True)
class LoaderConfig:
    """How training samples are read (not part of the result: a resume may change it).

    Each set (training, validation) caches its decoded samples within ``cache_mb``: with
    ``shared_cache`` (detector and pose sets) in one file all its reading processes share,
    the first samples that fit; otherwise in every process that reads it (the training
    process and each of the ``num_workers`` processes, so up to ``(num_workers + 1) *
    cache_mb`` in all), least recently used evicted first. A sample costs about 0.25 MB
    (detector, 320x256 input) or 0.65 MB (pose, 256-px context crop), so the default holds
    about 6,000 pose instances: a set that fits is decoded once, a larger one streams. A
    shared cache that holds the whole set is also read without the workers after the first
    epoch (and on a GPU from a copy on the GPU); when it cannot hold the set, the log says
    how large ``cache_mb`` would have to be.

    Attributes:
        num_workers: Background loader processes that read batches ahead (0: read in the
            training process).
        cache_mb: The cache budget per set and per process, MiB (2**20 bytes) of decoded
            tensors (0: no cache, every sample is decoded every epoch).
        cache_items: At most this many cached samples per set and process as well (None:
            no count limit; 0: no cache). Files written before ``cache_mb`` existed hold
            ``cache_items: 0``, and keep meaning no cache.
        shared_cache: Detector and pose sets keep their decoded samples (at the training
            resolution) in one memory-mapped file that the training process and every
            worker share (:class:`~bopsurg.models.data.SlotCache`; ``/dev/shm`` where it
            has room): each sample is decoded once in all, and ``cache_mb`` is the budget
            per set in all, not per process. False: each process its own LRU cache.
    """

    num_workers: int = 0
    cache_mb: int = 4096
    cache_items: int | None = None
    shared_cache: bool = True

    def __post_init__(self) -> None:
        if self.num_workers < 0 or self.cache_mb < 0:
            raise ValueError("loader.num_workers and loader.cache_mb must be >= 0")
        items = self.cache_items
        if items is not None and (isinstance(items, bool) or not isinstance(items, int)):
            raise ValueError(f"loader.cache_items must be null or an integer, got {items!r}")
        if items is not None and items < 0:
            raise ValueError("loader.cache_items must be >= 0 (or null: no count limit)")


def read_config_file(path: str | Path) -> dict[str, Any]:
    """The mapping in a ``.yaml``/``.yml`` (``yaml.safe_load``) or ``.json`` file.

    Raises:
        BopsurgError: Unreadable file, bad syntax, not a mapping or an unknown section.
    """
    p = Path(path)
    try:
        data = read_mapping(p)  # YAML is a superset of JSON
    except BopsurgError as err:
        raise BopsurgError(f"--config {err}") from err
    for key in data:
        if key not in SECTIONS:
            raise BopsurgError(
                f"--config {p}: unknown key {key!r} (sections: {', '.join(SECTIONS)})"
            )
    return data


def recipe_data(config: dict[str, Any], where: str) -> DataSpec | None:
    """The ``data`` section of a ``--config`` mapping (None without one).

    Raises:
        BopsurgError: A bad section, one line per bad field (:func:`parse_data_spec`).
    """
    if "data" not in config:
        return None
    return parse_data_spec(config["data"], where, "data.")


def run_splits(
    split: str | None, val_split: str | None, data: DataSpec | None
) -> tuple[str, str | None]:
    """``(split, val_split)`` of a run: the flags when given, else the recipe's ``data.train``
    and ``data.val``, else ``train`` and None (one scene in 10 held out)."""
    if split is None:
        split = ",".join(data.train) if data is not None and data.train else "train"
    if val_split is None and data is not None and data.val:
        val_split = ",".join(data.val)
    return split, val_split


def check_splits_made(
    dataset: str | Path, splits: list[str], data: DataSpec, config: str | Path
) -> None:
    """Refuse a run whose recipe's splits ``dataset`` lacks (or holds unfinished, or made from
    another spec): one line naming them and the command that makes them. Splits the recipe
    does not define are left to the trainer.

    Raises:
        BopsurgError: A split of ``splits`` defined in ``data`` is not made in ``dataset``.
    """
    specs = data.selected(tuple(n for n in dict.fromkeys(splits) if n in data.splits))
    missing = [s.name for s in missing_splits(Path(dataset), specs)]
    if missing:
        raise BopsurgError(
            f"{dataset}: split{'s' if len(missing) > 1 else ''} {', '.join(missing)} of "
            f"{config} missing or unfinished; make them with: bopsurg data {config} --root "
            f"{dataset} --only {','.join(missing)}"
        )


def _coerce(value: Any, hint: Any, where: str) -> Any:
    """``value`` as the type ``hint`` of a dataclass field (YAML lists become tuples,
    ``1e-3``, which YAML reads as a string, a float)."""
    origin = typing.get_origin(hint)
    if origin is tuple:
        args = typing.get_args(hint)
        if not isinstance(value, list | tuple):
            raise BopsurgError(f"{where}: expected a list, got {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0], where) for v in value)
        if len(value) != len(args):
            raise BopsurgError(f"{where}: expected {len(args)} values, got {value!r}")
        return tuple(_coerce(v, a, where) for v, a in zip(value, args, strict=True))
    if origin in (typing.Union, types.UnionType):
        return value
    if hint is bool:
        if not isinstance(value, bool):
            raise BopsurgError(f"{where}: expected true or false, got {value!r}")
        return value
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int | float | str):
            raise BopsurgError(f"{where}: expected an integer, got {value!r}")
        try:
            as_float = float(value)
        except ValueError:
            raise BopsurgError(f"{where}: expected an integer, got {value!r}") from None
        if as_float != int(as_float):
            raise BopsurgError(f"{where}: expected an integer, got {value!r}")
        return int(as_float)
    if hint is float:
        if isinstance(value, bool):
            raise BopsurgError(f"{where}: expected a number, got {value!r}")
        try:
            return float(value)
        except (TypeError, ValueError):
            raise BopsurgError(f"{where}: expected a number, got {value!r}") from None
    if hint is str:
        return str(value)
    return value


def build(cls: type[D], base: dict[str, Any], values: Any, where: str) -> D:
    """``cls(**{**base, **values})`` with each value checked and coerced to its field's type.

    Raises:
        BopsurgError: ``values`` is not a mapping, names an unknown field, holds a value of
            the wrong type, or the dataclass rejects it (its ``ValueError``), all one line
            starting with ``where``.
    """
    if values is None:
        values = {}
    if not isinstance(values, dict):
        raise BopsurgError(f"{where}: expected a mapping of fields, got {values!r}")
    assert dataclasses.is_dataclass(cls)
    hints = typing.get_type_hints(cls)
    fields = {f.name for f in dataclasses.fields(cls)}
    for key in values:
        if key not in fields:
            raise BopsurgError(f"{where}: unknown key {key!r} (known: {', '.join(sorted(fields))})")
    merged = {**base, **{k: _coerce(v, hints[k], f"{where}.{k}") for k, v in values.items()}}
    try:
        return cls(**merged)
    except (TypeError, ValueError) as err:
        raise BopsurgError(f"{where}: {err}") from err


def augment_config(
    values: Any, where: str, default: PhotometricConfig | None = None
) -> PhotometricConfig:
    """The ``augment`` section: an optional ``preset`` then field overrides of it, or of
    ``default`` (the trainer's own, ``off`` when None) without one."""
    default = default or PhotometricConfig()
    if values is None:
        return default
    if not isinstance(values, dict):
        raise BopsurgError(f"{where}: expected a mapping of fields, got {values!r}")
    values = dict(values)
    try:
        base = (
            PhotometricConfig.preset_values(str(values.pop("preset")))
            if "preset" in values
            else dataclasses.asdict(default)
        )
    except ValueError as err:
        raise BopsurgError(f"{where}.preset: {err}") from err
    return build(PhotometricConfig, base, values, where)


def apply_overrides(data: dict[str, Any], items: list[str], where: str = "--set") -> dict[str, Any]:
    """``data`` (a ``--config`` mapping) with each ``SECTION.KEY=VALUE`` (or ``preset=`` /
    ``seed=``) of ``items`` set; VALUE is read as YAML (``0.5``, ``true``, ``[1, 2]``).

    Raises:
        BopsurgError: An item without ``=``, an unknown section, or a section that is not a
            mapping (keys are checked later, with the section's fields).
    """
    out = {k: (dict(v) if isinstance(v, dict) else v) for k, v in data.items()}
    for item in items:
        key, eq, text = item.partition("=")
        if not eq or not key:
            raise BopsurgError(f"{where} {item!r}: expected SECTION.KEY=VALUE")
        try:
            value = yaml.safe_load(text)
        except yaml.YAMLError:
            raise BopsurgError(f"{where} {item!r}: the value is not valid YAML") from None
        section = key.partition(".")[0]
        if section not in SECTIONS:
            raise BopsurgError(
                f"{where} {item!r}: unknown section {section!r} (sections: {', '.join(SECTIONS)})"
            )
        if isinstance(out.get(section), dict) or "." not in key:
            out = nest([(key, value)], out)
        elif out.get(section) is None:
            out = nest([(key, value)], {**out, section: {}})
        else:
            raise BopsurgError(f"{where} {item!r}: {section} is not a section of fields")
    return out


def resolved(
    kind: str, preset: str, seed: int, model: Any, recipe: Any, loader: LoaderConfig
) -> dict[str, Any]:
    """The full configuration of a run as a ``--config`` mapping (every field explicit):
    ``recipe.augment`` is written as the ``augment`` section."""
    rec = to_plain(recipe)
    augment = rec.pop("augment", None)
    out: dict[str, Any] = {"preset": preset, "seed": seed, kind: to_plain(model), "recipe": rec}
    if augment is not None:
        out["augment"] = augment
    out["loader"] = to_plain(loader)
    return out


def write_config(out: str | Path, config: dict[str, Any]) -> Path:
    """Atomically write ``config`` as ``OUT/config.yaml``; returns its path."""
    from bopsurg.atomic import write_text

    path = Path(out) / "config.yaml"
    header = "# the resolved configuration of this run (bopsurg train ... --config this file)\n"
    write_text(path, header + to_yaml(config))
    return path

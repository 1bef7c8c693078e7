"""Training data from a BOP split, streamed from disk: an index in memory, images per batch.

An index of the split (per image or per GT instance: ids, camera, pose, box, a few numbers)
is built from the JSON annotations; the pixels are read and decoded (OpenCV) only when a
sample is asked for, so memory does not grow with the number of images. Two views:

- :class:`DetectionSet` (detector): per image, the image letterboxed to the network input
  (uint8) with its ``bbox_visib`` boxes.
- :class:`PoseSet` (pose head): per GT instance, a square *context crop* around its visible
  box (2.5 × the box's longer side, resampled to ``context`` px) holding RGB, the visible
  mask and the object-frame coordinates of every visible pixel. The coordinates are computed
  from the rendered depth and the GT pose (``X = R^T (z K^-1 [u, v, 1] - t)``), so nothing
  beyond the BOP files is stored on disk, and the crop is large enough for every dynamic
  zoom-in (DZI) jitter to be cut from it later.

Both are map-style ``torch.utils.data.Dataset`` objects: :func:`batch_loader` reads the index
batches of an epoch through a ``DataLoader`` (``num_workers`` background processes, or the
main process with 0) and stacks them into :class:`DetectionBatch` / :class:`PoseBatch`. Reading
is deterministic (no random draw), so the batches are the same whatever the worker count.
An optional LRU cache (:class:`LruCache`) keeps decoded samples within a memory budget
(``cache_mb`` MiB per set and per process, by the samples' actual tensor bytes), so a set
that fits is decoded once and then served from memory, while a larger one still streams.

Whole scenes are held out for validation (one in ``val_every``, drawn with a fixed seed), so
validation frames never share a trajectory replay with training frames.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import tempfile
import weakref
from collections import OrderedDict, deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Generic, TypeVar

import cv2
import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset

from bopsurg.bop.dataset import BopDataset, BopScene, list_scene_ids
from bopsurg.bop.images import image_size, load_depth, load_mask, load_rgb
from bopsurg.errors import DatasetError
from bopsurg.models.detector.letterbox import letterbox

log = logging.getLogger(__name__)

#: Context crop side relative to the visible box's longer side: covers the largest DZI crop
#: (1.5 pad x 1.25 scale) with its largest centre shift (0.25 of the box).
CONTEXT_RATIO = 2.5

T = TypeVar("T")


#: Scene-id stride between the splits of a :class:`SplitUnion` (BOP scene ids have 6 digits).
SCENE_ID_STRIDE = 1_000_000


class SplitUnion(BopDataset):
    """Several splits of one dataset read as one training set (e.g. ``train,train_wide``: the
    default viewpoints and a wider domain). The k-th split's scene ``s`` appears as scene
    ``k * SCENE_ID_STRIDE + s``, so the first split keeps its ids (and a one-split union reads
    exactly as the split). Models, models_info and cameras come from the shared root.

    Raises:
        DatasetError: A split folder is missing, or a split is named twice.
    """

    def __init__(self, root: str | Path, splits: Sequence[str]) -> None:
        names = [s.strip() for s in splits]
        if not names or any(not s for s in names):
            raise DatasetError(f"empty split name in {','.join(splits)!r}", path=root)
        twice = sorted({s for s in names if names.count(s) > 1})
        if twice:
            raise DatasetError(f"split {twice[0]!r} is named twice", path=root)
        super().__init__(root, names[0])
        self.others = [BopDataset(root, s) for s in names[1:]]  # splits 1, 2, ...
        self.split = ",".join(names)

    def __repr__(self) -> str:
        return f"SplitUnion({str(self.root)!r}, splits={self.split!r})"

    @functools.cached_property
    def scene_ids(self) -> list[int]:
        """Every split's scene ids, offset by ``k * SCENE_ID_STRIDE`` for the k-th split."""
        out = list_scene_ids(self.split_dir)
        for k, part in enumerate(self.others, start=1):
            out += [k * SCENE_ID_STRIDE + s for s in part.scene_ids]
        return out

    def scene(self, scene_id: int) -> BopScene:
        """The scene of the split ``scene_id // SCENE_ID_STRIDE`` (cached there)."""
        k, sid = divmod(int(scene_id), SCENE_ID_STRIDE)
        if k == 0:
            return super().scene(sid)
        if k > len(self.others):
            raise DatasetError(f"no scene {scene_id} in splits {self.split}", path=self.root)
        return self.others[k - 1].scene(sid)


def open_split(root: str | Path, split: str) -> BopDataset:
    """``split`` of the dataset at ``root``; a comma-separated list (``train,train_wide``)
    opens a :class:`SplitUnion`."""
    if "," in split:
        return SplitUnion(root, split.split(","))
    return BopDataset(root, split)


#: Seed of the held-out scene draw of :func:`split_scenes`. A stride through the scene ids
#: (every 10th, as before) aliased with the generator's cycle of the paper's 20 ECM base
#: poses (replay i starts from pose i mod 20): it held out poses 9 and 19 only, the two closest
#: (needle at 17-40 mm, median 30, against 62 mm for the other scenes), so no model trained on
#: a close-up and validation saw nothing else.
VAL_SEED = 0


def split_scenes(
    dataset: BopDataset, val_every: int = 10, val: BopDataset | None = None
) -> tuple[list[int], list[int]]:
    """Train and validation scene ids of ``dataset``.

    With ``val`` (a separate split), all of ``dataset`` trains. Otherwise ``len // val_every``
    scenes drawn with the fixed seed :data:`VAL_SEED` are held out (deterministic, and not a
    stride through the ids: see there); with fewer than ``val_every`` scenes the last one is,
    and a single scene is used for both.
    """
    ids = dataset.scene_ids
    if not ids:
        raise DatasetError("the split has no scenes", path=dataset.split_dir)
    if val is not None or val_every <= 0:
        return ids, []
    if len(ids) < val_every:
        held = ids[-1:]
    else:
        draw = np.random.default_rng(VAL_SEED).choice(len(ids), len(ids) // val_every, False)
        held = [ids[k] for k in sorted(draw)]
    held_ids = set(held)
    train = [s for s in ids if s not in held_ids] or ids
    return train, held


@dataclass(frozen=True)
class InstanceRecord:
    """One usable GT instance: where it is and what it looks like (full-image px, mm)."""

    scene_id: int
    im_id: int
    gt_id: int
    obj_id: int
    K: np.ndarray  # (3, 3)
    R: np.ndarray  # (3, 3)
    t: np.ndarray  # (3,) mm
    bbox_visib: tuple[int, int, int, int]  # x, y, w, h (w = x_max - x_min, BOP)
    visib_fract: float
    px_count_visib: int = -1  # visible-mask pixels (scene_gt_info.json); -1: unknown


def list_instances(
    dataset: BopDataset,
    scene_ids: Sequence[int],
    obj_ids: Sequence[int] | None = None,
    min_visib: float = 0.1,
) -> dict[tuple[int, int], list[InstanceRecord]]:
    """GT instances per image with ``visib_fract >= min_visib`` (images without any kept too,
    as negatives, so the detector learns empty frames)."""
    out: dict[tuple[int, int], list[InstanceRecord]] = {}
    for sid in scene_ids:
        scene = dataset.scene(sid)
        infos = scene.gt_info
        if infos is None:
            raise DatasetError(
                "scene_gt_info.json is missing (run 'bopsurg annotate' first)",
                path=scene.scene_dir / "scene_gt_info.json",
            )
        for im_id in scene.im_ids:
            recs = []
            for gt_id, (gt, info) in enumerate(
                zip(scene.gt.get(im_id, []), infos.get(im_id, []), strict=False)
            ):
                if obj_ids is not None and gt.obj_id not in obj_ids:
                    continue
                if info.visib_fract < min_visib or info.bbox_visib[2] < 1:
                    continue
                recs.append(
                    InstanceRecord(
                        sid, im_id, gt_id, gt.obj_id, scene.camera[im_id].K, gt.R, gt.t,
                        info.bbox_visib, info.visib_fract, int(info.px_count_visib),
                    )
                )  # fmt: skip
            out[(sid, im_id)] = recs
    return out


#: Bytes per MiB: ``cache_mb`` budgets are in MiB.
MIB = 2**20


def sample_nbytes(value: Any) -> int:
    """Bytes of the tensor/array data of ``value`` (``element_size() * nelement()`` of each
    tensor, ``nbytes`` of each array), summed over nested tuples, lists and dict values;
    anything else counts 0."""
    if isinstance(value, torch.Tensor):
        return int(value.element_size() * value.nelement())
    if isinstance(value, np.ndarray):
        return int(value.nbytes)
    if isinstance(value, tuple | list):
        return sum(sample_nbytes(v) for v in value)
    if isinstance(value, dict):
        return sum(sample_nbytes(v) for v in value.values())
    return 0


class LruCache(Generic[T]):
    """Values by key within a memory budget, the least recently used evicted first.

    A value is charged :func:`sample_nbytes` bytes. Storing one evicts the least recently
    used values until the total fits ``max_bytes`` (and the count ``max_items``); a value
    larger than the whole budget is returned but not stored. ``max_bytes == 0`` or
    ``max_items == 0`` keeps nothing. Not shared between processes: each loader worker has
    its own.

    Args:
        max_bytes: The budget, bytes (0: no cache).
        max_items: At most this many values as well (None: no count limit).

    Attributes:
        nbytes: Bytes held now. hits, misses, evictions: counts since creation.
    """

    def __init__(self, max_bytes: int = 0, max_items: int | None = None) -> None:
        if max_bytes < 0:
            raise ValueError(f"cache budget must be >= 0 bytes, got {max_bytes}")
        if max_items is not None and max_items < 0:
            raise ValueError(f"cache item count must be >= 0, got {max_items}")
        self.max_bytes, self.max_items = max_bytes, max_items
        self._items: OrderedDict[Any, tuple[T, int]] = OrderedDict()
        self.nbytes = self.hits = self.misses = self.evictions = 0

    @property
    def enabled(self) -> bool:
        """Whether anything can be stored."""
        return self.max_bytes > 0 and self.max_items != 0

    def get(self, key: Any, make: Callable[[], T]) -> T:
        """The cached value of ``key``, or ``make()`` (stored, evicting the least recently
        used values to stay within the budget)."""
        hit = self._items.get(key)
        if hit is not None:
            self._items.move_to_end(key)
            self.hits += 1
            return hit[0]
        self.misses += 1
        value = make()
        if not self.enabled:
            return value
        size = sample_nbytes(value)
        if size > self.max_bytes:
            return value
        while self._items and (
            self.nbytes + size > self.max_bytes
            or (self.max_items is not None and len(self._items) >= self.max_items)
        ):
            _, (_, old) = self._items.popitem(last=False)
            self.nbytes -= old
            self.evictions += 1
        self._items[key] = (value, size)
        self.nbytes += size
        return value

    def keys(self) -> list[Any]:
        """The cached keys, least recently used first."""
        return list(self._items)

    def __len__(self) -> int:
        return len(self._items)


#: The fixed layout of a sample in a :class:`SlotCache`: the shape and dtype of each array.
Layout = tuple[tuple[tuple[int, ...], np.dtype[Any]], ...]
#: Batches read ahead from a complete shared cache (:class:`BatchReader`).
CACHED_AHEAD = 3


def _shared_dir(nbytes: int) -> tuple[str, int]:
    """Where a shared cache of ``nbytes`` lives, and the bytes it may take there: ``/dev/shm``
    (memory) when half its free space holds it, else the temporary folder (disk, in the
    page cache), else whichever has more room, half of its free space (a mapping written
    past a full file system kills the process, so never more)."""
    room = []
    for d in ("/dev/shm", tempfile.gettempdir()):
        if os.path.isdir(d) and os.access(d, os.W_OK):
            st = os.statvfs(d)
            room.append((d, st.f_bavail * st.f_frsize // 2))
    for d, free in room:
        if free >= nbytes:
            return d, nbytes
    return max(room, key=lambda r: r[1]) if room else (tempfile.gettempdir(), 0)


class SlotCache:
    """Decoded samples of one fixed layout in a memory-mapped file that every process reading
    the set shares (the training process and each loader worker): each sample is decoded
    once, by whichever process first needs it, and read from the mapping after that.

    The file holds the first ``capacity`` samples (as many as ``max_bytes`` allows, and
    ``max_items``); later ones are decoded every time. A sample is written, then flagged as
    filled, so a reader never sees half of one; two processes that decode the same sample
    write the same bytes. The file lives in ``/dev/shm`` where there is one; on Linux it is
    unlinked at once and the workers open it through the creating process's descriptor
    (``/proc/PID/fd/N``), so it goes with the cache that made it, or with that process when
    it is killed.

    Args:
        n: Samples in the set.
        layout: Shape and dtype of each array of a sample (a tuple of arrays or tensors).
        max_bytes: The budget, bytes.
        max_items: At most this many samples (None: no count limit).
    """

    def __init__(
        self, n: int, layout: Layout, max_bytes: int, max_items: int | None = None
    ) -> None:
        self.layout, self.n = layout, n
        sizes = [int(np.prod(shape)) * dt.itemsize for shape, dt in layout]
        self.slot = sum(sizes)
        starts = np.cumsum([0, *sizes[:-1]]).tolist()
        #: (shape, torch dtype, first byte, bytes) of each array of a sample in its slot.
        self.fields = [
            (shape, torch.from_numpy(np.empty(0, dt)).dtype, at, size)
            for (shape, dt), at, size in zip(layout, starts, sizes, strict=True)
        ]
        count = min(n, max_bytes // max(1, self.slot), n if max_items is None else max_items)
        folder, room = _shared_dir(count * (self.slot + 1))
        self.capacity = min(count, room // (self.slot + 1))
        if 0 < self.capacity < n:
            log.info(
                "the shared cache holds %d of %d samples; about %d MiB would hold them all "
                "(loader.cache_mb), and batches would then skip the loader workers",
                self.capacity, n, -(-n * (self.slot + 1) // MIB),
            )  # fmt: skip
        fd, name = tempfile.mkstemp(prefix="bopsurg-samples-", suffix=".bin", dir=folder)
        os.ftruncate(fd, self.capacity * (self.slot + 1))  # sparse: pages come as written
        own = f"/proc/{os.getpid()}/fd/{fd}"
        self._finalizer: weakref.finalize[Any, Any] | None
        if os.path.exists(own):  # Linux: nameless at once, so a killed run leaves nothing
            os.unlink(name)
            self.path = own
            self._finalizer = weakref.finalize(self, os.close, fd)
        else:
            os.close(fd)
            self.path = name
            self._finalizer = weakref.finalize(self, _unlink, name)
        self._map: np.memmap[Any, np.dtype[np.uint8]] | None = None
        self.hits = self.misses = 0

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state["_map"] = None
        state["_finalizer"] = None  # a copy never removes the file
        return state

    def _mapping(self) -> np.memmap[Any, np.dtype[np.uint8]]:
        if self._map is None:
            self._map = np.memmap(
                self.path, np.uint8, "r+", shape=(self.capacity * (self.slot + 1),)
            )
        return self._map

    def get(self, i: int, make: Callable[[], Any]) -> Any:
        """Sample ``i``: from the mapping when filled, else ``make()`` (stored when it fits)."""
        if i >= self.capacity:
            return make()
        mm = self._mapping()
        flags, base = self.capacity * self.slot, i * self.slot
        if mm[flags + i]:
            self.hits += 1
            return self._unpack(mm[base : base + self.slot])
        self.misses += 1
        value = make()
        arrays = [np.asarray(v) for v in (value if isinstance(value, tuple) else (value,))]
        mm[base : base + self.slot] = np.concatenate([a.reshape(-1).view(np.uint8) for a in arrays])
        mm[flags + i] = 1
        return value

    def complete(self) -> bool:
        """Every sample of the set is in the mapping (:meth:`read_batch` can read any batch)."""
        return self.capacity == self.n and len(self) == self.n

    def read_batch(self, idx: Sequence[int], pin: bool = False) -> tuple[torch.Tensor, ...]:
        """Samples ``idx``, stacked: one tensor (B, *shape) per array of the layout, each
        gathered straight from the mapping into its own (page-locked: ``pin``) memory, so a
        batch costs one copy of its bytes (no per-sample tensors, no collation).

        Raises:
            KeyError: A sample is not in the mapping (see :meth:`complete`).
        """
        ix = np.asarray(idx, dtype=np.int64)
        mm = self._mapping()
        flags = mm[self.capacity * self.slot :]
        if ix.size and (ix.min() < 0 or ix.max() >= self.capacity or not flags[ix].all()):
            raise KeyError("samples not in the shared cache")
        rows = mm[: self.capacity * self.slot].reshape(self.capacity, self.slot)
        out = []
        for shape, dtype, at, size in self.fields:
            t = torch.empty((ix.size, *shape), dtype=dtype, pin_memory=pin)
            dest = t.numpy().view(np.uint8).reshape(ix.size, size)
            np.take(rows[:, at : at + size], ix, axis=0, out=dest)  # releases the GIL
            out.append(t)
        return tuple(out)

    def to_device(self, device: torch.device, chunk: int = 256) -> tuple[torch.Tensor, ...]:
        """The whole cache (it must be :meth:`complete`) as tensors (capacity, *shape) on
        ``device``, one per array of the layout, copied ``chunk`` samples at a time."""
        out = tuple(
            torch.empty((self.capacity, *shape), dtype=dtype, device=device)
            for shape, dtype, _, _ in self.fields
        )
        for a in range(0, self.capacity, chunk):
            part = self.read_batch(range(a, min(self.capacity, a + chunk)))
            for dest, src in zip(out, part, strict=True):
                dest[a : a + src.shape[0]].copy_(src)
        return out

    def _unpack(self, raw: np.ndarray) -> Any:
        out = [
            torch.from_numpy(raw[at : at + size].copy().view(dt).reshape(shape))
            for (shape, dt), (_, _, at, size) in zip(self.layout, self.fields, strict=True)
        ]
        return out[0] if len(out) == 1 else tuple(out)

    def __len__(self) -> int:
        mm = self._mapping()
        return int(mm[self.capacity * self.slot :].sum()) if self.capacity else 0


def _unlink(path: str) -> None:
    with contextlib.suppress(FileNotFoundError):
        os.unlink(path)


def sample_cache(
    n: int, layout: Layout, cache_mb: float, cache_items: int | None, shared: bool
) -> LruCache[Any] | SlotCache:
    """A set's cache of decoded samples: a :class:`SlotCache` shared by the processes
    (``shared``), or each process's own :class:`LruCache`."""
    if shared and cache_mb > 0 and cache_items != 0:
        return SlotCache(n, layout, int(cache_mb * MIB), cache_items)
    return _cache(cache_mb, cache_items)


def _cache(cache_mb: float, cache_items: int | None) -> LruCache[Any]:
    if cache_mb < 0:
        raise ValueError(f"cache_mb must be >= 0, got {cache_mb}")
    return LruCache(int(cache_mb * MIB), cache_items)


class _Keyed(Dataset[tuple[int, Any]]):
    """``(i, data[i])``: a sample with its index (what a loader worker reads)."""

    def __init__(self, data: Dataset[Any]) -> None:
        self.data = data

    def __getitem__(self, i: int) -> tuple[int, Any]:
        return i, self.data[i]


class _Order:
    """The batch sampler of a persistent loader: yields the batches set for this epoch (it
    runs in the training process; the workers only read)."""

    def __init__(self) -> None:
        self.batches: list[list[int]] = []

    def __iter__(self) -> Iterator[list[int]]:
        return iter(self.batches)

    def __len__(self) -> int:
        return len(self.batches)


class _Collate(Generic[T]):
    def __init__(self, collate: Callable[[list[Any], list[int]], T]) -> None:
        self.collate = collate

    def __call__(self, keyed: list[tuple[int, Any]]) -> T:
        return self.collate([s for _, s in keyed], [i for i, _ in keyed])


def _worker_init(_: int) -> None:
    # one OpenCV thread per loader process: the trainer's threads keep the cores
    cv2.setNumThreads(1)


class BatchReader(Generic[T]):
    """Reads index batches of a dataset, in order, as collated batches.

    With ``num_workers > 0`` a ``DataLoader`` with that many persistent background processes
    reads up to ``2 * num_workers`` batches ahead (the processes, and their sample caches,
    live as long as the reader); with 0 the batches are read in this process when asked for.
    The workers are *spawned* (a fresh interpreter each, started once per reader): a forked
    child can inherit a lock held by one of OpenCV's or torch's threads and hang for good.
    Reading draws no random number, so the batches do not depend on ``num_workers``.

    Once a dataset's shared cache (a :class:`SlotCache`, its ``cache``) holds every sample
    (after the first epoch, when it is large enough), the batches are read from it here
    instead: no worker decodes, copies or sends a sample again, and the batches are the same
    (the dataset's ``batch_from`` makes them). On a GPU with room for it (a quarter of its
    free memory) the whole cache is copied there once, and a batch is a gather on the
    device; otherwise each batch is gathered from the mapping by threads a few batches
    ahead, into page-locked memory when ``pin_memory``.

    Args:
        data: A map-style dataset (``data[i]`` reads sample i from disk).
        collate: Stacks the samples of one batch: ``(samples, indices) -> batch``.
        num_workers: Background loader processes.
        pin_memory: Batches come in page-locked memory (the workers' batches through their
            ``pin_memory()``, those gathered from a complete cache directly), so the copies
            to a GPU can overlap its work (``non_blocking=True``).
        prefetch: Batches each worker reads ahead.
        device: The training device: a complete shared cache may be copied there.
    """

    def __init__(
        self,
        data: Dataset[Any],
        collate: Callable[[list[Any], list[int]], T],
        num_workers: int = 0,
        pin_memory: bool = False,
        prefetch: int = 2,
        device: torch.device | None = None,
    ) -> None:
        self.data, self.collate, self.num_workers = data, collate, num_workers
        self.pin_memory, self.device = pin_memory, device
        #: Epochs read from the shared cache by this process, and of those, on the device.
        self.cached_epochs = self.resident_epochs = 0
        self._resident: tuple[torch.Tensor, ...] | None = None
        self._order = _Order()
        self._loader: DataLoader[Any] | None = None
        if num_workers > 0:
            self._loader = DataLoader(
                _Keyed(data), batch_sampler=self._order, num_workers=num_workers,
                collate_fn=_Collate(collate), worker_init_fn=_worker_init,
                persistent_workers=True, prefetch_factor=prefetch, pin_memory=pin_memory,
                multiprocessing_context="spawn",
            )  # fmt: skip

    def __call__(self, index_batches: Iterable[Sequence[int] | torch.Tensor]) -> Iterator[T]:
        """The batches of ``index_batches`` (index lists or tensors), in that order."""
        batches = [[int(i) for i in b] for b in index_batches]
        cache = getattr(self.data, "cache", None)
        if isinstance(cache, SlotCache) and cache.complete():
            self.cached_epochs += 1
            on_device = self._on_device(cache)
            if self.cached_epochs == 1:
                log.debug(
                    "every sample is in the shared cache: batches are read from it%s",
                    f" on {self.device}" if on_device else "",
                )
            if on_device:
                self.resident_epochs += 1
                return self._from_device(batches)
            return self._from_cache(cache, batches)
        if self._loader is None:
            return (self.collate([self.data[i] for i in b], b) for b in batches)
        self._order.batches = batches
        return iter(self._loader)

    def _on_device(self, cache: SlotCache) -> bool:
        """Whether the cache is on the (CUDA) device, copying it there if it fits."""
        dev = self.device
        if self._resident is None and dev is not None and dev.type == "cuda":
            free, _ = torch.cuda.mem_get_info(dev)
            if cache.capacity * cache.slot <= free // 4:
                self._resident = cache.to_device(dev)
        return self._resident is not None

    def _from_device(self, batches: list[list[int]]) -> Iterator[T]:
        assert self._resident is not None
        make = self.data.batch_from  # type: ignore[attr-defined]
        for b in batches:
            ix = torch.tensor(b, dtype=torch.int64).to(self._resident[0].device)
            yield make(b, tuple(a.index_select(0, ix) for a in self._resident))

    def _from_cache(self, cache: SlotCache, batches: list[list[int]]) -> Iterator[T]:
        make = self.data.batch_from  # type: ignore[attr-defined]

        def read(b: list[int]) -> T:  # the gathers release the GIL: threads run side by side
            return make(b, cache.read_batch(b, self.pin_memory))  # type: ignore[no-any-return]

        with ThreadPoolExecutor(max_workers=CACHED_AHEAD) as readers:
            ahead = deque(readers.submit(read, b) for b in batches[:CACHED_AHEAD])
            for k in range(len(batches)):
                batch = ahead.popleft().result()
                if k + CACHED_AHEAD < len(batches):
                    ahead.append(readers.submit(read, batches[k + CACHED_AHEAD]))
                yield batch

    def all(self, batch_size: int) -> Iterator[T]:
        """Every sample in index order, in batches of ``batch_size`` (validation)."""
        n = len(self.data)  # type: ignore[arg-type]
        return self(list(range(i, min(i + batch_size, n))) for i in range(0, n, batch_size))


# --------------------------------------------------------------------------- detector


def bbox_to_xyxy(bbox: Sequence[float], scale: float = 1.0) -> list[float]:
    """BOP ``(x, y, w, h)`` with ``w = x_max - x_min`` (pixel indices) to pixel-edge
    ``(x1, y1, x2, y2)`` (the box covers pixels x..x+w inclusive), times ``scale``."""
    x, y, w, h = bbox
    return [x * scale, y * scale, (x + w + 1) * scale, (y + h + 1) * scale]


@dataclass
class DetectionBatch:
    """One batch of :class:`DetectionSet`.

    Attributes:
        idx: (B,) sample indices.
        images: (B, 3, h, w) uint8 RGB at the network input size.
        targets: per image (n, 5) float32 ``[class, x1, y1, x2, y2]`` in input px.
    """

    idx: torch.Tensor
    images: torch.Tensor
    targets: list[torch.Tensor]

    def pin_memory(self) -> DetectionBatch:
        """The batch in page-locked memory (what a ``pin_memory`` loader calls)."""
        return DetectionBatch(self.idx, self.images.pin_memory(), self.targets)


class DetectionSet(Dataset[tuple[torch.Tensor, torch.Tensor]]):
    """Letterboxed images (read on demand) and their boxes (in memory).

    ``data[i]`` is ``(image (3, h, w) uint8 RGB at the network input, targets (n, 5))``.

    Attributes:
        targets: per image (n, 5) float32 ``[class, x1, y1, x2, y2]`` in input px.
        keys: (scene_id, im_id) per image.
        paths: the RGB file of each image.
        scales: (N,) input px per image px.
        classes: object id of each class index.
        input_hw: the network input (h, w), px.
    """

    def __init__(
        self,
        paths: list[Path],
        targets: list[torch.Tensor],
        keys: list[tuple[int, int]],
        scales: np.ndarray,
        classes: tuple[int, ...],
        input_hw: tuple[int, int],
        cache_mb: float = 0,
        cache_items: int | None = None,
        shared: bool = False,
    ) -> None:
        self.paths, self.targets, self.keys = paths, targets, keys
        self.scales, self.classes, self.input_hw = scales, classes, input_hw
        self.cache_mb, self.cache_items, self.shared = cache_mb, cache_items, shared
        layout: Layout = (((3, *input_hw), np.dtype(np.uint8)),)
        self.cache = sample_cache(len(keys), layout, cache_mb, cache_items, shared)

    def __len__(self) -> int:
        return len(self.keys)

    def image(self, i: int) -> torch.Tensor:
        """(3, h, w) uint8 letterboxed image ``i``, decoded from disk (or the cache)."""

        def read() -> torch.Tensor:
            im, _ = letterbox(load_rgb(self.paths[i]), self.input_hw)
            return torch.from_numpy(np.ascontiguousarray(im.transpose(2, 0, 1)))

        image: torch.Tensor = self.cache.get(i, read)
        return image

    def __getitem__(self, i: int) -> tuple[torch.Tensor, torch.Tensor]:
        return self.image(i), self.targets[i]

    def head(self, n: int) -> DetectionSet:
        """The first ``n`` images (smoke tests)."""
        return DetectionSet(
            self.paths[:n], self.targets[:n], self.keys[:n], self.scales[:n], self.classes,
            self.input_hw, self.cache_mb, self.cache_items, self.shared,
        )  # fmt: skip

    @staticmethod
    def collate(samples: list[tuple[torch.Tensor, torch.Tensor]], idx: list[int]) -> DetectionBatch:
        """Stack the samples of one batch."""
        return DetectionBatch(
            torch.tensor(idx, dtype=torch.int64),
            torch.stack([s[0] for s in samples]),
            [s[1] for s in samples],
        )

    def batch_from(self, idx: list[int], arrays: tuple[torch.Tensor, ...]) -> DetectionBatch:
        """The batch of images ``idx`` stacked already (``arrays``: the images)."""
        (images,) = arrays
        return DetectionBatch(
            torch.tensor(idx, dtype=torch.int64), images, [self.targets[i] for i in idx]
        )


def load_detection_set(
    dataset: BopDataset,
    scene_ids: Sequence[int],
    input_hw: tuple[int, int],
    classes: Sequence[int],
    *,
    min_visib: float = 0.1,
    progress: bool = True,
    cache_mb: float = 0,
    cache_items: int | None = None,
    shared: bool = False,
) -> DetectionSet:
    """The index of the images of ``scene_ids`` with their ``bbox_visib`` boxes (scaled to the
    letterboxed input; image sizes come from the file headers). ``progress`` is accepted for
    compatibility: nothing is decoded here. ``cache_mb`` (MiB) and ``cache_items`` bound the
    set's cache of decoded images (0 MiB: none): a :class:`SlotCache` shared by the loader
    processes with ``shared``, else each process's :class:`LruCache`."""
    del progress
    per_image = list_instances(dataset, scene_ids, classes, min_visib)
    keys = list(per_image)
    cls_index = {o: k for k, o in enumerate(classes)}
    paths = [dataset.scene(sid).rgb_path(im_id) for sid, im_id in keys]
    scales = []
    targets = []
    for key, path in zip(keys, paths, strict=True):
        w, h = image_size(path)
        scale = min(input_hw[0] / h, input_hw[1] / w)
        scales.append(scale)
        rows = [[cls_index[r.obj_id], *bbox_to_xyxy(r.bbox_visib, scale)] for r in per_image[key]]
        targets.append(torch.tensor(rows, dtype=torch.float32).reshape(-1, 5))
    hw = (int(input_hw[0]), int(input_hw[1]))
    return DetectionSet(
        paths, targets, keys, np.array(scales), tuple(classes), hw, cache_mb, cache_items, shared
    )


# --------------------------------------------------------------------------- pose head


@dataclass
class PoseBatch:
    """One batch of :class:`PoseSet`: context crops and everything the pose losses need.

    Attributes:
        idx: (B,) sample indices.
        rgb: (B, 3, C, C) uint8 context crops.
        mask: (B, C, C) bool visible masks.
        xyz: (B, 3, C, C) float16 object-frame coordinates (mm) of visible pixels, 0 elsewhere.
        ctx: (B, 3) float32 ``(a, cx, cy)``: context px = (image px - (cx, cy)) * a + C/2.
        K: (B, 3, 3) float32 camera matrices (image px).
        R: (B, 3, 3) float32 GT rotations; t: (B, 3) float32 GT translations (mm).
        bbox: (B, 4) float32 visible boxes ``(x, y, w, h)`` in image px (pixel edges:
            w = x_max - x_min + 1).
        image_hw: (B, 2) int64 full-image size.
    """

    idx: torch.Tensor
    rgb: torch.Tensor
    mask: torch.Tensor
    xyz: torch.Tensor
    ctx: torch.Tensor
    K: torch.Tensor
    R: torch.Tensor
    t: torch.Tensor
    bbox: torch.Tensor
    image_hw: torch.Tensor

    def pin_memory(self) -> PoseBatch:
        """The batch with its images in page-locked memory (a ``pin_memory`` loader's)."""
        return replace(
            self, rgb=self.rgb.pin_memory(), mask=self.mask.pin_memory(),
            xyz=self.xyz.pin_memory(),
        )  # fmt: skip


def object_coordinates(
    depth_mm: np.ndarray, mask: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray
) -> np.ndarray:
    """(H, W, 3) float32 model-frame coordinates (mm) of the pixels in ``mask``, 0 elsewhere:
    ``X = R^T (z K^-1 [u, v, 1]^T - t)`` with z the rendered depth (mm) at pixel (u, v)."""
    v, u = np.nonzero(mask)
    z = depth_mm[v, u].astype(np.float64)
    rays = np.linalg.solve(K, np.stack([u, v, np.ones_like(u)]).astype(np.float64))
    pts_cam = rays * z
    pts = (R.T @ (pts_cam - t.reshape(3, 1))).T
    out = np.zeros((*mask.shape, 3), np.float32)
    out[v, u] = pts
    return out


def context_affine(bbox: Sequence[int], context: int) -> tuple[float, float, float]:
    """``(a, cx, cy)`` of the context crop around a BOP visible box (see :class:`PoseBatch`)."""
    x, y, w, h = bbox
    cx, cy = x + w / 2.0, y + h / 2.0  # pixel-index centre of pixels x..x+w
    side = CONTEXT_RATIO * (max(w, h) + 1)
    return context / side, cx, cy


def _warp(img: np.ndarray, a: float, cx: float, cy: float, context: int, interp: int) -> np.ndarray:
    affine = np.array([[a, 0, context / 2 - a * cx], [0, a, context / 2 - a * cy]], np.float64)
    return cv2.warpAffine(img, affine, (context, context), flags=interp, borderValue=0)


#: One pose sample: context RGB (3, C, C) uint8, mask (C, C) bool, xyz (3, C, C) float16.
PoseSample = tuple[torch.Tensor, torch.Tensor, torch.Tensor]


class PoseSet(Dataset[PoseSample]):
    """Context crops of GT instances, cut from the images on demand.

    In memory, per instance: the record, the context affine and the pose (a few hundred
    bytes). ``data[i]`` reads the RGB, depth and visible mask of instance i's image, computes
    its object coordinates and cuts the three context crops (see :class:`PoseBatch`).

    Attributes:
        ctx: (N, 3) float32 ``(a, cx, cy)`` context affines.
        K, R, t, bbox, image_hw: as in :class:`PoseBatch`, for all N instances.
        records: the source instances.
        context: the context crop side C, px.
    """

    def __init__(
        self,
        dataset: BopDataset,
        records: list[InstanceRecord],
        image_hw: list[tuple[int, int]],
        context: int = 256,
        cache_mb: float = 0,
        cache_items: int | None = None,
        shared: bool = False,
    ) -> None:
        self.dataset, self.records, self.context = dataset, records, context
        self.cache_mb, self.cache_items, self.shared = cache_mb, cache_items, shared
        C = context
        layout: Layout = (
            ((3, C, C), np.dtype(np.uint8)),
            ((C, C), np.dtype(np.bool_)),
            ((3, C, C), np.dtype(np.float16)),
        )
        self.cache = sample_cache(len(records), layout, cache_mb, cache_items, shared)

        def f32(a: Any) -> torch.Tensor:
            return torch.from_numpy(np.asarray(a, dtype=np.float32).copy())

        self.ctx = f32([context_affine(r.bbox_visib, context) for r in records]).reshape(-1, 3)
        self.K = f32([r.K for r in records]).reshape(-1, 3, 3)
        self.R = f32([r.R for r in records]).reshape(-1, 3, 3)
        self.t = f32([r.t for r in records]).reshape(-1, 3)
        self.bbox = f32(
            [[b[0], b[1], b[2] + 1, b[3] + 1] for b in (r.bbox_visib for r in records)]
        ).reshape(-1, 4)
        self.image_hw = torch.tensor(image_hw, dtype=torch.int64).reshape(-1, 2)

    def __len__(self) -> int:
        return len(self.records)

    def __getitem__(self, i: int) -> PoseSample:
        sample: PoseSample = self.cache.get(i, lambda: self._read(i))
        return sample

    def _read(self, i: int) -> PoseSample:
        r, C = self.records[i], self.context
        scene = self.dataset.scene(r.scene_id)
        cam = scene.camera[r.im_id]
        if cam.depth_scale is None:
            raise DatasetError("depth_scale missing", path=scene.scene_dir / "scene_camera.json")
        rgb = load_rgb(scene.rgb_path(r.im_id))
        depth = load_depth(scene.depth_path(r.im_id)) * cam.depth_scale
        mask = load_mask(scene.mask_visib_path(r.im_id, r.gt_id)) & (depth > 0)
        xyz = object_coordinates(depth, mask, r.K, r.R, r.t)
        a, cx, cy = (float(v) for v in self.ctx[i])
        c_rgb = _warp(rgb, a, cx, cy, C, cv2.INTER_LINEAR)
        c_mask = _warp(mask.astype(np.uint8), a, cx, cy, C, cv2.INTER_NEAREST) > 0
        c_xyz = _warp(xyz, a, cx, cy, C, cv2.INTER_NEAREST)
        # layout changes in NumPy: torch's thread pool is slow for them on a busy machine
        return (
            torch.from_numpy(np.ascontiguousarray(c_rgb.transpose(2, 0, 1))),
            torch.from_numpy(c_mask),
            torch.from_numpy(np.ascontiguousarray(c_xyz.transpose(2, 0, 1)).astype(np.float16)),
        )

    def collate(self, samples: list[PoseSample], idx: list[int]) -> PoseBatch:
        """Stack the samples of one batch with their poses and boxes."""
        return self.batch_from(idx, tuple(torch.stack([s[k] for s in samples]) for k in range(3)))

    def batch_from(self, idx: list[int], arrays: tuple[torch.Tensor, ...]) -> PoseBatch:
        """The batch of samples ``idx`` whose arrays are stacked already (rgb, mask, xyz)."""
        rgb, mask, xyz = arrays
        ix = torch.tensor(idx, dtype=torch.int64)
        return PoseBatch(
            ix, rgb, mask, xyz,
            self.ctx[ix], self.K[ix], self.R[ix], self.t[ix], self.bbox[ix], self.image_hw[ix],
        )  # fmt: skip

    def head(self, n: int) -> PoseSet:
        """The first ``n`` instances (smoke tests)."""
        hw = [(int(h), int(w)) for h, w in self.image_hw[:n].tolist()]
        return PoseSet(
            self.dataset, self.records[:n], hw, self.context, self.cache_mb, self.cache_items,
            self.shared,
        )  # fmt: skip


def load_pose_set(
    dataset: BopDataset,
    scene_ids: Sequence[int],
    obj_id: int,
    *,
    context: int = 256,
    min_visib: float = 0.1,
    min_pixels: int = 16,
    progress: bool = True,
    cache_mb: float = 0,
    cache_items: int | None = None,
    shared: bool = False,
) -> PoseSet:
    """The index of every instance of ``obj_id`` with ``visib_fract >= min_visib`` and at
    least ``min_pixels`` visible pixels (``px_count_visib`` of scene_gt_info.json). Nothing is
    decoded here; ``progress`` is accepted for compatibility. ``cache_mb`` (MiB) and
    ``cache_items`` bound the set's cache of decoded samples (0 MiB: none; ``shared``: a
    :class:`SlotCache` shared by the loader processes, else each process's :class:`LruCache`).

    Raises:
        DatasetError: No such instance.
    """
    del progress
    per_image = list_instances(dataset, scene_ids, [obj_id], min_visib)
    records: list[InstanceRecord] = []
    image_hw: list[tuple[int, int]] = []
    for (sid, im_id), recs in per_image.items():
        recs = [r for r in recs if r.px_count_visib < 0 or r.px_count_visib >= min_pixels]
        if not recs:
            continue
        w, h = image_size(dataset.scene(sid).rgb_path(im_id))
        records += recs
        image_hw += [(h, w)] * len(recs)
    if not records:
        raise DatasetError(
            f"no instance of obj_id {obj_id} with visib_fract >= {min_visib} in scenes "
            f"{list(scene_ids)[:5]}...",
            path=dataset.split_dir,
        )
    return PoseSet(dataset, records, image_hw, context, cache_mb, cache_items, shared)

"""Training data streamed from disk (models/data.py): the sets hold an index, not pixels; memory
does not grow with the number of images; batches do not depend on the loader's workers; the
sample cache keeps to its byte budget, least recently used out first, and changes no batch."""

from __future__ import annotations

import gc
import tracemalloc
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from bopsurg.bop.dataset import BopDataset  # noqa: E402
from bopsurg.bop.images import load_rgb  # noqa: E402
from bopsurg.example import ExampleSpec, write_example_dataset  # noqa: E402
from bopsurg.models.data import (  # noqa: E402
    MIB,
    BatchReader,
    LruCache,
    load_detection_set,
    load_pose_set,
    sample_nbytes,
    split_scenes,
)
from bopsurg.models.detector.letterbox import letterbox  # noqa: E402
from tests.models.plane_depth import write_plane_depth  # noqa: E402

INPUT_HW = (256, 320)


@pytest.fixture(scope="module")
def split(tmp_path_factory) -> BopDataset:
    """The example (3 scenes x 8 images of 640x480) plus depth images (a plane at the needle's
    depth), so the pose head's object coordinates can be computed."""
    root = tmp_path_factory.mktemp("stream")
    ex = write_example_dataset(root, ExampleSpec(seed=2, scenes=3, images_per_scene=8))
    write_plane_depth(BopDataset(ex.root, ex.split))
    return BopDataset(ex.root, ex.split)


def _nbytes(obj, seen=None) -> int:
    """Bytes of every array and tensor reachable from ``obj``'s attributes, lists and dicts."""
    seen = set() if seen is None else seen
    if id(obj) in seen:
        return 0
    seen.add(id(obj))
    if isinstance(obj, torch.Tensor):
        return obj.numel() * obj.element_size()
    if isinstance(obj, np.ndarray):
        return obj.nbytes
    if isinstance(obj, dict):
        return sum(_nbytes(v, seen) for v in obj.values())
    if isinstance(obj, list | tuple):
        return sum(_nbytes(v, seen) for v in obj)
    if hasattr(obj, "__dict__") and not isinstance(obj, type | BopDataset):
        return _nbytes(vars(obj), seen)
    return 0


def _peak_bytes(fn) -> int:
    gc.collect()
    tracemalloc.start()
    try:
        fn()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_the_sets_hold_an_index_not_images(split):
    det = load_detection_set(split, split.scene_ids, INPUT_HW, [1], cache_mb=0)
    pose = load_pose_set(split, split.scene_ids, 1, cache_mb=0)
    assert len(det) == 24
    assert len(pose) >= 12
    one_image = 3 * INPUT_HW[0] * INPUT_HW[1]
    assert _nbytes(det) < one_image  # the old loader held all 24 letterboxed images
    assert _nbytes(pose) < 3 * 256 * 256  # ... and every 256-px context crop
    for i in range(len(det)):
        det[i]
    for i in range(len(pose)):
        pose[i]
    assert _nbytes(det) < one_image
    assert len(det.cache) == 0
    assert len(pose.cache) == 0


@pytest.mark.parametrize("kind", ["detector", "pose"])
def test_memory_does_not_grow_with_the_number_of_images(split, kind):
    """Peak traced memory (NumPy and Python allocations) of indexing a split and reading every
    sample once: one scene vs three. The in-memory loader's peak grew with the images."""

    def build_and_read(scene_ids):
        if kind == "detector":
            data = load_detection_set(split, scene_ids, INPUT_HW, [1], cache_mb=0)
        else:
            data = load_pose_set(split, scene_ids, 1, cache_mb=0)
        for _ in BatchReader(data, data.collate)([[i] for i in range(len(data))]):
            pass

    build_and_read(split.scene_ids[:1])  # warm caches of annotations and imports
    few = _peak_bytes(lambda: build_and_read(split.scene_ids[:1]))
    many = _peak_bytes(lambda: build_and_read(split.scene_ids))
    assert many < 1.3 * few + 2**19, (few, many)


def test_a_sample_is_the_image_letterboxed_and_its_boxes_scaled(split):
    det = load_detection_set(split, split.scene_ids, INPUT_HW, [1])
    i = 5
    sid, im_id = det.keys[i]
    expected, scale = letterbox(load_rgb(split.scene(sid).rgb_path(im_id)), INPUT_HW)
    image, targets = det[i]
    assert image.shape == (3, *INPUT_HW)
    assert image.dtype == torch.uint8
    assert torch.equal(image.permute(1, 2, 0), torch.from_numpy(expected))
    assert det.scales[i] == pytest.approx(scale)
    info = split.scene(sid).gt_info[im_id][0]
    x, y, w, h = info.bbox_visib
    np.testing.assert_allclose(
        targets[0, 1:].numpy(), np.array([x, y, x + w + 1, y + h + 1]) * scale
    )


def test_pose_samples_hold_the_crop_mask_and_coordinates(split):
    pose = load_pose_set(split, split.scene_ids, 1, context=128)
    rgb, mask, xyz = pose[0]
    assert rgb.shape == (3, 128, 128)
    assert rgb.dtype == torch.uint8
    assert mask.shape == (128, 128)
    assert mask.dtype == torch.bool
    assert mask.sum() > 0
    assert xyz.shape == (3, 128, 128)
    assert xyz.dtype == torch.float16
    assert (xyz[:, ~mask] == 0).all()
    assert (xyz[:, mask].abs().sum(0) > 0).all()
    batch = pose.collate([pose[2], pose[0]], [2, 0])
    assert batch.idx.tolist() == [2, 0]
    assert torch.equal(batch.R[0], pose.R[2])
    assert torch.equal(batch.rgb[1], rgb)


@pytest.mark.parametrize("kind", ["detector", "pose"])
def test_workers_read_the_same_batches_in_the_same_order(split, kind):
    if kind == "detector":
        data = load_detection_set(split, split.scene_ids, (64, 96), [1])
    else:
        data = load_pose_set(split, split.scene_ids, 1, context=64)
    order = [torch.tensor([3, 1, 4]), torch.tensor([0, 5, 2]), torch.tensor([7, 6])]
    inline = list(BatchReader(data, data.collate, 0)(order))
    reader = BatchReader(data, data.collate, 1)
    for _ in range(2):  # a persistent reader, refilled every epoch
        ahead = list(reader(order))
        assert [b.idx.tolist() for b in ahead] == [o.tolist() for o in order]
        for a, b in zip(inline, ahead, strict=True):
            assert torch.equal(a.images if kind == "detector" else a.rgb,
                               b.images if kind == "detector" else b.rgb)  # fmt: skip


def test_the_lru_cache_keeps_the_last_items_only():
    cache: LruCache[int] = LruCache(2**30, max_items=2)
    made = []

    def make(k):
        made.append(k)
        return k * 10

    got = [cache.get(k, lambda k=k: make(k)) for k in (1, 2, 1, 3, 2, 1)]
    assert got == [10, 20, 10, 30, 20, 10]
    assert made == [1, 2, 3, 2, 1]
    assert len(cache) == 2
    for off in (LruCache(0), LruCache(2**30, max_items=0)):
        off.get(1, lambda: 1)
        assert len(off) == 0
    with pytest.raises(ValueError, match=">= 0"):
        LruCache(-1)
    with pytest.raises(ValueError, match=">= 0"):
        LruCache(10, max_items=-1)


def test_sample_bytes_are_the_tensor_and_array_data():
    sample = (
        torch.zeros(3, 8, 8, dtype=torch.uint8),
        torch.zeros(8, 8, dtype=torch.bool),
        torch.zeros(3, 8, 8, dtype=torch.float16),
    )
    assert sample_nbytes(sample) == 192 + 64 + 384
    assert sample_nbytes(torch.zeros(4, 2, dtype=torch.float32)[:, 0]) == 16  # a view: its own
    assert sample_nbytes([np.zeros(5, np.float64), {"a": torch.zeros(2)}, 7, "x"]) == 48


def test_the_cache_keeps_within_its_byte_budget_least_recently_used_out_first():
    def tensor(kb):  # uint8: kb KiB
        return torch.zeros(kb * 1024, dtype=torch.uint8)

    cache: LruCache[torch.Tensor] = LruCache(10 * 1024)  # 10 KiB
    sizes = {"a": 4, "b": 4, "c": 2, "d": 3, "big": 11}

    def get(k):
        return cache.get(k, lambda: tensor(sizes[k]))

    for k in ("a", "b", "c"):
        get(k)
    assert cache.nbytes == 10 * 1024
    assert cache.keys() == ["a", "b", "c"]
    get("a")  # a hit: a becomes the most recently used
    assert cache.keys() == ["b", "c", "a"]
    get("d")  # 3 KiB more: b (4 KiB, least recently used) goes, c stays
    assert cache.keys() == ["c", "a", "d"]
    assert cache.nbytes == 9 * 1024
    assert get("big").numel() == 11 * 1024  # larger than the budget: returned, not kept
    assert cache.keys() == ["c", "a", "d"]
    assert (cache.hits, cache.misses, cache.evictions) == (1, 5, 1)
    assert cache.nbytes == sum(sample_nbytes(v) for v, _ in cache._items.values())


@pytest.mark.parametrize("kind", ["detector", "pose"])
def test_a_small_cache_evicts_and_gives_the_same_batches(split, kind):
    """A budget of about 3 samples: the cache stays under it, evicts, serves hits, and every
    batch is the same as without a cache, over two epochs in two orders."""

    def read(mb):
        if kind == "detector":
            return load_detection_set(split, split.scene_ids, INPUT_HW, [1], cache_mb=mb)
        return load_pose_set(split, split.scene_ids, 1, context=64, cache_mb=mb)

    one = 3 * INPUT_HW[0] * INPUT_HW[1] if kind == "detector" else (3 + 1 + 6) * 64 * 64
    plain, cached = read(0), read(3.5 * one / MIB)
    assert plain.cache.max_bytes == 0
    n = min(len(plain), 10)
    orders = [
        [torch.tensor([0, 1, 2]), torch.tensor([2, 0, 3]), torch.tensor([4, 3, 0])],
        [torch.tensor(list(range(n - 1, -1, -1)))],
    ]
    fields = ("images",) if kind == "detector" else ("rgb", "mask", "xyz")
    for order in orders:
        expected = list(BatchReader(plain, plain.collate)(order))
        got = list(BatchReader(cached, cached.collate)(order))
        for a, b in zip(expected, got, strict=True):
            assert torch.equal(a.idx, b.idx)
            for f in fields:
                assert torch.equal(getattr(a, f), getattr(b, f)), f
        assert cached.cache.nbytes <= cached.cache.max_bytes
        assert len(cached.cache) == 3
    assert cached.cache.hits > 0
    assert cached.cache.evictions > 0
    assert len(plain.cache) == 0


def test_a_default_budget_caches_the_whole_small_set(split):
    pose = load_pose_set(split, split.scene_ids, 1, context=64, cache_mb=4096)
    for _ in range(2):
        for i in range(len(pose)):
            pose[i]
    assert len(pose.cache) == len(pose)
    assert pose.cache.misses == len(pose)  # every sample decoded once
    assert pose.cache.nbytes == len(pose) * (3 + 1 + 6) * 64 * 64
    assert pose.head(2).cache.max_bytes == 4096 * MIB


def test_held_out_scenes_do_not_alias_with_the_viewpoint_cycle():
    """The generator starts replay i from the paper's ECM base pose i mod 20: the held-out
    scenes must cover that cycle (a stride of 10 held out poses 9 and 19 only, the two closest
    viewpoints), be one in 10, be the same on every call and train on nothing they hold."""
    ds = SimpleNamespace(scene_ids=list(range(1, 401)), split_dir=Path("train"))
    train, held = split_scenes(ds)  # type: ignore[arg-type]
    assert len(held) == 40
    assert set(train).isdisjoint(held)
    assert sorted(train + held) == ds.scene_ids
    assert len({(s - 1) % 20 for s in held}) >= 15
    assert split_scenes(ds) == (train, held)
    few = SimpleNamespace(scene_ids=[3, 7], split_dir=Path("train"))
    assert split_scenes(few) == ([3], [7])  # type: ignore[arg-type]


def test_the_shared_cache_is_filled_once_for_every_process_and_keeps_to_its_budget():
    """A :class:`SlotCache` copied to another process (pickled, as a loader worker gets it)
    fills the same file: what one decodes the other reads; samples past the budget are
    decoded every time; the file goes with the cache that made it."""
    import os
    import pickle

    import numpy as np

    from bopsurg.models.data import SlotCache

    layout = (((2, 3), np.dtype(np.uint8)), ((3,), np.dtype(np.float16)))
    slot = 6 + 6
    cache = SlotCache(5, layout, max_bytes=3 * (slot + 1) + 1)
    assert cache.capacity == 3
    worker = pickle.loads(pickle.dumps(cache))
    made = []

    def sample(i):
        def make():
            made.append(i)
            return torch.full((2, 3), i, dtype=torch.uint8), torch.arange(3).half() * i

        return make

    first = worker.get(1, sample(1))
    again = cache.get(1, sample(1))  # the other process: read, not decoded
    assert made == [1]
    assert cache.hits == 1
    for a, b in zip(first, again, strict=True):
        assert torch.equal(a, b)
        assert a.dtype == b.dtype
    cache.get(4, sample(4))
    cache.get(4, sample(4))  # beyond the capacity: decoded each time
    assert made == [1, 4, 4]
    assert len(cache) == 1
    path = cache.path
    del worker
    assert os.path.exists(path)
    del cache, again
    import gc

    gc.collect()
    assert not os.path.exists(path)


def test_a_complete_shared_cache_reads_whole_batches_equal_to_the_samples():
    """:meth:`SlotCache.read_batch` stacks exactly what :meth:`SlotCache.get` returns, in
    the order asked, and refuses a batch with a sample not in the mapping."""
    from bopsurg.models.data import SlotCache

    layout = (
        ((2, 3), np.dtype(np.uint8)),
        ((3,), np.dtype(np.bool_)),
        ((1, 3), np.dtype(np.float16)),
    )
    cache = SlotCache(4, layout, max_bytes=1 << 20)

    def sample(i):
        return (
            torch.full((2, 3), 10 + i, dtype=torch.uint8),
            torch.tensor([i % 2 == 0, True, i == 3]),
            torch.arange(3).half().reshape(1, 3) * (i + 0.5),
        )

    for i in (0, 1, 2):
        cache.get(i, lambda i=i: sample(i))
    assert not cache.complete()
    with pytest.raises(KeyError):
        cache.read_batch([0, 3])
    cache.get(3, lambda: sample(3))
    assert cache.complete()
    got = cache.read_batch([3, 0, 0, 2])
    for k, array in enumerate(got):
        want = torch.stack([sample(i)[k] for i in (3, 0, 0, 2)])
        assert array.dtype == want.dtype
        assert torch.equal(array, want)
        assert array.is_contiguous()
    whole = cache.to_device(torch.device("cpu"), chunk=3)  # what a GPU gets, in two chunks
    for k, array in enumerate(whole):
        assert torch.equal(array, torch.stack([sample(i)[k] for i in range(4)]))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_a_complete_cache_moves_to_the_gpu_and_gives_the_same_batches(split):
    data = load_pose_set(split, split.scene_ids, 1, context=64, cache_mb=64.0, shared=True)
    reader = BatchReader(data, data.collate, 0, device=torch.device("cuda"))
    order = [torch.tensor([3, 1, 4]), torch.tensor([0, 5, 2])]
    reference = list(reader(order))  # decoded sample by sample, filling the cache
    list(reader([torch.arange(len(data))]))
    resident = list(reader(order))
    assert reader.resident_epochs == 1
    for a, b in zip(reference, resident, strict=True):
        assert b.rgb.is_cuda
        for name in ("rgb", "mask", "xyz"):
            assert torch.equal(getattr(a, name), getattr(b, name).cpu())


@pytest.mark.parametrize("kind", ["detector", "pose"])
def test_once_the_shared_cache_is_full_batches_come_from_it_unchanged(split, kind):
    """The first pass fills the shared cache (through a worker); later passes read whole
    batches from it in this process, and they equal the batches read sample by sample."""
    big = {"cache_mb": 64.0, "shared": True}
    if kind == "detector":
        data = load_detection_set(split, split.scene_ids, (64, 96), [1], **big)
    else:
        data = load_pose_set(split, split.scene_ids, 1, context=64, **big)
    order = [torch.tensor([3, 1, 4]), torch.tensor([0, 5, 2]), torch.tensor([7, 6])]
    everything = [torch.arange(len(data))]
    reference = list(BatchReader(data, data.collate, 0)(order))  # sample by sample
    assert not data.cache.complete()
    reader = BatchReader(data, data.collate, 1)
    list(reader(everything))  # the worker decodes every sample into the shared cache
    assert reader.cached_epochs == 0
    assert data.cache.complete()
    cached = list(reader(order))
    assert reader.cached_epochs == 1
    fields = ("idx", "images") if kind == "detector" else ("idx", "rgb", "mask", "xyz", "ctx", "R")
    for a, b in zip(reference, cached, strict=True):
        for name in fields:
            assert torch.equal(getattr(a, name), getattr(b, name)), name
        if kind == "detector":
            assert all(torch.equal(x, y) for x, y in zip(a.targets, b.targets, strict=True))

"""Windows of grayscale PNGs: equal to the same window of OpenCV's full decode."""

from __future__ import annotations

import struct
import zlib

import cv2
import numpy as np
import pytest

from bopsurg.bop.images import load_depth, load_depth_window, load_mask, load_mask_window
from bopsurg.bop.png_rows import decode_gray_window
from bopsurg.errors import DatasetError


def _chunk(kind: bytes, body: bytes) -> bytes:
    crc = zlib.crc32(kind + body) & 0xFFFFFFFF
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", crc)


def _filtered(row: np.ndarray, prior: np.ndarray, kind: int, bpp: int) -> np.ndarray:
    """PNG filter ``kind`` of one row of bytes (the PNG specification's definitions)."""
    x = row.astype(np.int64)
    a = np.concatenate([np.zeros(bpp, np.int64), x[:-bpp]])
    b = prior.astype(np.int64)
    c = np.concatenate([np.zeros(bpp, np.int64), b[:-bpp]])
    if kind == 0:
        pred = np.zeros_like(x)
    elif kind == 1:
        pred = a
    elif kind == 2:
        pred = b
    elif kind == 3:
        pred = (a + b) // 2
    else:
        p = a + b - c
        pa, pb, pc = np.abs(p - a), np.abs(p - b), np.abs(p - c)
        pred = np.where((pa <= pb) & (pa <= pc), a, np.where(pb <= pc, b, c))
    return ((x - pred) % 256).astype(np.uint8)


def encode_png(im: np.ndarray, kinds: list[int], idat_parts: int = 3) -> bytes:
    """A grayscale PNG of ``im`` (uint8 or uint16) with the given filter per row."""
    bpp = im.dtype.itemsize
    rows = im.astype(">u2").view(np.uint8) if bpp == 2 else im
    rows = rows.reshape(im.shape[0], -1)
    prior = np.zeros(rows.shape[1], np.uint8)
    raw = b""
    for row, kind in zip(rows, kinds, strict=True):
        raw += bytes([kind]) + _filtered(row, prior, kind, bpp).tobytes()
        prior = row
    comp = zlib.compress(raw)
    step = -(-len(comp) // idat_parts)
    head = struct.pack(">IIBBBBB", im.shape[1], im.shape[0], 8 * bpp, 0, 0, 0, 0)
    body = b"".join(_chunk(b"IDAT", comp[i : i + step]) for i in range(0, len(comp), step))
    return b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", head) + body + _chunk(b"IEND", b"")


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_window_equals_full_decode_for_none_sub_up_rows(dtype):
    rng = np.random.default_rng(3)
    im = rng.integers(0, np.iinfo(dtype).max, size=(23, 17), endpoint=True).astype(dtype)
    kinds = rng.choice([0, 1, 2], size=23).tolist()
    kinds[5:9] = [2, 2, 2, 2]  # a run of Up rows
    data = encode_png(im, kinds)
    full = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(full, im)  # the encoder is right
    for rows, cols in [((0, 23), None), ((6, 8), (3, 11)), ((0, 1), (0, 17)), ((20, 99), (-3, 4))]:
        got = decode_gray_window(data, rows, cols)
        assert got is not None
        assert got.dtype == dtype
        r = slice(max(rows[0], 0), rows[1])
        c = slice(None) if cols is None else slice(max(cols[0], 0), cols[1])
        np.testing.assert_array_equal(got, im[r, c])


def test_empty_and_off_image_windows():
    im = np.arange(12, dtype=np.uint8).reshape(3, 4)
    data = encode_png(im, [1, 1, 1])
    assert decode_gray_window(data, (5, 9), (0, 4)).shape == (0, 4)
    assert decode_gray_window(data, (1, 2), (7, 9)).shape == (1, 0)
    assert decode_gray_window(data, (2, 1)).shape == (0, 4)


@pytest.mark.parametrize("kind", [3, 4])
def test_average_and_paeth_rows_are_left_to_the_full_decoder(tmp_path, kind):
    im = np.random.default_rng(0).integers(0, 65535, size=(6, 5)).astype(np.uint16)
    data = encode_png(im, [1, 1, kind, 0, 0, 0])
    assert decode_gray_window(data, (0, 6)) is None
    assert decode_gray_window(data, (0, 2)) is not None  # the rows before it still decode
    path = tmp_path / "d.png"
    path.write_bytes(data)
    np.testing.assert_array_equal(
        load_depth_window(path, (1, 5), (2, 4)), load_depth(path)[1:5, 2:4]
    )


def test_colour_and_non_png_files_use_the_full_decoder(tmp_path):
    mask = np.zeros((8, 9, 3), np.uint8)
    mask[2, 3, 1] = 255
    path = tmp_path / "m.png"
    cv2.imwrite(str(path), mask)
    assert decode_gray_window(path.read_bytes(), (0, 8)) is None
    np.testing.assert_array_equal(load_mask_window(path, (1, 4), (2, 5)), load_mask(path)[1:4, 2:5])
    tif = tmp_path / "d.tif"
    cv2.imwrite(str(tif), np.full((4, 4), 7.5, np.float32))
    np.testing.assert_array_equal(load_depth_window(tif, (1, 3)), np.full((2, 4), 7.5, np.float32))


def test_corrupt_or_short_data_is_a_dataset_error(tmp_path):
    im = np.arange(40, dtype=np.uint8).reshape(5, 8)
    data = encode_png(im, [0] * 5, idat_parts=1)
    path = tmp_path / "bad.png"
    start = data.index(b"IDAT") + 4
    path.write_bytes(data[:start] + b"\x00" * 10 + data[start + 10 :])
    with pytest.raises(DatasetError, match=r"bad\.png"):
        load_mask_window(path, (0, 5))
    path.write_bytes(data[: start + 6])
    with pytest.raises(DatasetError, match=r"bad\.png"):
        load_mask_window(path, (0, 5))

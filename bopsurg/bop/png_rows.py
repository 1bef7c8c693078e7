"""The first rows of a grayscale PNG, decoded without the rest of the file.

VSD only looks at the pixels around the rendered object and the ambiguity columns at two
pixels per mask, so decompressing a depth image or mask only down to the last row needed
saves most of the decoding (zlib streams can stop anywhere). The row filters ``None``,
``Sub`` and ``Up`` (the ones OpenCV and most BOP tools write) undo as running sums modulo 256
along rows or columns, vectorised; files with other filters (``Average``, ``Paeth``), colour,
palettes, interlacing or bit depths other than 8 and 16 are left to the caller's full decoder
(:func:`decode_gray_rows` returns None). The stream is not checksummed when stopped early.
"""

from __future__ import annotations

import struct
import zlib

import numpy as np
from numpy.typing import NDArray

_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_NONE, _SUB, _UP = 0, 1, 2


def _chunks(data: bytes) -> tuple[tuple[int, ...] | None, bytes]:
    """IHDR fields and the concatenated IDAT payload (None, b"" when not a valid PNG)."""
    header: tuple[int, ...] | None = None
    idat: list[bytes] = []
    pos = len(_SIGNATURE)
    while pos + 8 <= len(data):
        (length,) = struct.unpack_from(">I", data, pos)
        kind = data[pos + 4 : pos + 8]
        body = data[pos + 8 : pos + 8 + length]
        if kind == b"IHDR" and length == 13:
            header = struct.unpack(">IIBBBBB", body)
        elif kind == b"IDAT":
            idat.append(body)
        elif kind == b"IEND":
            break
        pos += 12 + length
    return header, b"".join(idat)


def _clip(span: tuple[int, int], size: int) -> tuple[int, int]:
    """(first, end) within [0, size], end >= first."""
    first = min(max(int(span[0]), 0), size)
    return first, min(max(int(span[1]), first), size)


def _unfilter(kinds: NDArray[np.uint8], px: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """Undo the None/Sub/Up filters of (n, W, bytes per pixel) filtered rows, modulo 256.

    ``px`` may hold the leftmost W columns of the rows only: both filters look left or up.
    """
    out = px.copy()
    sub = kinds == _SUB
    if sub.any():  # Sub: each byte adds the same byte of the pixel to its left
        out[sub] = np.cumsum(px[sub], axis=1, dtype=np.uint8)
    up = np.flatnonzero(kinds == _UP)
    if up.size:  # Up: each byte adds the byte above; a run of Up rows is a column sum
        starts = up[np.r_[True, np.diff(up) > 1]]
        ends = up[np.r_[np.diff(up) > 1, True]] + 1
        for a, b in zip(starts.tolist(), ends.tolist(), strict=True):  # runs, not pixels
            run = np.cumsum(px[a:b], axis=0, dtype=np.uint8)
            out[a:b] = run + out[a - 1] if a > 0 else run
    return out


def decode_gray_window(
    data: bytes, rows: tuple[int, int], cols: tuple[int, int] | None = None
) -> NDArray[np.uint8] | NDArray[np.uint16] | None:
    """A window of an 8- or 16-bit grayscale PNG, or None when the file is not supported.

    Only the compressed data down to the window's last row is inflated, and only the window's
    rows (all rows above it when one of them uses the Up filter) left of its right edge are
    unfiltered.

    Args:
        data: The PNG file's bytes.
        rows: (first, end) rows of the window, end exclusive; clipped to the image.
        cols: (first, end) columns, end exclusive, clipped to the image (default: all).

    Returns:
        The window's stored values, uint8 or uint16, equal to the same window of a full
        decode; None for anything but a non-interlaced 8/16-bit grayscale PNG whose rows
        down to the window's use the None, Sub and Up filters only (decode those fully).

    Raises:
        ValueError: The compressed data is corrupt or ends before the window's last row.
    """
    if not data.startswith(_SIGNATURE):
        return None
    header, idat = _chunks(data)
    if header is None:
        return None
    width, height, bit_depth, color, compression, filtering, interlace = header
    if color != 0 or bit_depth not in (8, 16) or compression or filtering or interlace:
        return None
    r0, r1 = _clip(rows, height)
    c0, c1 = (0, width) if cols is None else _clip(cols, width)
    bpp = bit_depth // 8
    stride = 1 + width * bpp
    try:
        raw = zlib.decompressobj().decompress(idat, r1 * stride)
    except zlib.error as e:
        raise ValueError(f"corrupt image data ({e})") from None
    if len(raw) < r1 * stride:
        raise ValueError("image data ends early")
    buf = np.frombuffer(raw, dtype=np.uint8, count=r1 * stride).reshape(r1, stride)
    kinds = buf[:, 0]
    if np.any(kinds > _UP):
        return None
    first = 0 if np.any(kinds[r0:r1] == _UP) else r0  # Up rows need the rows above them
    px = buf[first:r1, 1 : 1 + c1 * bpp].reshape(r1 - first, c1, bpp)
    out = _unfilter(kinds[first:r1], px)[r0 - first :, c0:]
    if bpp == 1:
        return out.reshape(r1 - r0, c1 - c0)
    return np.ascontiguousarray(out).view(">u2").reshape(r1 - r0, c1 - c0).astype(np.uint16)

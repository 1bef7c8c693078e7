"""Images of BOP datasets: RGB, 16-bit depth and binary masks, read and written with OpenCV.

* RGB: ``rgb/{im_id:06d}.png`` (real images) or ``.jpg`` (PBR), 8-bit, returned in RGB order.
* Depth: ``depth/{im_id:06d}.png``, 16-bit unsigned single-channel PNG; depth in mm = stored
  value × ``depth_scale`` of the image's ``scene_camera.json`` entry. :func:`load_depth`
  returns the raw stored values as float32, like the reference ``inout.load_depth``.
* Masks: ``mask[_visib]/{im_id:06d}_{gt_id:06d}.png``, 8-bit, 255 = object, 0 = background.

Files are decoded from bytes (``cv2.imdecode``) so paths with any characters work, and every
writer encodes in memory and writes atomically.
"""

from __future__ import annotations

import struct
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from bopsurg.atomic import write_bytes
from bopsurg.bop.files import read_bytes
from bopsurg.bop.png_rows import decode_gray_window
from bopsurg.errors import DatasetError, ShapeError

#: Largest value a 16-bit depth PNG can store.
DEPTH_MAX = 65535


def _decode(path: str | Path, flags: int) -> NDArray[np.generic]:
    p = Path(path)
    import cv2  # on first use: windowed PNG reads (VSD, masks) need no OpenCV

    data = read_bytes(p, DatasetError, expected="an image file", noun="image")
    im = None
    if data:
        buf = np.frombuffer(data, dtype=np.uint8)
        try:
            im = cv2.imdecode(buf, flags)
        except cv2.error:
            im = None
    if im is None:
        raise DatasetError("cannot decode image (corrupt or unsupported format)", path=p)
    return im


def _encode(path: str | Path, im: NDArray[Any], params: list[int] | None = None) -> None:
    suffix = Path(path).suffix.lower()
    import cv2

    ok, buf = cv2.imencode(suffix, im, params or [])
    if not ok:
        raise DatasetError(f"OpenCV cannot encode a {suffix} image", path=path)
    write_bytes(path, buf.tobytes())


def load_depth(path: str | Path) -> NDArray[np.float32]:
    """Load a depth image as its raw stored values.

    Args:
        path: A 16-bit single-channel PNG (or any single-channel image OpenCV reads, e.g. the
            float TIFFs of ITODD).

    Returns:
        (H, W) float32 stored values; multiply by ``depth_scale`` to get mm.

    Raises:
        DatasetError: Missing, unreadable or multi-channel file.
    """
    import cv2

    im = _decode(path, cv2.IMREAD_UNCHANGED)
    if im.ndim != 2:
        raise DatasetError(
            f"depth image must be single-channel, got {im.shape[2]} channels", path=path
        )
    return im.astype(np.float32)


def _decode_window(
    path: str | Path, rows: tuple[int, int], cols: tuple[int, int] | None
) -> NDArray[np.generic]:
    """A window of an image's stored values: only as much of a grayscale PNG as it needs,
    anything else decoded fully and cut."""
    p = Path(path)
    data = read_bytes(p, DatasetError, expected="an image file", noun="image")
    try:
        window = decode_gray_window(data, rows, cols)
    except ValueError as e:
        raise DatasetError(f"cannot decode image ({e})", path=p) from None
    if window is not None:
        return window
    import cv2

    im = _decode(p, cv2.IMREAD_UNCHANGED)
    r = slice(max(rows[0], 0), max(rows[1], 0))
    return im[r] if cols is None else im[r, max(cols[0], 0) : max(cols[1], 0)]


def load_depth_window(
    path: str | Path, rows: tuple[int, int], cols: tuple[int, int] | None = None
) -> NDArray[np.float32]:
    """:func:`load_depth`, cut to a window: ``load_depth(path)[r0:r1, c0:c1]``, faster.

    Args:
        path: A single-channel depth image.
        rows: (first, end) rows, px, end exclusive (clipped to the image).
        cols: (first, end) columns, px, end exclusive (default: all).

    Raises:
        DatasetError: Missing, unreadable, corrupt or multi-channel file.
    """
    im = _decode_window(path, rows, cols)
    if im.ndim != 2:
        raise DatasetError(
            f"depth image must be single-channel, got {im.shape[2]} channels", path=path
        )
    return im.astype(np.float32)


def save_depth(path: str | Path, depth: ArrayLike) -> None:
    """Write a depth image as a 16-bit single-channel PNG (atomic).

    Values are rounded to the nearest integer, as the reference ``inout.save_depth`` does;
    unlike the reference, values that do not fit in uint16 raise instead of wrapping around.

    Args:
        path: Destination, must end in ``.png``.
        depth: (H, W) values to store (mm / depth_scale).

    Raises:
        ShapeError: Not 2-D, non-finite, negative or > 65535 after rounding.
        DatasetError: ``path`` is not a PNG.
    """
    if Path(path).suffix.lower() != ".png":
        raise DatasetError("depth images must be saved as PNG", path=path)
    d = np.asarray(depth)
    if d.ndim != 2:
        raise ShapeError(f"expected a (H, W) depth image, got shape {d.shape}", field="depth")
    r = np.round(d.astype(np.float64))
    if not np.all(np.isfinite(r)):
        raise ShapeError("depth contains NaN or inf", field="depth", path=path)
    if r.size and (r.min() < 0 or r.max() > DEPTH_MAX):
        raise ShapeError(
            f"depth values must lie in [0, {DEPTH_MAX}] after rounding, got "
            f"[{r.min():g}, {r.max():g}] (choose a depth_scale that fits)",
            field="depth",
            path=path,
        )
    _encode(path, r.astype(np.uint16))


def load_mask(path: str | Path) -> NDArray[np.bool_]:
    """Load a mask: True where the stored value is non-zero.

    Args:
        path: An 8-bit PNG (255 = object); colour masks count any non-zero channel.

    Returns:
        (H, W) bool.

    Raises:
        DatasetError: Missing or unreadable file.
    """
    import cv2

    im = _decode(path, cv2.IMREAD_UNCHANGED)
    mask: NDArray[np.bool_] = np.any(im[:, :, :3] != 0, axis=2) if im.ndim == 3 else im != 0
    return mask


def load_mask_window(
    path: str | Path, rows: tuple[int, int], cols: tuple[int, int] | None = None
) -> NDArray[np.bool_]:
    """:func:`load_mask`, cut to a window: ``load_mask(path)[r0:r1, c0:c1]``, faster.

    Args:
        path: A mask image.
        rows: (first, end) rows, px, end exclusive (clipped to the image).
        cols: (first, end) columns, px, end exclusive (default: all).

    Raises:
        DatasetError: Missing, unreadable or corrupt file.
    """
    im = _decode_window(path, rows, cols)
    mask: NDArray[np.bool_] = np.any(im[:, :, :3] != 0, axis=2) if im.ndim == 3 else im != 0
    return mask


def save_mask(path: str | Path, mask: ArrayLike) -> None:
    """Write a mask as an 8-bit PNG with 255 = object, 0 = background (atomic).

    Args:
        path: Destination (``.png``).
        mask: (H, W) array; non-zero / True = object.

    Raises:
        ShapeError: ``mask`` is not 2-D.
    """
    m = np.asarray(mask)
    if m.ndim != 2:
        raise ShapeError(f"expected a (H, W) mask, got shape {m.shape}", field="mask")
    _encode(path, np.where(m != 0, 255, 0).astype(np.uint8))


def load_rgb(path: str | Path) -> NDArray[np.uint8]:
    """Load a colour (or gray) image as 8-bit RGB.

    Gray images are replicated to 3 channels, alpha is dropped, 16-bit images are scaled to 8
    bits. EXIF orientation is ignored (as the reference toolkit does).

    Args:
        path: PNG, JPEG, TIFF ...

    Returns:
        (H, W, 3) uint8 in RGB order.

    Raises:
        DatasetError: Missing or unreadable file.
    """
    import cv2

    im = _decode(path, cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    return np.ascontiguousarray(im[:, :, ::-1])


def save_rgb(path: str | Path, rgb: ArrayLike, *, jpg_quality: int = 95) -> None:
    """Write an RGB (or gray) image as PNG or JPEG, chosen by the suffix (atomic).

    Args:
        path: Destination ending in ``.png``, ``.jpg`` or ``.jpeg``.
        rgb: (H, W, 3) uint8 RGB, or (H, W) uint8 gray.
        jpg_quality: JPEG quality 0-100 (the reference's default 95).

    Raises:
        ShapeError: Wrong shape or dtype.
        DatasetError: Unsupported suffix.
    """
    suffix = Path(path).suffix.lower()
    if suffix not in (".png", ".jpg", ".jpeg"):
        raise DatasetError(f"unsupported image format {suffix!r} (use .png or .jpg)", path=path)
    im = np.asarray(rgb)
    if im.dtype != np.uint8:
        raise ShapeError(f"expected uint8, got {im.dtype}", field="rgb")
    if im.ndim == 3 and im.shape[2] == 3:
        im = np.ascontiguousarray(im[:, :, ::-1])  # OpenCV writes BGR
    elif im.ndim != 2:
        raise ShapeError(f"expected (H, W, 3) or (H, W), got shape {im.shape}", field="rgb")
    import cv2

    if suffix == ".png":
        params = [cv2.IMWRITE_PNG_COMPRESSION, 1]  # fastest zlib level: 1.4x faster, ~5% larger
    else:
        params = [cv2.IMWRITE_JPEG_QUALITY, int(jpg_quality)]
    _encode(path, im, params)


def _png_size(head: bytes) -> tuple[int, int] | None:
    if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR" and len(head) >= 24:
        w, h = struct.unpack(">II", head[16:24])
        return int(w), int(h)
    return None


def _jpeg_size(path: Path) -> tuple[int, int] | None:
    # Walk the JPEG markers up to the first start-of-frame (SOF0..SOF15 but DHT/JPG/DAC).
    with path.open("rb") as f:
        if f.read(2) != b"\xff\xd8":
            return None
        while True:
            byte = f.read(1)
            while byte and byte != b"\xff":
                byte = f.read(1)
            while byte == b"\xff":
                byte = f.read(1)
            if not byte:
                return None
            marker = byte[0]
            if marker in (0x01, *range(0xD0, 0xD8)):  # markers without a length
                continue
            size = f.read(2)
            if len(size) < 2:
                return None
            length = struct.unpack(">H", size)[0]
            if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
                data = f.read(5)
                if len(data) < 5:
                    return None
                h, w = struct.unpack(">HH", data[1:5])
                return int(w), int(h)
            f.seek(length - 2, 1)


def image_size(path: str | Path) -> tuple[int, int]:
    """Size of an image file, read from the PNG/JPEG header when possible.

    Args:
        path: Image file.

    Returns:
        (width, height) in px.

    Raises:
        DatasetError: Missing or unreadable file.
    """
    p = Path(path)
    try:
        with p.open("rb") as f:
            head = f.read(32)
    except FileNotFoundError:
        raise DatasetError("image not found", path=p) from None
    except OSError as e:
        raise DatasetError(f"cannot read image ({e.strerror or e})", path=p) from None
    size = _png_size(head)
    if size is None and head[:2] == b"\xff\xd8":
        size = _jpeg_size(p)
    if size is None:  # other formats (TIFF ...): decode
        import cv2

        im = _decode(p, cv2.IMREAD_UNCHANGED)
        size = (int(im.shape[1]), int(im.shape[0]))
    return size

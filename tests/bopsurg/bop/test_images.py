"""Depth, mask and RGB images: round trips, bit depth, errors."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from bopsurg.bop import (
    image_size,
    load_depth,
    load_mask,
    load_rgb,
    save_depth,
    save_mask,
    save_rgb,
)
from bopsurg.errors import DatasetError, ShapeError


def test_depth_uint16_round_trip_with_depth_scale(tmp_path: Path) -> None:
    path = tmp_path / "depth" / "000000.png"
    depth_scale = 0.1  # mm per stored unit
    depth_mm = np.array([[0.0, 500.04, 1234.56], [6553.5, 100.0, 0.05]])
    save_depth(path, depth_mm / depth_scale)
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16
    assert raw.ndim == 2
    d = load_depth(path)
    assert d.dtype == np.float32
    assert d.shape == (2, 3)
    np.testing.assert_array_equal(d, np.round(depth_mm / depth_scale))
    np.testing.assert_allclose(d * depth_scale, depth_mm, atol=depth_scale / 2 + 1e-9)
    assert d.max() == 65535


@pytest.mark.parametrize("bad", [-1.0, 65535.6, np.nan])
def test_depth_out_of_range(tmp_path: Path, bad: float) -> None:
    with pytest.raises(ShapeError, match="depth"):
        save_depth(tmp_path / "d.png", np.array([[1.0, bad]]))
    assert not (tmp_path / "d.png").exists()


def test_depth_must_be_png(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="PNG"):
        save_depth(tmp_path / "d.jpg", np.zeros((2, 2)))


def test_mask_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "m.png"
    mask = np.zeros((5, 7), dtype=bool)
    mask[1:3, 2:6] = True
    save_mask(path, mask)
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint8
    assert set(np.unique(raw).tolist()) == {0, 255}
    out = load_mask(path)
    assert out.dtype == np.bool_
    np.testing.assert_array_equal(out, mask)


def test_rgb_png_round_trip_is_exact(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, size=(6, 9, 3), dtype=np.uint8)
    save_rgb(tmp_path / "a.png", rgb)
    np.testing.assert_array_equal(load_rgb(tmp_path / "a.png"), rgb)
    # Stored in BGR by OpenCV: the red channel of the file is rgb[..., 0].
    bgr = cv2.imread(str(tmp_path / "a.png"))
    np.testing.assert_array_equal(bgr[..., 2], rgb[..., 0])


def test_rgb_jpg_round_trip_is_close(tmp_path: Path) -> None:
    rgb = np.zeros((32, 32, 3), dtype=np.uint8)
    rgb[..., 0] = 200
    rgb[..., 1] = 100
    save_rgb(tmp_path / "a.jpg", rgb, jpg_quality=95)
    out = load_rgb(tmp_path / "a.jpg")
    assert out.shape == (32, 32, 3)
    assert np.abs(out.astype(int) - rgb).mean() < 3


def test_gray_becomes_three_channels(tmp_path: Path) -> None:
    gray = np.arange(12, dtype=np.uint8).reshape(3, 4) * 20
    save_rgb(tmp_path / "g.png", gray)
    out = load_rgb(tmp_path / "g.png")
    assert out.shape == (3, 4, 3)
    np.testing.assert_array_equal(out[..., 1], gray)


@pytest.mark.parametrize("suffix", [".png", ".jpg", ".tif"])
def test_image_size(tmp_path: Path, suffix: str) -> None:
    path = tmp_path / f"x{suffix}"
    cv2.imwrite(str(path), np.zeros((17, 23, 3), dtype=np.uint8))
    assert image_size(path) == (23, 17)


def test_unreadable_and_missing_images(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="not found") as e:
        load_rgb(tmp_path / "none.png")
    assert str(tmp_path / "none.png") in str(e.value)
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"not an image")
    for loader in (load_rgb, load_depth, load_mask):
        with pytest.raises(DatasetError, match="cannot decode") as e:
            loader(bad)
        assert e.value.path == str(bad)
    with pytest.raises(DatasetError, match="not found"):
        image_size(tmp_path / "none.png")


def test_save_rgb_rejects_bad_input(tmp_path: Path) -> None:
    with pytest.raises(ShapeError, match="uint8"):
        save_rgb(tmp_path / "a.png", np.zeros((2, 2, 3)))
    with pytest.raises(DatasetError, match="unsupported"):
        save_rgb(tmp_path / "a.bmp", np.zeros((2, 2, 3), dtype=np.uint8))

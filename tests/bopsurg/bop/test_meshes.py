"""PLY models and models_info.json."""

from __future__ import annotations

import math
import struct
from pathlib import Path

import numpy as np
import pytest
import trimesh

from bopsurg.bop import (
    ObjectModel,
    compute_model_info,
    load_models_info,
    load_ply,
    save_models_info,
    save_ply,
)
from bopsurg.errors import DatasetError, ModelError

from .conftest import CUBE_FACES, CUBE_PTS

ASCII_PLY = """ply
format ascii 1.0
comment made by hand
element vertex 4
property float x
property float y
property float z
property float nx
property float ny
property float nz
property uchar red
property uchar green
property uchar blue
element face 2
property list uchar int vertex_indices
end_header
0 0 0 0 0 1 255 0 0
10.5 0 0 0 0 1 0 255 0
10.5 20.25 0 0 0 1 0 0 255
0 20.25 0 0 0 1 10 20 30
3 0 1 2
3 0 2 3
"""


def test_ascii_ply_by_hand(tmp_path: Path) -> None:
    path = tmp_path / "m.ply"
    path.write_text(ASCII_PLY)
    m = load_ply(path)
    np.testing.assert_array_equal(m.pts, [[0, 0, 0], [10.5, 0, 0], [10.5, 20.25, 0], [0, 20.25, 0]])
    assert m.pts.dtype == np.float64
    np.testing.assert_array_equal(m.faces, [[0, 1, 2], [0, 2, 3]])
    assert m.faces.dtype == np.int64
    np.testing.assert_array_equal(m.normals, np.tile([0, 0, 1], (4, 1)))
    np.testing.assert_array_equal(m.colors[3], [10, 20, 30])
    assert m.colors.dtype == np.uint8


def test_binary_round_trip_keeps_vertex_order(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    # Duplicate and unreferenced vertices must survive: trimesh's processing would merge them.
    pts = rng.normal(size=(50, 3)) * 100
    pts[10] = pts[3]
    faces = rng.integers(0, 40, size=(30, 3))
    model = ObjectModel(
        pts=pts,
        faces=faces,
        normals=rng.normal(size=(50, 3)),
        colors=rng.integers(0, 256, size=(50, 3), dtype=np.uint8),
    )
    path = tmp_path / "obj_000001.ply"
    save_ply(path, model)
    assert path.read_bytes().startswith(b"ply\nformat binary_little_endian 1.0\n")
    back = load_ply(path)
    np.testing.assert_array_equal(back.pts, pts.astype(np.float32))  # float32 storage
    np.testing.assert_array_equal(back.faces, faces)
    np.testing.assert_array_equal(back.normals, model.normals.astype(np.float32))
    np.testing.assert_array_equal(back.colors, model.colors)
    # Other readers see the same vertices in the same order.
    tm = trimesh.load(path, process=False)
    np.testing.assert_allclose(tm.vertices, back.pts)
    np.testing.assert_array_equal(tm.faces, faces)


def test_point_cloud_without_faces(tmp_path: Path) -> None:
    path = tmp_path / "pc.ply"
    path.write_text(
        "ply\nformat ascii 1.0\nelement vertex 2\nproperty double x\nproperty double y\n"
        "property double z\nend_header\n1 2 3\n4 5 6\n"
    )
    m = load_ply(path)
    assert m.faces.shape == (0, 3)
    save_ply(tmp_path / "pc2.ply", m)
    np.testing.assert_array_equal(load_ply(tmp_path / "pc2.ply").pts, m.pts)


def test_binary_big_endian_quads_and_extra_element(tmp_path: Path) -> None:
    header = (
        b"ply\r\nformat binary_big_endian 1.0\r\nelement vertex 4\r\nproperty double x\r\n"
        b"property double y\r\nproperty double z\r\nproperty int flags\r\nelement face 1\r\n"
        b"property list uchar uint vertex_index\r\nelement edge 1\r\nproperty int a\r\n"
        b"end_header\r\n"
    )
    verts = b"".join(
        struct.pack(">dddi", x, y, 0.0, 7) for x, y in [(0, 0), (1, 0), (1, 1), (0, 1)]
    )
    face = struct.pack(">BIIII", 4, 0, 1, 2, 3)
    path = tmp_path / "q.ply"
    path.write_bytes(header + verts + face + struct.pack(">i", 5))
    m = load_ply(path)
    np.testing.assert_array_equal(m.pts[:, :2], [[0, 0], [1, 0], [1, 1], [0, 1]])
    np.testing.assert_array_equal(m.faces, [[0, 1, 2], [0, 2, 3]])  # fan triangulation


def test_mixed_polygons_ascii(tmp_path: Path) -> None:
    path = tmp_path / "p.ply"
    path.write_text(
        "ply\nformat ascii 1.0\nelement vertex 5\nproperty float x\nproperty float y\n"
        "property float z\nelement face 2\nproperty list uchar int vertex_indices\nend_header\n"
        "0 0 0\n1 0 0\n1 1 0\n0 1 0\n2 2 2\n3 0 1 2\n4 0 1 3 4\n"
    )
    np.testing.assert_array_equal(load_ply(path).faces, [[0, 1, 2], [0, 1, 3], [0, 3, 4]])


def test_ply_errors(tmp_path: Path) -> None:
    with pytest.raises(ModelError, match="not found"):
        load_ply(tmp_path / "none.ply")
    bad = tmp_path / "bad.ply"
    bad.write_text("solid cube\n")
    with pytest.raises(ModelError, match="not a PLY"):
        load_ply(bad)
    bad.write_text(ASCII_PLY.replace("3 0 2 3\n", "3 0 2 9\n"))
    with pytest.raises(ModelError, match="out of range"):
        load_ply(bad)
    bad.write_text(ASCII_PLY.replace("3 0 2 3\n", ""))
    with pytest.raises(ModelError, match="truncated"):
        load_ply(bad)
    data = (tmp_path / "x.ply").as_posix()
    save_ply(data, ObjectModel(pts=CUBE_PTS, faces=CUBE_FACES))
    bad.write_bytes(Path(data).read_bytes()[:-5])
    with pytest.raises(ModelError, match="truncated") as e:
        load_ply(bad)
    assert e.value.path == str(bad)


def test_compute_model_info_unit_cube() -> None:
    info = compute_model_info(CUBE_PTS)
    assert info["diameter"] == pytest.approx(math.sqrt(3), abs=1e-12)
    assert info["min_x"] == -0.5
    assert info["size_z"] == 1.0
    assert set(info) == {"diameter", "min_x", "min_y", "min_z", "size_x", "size_y", "size_z"}


def test_diameter_matches_brute_force() -> None:
    rng = np.random.default_rng(2)
    pts = rng.normal(size=(400, 3)) * [30, 10, 5]
    brute = np.sqrt(((pts[:, None] - pts[None]) ** 2).sum(-1)).max()
    assert compute_model_info(pts)["diameter"] == pytest.approx(brute, rel=1e-12)


@pytest.mark.parametrize(
    ("pts", "expected"),
    [
        ([[0, 0, 0], [3, 4, 0], [1, 1, 0], [2, 0, 0], [0, 2, 0], [1, 3, 0]], 5.0),  # planar
        ([[0, 0, 0], [1, 1, 1], [2, 2, 2], [3, 3, 3], [0.5, 0.5, 0.5]], math.sqrt(27)),  # line
        ([[1, 2, 3]] * 6, 0.0),  # one point
    ],
)
def test_diameter_of_degenerate_point_sets(pts: list[list[float]], expected: float) -> None:
    assert compute_model_info(np.array(pts, dtype=float))["diameter"] == pytest.approx(expected)


def test_models_info_round_trip_with_symmetries(tmp_path: Path) -> None:
    path = tmp_path / "models_info.json"
    flip = np.diag([-1.0, -1.0, 1.0, 1.0]).ravel().tolist()
    infos = {
        2: {**compute_model_info(CUBE_PTS), "symmetries_discrete": [flip]},
        1: {
            "diameter": 100.5,
            "symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}],
        },
    }
    save_models_info(path, infos)
    text = path.read_text()
    assert text.startswith('{\n  "1": {"diameter": 100.5, "symmetries_continuous": [{"axis"')
    loaded = load_models_info(path)
    assert list(loaded) == [1, 2]
    assert loaded[2]["symmetries_discrete"] == [flip]
    assert loaded[1] == infos[1]


@pytest.mark.parametrize(
    ("entry", "field", "reason"),
    [
        ('{"diameter": 0}', "5/diameter", "must be > 0"),
        ('{"diameter": NaN}', "5/diameter", "finite"),
        ('{"size_x": 1}', "5/diameter", "missing"),
        (
            '{"diameter": 1, "symmetries_discrete": [[1, 0, 0]]}',
            "5/symmetries_discrete/0",
            "16 numbers",
        ),
        (
            '{"diameter": 1, "symmetries_continuous": [{"axis": [0, 0, 0], "offset": [0, 0, 0]}]}',
            "5/symmetries_continuous/0/axis",
            "non-zero",
        ),
        (
            '{"diameter": 1, "symmetries_continuous": [{"axis": [0, 0, 1]}]}',
            "5/symmetries_continuous/0/offset",
            "missing",
        ),
    ],
)
def test_models_info_errors(tmp_path: Path, entry: str, field: str, reason: str) -> None:
    path = tmp_path / "models_info.json"
    path.write_text(f'{{"5": {entry}}}')
    with pytest.raises(DatasetError, match=reason) as e:
        load_models_info(path)
    assert e.value.field == field

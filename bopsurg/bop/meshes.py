"""Object models (PLY meshes in mm) and ``models_info.json``.

BOP models are ``models[_eval]/obj_{obj_id:06d}.ply``: triangle meshes (or point clouds) whose
vertex coordinates are in mm, with the origin at the centre of the 3D bounding box. The
metrics use the vertices in file order, so :func:`load_ply` keeps them exactly as stored: no
merging, no reordering, no dropping of unreferenced vertices. The parser is a small numpy
reader (ascii, binary little and big endian, any scalar property types, extra elements and
properties skipped); polygons with more than 3 corners are split into triangle fans (the
reference only accepts triangles).

``models_info.json`` maps obj_id to ``diameter`` (mm, the largest distance between two
vertices), the bounding box ``min_x, min_y, min_z, size_x, size_y, size_z`` (mm) and the
optional symmetries: ``symmetries_discrete`` (a list of 4x4 row-major transforms, 16 numbers,
translation in mm) and ``symmetries_continuous`` (a list of ``{"axis": [3], "offset": [3]}``,
offset = a point on the axis in mm).
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from bopsurg.atomic import write_bytes
from bopsurg.bop._validate import (
    Issues,
    get_dict,
    get_float,
    get_floats,
    get_list,
    id_key,
)
from bopsurg.bop.jsonio import load_json, save_json
from bopsurg.errors import ModelError, ShapeError

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]

_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}


@dataclass(frozen=True, eq=False)
class ObjectModel:
    """A 3D object model.

    Attributes:
        pts: (V, 3) float64 vertices in mm, in file order.
        faces: (F, 3) int64 vertex indices of the triangles; (0, 3) for a point cloud.
        normals: (V, 3) float64 vertex normals, or None.
        colors: (V, 3) uint8 RGB vertex colours, or None.
    """

    pts: F64
    faces: NDArray[np.int64]
    normals: F64 | None = None
    colors: NDArray[np.uint8] | None = None

    def __post_init__(self) -> None:
        pts = np.asarray(self.pts, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ShapeError(f"expected shape (V, 3), got {pts.shape}", field="pts")
        faces = np.asarray(self.faces, dtype=np.int64)
        if faces.size == 0:
            faces = faces.reshape(0, 3)
        if faces.ndim != 2 or faces.shape[1] != 3:
            raise ShapeError(f"expected shape (F, 3), got {faces.shape}", field="faces")
        if faces.size and (faces.min() < 0 or faces.max() >= len(pts)):
            raise ShapeError(f"vertex index out of range [0, {len(pts)})", field="faces")
        object.__setattr__(self, "pts", pts)
        object.__setattr__(self, "faces", faces)
        if self.normals is not None:
            normals = np.asarray(self.normals, dtype=np.float64)
            if normals.shape != pts.shape:
                raise ShapeError(
                    f"expected shape {pts.shape}, got {normals.shape}", field="normals"
                )
            object.__setattr__(self, "normals", normals)
        if self.colors is not None:
            colors = np.asarray(self.colors)
            if colors.shape != pts.shape:
                raise ShapeError(f"expected shape {pts.shape}, got {colors.shape}", field="colors")
            object.__setattr__(self, "colors", colors.astype(np.uint8))

    @property
    def n_vertices(self) -> int:
        """Number of vertices V."""
        return len(self.pts)


# --------------------------------------------------------------------------- PLY reading


@dataclass
class _Property:
    name: str
    dtype: str  # numpy type code without byte order, e.g. "f4"
    count_dtype: str | None = None  # list properties: type of the count


@dataclass
class _Element:
    name: str
    count: int
    props: list[_Property]


def _parse_header(data: bytes, path: Path) -> tuple[str, list[_Element], int]:
    if not data.startswith(b"ply"):
        raise ModelError("not a PLY file (does not start with 'ply')", path=path)
    m = re.search(rb"end_header[ \t]*(\r?\n|\Z)", data)
    if m is None:
        raise ModelError("PLY header has no end_header line", path=path)
    header = data[: m.start()].decode("ascii", errors="replace").splitlines()
    fmt = None
    elements: list[_Element] = []
    for lineno, raw in enumerate(header, start=1):
        words = raw.split()
        if not words or words[0] in ("ply", "comment", "obj_info"):
            continue
        try:
            if words[0] == "format":
                fmt = words[1]
                if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
                    raise ValueError(f"unknown PLY format {fmt!r}")
            elif words[0] == "element":
                elements.append(_Element(words[1], int(words[2]), []))
            elif words[0] == "property":
                if not elements:
                    raise ValueError("property before any element")
                if words[1] == "list":
                    prop = _Property(words[4], _PLY_TYPES[words[3]], _PLY_TYPES[words[2]])
                else:
                    prop = _Property(words[2], _PLY_TYPES[words[1]])
                elements[-1].props.append(prop)
            else:
                raise ValueError(f"unknown header keyword {words[0]!r}")
        except (IndexError, KeyError, ValueError) as e:
            reason = str(e) if isinstance(e, ValueError) else f"bad line {raw.strip()!r}"
            raise ModelError(f"malformed PLY header: {reason}", path=path, line=lineno) from None
    if fmt is None:
        raise ModelError("malformed PLY header: no format line", path=path)
    for el in elements:
        if el.count < 0:
            raise ModelError(f"negative count of element {el.name!r}", path=path)
    return fmt, elements, m.end()


def _binary_element(
    data: bytes, offset: int, el: _Element, bo: str, path: Path
) -> tuple[dict[str, Any], int]:
    """Read one element from binary data; returns {property: array or list of arrays}."""
    n = el.count
    lists = [p for p in el.props if p.count_dtype is not None]
    if not lists:
        dt = np.dtype([(p.name, bo + p.dtype) for p in el.props])
        end = offset + dt.itemsize * n
        if end > len(data):
            raise ModelError(f"file is truncated in element {el.name!r}", path=path)
        arr = np.frombuffer(data, dtype=dt, count=n, offset=offset)
        return {p.name: arr[p.name] for p in el.props}, end
    if n == 0:
        return {p.name: np.zeros((0, 3)) for p in el.props}, offset
    # Fast path: every item has the same list lengths as the first (all triangles).
    pos = offset
    first: dict[str, int] = {}
    for p in el.props:
        if p.count_dtype is None:
            pos += np.dtype(p.dtype).itemsize
        else:
            cdt = np.dtype(bo + p.count_dtype)
            if pos + cdt.itemsize > len(data):
                raise ModelError(f"file is truncated in element {el.name!r}", path=path)
            k = int(np.frombuffer(data, dtype=cdt, count=1, offset=pos)[0])
            first[p.name] = k
            pos += cdt.itemsize + k * np.dtype(p.dtype).itemsize
    fields: list[tuple[Any, ...]] = []
    for p in el.props:
        if p.count_dtype is None:
            fields.append((p.name, bo + p.dtype))
        else:
            fields.append((f"_n_{p.name}", bo + p.count_dtype))
            fields.append((p.name, bo + p.dtype, (first[p.name],)))
    dt = np.dtype(fields)
    end = offset + dt.itemsize * n
    if end <= len(data):
        arr = np.frombuffer(data, dtype=dt, count=n, offset=offset)
        if all(np.all(arr[f"_n_{p.name}"] == first[p.name]) for p in lists):
            return {p.name: arr[p.name] for p in el.props}, end
    # Slow path: variable list lengths (polygons), item by item.
    out: dict[str, list[Any]] = {p.name: [] for p in el.props}
    pos = offset
    try:
        for _ in range(n):
            for p in el.props:
                if p.count_dtype is None:
                    val = np.frombuffer(data, dtype=bo + p.dtype, count=1, offset=pos)[0]
                    pos += np.dtype(p.dtype).itemsize
                    out[p.name].append(val)
                else:
                    cdt = np.dtype(bo + p.count_dtype)
                    k = int(np.frombuffer(data, dtype=cdt, count=1, offset=pos)[0])
                    pos += cdt.itemsize
                    vals = np.frombuffer(data, dtype=bo + p.dtype, count=k, offset=pos)
                    pos += k * np.dtype(p.dtype).itemsize
                    out[p.name].append(vals)
    except ValueError:
        raise ModelError(f"file is truncated in element {el.name!r}", path=path) from None
    return {k: (v if k in first else np.asarray(v)) for k, v in out.items()}, pos


def _ascii_element(
    tokens: list[bytes], pos: int, el: _Element, path: Path
) -> tuple[dict[str, Any], int]:
    n = el.count
    lists = [p for p in el.props if p.count_dtype is not None]
    try:
        if not lists:
            k = len(el.props)
            chunk = tokens[pos : pos + n * k]
            if len(chunk) < n * k:
                raise IndexError
            arr = np.array(chunk, dtype=np.float64).reshape(n, k)
            return {p.name: arr[:, i] for i, p in enumerate(el.props)}, pos + n * k
        if n == 0:
            return {p.name: np.zeros((0, 3)) for p in el.props}, pos
        # Fast path: every item as long as the first.
        lengths, q = [], pos
        for p in el.props:
            if p.count_dtype is None:
                lengths.append(1)
                q += 1
            else:
                k = int(tokens[q])
                lengths.append(k + 1)
                q += k + 1
        row = sum(lengths)
        chunk = tokens[pos : pos + n * row]
        if len(chunk) == n * row:
            arr = np.array(chunk, dtype=np.float64).reshape(n, row)
            out, col, ok = {}, 0, True
            for p, ln in zip(el.props, lengths, strict=True):
                if p.count_dtype is None:
                    out[p.name] = arr[:, col]
                else:
                    ok &= bool(np.all(arr[:, col] == ln - 1))
                    out[p.name] = arr[:, col + 1 : col + ln]
                col += ln
            if ok:
                return out, pos + n * row
        # Slow path: variable list lengths.
        res: dict[str, list[Any]] = {p.name: [] for p in el.props}
        for _ in range(n):
            for p in el.props:
                if p.count_dtype is None:
                    res[p.name].append(float(tokens[pos]))
                    pos += 1
                else:
                    k = int(tokens[pos])
                    res[p.name].append(np.array(tokens[pos + 1 : pos + 1 + k], dtype=np.float64))
                    if len(res[p.name][-1]) < k:
                        raise IndexError
                    pos += k + 1
        return {
            p.name: (res[p.name] if p.count_dtype else np.asarray(res[p.name])) for p in el.props
        }, pos
    except IndexError:
        raise ModelError(f"file is truncated in element {el.name!r}", path=path) from None
    except ValueError:
        raise ModelError(f"malformed ascii data in element {el.name!r}", path=path) from None


def _triangles(faces: Any, n_vertices: int, path: Path) -> NDArray[np.int64]:
    if isinstance(faces, np.ndarray):  # uniform length (F, k)
        f = faces.astype(np.int64)
        if f.ndim != 2 or (len(f) and f.shape[1] < 3):
            raise ModelError("faces must have at least 3 corners", path=path)
        if f.size and f.shape[1] > 3:  # fan triangulation of convex polygons
            k = f.shape[1]
            f = np.stack(
                [np.repeat(f[:, 0], k - 2), f[:, 1:-1].reshape(-1), f[:, 2:].reshape(-1)], axis=1
            )
        f = f.reshape(-1, 3)
    else:
        tris: list[tuple[int, int, int]] = []
        for poly in faces:
            p = np.asarray(poly, dtype=np.int64)
            if len(p) < 3:
                raise ModelError("faces must have at least 3 corners", path=path)
            tris.extend((p[0], p[i], p[i + 1]) for i in range(1, len(p) - 1))
        f = np.asarray(tris, dtype=np.int64).reshape(-1, 3)
    if f.size and (f.min() < 0 or f.max() >= n_vertices):
        raise ModelError(f"face vertex index out of range [0, {n_vertices})", path=path)
    return f


def _colors(values: list[NDArray[Any]], dtypes: list[str]) -> NDArray[np.uint8]:
    c = np.stack([np.asarray(v, dtype=np.float64) for v in values], axis=1)
    if all(d.startswith("f") for d in dtypes) and c.size and c.max() <= 1.0:
        c = c * 255.0  # float colours in [0, 1]
    return np.clip(np.rint(c), 0, 255).astype(np.uint8)


def load_ply(path: str | Path) -> ObjectModel:
    """Load a PLY model keeping the vertex order (no merging, no reordering).

    Args:
        path: ascii or binary PLY with an element ``vertex`` (``x, y, z`` in mm; optional
            ``nx, ny, nz`` and ``red, green, blue``) and optionally an element ``face`` with a
            list property ``vertex_indices`` (or ``vertex_index``). Without faces the model is
            a point cloud.

    Returns:
        The model; vertices float64 in mm.

    Raises:
        ModelError: Missing file, malformed header or data, no x/y/z, non-finite vertices,
            face indices out of range.
    """
    p = Path(path)
    try:
        data = p.read_bytes()
    except FileNotFoundError:
        raise ModelError("model file not found", path=p) from None
    except OSError as e:
        raise ModelError(f"cannot read model file ({e.strerror or e})", path=p) from None
    fmt, elements, offset = _parse_header(data, p)
    values: dict[str, dict[str, Any]] = {}
    if fmt == "ascii":
        tokens = data[offset:].split()
        pos = 0
        for el in elements:
            values[el.name], pos = _ascii_element(tokens, pos, el, p)
    else:
        bo = "<" if fmt == "binary_little_endian" else ">"
        for el in elements:
            values[el.name], offset = _binary_element(data, offset, el, bo, p)
    vertex = values.get("vertex")
    if vertex is None or not {"x", "y", "z"} <= vertex.keys():
        raise ModelError("PLY has no vertex element with x, y, z properties", path=p)
    pts = np.stack([np.asarray(vertex[k], dtype=np.float64) for k in "xyz"], axis=1)
    if not np.all(np.isfinite(pts)):
        raise ModelError("vertex coordinates contain NaN or inf", path=p)
    normals = None
    if {"nx", "ny", "nz"} <= vertex.keys():
        normals = np.stack([np.asarray(vertex[k], dtype=np.float64) for k in ("nx", "ny", "nz")], 1)
    colors = None
    vtypes = {q.name: q.dtype for el in elements if el.name == "vertex" for q in el.props}
    for names in (("red", "green", "blue"), ("diffuse_red", "diffuse_green", "diffuse_blue")):
        if set(names) <= vertex.keys():
            colors = _colors([vertex[k] for k in names], [vtypes[k] for k in names])
            break
    faces = np.zeros((0, 3), dtype=np.int64)
    face = values.get("face")
    if face is not None:
        key: str | None = next((k for k in ("vertex_indices", "vertex_index") if k in face), None)
        if key is None:
            face_el = next(el for el in elements if el.name == "face")
            key = next((q.name for q in face_el.props if q.count_dtype is not None), None)
        if key is not None:
            faces = _triangles(face[key], len(pts), p)
    return ObjectModel(pts=pts, faces=faces, normals=normals, colors=colors)


def save_ply(path: str | Path, model: ObjectModel) -> None:
    """Write a model as binary little-endian PLY (atomic).

    Vertex coordinates and normals are stored as float32, as in the BOP models (about 7
    significant digits: 0.1 µm at 1 m). Colours are uchar, faces ``list uchar int
    vertex_indices``. A point cloud (no faces) gets no face element.

    Args:
        path: Destination.
        model: The model.
    """
    pts = model.pts
    n = len(pts)
    fields: list[tuple[str, str]] = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if model.normals is not None:
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    if model.colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    vert = np.empty(n, dtype=np.dtype(fields))
    for i, k in enumerate("xyz"):
        vert[k] = pts[:, i]
    if model.normals is not None:
        for i, k in enumerate(("nx", "ny", "nz")):
            vert[k] = model.normals[:, i]
    if model.colors is not None:
        for i, k in enumerate(("red", "green", "blue")):
            vert[k] = model.colors[:, i]
    ply_type = {"<f4": "float", "u1": "uchar"}
    header = ["ply", "format binary_little_endian 1.0", "comment created by bopsurg"]
    header.append(f"element vertex {n}")
    header += [f"property {ply_type[t]} {name}" for name, t in fields]
    faces = model.faces
    if len(faces):
        if faces.max() > np.iinfo(np.int32).max:
            raise ShapeError("vertex index does not fit in a PLY int", field="faces")
        header += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    header.append("end_header")
    face_rec = np.empty(len(faces), dtype=np.dtype([("n", "u1"), ("v", "<i4", (3,))]))
    face_rec["n"] = 3
    face_rec["v"] = faces
    data = ("\n".join(header) + "\n").encode("ascii") + vert.tobytes() + face_rec.tobytes()
    write_bytes(path, data)


# --------------------------------------------------------------------------- model info


def _pairwise_max(pts: F64) -> float:
    """Largest distance between two of ``pts``, in blocks to bound memory."""
    best = 0.0
    block = max(1, 2_000_000 // max(len(pts), 1))
    for start in range(0, len(pts), block):
        chunk = pts[start : start + block]
        d2 = ((chunk[:, None, :] - pts[None, :, :]) ** 2).sum(axis=2)
        best = max(best, float(d2.max()))
    return math.sqrt(best)


def _extreme_points(pts: F64) -> F64:
    """A subset of ``pts`` that contains both ends of every diameter (hull vertices)."""
    if len(pts) <= 4:
        return pts
    # scipy on first use: reading models (every 'bopsurg eval') needs no Qhull.
    from scipy.spatial import ConvexHull, QhullError

    hull: F64
    try:
        hull = pts[ConvexHull(pts).vertices]
        return hull
    except QhullError:
        pass
    # Degenerate (flat or collinear): take the hull in the plane/line the points span.
    centred = pts - pts.mean(axis=0)
    _, s, vt = np.linalg.svd(centred, full_matrices=False)
    rank = int(np.sum(s > s[0] * 1e-12)) if s[0] > 0 else 0
    if rank == 0:
        return pts[:1]
    coords = centred @ vt[:rank].T
    if rank == 1:
        return pts[[int(coords.argmin()), int(coords.argmax())]]
    try:
        hull = pts[ConvexHull(coords[:, :2]).vertices]
        return hull
    except QhullError:
        return pts


def compute_model_info(pts: ArrayLike) -> dict[str, float]:
    """Diameter and bounding box of a model, as ``scripts/calc_model_info.py`` computes them.

    The diameter is exact (the reference's all-pairs maximum): the two farthest vertices lie
    on the convex hull, so only hull vertices are compared.

    Args:
        pts: (V, 3) vertices in mm.

    Returns:
        ``{"diameter", "min_x", "min_y", "min_z", "size_x", "size_y", "size_z"}`` in mm.
    """
    p = np.asarray(pts, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) == 0:
        raise ShapeError(f"expected shape (V, 3) with V >= 1, got {p.shape}", field="pts")
    if not np.all(np.isfinite(p)):
        raise ShapeError("contains NaN or inf", field="pts")
    lo, hi = p.min(axis=0), p.max(axis=0)
    size = hi - lo
    return {
        "diameter": _pairwise_max(_extreme_points(p)),
        "min_x": float(lo[0]),
        "min_y": float(lo[1]),
        "min_z": float(lo[2]),
        "size_x": float(size[0]),
        "size_y": float(size[1]),
        "size_z": float(size[2]),
    }


def _check_discrete(value: Any, where: str, issues: Issues) -> None:
    syms = get_list(value, where, issues, "a list of 4x4 transforms")
    for i, sym in enumerate(syms or []):
        flat = sym
        if isinstance(sym, list) and len(sym) == 4 and all(isinstance(r, list) for r in sym):
            flat = [v for row in sym for v in row]  # a nested 4x4, which the reference reshapes
        get_floats(flat, 16, f"{where}/{i}", issues, what=" (4x4 row-major, t in mm)")


def _check_continuous(value: Any, where: str, issues: Issues) -> None:
    syms = get_list(value, where, issues, "a list of {axis, offset}")
    for i, sym in enumerate(syms or []):
        d = get_dict(sym, f"{where}/{i}", issues, "a continuous symmetry {axis, offset}")
        if d is None:
            continue
        for key in ("axis", "offset"):
            if key not in d:
                issues("missing", f"{where}/{i}/{key}")
                continue
            v = get_floats(d[key], 3, f"{where}/{i}/{key}", issues)
            if key == "axis" and v is not None and not np.any(v != 0):
                issues("axis must be non-zero", f"{where}/{i}/axis")


def parse_models_info(content: Any, issues: Issues) -> dict[int, dict[str, Any]]:
    """Validate decoded ``models_info.json`` content; bad entries are left out."""
    out: dict[int, dict[str, Any]] = {}
    top = get_dict(content, None, issues, "a mapping from obj_id to model information")
    for key, entry in (top or {}).items():
        obj_id = id_key(key, str(key), issues, "obj_id")
        if obj_id is None:
            continue
        n_before = len(issues)
        d = get_dict(entry, str(obj_id), issues, "model information")
        if d is None:
            continue
        if "diameter" not in d:
            issues("missing", f"{obj_id}/diameter")
        else:
            dia = get_float(d["diameter"], f"{obj_id}/diameter", issues)
            if dia is not None and dia <= 0:
                issues(f"must be > 0, got {dia}", f"{obj_id}/diameter")
        for k in ("min_x", "min_y", "min_z", "size_x", "size_y", "size_z"):
            if k in d:
                get_float(d[k], f"{obj_id}/{k}", issues)
        if "symmetries_discrete" in d:
            _check_discrete(d["symmetries_discrete"], f"{obj_id}/symmetries_discrete", issues)
        if "symmetries_continuous" in d:
            _check_continuous(d["symmetries_continuous"], f"{obj_id}/symmetries_continuous", issues)
        if len(issues) == n_before:
            out[obj_id] = d
    return dict(sorted(out.items()))


def load_models_info(path: str | Path) -> dict[int, dict[str, Any]]:
    """Load and validate ``models_info.json``.

    Args:
        path: The file.

    Returns:
        obj_id → the entry as stored (``diameter`` etc. as numbers, symmetries as lists).

    Raises:
        DatasetError: Missing or malformed file; an entry without a finite positive
            ``diameter``; a discrete symmetry that is not 16 numbers; a continuous symmetry
            without a 3-number non-zero ``axis`` and 3-number ``offset``.
    """
    return parse_models_info(load_json(path, keys_to_int=True), Issues(path))


def save_models_info(path: str | Path, infos: Mapping[int, Mapping[str, Any]]) -> None:
    """Write ``models_info.json`` in the reference layout (atomic).

    Args:
        path: Destination.
        infos: obj_id → entry (numpy values are converted to Python numbers and lists).
    """
    save_json(path, {int(k): dict(v) for k, v in infos.items()})

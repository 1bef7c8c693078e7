"""The user's needle mesh as the rendered and annotated needle (``generate --object-model``).

Recordings pose *bopsurg's* needle (:func:`bopsurg.needle.needle_mesh` of the scene's
:class:`~bopsurg.needle.NeedleSpec`: arc in the model XY plane about the origin, tail on +X):
the replayed bag, the grasp offsets and the driving about the arc centre all refer to that
frame. A user's mesh has a model frame of its own. Both needles are fitted with
:func:`bopsurg.needle.fit_needle` and the rigid map that lays the user's arc onto the recorded
one (:func:`bopsurg.model_frames.arc_alignment`: centres, normals and arc middles coincide,
tail-to-tip kept) places the user's mesh where the recorded needle is::

    T_world_model = T_world_needle @ T_needle_model      (T_needle_model from the arcs)

so the motion stays the recorded one, while the rendered geometry, ``models/obj_000001.ply``,
models_info and every GT pose are the user's mesh and its frame.

Scale: the user's needle defines the geometry. Within :data:`RADIUS_RTOL` of the recorded
radius it is placed silently (one INFO line); beyond it, still placed by its arc centre and
plane (turning about the centre keeps it on its own arc) with one WARNING line saying how far
the jaws are off its wire; a radius that differs by more than :data:`UNIT_RATIO` times is
taken for a unit error (BOP models are in mm) and refused.
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from bopsurg.bop.meshes import ObjectModel, load_ply
from bopsurg.errors import InputError, ModelError
from bopsurg.model_frames import RADIUS_RTOL, arc_alignment
from bopsurg.needle import NeedleArc, NeedleSpec, fit_needle, needle_mesh, needle_model_info

F64 = NDArray[np.float64]

#: A fitted radius this many times larger or smaller than the recorded needle's is a unit
#: error (a mesh in metres or centimetres), not another needle.
UNIT_RATIO = 5.0


@dataclass(frozen=True, eq=False)
class NeedleModel:
    """A user's needle mesh and where it sits on the recorded needle.

    Attributes:
        model: The mesh (vertices mm, in its own model frame).
        T_needle_model: (4, 4) pose of the mesh's model frame in the recorded needle's frame,
            m (R row-major): ``x_needle = R x_model + t``.
        arc: The arc fitted to the mesh (mm, its model frame).
        recorded: The arc of the recorded needle (mm, bopsurg's needle frame).
        path: The mesh file, resolved.
        sha256: The file's SHA-256.
    """

    model: ObjectModel
    T_needle_model: F64
    arc: NeedleArc
    recorded: NeedleArc
    path: str
    sha256: str

    @property
    def radius_rel(self) -> float:
        """Relative difference of the fitted radius from the recorded needle's."""
        return (self.arc.radius - self.recorded.radius) / self.recorded.radius

    @property
    def off_scale(self) -> bool:
        """The radius differs from the recorded needle's beyond :data:`RADIUS_RTOL`."""
        return abs(self.radius_rel) > RADIUS_RTOL

    def describe(self) -> str:
        """One line: the fitted arc and how the mesh was placed on the recorded needle."""
        a, r = self.arc, self.recorded
        fitted = (
            f"{self.path}: fitted arc radius {a.radius:.2f} mm, {a.extent_deg:.1f} deg, "
            f"wire Ø {2 * a.wire_radius:.2f} mm (rms {a.rms_mm:.3f} mm)"
        )
        if not self.off_scale:
            return (
                f"{fitted}; placed on the recorded needle (radius {r.radius:.2f} mm, "
                f"{r.extent_deg:.1f} deg) through the fitted arcs"
            )
        return (
            f"{fitted}: {100 * self.radius_rel:+.0f} % from the recorded needle's "
            f"{r.radius:.2f} mm (tolerance {100 * RADIUS_RTOL:.0f} %); rendered and annotated "
            "at its own size with its arc centre, plane and middle on the recorded needle's, "
            f"so driving turns it along its own arc, but the jaws hold it "
            f"{abs(a.radius - r.radius):.2f} mm off its wire"
        )

    def model_info(self) -> dict[str, Any]:
        """``models_info`` entry: diameter, box, and the fitted tip, tail and plane normal."""
        return needle_model_info(self.model, self.arc)

    def record(self) -> dict[str, str]:
        """What the generation record holds: ``{"path": ..., "sha256": ...}``."""
        return {"path": self.path, "sha256": self.sha256}


def load_needle_model(
    path: str | Path, needle: NeedleSpec | None = None, *, sha256: str | None = None
) -> NeedleModel:
    """Load a needle mesh (PLY, mm), fit its arc and place it on the recorded needle.

    Args:
        path: PLY file (BOP: vertices in mm).
        needle: Geometry of the recorded needle (default :class:`NeedleSpec`).
        sha256: When given, the file must still have this checksum (a resumed generation).

    Returns:
        The mesh with its pose in the recorded needle's frame.

    Raises:
        ModelError: Missing or unreadable file, no faces, not a needle, or a radius that
            says the file is not in mm; one line naming the file.
        InputError: The file changed since the generation was started (``sha256``).
    """
    p = Path(path).resolve()
    model = load_ply(p)  # one-line ModelError for missing / unreadable / malformed files
    digest = hashlib.sha256(p.read_bytes()).hexdigest()
    if sha256 is not None and digest != sha256:
        raise InputError(
            f"the object model changed since this dataset was started (sha256 {digest[:12]}…, "
            f"recorded {sha256[:12]}…)",
            path=p,
        )
    if model.faces is None or len(model.faces) == 0:
        raise ModelError("not a mesh: the PLY has no faces (a needle mesh is needed)", path=p)
    arc = fit_needle(model, name=str(p))  # one-line ModelError: not a needle
    recorded = fit_needle(needle_mesh(needle or NeedleSpec()), name="the recorded needle")
    ratio = arc.radius / recorded.radius
    if not 1.0 / UNIT_RATIO <= ratio <= UNIT_RATIO:
        raise ModelError(
            f"fitted needle radius {arc.radius:.4g} mm is {ratio:.3g} times the recorded "
            f"needle's {recorded.radius:.2f} mm: BOP models are in mm (is the mesh in metres "
            "or centimetres?)",
            path=p,
        )
    # Any radius and extent within the unit check: the user's needle defines the geometry.
    A, a = arc_alignment(arc, recorded, radius_rtol=np.inf, extent_tol_deg=np.inf)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = A, a * 1e-3
    return NeedleModel(model, T, arc, recorded, str(p), digest)


def needle_spec_of_mesh(path: str | Path) -> tuple[NeedleSpec, NeedleModel]:
    """The :class:`NeedleSpec` of a user's needle mesh (``record --object-model``): its fitted
    centre-line radius, wire diameter and extent (tip taper as bopsurg's), so an episode can be
    planned (grasps on its wire, driving along its arc) for that needle.

    Raises:
        ModelError: See :func:`load_needle_model`; also an arc too short for the spec.
    """
    model = load_needle_model(path)
    arc = model.arc
    tip = NeedleSpec.tip_deg
    if arc.extent_deg <= tip:
        raise ModelError(
            f"fitted arc of {arc.extent_deg:.1f} deg is shorter than a needle tip ({tip} deg)",
            path=model.path,
        )
    spec = NeedleSpec(
        arc_radius=round(float(arc.radius), 4),
        wire_diameter=round(float(2 * arc.wire_radius), 4),
        body_deg=round(float(arc.extent_deg) - tip, 3),
    )
    return spec, model


def needle_model_from_config(value: Any, needle: NeedleSpec) -> NeedleModel:
    """The ``object_model`` scene key of a generation: a path, or ``{"path", "sha256"}``.

    Raises:
        TypeError: Neither form.
        ModelError, InputError: See :func:`load_needle_model`.
    """
    if isinstance(value, str | Path):
        return load_needle_model(value, needle)
    if isinstance(value, Mapping) and isinstance(value.get("path"), str):
        sha = value.get("sha256")
        sha = sha if isinstance(sha, str) else None
        return load_needle_model(value["path"], needle, sha256=sha)
    raise TypeError(f"'object_model' must be a PLY path or {{path, sha256}}, got {value!r}")


__all__ = [
    "UNIT_RATIO",
    "NeedleModel",
    "load_needle_model",
    "needle_model_from_config",
    "needle_spec_of_mesh",
]

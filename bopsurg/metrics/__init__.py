"""Batched BOP pose errors that reproduce ``bop_toolkit_lib.pose_error``, only much faster.

Every pose error takes N (estimate, GT) pairs at once (``R`` (N, 3, 3), ``t`` (N, 3) in mm; a
single pose or a batch of one broadcasts) and returns a float64 (N,) array equal to the
reference toolkit's per-pose value to float64 rounding (≤ 1e-9 relative, absolute near 0).

=================  ==========================================================  ======
function           definition (``P x = R x + t``, ``π`` pinhole projection)      unit
=================  ==========================================================  ======
:func:`re`         ``acos((tr(R_e R_g⁻¹) − 1) / 2)``                            deg
:func:`te`         ``‖t_g − t_e‖``                                              mm
:func:`mssd`       ``min_s max_x ‖P_e x − P_g (R_s x + t_s)‖`` (BOP19)           mm
:func:`mspd`       ``min_s max_x ‖π(P_e x) − π(P_g (R_s x + t_s))‖`` (BOP19)      px
:func:`add`        ``mean_x ‖P_e x − P_g x‖`` (ADD)                             mm
:func:`adi`        ``mean_x min_y ‖P_g x − P_e y‖`` (ADD-S / ADI)               mm
:func:`proj`       ``mean_x ‖π(P_e x) − π(P_g x)‖``                             px
:func:`vsd`        visible surface discrepancy, one value per τ (BOP19)         [0, 1]
=================  ==========================================================  ======

Helpers: :func:`symmetry_transforms` (symmetry sets from ``models_info.json``, the reference's
set and order), :func:`estimate_visib_mask` (visible-surface masks, ``bop19``/``bop18``) and
:func:`hull_vertices` (reusable MSSD candidates). The GPU path lives in
:mod:`bopsurg.metrics.torch_backend` (imports torch when called, never on import), the
per-pose oracle in :mod:`bopsurg.metrics.reference` (tests and benchmarks only).
"""

from typing import TYPE_CHECKING

from bopsurg._lazy import lazy_exports

if TYPE_CHECKING:
    from bopsurg.metrics.point_subsets import hull_vertices
    from bopsurg.metrics.pose_error import add, adi, mspd, mssd, proj, re, te
    from bopsurg.metrics.symmetry import Symmetries, as_symmetries, symmetry_transforms
    from bopsurg.metrics.visibility_mask import (
        estimate_visib_mask,
        estimate_visib_mask_est,
        estimate_visib_mask_gt,
    )
    from bopsurg.metrics.vsd import vsd

#: The module of each public name, imported on first access (:mod:`bopsurg._lazy`): the
#: registry's names and help lines (``bopsurg eval``'s parser) load no numpy.
_HOME: dict[str, str] = {
    "Symmetries": ".symmetry",
    "add": ".pose_error",
    "adi": ".pose_error",
    "as_symmetries": ".symmetry",
    "estimate_visib_mask": ".visibility_mask",
    "estimate_visib_mask_est": ".visibility_mask",
    "estimate_visib_mask_gt": ".visibility_mask",
    "hull_vertices": ".point_subsets",
    "mspd": ".pose_error",
    "mssd": ".pose_error",
    "proj": ".pose_error",
    "re": ".pose_error",
    "symmetry_transforms": ".symmetry",
    "te": ".pose_error",
    "vsd": ".vsd",
}

__all__ = [
    "Symmetries",
    "add",
    "adi",
    "as_symmetries",
    "estimate_visib_mask",
    "estimate_visib_mask_est",
    "estimate_visib_mask_gt",
    "hull_vertices",
    "mspd",
    "mssd",
    "proj",
    "re",
    "symmetry_transforms",
    "te",
    "vsd",
]

lazy_exports(__name__, _HOME)

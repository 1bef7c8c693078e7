"""The per-instance pose metrics of ``bopsurg eval``, declared once.

Each :class:`Metric` names its function, unit and inputs; ``bopsurg eval`` (its dispatch, the
``errors.csv`` columns, ``--metrics`` and ``--help``), the paper's table
(:mod:`bopsurg.evaluation.summary`) and the rerun recording (:mod:`bopsurg.viz.rerun_log`) all
read :data:`METRICS`, so a new metric is one function plus one entry here.

A metric function takes a :class:`PairBatch` (N estimate/GT pairs of one object, BOP units) and
returns an (N,) float64 array. Only the inputs a metric declares in ``needs`` are loaded into
the batch; the others are None.

VSD is not listed: it needs the scene's depth image and a renderer plugin, enters only the
BOP19 scores (:mod:`bopsurg.evaluation.bop19`) and is one value per tolerance τ, not per pair.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the metrics' names and help lines (eval's parser) load no numpy
    import numpy as np
    from numpy.typing import NDArray

    from bopsurg.metrics.symmetry import Symmetries

    F64 = NDArray[np.float64]


class Need(Enum):
    """An input a metric reads besides the two poses."""

    #: Model vertices (V, 3), mm.
    MODEL_POINTS = "model points"
    #: Symmetry transformations of the object (``models_info.json``).
    SYMMETRIES = "symmetries"
    #: The GT image's camera matrix (N, 3, 3), px.
    CAMERA = "K"


@dataclass(frozen=True)
class PairBatch:
    """N (estimate, GT) pairs of one object, with the inputs the metrics asked for.

    Attributes:
        R_est, R_gt: (N, 3, 3) rotations, row-major, model to camera.
        t_est, t_gt: (N, 3) translations, mm.
        pts: (V, 3) model vertices, mm (:attr:`Need.MODEL_POINTS`).
        syms: Symmetry transformations (:attr:`Need.SYMMETRIES`).
        K: (N, 3, 3) camera matrices of the GT images, px (:attr:`Need.CAMERA`).
    """

    R_est: F64
    t_est: F64
    R_gt: F64
    t_gt: F64
    pts: F64 | None = None
    syms: Symmetries | None = None
    K: F64 | None = None


@dataclass(frozen=True)
class Metric:
    """One per-instance pose metric.

    Attributes:
        name: Column name in ``errors.csv`` and key in ``--metrics``.
        label: How tables and plots title it, e.g. ``"ADD-S"``.
        unit: Unit of its values (``deg``, ``mm``, ``px``).
        description: One line for ``bopsurg eval --help``.
        function: ``PairBatch -> (N,) float64``.
        needs: Inputs it reads besides the poses.
        in_table: A row of the paper's table (and a histogram in the rerun recording).
        in_rerun: A per-frame time series in the rerun recording.
        auc: The summary reports its AUC over 0 … 0.1 × diameter (a distance in mm).
    """

    name: str
    label: str
    unit: str
    description: str
    function: Callable[[PairBatch], F64]
    needs: frozenset[Need] = frozenset()
    in_table: bool = False
    in_rerun: bool = False
    auc: bool = False

    def heading(self) -> str:
        """``"LABEL [unit]"``, the title of a table row or a plot axis."""
        return f"{self.label} [{self.unit}]"


def _re(b: PairBatch) -> F64:
    from bopsurg.metrics.pose_error import re

    return re(b.R_est, b.R_gt)


def _te(b: PairBatch) -> F64:
    from bopsurg.metrics.pose_error import te

    return te(b.t_est, b.t_gt)


def _mssd(b: PairBatch) -> F64:
    assert b.pts is not None
    from bopsurg.metrics.pose_error import mssd

    return mssd(b.R_est, b.t_est, b.R_gt, b.t_gt, b.pts, b.syms)


def _mspd(b: PairBatch) -> F64:
    assert b.pts is not None
    assert b.K is not None
    from bopsurg.metrics.pose_error import mspd

    return mspd(b.R_est, b.t_est, b.R_gt, b.t_gt, b.K, b.pts, b.syms)


def _add(b: PairBatch) -> F64:
    assert b.pts is not None
    from bopsurg.metrics.pose_error import add

    return add(b.R_est, b.t_est, b.R_gt, b.t_gt, b.pts)


def _adi(b: PairBatch) -> F64:
    assert b.pts is not None
    from bopsurg.metrics.pose_error import adi

    return adi(b.R_est, b.t_est, b.R_gt, b.t_gt, b.pts)


_PTS = Need.MODEL_POINTS
_SYM = Need.SYMMETRIES

#: The metrics of ``errors.csv``, in column order. Everything reads it when it runs, so an
#: entry added here (or by a test) is evaluated, written and shown everywhere.
METRICS: dict[str, Metric] = {
    m.name: m
    for m in (
        Metric("re", "RE", "deg", "rotation error", _re, in_table=True, in_rerun=True),
        Metric("te", "TE", "mm", "translation error", _te, in_table=True, in_rerun=True),
        Metric(
            "mssd", "MSSD", "mm", "maximum symmetry-aware surface distance", _mssd,
            frozenset({_PTS, _SYM}), in_table=True, in_rerun=True,
        ),
        Metric(
            "mspd", "MSPD", "px", "maximum symmetry-aware projection distance", _mspd,
            frozenset({_PTS, _SYM, Need.CAMERA}), in_rerun=True,
        ),
        Metric("add", "ADD", "mm", "average distance", _add, frozenset({_PTS}), auc=True),
        Metric(
            "adi", "ADD-S", "mm",
            "average closest-point distance (the costly one, ~0.5 us per vertex and estimate)",
            _adi, frozenset({_PTS}), auc=True,
        ),
    )
}  # fmt: skip


def metric(name: str) -> Metric:
    """The registered metric ``name``.

    Raises:
        KeyError: Not registered (the message lists the registered names).
    """
    try:
        return METRICS[name]
    except KeyError:
        raise KeyError(f"unknown metric {name!r}; choose from {', '.join(METRICS)}") from None


def table_metrics() -> tuple[Metric, ...]:
    """The rows of the paper's table, in registry order."""
    return tuple(m for m in METRICS.values() if m.in_table)


def rerun_metrics() -> tuple[Metric, ...]:
    """The per-frame series of the rerun recording, in registry order."""
    return tuple(m for m in METRICS.values() if m.in_rerun)


def help_lines(indent: str = "") -> list[str]:
    """One line per metric, ``name [unit]  LABEL: description``, for ``--help`` texts."""
    width = max(len(f"{m.name} [{m.unit}]") for m in METRICS.values())
    return [
        f"{indent}{m.name + ' [' + m.unit + ']':<{width}}  {m.label}: {m.description}"
        for m in METRICS.values()
    ]

"""Per-pose reference implementation of the BOP pose errors: the oracle for tests and the bench.

This module is **not for production use**: it evaluates one pose pair per call with plain numpy,
written from the definitions of ``bop_toolkit_lib.pose_error`` (thodan/bop_toolkit) and
mirroring their operation order (``transform_pts_Rt`` = ``R.dot(pts.T) + t``, ``project_pts``
with ``P = K.dot([R | t])`` and a homogeneous divide of all three rows, a Python loop over the
symmetries with ``np.linalg.norm(..., axis=1).max()`` and ``min`` over a list, a new
``cKDTree`` per call for ADD-S). The batched functions of :mod:`bopsurg.metrics` must agree with
it to 1e-9 (relative, or absolute near 0); the bench times it as the baseline.

Poses: ``R`` (3, 3), ``t`` (3,) or (3, 1) in mm, ``K`` (3, 3), ``pts`` (V, 3) in mm; symmetry
sets as ``(R_sym (S, 3, 3), t_sym (S, 3))`` or the reference's list of ``{"R", "t"}`` dicts.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import spatial

from bopsurg.geometry import depth_to_distance, rotation_about_axis

F64 = NDArray[np.float64]
SymList = list[dict[str, F64]]


def _col(t: ArrayLike) -> F64:
    return np.asarray(t, dtype=np.float64).reshape(3, 1)


def _sym_list(syms: Any) -> SymList:
    """Symmetries as the reference's list of ``{"R": (3, 3), "t": (3, 1)}`` dicts."""
    if syms is None:
        return [{"R": np.eye(3), "t": np.zeros((3, 1))}]
    if isinstance(syms, (list, tuple)) and syms and isinstance(syms[0], Mapping):
        return [{"R": np.asarray(s["R"], dtype=np.float64), "t": _col(s["t"])} for s in syms]
    R_sym, t_sym = syms
    return [{"R": np.asarray(R), "t": _col(t)} for R, t in zip(R_sym, t_sym, strict=True)]


def transform_pts_Rt(pts: F64, R: F64, t: F64) -> F64:  # noqa: N802 - the reference name
    """``(R @ pts.T + t).T``: (V, 3) mm, as ``bop_toolkit_lib.misc.transform_pts_Rt``."""
    pts_t = R.dot(pts.T) + t.reshape((3, 1))
    result: F64 = pts_t.T
    return result


def project_pts(pts: F64, K: F64, R: F64, t: F64) -> F64:
    """(V, 2) px, as ``bop_toolkit_lib.misc.project_pts`` (no z check; z = 0 gives inf/nan)."""
    P = K.dot(np.hstack((R, t.reshape(3, 1))))
    pts_h = np.hstack((pts, np.ones((pts.shape[0], 1))))
    pts_im = P.dot(pts_h.T)
    with np.errstate(divide="ignore", invalid="ignore"):
        pts_im /= pts_im[2, :]
    result: F64 = pts_im[:2, :].T
    return result


def symmetry_transforms_ref(model_info: Mapping[str, Any], max_sym_disc_step: float) -> SymList:
    """``misc.get_symmetry_transformations``: list of ``{"R": (3, 3), "t": (3, 1) mm}``."""
    trans_disc = [{"R": np.eye(3), "t": np.array([[0, 0, 0]]).T}]
    for sym in model_info.get("symmetries_discrete", []):
        sym_4x4 = np.reshape(sym, (4, 4))
        trans_disc.append({"R": sym_4x4[:3, :3], "t": sym_4x4[:3, 3].reshape((3, 1))})
    trans_cont = []
    for sym in model_info.get("symmetries_continuous", []):
        axis = np.array(sym["axis"])
        offset = np.array(sym["offset"]).reshape((3, 1))
        discrete_steps_count = int(np.ceil(np.pi / max_sym_disc_step))
        discrete_step = 2.0 * np.pi / discrete_steps_count
        for i in range(0, discrete_steps_count):
            R = rotation_about_axis(axis, i * discrete_step)
            trans_cont.append({"R": R, "t": -R.dot(offset) + offset})
    trans = []
    for tran_disc in trans_disc:
        if len(trans_cont):
            for tran_cont in trans_cont:
                R = tran_cont["R"].dot(tran_disc["R"])
                t = tran_cont["R"].dot(tran_disc["t"]) + tran_cont["t"]
                trans.append({"R": R, "t": t})
        else:
            trans.append(tran_disc)
    return trans


def re_ref(R_est: ArrayLike, R_gt: ArrayLike) -> float:
    """Rotation error in degrees, ``acos((tr(R_e R_g⁻¹) − 1) / 2)`` clipped to [−1, 1]."""
    R_e = np.asarray(R_est, dtype=np.float64)
    R_g = np.asarray(R_gt, dtype=np.float64)
    error_cos = float(0.5 * (np.trace(R_e.dot(np.linalg.inv(R_g))) - 1.0))
    error_cos = min(1.0, max(-1.0, error_cos))
    return 180.0 * math.acos(error_cos) / np.pi


def te_ref(t_est: ArrayLike, t_gt: ArrayLike) -> float:
    """Translation error in mm, ``‖t_g − t_e‖`` (both taken as 3-vectors)."""
    return float(np.linalg.norm(_col(t_gt) - _col(t_est)))


def mssd_ref(
    R_est: ArrayLike,
    t_est: ArrayLike,
    R_gt: ArrayLike,
    t_gt: ArrayLike,
    pts: ArrayLike,
    syms: Any = None,
) -> float:
    """MSSD in mm: min over symmetries of the max vertex distance (reference loop)."""
    pts_ = np.asarray(pts, dtype=np.float64)
    R_e, R_g = np.asarray(R_est, dtype=np.float64), np.asarray(R_gt, dtype=np.float64)
    t_e, t_g = _col(t_est), _col(t_gt)
    pts_est = transform_pts_Rt(pts_, R_e, t_e)
    es = []
    for sym in _sym_list(syms):
        R_gt_sym = R_g.dot(sym["R"])
        t_gt_sym = R_g.dot(sym["t"]) + t_g
        pts_gt_sym = transform_pts_Rt(pts_, R_gt_sym, t_gt_sym)
        es.append(np.linalg.norm(pts_est - pts_gt_sym, axis=1).max())
    return float(min(es))


def mspd_ref(
    R_est: ArrayLike,
    t_est: ArrayLike,
    R_gt: ArrayLike,
    t_gt: ArrayLike,
    K: ArrayLike,
    pts: ArrayLike,
    syms: Any = None,
) -> float:
    """MSPD in px: min over symmetries of the max projection distance (reference loop).

    As in the reference, ``np.max`` propagates NaN and Python's ``min`` keeps the first value
    when it is NaN, so the result is NaN exactly when the first (identity) term is NaN.
    """
    pts_ = np.asarray(pts, dtype=np.float64)
    K_ = np.asarray(K, dtype=np.float64)
    R_e, R_g = np.asarray(R_est, dtype=np.float64), np.asarray(R_gt, dtype=np.float64)
    t_e, t_g = _col(t_est), _col(t_gt)
    proj_est = project_pts(pts_, K_, R_e, t_e)
    es = []
    with np.errstate(invalid="ignore", over="ignore"):
        for sym in _sym_list(syms):
            R_gt_sym = R_g.dot(sym["R"])
            t_gt_sym = R_g.dot(sym["t"]) + t_g
            proj_gt_sym = project_pts(pts_, K_, R_gt_sym, t_gt_sym)
            es.append(np.linalg.norm(proj_est - proj_gt_sym, axis=1).max())
    return float(min(es))


def add_ref(
    R_est: ArrayLike, t_est: ArrayLike, R_gt: ArrayLike, t_gt: ArrayLike, pts: ArrayLike
) -> float:
    """ADD in mm: mean vertex distance between the two poses."""
    pts_ = np.asarray(pts, dtype=np.float64)
    pts_est = transform_pts_Rt(pts_, np.asarray(R_est, dtype=np.float64), _col(t_est))
    pts_gt = transform_pts_Rt(pts_, np.asarray(R_gt, dtype=np.float64), _col(t_gt))
    return float(np.linalg.norm(pts_est - pts_gt, axis=1).mean())


def adi_ref(
    R_est: ArrayLike, t_est: ArrayLike, R_gt: ArrayLike, t_gt: ArrayLike, pts: ArrayLike
) -> float:
    """ADD-S (ADI) in mm: mean over GT-posed vertices of the nearest estimate-posed vertex."""
    pts_ = np.asarray(pts, dtype=np.float64)
    pts_est = transform_pts_Rt(pts_, np.asarray(R_est, dtype=np.float64), _col(t_est))
    pts_gt = transform_pts_Rt(pts_, np.asarray(R_gt, dtype=np.float64), _col(t_gt))
    nn_index = spatial.cKDTree(pts_est)
    nn_dists, _ = nn_index.query(pts_gt, k=1)
    return float(nn_dists.mean())


def proj_ref(
    R_est: ArrayLike,
    t_est: ArrayLike,
    R_gt: ArrayLike,
    t_gt: ArrayLike,
    K: ArrayLike,
    pts: ArrayLike,
) -> float:
    """Mean projection distance in px (Brachmann et al., CVPR'16)."""
    pts_ = np.asarray(pts, dtype=np.float64)
    K_ = np.asarray(K, dtype=np.float64)
    proj_est = project_pts(pts_, K_, np.asarray(R_est, dtype=np.float64), _col(t_est))
    proj_gt = project_pts(pts_, K_, np.asarray(R_gt, dtype=np.float64), _col(t_gt))
    with np.errstate(invalid="ignore", over="ignore"):
        return float(np.linalg.norm(proj_est - proj_gt, axis=1).mean())


def _visib_ref(d_test: F64, d_model: F64, delta: float) -> NDArray[np.bool_]:
    """``visibility._estimate_visib_mask`` in mode ``bop19``."""
    d_test = np.asarray(d_test)
    d_model = np.asarray(d_model)
    model_mask = d_model > 0
    d_diff = d_model.astype(np.float32) - d_test.astype(np.float32)
    visib_mask = np.logical_and(np.logical_or(d_diff <= delta, d_test == 0), model_mask)
    result: NDArray[np.bool_] = visib_mask
    return result


def vsd_ref(
    depth_test: ArrayLike,
    depth_est: ArrayLike,
    depth_gt: ArrayLike,
    K: ArrayLike,
    delta: float,
    taus: Sequence[float],
    normalized_by_diameter: bool,
    diameter: float,
    cost_type: str = "step",
) -> list[float]:
    """VSD for each τ, from the test depth and the two rendered depths (mm, 0 = background)."""
    K_ = np.asarray(K, dtype=np.float64)
    dist_test = depth_to_distance(depth_test, K_)
    dist_gt = depth_to_distance(depth_gt, K_)
    dist_est = depth_to_distance(depth_est, K_)
    visib_gt = _visib_ref(dist_test, dist_gt, delta)
    visib_est = _visib_ref(dist_test, dist_est, delta)
    visib_est = np.logical_or(visib_est, np.logical_and(visib_gt, dist_est > 0))
    visib_inter = np.logical_and(visib_gt, visib_est)
    visib_union = np.logical_or(visib_gt, visib_est)
    visib_union_count = visib_union.sum()
    visib_comp_count = visib_union_count - visib_inter.sum()
    dists = np.abs(dist_gt[visib_inter] - dist_est[visib_inter])
    if normalized_by_diameter:
        dists /= diameter
    if visib_union_count == 0:
        return [1.0] * len(taus)
    errors = []
    for tau in taus:
        costs: NDArray[np.bool_] | F64
        if cost_type == "step":
            costs = dists >= tau
        elif cost_type == "tlinear":
            costs = dists / tau
            costs[costs > 1.0] = 1.0
        else:
            raise ValueError("Unknown pixel matching cost.")
        errors.append(float((np.sum(costs) + visib_comp_count) / float(visib_union_count)))
    return errors

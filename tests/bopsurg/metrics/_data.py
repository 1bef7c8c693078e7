"""Shared test data for the metrics tests: models, poses, cameras and the hypothesis profile."""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, settings
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

F64 = NDArray[np.float64]

#: Hypothesis settings for this suite: no deadline (2-core CI), few examples (runtime < 60 s).
HYP = settings(
    deadline=None,
    max_examples=40,
    suppress_health_check=[HealthCheck.too_slow],
)

#: The BOP tolerance: float64 results equal the reference to this (relative, or absolute).
RTOL = 1e-9
ATOL = 1e-9

K_CAM = np.array([[572.4, 0.0, 325.3], [0.0, 573.6, 242.0], [0.0, 0.0, 1.0]])

CONT_Z = {"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]}


def assert_close(actual: F64, expected: F64) -> None:
    """Equal to the reference within 1e-9 relative or 1e-9 absolute, NaN where it is NaN."""
    np.testing.assert_allclose(actual, expected, rtol=RTOL, atol=ATOL, equal_nan=True)


def box_model(
    rng: np.random.Generator, v: int, size: tuple[float, float, float] = (40, 30, 60)
) -> F64:
    """``v`` random points in a centred box (mm)."""
    return rng.uniform(-0.5, 0.5, (v, 3)) * np.asarray(size)


def arc_model(
    rng: np.random.Generator, v: int, radius: float = 12.0, tube: float = 0.4, span: float = np.pi
) -> F64:
    """A thin torus arc (a suture needle): points on the tube surface, mm. Not convex."""
    th = rng.uniform(0.0, span, v)
    ph = rng.uniform(0.0, 2.0 * np.pi, v)
    r = radius + tube * np.cos(ph)
    return np.stack([r * np.cos(th), r * np.sin(th), tube * np.sin(ph)], axis=1)


def random_rotations(rng: np.random.Generator, n: int) -> F64:
    return Rotation.random(n, random_state=int(rng.integers(2**31))).as_matrix()


def pose_pairs(
    rng: np.random.Generator, n: int, deg: float = 5.0, mm: float = 5.0
) -> tuple[F64, F64, F64, F64]:
    """GT poses 100-300 mm in front of the camera and estimates a few degrees/mm off them."""
    R_gt = random_rotations(rng, n)
    t_gt = np.stack(
        [rng.uniform(-40, 40, n), rng.uniform(-30, 30, n), rng.uniform(100, 300, n)], axis=1
    )
    d = Rotation.from_rotvec(rng.normal(0.0, 1.0, (n, 3)) * np.deg2rad(deg)).as_matrix()
    R_est = d @ R_gt
    t_est = t_gt + rng.normal(0.0, mm, (n, 3))
    return R_est, t_est, R_gt, t_gt

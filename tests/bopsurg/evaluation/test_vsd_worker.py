"""The VSD worker process: a failed worker says so and VSD falls back to this process (its
equality with the in-process errors on real renders is tested in test_bop19)."""

from __future__ import annotations

import numpy as np
import pytest

from bopsurg.evaluation.vsd_images import VSD_TAUS, ImageClaims, VsdJob
from bopsurg.evaluation.vsd_pairs import PendingVsd, VsdInputs
from bopsurg.evaluation.vsd_worker import VsdWorker, VsdWorkerError


def _empty_job(n_pairs: int) -> VsdJob:
    """P pairs in no image (as when no bounding-sphere projections overlap): errors are 1."""
    return VsdJob(
        images=(), models={}, obj_id=np.ones(n_pairs, dtype=np.int64),
        gt_key=np.arange(n_pairs, dtype=np.int64), R_est=np.tile(np.eye(3), (n_pairs, 1, 1)),
        t_est=np.zeros((n_pairs, 3)), R_gt=np.tile(np.eye(3), (n_pairs, 1, 1)),
        t_gt=np.zeros((n_pairs, 3)), diameter=np.ones(n_pairs), delta=15.0,
    )  # fmt: skip


def test_a_worker_answers_its_job():
    pytest.importorskip("pybullet")  # the worker loads the renderer before it answers
    worker = VsdWorker.start("pybullet")
    assert worker is not None
    worker.submit(_empty_job(3))
    np.testing.assert_array_equal(worker.result(), np.ones((len(VSD_TAUS), 3)))
    worker.close()
    with pytest.raises(VsdWorkerError, match="one job"):
        worker.submit(_empty_job(1))


def test_a_worker_without_its_renderer_fails_and_vsd_runs_here():
    worker = VsdWorker.start("no-such-renderer")
    assert worker is not None
    worker.submit(_empty_job(2))
    with pytest.raises(VsdWorkerError, match="no-such-renderer"):
        worker.result()
    worker.close()
    fallback = VsdWorker.start("no-such-renderer")
    assert fallback is not None
    inputs = VsdInputs(dataset=None, renderer=object(), worker=fallback)  # type: ignore[arg-type]
    errors = PendingVsd(_empty_job(2), inputs).result()
    np.testing.assert_array_equal(errors, np.ones((len(VSD_TAUS), 2)))
    fallback.close()


def test_close_before_a_result_ends_the_worker():
    worker = VsdWorker.start("pybullet")
    assert worker is not None
    with pytest.raises(VsdWorkerError, match="no VSD job"):
        worker.result()
    worker.close()
    assert worker._proc.returncode is not None
    worker.close()  # idempotent


@pytest.mark.parametrize("seed", range(5))
def test_claims_give_every_image_to_exactly_one_side(tmp_path, seed):
    """Front and back taken in any interleaving: each image once, front then back."""
    n = 9
    front = ImageClaims(tmp_path, n).from_front()
    back = ImageClaims(tmp_path, n).from_back()
    got: dict[str, list[int]] = {"front": [], "back": []}
    rng = np.random.default_rng(seed)
    sides = {"front": front, "back": back}
    while sides:
        name = str(rng.choice(sorted(sides)))
        i = next(sides[name], None)
        if i is None:
            del sides[name]
        else:
            got[name].append(i)
    k = len(got["front"])
    assert got["front"] == list(range(k))
    assert got["back"] == list(range(n - 1, k - 1, -1))

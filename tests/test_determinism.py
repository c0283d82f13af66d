"""rigbuild.determinism: every job's OpenCV pool and random seeds are pinned, and the two library calls that
varied between identical runs (cv2.calibrateCamera on several threads, open3d's Poisson on every hardware
thread) give one answer per input."""

from __future__ import annotations

import random
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from rigbuild.determinism import JOB_SEED, opencv_threads, setup_job


@pytest.fixture
def restore_opencv_threads():
    before = cv2.getNumThreads()
    yield
    cv2.setNumThreads(before)


def _draws() -> tuple:
    return (cv2.randu(np.zeros(4, np.float64), 0.0, 1.0).tolist(), np.random.random(4).tolist(), random.random())


def test_setup_job_sizes_opencv_to_the_job_threads_and_seeds_every_global_rng(restore_opencv_threads):
    assert setup_job(3) == {"opencv_threads": 3, "seed": JOB_SEED}
    assert cv2.getNumThreads() == 3
    first = _draws()
    _draws()  # the generators move on ...
    setup_job(1)
    assert cv2.getNumThreads() == 1
    assert _draws() == first  # ... and the next job starts them at the same place again
    setup_job(0)
    assert cv2.getNumThreads() == 1  # a job never gets fewer than one thread


def test_run_logged_pins_the_job_before_main_runs(tmp_path, restore_opencv_threads):
    from rigbuild.logs import run_logged

    cv2.setNumThreads(5)
    np.random.seed(123)
    seen = {}

    def main(smk):
        seen["threads"] = cv2.getNumThreads()
        seen["draw"] = np.random.random()

    job = SimpleNamespace(log=[str(tmp_path / "job.log")], rule="calibrate", wildcards={}, threads=2)
    run_logged(job, main)
    np.random.seed(JOB_SEED)
    assert seen == {"threads": 2, "draw": np.random.random()}
    assert "reproducibility: {'opencv_threads': 2, 'seed': 0}" in (tmp_path / "job.log").read_text()
    run_logged(SimpleNamespace(log=[], rule="calibrate", wildcards={}, threads=1), main)  # no log file: pinned too
    assert seen["threads"] == 1


def test_opencv_threads_sets_the_pool_for_the_block_and_restores_it(restore_opencv_threads):
    cv2.setNumThreads(2)
    with opencv_threads(1):
        assert cv2.getNumThreads() == 1
    assert cv2.getNumThreads() == 2
    with pytest.raises(ValueError), opencv_threads(1):
        raise ValueError("restored on an error too")
    assert cv2.getNumThreads() == 2


def _board_views(n_views: int = 8) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """A 9 x 6 board (20 mm squares) seen by a distorted 1280 x 800 camera from n_views poses."""
    gx, gy = np.meshgrid(np.arange(9) * 20.0, np.arange(6) * 20.0)
    obj = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1)
    K = np.array([[1100.0, 0, 650], [0, 1100, 390], [0, 0, 1]])
    dist = np.array([-0.12, 0.05, 0.001, -0.0005, 0.0])
    rng = np.random.default_rng(4)
    img = []
    for _ in range(n_views):
        rvec = rng.uniform(-0.4, 0.4, 3)
        tvec = np.array([-80.0, -50.0, 500.0]) + rng.uniform(-30, 30, 3)
        p = cv2.projectPoints(obj, rvec, tvec, K, dist)[0].reshape(-1, 2)
        img.append(p + rng.normal(0.0, 0.2, p.shape))
    return [obj] * n_views, img


def test_calibrate_intrinsics_gives_one_answer_whatever_opencv_threads(restore_opencv_threads):
    from rigbuild.calibrate.intrinsics import calibrate_intrinsics

    obj, img = _board_views()
    results = []
    for n in (4, 4, 4, 1):
        cv2.setNumThreads(n)
        r = calibrate_intrinsics(obj, img, (1280, 800))
        results.append(np.concatenate([r.K.ravel(), r.dist, r.t_views.ravel()]))
        assert cv2.getNumThreads() == n  # the caller's pool size is left as it was
    for other in results[1:]:
        np.testing.assert_array_equal(other, results[0])


def test_poisson_mesh_gives_one_answer_per_cloud():
    pytest.importorskip("open3d")
    from rigbuild.reconstruct.fuse import poisson_mesh

    # an oriented sphere of radius 50 mm, 3000 points
    rng = np.random.default_rng(0)
    n = rng.normal(size=(3000, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    p = 50.0 * n
    meshes = [poisson_mesh(p, n, depth=6) for _ in range(3)]
    assert len(meshes[0][1]) > 1000
    for V, F in meshes[1:]:
        np.testing.assert_array_equal(V, meshes[0][0])
        np.testing.assert_array_equal(F, meshes[0][1])

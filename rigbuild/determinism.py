"""Run-to-run reproducibility of a pipeline job: the same inputs and code give bit-identical outputs.

Two library calls were the sources of the differences between identical runs (measured on the tiny session
of tests/test_workflow_e2e.py, each rerun with the same inputs):

* ``cv2.calibrateCamera`` gives a different K / distortion (1e-9 relative, 1e-5 after the bundle
  adjustment) on every call when OpenCV's thread pool has more than one thread; one thread gives one answer.
  OpenCV sizes that pool to every CPU of the machine and ignores ``OMP_NUM_THREADS``.
  :func:`opencv_threads` runs a call on a pool of a given size (``rigbuild.calibrate.intrinsics``).
* open3d's screened Poisson (``create_from_point_cloud_poisson``) runs on every hardware thread by default
  (``n_threads=-1``, whatever ``OMP_NUM_THREADS`` or the CPU affinity say) and then gives different vertices
  on every call; ``n_threads=1`` gives one answer (``rigbuild.reconstruct.fuse.poisson_mesh``).

:func:`setup_job`, called by :func:`rigbuild.logs.run_logged` before every job, sizes OpenCV's pool to the
job's ``threads`` (so a job uses the cores Snakemake or SLURM gave it, and the same number on every
executor) and seeds the global random generators (OpenCV's, NumPy's legacy one, Python's) so that no
library drawing from them can vary between runs. The pipeline's own randomness uses explicit seeds.
"""

from __future__ import annotations

import contextlib
import random
from typing import Iterator

import numpy as np

#: the seed of the global random generators in every job (:func:`setup_job`)
JOB_SEED = 0


def setup_job(threads: int = 1, seed: int = JOB_SEED) -> dict:
    """Pin what a job's results could otherwise depend on besides its inputs.

    threads : the job's cores (Snakemake's ``threads``); OpenCV's thread pool gets that many (>= 1).
    seed : seed of OpenCV's ``cv2.theRNG``, NumPy's global ``np.random`` and Python's ``random``.
    Returns what was set: ``{"opencv_threads": n, "seed": seed}`` (the job log records it).
    """
    import cv2

    n = max(1, int(threads))
    cv2.setNumThreads(n)
    cv2.setRNGSeed(int(seed))
    np.random.seed(int(seed))
    random.seed(int(seed))
    return {"opencv_threads": n, "seed": int(seed)}


@contextlib.contextmanager
def opencv_threads(n: int) -> Iterator[None]:
    """Run the block with OpenCV's thread pool at ``n`` threads, then restore the previous size.

    For OpenCV calls whose result depends on how their parallel loops are scheduled
    (``cv2.calibrateCamera``): ``with opencv_threads(1): ...`` makes them deterministic.
    """
    import cv2

    before = cv2.getNumThreads()
    cv2.setNumThreads(int(n))
    try:
        yield
    finally:
        cv2.setNumThreads(before)

"""The calibrated world vs the ground-truth world.

Calibration puts the world in the reference camera's frame; a synthetic session's ground truth lives in
the head's frame. Errors against ground truth are measured after mapping estimates into the ground-truth
world by the similarity fitted on the camera centres (:func:`rigbuild.eval.reconstruction.align_to_ground_truth`).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from rigbuild.camera import Camera
from rigbuild.eval.reconstruction import align_to_ground_truth
from rigbuild.io.cameras import read_cameras


def calibrated_to_ground_truth(gt_dir: str | os.PathLike, cameras: str | os.PathLike | list[Camera]
                               ) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity ``x_gt = s R x_cal + t`` for a session's ``ground_truth/`` and its calibrated cameras
    (a ``cameras.json`` path or a list of :class:`Camera`)."""
    est = read_cameras(cameras) if isinstance(cameras, (str, os.PathLike)) else list(cameras)
    truth = read_cameras(Path(gt_dir) / "cameras.json")
    return align_to_ground_truth(est, truth)


def points_to_ground_truth(points: np.ndarray, similarity: tuple[float, np.ndarray, np.ndarray]) -> np.ndarray:
    """Positions (..., 3) in the calibrated world -> the ground-truth world."""
    s, R, t = similarity
    return s * np.asarray(points) @ R.T + t


def vectors_to_ground_truth(vectors: np.ndarray, similarity: tuple[float, np.ndarray, np.ndarray]) -> np.ndarray:
    """Displacements (..., 3) (e.g. blendshape deltas) in the calibrated world -> the ground-truth world."""
    s, R, _ = similarity
    return s * np.asarray(vectors) @ R.T

"""Calibration on real photos: OpenCV's chessboard stereo samples and the ChArUco tutorial images."""

from __future__ import annotations

import sys

import cv2
import numpy as np
import pytest

from rigbuild.calibrate.detect import detect_board, read_gray
from rigbuild.calibrate.intrinsics import calibrate_intrinsics
from rigbuild.calibrate.rig import CalibrationOptions, calibrate_rig
from rigbuild.session import BoardSpec

CHESS = BoardSpec("chessboard", 10, 7, 1.0)  # 9 x 6 inner corners; square size unknown: 1 unit
CHARUCO_TUTORIAL = BoardSpec("charuco", 5, 7, 40.0, 20.0, "DICT_6X6_250")
LEFT = ["01", "02", "03", "04", "05", "06", "07", "08", "09", "11", "12", "13", "14"]
# opencv/opencv modules/calib3d/misc/python/test/test_calibration.py (see the data folder's SOURCE.md)
REF_RMS = 0.196334638034
REF_K = np.array([[532.80992189, 0, 342.4952186], [0, 532.93346422, 233.8879292], [0, 0, 1]])
REF_DIST = np.array([-0.281325576, 0.0291130406, 0.0012123433, -0.000140825372, 0.154865844])


@pytest.fixture(scope="module")
def stereo(real_data):
    d = real_data / "opencv-chessboard-stereo"
    if not d.is_dir():
        pytest.skip("opencv-chessboard-stereo absent")
    return {side: {n: detect_board(read_gray(d / f"{side}{n}.jpg", (640, 480)), CHESS, subpix_window=5) for n in LEFT}
            for side in ("left", "right")}


def test_opencv_recipe_single_camera_reproduces_reference(stereo):
    pts, _ = CHESS.corner_points()
    dets = [stereo["left"][n] for n in LEFT]
    assert all(len(d) == 54 for d in dets)
    intr = calibrate_intrinsics([pts[d.ids] for d in dets], [d.corners for d in dets], (640, 480), flags=0,
                                criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, sys.float_info.epsilon))
    assert abs(intr.rms_px - REF_RMS) < 0.01
    assert np.abs(intr.K - REF_K).sum() < 10
    assert np.abs(intr.dist - REF_DIST).sum() < 0.05


def test_stereo_pair_calibrates(stereo):
    res = calibrate_rig(stereo, CHESS, (640, 480), CalibrationOptions(min_images=8, max_rms_px=0.5))
    assert res.rms_px < 0.5
    assert all(r < 0.5 for r in res.camera_rms().values())
    right = res.cameras[1]
    baseline = np.linalg.norm(right.center)
    # OpenCV's stereo sample: cameras side by side, ~3.3 squares apart, nearly parallel
    assert 2.5 < baseline < 4.5
    assert np.degrees(np.arccos((np.trace(right.R) - 1) / 2)) < 5.0


def test_charuco_tutorial_all_corners_and_rms(real_data):
    d = real_data / "opencv-charuco-tutorial"
    if not d.is_dir():
        pytest.skip("opencv-charuco-tutorial absent")
    dets = {f"{k}": detect_board(read_gray(d / f"img_{k:02d}.jpg", (640, 480)), CHARUCO_TUTORIAL) for k in range(4)}
    assert [len(x) for x in dets.values()] == [24, 24, 24, 24]
    pts, _ = CHARUCO_TUTORIAL.corner_points()
    intr = calibrate_intrinsics([pts[x.ids] for x in dets.values()], [x.corners for x in dets.values()], (640, 480))
    assert intr.rms_px < 0.3
    # the published calibration of these images (tutorial_camera_charuco.yml): fx 452.5, fy 456.8
    assert abs(intr.K[0, 0] - 452.5) / 452.5 < 0.03 and abs(intr.K[1, 1] - 456.8) / 456.8 < 0.03
    # the rig path (pose graph + robust bundle adjustment) on the one camera agrees
    res = calibrate_rig({"cam": dets}, CHARUCO_TUTORIAL, (640, 480), CalibrationOptions(min_images=4, max_rms_px=0.3))
    assert res.rms_px < 0.3
    assert abs(res.cameras[0].K[0, 0] - intr.K[0, 0]) / intr.K[0, 0] < 0.01

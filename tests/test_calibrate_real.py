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


def _qualisys_intrinsics(path) -> dict:
    """camera serial -> (fx, fy, cx, cy) px of the Qualisys reference (Calib.qca.txt stores 1/64 px)."""
    import xml.etree.ElementTree as ET

    out = {}
    for cam in ET.parse(path).getroot().iter("camera"):
        a = cam.find("intrinsic").attrib
        out[cam.attrib["serial"]] = np.array([float(a[k]) / 64 for k in ("focalLengthU", "focalLengthV",
                                                                          "centerPointU", "centerPointV")])
    return out


@pytest.mark.data
def test_sleap_anipose_calibrates_as_a_calibration_only_session(real_data, tmp_path):
    """Issue 21 acceptance: the 4-camera sleap-anipose ChArUco recording, described by
    config/calibration-only/sleap-charuco/session.yaml (its own folders and file names, JPEG), calibrated
    with config/sleap-charuco.yaml's parameters: every 4th frame held out, triangulated and reprojected."""
    import yaml

    from rigbuild.calibrate.stage import run_calibrate
    from rigbuild.paths import PROJECT_ROOT

    if not (real_data / "sleap-anipose-charuco-4cam").is_dir():
        pytest.skip("sleap-anipose-charuco-4cam absent")
    params = yaml.safe_load((PROJECT_ROOT / "config" / "sleap-charuco.yaml").read_text())["params"]["calibrate"]
    m = run_calibrate(PROJECT_ROOT / "config" / "calibration-only" / "sleap-charuco", tmp_path / "calib", params,
                      workers=2)
    print({k: m[k] for k in ("rms_px", "camera_rms_px", "heldout_reprojection_rms_px", "heldout_camera_rms_px",
                             "heldout_scale_deviation_pct", "plausibility_flags", "seconds")})
    # measured: fitted 0.283 px (0.16-0.47 per camera), held out 0.100 px (5 poses, 350 corners), scale +0.003 %
    assert m["status"] == "pass" and m["bundle_converged"] and m["n_images_used"] == 84
    assert m["heldout_n_board_poses"] == 5
    assert m["heldout_reprojection_rms_px"] <= 0.6
    assert abs(m["heldout_scale_deviation_pct"]) <= 0.2
    # the detection pictures are drawn on the cameras' images, which live outside the session folder here
    from calibration_pictures import assert_pictures_drawn_on_the_images

    assert_pictures_drawn_on_the_images(tmp_path / "calib", PROJECT_ROOT / "config" / "calibration-only" / "sleap-charuco")


@pytest.fixture(scope="module")
def pose2sim_intrinsics(real_data, tmp_path_factory):
    """Intrinsics of the 4 Pose2Sim cameras from their own checkerboard photos (calib_intrinsics), next to
    the Qualisys reference."""
    import yaml

    from rigbuild.calibrate.params import from_config
    from rigbuild.calibrate.session import known_intrinsics
    from rigbuild.session import read_session

    d = real_data / "pose2sim-calibration-4cam"
    if not d.is_dir():
        pytest.skip("pose2sim-calibration-4cam absent")
    folder = tmp_path_factory.mktemp("pose2sim")
    (folder / "session.yaml").write_text(yaml.safe_dump({
        "name": "pose2sim", "cameras": ["cam01", "cam02", "cam03", "cam04"], "image_size": [1088, 1920],
        "board": {"type": "chessboard", "squares_x": 5, "squares_y": 8, "square_size_mm": 60.0},
        "calibration": {"intrinsics_images": "{data}/pose2sim-calibration-4cam/intrinsics/int_{cam}_img"}}))
    est = known_intrinsics(read_session(folder), from_config({}), workers=2)
    ref = _qualisys_intrinsics(d / "Calib.qca.txt")
    got = {c: np.array([k.K[0, 0], k.K[1, 1], k.K[0, 2], k.K[1, 2]]) for c, k in est.items()}
    print({c: (np.round(100 * (got[c][:2] / ref[c][:2] - 1), 2), np.round(got[c][2:] - ref[c][2:], 1)) for c in ref})
    return est, got, ref


@pytest.mark.data
def test_pose2sim_focal_lengths_from_separate_checkerboard_photos(pose2sim_intrinsics):
    """Issue 21 acceptance: focal lengths within 0.5 % of the Qualisys reference. Measured: fx/fy -0.47/-0.48,
    +0.11/+0.11, -0.37/-0.40, -0.12/-0.14 % (7, 6, 7, 6 photos; 0.18-0.19 px RMS)."""
    est, got, ref = pose2sim_intrinsics
    assert all(k.source == "images" and k.rms_px < 0.3 for k in est.values())
    for c in ref:
        assert np.all(np.abs(got[c][:2] / ref[c][:2] - 1) <= 0.005), c


@pytest.mark.data
def test_pose2sim_photos_pin_the_principal_points(pose2sim_intrinsics):
    """OpenCV's covariance pins each principal point to a few px (one sigma; measured 1.6-2.3 px; a bootstrap over
    the photos gives 2-6.6 px, docs/decisions.md)."""
    est, _, _ = pose2sim_intrinsics
    for c, k in est.items():
        assert np.all(np.isfinite(k.sd)) and np.max(k.sd[2:]) <= 3.0, (c, k.sd)


@pytest.mark.data
def test_pose2sim_photo_sets_agree_like_one_camera_unlike_the_reference(pose2sim_intrinsics):
    """The four 'int_camNN_img' sets were shot by one camera (the same background, pixel-registered to 0.1 px
    between sets; one intrinsics fit over all photos is as good as four: docs/decisions.md). Their principal
    points agree within a few px (measured cx 555.4-560.5, cy 933.7-936.3), while the Qualisys reference's
    four cameras differ by 27 / 16 px (cx 513.2-540.1, cy 948.1-964.0): no estimate from these photos can
    match all four reference principal points."""
    _, got, ref = pose2sim_intrinsics
    ours = np.array([got[c][2:] for c in ref])
    theirs = np.array([ref[c][2:] for c in ref])
    assert np.ptp(ours, axis=0).max() <= 8.0
    assert np.ptp(theirs, axis=0).max() >= 15.0


@pytest.mark.data
@pytest.mark.xfail(strict=True, reason="not testable with this data: the four intrinsics photo sets are one camera "
                   "(test_pose2sim_photo_sets_agree_like_one_camera_unlike_the_reference; docs/decisions.md), while the reference's principal points differ "
                   "by up to 27 px between cameras; measured gaps cx +27.5 +20.9 +45.2 +19.8, cy -14.5 -26.9 -21.1 "
                   "-28.7 px")
def test_pose2sim_principal_points_from_separate_checkerboard_photos(pose2sim_intrinsics):
    """Issue 21 acceptance: principal points within 10 px of the Qualisys reference."""
    _, got, ref = pose2sim_intrinsics
    for c in ref:
        assert np.all(np.abs(got[c][2:] - ref[c][2:]) <= 10.0), c

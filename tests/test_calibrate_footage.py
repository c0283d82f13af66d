"""Issue 21 (calibration on real footage): board descriptions, the detection failure message, the bundle
adjustment's convergence gate, known / separately shot intrinsics and the model options, plausibility flags
and the held-out reprojection error. Board images are OpenCV's own board drawings under a perspective warp;
rig data are simulated detections (rigbuild.synth.calibration_scene)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from rigbuild.calibrate import qa
from rigbuild.calibrate.detect import board_variants, detect_board
from rigbuild.calibrate.heldout import heldout_errors, split_views
from rigbuild.calibrate.rig import CalibrationOptions, KnownIntrinsics, calibrate_rig
from rigbuild.calibrate.stage import run_calibrate
from rigbuild.camera import Camera
from rigbuild.errors import InputError, QualityGateError
from rigbuild.eval.calibration import compare_cameras
from rigbuild.session import BoardSpec, read_session
from rigbuild.synth.calibration_scene import arc_rig, random_board_poses, simulate_detections

BOARD = BoardSpec("charuco", 7, 5, 24.0, 18.0, "DICT_5X5_100")


def board_image(board: BoardSpec, size=(800, 600), inverted=False) -> np.ndarray:
    """OpenCV's drawing of ``board`` (white margin) seen at a slant, lightly blurred, (H, W) uint8."""
    sx, sy = board.squares_x, board.squares_y
    im = board.opencv_board().generateImage((60 * sx + 40, 60 * sy + 40), marginSize=20)
    src = np.float32([[0, 0], [im.shape[1], 0], [im.shape[1], im.shape[0]], [0, im.shape[0]]])
    dst = np.float32([[90, 60], [700, 90], [680, 560], [110, 520]]) * np.float32([size[0] / 800, size[1] / 600])
    out = cv2.GaussianBlur(cv2.warpPerspective(im, cv2.getPerspectiveTransform(src, dst), size, borderValue=255),
                           (3, 3), 0.8)
    return 255 - out if inverted else out


def _n_inner(board: BoardSpec) -> int:
    return (board.squares_x - 1) * (board.squares_y - 1)


# ------------------------------------------------------------------ finding 1: describing the board
def test_inverted_board_true_and_auto():
    img = board_image(BOARD, inverted=True)
    assert len(detect_board(img, BOARD)) == 0  # white markers on black: not found as printed
    assert len(detect_board(img, replace(BOARD, inverted=True))) == _n_inner(BOARD)
    assert len(detect_board(img, replace(BOARD, inverted="auto"))) == _n_inner(BOARD)
    assert len(detect_board(board_image(BOARD), replace(BOARD, inverted="auto"))) == _n_inner(BOARD)
    chess = BoardSpec("chessboard", 8, 6, 30.0)
    assert len(detect_board(board_image_chess(chess, inverted=True), replace(chess, inverted=True))) == 35


def board_image_chess(board: BoardSpec, inverted=False) -> np.ndarray:
    sq = 50
    im = np.full(((board.squares_y + 2) * sq, (board.squares_x + 2) * sq), 255, np.uint8)
    for y in range(board.squares_y):
        for x in range(board.squares_x):
            if (x + y) % 2 == 0:
                im[(y + 1) * sq:(y + 2) * sq, (x + 1) * sq:(x + 2) * sq] = 0
    im = cv2.GaussianBlur(cv2.resize(im, (640, 480)), (3, 3), 0.8)
    return 255 - im if inverted else im


def test_legacy_pattern_board():
    """OpenCV < 4.6 drew ChArUco boards with an even number of rows differently (legacy_pattern)."""
    board = BoardSpec("charuco", 6, 6, 30.0, 22.0, "DICT_4X4_100")
    legacy = replace(board, legacy_pattern=True)
    img = board_image(legacy)
    assert len(detect_board(img, board)) == 0
    assert len(detect_board(img, legacy)) == _n_inner(board)
    data = {"name": "s", "cameras": ["a", "b"], "image_size": [800, 600],
            "board": {"type": "charuco", "squares_x": 6, "squares_y": 6, "square_size_mm": 30,
                      "marker_size_mm": 22, "dictionary": "DICT_4X4_100", "legacy_pattern": True,
                      "inverted": "auto"}}
    from rigbuild.session import session_from_dict

    spec = session_from_dict(data, ".")
    assert spec.board.legacy_pattern is True and spec.board.inverted == "auto"
    assert len(detect_board(img, spec.board)) == _n_inner(board)


@pytest.mark.parametrize("name,canonical", [
    ("DICT_4X4_1000", "DICT_4X4_1000"), ("4x4_1000", "DICT_4X4_1000"), ("dict_apriltag_36h11", "DICT_APRILTAG_36h11"),
    ("DICT_ARUCO_ORIGINAL", "DICT_ARUCO_ORIGINAL"), ("APRILTAG_16h5", "DICT_APRILTAG_16h5"),
    ("DICT_ARUCO_MIP_36h12", "DICT_ARUCO_MIP_36h12"), ("7X7_50", "DICT_7X7_50"),
])
def test_any_predefined_dictionary(name, canonical):
    from rigbuild.session import session_from_dict

    data = {"name": "s", "cameras": ["a", "b"], "image_size": [800, 600],
            "board": {"type": "charuco", "squares_x": 7, "squares_y": 5, "square_size_mm": 30,
                      "marker_size_mm": 22, "dictionary": name}}
    spec = session_from_dict(data, ".")
    assert spec.board.dictionary == canonical
    assert len(detect_board(board_image(spec.board), spec.board)) == 24


def test_unknown_or_too_small_dictionary_is_named():
    from rigbuild.session import session_from_dict

    base = {"name": "s", "cameras": ["a", "b"], "image_size": [800, 600]}
    board = {"type": "charuco", "squares_x": 8, "squares_y": 11, "square_size_mm": 24, "marker_size_mm": 18}
    with pytest.raises(InputError, match=r"(?s)unknown ArUco dictionary 'CharucoBoard'.*DICT_APRILTAG_36h11"):
        session_from_dict({**base, "board": {**board, "dictionary": "CharucoBoard"}}, ".")
    with pytest.raises(InputError, match=r"DICT_APRILTAG_16h5 has 30 markers, a 8 x 11 ChArUco board needs 44"):
        session_from_dict({**base, "board": {**board, "dictionary": "DICT_APRILTAG_16h5"}}, ".")


def _image_session(folder: Path, board: dict, images: dict[str, list[np.ndarray]], size=(800, 600)) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for cam, ims in images.items():
        (folder / "calib" / cam).mkdir(parents=True, exist_ok=True)
        for k, im in enumerate(ims):
            cv2.imwrite(str(folder / "calib" / cam / f"{k}.png"), im)
    data = {"name": folder.name, "cameras": list(images), "image_size": list(size), "board": board}
    (folder / "session.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    return folder


def test_detection_failure_lists_the_variants_tried_and_the_fix(tmp_path):
    inv = [board_image(BOARD, inverted=True)] * 2
    board = {"type": "charuco", "squares_x": 7, "squares_y": 5, "square_size_mm": 24, "marker_size_mm": 18,
             "dictionary": "DICT_5X5_100"}
    s = _image_session(tmp_path / "inv", board, {"a": inv, "b": inv})
    with pytest.raises(InputError) as exc:
        run_calibrate(s, tmp_path / "out" / "calib", {})
    msg = str(exc.value)
    assert "session.yaml: field 'board': no charuco corners found in any of the 4 calibration images" in msg
    assert "tried on 2 sample images" in msg and "legacy_pattern: true" in msg and "squares_x: 5, squares_y: 7" in msg
    assert "with inverted: true: 48 corners in 2 sample images -> set board.inverted: true" in msg
    assert not (tmp_path / "out").exists()
    # a wrong dictionary: no variant helps, and no marker of it is seen
    s2 = _image_session(tmp_path / "dict", {**board, "dictionary": "DICT_6X6_250"}, {"a": [board_image(BOARD)] * 2,
                                                                                    "b": [board_image(BOARD)] * 2})
    with pytest.raises(InputError, match=r"0 DICT_6X6_250 markers found .*check board.dictionary"):
        run_calibrate(s2, tmp_path / "out2" / "calib", {})
    # the same session with inverted: auto calibrates past detection (2 images per camera: too few)
    data = yaml.safe_load((s / "session.yaml").read_text())
    data["board"]["inverted"] = "auto"
    (s / "session.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(QualityGateError, match="fewer than 4 usable board images"):
        run_calibrate(s, tmp_path / "out3" / "calib", {})


def test_board_variants_cover_polarity_layout_and_orientation():
    changes = [c for c, _ in board_variants(BOARD)]
    assert "inverted: true" in changes and "legacy_pattern: true" in changes
    assert "squares_x: 5, squares_y: 7" in changes
    assert len(changes) == len(set(changes)) == 7
    assert [c for c, _ in board_variants(BoardSpec("chessboard", 8, 6, 30.0))][0].startswith("squares_x: 9, squares_y: 7")


def test_calibration_images_elsewhere_with_a_view_key(tmp_path):
    """JPEG images named <cam>-<timestamp>-<frame>.jpg in another folder: calibration.images + view_key."""
    from rigbuild.calibrate.detect import session_images

    for cam in ("left", "right"):
        d = tmp_path / "footage" / cam / "frames"
        d.mkdir(parents=True)
        for k in (0, 2, 10):
            cv2.imwrite(str(d / f"{cam}-2024{k:02d}-{k}.jpg"), board_image(BOARD))
    data = {"name": "s", "cameras": ["left", "right"], "image_size": [800, 600],
            "board": {"type": "charuco", "squares_x": 7, "squares_y": 5, "square_size_mm": 24,
                      "marker_size_mm": 18, "dictionary": "DICT_5X5_100"},
            "calibration": {"images": str(tmp_path / "footage" / "{cam}" / "frames"), "view_key": r"-(\d+)$"}}
    (tmp_path / "s").mkdir()
    (tmp_path / "s" / "session.yaml").write_text(yaml.safe_dump(data))
    spec = read_session(tmp_path / "s")
    assert spec.calibration_only
    images = session_images(spec)
    assert list(images["left"]) == ["0", "2", "10"] and images["right"]["10"].name == "right-202410-10.jpg"
    data["calibration"]["view_key"] = r"_(\d+)$"
    (tmp_path / "s" / "session.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(InputError, match=r"calibration.view_key.*does not match image name"):
        session_images(read_session(tmp_path / "s"))


# ------------------------------------------------------------------ finding 5: convergence
def _sim(n_cams=4, n_poses=12, noise=0.05, seed=0, size=(640, 480), focal=800.0):
    cams = arc_rig(n_cams, size[0], size[1], focal_px=focal, distance_mm=450, azimuth_deg=90, seed=seed)
    poses = random_board_poses(n_poses, BOARD, seed=seed + 1, max_tilt_deg=35, spread_mm=40)
    return cams, poses, simulate_detections(cams, BOARD, poses, noise_px=noise, seed=seed + 2)


def test_bundle_adjustment_iterates_to_tolerance_or_fails_with_numbers():
    cams, _, det = _sim()
    res = calibrate_rig(det, BOARD, (640, 480), CalibrationOptions())
    assert res.bundle.status in (1, 2) and "converged" in res.bundle.message
    with pytest.raises(QualityGateError, match=r"(?s)did not converge: not converged after 2 iterations \(tolerance "
                                               r"1e-10; last relative cost decrease .*RMS .* -> .* px.*max_iterations"):
        calibrate_rig(det, BOARD, (640, 480), CalibrationOptions(max_iterations=2))
    capped = calibrate_rig(det, BOARD, (640, 480), CalibrationOptions(max_iterations=2), raise_gate=False)
    assert capped.status == "fail" and capped.bundle.status == 0


# ------------------------------------------------------------------ finding 6: intrinsics
def test_known_intrinsics_fixed_are_kept_and_extrinsics_fit():
    cams, _, det = _sim(noise=0.05)
    known = {c.id: KnownIntrinsics(c.K, c.dist, "given") for c in cams}
    res = calibrate_rig(det, BOARD, (640, 480), CalibrationOptions(), known=known)
    for est, true in zip(res.cameras, cams):
        assert np.array_equal(est.K, true.K) and np.array_equal(est.dist, true.dist)
    err = compare_cameras(res.cameras, cams)
    assert err["center_error_mm"] < 0.3 and err["rotation_error_deg"] < 0.05
    assert res.intrinsics_source == {c.id: "given" for c in cams}


def test_known_intrinsics_as_prior_are_refined():
    """A prior 1 % off: held, the focal error stays 1 %; as a prior the footage pulls it back, the more the
    looser the prior (sigma prior_focal_pct)."""
    cams, _, det = _sim(noise=0.05)
    off = {c.id: KnownIntrinsics(c.K * np.array([[1.01], [1.01], [1]]), c.dist, "images") for c in cams}

    def fit(**kw):
        r = calibrate_rig(det, BOARD, (640, 480), CalibrationOptions(max_rms_px=5, **kw), known=off)
        return compare_cameras(r.cameras, cams)["focal_error_pct"], r.rms_px

    f_fixed, rms_fixed = fit()
    f_tight, _ = fit(known_intrinsics="prior", prior_focal_pct=0.01)
    f_prior, rms_prior = fit(known_intrinsics="prior")
    f_loose, _ = fit(known_intrinsics="prior", prior_focal_pct=100.0, prior_principal_px=1000.0, prior_distortion=10.0)
    assert f_fixed == pytest.approx(1.0, abs=1e-9)
    assert abs(f_tight - f_fixed) < 0.01 and f_tight > f_prior > f_loose
    assert f_loose < 0.3 and rms_prior < rms_fixed


def test_model_options_fix_principal_point_aspect_and_tangential():
    cams, _, det = _sim(noise=0.05)
    res = calibrate_rig(det, BOARD, (640, 480), CalibrationOptions(fix_principal_point=True, fix_aspect_ratio=True,
                                                                  fix_tangential=True, fix_k3=True))
    for c in res.cameras:
        assert c.K[0, 2] == pytest.approx(319.5, abs=1e-9) and c.K[1, 2] == pytest.approx(239.5, abs=1e-9)
        assert c.K[0, 0] == pytest.approx(c.K[1, 1], rel=1e-12)
        assert c.dist[2] == 0 and c.dist[3] == 0 and c.dist[4] == 0
    free = calibrate_rig(det, BOARD, (640, 480), CalibrationOptions())
    assert all(c.K[0, 0] != c.K[1, 1] and c.dist[4] != 0 for c in free.cameras)  # k3 and tangential free by default


def test_given_intrinsics_in_session_yaml_and_in_a_file(tmp_path):
    from rigbuild.calibrate.intrinsics import given_intrinsics

    K = [[800.0, 0, 320], [0, 801.0, 240], [0, 0, 1]]
    out = given_intrinsics({"a": {"K": K, "dist": [-0.1, 0.01]}}, tmp_path, ["a", "b"])
    assert np.allclose(out["a"][1], [-0.1, 0.01, 0, 0, 0]) and "b" not in out
    (tmp_path / "intr.yaml").write_text(yaml.safe_dump({"b": {"K": K}}))
    assert np.allclose(given_intrinsics("intr.yaml", tmp_path, ["a", "b"])["b"][0], K)
    with pytest.raises(InputError, match=r"intrinsics for unknown camera 'c'"):
        given_intrinsics({"c": {"K": K}}, tmp_path, ["a", "b"])
    with pytest.raises(InputError, match=r"intr2.yaml: intrinsics file not found"):
        given_intrinsics("intr2.yaml", tmp_path, ["a", "b"])
    with pytest.raises(InputError, match=r"camera 'a': K must be"):
        given_intrinsics({"a": {"K": [[800, 0, 320], [0, 800, 240], [0, 1, 1]]}}, tmp_path, ["a"])


# ------------------------------------------------------------------ plausibility flags
def test_plausibility_flags():
    K = np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]])
    good = Camera("good", 640, 480, K, np.zeros(5), np.eye(3), np.zeros(3))
    off = Camera("off", 640, 480, np.array([[800.0, 0, 320], [0, 850, 774], [0, 0, 1]]), np.zeros(5), np.eye(3),
                 np.zeros(3))
    fold = Camera("fold", 640, 480, np.array([[300.0, 0, 320], [0, 300, 240], [0, 0, 1]]), [-0.4, 0.0, 0, 0, 0],
                  np.eye(3), np.zeros(3))
    flags = qa.plausibility_flags([good, off, fold], {"good": 20, "off": 20, "fold": 3}, 10)
    assert flags["good"] == []
    assert any("outside the central third" in f for f in flags["off"])
    assert any("differ by 6.2" in f for f in flags["off"])
    assert any("folds the image" in f for f in flags["fold"]) and any("seen in 3 board poses" in f for f in flags["fold"])
    assert not qa.distortion_folds(K, np.array([-0.4, 0.0, 0, 0, 0]), 640, 480)  # narrow lens: no fold in frame


def test_flags_reach_the_result():
    cams, _, det = _sim(n_poses=6)
    res = calibrate_rig(det, BOARD, (640, 480), CalibrationOptions(min_board_poses=8))
    assert all(any("board poses" in f for f in res.flags[c.id]) for c in res.cameras)
    rows = res.per_camera_rows()
    assert "board poses" in rows[0]["flags"] and rows[0]["intrinsics"] == "rig"


# ------------------------------------------------------------------ held-out reprojection
def test_heldout_reprojection_of_triangulated_corners():
    assert split_views([str(k) for k in range(9)], 4) == (["0", "1", "2", "4", "5", "6", "8"], ["3", "7"])
    assert split_views(["a", "b"], 0) == (["a", "b"], [])
    cams, _, det = _sim(noise=0.0)
    pts, _ = BOARD.corner_points()
    exact = heldout_errors(cams, det, ["3", "7"], pts)
    assert exact["rms_px"] < 1e-6 and abs(exact["scale_deviation_pct"]) < 1e-6 and exact["n_views"] == 2
    cams, _, det = _sim(noise=0.1, n_poses=16)
    fitted, held = split_views(sorted(det["cam00"], key=int), 4)
    fit = calibrate_rig({c: {v: d for v, d in views.items() if v in fitted} for c, views in det.items()}, BOARD,
                        (640, 480))
    h = heldout_errors(fit.cameras, det, held, pts)
    # 0.1 px noise per coordinate; triangulation absorbs some: between 0.05 and 0.15 px RMS (2-D)
    assert 0.05 < h["rms_px"] < 0.15 and set(h["camera_rms_px"]) == {c.id for c in cams}
    assert abs(h["scale_deviation_pct"]) < 0.05


def test_heldout_chessboard_views_numbered_from_the_other_end():
    """A chessboard held-out view one camera numbers from the other end is renumbered as the pose graph
    decided before triangulating (else its corners would pair with the wrong ones)."""
    from rigbuild.calibrate.detect import Detection
    from rigbuild.calibrate.session import consistent_labels

    chess = BoardSpec("chessboard", 8, 6, 20.0)
    cams = arc_rig(3, 640, 480, focal_px=800, distance_mm=450, azimuth_deg=60, seed=11)
    poses = random_board_poses(8, chess, seed=12, max_tilt_deg=30, spread_mm=30)
    det = simulate_detections(cams, chess, poses, noise_px=0.0, margin_px=-1e9)
    n = len(chess.corner_points()[0])
    for v in ("3", "6"):
        d = det["cam01"][v]
        det["cam01"][v] = Detection(n - 1 - d.ids[::-1], d.corners[::-1])
    res = calibrate_rig(det, chess, (640, 480), CalibrationOptions(min_images=4))
    pts = chess.corner_points()[0]
    assert heldout_errors(res.cameras, det, ["3"], pts)["rms_px"] > 10
    assert heldout_errors(res.cameras, consistent_labels(det, res), ["3"], pts)["rms_px"] < 1e-6


"""The rigbuild command line: init-session scaffolds and checks, eval prints the metrics table."""

from __future__ import annotations

import cv2
import numpy as np
import yaml

from rigbuild.cli import main
from rigbuild.io.atomic import write_json
from rigbuild.session import read_session


def _board_image(squares=(9, 6), inverted=False) -> np.ndarray:
    """A ChArUco board (DICT_5X5_100, the CLI's default dictionary) on a 640x480 white page."""
    from rigbuild.session import BoardSpec

    board = BoardSpec("charuco", squares[0], squares[1], 25.0, 18.0, "DICT_5X5_100").opencv_board()
    page = np.full((480, 640), 255, np.uint8)
    drawn = board.generateImage((60 * squares[0], 60 * squares[1]))
    page[(480 - drawn.shape[0]) // 2:][:drawn.shape[0], (640 - drawn.shape[1]) // 2:][:, :drawn.shape[1]] = drawn
    return 255 - page if inverted else page


def _folder(tmp_path, size=(64, 48), missing_view=False, bad_size=False, board=None):
    img = np.full((size[1], size[0], 3), 128, np.uint8) if board is None else board
    for cam in ("camA", "camB"):
        for n in range(3):
            p = tmp_path / "calib" / cam / f"{n}.png"
            p.parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(p), img if not (bad_size and cam == "camB" and n == 2) else img[:10])
        for f in range(4, 7):
            if missing_view and cam == "camB" and f == 5:
                continue
            p = tmp_path / "rom" / "smile" / cam / f"{f:06d}.png"
            p.parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(p), img)
    return tmp_path


def test_init_session_scaffolds_a_valid_session(tmp_path, capsys):
    folder = _folder(tmp_path / "actor1", board=_board_image())
    assert main(["init-session", str(folder), "--squares", "9", "6", "--square-mm", "25", "--marker-mm", "18"]) == 0
    spec = read_session(folder)
    assert spec.cameras == ["camA", "camB"] and (spec.width, spec.height) == (640, 480)
    assert spec.rom[0].name == "smile" and spec.rom[0].frames == [4, 5, 6] and spec.rom[0].neutral_frame == 4
    assert spec.board.squares_x == 9 and spec.board.square_size_mm == 25.0
    out = capsys.readouterr().out
    assert "2 cameras" in out
    assert "camA: 40/40, 40/40, 40/40 corners in 3 images" in out and "camB: 40/40" in out


def test_init_session_board_check_catches_a_wrong_board_spec(tmp_path, capsys):
    """Issue 21: the board is detected in a few images per camera before any run; an inverted print
    described as a normal one is reported with the change that finds it."""
    folder = _folder(tmp_path / "actor4", board=_board_image(inverted=True))
    assert main(["init-session", str(folder), "--squares", "9", "6", "--square-mm", "25", "--marker-mm", "18"]) == 1
    out = capsys.readouterr().out
    assert "camA: 0/40, 0/40, 0/40 corners in 3 images" in out
    assert "problem: board not found in the sample images of camA, camB" in out
    assert "with inverted: true: 120 corners in 3 sample images -> set board.inverted: true" in out
    assert main(["init-session", str(folder), "--squares", "9", "6", "--square-mm", "25", "--marker-mm", "18",
                 "--inverted", "auto", "--force"]) == 0
    assert read_session(folder).board.inverted == "auto"
    assert "camB: 40/40, 40/40, 40/40 corners" in capsys.readouterr().out


def test_init_session_reports_missing_views_and_bad_sizes(tmp_path, capsys):
    folder = _folder(tmp_path / "actor2", missing_view=True, bad_size=True)
    assert main(["init-session", str(folder)]) == 1
    out = capsys.readouterr().out
    assert "camB/000005.png: missing view" in out
    assert "camB/2.png: size 64x10" in out


def test_init_session_keeps_existing_yaml_unless_forced(tmp_path):
    folder = _folder(tmp_path / "actor3")
    main(["init-session", str(folder), "--fps", "48"])
    data = yaml.safe_load((folder / "session.yaml").read_text())
    main(["init-session", str(folder), "--fps", "24"])
    assert yaml.safe_load((folder / "session.yaml").read_text())["fps"] == data["fps"] == 48
    main(["init-session", str(folder), "--fps", "24", "--force"])
    assert yaml.safe_load((folder / "session.yaml").read_text())["fps"] == 24


def test_init_session_on_a_folder_without_calib_is_a_clear_error(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    assert main(["init-session", str(tmp_path / "empty")]) == 2
    assert "no calib/ folder" in capsys.readouterr().err


def test_eval_prints_table_with_status(tmp_path, capsys):
    write_json(tmp_path / "s1" / "metrics.json", {"calibration": {"rms_px": 0.1, "center_error_mm": 2.0}})
    assert main(["eval", "s1", "--results", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "calibration.rms_px" in out and "pass" in out and "fail" in out
    assert out.splitlines()[0] == "session fail"  # the report's summary comes first: the centre error fails
    assert main(["eval", "s1", "--results", str(tmp_path), "--strict"]) == 1
    assert main(["eval", "nosuch", "--results", str(tmp_path)]) == 1

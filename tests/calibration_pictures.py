"""Shared by the calibration tests: each camera's detection picture is drawn on that camera's image."""

from __future__ import annotations

import csv
from pathlib import Path

import cv2
import numpy as np


def assert_pictures_drawn_on_the_images(calib_dir: Path, session_dir: Path) -> None:
    """Every camera's ``detections/<cam>.jpg`` shows, dimmed to 0.6, the image where that camera found the
    most corners (reprojection_per_image.csv): its blue channel (no red shading there) matches within a few
    grey levels at the median pixel, which a grey canvas would not."""
    from rigbuild.calibrate.detect import read_gray, session_images
    from rigbuild.session import read_session

    images = session_images(read_session(session_dir))
    best: dict[str, tuple[int, str]] = {}
    with open(calib_dir / "reprojection_per_image.csv", newline="") as f:
        for row in csv.DictReader(f):
            if row["used"] == "1" and int(row["n_corners"]) > best.get(row["camera"], (-1, ""))[0]:
                best[row["camera"]] = (int(row["n_corners"]), row["view"])
    assert best and set(best) == set(images)
    for cam, (_, view) in best.items():
        pic = cv2.imread(str(calib_dir / "detections" / f"{cam}.jpg"))
        assert pic is not None, cam
        gray = read_gray(images[cam][view])
        expected = cv2.resize(gray, (pic.shape[1], pic.shape[0]), interpolation=cv2.INTER_AREA) * 0.6
        diff = np.abs(pic[40:, :, 0].astype(float) - expected[40:])
        assert np.median(diff) < 6.0, (cam, float(np.median(diff)))

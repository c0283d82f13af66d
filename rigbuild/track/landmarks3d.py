"""Face landmarks across views: the 468 face-mesh points found in every view of a frame
(:class:`rigbuild.track.landmarks.FaceLandmarker`) and triangulated with outlier rejection.

A view where no face is found is skipped with a warning; the points need two views that agree. Each point is
triangulated from all its views (:func:`rigbuild.track.features.triangulate`), then the view with the largest
reprojection error is dropped while that error exceeds ``max_error_px`` and at least ``min_views`` remain; the
point is lost (NaN) when no such consistent set is left. A side view's hidden half of the face (the network
still places it) and a silhouette contour that is a different skin line in every view are what this drops.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from rigbuild.camera import Camera
from rigbuild.errors import InputError
from rigbuild.track.features import triangulate
from rigbuild.track.landmarks import N_LANDMARKS


@dataclass
class ViewLandmarks:
    """The face-mesh points of one frame in every view.

    uv : (C, 468, 2) px (NaN rows for a view without a face); presence : (C,) score (0 where no face);
    missing : ids of the cameras where no face was found.
    """

    uv: np.ndarray
    presence: np.ndarray
    missing: list[str]


@dataclass
class Landmarks3D:
    """Triangulated face-mesh points: X (468, 3) mm (NaN = lost), rms (468,) px reprojection RMS over the views
    kept, used (C, 468) bool the views kept per point."""

    X: np.ndarray
    rms: np.ndarray
    used: np.ndarray

    @property
    def valid(self) -> np.ndarray:
        return np.isfinite(self.X[:, 0])


def detect_view_landmarks(images: list[np.ndarray], camera_ids: list[str], landmarker, where: str = "") -> ViewLandmarks:
    """Run ``landmarker`` on each image (RGB); a view without a face is skipped with a warning naming
    ``where`` (e.g. "sequence 'rom01' frame 3") and the camera."""
    C = len(images)
    uv = np.full((C, N_LANDMARKS, 2), np.nan)
    presence = np.zeros(C)
    missing = []
    for c, (img, cid) in enumerate(zip(images, camera_ids)):
        r = landmarker(img)
        if r is None:
            missing.append(cid)
            warnings.warn(f"landmarks: no face found in camera {cid}{' of ' + where if where else ''}; view skipped",
                          RuntimeWarning, stacklevel=2)
            continue
        uv[c], presence[c] = r.points[:, :2], r.presence
    return ViewLandmarks(uv, presence, missing)


def require_face(views: ViewLandmarks, camera_ids: list[str], where: str, path=None) -> None:
    """InputError when fewer than two views found a face (the landmarks cannot be triangulated)."""
    found = len(camera_ids) - len(views.missing)
    if found < 2:
        raise InputError(f"no face found in {'any' if found == 0 else 'all but one'} of the {len(camera_ids)} views "
                         f"of {where} (cameras without a face: {', '.join(views.missing)})", path=path,
                         fix="check that the actor's face is in the frame and lit in at least two cameras of this "
                             "frame, or pick another neutral_frame in session.yaml")


def triangulate_landmarks(cameras: list[Camera], uv: np.ndarray, max_error_px: float = 8.0, min_views: int = 2,
                          ref_width: float = 1280.0) -> Landmarks3D:
    """Triangulate (C, M, 2) px points (NaN = not seen) with outlier rejection (module docstring).

    max_error_px : for a ``ref_width``-px-wide image, scaled with each camera's width.
    """
    uv = np.asarray(uv, np.float64)
    C, M, _ = uv.shape
    used = np.isfinite(uv).all(2)
    thr = np.array([max_error_px * cam.width / ref_width for cam in cameras])
    for _ in range(max(C - min_views, 0) + 1):
        X, _, n = triangulate(cameras, uv, used)
        err = np.full((C, M), -np.inf)
        for c, cam in enumerate(cameras):
            m = used[c] & np.isfinite(X[:, 0])
            if m.any():
                err[c, m] = np.linalg.norm(cam.project(X[m]) - uv[c, m], axis=1) / thr[c]
        worst = np.argmax(err, axis=0)
        bad = (err[worst, np.arange(M)] > 1.0) & (n > min_views)
        if not bad.any():
            break
        used[worst[bad], np.flatnonzero(bad)] = False
    X, rms, n = triangulate(cameras, uv, used)
    err = np.zeros((C, M))
    for c, cam in enumerate(cameras):
        m = used[c] & np.isfinite(X[:, 0])
        if m.any():
            err[c, m] = np.linalg.norm(cam.project(X[m]) - uv[c, m], axis=1) / thr[c]
    lost = (n < min_views) | (err.max(0) > 1.0)
    X[lost] = np.nan
    rms[lost] = np.nan
    used[:, lost] = False
    return Landmarks3D(X, rms, used)


def frame_landmarks(cameras: list[Camera], images: list[np.ndarray], landmarker, where: str,
                    max_error_px: float = 8.0, min_views: int = 2, path=None) -> tuple[Landmarks3D, ViewLandmarks]:
    """Detect in every view and triangulate; InputError naming ``where`` when fewer than two views see a face."""
    views = detect_view_landmarks(images, [c.id for c in cameras], landmarker, where)
    require_face(views, [c.id for c in cameras], where, path)
    return triangulate_landmarks(cameras, views.uv, max_error_px, min_views), views


def neutral_landmarks(template, cameras: list[Camera], images: list[np.ndarray], where: str, path=None,
                      max_error_px: float = 8.0):
    """The ``landmarks`` coarse level's input for the neutral registration: the frame's landmarks triangulated
    and tied to the template through its committed table (:func:`rigbuild.track.landmark_table.load_table`).
    Returns :class:`rigbuild.track.register.LandmarkObservations`; InputError naming ``where`` when fewer than
    two views see a face, or a missing model with its install command."""
    from rigbuild.track.landmark_table import load_table
    from rigbuild.track.landmarks import FaceLandmarker
    from rigbuild.track.register import landmark_observations

    L3, _ = frame_landmarks(cameras, images, FaceLandmarker(), where, max_error_px, path=path)
    return landmark_observations(L3.X, load_table(template.name), template.n_vertices)

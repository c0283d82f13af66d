"""Pinhole camera with Brown distortion, OpenCV conventions.

``x_cam = R @ x_world + t`` (world in mm), camera axes x right, y down, z forward; pixel centres at
integer coordinates (OpenCV). ``dist = [k1, k2, p1, p2, k3]``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from rigbuild.errors import InputError


@dataclass
class Camera:
    """One calibrated camera.

    Attributes
    ----------
    id : camera id (folder name under ``calib/`` and ``rom/<seq>/``).
    width, height : image size in pixels.
    K : (3, 3) intrinsics (pixels).
    dist : (5,) Brown distortion ``[k1, k2, p1, p2, k3]``.
    R : (3, 3) world-to-camera rotation.
    t : (3,) world-to-camera translation, mm.
    """

    id: str
    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray
    R: np.ndarray
    t: np.ndarray

    def __post_init__(self) -> None:
        self.id = str(self.id)
        self.width = int(self.width)
        self.height = int(self.height)
        self.K = np.asarray(self.K, dtype=np.float64).reshape(3, 3)
        d = np.zeros(5)
        dist = np.asarray(self.dist, dtype=np.float64).reshape(-1)
        d[: min(5, dist.size)] = dist[:5]
        self.dist = d
        self.R = np.asarray(self.R, dtype=np.float64).reshape(3, 3)
        self.t = np.asarray(self.t, dtype=np.float64).reshape(3)

    # --------------------------------------------------------------- geometry
    @property
    def center(self) -> np.ndarray:
        """(3,) camera centre in world coordinates, mm."""
        return -self.R.T @ self.t

    @property
    def rvec(self) -> np.ndarray:
        """(3,) Rodrigues vector of ``R``."""
        import cv2

        return cv2.Rodrigues(self.R)[0].reshape(3)

    @property
    def P(self) -> np.ndarray:
        """(3, 4) projection matrix ``K [R | t]`` (no distortion)."""
        return self.K @ np.hstack([self.R, self.t[:, None]])

    def world_to_camera(self, X: np.ndarray) -> np.ndarray:
        """(..., 3) world points -> (..., 3) camera-frame points."""
        return np.asarray(X, dtype=np.float64) @ self.R.T + self.t

    def project(self, X: np.ndarray, distort: bool = True) -> np.ndarray:
        """Project world points (..., 3) to pixels (..., 2) (OpenCV pixel centres).

        Points behind the camera get NaN.
        """
        Xc = self.world_to_camera(X)
        z = Xc[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x = Xc[..., 0] / z
            y = Xc[..., 1] / z
        if distort:
            x, y = distort_normalized(x, y, self.dist)
        u = self.K[0, 0] * x + self.K[0, 1] * y + self.K[0, 2]
        v = self.K[1, 1] * y + self.K[1, 2]
        uv = np.stack([u, v], axis=-1)
        uv[z <= 0] = np.nan
        return uv

    def undistort_points(self, uv: np.ndarray) -> np.ndarray:
        """Distorted pixels (N, 2) -> normalized undistorted image coordinates (N, 2)."""
        import cv2

        pts = np.asarray(uv, dtype=np.float64).reshape(-1, 1, 2)
        out = cv2.undistortPoints(pts, self.K, self.dist, criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12))
        return out.reshape(-1, 2)

    def rays(self, uv: np.ndarray) -> np.ndarray:
        """Unit ray directions (N, 3) in world coordinates through distorted pixels ``uv`` (N, 2)."""
        xy = self.undistort_points(uv)
        d = np.hstack([xy, np.ones((xy.shape[0], 1))]) @ self.R  # = R.T @ d_cam
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    # ------------------------------------------------------------ conversion
    def to_dict(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "width": self.width,
            "height": self.height,
            "K": self.K.tolist(),
            "dist": self.dist.tolist(),
            "R": self.R.tolist(),
            "t": self.t.tolist(),
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], source: str = "cameras.json") -> "Camera":
        missing = [k for k in ("id", "width", "height", "K", "dist", "R", "t") if k not in d]
        if missing:
            raise InputError(f"camera entry lacks {missing}", path=source)
        return cls(d["id"], d["width"], d["height"], d["K"], d["dist"], d["R"], d["t"])


def distort_normalized(x: np.ndarray, y: np.ndarray, dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Apply Brown distortion ``[k1, k2, p1, p2, k3]`` to normalized coordinates (OpenCV model)."""
    k1, k2, p1, p2, k3 = np.asarray(dist, dtype=np.float64)[:5]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return xd, yd


def look_at(center: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, 1.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera ``(R, t)`` for a camera at ``center`` looking at ``target`` (OpenCV axes, y down).

    ``up`` is the world up direction; the image's y axis points along ``-up``.
    """
    c = np.asarray(center, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - c
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=np.float64))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ c

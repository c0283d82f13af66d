"""Figures of the tracking stage: the per-frame residual plot and the mesh/marker overlays on every view."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from rigbuild.io.atomic import atomic_path
from rigbuild.track.matches import ViewFrame


def residual_plot(path: str | os.PathLike, rows: list[dict], title: str) -> None:
    """residuals.png: per frame the constraint residual (median, p90, mm; lost frames marked) and the match
    counts per level. rows : :func:`rigbuild.track.stage.stats_rows` (one dict per frame)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    f = [r["frame"] for r in rows]
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.5))
    ax[0].plot(f, [r["residual_median_mm"] for r in rows], "o-", label="median")
    ax[0].plot(f, [r["residual_p90_mm"] for r in rows], "s--", label="p90")
    lost = [r["frame"] for r in rows if r["lost"]]
    for x in lost:
        ax[0].axvline(x, color="r", alpha=0.3)
    ax[0].set_xlabel("frame"); ax[0].set_ylabel("constraint residual (mm)"); ax[0].legend(); ax[0].set_title(title)
    for key in ("dots", "sparse", "flow"):
        ax[1].plot(f, [max(r[key], 0.5) for r in rows], "o-", label=key)
    ax[1].set_yscale("log"); ax[1].set_xlabel("frame"); ax[1].set_ylabel("matches"); ax[1].legend()
    fig.tight_layout()
    with atomic_path(Path(path), suffix=".png") as tmp:
        fig.savefig(tmp, dpi=90)
    plt.close(fig)


def overlay_view(view: ViewFrame, vertices: np.ndarray, markers: np.ndarray, face_vertices: np.ndarray,
                 width: int | None = None) -> np.ndarray:
    """A view's image (H, W, 3) uint8 BGR, scaled to ``width`` px (None: as captured), with every 7th
    face-region vertex (green dots), the markers (red circles) and the camera id drawn at that scale.

    vertices (V, 3) mm, markers (M, 3) mm in the view's world; face_vertices (R,) template vertex ids."""
    import cv2

    img = view.image[..., ::-1]
    cam = view.camera
    s = 1.0 if width is None else width / img.shape[1]
    img = cv2.resize(img, (width, round(img.shape[0] * s)), interpolation=cv2.INTER_AREA) if s != 1.0 \
        else np.ascontiguousarray(img)

    def px(X):
        uv = cam.project(X)
        return np.round((uv[np.isfinite(uv).all(1)] + 0.5) * s - 0.5).astype(int)

    for u, v in px(vertices[face_vertices[::7]]):
        cv2.circle(img, (u, v), 1, (0, 200, 0), -1)
    for u, v in px(markers):
        cv2.circle(img, (u, v), 4, (0, 0, 255), 1)
    cv2.putText(img, cam.id, (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (255, 255, 255), 2, cv2.LINE_AA)
    return img


def draw_overlay(path: str | os.PathLike, views: list[ViewFrame], vertices: np.ndarray, markers: np.ndarray,
                 face_vertices: np.ndarray, tile_width: int = 640, quality: int = 90) -> None:
    """One frame's :func:`overlay_view` on every camera, tiled in as few rows of at most 4 views as fit them,
    evenly filled (6 views: 2 rows of 3), each view at most ``tile_width`` px wide; written as JPEG to ``path``."""
    import cv2

    from rigbuild.montage import tile_images

    width = min(tile_width, views[0].camera.width)
    rows = -(-len(views) // 4)
    views_drawn = [overlay_view(v, vertices, markers, face_vertices, width) for v in views]
    sheet = tile_images(views_drawn, -(-len(views) // rows))
    with atomic_path(Path(path), suffix=".jpg") as tmp:
        if not cv2.imwrite(str(tmp), sheet, [cv2.IMWRITE_JPEG_QUALITY, int(quality)]):
            raise OSError(f"could not write {path}")

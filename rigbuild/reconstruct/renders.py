"""The report's pictures of a reconstructed sequence: ``renders/<frame:06d>.png`` at the neutral and the peak frame.

Each picture shows, seen by the sequence's reference camera (the one whose optical axis is nearest the mean
axis of all cameras: the frontal view of an arc), the colour-mapped filtered depth map of that camera (near
warm, far cool; black: no depth) beside a shaded render of the fused mesh ``mesh/<frame>.ply`` (uniform grey
albedo, Lambert light from the camera's upper left). Both panels are on the camera's undistorted pinhole grid,
scaled to ``width`` px. The peak frame is the reconstructed frame whose mesh lies farthest from the neutral
frame's (mean distance of a vertex sample to the nearest neutral vertex, mm; rigid head motion counts too).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np

from rigbuild.camera import Camera

PANEL_WIDTH = 480
#: vertices of a frame's mesh sampled for its distance to the neutral mesh
DISPLACEMENT_SAMPLES = 4000


def reference_view(cameras: Sequence[Camera]) -> int:
    """Index of the camera whose optical axis is nearest the normalized mean optical axis."""
    axes = np.stack([c.R[2] for c in cameras])
    mean = axes.sum(axis=0)
    mean /= max(np.linalg.norm(mean), 1e-12)
    return int(np.argmax(axes @ mean))


def scaled_pinhole(camera: Camera, width: int) -> Camera:
    """The pinhole camera (no distortion) of the same view with an image ``width`` px wide (OpenCV pixel
    centres kept: ``u' = s (u + 0.5) - 0.5``)."""
    s = width / camera.width
    K = np.asarray(camera.K, float).copy()
    K[:2, :] *= s
    K[0, 2] += 0.5 * s - 0.5
    K[1, 2] += 0.5 * s - 0.5
    return Camera(camera.id, int(width), max(1, int(round(camera.height * s))), K, np.zeros(5), camera.R, camera.t)


def mean_displacement(neutral_vertices: np.ndarray, vertices: np.ndarray, samples: int = DISPLACEMENT_SAMPLES) -> float:
    """Mean distance (mm) of up to ``samples`` evenly chosen ``vertices`` (V, 3) to the nearest of
    ``neutral_vertices`` (N, 3); NaN when either is empty."""
    from scipy.spatial import cKDTree

    if not len(neutral_vertices) or not len(vertices):
        return float("nan")
    sel = np.linspace(0, len(vertices) - 1, min(samples, len(vertices))).astype(np.int64)
    d, _ = cKDTree(neutral_vertices).query(vertices[sel])
    return float(np.mean(d))


def depth_panel(depth: np.ndarray, width: int) -> np.ndarray:
    """(h, width, 3) uint8 BGR: depth (H, W) mm colour-mapped over its 2nd..98th percentile (turbo, near
    red), black where there is none, with the range written on it."""
    import cv2

    valid = depth > 0
    out = np.zeros(depth.shape + (3,), np.uint8)
    if valid.any():
        lo, hi = np.percentile(depth[valid], [2, 98])
        level = np.clip((hi - depth) / max(hi - lo, 1e-6), 0, 1)  # near = 1 (red end of turbo)
        colour = cv2.applyColorMap((level * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
        out[valid] = colour[valid]
        text = f"depth {lo:.0f}-{hi:.0f} mm"
    else:
        text = "no depth"
    h = max(1, int(round(depth.shape[0] * width / depth.shape[1])))
    out = cv2.resize(out, (width, h), interpolation=cv2.INTER_AREA)
    cv2.putText(out, text, (6, h - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def mesh_panel(vertices: np.ndarray, faces: np.ndarray, camera: Camera, width: int) -> np.ndarray:
    """(h, width, 3) uint8 BGR: the mesh (V, 3) mm / (F, 3) shaded grey, seen by ``camera``'s pinhole grid
    scaled to ``width``; dark background (plain when the mesh is empty)."""
    from rigbuild.render import TexturedMesh, render_mesh

    cam = scaled_pinhole(camera, width)
    if not len(faces):
        return np.full((cam.height, cam.width, 3), 30, np.uint8)
    faces = np.asarray(faces, np.int64)
    mesh = TexturedMesh(np.asarray(vertices, float), faces, np.zeros((1, 2)), np.zeros_like(faces),
                        np.full((2, 2, 3), 200, np.uint8))
    light = camera.R.T @ np.array([-0.4, -0.5, -1.0])  # towards the light: the camera's upper left, in front
    rgb = render_mesh(cam, mesh, light_dir=light / np.linalg.norm(light), ambient=0.25, background=30,
                      with_geometry=False).color
    return np.ascontiguousarray(rgb[..., ::-1])


def frame_picture(depth: np.ndarray, vertices: np.ndarray, faces: np.ndarray, camera: Camera, title: str,
                  width: int = PANEL_WIDTH) -> np.ndarray:
    """The depth panel and the mesh panel side by side, ``title`` written on the depth panel."""
    import cv2

    left, right = depth_panel(depth, width), mesh_panel(vertices, faces, camera, width)
    h = min(left.shape[0], right.shape[0])
    out = np.concatenate([left[:h], right[:h]], axis=1)
    cv2.putText(out, title, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def write_renders(out_dir: str | os.PathLike, frames: Sequence[int], neutral_frame: int, name: str = "sequence",
                  width: int = PANEL_WIDTH) -> dict:
    """Pick the neutral and peak frames among the reconstructed ``frames`` and write their pictures to
    ``out_dir/renders/<frame:06d>.png`` from ``out_dir/depth/`` and ``out_dir/mesh/``.

    neutral_frame : the session's neutral frame (the first reconstructed frame when it was skipped).
    Returns ``{"neutral": frame | None, "peak": frame | None, "reference_camera": id | None,
    "displacement_mm": {frame: mm}}`` (the folder is created, empty when no frame was reconstructed).
    """
    import cv2

    from rigbuild.io.atomic import atomic_path
    from rigbuild.io.depth import read_depth_frame
    from rigbuild.io.ply import read_ply

    out = Path(out_dir)
    (out / "renders").mkdir(parents=True, exist_ok=True)
    frames = sorted(int(f) for f in frames)
    info: dict = {"neutral": None, "peak": None, "reference_camera": None, "displacement_mm": {}}
    if not frames:
        return info
    def mesh(f: int) -> dict:  # one frame's mesh in memory at a time
        return read_ply(out / "mesh" / f"{f:06d}.ply")

    f0 = int(neutral_frame) if int(neutral_frame) in frames else frames[0]
    first = mesh(f0)
    moved = {f: mean_displacement(first["vertices"], mesh(f)["vertices"]) for f in frames if f != f0}
    finite = {f: d for f, d in moved.items() if np.isfinite(d)}
    peak = max(finite, key=finite.__getitem__) if finite else None
    info.update(neutral=f0, peak=peak, displacement_mm={str(f): d for f, d in moved.items()})
    for f, label in ((f0, "neutral"), (peak, "peak")):
        if f is None:
            continue
        m = first if f == f0 else mesh(f)
        d = read_depth_frame(out / "depth" / f"{f:06d}.npz")
        k = reference_view(d.cameras)
        info["reference_camera"] = d.cameras[k].id
        extra = f", {moved[f]:.1f} mm from neutral" if f in moved else ""
        img = frame_picture(d.depth[k], m["vertices"], m.get("faces", np.zeros((0, 3))), d.cameras[k],
                            f"{name} frame {f} ({label}{extra}), {d.cameras[k].id}", width)
        with atomic_path(out / "renders" / f"{f:06d}.png", suffix=".png") as tmp:
            cv2.imwrite(str(tmp), img)
    return info

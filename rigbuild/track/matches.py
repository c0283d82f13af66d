"""Views, rendered sources and 2-D matches lifted to barycentric constraints (Ma et al. 2016 s. 2.2).

A *source* is a frame whose tracking mesh is known (the previous frame, or the neutral anchor frame); it
is rendered once per view into triangle-id / barycentric buffers, which give every source pixel its
surface point. The rendered motion field (where that surface point lands under the current estimate of
the target mesh) guides the search of every matching level. A 2-D match (source pixel, target pixel) in
one view is lifted to 3-D with the two frames' depth maps; the source point becomes a base point on the
tracking mesh plus a normal displacement ``h`` (:func:`normal_displacement`), and the constraint on the
target mesh is ``c = u_target - h n`` at the same barycentric point.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from rigbuild.camera import Camera
from rigbuild.errors import InputError
from rigbuild.track.features import lift
from rigbuild.track.laplacian import interpolate, interpolated_normals, normal_displacement, vertex_normals


@dataclass
class ViewFrame:
    """One camera at one frame: RGB image (H, W, 3) uint8, camera-z depth map (H, W) float32 mm (NaN = none)."""

    camera: Camera
    image: np.ndarray
    depth: np.ndarray
    _gray: np.ndarray | None = field(default=None, repr=False)
    _sift: tuple | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if self.depth is None:
            raise InputError(f"camera {self.camera.id}: no depth map", fix="run the reconstruct stage for this frame")
        if self.depth.shape != self.image.shape[:2]:
            raise InputError(f"camera {self.camera.id}: depth map {self.depth.shape} does not match image "
                             f"{self.image.shape[:2]}", fix="re-run the reconstruct stage at the session's image size")

    @property
    def gray(self) -> np.ndarray:
        if self._gray is None:
            self._gray = cv2.cvtColor(np.ascontiguousarray(self.image), cv2.COLOR_RGB2GRAY)
        return self._gray


@dataclass
class Matches:
    """Barycentric constraints on the target mesh from one level.

    tri (N,), bary (N, 3): base points on the tracking mesh; targets (N, 3) mm: ``c = u' - h n``;
    weights (N,): quality; view (N,) camera index; level: name.
    """

    tri: np.ndarray
    bary: np.ndarray
    targets: np.ndarray
    weights: np.ndarray
    view: np.ndarray
    level: str

    @staticmethod
    def empty(level: str) -> "Matches":
        return Matches(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64), level)

    @property
    def n(self) -> int:
        return int(self.tri.size)


def concat(matches: list[Matches], level: str = "all") -> Matches:
    """Concatenate match sets."""
    ms = [m for m in matches if m.n]
    if not ms:
        return Matches.empty(level)
    return Matches(np.concatenate([m.tri for m in ms]), np.concatenate([m.bary for m in ms]),
                   np.concatenate([m.targets for m in ms]), np.concatenate([m.weights for m in ms]),
                   np.concatenate([m.view for m in ms]), level)


def render_geometry(camera: Camera, vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Triangle-id (H, W) int32 (-1 = none) and barycentric (H, W, 3) float32 buffers of a mesh in a view,
    rendered with :func:`rigbuild.render.render_mesh` (flat dummy texture; only the geometry is used)."""
    from rigbuild.render import TexturedMesh, render_mesh

    faces = np.asarray(faces, dtype=np.int64)
    mesh = TexturedMesh(vertices, faces, np.zeros((1, 2)), np.zeros_like(faces), _FLAT_TEXTURE)
    res = render_mesh(camera, mesh, msaa=False)
    return res.tri_id, res.bary


_FLAT_TEXTURE = np.full((8, 8, 3), 128, dtype=np.uint8)


@dataclass
class SourceView:
    """A view of a source frame: its images/depth plus the source mesh's rendered id/barycentric buffers."""

    frame: ViewFrame
    tri_id: np.ndarray
    bary: np.ndarray

    def surface_points(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """tri (N,), bary (N, 3) of the source mesh at the pixels nearest to uv (N, 2); valid (N,)."""
        H, W = self.tri_id.shape
        iu = np.clip(np.rint(uv[:, 0]).astype(np.int64), 0, W - 1)
        iv = np.clip(np.rint(uv[:, 1]).astype(np.int64), 0, H - 1)
        inside = (uv[:, 0] >= -0.5) & (uv[:, 1] >= -0.5) & (uv[:, 0] <= W - 0.5) & (uv[:, 1] <= H - 0.5)
        tri = self.tri_id[iv, iu].astype(np.int64)
        return tri, self.bary[iv, iu].astype(np.float64), inside & (tri >= 0)


@dataclass
class Source:
    """A frame with a known tracking mesh: vertices (T, 3) mm, faces (F, 3), one :class:`SourceView` per camera."""

    vertices: np.ndarray
    faces: np.ndarray
    views: list[SourceView]
    name: str = "previous"

    @classmethod
    def build(cls, vertices: np.ndarray, faces: np.ndarray, frames: list[ViewFrame], name: str) -> "Source":
        views = []
        for f in frames:
            tri, bary = render_geometry(f.camera, vertices, faces)
            views.append(SourceView(f, tri, bary))
        return cls(np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64), views, name)

    def predict(self, view: int, tri: np.ndarray, bary: np.ndarray, estimate: np.ndarray) -> np.ndarray:
        """Predicted target pixels (N, 2) of source surface points under the target estimate (T, 3)."""
        cam = self.views[view].frame.camera
        return cam.project(interpolate(estimate, self.faces, tri, bary))

    def motion_field(self, view: int, estimate: np.ndarray, step: int = 1) -> np.ndarray:
        """Rendered motion field (H, W, 2) px: displacement of each source pixel's surface point to its
        projection under ``estimate`` (NaN where the source mesh is not seen). ``step`` > 1 computes it on a
        coarser grid and interpolates."""
        sv = self.views[view]
        H, W = sv.tri_id.shape
        ys, xs = np.mgrid[0:H:step, 0:W:step]
        tri = sv.tri_id[ys, xs]
        m = tri >= 0
        out = np.full(ys.shape + (2,), np.nan, dtype=np.float32)
        if m.any():
            pred = self.predict(view, tri[m].astype(np.int64), sv.bary[ys, xs][m].astype(np.float64), estimate)
            out[m] = (pred - np.stack([xs[m], ys[m]], 1)).astype(np.float32)
        if step > 1:
            out = cv2.resize(np.nan_to_num(out, nan=0.0), (W, H), interpolation=cv2.INTER_LINEAR)
            out[sv.tri_id < 0] = np.nan
        return out


def lift_matches(
    source: Source,
    view: int,
    src_uv: np.ndarray,
    tgt_uv: np.ndarray,
    target: ViewFrame,
    weights: np.ndarray,
    level: str,
    max_normal_offset_mm: float = 2.0,
    estimate: np.ndarray | None = None,
    max_prediction_error_mm: float | None = None,
) -> Matches:
    """2-D matches in one view -> barycentric constraints on the target mesh.

    src_uv, tgt_uv (N, 2) px in the source and target images of camera ``view``; weights (N,) quality.
    The source pixel is lifted with the source depth map and expressed as (triangle, barycentrics, h) on
    the source mesh; the target pixel is lifted with the target depth map. Matches are dropped where a
    depth is missing or discontinuous, where the base point leaves its triangle, where ``|h|`` exceeds
    ``max_normal_offset_mm`` (the reconstruction and the mesh disagree: occlusion, eyes, hair), or (given an
    ``estimate``) where the target point is further than ``max_prediction_error_mm`` from its prediction.
    """
    sv = source.views[view]
    src_uv = np.asarray(src_uv, dtype=np.float64).reshape(-1, 2)
    tgt_uv = np.asarray(tgt_uv, dtype=np.float64).reshape(-1, 2)
    tri, bary0, ok = sv.surface_points(src_uv)
    u_src = lift(sv.frame.camera, sv.frame.depth, src_uv)
    u_tgt = lift(target.camera, target.depth, tgt_uv)
    ok &= np.isfinite(u_src).all(1) & np.isfinite(u_tgt).all(1)
    if not ok.any():
        return Matches.empty(level)
    idx = np.flatnonzero(ok)
    normals = vertex_normals(source.vertices, source.faces)
    bary, h, valid = normal_displacement(source.vertices, source.faces, normals, u_src[idx], tri[idx], bary0[idx],
                                         iterations=3, tolerance=0.25)
    valid &= np.abs(h) <= max_normal_offset_mm
    n_src = interpolated_normals(normals, source.faces, tri[idx], bary)
    c = u_tgt[idx] - h[:, None] * n_src
    if estimate is not None and max_prediction_error_mm is not None:
        pred = interpolate(estimate, source.faces, tri[idx], bary)
        valid &= np.linalg.norm(pred - c, axis=1) <= max_prediction_error_mm
    keep = idx[valid]
    return Matches(tri[keep], bary[valid], c[valid], np.asarray(weights, dtype=np.float64)[keep],
                   np.full(keep.size, view, dtype=np.int64), level)

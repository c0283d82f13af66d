"""Views, sources and 2-D matches lifted to barycentric constraints (Ma et al. 2016 s. 2.2).

A *source* is a frame whose tracking mesh is known (the previous frame, or the neutral anchor frame); its
depth map gives every source pixel its surface point: the lifted pixel's closest point on the source mesh
(a render of the mesh says the same where mesh and reconstruction agree, at far higher cost). The motion
field (where that surface point lands under the current estimate of the target mesh) guides the search of
every matching level. A 2-D match (source pixel, target pixel) in one view is lifted to 3-D with the two
frames' depth maps; the source point becomes a base point on the tracking mesh plus a normal displacement
``h`` (:func:`normal_displacement`), and the constraint on the target mesh is ``c = u_target - h n`` at the same barycentric point.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from rigbuild.camera import Camera
from rigbuild.errors import InputError
from rigbuild.track.features import lift
from rigbuild.track.laplacian import interpolate, interpolated_normals, normal_displacement, vertex_normals


def map_views(fn, n_views: int, workers: int = 1) -> list:
    """``[fn(v) for v in range(n_views)]``, on a pool of ``workers`` threads when ``workers > 1``.

    The per-view work of the matching levels (SIFT, DIS flow, remaps, KD-tree queries) runs in OpenCV, NumPy
    and SciPy code that releases the GIL, so views proceed in parallel; each view touches only its own
    frames and caches. Results keep the view order.
    """
    if workers <= 1 or n_views <= 1:
        return [fn(v) for v in range(n_views)]
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=min(workers, n_views)) as pool:
        return list(pool.map(fn, range(n_views)))


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


def closest_surface_points(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, tree=None
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest points of ``points`` (N, 3) mm on the mesh (vertices (V, 3), faces (F, 3)) by libigl's AABB
    query. ``tree``: an ``igl.AABB`` already built on (vertices, faces) (built here when None).
    Returns tri (N,) int64, bary (N, 3) and distance (N,) mm."""
    import igl

    pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    if pts.shape[0] == 0:
        return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0)
    V = np.ascontiguousarray(vertices, dtype=np.float64)
    F = np.ascontiguousarray(faces, dtype=np.int64)
    if tree is None:
        d2, tri, closest = igl.point_mesh_squared_distance(pts, V, F)
    else:
        d2, tri, closest = tree.squared_distance(V, F, pts)
    f = F[tri]
    bary = np.asarray(igl.barycentric_coordinates(np.ascontiguousarray(closest), V[f[:, 0]], V[f[:, 1]], V[f[:, 2]]))
    bary = np.clip(bary, 0.0, None)
    bary /= np.maximum(bary.sum(1, keepdims=True), 1e-12)
    return np.asarray(tri, np.int64), bary, np.sqrt(np.maximum(d2, 0.0))


@dataclass
class SourcePoints:
    """Source pixels anchored on the source mesh (Ma et al. 2016 s. 2.2): the lifted pixel ``u`` written as
    a base point (tri (N,), bary (N, 3)) plus ``h`` (N,) mm along the interpolated unit normal (N, 3) there;
    ok (N,): the pixel has depth off any discontinuity, its closest mesh point is near, its base point
    stays in its triangle and ``|h|`` is small. Depends only on the source, so it is computed once per
    source pixel set and reused by every round and level."""

    tri: np.ndarray
    bary: np.ndarray
    h: np.ndarray
    normal: np.ndarray
    ok: np.ndarray

    def subset(self, idx: np.ndarray) -> "SourcePoints":
        return SourcePoints(self.tri[idx], self.bary[idx], self.h[idx], self.normal[idx], self.ok[idx])


@dataclass
class SourceView:
    """A view of a source frame: its image/depth plus the source mesh. A source pixel's surface point is its
    depth-map point's closest point on the source mesh (no render needed: the depth map already says which
    surface the pixel sees; points further than ``max_offset_mm`` from the mesh are not on it).
    ``tree``/``normals``: the source mesh's AABB tree and unit vertex normals, shared by the views (built once
    per source); ``cache``: per-view results that depend only on the source (grids, keypoint anchors)."""

    frame: ViewFrame
    vertices: np.ndarray
    faces: np.ndarray
    max_offset_mm: float = 2.0
    max_normal_offset_mm: float = 2.0
    tree: object = field(default=None, repr=False)
    normals: np.ndarray | None = field(default=None, repr=False)
    cache: dict = field(default_factory=dict, repr=False)

    def surface_points(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """tri (N,), bary (N, 3) of the source mesh under pixels uv (N, 2); valid (N,)."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        X = lift(self.frame.camera, self.frame.depth, uv)
        return self._closest(X)

    def _closest(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        ok = np.isfinite(X).all(1)
        tri = np.zeros(X.shape[0], np.int64)
        bary = np.full((X.shape[0], 3), 1.0 / 3.0)
        if ok.any():
            t, b, d = closest_surface_points(X[ok], self.vertices, self.faces, tree=self.tree)
            tri[ok], bary[ok] = t, b
            ok[ok] = d <= self.max_offset_mm
        return tri, bary, ok

    def grid_surface_points(self, box: tuple[int, int, int, int], step: int, offset: int = 0
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Surface points of the pixel grid ``y0 + offset + step i``, ``x0 + offset + step j`` (i, j >= 0) over
        ``box`` (y0, y1, x0, x1; the grid ends below ``y1 + step`` when ``offset`` is 0, below ``y1`` otherwise):
        uv (gy, gx, 2) and tri, bary, ok flattened. Cached per (box, step, offset); a grid that is a subset of
        a cached one is read from it."""
        key = ("grid", box, step, offset)
        if key in self.cache:
            return self.cache[key]
        y0, y1, x0, x1 = box
        end_y, end_x = (y1 + step, x1 + step) if offset == 0 else (y1, x1)
        ys, xs = np.mgrid[y0 + offset:end_y:step, x0 + offset:end_x:step]
        uv = np.stack([xs, ys], 2).astype(np.float64)
        res = None
        for k2, val in list(self.cache.items()):
            if not (isinstance(k2, tuple) and k2[0] == "grid" and k2[1] == box):
                continue
            s2, o2 = k2[2], k2[3]
            if step % s2 or (offset - o2) % s2 or offset < o2:
                continue
            uv2 = val[0]
            iy = (ys[:, 0] - (y0 + o2)) // s2
            ix = (xs[0] - (x0 + o2)) // s2
            if iy.size and ix.size and (iy[-1] >= uv2.shape[0] or ix[-1] >= uv2.shape[1]):
                continue
            flat = (iy[:, None] * uv2.shape[1] + ix[None, :]).ravel()
            res = (uv, val[1][flat], val[2][flat], val[3][flat])
            break
        if res is None:
            res = (uv, *self.surface_points(uv.reshape(-1, 2)))
        self.cache[key] = res
        return res

    def anchored(self, uv: np.ndarray, surface: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
                 ) -> SourcePoints:
        """Source pixels uv (N, 2) anchored on the source mesh (:class:`SourcePoints`). ``surface``: their
        precomputed :meth:`surface_points` (tri, bary, ok)."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        u = lift(self.frame.camera, self.frame.depth, uv)
        tri, bary0, ok = self._closest(u) if surface is None else surface
        ok = ok & np.isfinite(u).all(1)
        n = uv.shape[0]
        bary, h, nrm = bary0.copy(), np.zeros(n), np.zeros((n, 3))
        idx = np.flatnonzero(ok)
        if idx.size:
            normals = self.normals if self.normals is not None else vertex_normals(self.vertices, self.faces)
            b, hh, valid = normal_displacement(self.vertices, self.faces, normals, u[idx], tri[idx], bary0[idx],
                                               iterations=3, tolerance=0.25)
            valid &= np.abs(hh) <= self.max_normal_offset_mm
            bary[idx], h[idx] = b, hh
            nrm[idx] = interpolated_normals(normals, self.faces, tri[idx], b)
            ok[idx] = valid
        return SourcePoints(tri, bary, h, nrm, ok)

    def surface_box(self, pad: int = 16) -> tuple[int, int, int, int] | None:
        """Pixel box (y0, y1, x0, x1) around the source's depth (the observed surface), or None (cached)."""
        key = ("box", pad)
        if key not in self.cache:
            fin = np.isfinite(self.frame.depth)
            rows, cols = np.flatnonzero(fin.any(1)), np.flatnonzero(fin.any(0))
            if rows.size == 0:
                self.cache[key] = None
            else:
                H, W = fin.shape
                self.cache[key] = (max(rows[0] - pad, 0), min(rows[-1] + pad + 1, H),
                                   max(cols[0] - pad, 0), min(cols[-1] + pad + 1, W))
        return self.cache[key]


@dataclass
class Source:
    """A frame with a known tracking mesh: vertices (T, 3) mm, faces (F, 3), one :class:`SourceView` per camera."""

    vertices: np.ndarray
    faces: np.ndarray
    views: list[SourceView]
    name: str = "previous"

    @classmethod
    def build(cls, vertices: np.ndarray, faces: np.ndarray, frames: list[ViewFrame], name: str) -> "Source":
        """The source's views sharing one AABB tree and one set of vertex normals of its mesh."""
        import igl

        v = np.ascontiguousarray(vertices, dtype=np.float64)
        f = np.ascontiguousarray(faces, dtype=np.int64)
        tree = igl.AABB()
        tree.init(v, f)
        normals = vertex_normals(v, f)
        return cls(v, f, [SourceView(fr, v, f, tree=tree, normals=normals) for fr in frames], name)

    def predict(self, view: int, tri: np.ndarray, bary: np.ndarray, estimate: np.ndarray) -> np.ndarray:
        """Predicted target pixels (N, 2) of source surface points under the target estimate (T, 3)."""
        cam = self.views[view].frame.camera
        return cam.project(interpolate(estimate, self.faces, tri, bary))

    def motion_field(self, view: int, estimate: np.ndarray, step: int = 8,
                     box: tuple[int, int, int, int] | None = None) -> np.ndarray:
        """Motion field (h, w, 2) px over ``box`` (y0, y1, x0, x1; default the whole image): displacement of
        each source pixel's surface point to its projection under ``estimate``, sampled every ``step`` px and
        interpolated bilinearly (the field is smooth); NaN where no grid sample near the pixel is on the mesh.
        The grid's surface points are cached on the view (a source is matched many times)."""
        sv = self.views[view]
        H, W = sv.frame.depth.shape
        box = tuple(int(b) for b in (box or (0, H, 0, W)))
        y0, y1, x0, x1 = box
        grid, tri, bary, ok = sv.grid_surface_points(box, step)
        uv = grid.reshape(-1, 2)
        coarse = np.zeros((uv.shape[0], 2), np.float32)
        if ok.any():
            coarse[ok] = (self.predict(view, tri[ok], bary[ok], estimate) - uv[ok]).astype(np.float32)
        gy, gx = grid.shape[:2]
        # normalized-convolution fill of the grid holes, then bilinear up-sampling to the pixel box
        wgt = ok.reshape(gy, gx).astype(np.float32)
        c = coarse.reshape(gy, gx, 2) * wgt[..., None]
        sz = (x1 - x0, y1 - y0)
        mapx = (np.arange(x0, x1, dtype=np.float32) - x0) / step
        mapy = (np.arange(y0, y1, dtype=np.float32) - y0) / step
        mx, my = np.meshgrid(mapx.astype(np.float32), mapy.astype(np.float32))
        up_w = cv2.remap(wgt, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        up_c = cv2.remap(c, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        out = up_c / np.maximum(up_w, 1e-6)[..., None]
        out[up_w < 1e-3] = np.nan
        assert out.shape[:2] == (sz[1], sz[0])
        return out


def lift_matches(
    source: Source,
    view: int,
    src: SourcePoints,
    tgt_uv: np.ndarray,
    target: ViewFrame,
    weights: np.ndarray,
    level: str,
    estimate: np.ndarray | None = None,
    max_prediction_error_mm: float | None = None,
) -> Matches:
    """2-D matches in one view -> barycentric constraints on the target mesh.

    src: the matches' source pixels anchored on the source mesh (``source.views[view].anchored(src_uv)``,
    (triangle, barycentrics, h, normal) per pixel); tgt_uv (N, 2) px in the target image of camera ``view``;
    weights (N,) quality. The target pixel is lifted with the target depth map ``u'`` and the constraint is
    ``c = u' - h n`` at the source's base point. Matches are dropped where the source anchoring failed (see
    :class:`SourcePoints`), where the target depth is missing or discontinuous, or (given an ``estimate``)
    where the target point is further than ``max_prediction_error_mm`` from its prediction.
    """
    tgt_uv = np.asarray(tgt_uv, dtype=np.float64).reshape(-1, 2)
    u_tgt = lift(target.camera, target.depth, tgt_uv)
    ok = src.ok & np.isfinite(u_tgt).all(1)
    if not ok.any():
        return Matches.empty(level)
    idx = np.flatnonzero(ok)
    c = u_tgt[idx] - src.h[idx, None] * src.normal[idx]
    valid = np.ones(idx.size, dtype=bool)
    if estimate is not None and max_prediction_error_mm is not None:
        pred = interpolate(estimate, source.faces, src.tri[idx], src.bary[idx])
        valid = np.linalg.norm(pred - c, axis=1) <= max_prediction_error_mm
    keep = idx[valid]
    return Matches(src.tri[keep], src.bary[keep], c[valid], np.asarray(weights, dtype=np.float64)[keep],
                   np.full(keep.size, view, dtype=np.int64), level)

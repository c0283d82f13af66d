"""Coarse-to-fine tracking of a ROM sequence (Ma et al. 2016 s. 2): per frame, three levels of image
correspondence (painted dots -> SIFT -> guided dense flow), each lifted to barycentric constraints and
solved with the Laplacian deformation of eq. 1; every frame is matched both against the previous frame
and against the neutral anchor frame (drift control); lost tracking is detected per frame.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from rigbuild.errors import InputError
from rigbuild.geometry.rigid import apply_rigid, fit_rigid_motion
from rigbuild.track.features import (
    assign_detections,
    cluster_lifted_dots,
    consistent_displacements,
    detect_dots,
    lift,
    surface_neighbours,
    triangulate,
)
from rigbuild.track.flow import flow_matches, points_flow
from rigbuild.track.laplacian import LaplacianSolver, vertex_normals
from rigbuild.track.matches import Matches, Source, ViewFrame, concat, map_views
from rigbuild.track.params import DotParams, TrackParams
from rigbuild.track.register import RayObservations
from rigbuild.track.sparse import sift_features, sparse_matches

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------------- dots
def frame_dots(frame: ViewFrame, params: DotParams) -> np.ndarray:
    """Dot detections (N, 2) of a view (cached on the frame)."""
    if not hasattr(frame, "_dots") or frame._dots is None:
        mask = np.isfinite(frame.depth)
        frame._dots = detect_dots(frame.image, params, mask=mask)[0]
    return frame._dots


def neutral_dots(frames: list[ViewFrame], params: DotParams, cluster_mm: float = 2.5, fill_radius_px: int = 8
                 ) -> tuple[np.ndarray, RayObservations]:
    """Unlabeled 3-D dots of a neutral frame: detections lifted with the depth maps, clustered across views,
    triangulated from their 2-D detections. Returns dots (D, 3) mm and the detections as rays (dot index)."""
    dets = [frame_dots(f, params) for f in frames]
    # stereo often leaves a hole on a dark dot: the skin around it gives the depth for the clustering (the dots
    # themselves are triangulated from their 2-D centres below)
    lifted = [lift(f.camera, f.depth, d, fill_radius_px=fill_radius_px) if d.shape[0] else np.zeros((0, 3))
              for f, d in zip(frames, dets)]
    clusters = cluster_lifted_dots(lifted, radius_mm=cluster_mm)
    C, D = len(frames), len(clusters)
    uv = np.full((C, D, 2), np.nan)
    for k, members in enumerate(clusters):
        for c, i in members:
            uv[c, k] = dets[c][i]
    X, rms, n = triangulate([f.camera for f in frames], uv)
    good = np.isfinite(X).all(1) & (rms <= 2.5)
    X, uv = X[good], uv[:, good]
    mk, org, drc = [], [], []
    for c, f in enumerate(frames):
        ok = np.isfinite(uv[c]).all(1)
        if ok.any():
            mk.append(np.flatnonzero(ok))
            org.append(np.repeat(f.camera.center[None], ok.sum(), 0))
            drc.append(f.camera.rays(uv[c, ok]))
    rays = RayObservations(np.concatenate(mk), np.concatenate(org), np.concatenate(drc)) if mk else \
        RayObservations(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)))
    return X, rays


def scan_from_depth(frames: list[ViewFrame], step: int = 2, normal_neighbours: int = 40
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Point cloud (N, 3) mm with unit normals (N, 3) from the depth maps of a frame (every ``step`` px).

    Normals: the PCA of each point's ``normal_neighbours`` nearest points of the merged cloud
    (:func:`rigbuild.geometry.mesh.point_cloud_normals`), oriented towards the camera like the cross product of
    neighbouring lifted pixels; 0 keeps those one-pixel normals (their noise slides the point-to-plane
    registration along the surface)."""
    pts, nrm = [], []
    for f in frames:
        H, W = f.depth.shape
        ys, xs = np.mgrid[0:H - step:step, 0:W - step:step]
        uv = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64)
        P = lift(f.camera, f.depth, uv)
        Px = lift(f.camera, f.depth, uv + [step, 0])
        Py = lift(f.camera, f.depth, uv + [0, step])
        n = np.cross(Px - P, Py - P)
        ln = np.linalg.norm(n, axis=1)
        ok = np.isfinite(n).all(1) & (ln > 0)
        n = n[ok] / ln[ok, None]
        view = f.camera.center - P[ok]
        n *= np.sign(np.einsum("nd,nd->n", n, view))[:, None]
        pts.append(P[ok])
        nrm.append(n)
    pts, nrm = np.concatenate(pts), np.concatenate(nrm)
    if normal_neighbours > 0:
        from rigbuild.geometry.mesh import point_cloud_normals

        nrm = point_cloud_normals(pts, nrm, normal_neighbours)
    return pts, nrm


def _subset(m: Matches, keep: np.ndarray) -> Matches:
    return Matches(m.tri[keep], m.bary[keep], m.targets[keep], m.weights[keep], m.view[keep], m.level)


# --------------------------------------------------------------------------------------------- tracker
@dataclass
class FrameStats:
    """Per-frame tracking statistics (one row of residuals.csv)."""

    frame: int
    dots: int = 0
    sparse: int = 0
    flow: int = 0
    anchor_matches: int = 0
    residual_median_mm: float = float("nan")
    residual_p90_mm: float = float("nan")
    lost: bool = False
    reason: str = ""


class SequenceTracker:
    """Tracks one sequence starting from the actor's registered neutral.

    local_neutral : (T, 3) mm registered neutral on the tracking mesh; faces : (F, 3) tracking-mesh
    triangles; marker_local : (M,) tracking-mesh ids of the dot (marker) vertices; anchor_frames : the views
    of the neutral frame the neutral was registered to (the anchor for drift); dot_points : (tri (M,), bary
    (M, 3)) the dots' own surface points on the tracking mesh (each detected dot where it sits on the
    registered neutral, not a template vertex) instead of ``marker_local``'s vertices (None: the vertices).
    The Laplacian system's symbolic factorization is computed once here and reused for every solve.
    """

    def __init__(self, local_neutral: np.ndarray, faces: np.ndarray, marker_local: np.ndarray,
                 anchor_frames: list[ViewFrame], params: TrackParams | None = None,
                 vertex_tri: np.ndarray | None = None, vertex_corner: np.ndarray | None = None,
                 dot_points: tuple[np.ndarray, np.ndarray] | None = None):
        self.p = params or TrackParams()
        self.neutral = np.asarray(local_neutral, dtype=np.float64)
        self.faces = np.asarray(faces, dtype=np.int64)
        self.marker_local = np.asarray(marker_local, dtype=np.int64)
        self.solver = LaplacianSolver(self.neutral, self.faces)
        self.ring = self.solver.L.copy()  # 1-ring pattern (with the diagonal) for the confidences
        self.ring.data = (np.abs(self.ring.data) > 0).astype(np.float64)
        self.solver.workers = self.p.workers
        if vertex_tri is None:
            vertex_tri = np.full(self.neutral.shape[0], -1, np.int64)
            vertex_corner = np.zeros(self.neutral.shape[0], np.int64)
            for c in range(3):
                vertex_tri[self.faces[:, c]] = np.arange(self.faces.shape[0])
                vertex_corner[self.faces[:, c]] = c
        self.vertex_tri, self.vertex_corner = vertex_tri, vertex_corner
        if dot_points is None:
            self.dot_tri, self.dot_bary = self._vertex_points(self.marker_local)
        else:
            self.dot_tri = np.asarray(dot_points[0], np.int64)
            self.dot_bary = np.asarray(dot_points[1], np.float64)
            self.marker_local = self.faces[self.dot_tri, np.argmax(self.dot_bary, 1)]  # each dot's nearest vertex
        # dot neighbourhoods along the surface and the dot spacing, for the displacement-consistency test
        painted = "features" in self.p.levels and self.marker_local.size > 0
        if painted:
            self.dot_nbrs, nd = surface_neighbours(self.neutral, self.faces, self.marker_local,
                                                   k=self.p.dot_neighbours)
            first = nd[:, 0][np.isfinite(nd[:, 0])]
        else:  # an unpainted face (no dots level): no dot neighbourhoods
            self.dot_nbrs, first = np.full((self.marker_local.size, self.p.dot_neighbours), -1), np.zeros(0)
        self.dot_spacing_mm = float(np.median(first)) if first.size else float("inf")
        self.anchor = Source.build(self.neutral, self.faces, anchor_frames, "anchor") if self.p.anchor else None
        self.anchor_dots = self.dot_matches(anchor_frames, self.neutral, self.p.dot_radius_px[-1]).n if painted else 0

    # ------------------------------------------------------------------ levels
    def _vertex_points(self, ids):
        bary = np.zeros((ids.size, 3))
        bary[np.arange(ids.size), self.vertex_corner[ids]] = 1.0
        return self.vertex_tri[ids], bary

    def _dot_positions(self, estimate: np.ndarray) -> np.ndarray:
        """(M, 3) mm the dots' surface points on the tracking-mesh vertices ``estimate``."""
        return np.einsum("mk,mkd->md", self.dot_bary, estimate[self.faces[self.dot_tri]])

    def _dot_normals(self, estimate: np.ndarray) -> np.ndarray:
        """(M, 3) the interpolated vertex normals at the dots (not renormalized: used for a facing sign)."""
        return np.einsum("mk,mkd->md", self.dot_bary, vertex_normals(estimate, self.faces)[self.faces[self.dot_tri]])

    def dot_matches(self, frames: list[ViewFrame], estimate: np.ndarray, radius_px: float,
                    consistent: bool = False, predicted_uv: np.ndarray | None = None) -> Matches:
        """Dots assigned to the predicted marker projections, triangulated -> constraints at marker vertices.
        ``consistent``: drop dots that do not move like their neighbours (``dot_consistency``);
        ``predicted_uv`` (C, M, 2) px: predictions to use instead of the estimate's projections (NaN = none)."""
        M = self.marker_local.size
        C = len(frames)
        uv = np.full((C, M, 2), np.nan)
        pred3 = self._dot_positions(estimate)
        nrm = self._dot_normals(estimate)
        for c, f in enumerate(frames):
            det = frame_dots(f, self.p.dots)
            cam = f.camera
            pr = cam.project(pred3) if predicted_uv is None else predicted_uv[c].copy()
            facing = np.einsum("md,md->m", nrm, cam.center - pred3) > 0
            pr[~facing] = np.nan
            a = assign_detections(pr, det, radius_px * cam.width / 1280.0)
            uv[c, a >= 0] = det[a[a >= 0]]
        X, rms, n = triangulate([f.camera for f in frames], uv)
        ok = np.isfinite(X).all(1) & (rms <= self.p.max_triangulation_rms_px)
        if consistent and self.p.dot_consistency > 0:
            ok = consistent_displacements(np.where(ok[:, None], X - pred3, 0.0), ok, self.dot_nbrs,
                                          self.p.dot_consistency * self.dot_spacing_mm)
        ids = np.flatnonzero(ok)
        tri, bary = self.dot_tri[ids], self.dot_bary[ids]
        return Matches(tri, bary, X[ids], np.full(ids.size, self.p.dot_weight), np.zeros(ids.size, np.int64), "features")

    def dot_flow_prediction(self, previous: Source, frames: list[ViewFrame], estimate: np.ndarray) -> np.ndarray:
        """Where each dot should be in each view, by image motion: (C, M, 2) px.

        The dots' projections under ``estimate`` (the previous frame's mesh) moved by the DIS optical flow
        from the previous image to the current one (:func:`rigbuild.track.flow.points_flow`). A dot that
        moved further than the coarse assignment radius between frames (a jaw-open onset) is otherwise
        assigned to its neighbour's detection.
        """
        pred3 = self._dot_positions(estimate)

        def view(c: int) -> np.ndarray:
            uv = frames[c].camera.project(pred3)
            return uv + points_flow(previous.views[c].frame.gray, frames[c].gray, uv, scale=self.p.dot_flow_scale)

        return np.stack(map_views(view, len(frames), self.p.workers))

    def _robust_rigid(self, m: Matches, estimate: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """Trimmed Kabsch of the matches' current positions onto their targets: R, t, inlier RMS (mm)."""
        src = np.einsum("nk,nkd->nd", m.bary, estimate[self.faces[m.tri]])
        keep = np.ones(m.n, dtype=bool)
        for _ in range(4):
            R, t = fit_rigid_motion(src[keep], m.targets[keep])
            r = np.linalg.norm(apply_rigid(src, R, t) - m.targets, axis=1)
            keep = r <= max(2.5 * np.median(r), 1.0)
            if keep.sum() < 4:
                keep = r <= np.sort(r)[min(3, r.size - 1)]
        rms = float(np.sqrt(np.mean(r[keep] ** 2)))
        return R, t, rms

    def _solve(self, m: Matches, lam: float, estimate: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        delta = self.solver.rotated_delta(estimate)
        p, rep = self.solver.solve(m.tri, m.bary, m.targets, m.weights, lam, delta=delta, prior=estimate)
        return p, rep.residual_mm

    # ------------------------------------------------------------------ frames
    def rigid_start(self, frames: list[ViewFrame], sequence: str = "") -> np.ndarray:
        """Rigidly place the neutral on the first frame of a sequence from its dots; raise InputError when
        the first frame is not neutral-like (rigid dot residual above ``neutral_check_mm``).

        The first assignment predicts the dots by optical flow from the anchor (global neutral) frame's images
        (:meth:`dot_flow_prediction`, with ``anchor`` and ``dot_flow``): a sequence's rest pose differs from
        the anchor's by a head motion of several degrees and millimetres, tens of pixels, which trades dots
        between neighbours in an assignment at the unmoved neutral's projections."""
        if "features" not in self.p.levels:
            return self._rigid_start_from_features(frames, sequence)
        flow_uv = (self.dot_flow_prediction(self.anchor, frames, self.neutral)
                   if self.anchor is not None and self.p.dot_flow else None)
        m = self.dot_matches(frames, self.neutral, self.p.dot_radius_px[0], predicted_uv=flow_uv)
        if m.n < 4:
            raise InputError(f"sequence '{sequence}': only {m.n} painted dots found on its first frame",
                             fix="check the images of the sequence's neutral_frame and the dot detector settings")
        R, t, _ = self._robust_rigid(m, self.neutral)
        for r_px in self.p.dot_radius_px[1:]:  # re-assign closer to the rigid prediction
            m2 = self.dot_matches(frames, apply_rigid(self.neutral, R, t), r_px)
            if m2.n >= 4:
                R, t, _ = self._robust_rigid(m2, self.neutral)
        # neutral check: the dots found within neutral_check_radius_px of the rigidly placed neutral (a dot an
        # expression moved by up to about that radius is found there and measured; the finest radius would find
        # only the dots that did not move) must fit it within neutral_check_mm, and most of the anchor's dots must
        # be found (a dot the head motion turned away or the light dimmed is not evidence of an expression)
        m = self.dot_matches(frames, apply_rigid(self.neutral, R, t), self.p.neutral_check_radius_px)
        if m.n < self.p.lost_min_dot_fraction * self.anchor_dots:
            raise InputError(
                f"sequence '{sequence}': its first frame is not neutral-like (only {m.n} of the {self.anchor_dots} "
                f"painted dots of the neutral frame are found near the rigidly placed neutral)",
                path="session.yaml", fix=f"set rom[{sequence}].neutral_frame to a frame where the actor is at rest")
        src = np.einsum("nk,nkd->nd", m.bary, self.neutral[self.faces[m.tri]])
        r = np.linalg.norm(apply_rigid(src, R, t) - m.targets, axis=1)
        p90 = float(np.percentile(r, 90))
        if p90 > self.p.neutral_check_mm:
            raise InputError(
                f"sequence '{sequence}': its first frame is not neutral-like (the neutral fits its {m.n} dots rigidly "
                f"only to {p90:.2f} mm (90th percentile) > {self.p.neutral_check_mm} mm)",
                path="session.yaml", fix=f"set rom[{sequence}].neutral_frame to a frame where the actor is at rest")
        return apply_rigid(self.neutral, R, t)

    def _rigid_start_from_features(self, frames: list[ViewFrame], sequence: str) -> np.ndarray:
        """Rigidly place the neutral on the first frame of a sequence from SIFT matches against the anchor
        (global neutral) frame: the start of an unpainted face (no ``features`` level). The first round searches
        ``dot_radius_px[0]`` around the unmoved neutral's predictions (a rest pose differs from the anchor's by a
        head motion of tens of pixels), the schedule's rounds then re-match around the rigid placement. The
        neutral check: the 90th percentile of the first round's residuals re-matched around the rigid neutral
        within ``neutral_check_mm``, from at least ``lost_min_matches`` matches per view."""
        from dataclasses import replace

        if self.anchor is None:
            raise InputError(f"sequence '{sequence}': an unpainted face (no painted dots) needs the anchor frame "
                             "to start a sequence", path="config params.track.anchor", fix="set anchor: true")
        sch = self.p.sparse
        wide = replace(sch, radius_px=(float(self.p.dot_radius_px[0]),))
        m = sparse_matches(self.anchor, frames, self.neutral, 0, wide, max_prediction_error_mm=float("inf"),
                           workers=self.p.workers)
        need = self.p.lost_min_matches * len(frames)
        if m.n < max(need, 4):
            raise InputError(f"sequence '{sequence}': only {m.n} image features of its first frame match the "
                             f"neutral frame's (at least {need} needed)", path="session.yaml",
                             fix=f"set rom[{sequence}].neutral_frame to a frame where the actor is at rest")
        R, t, _ = self._robust_rigid(m, self.neutral)
        for k in range(len(sch.radius_px)):
            m = sparse_matches(self.anchor, frames, apply_rigid(self.neutral, R, t), k, sch, workers=self.p.workers)
            if m.n >= 4:
                R, t, _ = self._robust_rigid(m, self.neutral)
        m = sparse_matches(self.anchor, frames, apply_rigid(self.neutral, R, t), 0, sch, workers=self.p.workers)
        src = np.einsum("nk,nkd->nd", m.bary, self.neutral[self.faces[m.tri]])
        r = np.linalg.norm(apply_rigid(src, R, t) - m.targets, axis=1)
        p90 = float(np.percentile(r, 90)) if r.size else float("inf")
        if m.n < need or p90 > self.p.neutral_check_mm:
            raise InputError(
                f"sequence '{sequence}': its first frame is not neutral-like (the neutral fits {m.n} image features "
                f"rigidly only to {p90:.2f} mm (90th percentile; at most {self.p.neutral_check_mm} mm from at least "
                f"{need} features))", path="session.yaml",
                fix=f"set rom[{sequence}].neutral_frame to a frame where the actor is at rest")
        return apply_rigid(self.neutral, R, t)

    def _prefetch_detections(self, frames: list[ViewFrame]):
        """Detect the frame's painted dots (all views at once) and, with ``workers`` > 1, start its SIFT
        features in the background while the (serial) dot level runs. Returns a function that waits for the
        SIFT features (the detections are cached on the frames)."""
        if "features" in self.p.levels:
            map_views(lambda c: frame_dots(frames[c], self.p.dots), len(frames), self.p.workers)
        if "sparse" not in self.p.levels or self.p.workers <= 1:
            return lambda: None
        from concurrent.futures import ThreadPoolExecutor

        pool = ThreadPoolExecutor(max_workers=max(self.p.workers - 1, 1))
        jobs = [pool.submit(sift_features, f, self.p.sparse) for f in frames]
        pool.shutdown(wait=False)

        def wait() -> None:
            for j in jobs:
                j.result()

        return wait

    def track_frame(self, frames: list[ViewFrame], estimate: np.ndarray, sources: list[Source], frame: int
                    ) -> tuple[np.ndarray, FrameStats, Matches]:
        """Register the tracking mesh to one target frame, coarse to fine. Returns vertices (T, 3), stats and
        the final constraint set."""
        st = FrameStats(frame)
        p = estimate.copy()
        sift_ready = self._prefetch_detections(frames)
        dots = Matches.empty("features")
        if "features" in self.p.levels:
            for k, r in enumerate(self.p.dot_radius_px):
                flow_uv = None
                if k == 0:  # coarse: robust rigid motion first, then re-assign
                    prev = next((s for s in sources if s.name == "previous"), None)
                    if prev is not None and self.p.dot_flow:
                        flow_uv = self.dot_flow_prediction(prev, frames, p)
                    dots = self.dot_matches(frames, p, r, predicted_uv=flow_uv)
                    if dots.n < 4:
                        continue
                    R, t, _ = self._robust_rigid(dots, p)
                    p = apply_rigid(p, R, t)
                dots = self.dot_matches(frames, p, r, consistent=True, predicted_uv=flow_uv)
                if dots.n < 4:
                    continue
                for _ in range(self.p.rotation_iterations):
                    p, res = self._solve(dots, self.p.lam_features, p)
                    bad = res > max(4.0 * np.median(res), 0.5)
                    if bad.any() and (~bad).sum() >= 4:  # drop mislabeled dots and re-solve
                        dots = _subset(dots, ~bad)
            st.dots = dots.n
        sparse = Matches.empty("sparse")
        if "sparse" in self.p.levels:
            sift_ready()
            sch = self.p.sparse
            for k in range(len(sch.radius_px)):
                parts = []
                for s in sources:
                    mm = sparse_matches(s, frames, p, k, sch, workers=self.p.workers)
                    if s.name == "anchor":
                        mm.weights = mm.weights * self.p.anchor_weight
                        st.anchor_matches = mm.n
                    parts.append(mm)
                sparse = concat(parts, "sparse")
                allm = concat([dots, sparse])
                if allm.n >= 4:
                    p, _ = self._solve(allm, sch.lam[min(k, len(sch.lam) - 1)], p)
            st.sparse = sparse.n
        flow = Matches.empty("flow")
        if "flow" in self.p.levels:
            for _ in range(self.p.flow_iterations):
                parts = []
                for s in sources:
                    if s.name not in self.p.flow.sources:
                        continue
                    mm = flow_matches(s, frames, p, self.p.flow, workers=self.p.workers)
                    if s.name == "anchor":
                        mm.weights = mm.weights * self.p.anchor_weight
                        st.anchor_matches = mm.n
                    parts.append(mm)
                flow = concat(parts, "flow")
                allm = concat([dots, sparse, flow])
                if allm.n >= 4:
                    p, _ = self._solve(allm, self.p.lam_flow, p)
            st.flow = flow.n
        final = concat([dots, sparse, flow])
        if final.n:
            res = np.linalg.norm(np.einsum("nk,nkd->nd", final.bary, p[self.faces[final.tri]]) - final.targets, axis=1)
            st.residual_median_mm = float(np.median(res))
            st.residual_p90_mm = float(np.percentile(res, 90))
        n_img = sparse.n + flow.n
        needs_img = ("sparse" in self.p.levels) or ("flow" in self.p.levels)
        reasons = []
        if final.n < 4:
            reasons.append(f"{final.n} constraints")
        if needs_img and n_img < self.p.lost_min_matches * len(frames):
            reasons.append(f"{n_img} image matches < {self.p.lost_min_matches * len(frames)}")
        if "features" in self.p.levels and st.dots < self.p.lost_min_dot_fraction * self.anchor_dots:
            reasons.append(f"{st.dots} painted dots found < {self.p.lost_min_dot_fraction:g} of the "
                           f"{self.anchor_dots} on the neutral frame")
        if np.isfinite(st.residual_median_mm) and st.residual_median_mm > self.p.lost_residual_mm:
            reasons.append(f"median residual {st.residual_median_mm:.2f} mm > {self.p.lost_residual_mm} mm")
        st.lost = bool(reasons)
        st.reason = "; ".join(reasons)
        if st.lost:
            log.warning("frame %d: tracking lost (%s)", frame, st.reason)
        return p, st, final

    def track(self, frames_per_time: list[list[ViewFrame]], frame_ids: list[int], sequence: str = "",
              progress=None) -> tuple[np.ndarray, np.ndarray, list[FrameStats]]:
        """Track a whole sequence (its first frame is the neutral frame).

        frames_per_time : per frame, the views (ViewFrame per camera, same camera order as the anchor).
        Returns vertices (F, T, 3) mm, per-vertex confidence (F, T) in [0, 1], per-frame stats.
        """
        out, conf, stats = [], [], []
        sources_prev: Source | None = None
        prev = prev2 = None
        from rigbuild.progress import progress as progress_bar

        steps = progress_bar(list(zip(frames_per_time, frame_ids)), f"tracking {sequence}", unit="frame")
        for i, (frames, fid) in enumerate(steps):
            if i == 0:
                starts = "features" in self.p.levels or ("sparse" in self.p.levels and self.anchor is not None)
                est = self.rigid_start(frames, sequence) if starts else self.neutral.copy()
                srcs = [self.anchor] if self.anchor is not None else []
            else:
                est = prev + (prev - prev2) if (prev2 is not None and self.p.constant_velocity) else prev.copy()
                srcs = [sources_prev] + ([self.anchor] if self.anchor is not None else [])
            p, st, final = self.track_frame(frames, est, [s for s in srcs if s is not None], fid)
            out.append(p)
            conf.append(self.confidence(final, lost=st.lost))
            stats.append(st)
            if progress:
                progress(st)
            prev2, prev = prev, p
            if i + 1 < len(frames_per_time) and (("sparse" in self.p.levels) or ("flow" in self.p.levels)):
                sources_prev = Source.build(p, self.faces, frames, "previous")
        return np.stack(out), np.stack(conf), stats

    def confidence(self, m: Matches, lost: bool = False) -> np.ndarray:
        """Per-vertex confidence (T,) of a frame's final constraints (:func:`match_confidence`); 0 on a lost frame."""
        if lost:
            return np.zeros(self.neutral.shape[0])
        return match_confidence(self.ring, self.faces, m, self.p.confidence_scale)


def match_confidence(ring, faces: np.ndarray, m: Matches, scale: float) -> np.ndarray:
    """Per-vertex confidence (T,) in [0, 1]: ``1 - exp(-s / (scale * median s))`` with ``s`` the match weight
    (quality x barycentric share) landing on the vertex's 1-ring (``ring`` (T, T) 0/1 with the diagonal, e.g.
    the Laplacian's pattern; faces (F, 3)) and the median over the vertices that have any; 0 where none lands.

    ``s`` says how well the images pin the vertex down."""
    T = ring.shape[0]
    if m.n == 0:
        return np.zeros(T)
    s = np.zeros(T)
    for k in range(3):
        np.add.at(s, faces[m.tri, k], m.weights * m.bary[:, k])
    s = ring.T @ s
    pos = s[s > 0]
    if pos.size == 0:
        return np.zeros(T)
    return 1.0 - np.exp(-s / (scale * float(np.median(pos))))

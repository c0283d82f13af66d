"""Multi-camera rig calibration from board detections: intrinsics -> pose graph -> global bundle adjustment.

World frame: the reference camera's frame (default: the first camera listed in session.yaml), i.e. that
camera has ``R = I, t = 0``; x right, y down, z forward (OpenCV axes), millimetres. The metric scale comes
from the board's square size (the board corners are fixed in mm during the adjustment). No gravity/up.

Image pairing: images of different cameras with the same view key (file name, e.g. ``calib/cam03/12.png``
and ``calib/cam07/12.png``) show the same board pose (synchronized capture); that is what links cameras.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np

from rigbuild.calibrate import qa
from rigbuild.calibrate.bundle import CX, CY, FX, K3_INDEX, N_CAM, TANGENTIAL, BundleResult, Observations, \
    AUTO_SCALE_SIGMAS, bundle_adjust, robust_noise_px, view_angle_weights, \
    view_angles_deg
from rigbuild.calibrate.detect import Detection, is_usable
from rigbuild.calibrate.intrinsics import Intrinsics, board_poses, calibrate_intrinsics, calibration_flags
from rigbuild.errors import QualityGateError
from rigbuild.calibrate.params import CalibrationOptions
from rigbuild.calibrate.posegraph import PoseGraph, build_pose_graph
from rigbuild.calibrate.rotations import rodrigues, rotation_to_rvec
from rigbuild.camera import Camera
from rigbuild.progress import progress
from rigbuild.session import BoardSpec


@dataclass
class RigCalibration:
    """Result of :func:`calibrate_rig`.

    cameras : calibrated cameras (input order), world = reference camera frame, mm.
    view_keys : (V,) board-pose keys; board_R (V, 3, 3), board_t (V, 3): board-to-world poses.
    obs : the observations used; residuals : (N, 2) px after the adjustment.
    board_points : (P, 3) board-frame corners, mm.
    image_names : camera id -> view key -> image name (for reports).
    dropped : camera id -> names of images dropped for too few corners.
    """

    cameras: list[Camera]
    reference: str
    view_keys: list[str]
    board_R: np.ndarray
    board_t: np.ndarray
    obs: Observations
    residuals: np.ndarray
    board_points: np.ndarray
    image_names: dict[str, dict[str, str]]
    dropped: dict[str, list[str]]
    initial_rms_px: dict[str, float]
    bundle: BundleResult
    graph: PoseGraph
    seconds: dict[str, float] = field(default_factory=dict)
    intrinsics_source: dict[str, str] = field(default_factory=dict)  # camera id -> rig | images | given
    flags: dict[str, list[str]] = field(default_factory=dict)  # camera id -> plausibility flags
    gate_failures: list[str] = field(default_factory=list)  # RMS / convergence gate messages (empty: pass)
    heldout: dict | None = None  # rigbuild.calibrate.heldout.heldout_errors of a fit without every n-th pose
    known_sd: dict[str, np.ndarray] = field(default_factory=dict)  # camera id -> KnownIntrinsics.sd
    # a second adjustment's noise model: corner noise_px and the robust_scale_px it set (robust_scale_px auto), the
    # angle bins' edges (deg) and noise (px) (noise_model view_angle)
    noise: dict | None = None

    @property
    def status(self) -> str:
        """``pass`` or ``fail`` (the RMS and convergence gates)."""
        return "fail" if self.gate_failures else "pass"

    @property
    def rms_px(self) -> float:
        return float(np.sqrt(np.mean(np.sum(self.residuals ** 2, axis=1))))

    def intrinsics_sd(self) -> dict[str, np.ndarray]:
        """camera id -> (4,) standard deviations of fx, fy, cx, cy (px) of the delivered intrinsics: the bundle
        adjustment's covariance, or for intrinsics held fixed their own fit's (NaN: given, or held)."""
        out = {}
        sd = self.bundle.cam_sd if self.bundle.cam_sd is not None else np.full((len(self.cameras), N_CAM), np.nan)
        for i, cam in enumerate(self.cameras):
            s = sd[i, FX:CY + 1]
            if cam.id in self.known_sd and not np.isfinite(s).any():
                s = self.known_sd[cam.id]
            out[cam.id] = np.asarray(s, dtype=np.float64)
        return out

    def corner_world(self, view: np.ndarray, corner: np.ndarray) -> np.ndarray:
        """World positions (N, 3) mm of board corners ``corner`` (N,) at board poses ``view`` (N,)."""
        P = self.board_points[corner]
        return np.einsum("nij,nj->ni", self.board_R[view], P) + self.board_t[view]

    def camera_rms(self) -> dict[str, float]:
        """camera id -> RMS reprojection error (px) over all its corners."""
        e2 = np.sum(self.residuals ** 2, axis=1)
        return {c.id: float(np.sqrt(np.mean(e2[self.obs.cam == i]))) if np.any(self.obs.cam == i) else float("nan")
                for i, c in enumerate(self.cameras)}

    def image_rms(self) -> dict[str, dict[str, float]]:
        """camera id -> image name -> RMS (px)."""
        e2 = np.sum(self.residuals ** 2, axis=1)
        out: dict[str, dict[str, float]] = {c.id: {} for c in self.cameras}
        key = self.obs.cam * len(self.view_keys) + self.obs.view
        order = np.argsort(key, kind="stable")
        uniq, start = np.unique(key[order], return_index=True)
        for k, s, e in zip(uniq, start, np.append(start[1:], key.size)):
            ci, vi = divmod(int(k), len(self.view_keys))
            cam = self.cameras[ci].id
            out[cam][self.image_names[cam][self.view_keys[vi]]] = float(np.sqrt(np.mean(e2[order[s:e]])))
        return out

    def per_image_rows(self) -> list[dict]:
        """Rows for ``reprojection_per_image.csv`` (used and dropped images)."""
        e = np.linalg.norm(self.residuals, axis=1)
        rows = []
        for ci, cam in enumerate(self.cameras):
            for vi, v in enumerate(self.view_keys):
                m = (self.obs.cam == ci) & (self.obs.view == vi)
                if m.any():
                    rows.append({"camera": cam.id, "image": self.image_names[cam.id][v], "view": v, "used": 1,
                                 "n_corners": int(m.sum()), "rms_px": float(np.sqrt(np.mean(e[m] ** 2))),
                                 "max_px": float(e[m].max())})
            for name in self.dropped.get(cam.id, []):
                rows.append({"camera": cam.id, "image": name, "view": "", "used": 0, "n_corners": 0,
                             "rms_px": float("nan"), "max_px": float("nan")})
        return rows

    def per_camera_rows(self) -> list[dict]:
        """Rows for ``reprojection_per_camera.csv``."""
        e = np.linalg.norm(self.residuals, axis=1)
        rows = []
        sd = self.intrinsics_sd()
        for ci, cam in enumerate(self.cameras):
            m = self.obs.cam == ci
            rows.append({
                "camera": cam.id, "n_images": int(np.unique(self.obs.view[m]).size),
                "n_dropped": len(self.dropped.get(cam.id, [])), "n_corners": int(m.sum()),
                "rms_px": float(np.sqrt(np.mean(e[m] ** 2))), "max_px": float(e[m].max()),
                "initial_rms_px": self.initial_rms_px[cam.id],
                "fx": cam.K[0, 0], "fy": cam.K[1, 1], "cx": cam.K[0, 2], "cy": cam.K[1, 2],
                "k1": cam.dist[0], "k2": cam.dist[1], "p1": cam.dist[2], "p2": cam.dist[3], "k3": cam.dist[4],
                "sd_fx": sd[cam.id][0], "sd_fy": sd[cam.id][1], "sd_cx": sd[cam.id][2], "sd_cy": sd[cam.id][3],
                "intrinsics": self.intrinsics_source.get(cam.id, "rig"),
                "flags": "; ".join(self.flags.get(cam.id, [])),
            })
        return rows


def board_symmetry(board: BoardSpec):
    """Board-frame pose (R, t) mapping corner i to corner N-1-i for a chessboard (180 degrees about the
    board normal through its centre); None for ChArUco (no symmetry)."""
    if board.type != "chessboard":
        return None
    pts, _ = board.corner_points()
    return np.diag([-1.0, -1.0, 1.0]), pts[0] + pts[-1]


def gather_observations(detections: Mapping[str, Mapping[str, Detection]], camera_ids: Sequence[str],
                        view_keys: Sequence[str]) -> Observations:
    """Stack detections (camera id -> view key -> Detection) into flat :class:`Observations`."""
    vindex = {v: i for i, v in enumerate(view_keys)}
    cam, view, corner, uv = [], [], [], []
    for ci, c in enumerate(camera_ids):
        for v, det in detections[c].items():
            if v in vindex and len(det):
                cam.append(np.full(len(det), ci))
                view.append(np.full(len(det), vindex[v]))
                corner.append(det.ids)
                uv.append(det.corners)
    return Observations(np.concatenate(cam), np.concatenate(view), np.concatenate(corner), np.concatenate(uv))


@dataclass
class KnownIntrinsics:
    """Intrinsics of one camera known before the rig fit: given (session.yaml) or calibrated from that
    camera's own images. K (3, 3) px, dist (5,), source ``given`` or ``images``, rms_px of their own fit,
    sd (4,) standard deviations of fx, fy, cx, cy px from that fit (NaN: given)."""

    K: np.ndarray
    dist: np.ndarray
    source: str
    rms_px: float = float("nan")
    sd: np.ndarray = field(default_factory=lambda: np.full(4, np.nan))


def _camera_intrinsics(detections, usable, pts, image_size, opt: CalibrationOptions,
                       known: Mapping[str, KnownIntrinsics]) -> dict[str, Intrinsics]:
    """Per camera: Zhang's method on its rig views, or board poses by PnP for known intrinsics."""
    flags = calibration_flags(fix_k3=opt.fix_k3, zero_tangent=opt.fix_tangential, fix_aspect=opt.fix_aspect_ratio,
                              fix_principal_point=opt.fix_principal_point)
    intr = {}
    for c in progress(list(detections), "intrinsic calibration", unit="camera"):
        obj = [pts[detections[c][v].ids] for v in usable[c]]
        img = [detections[c][v].corners for v in usable[c]]
        if c in known:
            intr[c] = board_poses(obj, img, known[c].K, known[c].dist)
        else:
            intr[c] = calibrate_intrinsics(obj, img, image_size, flags=flags, camera=c)
    return intr


def _held_unknowns(cam_ids, known, opt: CalibrationOptions) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(fixed (C, 15) bool, tie_aspect (C,) bool, prior_sigma (C, 15) or None) for the bundle adjustment."""
    C = len(cam_ids)
    fixed = np.zeros((C, N_CAM), dtype=bool)
    tie = np.zeros(C, dtype=bool)
    prior = np.full((C, N_CAM), np.inf)
    for i, c in enumerate(cam_ids):
        if c in known and opt.known_intrinsics == "fixed":
            fixed[i, FX:] = True
            continue
        if c in known:
            f = known[c].K[0, 0]
            prior[i, FX:CY + 1] = [f * opt.prior_focal_pct / 100, f * opt.prior_focal_pct / 100,
                                   opt.prior_principal_px, opt.prior_principal_px]
            prior[i, CY + 1:] = opt.prior_distortion
        fixed[i, [CX, CY]] |= opt.fix_principal_point
        fixed[i, list(TANGENTIAL)] |= opt.fix_tangential
        fixed[i, K3_INDEX] |= opt.fix_k3
        tie[i] = opt.fix_aspect_ratio
    return fixed, tie, (prior if np.isfinite(prior).any() else None)


def calibrate_rig(
    detections: Mapping[str, Mapping[str, Detection]],
    board: BoardSpec,
    image_size: tuple[int, int],
    options: CalibrationOptions | None = None,
    image_names: Mapping[str, Mapping[str, str]] | None = None,
    known: Mapping[str, KnownIntrinsics] | None = None,
    raise_gate: bool = True,
) -> RigCalibration:
    """Calibrate every camera's intrinsics and the rig's extrinsics.

    detections : camera id -> view key -> Detection (same key = same board pose, see module doc).
    board : the board (its square size sets the metric scale, mm).
    image_size : (width, height) px.
    image_names : camera id -> view key -> name used in reports and QA messages (default ``cam/key``).
    known : camera id -> intrinsics known beforehand (held or a prior: ``options.known_intrinsics``).
    raise_gate : raise QualityGateError when the RMS or convergence gate fails; False: the failures are
        in ``result.gate_failures`` (the caller writes the outputs first, :mod:`rigbuild.calibrate.session`).

    Raises QualityGateError (too few usable images, a camera linked to no other; RMS / convergence with
    ``raise_gate``).
    """
    opt = options or CalibrationOptions()
    known = dict(known or {})
    t0 = time.perf_counter()
    cam_ids = list(detections)
    names = {c: {v: (image_names or {}).get(c, {}).get(v, f"{c}/{v}") for v in detections[c]} for c in cam_ids}
    pts, _ = board.corner_points()

    usable: dict[str, list[str]] = {}
    dropped: dict[str, list[str]] = {}
    for c in cam_ids:
        usable[c] = [v for v, d in detections[c].items() if is_usable(d, board, opt.min_corners)]
        dropped[c] = [names[c][v] for v, d in detections[c].items() if v not in usable[c]]
    qa.check_image_counts({c: [names[c][v] for v in usable[c]] for c in cam_ids}, dropped, opt.min_images)

    # 1. intrinsics (or known ones) and per-view board poses, one camera at a time
    intr = _camera_intrinsics(detections, usable, pts, image_size, opt, known)
    view_poses = {c: {v: (intr[c].R_views[k], intr[c].t_views[k]) for k, v in enumerate(usable[c])} for c in cam_ids}
    t1 = time.perf_counter()

    # 2. pose graph
    reference = opt.reference_camera or cam_ids[0]
    graph = build_pose_graph(view_poses, reference, board_symmetry(board))
    qa.check_connected(graph.unreachable, reference, {c: [names[c][v] for v in usable[c]] for c in cam_ids})
    view_keys = sorted(graph.boards, key=lambda k: (len(k), k))
    t2 = time.perf_counter()

    # 3. global bundle adjustment (chessboard views numbered the other way round are renumbered first)
    used = {c: {v: detections[c][v] for v in usable[c]} for c in cam_ids}
    for c, views in graph.flipped.items():
        for v in views:
            d = used[c][v]
            used[c][v] = Detection(len(pts) - 1 - d.ids, d.corners)
    obs = gather_observations(used, cam_ids, view_keys)
    cam_params = np.zeros((len(cam_ids), N_CAM))
    for i, c in enumerate(cam_ids):
        R, t = graph.cameras[c]
        K = intr[c].K
        cam_params[i] = np.concatenate([rotation_to_rvec(R), t, [K[0, 0], K[1, 1], K[0, 2], K[1, 2]], intr[c].dist])
    board_params = np.stack([np.concatenate([rotation_to_rvec(graph.boards[v][0]), graph.boards[v][1]])
                             for v in view_keys])
    fixed, tie, prior = _held_unknowns(cam_ids, known, opt)
    def adjust(cp0, bp0, scale, weight=None):
        return bundle_adjust(cp0, bp0, obs, pts, fixed_pose_cams=(cam_ids.index(reference),),
                             loss=opt.robust_loss, f_scale_px=scale, max_iterations=opt.max_iterations,
                             tol=opt.tolerance, fixed=fixed, tie_aspect=tie, prior_sigma=prior, obs_weight=weight)

    auto = opt.robust_scale_px == "auto"
    ba = adjust(cam_params, board_params, 1.0 if auto else float(opt.robust_scale_px))
    noise = None
    if auto or opt.noise_model == "view_angle":  # a second adjustment from the first one's corner noise
        weight = None
        if opt.noise_model == "view_angle":  # corners seen obliquely are noisier: weigh them by their angle's noise
            weight, edges, sigma = view_angle_weights(view_angles_deg(ba.cam_params, ba.board_params, obs, pts),
                                                      ba.residuals)
            noise = {"view_angle_edges_deg": edges.tolist(), "sigma_px": sigma.tolist()}
        white = ba.residuals if weight is None else ba.residuals * np.sqrt(weight)[:, None]
        noise_px = robust_noise_px(white)
        scale = max(AUTO_SCALE_SIGMAS * noise_px, 1e-3) if auto else float(opt.robust_scale_px)
        noise = {**(noise or {}), "noise_px": noise_px, "robust_scale_px": scale}
        first = ba
        ba = adjust(first.cam_params, first.board_params, scale, weight)
        ba.nfev += first.nfev
        ba.seconds += first.seconds
        ba.initial_rms_px = first.initial_rms_px
    t3 = time.perf_counter()

    cameras = []
    for i, c in enumerate(cam_ids):
        p = ba.cam_params[i]
        K = np.array([[p[6], 0, p[8]], [0, p[7], p[9]], [0, 0, 1.0]])
        cameras.append(Camera(c, image_size[0], image_size[1], K, p[10:15], rodrigues(p[0:3]), p[3:6]))
    result = RigCalibration(
        cameras=cameras, reference=reference, view_keys=view_keys,
        board_R=rodrigues(ba.board_params[:, 0:3]), board_t=ba.board_params[:, 3:6].copy(), obs=obs,
        residuals=ba.residuals, board_points=pts, image_names=names, dropped=dropped, noise=noise,
        initial_rms_px={c: (known[c].rms_px if c in known else intr[c].rms_px) for c in cam_ids}, bundle=ba,
        graph=graph, seconds={"intrinsics": t1 - t0, "pose_graph": t2 - t1, "bundle": t3 - t2, "total": t3 - t0},
        intrinsics_source={c: known[c].source if c in known else "rig" for c in cam_ids},
        known_sd={c: known[c].sd for c in known if opt.known_intrinsics == "fixed"},
    )
    result.flags = qa.plausibility_flags(cameras, {c.id: int(np.unique(obs.view[obs.cam == i]).size)
                                                   for i, c in enumerate(cameras)}, opt.min_board_poses,
                                         principal_point_sd={c: qa.max_finite(s[2:]) for c, s in
                                                             result.intrinsics_sd().items()})
    result.gate_failures = [m for m in (qa.rms_message(result.camera_rms(), result.image_rms(), opt.max_rms_px),
                                        qa.convergence_message(ba, opt.max_iterations)) if m]
    if raise_gate and result.gate_failures:
        raise QualityGateError("\n".join(result.gate_failures))
    return result

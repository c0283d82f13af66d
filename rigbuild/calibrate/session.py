"""Calibrate a session folder and write ``results/<session>/calib/``.

Outputs (all written to a staging folder first and moved into place only when everything succeeded,
so a failure - bad input or a QA gate - leaves nothing half-written):

- ``cameras.json`` (rigbuild.io.cameras schema, as the generator writes it; world = reference camera frame, mm)
- ``colmap/cameras.txt, images.txt, points3D.txt`` (board corners as 3-D points, loadable by pycolmap)
- ``reprojection_per_image.csv``, ``reprojection_per_camera.csv``
- ``residuals.png``, ``camera_layout.png``, ``detections/<cam>.jpg`` (:mod:`rigbuild.calibrate.pictures`)
- ``calib_metrics.json``: the metrics fragment ``{"calibration": {...}}`` (no ground truth; the
  ``eval_calibration`` rule compares ``cameras.json`` with the ground truth): ``status`` (pass / fail of the
  RMS and convergence gates), plausibility flags, held-out reprojection RMS (:mod:`rigbuild.calibrate.heldout`)

Intrinsics per camera (:func:`known_intrinsics`): given in session.yaml ``intrinsics:``, else calibrated
from that camera's own ``calib_intrinsics/<cam>/`` images, else estimated from the rig footage.
"""

from __future__ import annotations

import csv
import io
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from rigbuild.calibrate.detect import (Detection, FaceOnRefinement, count_corners, describe_board, detect_images,
                                      detect_paths, diagnose_board, is_usable, read_gray, session_images)
from rigbuild.calibrate import qa
from rigbuild.calibrate.heldout import heldout_errors, split_views
from rigbuild.calibrate.intrinsics import calibrate_intrinsics, calibration_flags, given_intrinsics
from rigbuild.calibrate.params import CalibrationOptions, from_config
from rigbuild.calibrate.pictures import DETECTIONS_DIR, detection_files, write_detection_pictures
from rigbuild.calibrate.rig import KnownIntrinsics, RigCalibration, calibrate_rig
from rigbuild.errors import InputError, QualityGateError
from rigbuild.io.atomic import write_text
from rigbuild.io.cameras import write_cameras
from rigbuild.io.colmap import write_colmap_text
from rigbuild.io.metrics import write_metrics_fragment
from rigbuild.session import SessionSpec, read_session

OUTPUT_FILES = (
    "cameras.json",
    "colmap/cameras.txt",
    "colmap/images.txt",
    "colmap/points3D.txt",
    "reprojection_per_image.csv",
    "reprojection_per_camera.csv",
    "residuals.png",
    "camera_layout.png",
    "calib_metrics.json",
)


def no_board_error(spec: SessionSpec, images: Mapping[str, Mapping[str, Path]], where: str = "calibration"
                   ) -> InputError:
    """The error for a board spec that finds no corner: what was tried, which nearby spec would work."""
    n = sum(len(v) for v in images.values())
    sample = [p for views in images.values() for p in list(views.values())[:1]][:3]
    grays = {str(p.relative_to(spec.root)) if p.is_relative_to(spec.root) else str(p): read_gray(p) for p in sample}
    lines = diagnose_board(grays, spec.board)
    return InputError(f"field 'board': no {spec.board.type} corners found in any of the {n} {where} images "
                      f"(board: {describe_board(spec.board)}); " + "; ".join(lines), path=spec.root / "session.yaml",
                      fix="check board.type, squares_x/squares_y, dictionary, inverted (white on black: true, or "
                      "auto) and legacy_pattern against the printed board ('rigbuild init-session' checks a few "
                      "images)")


def face_on(params: CalibrationOptions) -> FaceOnRefinement | None:
    """The detector's face-on corner refinement from the stage's ``face_on_subpix_*`` (None when off)."""
    if params.face_on_subpix_deg <= 0:
        return None
    return FaceOnRefinement(params.face_on_subpix_deg, params.face_on_subpix_blur_px, params.face_on_subpix_window)


def known_intrinsics(spec: SessionSpec, params: CalibrationOptions, workers: int = 1) -> dict[str, KnownIntrinsics]:
    """camera id -> intrinsics known before the rig fit: session.yaml ``intrinsics:`` (source ``given``),
    else Zhang's method on the camera's own ``calib_intrinsics/<cam>/`` images (source ``images``, with the
    stage's model options; detected on ``workers`` threads). Cameras with neither are absent (their
    intrinsics come from the rig footage)."""
    out = {c: KnownIntrinsics(K, d, "given") for c, (K, d) in
           given_intrinsics(spec.raw.get("intrinsics"), spec.root, spec.cameras).items()}
    pts, _ = spec.board.corner_points()
    flags = calibration_flags(fix_k3=params.fix_k3, zero_tangent=params.fix_tangential,
                              fix_aspect=params.fix_aspect_ratio, fix_principal_point=params.fix_principal_point)
    for cam in spec.cameras:
        paths = spec.intrinsics_images(cam)
        if cam in out or not paths:
            continue
        dets = dict(zip(paths, detect_paths(paths, spec.board, (spec.width, spec.height), params.subpix_window,
                                            workers, f"intrinsics board detection {cam}", face_on(params))))
        if not any(len(d) for d in dets.values()):
            raise no_board_error(spec, {cam: {p.stem: p for p in paths}}, f"intrinsics ({spec.intrinsics_dir(cam)})")
        good = [d for d in dets.values() if is_usable(d, spec.board, params.min_corners)]
        intr = calibrate_intrinsics([pts[d.ids] for d in good], [d.corners for d in good], (spec.width, spec.height),
                                    flags=flags, camera=cam)
        out[cam] = KnownIntrinsics(intr.K, intr.dist, "images", intr.rms_px, intr.sd)
    return out


def consistent_labels(detections: Mapping[str, Mapping[str, Detection]], result: RigCalibration
                      ) -> dict[str, dict[str, Detection]]:
    """Detections with the corner numbering the pose graph chose for each (camera, view): a chessboard
    seen turned by 180 degrees in one camera is renumbered (``result.graph.flipped``), so that a corner id
    names one physical corner in every camera (ChArUco: unchanged)."""
    n = len(result.board_points)
    return {c: {v: Detection(n - 1 - d.ids, d.corners) if v in result.graph.flipped.get(c, []) else d
                for v, d in views.items()} for c, views in detections.items()}


def calibrate_session(session_dir: str | os.PathLike, params: CalibrationOptions | Mapping | None = None,
                      workers: int = 1) -> tuple[SessionSpec, RigCalibration]:
    """Detect the board in every calibration image of a session and calibrate the rig.

    params : the stage's parameters (a mapping goes through :func:`rigbuild.calibrate.params.from_config`;
        None = defaults).
    workers : threads for the board detection (:func:`rigbuild.calibrate.detect.detect_paths`).
    Raises InputError (bad images, a board spec that matches no image) or QualityGateError (too few images,
    cameras not linked). The RMS and convergence gates do not raise: ``result.gate_failures`` lists them
    (:func:`rigbuild.calibrate.stage.run_calibrate` writes the outputs, then fails). With
    ``params.heldout_every`` the rig is calibrated a second time without every n-th board pose and
    ``result.heldout`` holds :func:`rigbuild.calibrate.heldout.heldout_errors` (or ``{"error": text}``).
    """
    spec = read_session(session_dir)
    params = params if isinstance(params, CalibrationOptions) else from_config(params)
    images = session_images(spec)
    t0 = time.perf_counter()
    detections = detect_images(images, spec.board, (spec.width, spec.height), params.subpix_window, workers,
                               face_on(params))
    t_detect = time.perf_counter() - t0
    if count_corners(detections) == 0:
        raise no_board_error(spec, images)
    known = known_intrinsics(spec, params, workers)
    names = {c: {v: str(p.relative_to(spec.root)) if p.is_relative_to(spec.root) else f"{c}/{p.name}"
                 for v, p in views.items()} for c, views in images.items()}
    result = calibrate_rig(detections, spec.board, (spec.width, spec.height), params, image_names=names,
                           known=known, raise_gate=False)
    fitted, held = split_views(result.view_keys, params.heldout_every)
    if held:
        try:
            sub = {c: {v: d for v, d in views.items() if v not in held} for c, views in detections.items()}
            fit = calibrate_rig(sub, spec.board, (spec.width, spec.height), params, known=known, raise_gate=False)
            result.heldout = heldout_errors(fit.cameras, consistent_labels(detections, result), held,
                                            result.board_points)
            result.heldout["n_views_fitted"] = len(fitted)
        except (QualityGateError, InputError) as exc:  # too few views left for some camera: reported, not fatal
            result.heldout = {"error": f"no held-out fit without {len(held)} board poses: {exc}"}
    result.seconds["detect"] = t_detect
    result.seconds["total"] = time.perf_counter() - t0
    return spec, result


def colmap_tracks(result: RigCalibration) -> dict[str, Any]:
    """COLMAP model content: one image per used (camera, view), one 3-D point per observed (view, corner)."""
    obs = result.obs
    V = len(result.view_keys)
    img_key = obs.cam * V + obs.view
    uniq_img, obs_image = np.unique(img_key, return_inverse=True)
    image_camera = uniq_img // V
    image_names = [result.image_names[result.cameras[int(k // V)].id][result.view_keys[int(k % V)]]
                   for k in uniq_img]
    pt_key = obs.view.astype(np.int64) * (int(obs.corner.max()) + 1) + obs.corner
    uniq_pt, obs_point = np.unique(pt_key, return_inverse=True)
    n_corner = int(obs.corner.max()) + 1
    pv, pc = uniq_pt // n_corner, uniq_pt % n_corner
    return {"image_names": image_names, "image_camera": image_camera, "obs_image": obs_image,
            "obs_point": obs_point, "view_of_point": pv, "corner_of_point": pc}


def _csv_text(rows: list[dict]) -> str:
    buf = io.StringIO()
    if rows:
        w = csv.DictWriter(buf, fieldnames=list(rows[0]))
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    return buf.getvalue()


def plot_residuals(result: RigCalibration, path: str | os.PathLike) -> None:
    """Residual scatter (dx, dy) coloured by camera and per-camera error distributions, PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    res = result.residuals
    e = np.linalg.norm(res, axis=1)
    fig, ax = plt.subplots(1, 2, figsize=(12, 5))
    cmap = plt.get_cmap("tab20")
    for i, cam in enumerate(result.cameras):
        m = result.obs.cam == i
        ax[0].scatter(res[m, 0], res[m, 1], s=2, color=cmap(i % 20), label=cam.id)
    lim = max(float(np.percentile(np.abs(res), 99.9)) * 1.2, 1e-3)
    ax[0].set(xlim=(-lim, lim), ylim=(-lim, lim), aspect="equal", xlabel="du (px)", ylabel="dv (px)",
              title=f"reprojection residuals, RMS {result.rms_px:.3f} px")
    if len(result.cameras) <= 20:
        ax[0].legend(fontsize=6, markerscale=3, ncol=2)
    ax[1].boxplot([e[result.obs.cam == i] for i in range(len(result.cameras))], showfliers=True)
    ax[1].set_xticks(range(1, len(result.cameras) + 1), [c.id for c in result.cameras], rotation=90)
    ax[1].set(ylabel="|error| (px)", title="per-camera reprojection error")
    fig.tight_layout()
    _save_fig(fig, path)


def plot_camera_layout(result: RigCalibration, path: str | os.PathLike, frustum_mm: float | None = None) -> None:
    """Camera frusta and board corner positions, top (x-z) and front (x-y) views of the world frame, PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    centres = np.stack([c.center for c in result.cameras])
    corners = result.corner_world(result.obs.view, result.obs.corner)
    span = max(float(np.ptp(np.vstack([centres, corners]), axis=0).max()), 1.0)
    size = frustum_mm or 0.08 * span
    fig, ax = plt.subplots(1, 2, figsize=(12, 6))
    for a, (i, j, name) in zip(ax, [(0, 2, "top view (x, z)"), (0, 1, "front view (x, y)")]):
        a.scatter(corners[:, i], corners[:, j], s=1, color="0.6", label="board corners")
        for cam in result.cameras:
            w, h = cam.width, cam.height
            uv = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], float)
            rays = cam.rays(uv)
            tips = cam.center + rays * size
            for tip in tips:
                a.plot([cam.center[i], tip[i]], [cam.center[j], tip[j]], color="C0", lw=0.6)
            loop = np.vstack([tips, tips[:1]])
            a.plot(loop[:, i], loop[:, j], color="C0", lw=0.6)
            a.annotate(cam.id, (cam.center[i], cam.center[j]), fontsize=7,
                       color="C3" if cam.id == result.reference else "k")
        a.set(aspect="equal", title=name, xlabel="xyz"[i] + " (mm)", ylabel="xyz"[j] + " (mm)")
        if j == 1:
            a.invert_yaxis()  # world = reference camera frame, y down
    ax[0].legend(fontsize=7)
    fig.suptitle(f"calibrated rig: world = camera {result.reference} frame (mm)")
    fig.tight_layout()
    _save_fig(fig, path)


def _save_fig(fig, path) -> None:
    import matplotlib.pyplot as plt

    from rigbuild.io.atomic import atomic_path

    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def calibration_metrics(result: RigCalibration) -> dict[str, Any]:
    """The ``calibration`` block of the stage's metrics fragment (no ground truth)."""
    cam_rms = result.camera_rms()
    sd = result.intrinsics_sd()
    m = {
        "status": result.status,
        "gate": "; ".join(f.splitlines()[0] for f in result.gate_failures) or None,
        "n_gate_failures": len(result.gate_failures),
        "rms_px": result.rms_px,
        "max_camera_rms_px": max(cam_rms.values()),
        "camera_rms_px": cam_rms,
        "n_cameras": len(result.cameras),
        "n_board_poses": len(result.view_keys),
        "n_images_used": int(np.unique(result.obs.cam * len(result.view_keys) + result.obs.view).size),
        "n_images_dropped": sum(len(v) for v in result.dropped.values()),
        "n_corners": len(result.obs),
        "reference_camera": result.reference,
        "bundle_iterations_nfev": result.bundle.nfev,
        "bundle_converged": result.bundle.status in (1, 2),
        "intrinsics_source": dict(result.intrinsics_source),
        "camera_principal_point_sd_px": {c: qa.max_finite(s[2:]) for c, s in sd.items()},
        "camera_focal_sd_pct": {c.id: qa.max_finite(100 * sd[c.id][:2] / c.K[0, 0]) for c in result.cameras},
        "n_plausibility_flags": sum(len(f) for f in result.flags.values()),
        "plausibility_flags": {c: "; ".join(f) for c, f in result.flags.items() if f},
        "seconds": result.seconds.get("total"),
        "seconds_detect": result.seconds.get("detect"),
        "seconds_bundle": result.seconds.get("bundle"),
    }
    if result.noise is not None:  # the second adjustment's noise model (robust_scale_px auto, noise_model)
        m.update(corner_noise_px=result.noise["noise_px"], robust_scale_px=result.noise["robust_scale_px"])
    h = result.heldout or {}
    if "rms_px" in h:
        m.update(heldout_reprojection_rms_px=h["rms_px"], heldout_camera_rms_px=h["camera_rms_px"],
                 heldout_n_corners=h["n_corners"], heldout_n_board_poses=h["n_views"],
                 heldout_scale_deviation_pct=h["scale_deviation_pct"])
    elif "error" in h:
        m["heldout"] = h["error"].splitlines()[0]
    return m


def output_files(result: RigCalibration) -> list[str]:
    """Every file :func:`write_outputs` writes, relative to the calib folder, in the order they are moved into
    place: the metrics fragment last."""
    last = "calib_metrics.json"
    return [*(f for f in OUTPUT_FILES if f != last), *detection_files([c.id for c in result.cameras]), last]


def write_outputs(result: RigCalibration, out_dir: str | os.PathLike, session: str,
                  image_paths: Mapping[str, Mapping[str, str | os.PathLike]] | None = None) -> dict[str, Any]:
    """Write every calibration output into ``out_dir`` (staged, then moved; see module doc).

    image_paths : camera id -> view key -> calibration image (:func:`session_images`), the detection pictures'
    backgrounds (None: a grey canvas). Returns the metrics written to ``calib_metrics.json`` (the
    ``calibration`` block of the fragment).
    """
    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.staging.", dir=out_dir.parent))
    try:
        metrics = calibration_metrics(result)
        write_cameras(stage / "cameras.json", result.cameras, session=session,
                      world_frame=f"camera {result.reference} (R = I, t = 0); metric scale from the board")
        tr = colmap_tracks(result)
        pts = result.corner_world(tr["view_of_point"], tr["corner_of_point"])
        e = np.linalg.norm(result.residuals, axis=1)
        perr = np.bincount(tr["obs_point"], weights=e) / np.maximum(np.bincount(tr["obs_point"]), 1)
        write_colmap_text(stage / "colmap", result.cameras, tr["image_names"], tr["image_camera"], pts,
                          tr["obs_image"], tr["obs_point"], result.obs.uv, perr)
        write_text(stage / "reprojection_per_image.csv", _csv_text(result.per_image_rows()))
        write_text(stage / "reprojection_per_camera.csv", _csv_text(result.per_camera_rows()))
        plot_residuals(result, stage / "residuals.png")
        plot_camera_layout(result, stage / "camera_layout.png")
        write_detection_pictures(result, stage, image_paths)
        write_metrics_fragment(stage / "calib_metrics.json", "calibration", metrics)
        shutil.rmtree(out_dir / DETECTIONS_DIR, ignore_errors=True)  # no picture of a camera no longer in the rig
        for rel in output_files(result):
            dst = out_dir / rel
            dst.parent.mkdir(parents=True, exist_ok=True)
            os.replace(stage / rel, dst)
    finally:
        shutil.rmtree(stage, ignore_errors=True)
    return metrics


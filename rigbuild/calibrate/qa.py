"""Calibration QA gates and plausibility flags.

Gates raise ``QualityGateError`` naming the cameras and images to re-shoot (the ``*_message`` variants
return the text, or None when the gate passes, so the stage can write its outputs before failing).
Plausibility flags (:func:`plausibility_flags`) never stop a run: they name what looks wrong.
"""

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from rigbuild.errors import QualityGateError


def _names(images: Sequence[str], limit: int = 12) -> str:
    images = list(images)
    text = ", ".join(images[:limit])
    return text + (f" (+{len(images) - limit} more)" if len(images) > limit else "")


def check_image_counts(usable: Mapping[str, Sequence[str]], dropped: Mapping[str, Sequence[str]],
                       min_images: int) -> None:
    """Every camera needs ``min_images`` usable board images.

    usable, dropped : camera id -> image names (usable ones; ones with too few corners).
    """
    bad = {c: len(v) for c, v in usable.items() if len(v) < min_images}
    if not bad:
        return
    lines = [f"calibration: {len(bad)} camera(s) have fewer than {min_images} usable board images:"]
    for c, n in bad.items():
        d = list(dropped.get(c, []))
        lines.append(f"  {c}: {n} usable" + (f"; too few corners in {_names(d)}" if d else ""))
    lines.append(f"  re-shoot: more board views for cameras {', '.join(bad)} (whole board in view, "
                 "varied tilt), or lower params.calibrate.min_images")
    raise QualityGateError("\n".join(lines))


def check_connected(unreachable: Sequence[str], reference: str, views: Mapping[str, Sequence[str]]) -> None:
    """Every camera must share a chain of board views with the reference camera.

    views : camera id -> names of its usable images (to say which images exist but overlap nothing).
    """
    if not unreachable:
        return
    lines = [f"calibration: camera(s) {', '.join(unreachable)} share no board view (directly or through "
             f"other cameras) with reference camera {reference}:"]
    for c in unreachable:
        lines.append(f"  {c}: usable images {_names(views.get(c, []))} show board poses no connected camera saw")
    lines.append("  re-shoot: hold the board where these cameras and at least one other camera see it at the "
                 "same time (same image number)")
    raise QualityGateError("\n".join(lines))


def rms_message(camera_rms: Mapping[str, float], image_rms: Mapping[str, Mapping[str, float]],
                max_rms_px: float) -> str | None:
    """The RMS gate's failure text (every camera's RMS must be at most ``max_rms_px``), None when it passes.

    camera_rms : camera id -> RMS px; image_rms : camera id -> image name -> RMS px.
    """
    bad = {c: r for c, r in camera_rms.items() if not r <= max_rms_px}
    if not bad:
        return None
    lines = [f"calibration: reprojection RMS above params.calibrate.max_rms_px = {max_rms_px:g} px:"]
    for c, r in bad.items():
        imgs = sorted(image_rms.get(c, {}).items(), key=lambda kv: -kv[1])
        worst = [f"{n} ({e:.2f} px)" for n, e in imgs if e > max_rms_px] or [f"{n} ({e:.2f} px)" for n, e in imgs[:3]]
        lines.append(f"  {c}: RMS {r:.3f} px; worst images {_names(worst)}")
    lines.append(f"  re-shoot: cameras {', '.join(bad)} (check focus, motion blur, board flatness) or drop the "
                 "listed images")
    return "\n".join(lines)


def check_rms(camera_rms: Mapping[str, float], image_rms: Mapping[str, Mapping[str, float]],
              max_rms_px: float) -> None:
    """Raise QualityGateError when :func:`rms_message` reports a failure."""
    msg = rms_message(camera_rms, image_rms, max_rms_px)
    if msg:
        raise QualityGateError(msg)


def convergence_message(bundle, max_iterations: int) -> str | None:
    """The convergence gate's failure text (bundle adjustment stopped by its iteration cap), None when it
    converged. bundle : :class:`rigbuild.calibrate.bundle.BundleResult`."""
    if bundle.status in (1, 2):
        return None
    return (f"calibration: bundle adjustment did not converge: {bundle.message}; RMS {bundle.initial_rms_px:.3f} "
            f"-> {bundle.rms_px:.3f} px, {bundle.nfev} residual evaluations\n"
            f"  raise params.calibrate.max_iterations (now {max_iterations}) or check the flags in "
            "reprojection_per_camera.csv (an implausible start, e.g. a principal point outside the image)")


def distortion_folds(K: np.ndarray, dist: np.ndarray, width: int, height: int) -> bool:
    """True when the radial model ``r (1 + k1 r^2 + k2 r^4 + k3 r^6)`` stops increasing before it reaches
    the image corners (the distortion folds the image inside its frame: some pixels have two rays)."""
    k1, k2, k3 = float(dist[0]), float(dist[1]), float(dist[4])
    corners = np.array([[0, 0], [width - 1, 0], [0, height - 1], [width - 1, height - 1]], float)
    rd_max = float(np.max(np.hypot((corners[:, 0] - K[0, 2]) / K[0, 0], (corners[:, 1] - K[1, 2]) / K[1, 1])))
    r = np.linspace(0.0, 3.0 * rd_max, 3000)
    r2 = r * r
    slope = 1 + 3 * k1 * r2 + 5 * k2 * r2 ** 2 + 7 * k3 * r2 ** 3
    down = np.flatnonzero(slope <= 0)
    if down.size == 0:
        return False
    rr = r[down[0]] ** 2
    return bool(r[down[0]] * (1 + k1 * rr + k2 * rr ** 2 + k3 * rr ** 3) < rd_max)


def max_finite(values) -> float | None:
    """The largest finite value of ``values`` (None: none finite, e.g. every unknown held)."""
    v = np.asarray(values, dtype=np.float64)
    return float(v[np.isfinite(v)].max()) if np.isfinite(v).any() else None


def plausibility_flags(cameras: Sequence, board_poses: Mapping[str, int], min_board_poses: int,
                       max_aspect_pct: float = 5.0, principal_point_sd: Mapping[str, float] | None = None,
                       max_principal_point_sd_px: float = 5.0) -> dict[str, list[str]]:
    """camera id -> plausibility flags (empty list: none) of calibrated cameras.

    cameras : :class:`rigbuild.camera.Camera` list; board_poses : camera id -> board poses it saw.
    principal_point_sd : camera id -> the larger standard deviation of cx, cy (px; NaN or None = not estimated).
    Flags: principal point outside the central third of the image, fx and fy differing by more than
    ``max_aspect_pct``, distortion that folds the image inside its frame, fewer than ``min_board_poses``,
    a principal point the board views pin no better than ``max_principal_point_sd_px`` (one sigma).
    """
    out = {}
    for cam in cameras:
        K, w, h = cam.K, cam.width, cam.height
        flags = []
        if not (w / 3 <= K[0, 2] <= 2 * w / 3 and h / 3 <= K[1, 2] <= 2 * h / 3):
            flags.append(f"principal point ({K[0, 2]:.0f}, {K[1, 2]:.0f}) px outside the central third of the "
                         f"{w}x{h} image")
        ratio_pct = 100 * (max(K[0, 0], K[1, 1]) / min(K[0, 0], K[1, 1]) - 1)
        if ratio_pct > max_aspect_pct:
            flags.append(f"fx {K[0, 0]:.0f} and fy {K[1, 1]:.0f} px differ by {ratio_pct:.1f} % (> {max_aspect_pct:g} %)")
        if distortion_folds(K, cam.dist, w, h):
            flags.append(f"distortion folds the image inside its frame (k1 {cam.dist[0]:.3g}, k2 {cam.dist[1]:.3g}, "
                         f"k3 {cam.dist[4]:.3g}): beyond the board's reach the model is not valid; show the "
                         "board near the image corners, or fix_k3")
        n = board_poses.get(cam.id, 0)
        if n < min_board_poses:
            flags.append(f"seen in {n} board poses (< params.calibrate.min_board_poses = {min_board_poses})")
        sd = (principal_point_sd or {}).get(cam.id)
        if sd is not None and sd > max_principal_point_sd_px:
            flags.append(f"principal point uncertain by {sd:.1f} px (one sigma, > {max_principal_point_sd_px:g}): "
                         "show the board tilted 30-50 degrees towards each side and near the image corners, "
                         "or fix_principal_point")
        out[cam.id] = flags
    return out

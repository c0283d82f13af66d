"""Calibration QA gates. Each raises ``QualityGateError`` naming the cameras and images to re-shoot."""

from __future__ import annotations

from typing import Mapping, Sequence

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


def check_rms(camera_rms: Mapping[str, float], image_rms: Mapping[str, Mapping[str, float]],
              max_rms_px: float) -> None:
    """Every camera's reprojection RMS must be at most ``max_rms_px``.

    camera_rms : camera id -> RMS px; image_rms : camera id -> image name -> RMS px.
    """
    bad = {c: r for c, r in camera_rms.items() if not r <= max_rms_px}
    if not bad:
        return
    lines = [f"calibration: reprojection RMS above params.calibrate.max_rms_px = {max_rms_px:g} px:"]
    for c, r in bad.items():
        imgs = sorted(image_rms.get(c, {}).items(), key=lambda kv: -kv[1])
        worst = [f"{n} ({e:.2f} px)" for n, e in imgs if e > max_rms_px] or [f"{n} ({e:.2f} px)" for n, e in imgs[:3]]
        lines.append(f"  {c}: RMS {r:.3f} px; worst images {_names(worst)}")
    lines.append(f"  re-shoot: cameras {', '.join(bad)} (check focus, motion blur, board flatness) or drop the "
                 "listed images")
    raise QualityGateError("\n".join(lines))

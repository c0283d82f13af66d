"""Reconstruct every frame of one ROM sequence and write the stage's outputs.

Outputs under ``out_dir`` (``results/<session>/reconstruct/<sequence>/``)::

    depth/<frame:06d>.npz     all cameras' filtered depth + confidence (rigbuild.io.depth)
    points/<frame:06d>.ply    fused oriented point cloud (mm, normals, colours)
    mesh/<frame:06d>.ply      surface cropped to the head
    coverage/<frame:06d>.png  per-camera coverage tiles (green: depth; red: foreground without depth)
    geometry/<frame:06d>.npz  the fused points and the mesh at full (float64) precision, for evaluation
    frames/<frame:06d>.json   frame record: stats and skip reason
    coverage.png              coverage per camera and frame (skipped frames marked)
    renders/<frame:06d>.png   the neutral and the peak frame: reference camera's depth and the shaded mesh
    recon_summary.json        per-frame stats, skipped frames with reasons, summary

Nothing here reads ground truth: the ``eval_reconstruction*`` rules (rules/eval_reconstruct.smk) score
the geometry files.

A frame with a missing, mis-sized, black or saturated view is *skipped* (``on_bad_frame: skip``: a
warning, an empty depth file flagged ``skipped`` with the reason, empty PLYs, and an entry in
``recon_summary.json``) or *fails* the job (``on_bad_frame: fail``). Cameras that do not match the session
(missing ids, other image size) always fail.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from rigbuild.camera import Camera
from rigbuild.errors import InputError
from rigbuild.progress import progress
from rigbuild.reconstruct.frame import FrameReconstruction, reconstruct_frame
from rigbuild.reconstruct.params import ReconstructParams
from rigbuild.reconstruct.stereo import pinhole

SUMMARY_FILE = "recon_summary.json"


def write_geometry(path: str | os.PathLike, points: np.ndarray, mesh_vertices: np.ndarray,
                   mesh_faces: np.ndarray) -> None:
    """``geometry/<frame>.npz``: points (P, 3), mesh_vertices (V, 3) float64 mm, mesh_faces (F, 3) int64,
    uncompressed (the PLYs hold float32; evaluation measures the reconstruction itself)."""
    from rigbuild.io.atomic import save_npz

    save_npz(path, compressed=False, points=np.asarray(points, np.float64).reshape(-1, 3),
             mesh_vertices=np.asarray(mesh_vertices, np.float64).reshape(-1, 3),
             mesh_faces=np.asarray(mesh_faces, np.int64).reshape(-1, 3))


def read_geometry(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """The arrays written by :func:`write_geometry`."""
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in ("points", "mesh_vertices", "mesh_faces")}


def match_cameras(session_cameras: Sequence[str], width: int, height: int, cameras: Sequence[Camera],
                  source: str = "cameras.json") -> list[Camera]:
    """Calibrated cameras in session order; InputError if an id is missing or a size differs."""
    by_id = {c.id: c for c in cameras}
    missing = [c for c in session_cameras if c not in by_id]
    if missing:
        raise InputError(f"cameras {missing} of session.yaml are not in the calibration {sorted(by_id)}",
                         path=source, fix="re-run calibration for this session (or fix the camera ids)")
    out = [by_id[c] for c in session_cameras]
    bad = [c.id for c in out if (c.width, c.height) != (width, height)]
    if bad:
        raise InputError(f"cameras {bad} are calibrated for another image size than the session's "
                         f"{width}x{height}", path=source, fix="re-run calibration on this session's images")
    return out


def read_image(path: Path) -> np.ndarray | None:
    """An image as stored (grey or BGR, uint8/uint16), or None when the file is missing/unreadable."""
    import cv2

    if not Path(path).exists():
        return None
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is not None and img.ndim == 3 and img.shape[2] == 4:
        img = img[..., :3]
    return img


def coverage_tiles(rec: FrameReconstruction, tile_width: int = 320) -> np.ndarray:
    """(h, w, 3) uint8 BGR montage: per camera its undistorted image (``rec.undistorted``, the depth maps' grid)
    in grey, depth pixels tinted green, foreground pixels without depth tinted red, and the coverage percentage
    written on it."""
    import cv2

    from rigbuild.montage import tile_images
    from rigbuild.reconstruct.stereo import to_gray_float

    tiles = []
    for k, cam in enumerate(rec.cameras):
        und = rec.undistorted[k]
        g = (to_gray_float(und) * 255).astype(np.uint8)
        t = cv2.cvtColor(g, cv2.COLOR_GRAY2BGR).astype(np.float32) * 0.6
        has = rec.depth[k] > 0
        hole = rec.mask[k] & ~has
        t[has] += (0, 90, 0)
        t[hole] += (0, 0, 110)
        t = np.clip(t, 0, 255).astype(np.uint8)
        s = tile_width / t.shape[1]
        t = cv2.resize(t, (tile_width, int(round(t.shape[0] * s))), interpolation=cv2.INTER_AREA)
        cov = rec.stats["coverage"][cam.id]
        cv2.putText(t, f"{cam.id} {100 * cov:.1f}%", (6, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (255, 255, 255), 1,
                    cv2.LINE_AA)
        tiles.append(t)
    return tile_images(tiles, min(4, len(tiles)))


def coverage_plot(path: Path, frames: Sequence[int], camera_ids: Sequence[str], coverage: np.ndarray,
                  skipped: dict[int, str], title: str) -> None:
    """Heat map of coverage (frames x cameras, NaN for skipped frames) written atomically as PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from rigbuild.io.atomic import atomic_path

    fig, ax = plt.subplots(figsize=(max(4.0, 0.35 * len(frames) + 2.5), 0.35 * len(camera_ids) + 1.6))
    im = ax.imshow(np.asarray(coverage, float).T, aspect="auto", vmin=0, vmax=1, cmap="viridis",
                   interpolation="nearest")
    ax.set_yticks(range(len(camera_ids)), camera_ids)
    step = max(1, len(frames) // 20)
    ax.set_xticks(range(0, len(frames), step), [str(f) for f in frames[::step]])
    for k, f in enumerate(frames):
        if f in skipped:
            ax.text(k, (len(camera_ids) - 1) / 2, "skipped", rotation=90, ha="center", va="center", color="red",
                    fontsize=7)
    ax.set_xlabel("frame")
    ax.set_title(title, fontsize=9)
    fig.colorbar(im, ax=ax, label="coverage (foreground pixels with depth)")
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)


def process_frame(frame: int, paths: Sequence[Path], cameras: Sequence[Camera], params: ReconstructParams,
                  out_dir: str | os.PathLike, name: str = "sequence", log: Callable[[str], None] = print) -> dict:
    """Reconstruct one frame from its image files and write ``depth/``, ``points/``, ``mesh/``,
    ``geometry/`` and ``coverage/`` files for it; a bad frame is skipped (empty files flagged ``skipped``)
    or raises, per ``params.on_bad_frame``. Returns the frame record: ``frame``, ``skipped`` (reason or
    None), and for a reconstructed frame its stats."""
    import cv2

    from rigbuild.io.atomic import atomic_path
    from rigbuild.io.depth import write_depth
    from rigbuild.io.ply import write_ply

    out = Path(out_dir)
    f = int(frame)
    images = [read_image(p) for p in paths]
    try:
        rec = reconstruct_frame(images, cameras, params, names=[str(p) for p in paths])
    except InputError as exc:
        if params.on_bad_frame == "fail":
            raise InputError(f"{name} frame {f}: {exc}", fix="fix the images, or set "
                             "params.reconstruct.on_bad_frame: skip to skip such frames") from None
        reason = str(exc)
        log(f"WARNING: {name} frame {f} skipped: {reason}")
        H, W = cameras[0].height, cameras[0].width
        pcams = [pinhole(c) for c in cameras]
        write_depth(out / "depth" / f"{f:06d}.npz", pcams, np.zeros((len(cameras), H, W), np.float32),
                    np.zeros((len(cameras), H, W), np.float32), frame=f, skipped=True, reason=reason)
        write_ply(out / "points" / f"{f:06d}.ply", np.zeros((0, 3)), normals=np.zeros((0, 3)), colors=np.zeros((0, 3)))
        write_ply(out / "mesh" / f"{f:06d}.ply", np.zeros((0, 3)), faces=np.zeros((0, 3), np.int64))
        write_geometry(out / "geometry" / f"{f:06d}.npz", np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)))
        tile = np.zeros((240, 320, 3), np.uint8)
        cv2.putText(tile, f"frame {f} skipped", (10, 120), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (0, 0, 255), 2)
        with atomic_path(out / "coverage" / f"{f:06d}.png", suffix=".png") as tmp:
            cv2.imwrite(str(tmp), tile)
        return {"frame": f, "skipped": reason}
    write_depth(out / "depth" / f"{f:06d}.npz", rec.cameras, rec.depth, rec.confidence, rec.n_views, frame=f)
    write_ply(out / "points" / f"{f:06d}.ply", rec.points, normals=rec.normals, colors=rec.colors)
    write_ply(out / "mesh" / f"{f:06d}.ply", rec.mesh_vertices, faces=rec.mesh_faces)
    write_geometry(out / "geometry" / f"{f:06d}.npz", rec.points, rec.mesh_vertices, rec.mesh_faces)
    with atomic_path(out / "coverage" / f"{f:06d}.png", suffix=".png") as tmp:
        cv2.imwrite(str(tmp), coverage_tiles(rec))
    record = {"frame": f, "skipped": None}
    record.update({k: rec.stats[k] for k in ("coverage", "stereo_consistency_mm", "stereo_consistency_p90_mm",
                                             "n_points", "n_mesh_vertices", "n_mesh_faces", "seconds",
                                             "cpu_seconds", "neighbours")})
    msg = (f"{name} frame {f}: {rec.stats['n_points']} points, {rec.stats['n_mesh_faces']} faces, mean coverage "
           f"{np.mean(list(rec.stats['coverage'].values())):.3f}, stereo consistency "
           f"{rec.stats['stereo_consistency_mm']:.3f} mm, {rec.stats['seconds']['total']:.1f} s")
    log(msg)
    return record


def _nanmedian(values: Sequence[float | None]) -> float:
    """Median of the finite values (None, as JSON stores NaN, counts as missing); NaN when none is."""
    v = np.asarray([np.nan if x is None else float(x) for x in values], float)
    v = v[np.isfinite(v)]
    return float(np.median(v)) if len(v) else float("nan")


def summarize_sequence(records: Sequence[dict], camera_ids: Sequence[str], out_dir: str | os.PathLike,
                       name: str = "sequence", neutral_frame: int | None = None) -> dict:
    """Write ``coverage.png``, ``renders/`` (:func:`rigbuild.reconstruct.renders.write_renders`, from the
    frames' depth and mesh files; ``neutral_frame`` None: the first frame) and ``recon_summary.json`` from
    the frame records; return the summary.

    Summary: ``frames``, ``reconstructed``, ``skipped`` {frame: reason}, ``mean_coverage``,
    ``min_coverage``, ``stereo_consistency_mm`` (median over the reconstructed frames of their cross-view
    depth disagreement, NaN if none has one), ``seconds_per_frame``, ``per_frame`` (the frame records). The
    errors against ground truth (synthetic sessions) are the ``eval_reconstruction_sequence`` rule's;
    ``renders``: the pictures' frames (``neutral``, ``peak``), ``reference_camera`` and each frame's
    ``displacement_mm`` from the neutral mesh.
    """
    from rigbuild.io.atomic import write_json
    from rigbuild.reconstruct.renders import write_renders

    records = sorted(records, key=lambda r: r["frame"])
    frames = [r["frame"] for r in records]
    skipped = {r["frame"]: r["skipped"] for r in records if r.get("skipped")}
    done = [r for r in records if not r.get("skipped")]
    cov = np.full((len(records), len(camera_ids)), np.nan)
    for k, r in enumerate(records):
        if not r.get("skipped"):
            cov[k] = [r["coverage"].get(c, np.nan) for c in camera_ids]
    coverage_plot(Path(out_dir) / "coverage.png", frames, list(camera_ids), cov, skipped,
                  f"{name}: reconstruction coverage")
    summary = {
        "frames": frames,
        "reconstructed": [r["frame"] for r in done],
        "skipped": {str(f): why for f, why in skipped.items()},
        "mean_coverage": float(np.nanmean(cov)) if done else float("nan"),
        "min_coverage": float(np.nanmin(cov)) if done else float("nan"),
        "stereo_consistency_mm": _nanmedian([r.get("stereo_consistency_mm") for r in done]),
        "seconds_per_frame": float(np.mean([r["seconds"]["total"] for r in done])) if done else float("nan"),
        "renders": write_renders(out_dir, [r["frame"] for r in done],
                                 frames[0] if neutral_frame is None or not frames else neutral_frame, name),
        "per_frame": {str(r["frame"]): r for r in records},
    }
    write_json(Path(out_dir) / SUMMARY_FILE, summary)
    return summary


def reconstruct_sequence(image_path: Callable[[str, int], Path], cameras: Sequence[Camera], frames: Sequence[int],
                         params: ReconstructParams, out_dir: str | os.PathLike, name: str = "sequence",
                         log: Callable[[str], None] = print) -> dict:
    """:func:`process_frame` for every frame, then :func:`summarize_sequence` (one process, in order).

    image_path(camera_id, frame) -> the image file.
    """
    records = [process_frame(f, [image_path(c.id, f) for c in cameras], cameras, params, out_dir, name, log)
               for f in progress(frames, f"reconstructing {name}", total=len(frames), unit="frame")]
    return summarize_sequence(records, [c.id for c in cameras], out_dir, name)

"""Reconstruct every frame of one ROM sequence and write the stage's outputs.

Outputs under ``out_dir`` (``results/<session>/reconstruct/<sequence>/``)::

    depth/<frame:06d>.npz     all cameras' filtered depth + confidence (rigbuild.io.depth)
    points/<frame:06d>.ply    fused oriented point cloud (mm, normals, colours)
    mesh/<frame:06d>.ply      surface cropped to the head
    coverage/<frame:06d>.png  per-camera coverage tiles (green: depth; red: foreground without depth)
    frames/<frame:06d>.json   frame record: stats, skip reason, errors vs ground truth (synthetic sessions)
    coverage.png              coverage per camera and frame (skipped frames marked)
    recon_metrics.json        per-frame stats, skipped frames with reasons, summary

A frame with a missing, mis-sized, black or saturated view is *skipped* (``on_bad_frame: skip``: a
warning, an empty depth file flagged ``skipped`` with the reason, empty PLYs, and an entry in
``recon_metrics.json``) or *fails* the job (``on_bad_frame: fail``). Cameras that do not match the session
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
from rigbuild.reconstruct.frame import FrameReconstruction, ReconstructParams, reconstruct_frame
from rigbuild.reconstruct.stereo import pinhole


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


def coverage_tiles(rec: FrameReconstruction, images: Sequence[np.ndarray], tile_width: int = 320) -> np.ndarray:
    """(h, w, 3) uint8 BGR montage: per camera its image in grey, depth pixels tinted green, foreground
    pixels without depth tinted red, and the coverage percentage written on it."""
    import cv2

    from rigbuild.reconstruct.stereo import to_gray_float, undistort_view

    tiles = []
    for k, cam in enumerate(rec.cameras):
        und, _ = undistort_view(images[k], cam)
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
    cols = min(4, len(tiles))
    rows = int(np.ceil(len(tiles) / cols))
    h, w = tiles[0].shape[:2]
    out = np.zeros((rows * h, cols * w, 3), np.uint8)
    for k, t in enumerate(tiles):
        r, c = divmod(k, cols)
        out[r * h:(r + 1) * h, c * w:(c + 1) * w] = t
    return out


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
                  out_dir: str | os.PathLike, name: str = "sequence", log: Callable[[str], None] = print,
                  evaluate: Callable[[int, FrameReconstruction], dict] | None = None) -> dict:
    """Reconstruct one frame from its image files and write ``depth/``, ``points/``, ``mesh/`` and
    ``coverage/`` files for it; a bad frame is skipped (empty files flagged ``skipped``) or raises, per
    ``params.on_bad_frame``. Returns the frame record: ``frame``, ``skipped`` (reason or None), and for a
    reconstructed frame its stats and, with ``evaluate``, ``ground_truth`` (errors vs ground truth)."""
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
        tile = np.zeros((240, 320, 3), np.uint8)
        cv2.putText(tile, f"frame {f} skipped", (10, 120), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (0, 0, 255), 2)
        with atomic_path(out / "coverage" / f"{f:06d}.png", suffix=".png") as tmp:
            cv2.imwrite(str(tmp), tile)
        return {"frame": f, "skipped": reason}
    write_depth(out / "depth" / f"{f:06d}.npz", rec.cameras, rec.depth, rec.confidence, rec.n_views, frame=f)
    write_ply(out / "points" / f"{f:06d}.ply", rec.points, normals=rec.normals, colors=rec.colors)
    write_ply(out / "mesh" / f"{f:06d}.ply", rec.mesh_vertices, faces=rec.mesh_faces)
    with atomic_path(out / "coverage" / f"{f:06d}.png", suffix=".png") as tmp:
        cv2.imwrite(str(tmp), coverage_tiles(rec, images))
    record = {"frame": f, "skipped": None}
    record.update({k: rec.stats[k] for k in ("coverage", "n_points", "n_mesh_vertices", "n_mesh_faces", "seconds",
                                             "cpu_seconds", "neighbours")})
    msg = (f"{name} frame {f}: {rec.stats['n_points']} points, {rec.stats['n_mesh_faces']} faces, mean coverage "
           f"{np.mean(list(rec.stats['coverage'].values())):.3f}, {rec.stats['seconds']['total']:.1f} s")
    if evaluate is not None:
        ev = evaluate(f, rec)
        record["ground_truth"] = ev
        msg += (f"; vs ground truth: median {ev['median_error_mm']:.3f} mm, p90 {ev['p90_error_mm']:.3f} mm, "
                f"completeness {ev['completeness']:.3f}")
    log(msg)
    return record


def summarize_sequence(records: Sequence[dict], camera_ids: Sequence[str], out_dir: str | os.PathLike,
                       name: str = "sequence") -> dict:
    """Write ``coverage.png`` and ``recon_metrics.json`` from the frame records; return the summary.

    Summary: ``frames``, ``reconstructed``, ``skipped`` {frame: reason}, ``mean_coverage``,
    ``min_coverage``, ``seconds_per_frame``, ``per_frame``; with ground truth, ``ground_truth`` holding the
    worst frame's ``median_error_mm``/``p90_error_mm``/``completeness`` (the acceptance is per frame) and
    the means over frames (``mean_*``).
    """
    from rigbuild.io.atomic import write_json

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
        "seconds_per_frame": float(np.mean([r["seconds"]["total"] for r in done])) if done else float("nan"),
        "per_frame": {str(r["frame"]): r for r in records},
    }
    ev = [r["ground_truth"] for r in done if "ground_truth" in r]
    if ev:
        summary["ground_truth"] = {
            "median_error_mm": float(max(e["median_error_mm"] for e in ev)),
            "p90_error_mm": float(max(e["p90_error_mm"] for e in ev)),
            "completeness": float(min(e["completeness"] for e in ev)),
            "mean_median_error_mm": float(np.mean([e["median_error_mm"] for e in ev])),
            "mean_p90_error_mm": float(np.mean([e["p90_error_mm"] for e in ev])),
            "mean_completeness": float(np.mean([e["completeness"] for e in ev])),
            "point_median_error_mm": float(max(e["point_median_error_mm"] for e in ev)),
            "frames_evaluated": len(ev),
        }
    write_json(Path(out_dir) / "recon_metrics.json", summary)
    return summary


def reconstruct_sequence(image_path: Callable[[str, int], Path], cameras: Sequence[Camera], frames: Sequence[int],
                         params: ReconstructParams, out_dir: str | os.PathLike, name: str = "sequence",
                         log: Callable[[str], None] = print,
                         evaluate: Callable[[int, FrameReconstruction], dict] | None = None) -> dict:
    """:func:`process_frame` for every frame, then :func:`summarize_sequence` (one process, in order).

    image_path(camera_id, frame) -> the image file.
    """
    records = [process_frame(f, [image_path(c.id, f) for c in cameras], cameras, params, out_dir, name, log, evaluate)
               for f in progress(frames, f"reconstructing {name}", total=len(frames), unit="frame")]
    return summarize_sequence(records, [c.id for c in cameras], out_dir, name)


# ------------------------------------------------------------------------------ Snakemake stage
def _stage_inputs(session_root, sequence: str, cameras_json, params: dict | None):
    from rigbuild.io.cameras import read_cameras
    from rigbuild.session import read_session

    spec = read_session(session_root)
    seq = spec.sequence(sequence)
    p = ReconstructParams.from_dict(params)
    cams = match_cameras(spec.cameras, spec.width, spec.height, read_cameras(cameras_json), str(cameras_json))
    return spec, seq, p, cams


def run_frame_job(session_root: str | os.PathLike, sequence: str, frames: Sequence[int],
                  cameras_json: str | os.PathLike, params: dict | None, out_dir: str | os.PathLike,
                  log: Callable[[str], None] = print) -> list[dict]:
    """Rule ``reconstruct_frame``: reconstruct frames of one sequence; each frame's record
    (stats, skip reason, ground-truth errors when the session has ``ground_truth/``) is written to
    ``out_dir/frames/<frame:06d>.json``."""
    from rigbuild.eval.reconstruction import SequenceEvaluator
    from rigbuild.io.atomic import write_json

    spec, seq, p, cams = _stage_inputs(session_root, sequence, cameras_json, params)
    bad = [f for f in frames if f not in seq.frames]
    if bad:
        raise InputError(f"frames {bad} are not in sequence {sequence} ({seq.start}..{seq.end})",
                         path=Path(session_root) / "session.yaml")
    evaluator = SequenceEvaluator(session_root, sequence, cams) \
        if SequenceEvaluator.available(session_root, sequence) else None
    records = []
    for f in progress(frames, f"reconstructing {sequence}", total=len(frames), unit="frame"):
        rec = process_frame(f, [spec.rom_image(sequence, c.id, f) for c in cams], cams, p, out_dir, sequence, log,
                            evaluator)
        write_json(Path(out_dir) / "frames" / f"{f:06d}.json", rec)
        records.append(rec)
    return records


def run_sequence_summary(session_root: str | os.PathLike, sequence: str, frame_jsons: Sequence[str | os.PathLike],
                         out_dir: str | os.PathLike, metrics_path: str | os.PathLike | None) -> dict:
    """Rule ``reconstruct_summary``: frame records -> ``coverage.png``, ``recon_metrics.json`` and
    ``reconstruction.*`` in ``metrics_path`` (per sequence under ``sequences.<name>``; the session-level
    acceptance keys ``median_error_mm``, ``p90_error_mm``, ``completeness`` are the worst over sequences)."""
    import json

    from rigbuild.io.metrics import merge_metrics, read_metrics
    from rigbuild.session import read_session

    spec = read_session(session_root)
    records = [json.loads(Path(p).read_text()) for p in frame_jsons]
    summary = summarize_sequence(records, spec.cameras, out_dir, sequence)
    if metrics_path is not None:
        values = {"mean_coverage": summary["mean_coverage"], "seconds_per_frame": summary["seconds_per_frame"],
                  "frames": len(summary["frames"]), "skipped_frames": len(summary["skipped"])}
        values.update(summary.get("ground_truth", {}))
        per_seq = dict(read_metrics(metrics_path).get("reconstruction", {}).get("sequences", {}))
        per_seq[sequence] = values
        merge_metrics(metrics_path, "reconstruction", {"sequences": per_seq, **pool_sequences(per_seq)})
    return summary


def pool_sequences(per_seq: dict) -> dict:
    """Session-level ``reconstruction.*`` from per-sequence values: the worst sequence's median/p90 error
    and completeness (acceptance keys), mean coverage, total skipped frames."""
    out = {"skipped_frames": int(sum(v.get("skipped_frames", 0) for v in per_seq.values())),
           "mean_coverage": float(np.nanmean([v.get("mean_coverage", np.nan) for v in per_seq.values()]))}
    ev = [v for v in per_seq.values() if "median_error_mm" in v]
    if ev:
        out["median_error_mm"] = float(max(v["median_error_mm"] for v in ev))
        out["p90_error_mm"] = float(max(v["p90_error_mm"] for v in ev))
        out["completeness"] = float(min(v["completeness"] for v in ev))
    return out

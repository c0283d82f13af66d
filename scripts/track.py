"""Snakemake entry point of the tracking stage (rules track_neutral and track_sequence in rules/track.smk).

Reads the session, calibrated cameras, ROM images and the reconstruction's depth maps; writes the outputs
atomically and merges ``tracking.*`` into ``results/<session>/metrics.json``. Only the session-level metrics
job (rule track_metrics) reads ``ground_truth/``, through :mod:`rigbuild.eval`, to add accuracy metrics.
"""


import csv
import io
import logging
import os
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from rigbuild.dots import painted_dot_vertices  # noqa: E402
from rigbuild.errors import InputError  # noqa: E402
from rigbuild.io.atomic import atomic_path, save_npz, write_json, write_text  # noqa: E402
from rigbuild.io.cameras import read_cameras  # noqa: E402
from rigbuild.io.metrics import merge_metrics  # noqa: E402
from rigbuild.session import read_session  # noqa: E402
from rigbuild.track.features import depth_to_image_grid  # noqa: E402
from rigbuild.track.matches import ViewFrame  # noqa: E402
from rigbuild.track.sequence import TrackParams  # noqa: E402

log = logging.getLogger("track")


def read_image_rgb(path: Path) -> np.ndarray:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise InputError("image missing or unreadable", path=path, fix="re-run the capture / synth stage")
    return np.ascontiguousarray(img[..., ::-1])


def read_depth_maps(path: Path, cameras) -> list[np.ndarray]:
    """Depth maps of one frame (one per camera, in camera order) resampled to the distorted image grids.

    Accepts the reconstruct stage's npz: ``depth`` (N, H, W) (or one (H, W) per ``depth_<cam>`` key) camera z
    in mm on undistorted pinhole grids (0/NaN = none), optional ``K`` (N, 3, 3) and ``camera_ids``.
    """
    if not path.exists():
        raise InputError("depth map missing", path=path,
                         fix="run the reconstruct stage for this sequence (rule reconstruct) before tracking")
    try:
        from rigbuild.io.depth import read_depth  # the reconstruction's reader, when present

        z = read_depth(path)
        data = {k: z[k] for k in z} if isinstance(z, dict) else {"depth": np.asarray(z)}
    except ImportError:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    ids = [str(c) for c in data.get("camera_ids", [])]
    out = []
    for i, cam in enumerate(cameras):
        if f"depth_{cam.id}" in data:
            d = data[f"depth_{cam.id}"]
        elif "depth" in data:
            D = np.asarray(data["depth"])
            j = ids.index(cam.id) if cam.id in ids else i
            if D.ndim == 2:
                D = D[None]
            if j >= D.shape[0]:
                raise InputError(f"no depth map for camera {cam.id}", path=path, fix="re-run reconstruct")
            d = D[j]
        else:
            raise InputError("npz has no 'depth' array", path=path, fix="re-run reconstruct")
        j = ids.index(cam.id) if cam.id in ids else i
        K = np.asarray(data["K"])[j] if "K" in data and np.asarray(data["K"]).ndim == 3 else None
        if d.shape != (cam.height, cam.width):
            raise InputError(f"depth map of camera {cam.id} is {d.shape}, images are {(cam.height, cam.width)}",
                             path=path, fix="re-run reconstruct at the session's image size")
        out.append(depth_to_image_grid(d, cam, K))
    return out


def load_frame(spec, cameras, seq: str, frame: int, depth_dir: Path) -> list[ViewFrame]:
    depths = read_depth_maps(depth_dir / f"{frame:06d}.npz", cameras)
    return [ViewFrame(cam, read_image_rgb(spec.rom_image(seq, cam.id, frame)), d) for cam, d in zip(cameras, depths)]


def _template(spec, params: dict):
    from rigbuild.io.rigs import load_rig

    return load_rig(params.get("template_rig", spec.template_rig))


def run_neutral(smk) -> None:
    from rigbuild.track.stage import track_neutral_frame

    tp = dict(smk.params.track)
    session_root = Path(smk.params.session_dir)
    spec = read_session(session_root)
    cameras = read_cameras(smk.input.cameras)
    seq = spec.rom[0]
    frames = load_frame(spec, cameras, seq.name, seq.neutral_frame, Path(smk.params.depth_dir))
    template = _template(spec, tp)
    params = TrackParams.from_dict({k: v for k, v in tp.items() if k not in ("registration", "template_rig")})
    t0 = time.perf_counter()
    reg, _ = track_neutral_frame(template, frames, params, tp.get("registration"),
                                 dot_vertices=painted_dot_vertices(template, spec.dot_stencil_mm))
    save_npz(smk.output.neutral, vertices=reg.vertices.astype(np.float32), markers=reg.markers.astype(np.float32),
             marker_vertices=template.marker_vertices, marker_names=np.asarray(template.marker_names),
             scale=np.float64(reg.similarity[0]), rotation=reg.similarity[1], translation=reg.similarity[2],
             dot_labels=reg.dot_labels, sequence=np.asarray(seq.name), frame=np.int64(seq.neutral_frame))
    values = {"neutral_scan_rms_mm": reg.scan_rms_mm, "neutral_dot_rms_mm": reg.dot_rms_mm,
              "neutral_dots_matched": int((reg.dot_labels >= 0).sum()), "neutral_seconds": time.perf_counter() - t0}
    merge_metrics(smk.params.metrics, "tracking", values)


def _residual_plot(path: Path, rows: list[dict], title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    f = [r["frame"] for r in rows]
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.5))
    ax[0].plot(f, [r["residual_median_mm"] for r in rows], "o-", label="median")
    ax[0].plot(f, [r["residual_p90_mm"] for r in rows], "s--", label="p90")
    lost = [r["frame"] for r in rows if r["lost"]]
    for x in lost:
        ax[0].axvline(x, color="r", alpha=0.3)
    ax[0].set_xlabel("frame"); ax[0].set_ylabel("constraint residual (mm)"); ax[0].legend(); ax[0].set_title(title)
    for key in ("dots", "sparse", "flow"):
        ax[1].plot(f, [max(r[key], 0.5) for r in rows], "o-", label=key)
    ax[1].set_yscale("log"); ax[1].set_xlabel("frame"); ax[1].set_ylabel("matches"); ax[1].legend()
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=90)
    plt.close(fig)


def _overlay(path: Path, view: ViewFrame, vertices: np.ndarray, markers: np.ndarray, face_vertices: np.ndarray) -> None:
    import cv2

    img = np.ascontiguousarray(view.image[..., ::-1]).copy()
    cam = view.camera
    pts = cam.project(vertices[face_vertices[::7]])
    for u, v in pts[np.isfinite(pts).all(1)]:
        cv2.circle(img, (int(round(u)), int(round(v))), 1, (0, 200, 0), -1)
    mk = cam.project(markers)
    for u, v in mk[np.isfinite(mk).all(1)]:
        cv2.circle(img, (int(round(u)), int(round(v))), 4, (0, 0, 255), 1)
    with atomic_path(path, suffix=".png") as tmp:
        cv2.imwrite(str(tmp), img)


def run_sequence(smk) -> None:
    from rigbuild.io.markers import write_markers_c3d
    from rigbuild.track.stage import stats_rows, track_rom_sequence

    tp = dict(smk.params.track)
    session_root = Path(smk.params.session_dir)
    spec = read_session(session_root)
    cameras = read_cameras(smk.input.cameras)
    seq_name = smk.wildcards.sequence
    seq = next((s for s in spec.rom if s.name == seq_name), None)
    if seq is None:
        raise InputError(f"no ROM sequence '{seq_name}'", path=session_root / "session.yaml")
    template = _template(spec, tp)
    params = TrackParams.from_dict({k: v for k, v in tp.items() if k not in ("registration", "template_rig")})
    params.workers = max(int(smk.threads), 1)
    with np.load(smk.input.neutral) as z:
        neutral = z["vertices"].astype(np.float64)
    anchor_seq = spec.rom[0]
    anchor = load_frame(spec, cameras, anchor_seq.name, anchor_seq.neutral_frame, Path(smk.params.anchor_depth_dir))
    frame_ids = [f for f in seq.frames if f >= seq.neutral_frame]
    depth_dir = Path(smk.params.depth_dir)
    frames = [load_frame(spec, cameras, seq.name, f, depth_dir) for f in frame_ids]
    t0 = time.perf_counter()
    V, C, markers, stats = track_rom_sequence(template, neutral, anchor, frames, frame_ids, seq.name, params,
                                              progress=lambda s: log.info("frame %d: %s", s.frame, s),
                                              dot_vertices=painted_dot_vertices(template, spec.dot_stencil_mm))
    seconds = time.perf_counter() - t0
    lost = np.asarray([s.lost for s in stats], dtype=bool)
    if lost.any():  # lost frames reach the retargeting stages as marker gaps, not as wrong positions
        markers = markers.copy()
        markers[lost] = np.nan
        log.warning("%s: %d lost frame(s) %s written as marker gaps (NaN)", seq.name, int(lost.sum()),
                    [s.frame for s in stats if s.lost])
    out = smk.output
    save_npz(out.vertices, vertices=V, confidence=C, frames=np.asarray(frame_ids),
             lost=lost)
    save_npz(out.markers, markers=markers.astype(np.float32), marker_names=np.asarray(template.marker_names),
             fps=np.float64(spec.fps), frames=np.asarray(frame_ids))
    write_markers_c3d(out.c3d, markers, template.marker_names, spec.fps)
    rows = stats_rows(stats)
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(rows[0].keys()))
    w.writeheader()
    w.writerows(rows)
    write_text(out.residuals_csv, buf.getvalue())
    _residual_plot(Path(out.residuals_png), rows, f"{smk.wildcards.session} / {seq.name}")
    ov = Path(out.overlay)
    ov.mkdir(parents=True, exist_ok=True)
    peak = int(np.argmax([np.abs(V[i] - V[0]).max() for i in range(len(V))]))
    for i in sorted({0, peak, len(V) - 1}):
        _overlay(ov / f"{frame_ids[i]:06d}.png", frames[i][0], V[i], markers[i], template.face_vertices)
    seq_metrics = {"frames": len(frame_ids), "lost_frames": int(sum(s.lost for s in stats)),
                   "seconds_per_frame": seconds / max(len(frame_ids), 1),
                   "median_residual_mm": float(np.nanmedian([s.residual_median_mm for s in stats])),
                   "lost": [s.frame for s in stats if s.lost]}
    write_json(out.metrics, seq_metrics)
    merge_metrics(smk.params.metrics, "tracking", {f"{seq.name}_lost_frames": seq_metrics["lost_frames"],
                                                   f"{seq.name}_seconds_per_frame": seq_metrics["seconds_per_frame"]})


def main(smk) -> None:
    if smk.rule == "track_neutral":
        run_neutral(smk)
    elif smk.rule == "track_sequence":
        run_sequence(smk)
    elif smk.rule == "track_metrics":
        run_metrics(smk)
    else:
        raise ValueError(f"scripts/track.py does not handle rule {smk.rule}")


def run_metrics(smk) -> None:
    """Session-level tracking metrics: lost frames from the per-sequence metrics and, for a synthetic session
    (``ground_truth/`` present), the accuracy against ground truth (rigbuild.eval; the tracking jobs
    themselves never read it)."""
    import json

    from rigbuild.eval.tracking import ground_truth_tracking_metrics

    per = {Path(p).parent.name: json.loads(Path(p).read_text()) for p in smk.input.seq_metrics}
    values = {"lost_frames": int(sum(int(d.get("lost_frames", 0)) for d in per.values())), "sequences": len(per)}
    gt_dir = Path(smk.params.session_dir) / "ground_truth"
    if gt_dir.is_dir():
        spec = read_session(Path(smk.params.session_dir))
        template = _template(spec, dict(smk.params.track))
        with np.load(smk.input.neutral) as z:
            neutral = z["vertices"].astype(np.float64)
            neutral_at = (str(z["sequence"]), int(z["frame"]))
        tracked = {}
        for p in smk.input.vertices:
            with np.load(p) as z:
                tracked[Path(p).parent.name] = (z["vertices"].astype(np.float64), z["frames"].astype(np.int64))
        gt_values, gt_per = ground_truth_tracking_metrics(gt_dir, smk.input.cameras, template.faces,
                                                          template.face_vertices, neutral, neutral_at, tracked)
        values.update(gt_values)
        for name, d in gt_per.items():
            per[name].update(d)
    merge_metrics(smk.params.metrics, "tracking", values)
    write_json(smk.output.summary, {"tracking": values, "sequences": per})


if "snakemake" in globals():
    from rigbuild.logs import run_logged

    run_logged(snakemake, main)  # noqa: F821

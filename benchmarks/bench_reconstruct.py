"""Benchmark of issue 4: seconds per frame of CPU multi-view stereo at 1280x960 (8 and 16 cameras), peak
memory, and the accuracy against ground truth of the same frames.

The ICT head (needs $RIGBUILD_DATA) is rendered by rigbuild.render with a speckle texture, sensor noise and
lens distortion, seen by cameras 450 mm away: 8 on a 120-degree arc, or 16 in two rows of 8 (pitch -12/+12
degrees). Each configuration is reconstructed in a fresh child process limited to ``--cores`` cores
(default 2: the issue's "2 cores"), which reports wall time, CPU time and its peak RSS.

Run: ``.venv/bin/python benchmarks/bench_reconstruct.py [--frames 2] [--cores 2]``; writes
``benchmarks/out/reconstruct.json`` and prints a table. Goal (issue 4): under 20 s per frame for 8 cameras.
Wall time depends on what else the machine runs: CPU seconds are reported too (on an idle machine the
wall time is at most the CPU time).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))


def render_frames(n_cameras: int, n_frames: int, out: Path) -> list[Path]:
    import numpy as np

    from recon_scene import camera_arc
    from rigbuild.io.rigs import read_ict_rig
    from rigbuild.paths import ict_dir
    from rigbuild.render import TexturedMesh, render_mesh, speckle_texture

    rig = read_ict_rig(ict_dir())
    face = rig.neutral[rig.face_vertices]
    target = np.array([0.0, face[:, 1].mean() + 20.0, face[:, 2].max() - 60.0])
    rows = 1 if n_cameras <= 8 else 2
    cams = camera_arc(n_cameras, 1280, 960, 1800.0, 450.0, target=target, yaw_span_deg=120.0, rows=rows,
                      pitch_deg=(-12.0, 12.0), dist=(-0.05, 0.02, 0.0, 0.0, 0.0))
    tex = speckle_texture(2048, 0)
    files = []
    for f in range(n_frames):
        w = np.zeros(rig.n_shapes)
        if f % 2 == 1:
            for name, val in (("jawOpen", 0.4), ("mouthSmile_L", 0.5), ("mouthSmile_R", 0.5)):
                if name in rig.shape_names:
                    w[rig.shape_index(name)] = val
        V = rig.evaluate(w)
        mesh = TexturedMesh(V, rig.faces, rig.uvs, rig.face_uvs, tex)
        images = np.stack([render_mesh(c, mesh, noise_sigma=1.5, seed=100 * f + k).color[..., ::-1]
                           for k, c in enumerate(cams)])
        p = out / f"frame_{n_cameras}_{f}.npz"
        np.savez(p, images=images, vertices=V, faces=rig.faces, face=rig.face_vertices,
                 cameras=json.dumps([c.to_dict() for c in cams]))
        files.append(p)
    return files


def _child(path: str, cores: int, queue) -> None:
    """Reconstruct one frame in this process (pinned to ``cores`` cores); report timings and peak RSS."""
    import resource

    try:
        os.sched_setaffinity(0, set(sorted(os.sched_getaffinity(0))[:cores]))
    except (AttributeError, OSError):
        pass
    import cv2
    import numpy as np

    cv2.setNumThreads(cores)
    from rigbuild.camera import Camera
    from rigbuild.eval.reconstruction import evaluate_frame
    from rigbuild.reconstruct.frame import ReconstructParams, reconstruct_frame

    z = np.load(path)
    cams = [Camera.from_dict(d) for d in json.loads(str(z["cameras"]))]
    images = list(z["images"])
    t0, c0 = time.perf_counter(), time.process_time()
    rec = reconstruct_frame(images, cams, ReconstructParams())
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    ev = evaluate_frame(z["vertices"], z["faces"], z["face"], cams, rec.mesh_vertices, rec.mesh_faces, rec.points)
    ev.pop("distances")
    queue.put({"wall_s": wall, "cpu_s": cpu, "peak_rss_mb": peak_mb, "stages_s": rec.stats["seconds"],
               "stages_cpu_s": rec.stats["cpu_seconds"], "n_points": rec.stats["n_points"],
               "mean_coverage": float(np.mean(list(rec.stats["coverage"].values()))), "accuracy": ev})


def run_child(path: Path, cores: int) -> dict:
    import multiprocessing as mp

    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    p = ctx.Process(target=_child, args=(str(path), cores, q))
    p.start()
    out = q.get()
    p.join()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=2)
    ap.add_argument("--cores", type=int, default=2)
    ap.add_argument("--cameras", type=int, nargs="+", default=[8, 16])
    args = ap.parse_args()
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    from rigbuild.paths import ict_dir

    if not (ict_dir() / "generic_neutral_mesh.obj").exists():
        sys.exit(f"bench_reconstruct: ICT-FaceKit not found at {ict_dir()} (set RIGBUILD_DATA)")
    results = {"image_size": [1280, 960], "cores": args.cores, "goal_s_per_frame_8_cameras": 20.0,
               "load_average_at_start": os.getloadavg(), "configs": {}}
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.cameras:
            files = render_frames(n, args.frames, Path(tmp))
            runs = [run_child(f, args.cores) for f in files]
            results["configs"][f"{n}_cameras"] = {
                "seconds_per_frame": sum(r["wall_s"] for r in runs) / len(runs),
                "cpu_seconds_per_frame": sum(r["cpu_s"] for r in runs) / len(runs),
                "peak_rss_mb": max(r["peak_rss_mb"] for r in runs),
                "median_error_mm": max(r["accuracy"]["median_error_mm"] for r in runs),
                "p90_error_mm": max(r["accuracy"]["p90_error_mm"] for r in runs),
                "completeness": min(r["accuracy"]["completeness"] for r in runs),
                "frames": runs,
            }
    results["load_average_at_end"] = os.getloadavg()
    (HERE / "out").mkdir(exist_ok=True)
    from rigbuild.io.atomic import write_json

    write_json(HERE / "out" / "reconstruct.json", results)
    print(f"{'config':<12}{'s/frame':>9}{'cpu s':>8}{'peak MB':>9}{'median mm':>11}{'p90 mm':>8}{'complete':>10}")
    for k, v in results["configs"].items():
        print(f"{k:<12}{v['seconds_per_frame']:>9.1f}{v['cpu_seconds_per_frame']:>8.1f}{v['peak_rss_mb']:>9.0f}"
              f"{v['median_error_mm']:>11.3f}{v['p90_error_mm']:>8.3f}{v['completeness']:>10.4f}")
    print(f"goal: < 20 s per frame for 8 cameras on {args.cores} cores; load average "
          f"{results['load_average_at_start'][0]:.1f} -> {results['load_average_at_end'][0]:.1f} "
          "(wall time is inflated when other jobs share the cores)")


if __name__ == "__main__":
    main()

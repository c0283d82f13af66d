"""Benchmark of rig calibration (issue 3).

1. Time to calibrate 16 cameras x 30 board poses (simulated detections, 1280x960, 0.1 px noise) and how it
   grows with cameras and poses (goal: under 60 s on 2 cores).
2. The solver comparison behind rigbuild.calibrate.bundle: scipy least_squares (trf + jac_sparsity) vs
   the Levenberg-Marquardt used, on the same problem.
3. Accuracy against ground truth for ICT-tier rigs (8 and 16 cameras, 1280x960) as a function of corner
   noise, number of board poses and board size, against the issue's bounds.
4. Detection time per 1280x960 image (images rendered by tests/calib_scene.py).

Writes benchmarks/out/calibrate.json and prints a table. Run: OPENBLAS_NUM_THREADS=1 python benchmarks/bench_calibrate.py
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from scipy.optimize import least_squares  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from rigbuild.calibrate.bundle import Observations, jacobian_sparsity, project  # noqa: E402
from rigbuild.calibrate.detect import detect_board  # noqa: E402
from rigbuild.calibrate.rig import CalibrationOptions, calibrate_rig  # noqa: E402
from rigbuild.calibrate.simulate import arc_rig, random_board_poses, simulate_detections  # noqa: E402
from rigbuild.eval.calibration import compare_cameras  # noqa: E402
from rigbuild.session import BoardSpec  # noqa: E402

BOARD = BoardSpec("charuco", 7, 5, 24.0, 18.0, "DICT_5X5_100")
BOUNDS = {"rms_px": 0.2, "focal_error_pct": 0.1, "principal_point_error_px": 1.0, "center_error_mm": 0.3,
          "rotation_error_deg": 0.02}


def problem(n_cams, n_poses, noise=0.1, board=BOARD, seed=0):
    cams = arc_rig(n_cams, 1280, 960, focal_px=1500.0, distance_mm=450.0, azimuth_deg=120.0, seed=seed)
    poses = random_board_poses(n_poses, board, seed=seed + 1)
    return cams, simulate_detections(cams, board, poses, noise_px=noise, seed=seed + 2)


def run(n_cams, n_poses, noise=0.1, board=BOARD, seed=0):
    cams, det = problem(n_cams, n_poses, noise, board, seed)
    t = time.perf_counter()
    res = calibrate_rig(det, board, (1280, 960), CalibrationOptions(max_rms_px=1.0))
    total = time.perf_counter() - t
    err = compare_cameras(res.cameras, cams)
    return {"cameras": n_cams, "poses": n_poses, "noise_px": noise, "board": f"{board.squares_x}x{board.squares_y}",
            "corners": len(res.obs), "seconds": total, "seconds_bundle": res.seconds["bundle"],
            "seconds_intrinsics": res.seconds["intrinsics"], "iterations_nfev": res.bundle.nfev,
            "rms_px": res.rms_px, **{k: err[k] for k in ("focal_error_pct", "principal_point_error_px",
                                                         "center_error_mm", "center_error_mm_mean",
                                                         "rotation_error_deg", "rotation_error_deg_mean",
                                                         "scale_error_pct")}}


def scipy_comparison(n_cams=8, n_poses=20):
    """Same initial values (from calibrate_rig's pose graph) solved by scipy least_squares trf/lsmr."""
    cams, det = problem(n_cams, n_poses)
    t = time.perf_counter()
    ours = calibrate_rig(det, BOARD, (1280, 960), CalibrationOptions(max_rms_px=1.0))
    t_ours = ours.seconds["bundle"]
    from rigbuild.calibrate import rig as rigmod

    captured = {}
    orig = rigmod.bundle_adjust

    def capture(cp, bp, obs, pts, **kw):
        captured.update(cp=cp.copy(), bp=bp.copy(), obs=obs, pts=pts, kw=kw)
        return orig(cp, bp, obs, pts, **kw)

    rigmod.bundle_adjust = capture
    try:
        calibrate_rig(det, BOARD, (1280, 960), CalibrationOptions(max_rms_px=1.0))
    finally:
        rigmod.bundle_adjust = orig
    cp, bp, obs, pts = captured["cp"], captured["bp"], captured["obs"], captured["pts"]
    C, V = cp.shape[0], bp.shape[0]
    full0 = np.concatenate([cp.ravel(), bp.ravel()])
    free = np.ones(full0.size, bool)
    free[:6] = False
    free = np.flatnonzero(free)

    def fun(x):
        full = full0.copy()
        full[free] = x
        return (project(full[: C * 15].reshape(C, 15), full[C * 15:].reshape(V, 6), obs, pts) - obs.uv).ravel()

    t = time.perf_counter()
    sol = least_squares(fun, full0[free], jac_sparsity=jacobian_sparsity(obs, C, V, free), method="trf",
                        tr_solver="lsmr", x_scale="jac", loss="soft_l1", f_scale=1.0, ftol=1e-12, xtol=1e-12,
                        gtol=1e-12, max_nfev=200)
    t_scipy = time.perf_counter() - t
    r = sol.fun.reshape(-1, 2)
    return {"problem": f"{n_cams} cameras x {n_poses} poses", "lm_seconds": t_ours, "lm_rms_px": ours.rms_px,
            "lm_message": ours.bundle.message, "scipy_seconds": t_scipy,
            "scipy_rms_px": float(np.sqrt(np.mean(np.sum(r ** 2, 1)))), "scipy_nfev": int(sol.nfev),
            "scipy_message": sol.message}


def detection_timing(n=3):
    from calib_scene import render_board_image

    cams = arc_rig(2, 1280, 960, focal_px=1500.0, distance_mm=450.0, azimuth_deg=60.0, seed=3)
    poses = random_board_poses(n, BOARD, seed=4, max_tilt_deg=30)
    times, counts = [], []
    for cam in cams:
        for R, t in poses:
            img = render_board_image(cam, BOARD, R, t)
            t0 = time.perf_counter()
            counts.append(len(detect_board(img, BOARD)))
            times.append(time.perf_counter() - t0)
    return {"images": len(times), "median_seconds_per_image": float(np.median(times)),
            "corners_found": counts}


def main():
    out = {"machine": f"{os.cpu_count()} cores, OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS')}, "
                      f"load average {os.getloadavg()[0]:.1f} at start"}
    print("== timing: 16 cameras x 30 poses, and growth")
    grid = []
    for c, p in [(16, 30), (4, 30), (8, 30), (16, 10), (16, 20), (16, 60)]:
        row = run(c, p)
        grid.append(row)
        print(f"{c:3d} cams {p:3d} poses {row['corners']:6d} corners  {row['seconds']:6.2f} s "
              f"(bundle {row['seconds_bundle']:5.2f} s)  rms {row['rms_px']:.3f}")
    out["timing"] = grid
    out["timing_16x30_seconds"] = grid[0]["seconds"]
    print("== solver comparison")
    out["solver_comparison"] = scipy_comparison()
    print(json.dumps(out["solver_comparison"], indent=1))
    print("== accuracy (ICT tier, 1280x960) vs bounds", BOUNDS)
    acc = []
    big = BoardSpec("charuco", 11, 8, 16.0, 12.0, "DICT_5X5_100")
    for c, p, noise, board in [(8, 30, 0.1, BOARD), (8, 30, 0.05, BOARD), (8, 60, 0.05, BOARD),
                               (16, 30, 0.05, BOARD), (8, 30, 0.05, big), (16, 60, 0.05, big)]:
        row = run(c, p, noise, board)
        row["meets_bounds"] = {k: bool(row[k] <= v) for k, v in BOUNDS.items()}
        acc.append(row)
        print(f"{c:3d} cams {p:3d} poses noise {noise:.2f} board {row['board']:5s}: rms {row['rms_px']:.3f} "
              f"focal {row['focal_error_pct']:.4f}% pp {row['principal_point_error_px']:.2f} px "
              f"centre {row['center_error_mm']:.3f} mm (mean {row['center_error_mm_mean']:.3f}) "
              f"rot {row['rotation_error_deg']:.4f} deg (mean {row['rotation_error_deg_mean']:.4f}) "
              f"scale {row['scale_error_pct']:+.4f}%")
    out["accuracy"] = acc
    print("== detection")
    out["detection"] = detection_timing()
    print(out["detection"])
    path = ROOT / "benchmarks" / "out" / "calibrate.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    from rigbuild.io.atomic import write_json

    write_json(path, out)
    print("wrote", path)


if __name__ == "__main__":
    main()

"""Benchmark of rig calibration (issue 3).

1. Time to calibrate 16 cameras x 30 board poses (simulated detections, 1280x960, 0.1 px noise) and how it
   grows with cameras and poses (goal: under 60 s on 2 cores).
2. The solver comparison behind rigbuild.calibrate.bundle: scipy least_squares (trf + jac_sparsity) vs
   the Levenberg-Marquardt used, on the same problem.
3. Accuracy against ground truth for ICT-tier rigs (8 and 16 cameras, 1280x960) as a function of corner
   noise, number of board poses and board size, against the issue's bounds.
4. Detection time per 1280x960 image (images rendered by the project renderer, rigbuild.render.board).
5. The issue's acceptance on a rendered ICT-tier session: config/ict.yaml's synthetic block (8 cameras,
   1280x960, 11x8 ChArUco of 16 mm squares, 40 poses, 1.5 grey-level noise) rendered by
   rigbuild.synth.calibration_scene.render_calibration_session (the generator's functions and seeds), calibrated
   by rigbuild.calibrate.session.calibrate_session, compared with ground truth; plus the corner
   localisation accuracy of render + detector (detected corners vs Camera.project of the true corners).

6. Real footage (issue 21): the 4-camera sleap-anipose ChArUco recording (84 JPEG images, 1280x1024) as the
   calibration-only session config/calibration-only/sleap-charuco with config/sleap-charuco.yaml's
   parameters over config/config.yaml's (as the pipeline merges them), timed end to end (detection,
   intrinsics, pose graph, bundle adjustment, held-out refit; goal: under 30 s on 2 cores); skipped when
   $RIGBUILD_DATA lacks it.
7. Section 5 with separately shot intrinsics: 12 close-up boards per camera seen by it alone
   (calib_intrinsics/<cam>/), their intrinsics held in the rig fit (known_intrinsics: fixed) or as priors
   (prior); the same bounds.
8. The corners' noise model on the realistic tiers' own calibration images (rigbuild.synth.session.
   generate_calibration_only: the bytes the pipeline's generator writes): the development actor
   (config/ict-dev.yaml, where the choice is made) and the acceptance actors (config/ict.yaml, config/ict-b.yaml),
   each calibrated with config/config.yaml's calibrate block and with it under robust_scale_px 1 (equal weights,
   1 px soft-L1), auto, and auto + noise_model view_angle, the last also with OpenCV's own ChArUco corners
   (face_on_subpix_deg 0: no second pass on the corners seen nearly face-on); the same bounds.

Writes benchmarks/out/calibrate.json and prints a table.
Run: OPENBLAS_NUM_THREADS=1 python benchmarks/bench_calibrate.py [--only timing,solver,accuracy,detection,rendered,real,separate]
(--only reruns the named sections and keeps the others from the existing json.)
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from scipy.optimize import least_squares  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from rigbuild.calibrate.bundle import Observations, jacobian_sparsity, project  # noqa: E402
from rigbuild.calibrate.detect import detect_board  # noqa: E402
from rigbuild.calibrate.rig import CalibrationOptions, calibrate_rig  # noqa: E402
from rigbuild.synth.calibration_scene import arc_rig, random_board_poses, simulate_detections  # noqa: E402
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
    """Render n poses x 2 cameras with the project renderer and time the ChArUco detection."""
    from rigbuild.render.board import render_board
    from rigbuild.synth.rig_layout import DEFAULT_TARGET, make_board_poses, make_camera_rig

    cams = make_camera_rig(2, 1280, 960, distance_mm=450.0, arc_deg=(-20.0, 20.0), seed=3)
    poses, _ = make_board_poses(cams, BOARD, n, seed=4, center=DEFAULT_TARGET)
    times, counts = [], []
    for cam in cams:
        for k, (R, t) in enumerate(poses):
            img = render_board(cam, BOARD, R, t, noise_sigma=1.5, seed=k)
            t0 = time.perf_counter()
            counts.append(len(detect_board(img[..., 1], BOARD)))
            times.append(time.perf_counter() - t0)
    return {"images": len(times), "median_seconds_per_image": float(np.median(times)),
            "corners_found": counts}


def pipeline_calibrate_block() -> dict:
    """config/config.yaml's ``params.calibrate``: what every tier's calibrate rule runs with (a tier's or session's
    config is merged over it)."""
    import yaml

    return yaml.safe_load((ROOT / "config" / "config.yaml").read_text())["params"]["calibrate"]


def rendered_ict_tier(folder=None, intrinsics_poses: int = 0, params: dict | None = None):
    """Section 5: render config/ict.yaml's calibration images, calibrate, compare with ground truth.
    ``intrinsics_poses`` > 0 (section 7): also each camera's own close-up boards (calib_intrinsics/<cam>/), whose
    intrinsics the rig fit holds (``params``: over config/config.yaml's calibrate block, as the pipeline merges
    them; known_intrinsics fixed by default, or prior)."""
    import tempfile

    import yaml

    from rigbuild.calibrate.detect import Detection
    from rigbuild.calibrate.session import calibrate_session, calibration_metrics
    from rigbuild.synth.calibration_scene import render_calibration_session
    from rigbuild.eval.calibration import compare_cameras, corner_error_summary, corner_localisation_errors
    from rigbuild.io.cameras import read_cameras

    block = yaml.safe_load((ROOT / "config" / "ict.yaml").read_text())["sessions"]["ict"]["synthetic"]
    tmp = None
    if folder is None:
        tmp = tempfile.TemporaryDirectory(prefix="bench_calib_ict_")
        folder = Path(tmp.name) / "ict"
    folder = Path(folder)
    render_s = t_render = None  # None: a session rendered before was reused (--rendered-folder)
    if not (folder / "ground_truth" / "cameras.json").exists():
        t0 = time.perf_counter()
        render_s = render_calibration_session(folder, "ict", block, intrinsics_poses=intrinsics_poses)["seconds"]
        t_render = time.perf_counter() - t0
    from rigbuild.calibrate.params import from_config

    base = pipeline_calibrate_block()  # ``params`` over it, as the pipeline merges a tier's config
    spec, res = calibrate_session(folder, from_config({**base, **(params or {})}), workers=2)  # the rule's 2 threads
    truth = read_cameras(folder / "ground_truth" / "cameras.json")
    gt = np.load(folder / "ground_truth" / "board_poses.npz")
    # corner localisation: every observation the calibration used vs the true projection
    obs = res.obs
    used = {c.id: {res.view_keys[v]: Detection(obs.corner[(obs.cam == ci) & (obs.view == v)],
                                               obs.uv[(obs.cam == ci) & (obs.view == v)])
                   for v in np.unique(obs.view[obs.cam == ci])} for ci, c in enumerate(res.cameras)}
    loc = corner_localisation_errors(used, truth, spec.board, list(zip(gt["R"], gt["t"])))
    err, view_angle = loc["errors"], loc["view_angle_deg"]
    by_angle = []
    for lo, hi in [(0, 30), (30, 45), (45, 55), (55, 65), (65, 90)]:
        m = (view_angle >= lo) & (view_angle < hi)
        if m.any():
            by_angle.append({"view_angle_deg": f"{lo}-{hi}", **corner_error_summary(err[m])})
    acc = compare_cameras(res.cameras, truth)
    m = calibration_metrics(res)
    out = {"session": "config/ict.yaml sessions.ict.synthetic (calibration images only)",
           "block": {k: block[k] for k in ("seed", "n_cameras", "image_size", "camera_distance_mm", "calib_poses",
                                           "board")},
           "render_seconds": render_s, "render_and_write_seconds": t_render, "intrinsics_poses": intrinsics_poses,
           "params": {**base, **(params or {})},
           "intrinsics_source": m["intrinsics_source"],
           **{k: m[k] for k in ("rms_px", "max_camera_rms_px", "n_images_used", "n_images_dropped", "n_corners",
                                "bundle_iterations_nfev", "bundle_converged", "seconds", "seconds_detect",
                                "seconds_bundle")},
           **acc,
           "corner_localisation_px": corner_error_summary(err),
           "corner_localisation_by_view_angle": by_angle}
    out["meets_bounds"] = {k: bool(out[k] <= v) for k, v in BOUNDS.items()}
    if tmp is not None:
        tmp.cleanup()
    return out


def real_footage():
    """Section 6: the sleap-anipose recording through calibrate_session (2 detection processes, as the rule
    runs it), timed; None without the data."""
    import yaml

    from rigbuild.calibrate.params import from_config
    from rigbuild.calibrate.session import calibrate_session, calibration_metrics
    from rigbuild.paths import data_dir

    if not (data_dir() / "sleap-anipose-charuco-4cam").is_dir():
        return None
    base = pipeline_calibrate_block()  # the session's config over it, as the pipeline merges them
    params = {**base, **yaml.safe_load((ROOT / "config" / "sleap-charuco.yaml").read_text())["params"]["calibrate"]}
    t0, c0 = time.perf_counter(), time.process_time()
    _, res = calibrate_session(ROOT / "config" / "calibration-only" / "sleap-charuco", from_config(params),
                               workers=2)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    m = calibration_metrics(res)
    keep = ("status", "rms_px", "camera_rms_px", "heldout_reprojection_rms_px", "heldout_camera_rms_px",
            "heldout_scale_deviation_pct", "heldout_n_board_poses", "heldout_n_corners", "n_images_used",
            "n_corners", "bundle_iterations_nfev", "bundle_converged", "plausibility_flags", "seconds_detect",
            "seconds_bundle")
    return {"session": "config/calibration-only/sleap-charuco (params: config/sleap-charuco.yaml)",
            "params": params, "wall_seconds": wall, "cpu_seconds": cpu, "load_average": os.getloadavg()[0],
            "goal_seconds": 30.0, "meets_goal": bool(wall < 30.0),
            "seconds_rig_fit_and_heldout": wall - m["seconds_detect"], **{k: m[k] for k in keep}}


NOISE_TIERS = (("ict-dev.yaml", "ict_dev"), ("ict.yaml", "ict"), ("ict-b.yaml", "ict_b"))
NOISE_VARIANTS = (("fixed_1px", {"robust_scale_px": 1.0, "noise_model": "none"}),
                  ("auto", {"robust_scale_px": "auto", "noise_model": "none"}),
                  ("auto_view_angle", {"robust_scale_px": "auto", "noise_model": "view_angle"}),
                  ("auto_view_angle_opencv_corners", {"robust_scale_px": "auto", "noise_model": "view_angle",
                                                      "face_on_subpix_deg": 0.0}))


def noise_models(folder: Path) -> dict:
    """Section 8: each tier's calibration images (rendered into ``folder``/<session>, reused if there), calibrated
    with each noise variant over config/config.yaml's calibrate block; errors against the truth."""
    import yaml

    from rigbuild.calibrate.params import from_config
    from rigbuild.calibrate.session import calibrate_session, calibration_metrics
    from rigbuild.io.cameras import read_cameras
    from rigbuild.synth.session import generate_calibration_only

    base = pipeline_calibrate_block()
    out = {"base_params": base, "variants": dict(NOISE_VARIANTS), "tiers": {}}
    for config, name in NOISE_TIERS:
        block = yaml.safe_load((ROOT / "config" / config).read_text())["sessions"][name]["synthetic"]
        sess = folder / name
        if not (sess / "session.yaml").exists():
            t0 = time.perf_counter()
            generate_calibration_only(sess, name, block)
            print(f"  {name}: rendered in {time.perf_counter() - t0:.0f} s")
        truth = read_cameras(sess / "ground_truth" / "cameras.json")
        rows = {}
        for key, variant in NOISE_VARIANTS:
            spec, res = calibrate_session(sess, from_config({**base, **variant}), workers=2)
            m = calibration_metrics(res)
            row = {**{k: m[k] for k in ("rms_px", "seconds_bundle", "bundle_iterations_nfev")},
                   "heldout_reprojection_rms_px": (res.heldout or {}).get("rms_px"), "noise": res.noise,
                   **compare_cameras(res.cameras, truth)}
            row["meets_bounds"] = {k: bool(row[k] <= v) for k, v in BOUNDS.items()}
            rows[key] = row
            print(f"  {name:8s} {key:16s} rms {row['rms_px']:.3f} px  focal {row['focal_error_pct']:.4f} %  pp "
                  f"{row['principal_point_error_px']:.3f} px  centre {row['center_error_mm']:.4f} mm  rotation "
                  f"{row['rotation_error_deg']:.4f} deg (mean {row['rotation_error_deg_mean']:.4f})  bundle "
                  f"{row['seconds_bundle']:.1f} s")
        out["tiers"][name] = {"config": f"config/{config}", "seed": block["seed"], **rows}
    return out


SECTIONS = ("timing", "solver", "accuracy", "detection", "rendered", "real", "separate", "noise")


def main(argv=None):
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default=",".join(SECTIONS), help="comma-separated sections to run")
    ap.add_argument("--rendered-folder", default=None,
                    help="section 5: render the ICT-tier calibration session here (kept; reused if present)")
    args = ap.parse_args(argv)
    only = [x for x in args.only.split(",") if x]
    unknown = sorted(set(only) - set(SECTIONS))
    if unknown:
        ap.error(f"unknown sections {unknown}; choose from {SECTIONS}")
    path = ROOT / "benchmarks" / "out" / "calibrate.json"
    out = json.loads(path.read_text()) if path.exists() and set(only) != set(SECTIONS) else {}
    from common import machine

    out["machine"] = {**machine(), "openblas_threads": os.environ.get("OPENBLAS_NUM_THREADS"),
                      "load_average_at_start": round(os.getloadavg()[0], 1)}
    out["sections_run"] = only
    if "timing" in only:
        print("== timing: 16 cameras x 30 poses, and growth")
        grid = []
        for c, p in [(16, 30), (4, 30), (8, 30), (16, 10), (16, 20), (16, 60)]:
            row = run(c, p)
            grid.append(row)
            print(f"{c:3d} cams {p:3d} poses {row['corners']:6d} corners  {row['seconds']:6.2f} s "
                  f"(bundle {row['seconds_bundle']:5.2f} s)  rms {row['rms_px']:.3f}")
        out["timing"] = grid
        out["timing_16x30_seconds"] = grid[0]["seconds"]
    if "solver" in only:
        print("== solver comparison")
        out["solver_comparison"] = scipy_comparison()
        print(json.dumps(out["solver_comparison"], indent=1))
    if "accuracy" in only:
        print("== accuracy (simulated detections, ICT-tier sizes, 1280x960) vs bounds", BOUNDS)
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
    if "detection" in only:
        print("== detection")
        out["detection"] = detection_timing()
        print(out["detection"])
    if "rendered" in only:
        print("== rendered ICT tier (config/ict.yaml) vs bounds", BOUNDS)
        r = rendered_ict_tier(args.rendered_folder)
        out["rendered_ict_tier"] = r
        print(f"  {r['n_cameras']} cameras, {r['n_images_used']} images used ({r['n_images_dropped']} dropped), "
              f"{r['n_corners']} corners; render {r['render_and_write_seconds'] or 0:.0f} s, calibrate "
              f"{r['seconds']:.1f} s (detect {r['seconds_detect']:.1f} s, bundle {r['seconds_bundle']:.1f} s)")
        c = r["corner_localisation_px"]
        print(f"  corner localisation: rms {c['rms']:.4f} px, bias ({c['bias_u']:+.4f}, {c['bias_v']:+.4f}) px, "
              f"p99 {c['p99']:.3f}, max {c['max']:.3f}")
        for row in r["corner_localisation_by_view_angle"]:
            print(f"    view angle {row['view_angle_deg']:>6s} deg: {row['n']:6d} corners rms {row['rms']:.4f} px "
                  f"max {row['max']:.3f}")
        print(f"  {'metric':28s} {'measured':>10s} {'bound':>8s}")
        for k, v in BOUNDS.items():
            print(f"  {k:28s} {r[k]:10.4f} {v:8.3f}  {'ok' if r['meets_bounds'][k] else 'NOT MET'}")
        print(f"  (mean over cameras: centre {r['center_error_mm_mean']:.4f} mm, rotation "
              f"{r['rotation_error_deg_mean']:.4f} deg, focal {r['focal_error_pct_mean']:.4f} %; "
              f"scale {r['scale_error_pct']:+.4f} %)")
    if "separate" in only:
        print("== rendered ICT tier with separately shot intrinsics (12 close-ups per camera) vs bounds", BOUNDS)
        with tempfile.TemporaryDirectory(prefix="bench_calib_sep_") as tmp:
            for key, params in (("rendered_ict_tier_separate_intrinsics", {"known_intrinsics": "fixed"}),
                                ("rendered_ict_tier_separate_intrinsics_prior", {"known_intrinsics": "prior"})):
                r = rendered_ict_tier(Path(tmp) / "ict", intrinsics_poses=12, params=params)
                out[key] = r
                print(f"  {params}: intrinsics {sorted(set(r['intrinsics_source'].values()))}; calibrate "
                      f"{r['seconds']:.1f} s")
                for k, v in BOUNDS.items():
                    print(f"  {k:28s} {r[k]:10.4f} {v:8.3f}  {'ok' if r['meets_bounds'][k] else 'NOT MET'}")
    if "noise" in only:
        print("== corner noise model on the realistic tiers' calibration images vs bounds", BOUNDS)
        if args.rendered_folder:
            out["noise_models"] = noise_models(Path(args.rendered_folder))
        else:
            with tempfile.TemporaryDirectory(prefix="bench_calib_noise_") as tmp:
                out["noise_models"] = noise_models(Path(tmp))
    if "real" in only:
        print("== real footage: sleap-anipose 4 cameras (calibration-only session)")
        r = real_footage()
        out["real_sleap_anipose"] = r
        if r is None:
            print("  skipped: sleap-anipose-charuco-4cam not in $RIGBUILD_DATA")
        else:
            print(f"  {r['wall_seconds']:.1f} s (goal 30 s; detection {r['seconds_detect']:.1f} s; {r['cpu_seconds']:.1f} "
                  f"CPU-seconds at load {r['load_average']:.1f}), status {r['status']}, "
                  f"rms {r['rms_px']:.3f} px, held out {r['heldout_reprojection_rms_px']:.3f} px "
                  f"({r['heldout_n_board_poses']} poses), scale {r['heldout_scale_deviation_pct']:+.4f} %")
    path.parent.mkdir(parents=True, exist_ok=True)
    from rigbuild.io.atomic import write_json

    write_json(path, out)
    print("wrote", path)


if __name__ == "__main__":
    main()

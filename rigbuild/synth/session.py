"""Generate a complete synthetic capture session with ground truth.

:func:`plan_session` turns the ``synthetic:`` block of a config entry into the ``session.yaml`` dict
(so the Snakemake DAG is known before anything is rendered); :func:`generate_session` writes the
session folder: ``session.yaml``, ``calib/<cam>/<n>.png``, ``rom/<seq>/<cam>/<frame:06d>.png``,
``performances/<name>.c3d`` and ``ground_truth/`` (cameras.json, rom/<seq>.npz, actor_rig.npz,
template_rig.npz, performances/<name>.npz, actor_info.json). Pipeline stages never read ground_truth/.
"""

from __future__ import annotations

import copy
import os
import shutil
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from rigbuild.errors import InputError

#: defaults of the ``synthetic:`` block (config/config.yaml documents each key)
SYNTH_DEFAULTS: dict[str, Any] = {
    "template_rig": "procedural",
    "seed": 0,
    "n_cameras": 6,
    "image_size": [640, 480],
    "camera_distance_mm": 450.0,
    "camera_arc_deg": [-60.0, 60.0],
    "camera_rows": 1,
    "distortion_scale": 1.0,
    # [lo, hi] of the lenses' k3 (sixth-order radial distortion), drawn per camera; [0, 0]: k3 = 0
    "distortion_k3": [0.0, 0.0],
    "noise_sigma": 1.5,
    # spacing (mm) of the registration dots painted between the markers (rigbuild.dots); None: markers only
    "dot_stencil_mm": None,
    # multisample anti-aliasing of the board and face renders (why off: docs/decisions.md)
    "msaa": False,
    # how the cameras see the face (rigbuild.synth.capture): speckle | realistic skin; single | studio lights;
    # camera: a sensor model (rigbuild.render.sensor.SensorParams keys) or None (8-bit Gaussian noise_sigma);
    # shutter: exposure as a fraction of the frame interval (motion blur, with a camera block)
    "appearance": "speckle",
    "lights": "single",
    "camera": None,
    "shutter": 0.5,
    # painted dots (rigbuild.synth.dots): stencil (the markers and the stencil sites, painted by hand: offsets
    # along the skin of sd dot_placement_sd_mm, a missing fraction, diameters and darkness drawn per dot) | none
    "dots": "stencil",
    "dot_placement_sd_mm": 0.0,
    "dot_missing_fraction": 0.0,
    "dot_diameter_mm": [3.0, 3.0],
    "dot_darkness": [0.902, 0.902],
    "calib_poses": 20,
    "board": {"type": "charuco", "squares_x": 7, "squares_y": 5, "square_size_mm": 24.0,
              "marker_size_mm": 18.0, "dictionary": "DICT_5X5_100"},
    "rom": {"n_sequences": 4, "frames_per_sequence": 9, "coverage": 2, "peak_range": [1.0, 1.0],
            "max_rotation_deg": 2.0, "max_translation_mm": 3.0, "hold_frames": None, "head_bound": "per_axis",
            "neutral_pose_deg": 0.0, "neutral_pose_mm": 0.0, "render_sequences": None},
    # marker_placement_sd_mm: hand placement of the mocap markers along the skin; occlusion: gaps where fewer
    # than min_cameras cameras of the rig see a marker (with gap_fraction's random gaps on top)
    "performance": {"n": 1, "duration_s": 10.0, "fps": 30.0, "noise_mm": 0.2, "gap_fraction": 0.01,
                    "marker_placement_sd_mm": 0.0, "occlusion": False, "min_cameras": 2},
    "actor": {"intensity_range": [0.6, 1.5], "asymmetry": 0.25, "crosstalk": 0.08, "warp": 0.15,
              "identity_sigma": None, "expression_novelty": None},
}


def _merge(base: dict, override: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in (override or {}).items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _merge(out[k], v)
        else:
            out[k] = v
    return out


def synth_params(synthetic: dict | None) -> dict:
    """The ``synthetic:`` block with defaults filled in."""
    return _merge(SYNTH_DEFAULTS, synthetic or {})


def rendered_sequences(p: dict, where: str = "synthetic") -> list[int]:
    """Indices of the ROM sequences a session holds (``rom.render_sequences``, default all ``n_sequences``): the
    shapes are planned over all ``n_sequences`` either way, so a benchmark can render a few of a tier's
    sequences exactly as the tier has them."""
    n_seq = int(p["rom"]["n_sequences"])
    wanted = p["rom"].get("render_sequences")
    if wanted is None:
        return list(range(n_seq))
    bad = [int(s) for s in wanted if not 0 <= int(s) < n_seq]
    if bad or len(set(wanted)) != len(wanted) or not wanted:
        raise InputError(f"field '{where}.rom.render_sequences' is {list(wanted)}", path="config",
                         fix=f"list sequence indices, each once, in 0..{n_seq - 1} (rom.n_sequences {n_seq}), "
                             "or leave render_sequences out")
    return sorted(int(s) for s in wanted)


def plan_session(name: str, synthetic: dict | None) -> dict:
    """The ``session.yaml`` dict a synthetic session will have (cameras, sequences, performances)."""
    p = synth_params(synthetic)
    F = int(p["rom"]["frames_per_sequence"])
    return {
        "name": name,
        "units": "mm",
        "cameras": [f"cam{i:02d}" for i in range(int(p["n_cameras"]))],
        "image_size": [int(p["image_size"][0]), int(p["image_size"][1])],
        "fps": float(p["performance"]["fps"]),
        "board": dict(p["board"]),
        "rom": [{"name": f"rom{s:02d}", "frames": [0, F - 1], "neutral_frame": 0} for s in rendered_sequences(p)],
        "performances": [{"name": f"perf{i:02d}", "file": f"performances/perf{i:02d}.c3d"}
                         for i in range(int(p["performance"]["n"]))],
        "template_rig": str(p["template_rig"]),
        "synthetic": {"seed": int(p["seed"]), "generator": "rigbuild.synth.session"},
    } | ({"dots": "none"} if p["dots"] == "none" else
         {"dot_stencil_mm": float(p["dot_stencil_mm"])} if p["dot_stencil_mm"] is not None else {})


def planned_files(name: str, synthetic: dict | None) -> list[str]:
    """Every file (relative to the session folder) a synthetic session will hold, ground truth excluded."""
    p = synth_params(synthetic)
    plan = plan_session(name, synthetic)
    files = ["session.yaml"]
    files += [f"calib/{cam}/{n}.png" for cam in plan["cameras"] for n in range(int(p["calib_poses"]))]
    for seq in plan["rom"]:
        first, last = seq["frames"]
        files += [f"rom/{seq['name']}/{cam}/{f:06d}.png" for f in range(first, last + 1) for cam in plan["cameras"]]
    files += [perf["file"] for perf in plan["performances"]]
    return files + planned_ground_truth(name, synthetic)


def planned_ground_truth(name: str, synthetic: dict | None) -> list[str]:
    """Ground-truth files (relative to the session folder) the generator writes; only rigbuild.eval reads them."""
    plan = plan_session(name, synthetic)
    files = ["ground_truth/cameras.json", "ground_truth/actor_rig.npz", "ground_truth/template_rig.npz",
             "ground_truth/dots.npz"]
    files += [f"ground_truth/rom/{seq['name']}.npz" for seq in plan["rom"]]
    files += [f"ground_truth/performances/{perf['name']}.npz" for perf in plan["performances"]]
    return files


def _write_png(path: Path, image: np.ndarray) -> None:
    import cv2

    from rigbuild.io.atomic import atomic_path

    with atomic_path(path, suffix=".png") as tmp:
        bgr = image[..., ::-1] if image.ndim == 3 else image
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(bgr), [cv2.IMWRITE_PNG_COMPRESSION, 1]):
            raise OSError(f"could not write {path}")


class _BackgroundWriter:
    """Finish (the sensor) and write each rendered image on one worker thread while the next one renders:
    ``submit(path, finish)`` with ``finish() -> (H, W, 3) uint8``; at most ``depth`` images wait; ``wait()``
    returns once all are written and re-raises the first error."""

    def __init__(self, depth: int = 2) -> None:
        from concurrent.futures import ThreadPoolExecutor

        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="png-writer")
        self._pending: list = []
        self._depth = depth

    def submit(self, path: Path, finish: Callable[[], np.ndarray]) -> None:
        while len(self._pending) >= self._depth:
            self._pending.pop(0).result()
        self._pending.append(self._pool.submit(lambda: _write_png(path, finish())))

    def __enter__(self) -> "_BackgroundWriter":
        return self

    def __exit__(self, *exc) -> None:
        try:
            if exc[0] is None:
                self.wait()
        finally:
            for f in self._pending:
                f.cancel()
            self._pool.shutdown(wait=True)

    def wait(self) -> None:
        while self._pending:
            self._pending[0].result()
            self._pending.pop(0)


def generate_session(out_dir: str | os.PathLike, name: str, synthetic: dict | None,
                     progress: Callable[[str], None] | None = None) -> dict:
    """Render a whole synthetic session into ``out_dir`` (replaced if it exists). Returns timings.

    Everything derives from ``synthetic["seed"]``: the same config gives byte-identical files.
    The folder is built under a temporary name and renamed at the end, so an interrupted run
    leaves no half-written session.
    """
    from rigbuild.io.atomic import write_json
    from rigbuild.session import session_from_dict, write_session
    from rigbuild.synth.capture import capture_setup

    say = progress or (lambda msg: None)
    p = synth_params(synthetic)
    plan = plan_session(name, synthetic)
    out_dir = Path(out_dir)
    tmp_dir = out_dir.with_name(f".{out_dir.name}.partial")
    if tmp_dir.exists():
        shutil.rmtree(tmp_dir)
    tmp_dir.mkdir(parents=True)
    spec = session_from_dict(plan, tmp_dir)
    gt = tmp_dir / "ground_truth"
    timings: dict[str, float] = {}
    t0 = time.perf_counter()

    actor, dots = _write_rigs(gt, spec, p)
    timings["rigs_s"] = time.perf_counter() - t0
    face_centre = actor.neutral[actor.face_vertices].mean(0)
    cameras = _write_cameras(gt, spec, p, name, face_centre)
    setup = capture_setup(p, actor, cameras, face_centre, spec.width)
    t1 = time.perf_counter()
    _render_calibration(tmp_dir, gt, spec, p, cameras, face_centre, setup, say)
    timings["calib_images_s"] = time.perf_counter() - t1
    t2 = time.perf_counter()
    n_images = _render_rom(gt, spec, p, actor, cameras, face_centre, dots, setup, say)
    timings["rom_images_s"] = time.perf_counter() - t2
    timings["rom_images"] = n_images
    _write_performances(tmp_dir, gt, spec, p, actor, face_centre, cameras)

    write_session(plan, tmp_dir)
    timings["total_s"] = time.perf_counter() - t0
    write_json(gt / "generation.json", {"timings": timings, "params": p})
    if out_dir.exists():
        shutil.rmtree(out_dir)
    os.replace(tmp_dir, out_dir)
    return timings


def generate_mocap_only(out_dir: str | os.PathLike, name: str, synthetic: dict | None) -> Path:
    """The session's rigs, cameras and performances without any image: ``ground_truth/`` (actor_rig.npz,
    template_rig.npz, cameras.json, dots.npz, performances/<name>.npz) and ``performances/<name>.c3d``, the
    same bytes :func:`generate_session` writes for them (the same seeds), for benchmarks of the marker-space
    stages. ``out_dir`` is replaced. Returns it."""
    from rigbuild.session import session_from_dict

    p = synth_params(synthetic)
    plan = plan_session(name, synthetic)
    out_dir = Path(out_dir)
    if out_dir.exists():
        shutil.rmtree(out_dir)
    (out_dir / "ground_truth" / "performances").mkdir(parents=True)
    (out_dir / "performances").mkdir(parents=True)
    spec = session_from_dict(plan, out_dir)
    gt = out_dir / "ground_truth"
    actor, _ = _write_rigs(gt, spec, p)
    face_centre = actor.neutral[actor.face_vertices].mean(0)
    cameras = _write_cameras(gt, spec, p, name, face_centre)
    _write_performances(out_dir, gt, spec, p, actor, face_centre, cameras)
    return out_dir


def generate_calibration_only(out_dir: str | os.PathLike, name: str, synthetic: dict | None) -> Path:
    """The session's calibration images without the ROM or the performances: ``calib/<cam>/<n>.png``,
    ``ground_truth/`` (rigs, cameras.json, board_poses.npz, board_visibility.json) and ``session.yaml``, the same
    bytes :func:`generate_session` writes for them (the same seeds), for benchmarks of the calibration stage.
    ``out_dir`` is replaced. Returns it."""
    from rigbuild.session import session_from_dict, write_session
    from rigbuild.synth.capture import capture_setup

    p = synth_params(synthetic)
    plan = plan_session(name, synthetic)
    out_dir = Path(out_dir)
    if out_dir.exists():
        shutil.rmtree(out_dir)
    out_dir.mkdir(parents=True)
    spec = session_from_dict(plan, out_dir)
    gt = out_dir / "ground_truth"
    actor, _ = _write_rigs(gt, spec, p)
    face_centre = actor.neutral[actor.face_vertices].mean(0)
    cameras = _write_cameras(gt, spec, p, name, face_centre)
    setup = capture_setup(p, actor, cameras, face_centre, spec.width)
    _render_calibration(out_dir, gt, spec, p, cameras, face_centre, setup, lambda msg: None)
    write_session(plan, out_dir)
    return out_dir


def _write_rigs(gt: Path, spec, p: dict):
    """Load the template, make the actor and write both rigs (and actor_info.json) under ``gt``.

    Returns the actor :class:`~rigbuild.rig.Rig` and the (D,) vertex ids of the painted dots: laid out on the
    template (the stencil) and painted at the same vertices of the actor.
    """
    from rigbuild.dots import painted_dot_vertices
    from rigbuild.io.atomic import write_json
    from rigbuild.io.rigs import load_rig, write_rig_npz
    from rigbuild.paths import ict_dir
    from rigbuild.synth.actor import make_actor_rig

    template = load_rig(p["template_rig"])
    if template.marker_vertices.size == 0:
        raise InputError(f"template rig '{p['template_rig']}' has no marker set", fix="add markers to the rig")
    dot_vertices = painted_dot_vertices(template, spec.dot_stencil_mm)
    identity_folder = ict_dir() if p["template_rig"] == "ict" else None
    a = p["actor"]
    novelty = None if a["expression_novelty"] is None else tuple(float(x) for x in a["expression_novelty"])
    actor, actor_info = make_actor_rig(template, seed=int(p["seed"]), identity_folder=identity_folder,
                                       intensity_range=tuple(a["intensity_range"]), asymmetry=a["asymmetry"],
                                       crosstalk=a["crosstalk"], warp=a["warp"], identity_sigma=a["identity_sigma"],
                                       expression_novelty=novelty)
    write_rig_npz(gt / "actor_rig.npz", actor)
    write_rig_npz(gt / "template_rig.npz", template)
    write_json(gt / "actor_info.json", actor_info)
    return actor, _paint_dots(gt, p, actor, dot_vertices, template.marker_vertices.size)


def _paint_dots(gt: Path, p: dict, actor, site_vertices: np.ndarray, n_markers: int):
    """The dots painted on the actor (:class:`rigbuild.synth.dots.PaintedDots`; none with ``dots: none``): by
    hand near each stencil site (the markers first, never missing); where they are goes to ``gt/dots.npz``."""
    from rigbuild.io.atomic import save_npz
    from rigbuild.synth.dots import no_dots, place_painted_dots

    if p["dots"] == "none":
        painted = no_dots()
    else:
        painted = place_painted_dots(actor, site_vertices, sigma_mm=float(p["dot_placement_sd_mm"]),
                                     missing_fraction=float(p["dot_missing_fraction"]),
                                     diameter_mm=tuple(float(x) for x in p["dot_diameter_mm"]),
                                     darkness=tuple(float(x) for x in p["dot_darkness"]), seed=int(p["seed"]) + 11,
                                     keep_first=int(n_markers))
    save_npz(gt / "dots.npz", triangles=painted.triangles, bary=painted.bary, radius_mm=painted.radius_mm,
             albedo=painted.albedo, site=painted.site, site_vertex=np.asarray(site_vertices)[painted.site]
             if len(painted) else np.zeros(0, np.int64), missing_sites=np.asarray(painted.missing_sites))
    return painted


def _write_cameras(gt: Path, spec, p: dict, name: str, face_centre: np.ndarray) -> list:
    """The synthetic camera rig aimed at ``face_centre`` (3,) mm, written to ``gt/cameras.json``."""
    from rigbuild.io.cameras import write_cameras
    from rigbuild.synth.rig_layout import make_camera_rig

    cameras = make_camera_rig(n_cameras=len(spec.cameras), width=spec.width, height=spec.height,
                              distance_mm=float(p["camera_distance_mm"]), arc_deg=tuple(p["camera_arc_deg"]),
                              rows=int(p["camera_rows"]), target=face_centre,
                              distortion_scale=float(p["distortion_scale"]), seed=int(p["seed"]),
                              k3_range=tuple(float(x) for x in p["distortion_k3"]))
    write_cameras(gt / "cameras.json", cameras, session=name)
    return cameras


def _render_calibration(tmp_dir: Path, gt: Path, spec, p: dict, cameras: list, face_centre: np.ndarray, setup,
                        say: Callable[[str], None]) -> None:
    """Render ``calib/<cam>/<n>.png`` for random board poses; write the poses and their visibility."""
    from rigbuild.io.atomic import save_npz, write_json
    from rigbuild.progress import progress as progress_bar
    from rigbuild.synth.capture import render_board_capture
    from rigbuild.synth.rig_layout import make_board_poses

    seed = int(p["seed"])
    poses, seen_by = make_board_poses(cameras, spec.board, n_poses=int(p["calib_poses"]), seed=seed + 1,
                                      center=face_centre)
    with _BackgroundWriter() as writer:
        for cam in progress_bar(cameras, "calibration images", unit="camera"):
            for n, (Rb, tb) in enumerate(poses):
                writer.submit(tmp_dir / "calib" / cam.id / f"{n}.png",
                              render_board_capture(cam, setup, spec.board, Rb, tb, seed=seed * 1000 + n))
            writer.wait()  # the camera's images are on disk when its progress line says so
    say(f"calibration images: {len(cameras)} cameras x {len(poses)} poses")
    save_npz(gt / "board_poses.npz", R=np.array([r for r, _ in poses]), t=np.array([t for _, t in poses]))
    write_json(gt / "board_visibility.json", {"seen_fully_by": seen_by})


def _rigid_about(face_centre: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """World translations (F, 3) of a rigid motion about the face centre: x' = R (x - c) + c + t = R x + t_world."""
    return face_centre[None] - np.einsum("fij,j->fi", R, face_centre) + t


def _render_rom(gt: Path, spec, p: dict, actor, cameras: list, face_centre: np.ndarray, dots, setup,
                say: Callable[[str], None]) -> int:
    """Render every ROM sequence (``rom/<seq>/<cam>/<frame>.png``) and write ``gt/rom/<seq>.npz``.

    dots : the painted :class:`~rigbuild.synth.dots.PaintedDots`; setup : the session's capture setup.
    Returns the number of images rendered.
    """
    from rigbuild.io.atomic import save_npz
    from rigbuild.progress import progress as progress_bar
    from rigbuild.synth.capture import exposure_motion, render_face
    from rigbuild.synth.dots import dot_centres
    from rigbuild.synth.motion import make_head_motion, make_rom_weights

    seed = int(p["seed"])
    rom_cfg = p["rom"]
    holds = None if rom_cfg["hold_frames"] is None else tuple(int(x) for x in rom_cfg["hold_frames"])
    seqs = make_rom_weights(actor.shape_names, int(rom_cfg["n_sequences"]), int(rom_cfg["frames_per_sequence"]),
                            seed=seed + 2, coverage=int(rom_cfg["coverage"]),
                            peak_range=tuple(float(x) for x in rom_cfg["peak_range"]), hold_frames=holds)
    n_images = 0
    with _BackgroundWriter() as writer:
        planned = [(s, seq, seqs[s]) for s, seq in zip(rendered_sequences(p), spec.rom)]
        for s, seq, Wseq in progress_bar(planned, "ROM images", unit="sequence"):
            R, t = make_head_motion(Wseq.shape[0], seed=seed + 100 + s,
                                    max_rotation_deg=float(rom_cfg["max_rotation_deg"]),
                                    max_translation_mm=float(rom_cfg["max_translation_mm"]),
                                    bound=rom_cfg["head_bound"],
                                    neutral_pose_deg=float(rom_cfg["neutral_pose_deg"]),
                                    neutral_pose_mm=float(rom_cfg["neutral_pose_mm"]))
            t_world = _rigid_about(face_centre, R, t)
            verts = actor.evaluate(Wseq)
            verts = np.einsum("fij,fvj->fvi", R, verts) + t_world[:, None, :]
            for i, frame in enumerate(seq.frames):
                centres = dot_centres(dots, verts[i]) if len(dots) else None
                motion = exposure_motion(verts, i, setup.shutter) if setup.linear else None
                for cam in cameras:
                    finish = render_face(cam, setup, verts[i], seed * 7919 + s * 1000 + i, motion, centres,
                                         dots.radius_mm, dots.albedo)
                    writer.submit(spec.rom_image(seq.name, cam.id, frame), finish)
                    n_images += 1
            writer.wait()
            save_npz(gt / "rom" / f"{seq.name}.npz", vertices=verts.astype(np.float32), weights=Wseq.astype(np.float32),
                     rotation=R.astype(np.float32), translation=t_world.astype(np.float32),
                     shape_names=np.asarray(actor.shape_names), frames=np.asarray(seq.frames))
            say(f"ROM {seq.name}: {len(seq.frames)} frames x {len(cameras)} cameras")
    return n_images


def _write_performances(tmp_dir: Path, gt: Path, spec, p: dict, actor, face_centre: np.ndarray, cameras: list) -> None:
    """Write each performance's recorded markers (``performances/<name>.c3d``: noise, gaps) and its ground truth.

    By default the markers sit at the actor's marker vertices; with ``marker_placement_sd_mm`` they are placed
    by hand along the skin, and with ``occlusion`` a marker is a gap where fewer than ``min_cameras`` cameras
    of the rig see it (:func:`rigbuild.synth.markers.performance_markers`).
    """
    from rigbuild.io.atomic import save_npz
    from rigbuild.io.markers import write_markers_c3d
    from rigbuild.synth.motion import make_head_motion, make_performance_weights, markers_from_rig

    seed = int(p["seed"])
    pc = p["performance"]
    fps = float(pc["fps"])
    n_frames = int(round(float(pc["duration_s"]) * fps))
    by_hand = float(pc["marker_placement_sd_mm"]) > 0 or bool(pc["occlusion"])
    for i, perf in enumerate(spec.performances):
        Wp = make_performance_weights(actor.shape_names, n_frames, fps, seed=seed + 500 + i)
        R, t = make_head_motion(n_frames, seed=seed + 600 + i, max_rotation_deg=4.0, max_translation_mm=6.0)
        t_world = _rigid_about(face_centre, R, t)
        if by_hand:
            clean, noisy = _hand_placed_markers(p, actor, Wp, R, t_world, cameras, seed + 800 + i)
        else:
            clean = markers_from_rig(actor, Wp, R, t_world)
            noisy = markers_from_rig(actor, Wp, R, t_world, noise_mm=float(pc["noise_mm"]),
                                     gap_fraction=float(pc["gap_fraction"]), seed=seed + 700 + i)
        write_markers_c3d(tmp_dir / perf.file, noisy, actor.marker_names, fps)
        save_npz(gt / "performances" / f"{perf.name}.npz", weights=Wp.astype(np.float32),
                 shape_names=np.asarray(actor.shape_names), markers=clean.astype(np.float32),
                 marker_vertices=actor.marker_vertices, marker_names=np.asarray(actor.marker_names),
                 rotation=R.astype(np.float32), translation=t_world.astype(np.float32), fps=np.float64(fps))


def _hand_placed_markers(p: dict, actor, W: np.ndarray, R: np.ndarray, t: np.ndarray, cameras: list, seed: int):
    """(clean, recorded) markers (F, M, 3) mm placed by hand on the actor's skin: recorded with noise, the
    occlusion gaps of the rig's cameras (``occlusion``) and random gaps (``gap_fraction``)."""
    from rigbuild.synth.dots import place_painted_dots
    from rigbuild.synth.markers import performance_markers

    pc = p["performance"]
    placement = place_painted_dots(actor, actor.marker_vertices, sigma_mm=float(pc["marker_placement_sd_mm"]),
                                   missing_fraction=0.0, seed=seed)
    clean = performance_markers(actor, W, R, t, placement, None, noise_mm=0.0, seed=seed)
    noisy = performance_markers(actor, W, R, t, placement, cameras if pc["occlusion"] else None,
                                noise_mm=float(pc["noise_mm"]), seed=seed + 1, min_cameras=int(pc["min_cameras"]))
    rng = np.random.default_rng(seed + 2)
    gaps = rng.random(noisy.shape[:2]) < float(pc["gap_fraction"])
    noisy[gaps] = np.nan
    return clean, noisy


def check_synthetic(synthetic: dict | None, where: str) -> dict:
    """The synthetic block with defaults, checked: bad realism keys fail at DAG start naming the key and the fix."""
    from rigbuild.synth.capture import check_capture_keys

    p = synth_params(synthetic)
    check_capture_keys(p, where)
    a, r, pc = p["actor"], p["rom"], p["performance"]
    for key, value in (("actor.identity_sigma", a["identity_sigma"]), ("rom.neutral_pose_deg", r["neutral_pose_deg"]),
                       ("rom.neutral_pose_mm", r["neutral_pose_mm"]),
                       ("performance.marker_placement_sd_mm", pc["marker_placement_sd_mm"])):
        if value is not None and float(value) < 0:
            raise InputError(f"field '{where}.{key}' is {value}: it cannot be negative", path="config",
                             fix=f"give {key.split('.')[-1]} >= 0")
    lo, hi = (float(x) for x in p["distortion_k3"])
    if not (np.isfinite(lo) and np.isfinite(hi) and lo <= hi):
        raise InputError(f"field '{where}.distortion_k3' is {p['distortion_k3']}", path="config",
                         fix="give [lo, hi] with lo <= hi (typical lenses: within [-0.2, 0.2])")
    if r["head_bound"] not in ("per_axis", "total"):
        raise InputError(f"field '{where}.rom.head_bound' is {r['head_bound']!r}", path="config",
                         fix="use per_axis or total")
    rendered_sequences(p, where)
    if r["hold_frames"] is not None:
        lo, hi = (int(x) for x in r["hold_frames"])
        if not 1 <= lo <= hi:
            raise InputError(f"field '{where}.rom.hold_frames' is {r['hold_frames']}", path="config",
                             fix="give [lo, hi] frames with 1 <= lo <= hi")
    return p

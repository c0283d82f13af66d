"""Synthetic capture generation speed: seconds per rendered image (clean speckle path at two resolutions; the
realistic capture: skin, studio lights with shadows, sensor with motion blur, defocus and JPEG) and the time to
generate the whole demo session. Goals: < 0.5 s per clean 1280x960 image (foundation issue), < 1 s per
realistic 1280x960 image with motion blur on 2 cores (issue 19), demo session < 2 minutes.

    .venv/bin/python benchmarks/bench_synth.py
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import print_table, write_result  # noqa: E402

from rigbuild.io.rigs import load_rig  # noqa: E402
from rigbuild.paths import PROJECT_ROOT, ict_dir  # noqa: E402
from rigbuild.render import render_mesh  # noqa: E402
from rigbuild.render.mesh import TexturedMesh, speckle_texture  # noqa: E402
from rigbuild.synth.rig_layout import make_camera_rig  # noqa: E402
from rigbuild.synth.session import generate_session  # noqa: E402


def time_renders(rig_spec: str, width: int, height: int, backend: str, n: int = 5) -> tuple[float, float]:
    """Median wall and CPU seconds of one session image (colour only, as the generator renders)."""
    rig = load_rig(rig_spec)
    cams = make_camera_rig(n_cameras=4, width=width, height=height, target=rig.neutral[rig.face_vertices].mean(0))
    mesh = TexturedMesh(rig.neutral, rig.faces, rig.uvs, rig.face_uvs, speckle_texture(2048 if width >= 1000 else 1024, 0))
    for cam in cams:  # warm-up: context, texture upload, framebuffers and ray tables of every camera
        render_mesh(cam, mesh, backend=backend, msaa=False, with_geometry=False)
    wall, cpu = [], []
    for i in range(n):
        t0, c0 = time.perf_counter(), time.process_time()
        render_mesh(cams[i % 4], mesh, noise_sigma=1.5, seed=i, backend=backend, msaa=False, with_geometry=False)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return float(np.median(wall)), float(np.median(cpu))


def time_realistic(rig_spec: str, width: int, height: int, n: int = 4) -> tuple[float, float]:
    """Median wall and CPU seconds of one realistic capture (rigbuild.synth.capture.capture_face): realistic skin,
    studio lights, the default sensor (f/8, vignetting, Bayer, noise) with JPEG 92 and motion blur from a 2 mm
    head movement over the exposure. The skin atlas is painted once before timing (once per session), and each
    camera renders once before timing (its distortion tables are computed once per camera and session)."""
    from rigbuild.synth.capture import capture_face, capture_setup
    from rigbuild.synth.session import synth_params

    rig = load_rig(rig_spec)
    centre = rig.neutral[rig.face_vertices].mean(0)
    cams = make_camera_rig(n_cameras=4, width=width, height=height, target=centre)
    p = synth_params({"appearance": "realistic", "lights": "studio", "camera": {"jpeg_quality": 92}})
    setup = capture_setup(p, rig, cams, centre, width)
    motion = np.tile([2.0, 0.5, 0.0], (rig.n_vertices, 1))
    for cam in cams:  # warm-up as in a session, where each camera renders every frame: its ray tables once
        capture_face(cam, setup, rig.neutral, 0, motion)
    wall, cpu = [], []
    for i in range(n):
        t0, c0 = time.perf_counter(), time.process_time()
        capture_face(cams[i % 4], setup, rig.neutral, i, motion)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return float(np.median(wall)), float(np.median(cpu))


def main() -> None:
    rows = []
    specs = ["procedural"] + (["ict"] if (ict_dir() / "generic_neutral_mesh.obj").exists() else [])
    for spec in specs:
        for (w, h) in [(640, 480), (1280, 960)]:
            for backend in ("gl", "embree"):
                wall, cpu = time_renders(spec, w, h, backend, n=5 if backend == "gl" else 2)
                rows.append({"rig": spec, "resolution": f"{w}x{h}", "backend": backend, "s_per_image": wall,
                             "cpu_s_per_image": cpu, "goal_s": 0.5 if w >= 1280 else None})
        for (w, h) in [(640, 480), (1280, 960)]:
            wall, cpu = time_realistic(spec, w, h)
            rows.append({"rig": spec, "resolution": f"{w}x{h}", "backend": "gl realistic", "s_per_image": wall,
                         "cpu_s_per_image": cpu, "goal_s": 1.0 if w >= 1280 else None})
    cfg = yaml.safe_load((PROJECT_ROOT / "config" / "config.yaml").read_text())
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        timings = generate_session(Path(tmp) / "demo", "demo", cfg["sessions"]["demo"]["synthetic"])
        demo_s = time.perf_counter() - t0
    print_table(rows, ["rig", "resolution", "backend", "s_per_image", "cpu_s_per_image", "goal_s"])
    print(f"\ndemo session generation: {demo_s:.1f} s (goal < 120 s); {timings}")
    write_result("synth", {"renders": rows, "demo_session_s": demo_s, "demo_session_goal_s": 120.0,
                           "demo_timings": timings})


if __name__ == "__main__":
    main()

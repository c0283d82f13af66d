"""A tiny synthetic session end to end: contract, determinism, ground truth consistent with the images."""

from __future__ import annotations

import hashlib
import json

import cv2
import numpy as np
import pytest

from rigbuild.io.cameras import read_cameras
from rigbuild.io.markers import read_markers
from rigbuild.io.rigs import read_rig_npz
from rigbuild.render import render_mesh
from rigbuild.render.mesh import TexturedMesh, speckle_texture
from rigbuild.session import read_session
from rigbuild.synth.session import generate_session, planned_files

TINY = {
    "template_rig": "procedural",
    "seed": 3,
    "n_cameras": 3,
    "image_size": [320, 240],
    "calib_poses": 6,
    # a coarse board: at 320x240 the default 24 mm squares are too small for ArUco decoding
    "board": {"type": "charuco", "squares_x": 5, "squares_y": 4, "square_size_mm": 40.0,
              "marker_size_mm": 30.0, "dictionary": "DICT_4X4_50"},
    "rom": {"n_sequences": 2, "frames_per_sequence": 5},
    "performance": {"n": 1, "duration_s": 2.0, "fps": 30.0, "noise_mm": 0.1, "gap_fraction": 0.02},
}


@pytest.fixture(scope="module")
def tiny_session(tmp_path_factory):
    root = tmp_path_factory.mktemp("synth")
    generate_session(root / "tiny", "tiny", TINY)
    return root / "tiny"


def _digest(folder):
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        if p.is_file() and p.name != "generation.json":  # generation.json holds timings
            h.update(str(p.relative_to(folder)).encode())
            h.update(p.read_bytes())
    return h.hexdigest()


def test_session_matches_contract_and_plan(tiny_session):
    spec = read_session(tiny_session)
    assert spec.cameras == ["cam00", "cam01", "cam02"] and (spec.width, spec.height) == (320, 240)
    assert [s.name for s in spec.rom] == ["rom00", "rom01"] and spec.rom[0].frames == [0, 1, 2, 3, 4]
    for rel in planned_files("tiny", TINY):
        assert (tiny_session / rel).is_file(), rel
    img = cv2.imread(str(spec.rom_image("rom00", "cam01", 2)))
    assert img.shape == (240, 320, 3)
    for name in ("cameras.json", "actor_rig.npz", "rom/rom00.npz", "performances/perf00.npz"):
        assert (tiny_session / "ground_truth" / name).is_file()


def test_same_seed_gives_identical_files(tiny_session, tmp_path):
    generate_session(tmp_path / "again", "tiny", TINY)
    assert _digest(tmp_path / "again") == _digest(tiny_session)


def test_ground_truth_projects_onto_rendered_surface(tiny_session):
    """Re-render a ROM frame from ground truth: the image is the stored one, and visible GT vertices
    project where the depth buffer holds their depth (reprojection error < 0.5 px)."""
    spec = read_session(tiny_session)
    cams = read_cameras(tiny_session / "ground_truth" / "cameras.json")
    actor = read_rig_npz(tiny_session / "ground_truth" / "actor_rig.npz")
    with np.load(tiny_session / "ground_truth" / "rom" / "rom01.npz") as z:
        verts = z["vertices"][2].astype(np.float64)
    cam = cams[1]
    mesh = TexturedMesh(verts, actor.faces, actor.uvs, actor.face_uvs, speckle_texture(1024, 3),
                        dot_centers=verts[actor.marker_vertices])
    res = render_mesh(cam, mesh, msaa=False)
    face = actor.face_vertices
    uv = cam.project(verts[face])
    z = cam.world_to_camera(verts[face])[:, 2]
    inside = (uv[:, 0] > 1) & (uv[:, 0] < cam.width - 2) & (uv[:, 1] > 1) & (uv[:, 1] < cam.height - 2)
    px = np.round(uv[inside]).astype(int)
    d = res.depth[px[:, 1], px[:, 0]]
    visible = np.isfinite(d) & (np.abs(d - z[inside]) < 2.0)
    assert visible.sum() > 0.3 * inside.sum()
    # depth gradient -> reprojection error of the depth disagreement
    gy, gx = np.gradient(np.nan_to_num(res.depth, nan=0.0))
    slope = np.hypot(gx, gy)[px[:, 1], px[:, 0]][visible]
    # sub-pixel: the vertex sits at uv, the buffer sample at the rounded pixel; allow that offset
    offset = np.linalg.norm(uv[inside][visible] - px[visible], axis=1)
    err_px = np.abs(d[visible] - z[inside][visible]) / np.maximum(slope, 1e-3) - offset
    assert np.median(err_px) < 0.5
    stored = cv2.imread(str(spec.rom_image("rom01", cam.id, 2)))[..., ::-1]
    # the stored image adds sensor noise; without noise the render must match it closely
    assert np.abs(stored.astype(int) - res.color.astype(int)).mean() < 4.0


def test_charuco_detected_where_board_is_visible(tiny_session):
    spec = read_session(tiny_session)
    seen = json.loads((tiny_session / "ground_truth" / "board_visibility.json").read_text())["seen_fully_by"]
    detector = cv2.aruco.CharucoDetector(spec.board.opencv_board())
    n_corners = spec.board.corner_points()[0].shape[0]
    checked = 0
    for n, cams in enumerate(seen):
        for cam in cams:
            img = cv2.imread(str(tiny_session / "calib" / cam / f"{n}.png"), cv2.IMREAD_GRAYSCALE)
            corners, ids, _, _ = detector.detectBoard(img)
            assert ids is not None and len(ids) >= 0.75 * n_corners, (cam, n)
            checked += 1
    assert checked >= 2 * len(seen)


def test_performance_c3d_matches_ground_truth(tiny_session):
    take = read_markers(tiny_session / "performances" / "perf00.c3d")
    with np.load(tiny_session / "ground_truth" / "performances" / "perf00.npz") as z:
        clean = z["markers"].astype(np.float64)
        names = [str(s) for s in z["marker_names"]]
    assert take.names == names and take.fps == 30.0 and take.markers.shape == clean.shape
    gaps = np.isnan(take.markers[..., 0])
    assert 0.01 < gaps.mean() < 0.1
    err = np.abs(take.markers - clean)[~gaps]
    assert err.max() < 0.1 * 6 and 0.05 < err.std() < 0.15  # the configured 0.1 mm sensor noise


def test_dot_stencil_spacing_reaches_session_yaml(tmp_path):
    """synthetic dot_stencil_mm -> session.yaml dot_stencil_mm -> SessionSpec; absent: markers only; a
    non-positive spacing is refused naming the field."""
    from rigbuild.errors import InputError
    from rigbuild.session import session_from_dict
    from rigbuild.synth.session import plan_session

    plan = plan_session("tiny", {**TINY, "dot_stencil_mm": 16})
    assert plan["dot_stencil_mm"] == 16.0
    assert session_from_dict(plan, tmp_path).dot_stencil_mm == 16.0
    plain = plan_session("tiny", TINY)
    assert "dot_stencil_mm" not in plain and session_from_dict(plain, tmp_path).dot_stencil_mm is None
    with pytest.raises(InputError, match="dot_stencil_mm"):
        session_from_dict({**plan, "dot_stencil_mm": -2}, tmp_path)


def test_render_sequences_renders_those_sequences_as_the_full_session_has_them(tiny_session, tmp_path):
    """``rom.render_sequences: [1]`` holds rom01 only, with the images and ground truth the full session has for it
    (the shapes are still planned over both sequences); a bad index fails naming the key."""
    from rigbuild.errors import InputError
    from rigbuild.synth.session import check_synthetic

    only = {**TINY, "rom": {**TINY["rom"], "render_sequences": [1]}}
    generate_session(tmp_path / "one", "tiny", only)
    spec = read_session(tmp_path / "one")
    assert [s.name for s in spec.rom] == ["rom01"]
    assert not (tmp_path / "one" / "rom" / "rom00").exists()
    for cam in spec.cameras:
        for f in spec.rom[0].frames:
            a = (tmp_path / "one" / "rom" / "rom01" / cam / f"{f:06d}.png").read_bytes()
            assert a == (tiny_session / "rom" / "rom01" / cam / f"{f:06d}.png").read_bytes()
    with np.load(tmp_path / "one" / "ground_truth" / "rom" / "rom01.npz") as z1, \
            np.load(tiny_session / "ground_truth" / "rom" / "rom01.npz") as z2:
        np.testing.assert_array_equal(z1["weights"], z2["weights"])
        np.testing.assert_array_equal(z1["vertices"], z2["vertices"])
    with pytest.raises(InputError, match="render_sequences"):
        check_synthetic({**TINY, "rom": {**TINY["rom"], "render_sequences": [2]}}, "sessions.s.synthetic")

"""Rig loading checks each shape OBJ's topology against the neutral's: vertex count and face list."""

from __future__ import annotations

import numpy as np
import pytest

from rigbuild.errors import InputError
from rigbuild.io.obj import write_obj
from rigbuild.io.rigs import load_rig, read_obj_folder_rig, write_obj_folder_rig
from rigbuild.rig import Rig

from grid_mesh import grid_mesh


def _rig() -> Rig:
    verts, faces = grid_mesh(6, 50.0)
    d = np.zeros((2,) + verts.shape)
    d[0, :, 2] = 2.0 * np.exp(-((verts[:, 0] - verts[:, 0].mean()) ** 2) / 100.0)
    d[1, :, 1] = -3.0 * (verts[:, 1] < verts[:, 1].mean())
    return Rig(verts, d, ["jawOpen", "smile"], faces, name="grid")


def test_same_topology_loads(tmp_path):
    rig = _rig()
    write_obj_folder_rig(rig, tmp_path / "rig")
    back = load_rig(tmp_path / "rig")
    np.testing.assert_allclose(back.deltas, rig.deltas, atol=1e-5)
    np.testing.assert_array_equal(back.faces, rig.faces)


def test_reordered_shape_is_an_input_error_naming_the_file(tmp_path):
    """A jawOpen exported with another vertex order: same vertex count, faces renumbered to match; the rig
    reader used to take it and subtract the neutral vertex by vertex (displacements of the mesh's size)."""
    rig = _rig()
    folder = tmp_path / "rig"
    write_obj_folder_rig(rig, folder)
    perm = np.random.default_rng(0).permutation(rig.n_vertices)
    inv = np.argsort(perm)
    shape = (rig.neutral + rig.deltas[0])[perm]
    write_obj(folder / "jawOpen.obj", shape, inv[rig.faces])
    with pytest.raises(InputError) as e:
        read_obj_folder_rig(folder)
    msg = str(e.value)
    assert "jawOpen.obj" in msg and "face list differs" in msg and "another order" in msg


def test_shape_without_faces_is_an_input_error(tmp_path):
    rig = _rig()
    folder = tmp_path / "rig"
    write_obj_folder_rig(rig, folder)
    (folder / "smile.obj").write_text("".join(f"v {x} {y} {z}\n" for x, y, z in rig.neutral + rig.deltas[1]))
    with pytest.raises(InputError, match="smile.obj"):
        read_obj_folder_rig(folder)


def test_same_faces_written_differently_load(tmp_path):
    """Face lines that differ only in formatting (``f 1/1/1 ...`` against ``f 1 ...``) are the same faces."""
    rig = _rig()
    folder = tmp_path / "rig"
    write_obj_folder_rig(rig, folder)
    v = rig.neutral + rig.deltas[1]
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in v]
    lines += [f"f {a + 1}/{a + 1}/{a + 1} {b + 1}/{b + 1}/{b + 1} {c + 1}/{c + 1}/{c + 1}\n" for a, b, c in rig.faces]
    (folder / "smile.obj").write_text("".join(lines))
    np.testing.assert_allclose(read_obj_folder_rig(folder).deltas[1], rig.deltas[1], atol=1e-5)


def test_ict_shapes_pass_the_face_check(ict_folder):
    from rigbuild.io.rigs import read_ict_rig

    rig = read_ict_rig(ict_folder, expressions=["jawOpen", "mouthSmile_L"])
    assert rig.n_shapes == 2 and np.abs(rig.deltas).max() > 1.0

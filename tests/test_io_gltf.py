"""glTF 2.0 rig export: checked by parsing the file with json/base64/struct here (independently of
the writer's reader) and by the round trip through read_gltf_rig."""

from __future__ import annotations

import base64
import json
import struct
import warnings

import numpy as np
import pytest

from rigbuild.io.gltf import read_gltf_rig, write_gltf_rig
from rigbuild.rig import Rig


def small_rig(with_uvs: bool) -> Rig:
    verts = np.array([[0, 0, 0], [10, 0, 0], [10, 10, 0], [0, 10, 0], [5, 5, 3.0]])
    faces = np.array([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
    deltas = np.zeros((2, 5, 3))
    deltas[0, 4] = [0, 0, 2.5]
    deltas[1, 1] = [1.0, -0.5, 0]
    kw = {}
    if with_uvs:
        kw = dict(uvs=np.array([[0, 0], [1, 0], [1, 1], [0, 1], [0.5, 0.5], [0.9, 0.1]]),
                  face_uvs=np.array([[0, 1, 4], [5, 2, 4], [2, 3, 4], [3, 0, 4]]))  # vertex 1 has two UVs
    return Rig(verts, deltas, ["jawOpen", "mouthLeft"], faces, name="tiny", **kw)


def _parse_gltf(path):
    doc = json.loads(path.read_text())
    buf = base64.b64decode(doc["buffers"][0]["uri"].split(",", 1)[1])
    assert len(buf) == doc["buffers"][0]["byteLength"]

    def acc(i):
        a = doc["accessors"][i]
        v = doc["bufferViews"][a["bufferView"]]
        n = {"SCALAR": 1, "VEC2": 2, "VEC3": 3}[a["type"]]
        dt = {5126: "<f4", 5125: "<u4"}[a["componentType"]]
        return np.frombuffer(buf, dtype=dt, count=a["count"] * n, offset=v["byteOffset"]).reshape(-1, n)

    return doc, acc


def test_gltf_structure_and_morph_targets(tmp_path):
    rig = small_rig(with_uvs=False)
    p = tmp_path / "rig.gltf"
    write_gltf_rig(p, rig)
    doc, acc = _parse_gltf(p)
    assert doc["asset"]["version"] == "2.0"
    assert doc["asset"]["extras"]["units"] == "m" and doc["asset"]["extras"]["source_units"] == "mm"
    mesh = doc["meshes"][0]
    assert mesh["extras"]["targetNames"] == ["jawOpen", "mouthLeft"]
    assert mesh["weights"] == [0.0, 0.0]
    prim = mesh["primitives"][0]
    pos = acc(prim["attributes"]["POSITION"])
    np.testing.assert_allclose(pos, rig.neutral / 1000.0, atol=1e-7)
    a = doc["accessors"][prim["attributes"]["POSITION"]]
    np.testing.assert_allclose(a["min"], pos.min(0), atol=1e-7)
    np.testing.assert_allclose(a["max"], pos.max(0), atol=1e-7)
    np.testing.assert_array_equal(acc(prim["indices"]).reshape(-1, 3), rig.faces)
    t0 = acc(prim["targets"][0]["POSITION"])
    np.testing.assert_allclose(t0[4], [0, 0, 0.0025], atol=1e-9)
    assert np.count_nonzero(t0) == 1
    for view in doc["bufferViews"]:
        assert view["byteOffset"] % 4 == 0


@pytest.mark.parametrize("suffix", [".gltf", ".glb"])
@pytest.mark.parametrize("with_uvs", [False, True])
def test_gltf_round_trip(tmp_path, suffix, with_uvs):
    rig = small_rig(with_uvs)
    p = tmp_path / f"rig{suffix}"
    write_gltf_rig(p, rig)
    if suffix == ".glb":
        raw = p.read_bytes()
        magic, version, length = struct.unpack_from("<III", raw, 0)
        assert (magic, version, length) == (0x46546C67, 2, len(raw))
    back = read_gltf_rig(p)
    assert back.shape_names == rig.shape_names
    np.testing.assert_allclose(back.neutral, rig.neutral, atol=1e-4)
    np.testing.assert_allclose(back.deltas, rig.deltas, atol=1e-4)
    # same triangles (up to the UV split the faces map back to the source vertices)
    np.testing.assert_array_equal(back.faces, rig.faces)


def test_gltf_uv_split_duplicates_the_shared_vertex(tmp_path):
    rig = small_rig(with_uvs=True)
    p = tmp_path / "rig.gltf"
    write_gltf_rig(p, rig)
    doc, acc = _parse_gltf(p)
    prim = doc["meshes"][0]["primitives"][0]
    assert acc(prim["attributes"]["POSITION"]).shape[0] == 6  # vertex 1 split in two
    src = doc["meshes"][0]["extras"]["sourceVertex"]
    assert sorted(src) == [0, 1, 1, 2, 3, 4]
    uv = acc(prim["attributes"]["TEXCOORD_0"])
    np.testing.assert_allclose(sorted(uv[:, 1]), sorted(1 - np.array([0, 0, 1, 1, 0.5, 0.1])), atol=1e-7)


# ------------------------------------------------------------------ independent reader: pygltflib only
import pygltflib  # noqa: E402  (pinned in pyproject, 1.16.5; the checks below use it alone)
from pygltflib.validator import validate as pygltflib_validate  # noqa: E402

from rigbuild.io.gltf_anim import write_gltf_animation  # noqa: E402

_AXES = "right-handed, +y up, +z towards the face's front (glTF convention)"


def random_rig(n_vertices: int = 120, n_shapes: int = 5, seed: int = 0) -> Rig:
    """A random triangle soup rig in mm with local (sparse) shapes: each moves a random third of the vertices."""
    rng = np.random.default_rng(seed)
    verts = rng.normal(size=(n_vertices, 3)) * 40.0 + [0.0, 20.0, 90.0]
    faces = np.stack([rng.permutation(n_vertices)[:3] for _ in range(2 * n_vertices)])
    deltas = rng.normal(size=(n_shapes, n_vertices, 3)) * 3.0
    deltas *= (rng.uniform(size=(n_shapes, n_vertices, 1)) < 0.33)
    return Rig(verts, deltas, [f"shape_{k}" for k in range(n_shapes)], faces, name="random")


def _pyg_load(path):
    """Load with pygltflib and return (gltf, its binary buffer) - .glb chunk or the embedded data URI."""
    g = pygltflib.GLTF2().load(str(path))
    assert len(g.buffers) == 1
    blob = g.binary_blob()
    if blob is None:
        assert g.buffers[0].uri.startswith("data:")
        blob = g.get_data_from_buffer_uri(g.buffers[0].uri)
    assert len(blob) >= g.buffers[0].byteLength
    with warnings.catch_warnings():  # pygltflib marks its validator 'provisional'
        warnings.simplefilter("ignore", UserWarning)
        pygltflib_validate(g)  # pygltflib's own checks (accessors, buffer views, meshes, animations); raises
    return g, blob


_DTYPES = {pygltflib.FLOAT: "<f4", pygltflib.UNSIGNED_INT: "<u4", pygltflib.UNSIGNED_SHORT: "<u2"}
_NCOMP = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}


def _pyg_accessor(g, blob, index: int) -> np.ndarray:
    """Decode accessor ``index`` through pygltflib's accessor / bufferView objects (dense and sparse)."""
    a = g.accessors[index]
    n = _NCOMP[a.type]
    dt = np.dtype(_DTYPES[a.componentType])
    if a.bufferView is None:
        out = np.zeros((a.count, n), dt)
    else:
        v = g.bufferViews[a.bufferView]
        assert v.byteStride in (None, 0, dt.itemsize * n)  # tightly packed
        start = (v.byteOffset or 0) + (a.byteOffset or 0)
        assert start + a.count * n * dt.itemsize <= (v.byteOffset or 0) + v.byteLength
        out = np.frombuffer(blob, dt, count=a.count * n, offset=start).reshape(a.count, n).copy()
    if a.sparse is not None:
        iv, vv = g.bufferViews[a.sparse.indices.bufferView], g.bufferViews[a.sparse.values.bufferView]
        idx = np.frombuffer(blob, _DTYPES[a.sparse.indices.componentType], count=a.sparse.count,
                            offset=(iv.byteOffset or 0) + (a.sparse.indices.byteOffset or 0))
        val = np.frombuffer(blob, dt, count=a.sparse.count * n,
                            offset=(vv.byteOffset or 0) + (a.sparse.values.byteOffset or 0)).reshape(-1, n)
        out[idx] = val
    return out


def _check_minmax(acc, data: np.ndarray) -> None:
    np.testing.assert_array_equal(np.asarray(acc.min, np.float32), data.min(0))
    np.testing.assert_array_equal(np.asarray(acc.max, np.float32), data.max(0))


@pytest.mark.parametrize("suffix", [".gltf", ".glb"])
@pytest.mark.parametrize("make", ["small", "small_uv", "random"])
def test_rig_loaded_by_pygltflib(tmp_path, suffix, make):
    rig = {"small": lambda: small_rig(False), "small_uv": lambda: small_rig(True), "random": random_rig}[make]()
    p = tmp_path / f"rig{suffix}"
    write_gltf_rig(p, rig)
    g, blob = _pyg_load(p)
    assert g.asset.version == "2.0"
    ex = g.asset.extras
    assert (ex["units"], ex["source_units"], ex["scale"], ex["axes"]) == ("m", "mm", 0.001, _AXES)
    assert len(g.meshes) == 1 and len(g.meshes[0].primitives) == 1
    mesh, prim = g.meshes[0], g.meshes[0].primitives[0]
    assert g.nodes[g.scenes[g.scene].nodes[0]].mesh == 0
    assert prim.mode == pygltflib.TRIANGLES
    # one morph target per shape, named in mesh.extras.targetNames, default weights 0
    assert len(prim.targets) == rig.n_shapes
    assert mesh.extras["targetNames"] == list(rig.shape_names)
    assert mesh.weights == [0.0] * rig.n_shapes
    # glTF vertex -> rig vertex (identity unless UV seams split vertices)
    src = np.asarray(mesh.extras.get("sourceVertex", np.arange(rig.n_vertices)))
    n_gl = src.size
    assert (n_gl > rig.n_vertices) == (make == "small_uv")
    a_pos = g.accessors[prim.attributes.POSITION]
    assert a_pos.count == n_gl and a_pos.type == "VEC3" and a_pos.componentType == pygltflib.FLOAT
    pos = _pyg_accessor(g, blob, prim.attributes.POSITION)
    expect = (rig.neutral[src] * 1e-3).astype(np.float32)
    np.testing.assert_array_equal(pos, expect)  # float32 written, float32 read: bit exact
    np.testing.assert_allclose(pos.astype(np.float64) * 1e3, rig.neutral[src], rtol=1e-6, atol=1e-4)
    _check_minmax(a_pos, pos)
    tris = _pyg_accessor(g, blob, prim.indices).reshape(-1, 3)
    assert g.accessors[prim.indices].count == rig.faces.size
    np.testing.assert_array_equal(src[tris], rig.faces)
    for k, tgt in enumerate(prim.targets):
        a = g.accessors[tgt["POSITION"]]
        assert a.count == n_gl and a.type == "VEC3"
        d = _pyg_accessor(g, blob, tgt["POSITION"])
        np.testing.assert_array_equal(d, (rig.deltas[k][src] * 1e-3).astype(np.float32))
        np.testing.assert_allclose(d.astype(np.float64) * 1e3, rig.deltas[k][src], rtol=1e-6, atol=1e-4)
        _check_minmax(a, d)
    if make == "small_uv":
        uv = _pyg_accessor(g, blob, prim.attributes.TEXCOORD_0)
        assert uv.shape == (n_gl, 2) and np.all((uv >= 0) & (uv <= 1))


@pytest.mark.parametrize("make", ["small", "random"])
def test_weight_animation_loaded_by_pygltflib(tmp_path, make):
    rig = small_rig(False) if make == "small" else random_rig(seed=1)
    rng = np.random.default_rng(7)
    F, fps = 17, 24.0
    W = rng.uniform(0, 1, size=(F, rig.n_shapes))
    p = tmp_path / "anim.gltf"
    write_gltf_animation(p, rig, W, fps)
    g, blob = _pyg_load(p)
    ex = g.asset.extras
    assert (ex["units"], ex["source_units"], ex["scale"], ex["axes"]) == ("m", "mm", 0.001, _AXES)
    assert ex["fps"] == fps and ex["n_frames"] == F
    mesh, prim = g.meshes[0], g.meshes[0].primitives[0]
    assert mesh.extras["targetNames"] == list(rig.shape_names)
    assert len(prim.targets) == rig.n_shapes and mesh.weights == [0.0] * rig.n_shapes
    pos = _pyg_accessor(g, blob, prim.attributes.POSITION)
    assert g.accessors[prim.attributes.POSITION].count == rig.n_vertices
    np.testing.assert_array_equal(pos, (rig.neutral * 1e-3).astype(np.float32))
    _check_minmax(g.accessors[prim.attributes.POSITION], pos)
    np.testing.assert_array_equal(_pyg_accessor(g, blob, prim.indices).reshape(-1, 3), rig.faces)
    n_sparse = 0
    for k, tgt in enumerate(prim.targets):
        a = g.accessors[tgt["POSITION"]]
        assert a.count == rig.n_vertices
        n_sparse += a.sparse is not None and a.sparse.count < rig.n_vertices
        d = _pyg_accessor(g, blob, tgt["POSITION"])
        np.testing.assert_array_equal(d, (rig.deltas[k] * 1e-3).astype(np.float32))
        _check_minmax(a, d)
    assert n_sparse == rig.n_shapes  # every shape moves only some vertices: all targets are sparse
    # the animation: one channel driving the mesh node's morph weights
    assert len(g.animations) == 1
    anim = g.animations[0]
    assert len(anim.channels) == 1
    ch = anim.channels[0]
    assert ch.target.path == "weights" and g.nodes[ch.target.node].mesh == 0
    smp = anim.samplers[ch.sampler]
    assert smp.interpolation == "LINEAR"
    t = _pyg_accessor(g, blob, smp.input)[:, 0]
    np.testing.assert_array_equal(t, (np.arange(F) / fps).astype(np.float32))
    assert g.accessors[smp.input].min == [0.0] and g.accessors[smp.input].max[0] == pytest.approx((F - 1) / fps)
    a_out = g.accessors[smp.output]
    assert a_out.count == F * rig.n_shapes
    w = _pyg_accessor(g, blob, smp.output).reshape(F, rig.n_shapes)
    np.testing.assert_array_equal(w, W.astype(np.float32))


def test_gltf_animation_head_motion_channels(tmp_path):
    """Head motion about a pivot: the node's rotation/translation channels reproduce R (x - c) + c + d."""
    from scipy.spatial.transform import Rotation

    from rigbuild.io.gltf_anim import read_gltf_animation_weights

    rig = random_rig(n_vertices=30, n_shapes=3)
    F = 4
    W = np.linspace(0, 1, F * rig.n_shapes).reshape(F, rig.n_shapes)
    R = Rotation.from_euler("y", np.linspace(0, 20, F)[:, None], degrees=True).as_matrix()
    d = np.stack([np.linspace(0, 5, F), np.zeros(F), np.ones(F)], 1)  # mm
    c = np.array([1.0, 2.0, 3.0])
    p = tmp_path / "head.gltf"
    write_gltf_animation(p, rig, W, 30.0, head_rotation=R, head_translation=d, pivot=c)
    g, blob = _pyg_load(p)
    anim = g.animations[0]
    paths = {ch.target.path: ch.sampler for ch in anim.channels}
    assert set(paths) == {"weights", "rotation", "translation"}
    q = _pyg_accessor(g, blob, anim.samplers[paths["rotation"]].output).astype(float)
    t = _pyg_accessor(g, blob, anim.samplers[paths["translation"]].output).astype(float)
    x = np.array([10.0, -4.0, 7.0])  # a point in mm
    for f in range(F):
        moved = Rotation.from_quat(q[f]).as_matrix() @ (x * 1e-3) + t[f]
        np.testing.assert_allclose(moved, (R[f] @ (x - c) + c + d[f]) * 1e-3, atol=1e-6)
    _, W_back, _ = read_gltf_animation_weights(p)
    np.testing.assert_allclose(W_back, W, atol=1e-6)

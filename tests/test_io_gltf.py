"""glTF 2.0 rig export: checked by parsing the file with json/base64/struct here (independently of
the writer's reader) and by the round trip through read_gltf_rig."""

from __future__ import annotations

import base64
import json
import struct

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

"""The personalized rig's files are in the template's head frame (+y up, +z towards the viewer, metres in glTF,
origin at the head's centre) whatever the capture frame; the capture-to-head transform is saved beside them.
The glTF is read with pygltflib, an independent reader, as a studio's importer would."""

from __future__ import annotations

import json

import numpy as np
import pygltflib
import pytest

from rigbuild.camera import look_at
from rigbuild.io.rigs import load_rig, read_obj_folder_rig, read_rig_npz
from rigbuild.personalize.export import export_rigs
from rigbuild.personalize.params import ExportParams, from_config


@pytest.fixture(scope="module")
def template():
    return load_rig("procedural")


def _capture_frame(rig, seed: int = 0):
    """``rig`` as a calibrated rig sees it: in the first camera's OpenCV frame (y down, z away from the camera,
    the face 450 mm in front of it, looking back at the camera), slightly bigger (an actor, not the template)."""
    Rc, tc = look_at(np.array([60.0, 30.0, 450.0]), np.zeros(3))
    actor = rig.copy()
    actor.neutral = rig.neutral * 1.05
    actor.deltas = rig.deltas * 1.05
    return actor.transformed(Rc, tc), (Rc, tc)


def _gltf_positions(path):
    g = pygltflib.GLTF2().load(str(path))
    g.convert_buffers(pygltflib.BufferFormat.BINARYBLOB)  # the data URI -> bytes
    blob = g.binary_blob()
    prim = g.meshes[0].primitives[0]

    def accessor(i):
        acc = g.accessors[i]
        view = g.bufferViews[acc.bufferView]
        start = (view.byteOffset or 0) + (acc.byteOffset or 0)
        return np.frombuffer(blob, np.float32, acc.count * 3, start).reshape(acc.count, 3).astype(np.float64)

    names = g.meshes[0].extras["targetNames"]
    # glTF vertices are split where a position has several UVs; sourceVertex maps them back to the rig's
    src = np.asarray(g.meshes[0].extras["sourceVertex"])
    first = np.zeros(src.max() + 1, dtype=np.int64)
    first[src[::-1]] = np.arange(src.size)[::-1]
    targets = {n: accessor(t["POSITION"] if isinstance(t, dict) else t.POSITION)[first]
               for n, t in zip(names, prim.targets)}
    return g, accessor(prim.attributes.POSITION)[first], targets


def test_gltf_is_up_forward_and_metres(template, tmp_path):
    rig, _ = _capture_frame(template)
    export_rigs(tmp_path, rig, rig, template)
    g, pos, targets = _gltf_positions(tmp_path / "rig.gltf")
    mk = {n: pos[v] for n, v in zip(template.marker_names, template.marker_vertices)}
    brows = np.mean([mk["browInner_L"], mk["browInner_R"]], axis=0)
    nose = mk["noseTip_C"]
    assert brows[1] - nose[1] > 0.04  # up: the brows 50 mm above the nose tip (+y)
    assert nose[2] - brows[2] > 0.01  # forward: the nose tip in front of the brows (+z, towards the viewer)
    assert mk["browOuter_L"][0] > mk["browOuter_R"][0]  # the actor's left at +x
    width = np.linalg.norm(mk["browOuter_L"] - mk["browOuter_R"])
    assert width == pytest.approx(1.05 * 0.087, rel=0.02)  # metres: 87 mm between the template's brows, x 1.05
    assert np.abs(pos.mean(0) - template.neutral.mean(0) / 1000 * 1.05).max() < 0.01  # origin: the head's centre
    jaw = targets["jawOpen"][template.marker_vertices[template.marker_names.index("chin_C")]]
    assert jaw[1] < -0.005  # jawOpen moves the chin down, in metres
    assert g.asset.extras["frame"].startswith("template head frame")


def test_transform_is_saved_and_maps_capture_to_head(template, tmp_path):
    rig, (Rc, tc) = _capture_frame(template)
    rec = export_rigs(tmp_path, rig, rig, template)
    saved = json.loads((tmp_path / "head_frame.json").read_text())
    M = np.asarray(saved["capture_to_head"])
    assert saved["capture_frame_files"] == ["weights.npz", "fit.npz"] and rec["fit"]["rms_mm"] < 10
    np.testing.assert_allclose(M[:3, :3], Rc.T, atol=1e-9)  # undoes the camera's rotation, no scale
    head = read_rig_npz(tmp_path / "rig.npz")
    np.testing.assert_allclose(head.neutral, rig.neutral @ M[:3, :3].T + M[:3, 3], atol=1e-3)
    with np.load(tmp_path / "rig.npz") as z:
        np.testing.assert_allclose(z["capture_to_head"], M)
    obj = read_obj_folder_rig(tmp_path / "rig_obj")
    np.testing.assert_allclose(obj.neutral, head.neutral, atol=1e-4)
    meta = json.loads((tmp_path / "rig_obj" / "rig.json").read_text())
    assert "+y up" in meta["axes"] and meta["frame"].startswith("template head frame")
    np.testing.assert_allclose(read_rig_npz(tmp_path / "initial_rig.npz").neutral, head.neutral, atol=1e-3)


def test_arkit_names(template, tmp_path):
    rig, _ = _capture_frame(template)
    rec = export_rigs(tmp_path, rig, rig, template, from_config({"export": {"names": "arkit"}}).export)
    g, pos, targets = _gltf_positions(tmp_path / "rig.gltf")
    names = list(targets)
    assert "eyeBlinkLeft" in names and "browInnerUp" in names and "jawOpen" in names
    assert not any(n.endswith(("_L", "_R")) for n in names)
    plain = tmp_path / "template_names"
    plain.mkdir()
    export_rigs(plain, rig, rig, template, ExportParams())
    halves = _gltf_positions(plain / "rig.gltf")[2]
    np.testing.assert_allclose(targets["browInnerUp"], halves["browInnerUp_L"] + halves["browInnerUp_R"], atol=2e-6)
    np.testing.assert_allclose(targets["eyeBlinkLeft"], halves["eyeBlink_L"])
    meta = json.loads((tmp_path / "rig_obj" / "rig.json").read_text())
    assert "tongueOut" in meta["arkit_missing"] and meta["names"] == "arkit"
    assert meta["no_arkit_counterpart"] == [] and meta["arkit_sources"]["eyeBlinkLeft"] == ["eyeBlink_L"]
    assert g.asset.extras["arkit_missing"] == rec["naming"]["arkit_missing"]
    assert (tmp_path / "rig_obj" / "mouthSmileLeft.obj").is_file()


def test_arkit_keeps_shapes_it_cannot_name_and_validates():
    from rigbuild.errors import InputError
    from rigbuild.io.arkit import arkit_rig, arkit_map
    from rigbuild.rig import Rig

    order, sources = arkit_map()
    assert len(order) == 52 and len(set(order)) == 52
    assert sum(1 for a in order if sources.get(a) == (a,)) == 13  # the names ICT spells as ARKit does
    v = np.random.default_rng(0).normal(size=(5, 3))
    rig = Rig(v, np.ones((3, 5, 3)), ["jawOpen", "tongueUp", "browInnerUp_L"], np.array([[0, 1, 2]]))
    out, info = arkit_rig(rig)
    assert out.shape_names == ["jawOpen", "tongueUp", "browInnerUp_L"]
    assert info["no_arkit_counterpart"] == ["tongueUp", "browInnerUp_L"] and "browInnerUp" in info["arkit_missing"]
    with pytest.raises(InputError, match="export.names"):
        from_config({"export": {"names": "ARKit52"}})
    with pytest.raises(InputError, match="did you mean 'names'"):
        from_config({"export": {"name": "arkit"}})

"""glTF 2.0 export of a blendshape rig: one mesh, the neutral as POSITION, one morph target per shape.

- ``.gltf``: JSON with the binary buffer embedded as a base64 data URI; ``.glb``: the binary container.
- Morph target names in ``mesh.extras.targetNames`` (the de-facto convention read by three.js,
  Blender and Babylon); default weights 0.
- glTF positions are metres with +Y up and +Z forward; the rig (mm, +y up, +z towards the face's
  front) is scaled by ``scale`` (default 0.001, mm -> m); ``asset.extras`` records ``units``,
  ``source_units``, ``scale`` and ``axes`` so :func:`read_gltf_rig` restores the rig in mm.
- With UVs, vertices are split where one position has several UVs (as glTF needs one UV per vertex);
  ``mesh.extras.sourceVertex`` maps each glTF vertex back to the rig's vertex.
"""

from __future__ import annotations

import base64
import json
import os
import struct
from pathlib import Path

import numpy as np

from rigbuild.errors import InputError
from rigbuild.io.atomic import write_bytes
from rigbuild.rig import HEAD_FRAME_AXES, UNIT_TO_MM, Rig

_FLOAT = 5126
_UINT = 5125
_ARRAY_BUFFER = 34962
_ELEMENT_ARRAY_BUFFER = 34963


def _split_by_uv(rig: Rig) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(source vertex per glTF vertex (N,), triangles (F, 3) into glTF vertices, uvs (N, 2) or None)."""
    if rig.uvs is None or rig.face_uvs is None:
        return np.arange(rig.n_vertices), rig.faces, None
    pairs = np.stack([rig.faces.ravel(), rig.face_uvs.ravel()], 1)
    uniq, inv = np.unique(pairs, axis=0, return_inverse=True)
    return uniq[:, 0], inv.reshape(-1, 3), rig.uvs[uniq[:, 1]]


def gltf_rig_document(rig: Rig, scale: float | None = None, extras: dict | None = None) -> tuple[dict, bytes]:
    """The glTF JSON dict and its binary buffer for ``rig`` (see the module docstring); ``extras`` are added to
    ``asset.extras`` (e.g. the frame the rig was moved into)."""
    if scale is None:
        scale = rig.metres_per_unit
    src, tris, uvs = _split_by_uv(rig)
    blobs: list[bytes] = []
    views: list[dict] = []
    accessors: list[dict] = []
    offset = 0

    def add(arr: np.ndarray, ctype: int, atype: str, target: int | None, minmax: bool) -> int:
        nonlocal offset
        data = np.ascontiguousarray(arr).tobytes()
        pad = (-len(data)) % 4
        view = {"buffer": 0, "byteOffset": offset, "byteLength": len(data)}
        if target is not None:
            view["target"] = target
        views.append(view)
        blobs.append(data + b"\0" * pad)
        offset += len(data) + pad
        acc = {"bufferView": len(views) - 1, "componentType": ctype, "count": int(arr.shape[0]), "type": atype}
        if minmax:
            acc["min"] = arr.min(0).astype(float).tolist()
            acc["max"] = arr.max(0).astype(float).tolist()
        accessors.append(acc)
        return len(accessors) - 1

    pos = (rig.neutral[src] * scale).astype(np.float32)
    a_pos = add(pos, _FLOAT, "VEC3", _ARRAY_BUFFER, True)
    a_idx = add(tris.reshape(-1).astype(np.uint32), _UINT, "SCALAR", _ELEMENT_ARRAY_BUFFER, False)
    attributes = {"POSITION": a_pos}
    if uvs is not None:
        # glTF's UV origin is the top-left: v' = 1 - v
        attributes["TEXCOORD_0"] = add(np.stack([uvs[:, 0], 1.0 - uvs[:, 1]], 1).astype(np.float32),
                                       _FLOAT, "VEC2", _ARRAY_BUFFER, False)
    targets = []
    for d in rig.deltas:
        targets.append({"POSITION": add((d[src] * scale).astype(np.float32), _FLOAT, "VEC3", _ARRAY_BUFFER, True)})
    primitive = {"attributes": attributes, "indices": a_idx, "mode": 4}
    if targets:
        primitive["targets"] = targets
    mesh = {"name": rig.name, "primitives": [primitive],
            "extras": {"targetNames": list(rig.shape_names), "sourceVertex": None}}
    if targets:
        mesh["weights"] = [0.0] * len(targets)
    buffer = b"".join(blobs)
    doc = {
        "asset": {
            "version": "2.0",
            "generator": "rigbuild.io.gltf",
            "extras": {"units": "m" if scale == rig.metres_per_unit else f"{scale} x {rig.units}",
                       "source_units": rig.units, "scale": scale, "axes": HEAD_FRAME_AXES,
                       "n_source_vertices": rig.n_vertices, **(extras or {})},
        },
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"name": rig.name, "mesh": 0}],
        "meshes": [mesh],
        "buffers": [{"byteLength": len(buffer)}],
        "bufferViews": views,
        "accessors": accessors,
    }
    if uvs is not None:
        mesh["extras"]["sourceVertex"] = src.astype(int).tolist()
    else:
        del mesh["extras"]["sourceVertex"]
    return doc, buffer


def write_gltf_rig(path: str | os.PathLike, rig: Rig, scale: float | None = None, extras: dict | None = None) -> None:
    """Write ``rig`` as glTF 2.0 (``.gltf`` embedded buffer or ``.glb``) atomically; ``extras`` as in
    :func:`gltf_rig_document`."""
    path = Path(path)
    doc, buffer = gltf_rig_document(rig, scale, extras)
    if path.suffix.lower() == ".glb":
        js = json.dumps(doc, separators=(",", ":")).encode("utf-8")
        js += b" " * ((-len(js)) % 4)
        body = struct.pack("<II", len(js), 0x4E4F534A) + js + struct.pack("<II", len(buffer), 0x004E4942) + buffer
        write_bytes(path, struct.pack("<III", 0x46546C67, 2, 12 + len(body)) + body)
        return
    if path.suffix.lower() != ".gltf":
        raise InputError("glTF output must end in .gltf or .glb", path=path)
    doc["buffers"][0]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(buffer).decode("ascii")
    write_bytes(path, json.dumps(doc, separators=(",", ":")).encode("utf-8"))


def _load(path: Path) -> tuple[dict, bytes]:
    raw = path.read_bytes()
    if raw[:4] == b"glTF":
        magic, version, length = struct.unpack_from("<III", raw, 0)
        jlen, jtype = struct.unpack_from("<II", raw, 12)
        doc = json.loads(raw[20:20 + jlen])
        blen, btype = struct.unpack_from("<II", raw, 20 + jlen)
        if jtype != 0x4E4F534A or btype != 0x004E4942:
            raise InputError("malformed .glb chunks", path=path)
        return doc, raw[28 + jlen:28 + jlen + blen]
    doc = json.loads(raw)
    uri = doc["buffers"][0].get("uri", "")
    if not uri.startswith("data:"):
        return doc, (path.parent / uri).read_bytes()
    return doc, base64.b64decode(uri.split(",", 1)[1])


def read_accessor(doc: dict, buffer: bytes, index: int) -> np.ndarray:
    """An accessor's data as a numpy array (float32 or uint32), shape (count, n_components)."""
    acc = doc["accessors"][index]
    view = doc["bufferViews"][acc["bufferView"]]
    dtype = {_FLOAT: np.float32, _UINT: np.uint32, 5123: np.uint16}[acc["componentType"]]
    ncomp = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}[acc["type"]]
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    arr = np.frombuffer(buffer, dtype=dtype, count=acc["count"] * ncomp, offset=start)
    return arr.reshape(acc["count"], ncomp)


def read_gltf_rig(path: str | os.PathLike) -> Rig:
    """Read a rig written by :func:`write_gltf_rig` back (mm, the rig's original vertex order)."""
    path = Path(path)
    if not path.exists():
        raise InputError("glTF file not found", path=path)
    doc, buffer = _load(path)
    mesh = doc["meshes"][0]
    prim = mesh["primitives"][0]
    extras = doc.get("asset", {}).get("extras", {})
    scale = float(extras.get("scale", 0.001))
    to_mm = UNIT_TO_MM.get(extras.get("source_units", "mm"), 1.0)
    pos = read_accessor(doc, buffer, prim["attributes"]["POSITION"]).astype(np.float64) / scale
    tris = read_accessor(doc, buffer, prim["indices"]).reshape(-1, 3).astype(np.int64)
    names = mesh.get("extras", {}).get("targetNames", [f"target{i}" for i in range(len(prim.get("targets", [])))])
    deltas = [read_accessor(doc, buffer, t["POSITION"]).astype(np.float64) / scale for t in prim.get("targets", [])]
    src = mesh.get("extras", {}).get("sourceVertex")
    if src is not None:
        src = np.asarray(src, dtype=np.int64)
        nV = int(extras.get("n_source_vertices", src.max() + 1))
        neutral = np.zeros((nV, 3))
        neutral[src] = pos
        d = np.zeros((len(deltas), nV, 3))
        for k, dk in enumerate(deltas):
            d[k, src] = dk
        faces = src[tris]
    else:
        neutral, faces = pos, tris
        d = np.stack(deltas) if deltas else np.zeros((0, pos.shape[0], 3))
    return Rig(neutral=neutral * to_mm, deltas=d * to_mm, shape_names=names, faces=faces, units="mm",
               name=mesh.get("name", path.stem))

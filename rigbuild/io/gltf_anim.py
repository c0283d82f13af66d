"""glTF 2.0 animation of morph-target weights: a rig as a mesh with one morph target per shape, plus one
animation whose channel drives the mesh node's ``weights`` over time.

Self-contained (one ``.gltf`` JSON with the binary buffer embedded as a base64 data URI, so the file can be
written atomically and opened in Blender / three.js / any glTF viewer). Positions are written in metres (the
glTF unit), converted from the rig's units; ``asset.extras`` records ``units`` ("m"), ``source_units``,
``scale`` (rig units -> m), ``axes``, ``fps`` and ``n_frames``. Morph targets are stored as sparse accessors
(only the vertices a shape moves), so a 26k-vertex, 53-shape ICT rig stays small. Optional head motion
(per-frame rotation and translation about a pivot) is written as the node's ``rotation`` / ``translation``
channels of the same animation.
"""

from __future__ import annotations

import base64
import json
import os

import numpy as np

from rigbuild.io.atomic import write_text
from rigbuild.rig import HEAD_FRAME_AXES, Rig

FLOAT = 5126
UINT = 5125
ARRAY_BUFFER = 34962
ELEMENT_ARRAY_BUFFER = 34963


class _Buffer:
    """Accumulates 4-byte aligned binary chunks and their buffer views / accessors."""

    def __init__(self) -> None:
        self.chunks: list[bytes] = []
        self.length = 0
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def view(self, data: np.ndarray, target: int | None = None) -> int:
        raw = np.ascontiguousarray(data).tobytes()
        pad = (-len(raw)) % 4
        v = {"buffer": 0, "byteOffset": self.length, "byteLength": len(raw)}
        if target is not None:
            v["target"] = target
        self.chunks.append(raw + b"\0" * pad)
        self.length += len(raw) + pad
        self.views.append(v)
        return len(self.views) - 1

    def accessor(self, acc: dict) -> int:
        self.accessors.append(acc)
        return len(self.accessors) - 1


def rotation_quaternions_xyzw(R: np.ndarray) -> np.ndarray:
    """Unit quaternions (F, 4) in glTF order (x, y, z, w) of rotation matrices (F, 3, 3)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_quat()


def gltf_animation_document(
    rig: Rig, weights: np.ndarray, fps: float, threshold: float = 1e-7, name: str | None = None,
    head_rotation: np.ndarray | None = None, head_translation: np.ndarray | None = None,
    pivot: np.ndarray | None = None,
) -> dict:
    """The glTF JSON document (dict) of ``rig`` animated by ``weights`` (F, K) at ``fps``.

    ``threshold`` (rig units): a vertex belongs to a shape's sparse morph target if it moves more than this.
    head_rotation (F, 3, 3), head_translation (F, 3) rig units, pivot (3,) rig units (default the origin):
    the head motion ``x' = R (x - pivot) + pivot + translation``, written as the node's rotation and
    translation channels (translation in metres).
    """
    w = np.asarray(weights, dtype=np.float32)
    if w.ndim != 2 or w.shape[1] != rig.n_shapes:
        raise ValueError(f"weights must be (F, {rig.n_shapes}), got {w.shape}")
    to_m = rig.metres_per_unit
    buf = _Buffer()
    pos = (rig.neutral * to_m).astype(np.float32)
    a_pos = buf.accessor({
        "bufferView": buf.view(pos, ARRAY_BUFFER), "componentType": FLOAT, "count": int(pos.shape[0]),
        "type": "VEC3", "min": pos.min(0).tolist(), "max": pos.max(0).tolist(),
    })
    idx = rig.faces.astype(np.uint32).reshape(-1)
    a_idx = buf.accessor({"bufferView": buf.view(idx, ELEMENT_ARRAY_BUFFER), "componentType": UINT,
                          "count": int(idx.size), "type": "SCALAR"})
    targets = []
    for k in range(rig.n_shapes):
        d = (rig.deltas[k] * to_m).astype(np.float32)
        moved = np.flatnonzero(np.abs(rig.deltas[k]).max(1) > threshold)
        acc = {"componentType": FLOAT, "count": int(pos.shape[0]), "type": "VEC3",
               "min": (d.min(0) if moved.size else np.zeros(3)).tolist(),
               "max": (d.max(0) if moved.size else np.zeros(3)).tolist()}
        if moved.size:
            acc["sparse"] = {
                "count": int(moved.size),
                "indices": {"bufferView": buf.view(moved.astype(np.uint32)), "componentType": UINT},
                "values": {"bufferView": buf.view(d[moved])},
            }
        targets.append({"POSITION": buf.accessor(acc)})
    F = w.shape[0]
    times = (np.arange(F) / float(fps)).astype(np.float32)
    a_t = buf.accessor({"bufferView": buf.view(times), "componentType": FLOAT, "count": F, "type": "SCALAR",
                        "min": [float(times.min())], "max": [float(times.max())]})
    a_w = buf.accessor({"bufferView": buf.view(w.reshape(-1)), "componentType": FLOAT, "count": int(w.size),
                        "type": "SCALAR"})
    samplers = [{"input": a_t, "output": a_w, "interpolation": "LINEAR"}]
    channels = [{"sampler": 0, "target": {"node": 0, "path": "weights"}}]
    if head_rotation is not None and head_translation is not None:
        Rh = np.asarray(head_rotation, dtype=np.float64)
        d = np.asarray(head_translation, dtype=np.float64)
        if Rh.shape != (F, 3, 3) or d.shape != (F, 3):
            raise ValueError(f"head motion must be ({F}, 3, 3) and ({F}, 3), got {Rh.shape} and {d.shape}")
        c = np.zeros(3) if pivot is None else np.asarray(pivot, dtype=np.float64)
        trans = ((c + d - Rh @ c) * to_m).astype(np.float32)  # R (x - c) + c + d = R x + (c + d - R c)
        a_q = buf.accessor({"bufferView": buf.view(rotation_quaternions_xyzw(Rh).astype(np.float32)),
                            "componentType": FLOAT, "count": F, "type": "VEC4"})
        a_tr = buf.accessor({"bufferView": buf.view(trans), "componentType": FLOAT, "count": F, "type": "VEC3"})
        samplers += [{"input": a_t, "output": a_q, "interpolation": "LINEAR"},
                     {"input": a_t, "output": a_tr, "interpolation": "LINEAR"}]
        channels += [{"sampler": 1, "target": {"node": 0, "path": "rotation"}},
                     {"sampler": 2, "target": {"node": 0, "path": "translation"}}]
    data = b"".join(buf.chunks)
    label = name or rig.name
    return {
        "asset": {"version": "2.0", "generator": "rigbuild.io.gltf_anim",
                  "extras": {"units": "m", "source_units": rig.units, "scale": to_m,
                             "axes": HEAD_FRAME_AXES,
                             "fps": float(fps), "n_frames": int(F)}},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": label}],
        "meshes": [{
            "name": label,
            "primitives": [{"attributes": {"POSITION": a_pos}, "indices": a_idx, "mode": 4, "targets": targets}],
            "weights": [0.0] * rig.n_shapes,
            "extras": {"targetNames": list(rig.shape_names)},
        }],
        "animations": [{
            "name": f"{label}_weights",
            "samplers": samplers,
            "channels": channels,
        }],
        "buffers": [{"byteLength": len(data),
                     "uri": "data:application/octet-stream;base64," + base64.b64encode(data).decode("ascii")}],
        "bufferViews": buf.views,
        "accessors": buf.accessors,
    }


def write_gltf_animation(path: str | os.PathLike, rig: Rig, weights: np.ndarray, fps: float,
                         head_rotation: np.ndarray | None = None, head_translation: np.ndarray | None = None,
                         pivot: np.ndarray | None = None) -> None:
    """Write ``rig`` with its morph-target ``weights`` (F, K) animation at ``fps`` as a ``.gltf`` (atomic);
    optional head motion as in :func:`gltf_animation_document`."""
    doc = gltf_animation_document(rig, weights, fps, head_rotation=head_rotation,
                                  head_translation=head_translation, pivot=pivot)
    write_text(path, json.dumps(doc, separators=(",", ":")))


def read_gltf_animation_weights(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Read back (times (F,), weights (F, K), target names) from a file written by :func:`write_gltf_animation`."""
    doc = json.loads(open(path, encoding="utf-8").read())
    data = base64.b64decode(doc["buffers"][0]["uri"].split(",", 1)[1])

    def get(i: int) -> np.ndarray:
        acc = doc["accessors"][i]
        v = doc["bufferViews"][acc["bufferView"]]
        return np.frombuffer(data, np.float32, count=v["byteLength"] // 4, offset=v["byteOffset"])

    smp = doc["animations"][0]["samplers"][0]
    names = doc["meshes"][0]["extras"]["targetNames"]
    t = get(smp["input"])
    return t.copy(), get(smp["output"]).reshape(t.size, len(names)).copy(), names

"""Outputs of spacetime expression cloning: the fig. 11 velocity-error plot and a glTF animation.

``write_gltf_morph_animation`` is a minimal glTF 2.0 writer (mesh with one morph target per shape,
a ``weights`` animation channel, and the re-applied head motion as the node's rotation/translation
channels). It stands in until a shared ``rigbuild.io.gltf_anim.write_gltf_animation`` exists.
"""

from __future__ import annotations

import base64
import json
import os
from typing import Mapping

import numpy as np

from rigbuild.io.atomic import atomic_path, write_text
from rigbuild.rig import Rig

METHOD_LABELS = {
    "spacetime": "spacetime (ours)",
    "no_constraint": "No Const",
    "perframe_range": "Range PF",
    "perframe_prior": "Prior PF",
}


def plot_velocity_error(path: str | os.PathLike, curves: Mapping[str, np.ndarray], fps: float, title: str = "") -> None:
    """Fig. 11 of the paper: (a) the sum of velocity errors per method, (b) per-frame deltas of the
    velocity error from "No Const" along the time line. curves : {method: (F,) mm^2}."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(curves)
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 3.8), gridspec_kw={"width_ratios": [1, 2.6]})
    sums = [float(np.sum(curves[n])) for n in names]
    ax1.bar(range(len(names)), sums, color=["C0", "C7", "C1", "C2", "C3", "C4"][: len(names)])
    ax1.set_xticks(range(len(names)), [METHOD_LABELS.get(n, n) for n in names], rotation=20, fontsize=8)
    ax1.set_ylabel("sum of velocity errors (mm$^2$)")
    ax1.set_title("(a) ||D(BW)$^T$ - DS$^T$||$_F^2$", fontsize=9)
    base = curves.get("no_constraint")
    for n in names:
        if n == "no_constraint":
            continue
        c = np.asarray(curves[n])
        y = c - base if base is not None else c
        t = np.arange(c.size) / float(fps)
        ax2.plot(t, y, "-" if n == "spacetime" else ":", lw=1.2, label=METHOD_LABELS.get(n, n))
    ax2.set_xlabel("time (s)")
    ax2.set_ylabel("velocity error - No Const (mm$^2$)" if base is not None else "velocity error (mm$^2$)")
    ax2.set_title("(b) per-frame difference from No Const", fontsize=9)
    ax2.legend(fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def _quat_xyzw(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_quat()


def write_gltf_morph_animation(
    path: str | os.PathLike,
    rig: Rig,
    weights: np.ndarray,
    fps: float,
    head_rotation: np.ndarray | None = None,
    head_translation: np.ndarray | None = None,
    pivot: np.ndarray | None = None,
    vertices: np.ndarray | None = None,
) -> None:
    """Write a self-contained ``.gltf`` (buffers as data URIs), positions in metres.

    rig : the character (mm); weights : (F, K); head_rotation (F, 3, 3) / head_translation (F, 3) mm
    (pivot translation, :func:`rigbuild.retarget.seol.head_motion_about_pivot`) about ``pivot`` (3,) mm,
    written as the node's rotation and translation channels; vertices : optional (V,) subset of
    vertices to export (default the face region, to keep files small; triangles outside are dropped).
    """
    W = np.asarray(weights, dtype=np.float32)
    F, K = W.shape
    rig_mm = rig if rig.units == "mm" else rig.to_units("mm")
    keep = rig_mm.face_vertices if vertices is None else np.asarray(vertices, dtype=np.int64)
    remap = -np.ones(rig_mm.n_vertices, dtype=np.int64)
    remap[keep] = np.arange(keep.size)
    tri = remap[rig_mm.faces]
    tri = tri[(tri >= 0).all(1)].astype(np.uint32)
    pos = (rig_mm.neutral[keep] * 1e-3).astype(np.float32)
    morphs = (rig_mm.deltas[:, keep] * 1e-3).astype(np.float32)
    times = (np.arange(F) / float(fps)).astype(np.float32)

    blobs: list[bytes] = []
    views: list[dict] = []
    accessors: list[dict] = []

    def add(arr: np.ndarray, comp: int, typ: str, target: int | None = None, minmax: bool = False) -> int:
        data = np.ascontiguousarray(arr).tobytes()
        offset = sum(len(b) for b in blobs)
        blobs.append(data + b"\0" * ((-len(data)) % 4))
        view = {"buffer": 0, "byteOffset": offset, "byteLength": len(data)}
        if target is not None:
            view["target"] = target
        views.append(view)
        acc = {"bufferView": len(views) - 1, "componentType": comp, "count": int(arr.shape[0]), "type": typ}
        if minmax:
            flat = arr.reshape(arr.shape[0], -1)
            acc["min"] = flat.min(0).tolist()
            acc["max"] = flat.max(0).tolist()
        accessors.append(acc)
        return len(accessors) - 1

    FLOAT, UINT = 5126, 5125
    a_pos = add(pos, FLOAT, "VEC3", 34962, minmax=True)
    a_idx = add(tri.reshape(-1), UINT, "SCALAR", 34963)
    a_targets = [add(morphs[k], FLOAT, "VEC3", 34962, minmax=True) for k in range(K)]
    a_time = add(times, FLOAT, "SCALAR", minmax=True)
    a_w = add(W.reshape(-1), FLOAT, "SCALAR")
    samplers = [{"input": a_time, "output": a_w, "interpolation": "LINEAR"}]
    channels = [{"sampler": 0, "target": {"node": 0, "path": "weights"}}]
    node: dict = {"mesh": 0, "name": rig.name}
    if head_rotation is not None and head_translation is not None:
        c = np.zeros(3) if pivot is None else np.asarray(pivot, dtype=np.float64)
        Rh = np.asarray(head_rotation, dtype=np.float64)
        # x' = R (x - c) + c + d = R x + (c + d - R c)
        trans = (c + np.asarray(head_translation) - Rh @ c) * 1e-3
        a_q = add(_quat_xyzw(Rh).astype(np.float32), FLOAT, "VEC4")
        a_t = add(trans.astype(np.float32), FLOAT, "VEC3")
        samplers += [{"input": a_time, "output": a_q, "interpolation": "LINEAR"},
                     {"input": a_time, "output": a_t, "interpolation": "LINEAR"}]
        channels += [{"sampler": 1, "target": {"node": 0, "path": "rotation"}},
                     {"sampler": 2, "target": {"node": 0, "path": "translation"}}]
    blob = b"".join(blobs)
    doc = {
        "asset": {"version": "2.0", "generator": "rigbuild seol"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [node],
        "meshes": [{
            "name": rig.name,
            "primitives": [{"attributes": {"POSITION": a_pos}, "indices": a_idx, "mode": 4,
                            "targets": [{"POSITION": a} for a in a_targets]}],
            "weights": [0.0] * K,
            "extras": {"targetNames": list(rig.shape_names)},
        }],
        "animations": [{"name": "retarget", "samplers": samplers, "channels": channels}],
        "buffers": [{"byteLength": len(blob),
                     "uri": "data:application/octet-stream;base64," + base64.b64encode(blob).decode("ascii")}],
        "bufferViews": views,
        "accessors": accessors,
    }
    write_text(path, json.dumps(doc))

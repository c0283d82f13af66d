"""The report's 3D view: the personalized rig with one slider per shape, and playback of each retargeted take on
its character, drawn by three.js (:mod:`rigbuild.assets.web`) inlined in the page with ``viewer.js``.

The meshes travel compactly as base64 in one JSON block: neutral positions quantized to int16 over the
mesh's bounding box (mm), each shape's delta only at the vertices it moves (> ``tol_mm``) as int16 with a
per-shape scale, one face list per distinct topology, weight curves as int16 with a per-take offset and scale.
Rigs above ``max_vertices`` keep only the faces of their face region.
"""

from __future__ import annotations

import base64
import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rigbuild.io.curves import read_weight_curves_csv
from rigbuild.io.rigs import read_rig_npz
from rigbuild.rig import UNIT_TO_MM, Rig

VIEWER_JS = Path(__file__).with_name("viewer.js")
#: the folder beside report.html holding the viewer's files when the page would be too large inline
ASSETS_FOLDER = "report_files"
DATA_JS, THREE_JS = "viewer-data.js", "three.min.js"


@dataclass
class Packer:
    """tol_mm: smallest vertex displacement of a shape that is kept; max_vertices: above it a rig is cut to the
    faces of its face region."""

    tol_mm: float = 0.01
    max_vertices: int = 20000

    def __post_init__(self) -> None:
        self.topologies: dict[str, str] = {}  # sha1 of the face list -> its base64
        self.models: dict[str, dict] = {}  # rig file -> packed model

    def _faces(self, faces: np.ndarray, n_vertices: int) -> str:
        arr = faces.astype(np.uint16 if n_vertices <= 65535 else np.uint32)
        key = hashlib.sha1(arr.tobytes()).hexdigest()[:16]
        self.topologies.setdefault(key, b64(arr))
        return key

    def model(self, rig: Rig, label: str) -> dict:
        """Pack one rig (any units; shown in mm)."""
        neutral = rig.neutral * UNIT_TO_MM[rig.units]
        deltas = rig.deltas * UNIT_TO_MM[rig.units]
        faces = rig.faces
        if neutral.shape[0] > self.max_vertices and rig.face_region is not None and rig.face_region.size:
            keep = np.zeros(neutral.shape[0], bool)
            keep[rig.face_region] = True
            faces = faces[keep[faces].all(1)]
            used = np.unique(faces)
            remap = np.full(neutral.shape[0], -1, np.int64)
            remap[used] = np.arange(used.size)
            neutral, deltas, faces = neutral[used], deltas[:, used], remap[faces]
        V = neutral.shape[0]
        lo, hi = neutral.min(0), neutral.max(0)
        step = np.maximum(hi - lo, 1e-6) / 65534.0
        q = np.round((neutral - lo) / step - 32767).astype(np.int16)
        counts, idx, vals, scales = [], [], [], []
        norms = np.linalg.norm(deltas, axis=2)
        for k in range(deltas.shape[0]):
            sel = np.flatnonzero(norms[k] > self.tol_mm)
            d = deltas[k, sel]
            s = float(np.abs(d).max()) / 32767.0 if sel.size else 1.0
            counts.append(int(sel.size))
            idx.append(sel)
            vals.append(np.round(d / s).astype(np.int16))
            scales.append(s)
        itype = np.uint16 if V <= 65535 else np.uint32
        return {"label": label, "n_vertices": V, "faces": self._faces(faces, V),
                "neutral": {"q": b64(q), "lo": lo.tolist(), "step": step.tolist()},
                "shapes": list(rig.shape_names), "counts": counts, "scales": scales,
                "idx": b64(np.concatenate(idx).astype(itype) if idx else np.zeros(0, itype)),
                "deltas": b64(np.concatenate(vals) if vals else np.zeros((0, 3), np.int16))}

    def model_file(self, path: Path, label: str) -> str:
        """Pack the rig npz at ``path`` once; returns its model id."""
        key = str(path)
        if key not in self.models:
            self.models[key] = self.model(read_rig_npz(path), label)
        return key


def b64(arr: np.ndarray) -> str:
    """Little-endian array bytes as base64 (the page decodes them into typed arrays)."""
    a = np.ascontiguousarray(arr)
    return base64.b64encode(a.astype(a.dtype.newbyteorder("<")).tobytes()).decode("ascii")


def pack_take(csv_path: Path, model_id: str, label: str) -> dict:
    """One retargeted take: weights (F, K) int16 with an offset and scale, the shape names, fps."""
    w, names, times = read_weight_curves_csv(csv_path)
    beside = csv_path.with_suffix(".json")
    if beside.exists():  # weights.json carries the take's exact rate
        fps = float(json.loads(beside.read_text(encoding="utf-8"))["fps"])
    else:  # the CSV's times are rounded to 1 us: the rate over the whole take
        fps = float((times.size - 1) / (times[-1] - times[0])) if times.size > 1 else 30.0
    lo, hi = (float(w.min()), float(w.max())) if w.size else (0.0, 0.0)
    scale = max(hi - lo, 1e-9) / 65534.0
    q = np.round((w - lo) / scale - 32767).astype(np.int16)
    return {"label": label, "model": model_id, "shapes": names, "fps": fps, "n_frames": int(w.shape[0]),
            "offset": lo + 32767 * scale, "scale": scale, "weights": b64(q)}


def take_files(results_dir: Path) -> list[tuple[Path, str, str, str]]:
    """(weights.csv, method, performance, character) of every retargeted take, by performance, character and
    method in the pipeline's order (:data:`rigbuild.retarget.methods.PIPELINE_METHODS`; others after)."""
    from rigbuild.retarget.methods import PIPELINE_METHODS

    out = []
    for p in results_dir.glob("retarget/*/*/*/weights.csv"):
        method, perf, character = p.parts[-4:-1]
        out.append((p, method, perf, character))
    order = {m: i for i, m in enumerate(PIPELINE_METHODS)}
    return sorted(out, key=lambda r: (r[2], r[3], order.get(r[1], len(order)), r[1]))


def viewer_data(results_dir: str | os.PathLike, packer: Packer | None = None) -> dict[str, Any] | None:
    """The viewer's JSON: models (the personalized rig first, then each character with a take), takes and
    topologies; None when the results hold neither a personalized rig nor a take."""
    results_dir = Path(results_dir)
    packer = packer or Packer()
    rig = results_dir / "personalize" / "rig.npz"
    if rig.exists():
        packer.model_file(rig, "personalized rig (personalize/rig.npz)")
    takes = []
    for csv, method, perf, character in take_files(results_dir):
        char = results_dir / "characters" / f"{character}.npz"
        if not char.exists():
            continue
        mid = packer.model_file(char, f"character {character} (characters/{character}.npz)")
        takes.append(pack_take(csv, mid, f"{perf} → {character} ({method})"))
    if not packer.models:
        return None
    ids = {k: f"m{i}" for i, k in enumerate(packer.models)}
    for t in takes:
        t["model"] = ids[t["model"]]
    return {"models": {ids[k]: m for k, m in packer.models.items()}, "takes": takes,
            "topologies": packer.topologies}


def viewer_html(data: dict[str, Any], three_js: str, assets: dict[str, str] | None = None,
                folder: str = ASSETS_FOLDER) -> str:
    """The viewer's markup, its data and its scripts (three.js, viewer.js): inline, or with ``assets`` (a dict
    that receives file name -> text) the data and three.js as classic scripts in ``folder`` beside the page
    (``<script src>`` loads from ``file://`` too)."""
    blob = json.dumps(data, separators=(",", ":"))
    markup = ('<div id="rb-viewer"><div id="rb-canvas"><p class="hint">drag: turn · wheel: zoom</p></div>'
              '<div id="rb-controls"><label>show <select id="rb-select"></select></label>'
              '<div id="rb-play"><button id="rb-playbtn" type="button">play</button> '
              '<input id="rb-frame" type="range" min="0" max="0" value="0"> <span id="rb-frametext"></span></div>'
              '<div id="rb-sliders"></div></div></div>')
    viewer = f"<script>{VIEWER_JS.read_text(encoding='utf-8')}</script>"
    if assets is None:
        safe = blob.replace("</", "<\\/")
        return (markup + f'<script type="application/json" id="rb-viewer-data">{safe}</script>'
                f"<script>{three_js}</script>" + viewer)
    assets[DATA_JS] = f"window.RB_VIEWER_DATA = {blob};\n"
    assets[THREE_JS] = three_js
    return (markup + f'<script src="{folder}/{THREE_JS}"></script><script src="{folder}/{DATA_JS}"></script>'
            + viewer)

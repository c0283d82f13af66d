"""Facial marker sets: named vertex indices per rig, stored as data, and their landmark-based definition.

A marker set is ``{name: vertex_index}`` for one rig topology, stored in
``rigbuild/assets/marker_sets/<rig>.json`` as ``{"rig": "<rig>", "markers": {name: index, ...}}``.

Names are shared between rigs where the regions correspond (``browInner_L``, ``lipUpper_C``, ...), which is
what lets retargeting pair markers of different rigs by name. ``_L`` is the actor's left (+x), ``_R`` the
actor's right (-x), ``_C`` the midline.

Both the ICT set (``scripts/dev/make_ict_markers.py``) and the procedural head's set
(:func:`rigbuild.assets.head.procedural_head_rig`) are placed by the same recipe: each marker's target
point is a weighted combination of the 68 Multi-PIE landmarks plus a small offset in mm
(:data:`MARKER_RECIPES`, :func:`marker_targets`), snapped to the nearest front-facing face-region vertex
seen from the front (:func:`snap_to_surface`).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from rigbuild.errors import InputError
from rigbuild.geometry.mesh import vertex_normals  # noqa: F401 (re-exported)

#: folder of the marker-set JSON files shipped with rigbuild (package data)
MARKER_DIR = Path(__file__).resolve().parent / "marker_sets"

#: Multi-PIE 68 landmark index of the mirror-image landmark (actor's left <-> right).
MULTIPIE_MIRROR = np.array(
    list(range(16, -1, -1))  # jaw 0..16
    + list(range(26, 16, -1))  # brows 17..26
    + [27, 28, 29, 30]  # nose bridge
    + [35, 34, 33, 32, 31]  # nostril base
    + [45, 44, 43, 42, 47, 46]  # right eye -> left eye
    + [39, 38, 37, 36, 41, 40]  # left eye -> right eye
    + [54, 53, 52, 51, 50, 49, 48]  # outer upper lip
    + [59, 58, 57, 56, 55]  # outer lower lip
    + [64, 63, 62, 61, 60]  # inner upper lip
    + [67, 66, 65],  # inner lower lip
    dtype=np.int64,
)

#: Marker recipes: name -> ({landmark index: weight}, offset (x, y, z) in mm). ``_L`` recipes use the
#: actor's-left landmarks; the ``_R`` marker is the mirror image (landmarks via :data:`MULTIPIE_MIRROR`,
#: x offset negated). ``_C`` recipes are symmetric. Weights sum to 1.
MARKER_RECIPES: dict[str, tuple[dict[int, float], tuple[float, float, float]]] = {
    # brows and forehead
    "browInner_L": ({22: 1.0}, (0.0, 0.0, 0.0)),
    "browMid_L": ({24: 1.0}, (0.0, 0.0, 0.0)),
    "browOuter_L": ({26: 1.0}, (0.0, 0.0, 0.0)),
    "foreheadInner_L": ({22: 1.0}, (0.0, 18.0, 0.0)),
    "foreheadOuter_L": ({25: 1.0}, (0.0, 18.0, 0.0)),
    "temple_L": ({26: 0.5, 16: 0.5}, (0.0, 4.0, 0.0)),
    # lids and eye corners
    "lidUpper_L": ({43: 0.5, 44: 0.5}, (0.0, 3.0, 0.0)),
    "lidLower_L": ({46: 0.5, 47: 0.5}, (0.0, -3.0, 0.0)),
    "eyeInner_L": ({42: 1.0}, (-3.0, 0.0, 0.0)),
    "eyeOuter_L": ({45: 1.0}, (4.0, 0.0, 0.0)),
    # cheeks
    "cheekUpper_L": ({46: 0.5, 47: 0.5}, (0.0, -14.0, 0.0)),
    "cheekbone_L": ({15: 0.6, 45: 0.4}, (0.0, -10.0, 0.0)),
    "cheekMid_L": ({14: 0.5, 35: 0.5}, (0.0, 0.0, 0.0)),
    "cheek_L": ({13: 0.5, 35: 0.2, 54: 0.3}, (0.0, 0.0, 0.0)),
    "cheekLower_L": ({12: 0.5, 54: 0.5}, (0.0, 0.0, 0.0)),
    "nasolabial_L": ({35: 0.5, 54: 0.5}, (6.0, 0.0, 0.0)),
    # nose
    "noseWing_L": ({35: 1.0}, (3.0, 2.0, 0.0)),
    "noseSide_L": ({29: 0.5, 47: 0.3, 35: 0.2}, (0.0, 0.0, 0.0)),
    # lips and mouth
    "lipUpper_L": ({52: 1.0}, (0.0, 0.0, 0.0)),
    "lipUpperOuter_L": ({53: 1.0}, (0.0, 0.0, 0.0)),
    "mouthCorner_L": ({54: 1.0}, (0.0, 0.0, 0.0)),
    "lipLowerOuter_L": ({55: 1.0}, (0.0, 0.0, 0.0)),
    "lipLower_L": ({56: 1.0}, (0.0, 0.0, 0.0)),
    "philtrumSide_L": ({52: 0.5, 35: 0.5}, (0.0, 0.0, 0.0)),
    # chin and jaw
    "chin_L": ({56: 0.5, 9: 0.5}, (0.0, 0.0, 0.0)),
    "jaw_L1": ({9: 0.9, 33: 0.1}, (0.0, 0.0, 0.0)),
    "jaw_L2": ({10: 0.9, 33: 0.1}, (0.0, 0.0, 0.0)),
    "jaw_L3": ({11: 0.9, 33: 0.1}, (0.0, 0.0, 0.0)),
    "jaw_L4": ({12: 0.9, 33: 0.1}, (0.0, 0.0, 0.0)),
    "jaw_L5": ({13: 0.9, 33: 0.1}, (0.0, 0.0, 0.0)),
    # midline
    "forehead_C": ({21: 0.5, 22: 0.5}, (0.0, 22.0, 0.0)),
    "glabella_C": ({21: 0.25, 22: 0.25, 27: 0.5}, (0.0, 0.0, 0.0)),
    "noseBridge_C": ({28: 1.0}, (0.0, 0.0, 0.0)),
    "noseTip_C": ({30: 1.0}, (0.0, 0.0, 0.0)),
    "philtrum_C": ({33: 0.5, 51: 0.5}, (0.0, 0.0, 0.0)),
    "lipUpper_C": ({51: 1.0}, (0.0, 0.0, 0.0)),
    "lipLower_C": ({57: 1.0}, (0.0, 0.0, 0.0)),
    "chin_C": ({57: 0.4, 8: 0.6}, (0.0, 0.0, 0.0)),
    "chinLow_C": ({8: 1.0}, (0.0, 3.0, 0.0)),
}


def marker_names() -> list[str]:
    """The M marker names in canonical order: every ``_L`` marker then its ``_R`` mirror, then ``_C``."""
    left = [n for n in MARKER_RECIPES if not n.endswith("_C")]
    names: list[str] = []
    for n in left:
        names += [n, mirror_name(n)]
    names += [n for n in MARKER_RECIPES if n.endswith("_C")]
    return names


def mirror_name(name: str) -> str:
    """``browInner_L`` <-> ``browInner_R``, ``jaw_L3`` <-> ``jaw_R3``; ``_C`` names map to themselves."""
    head, _, tail = name.rpartition("_")
    if tail.startswith("L"):
        return f"{head}_R{tail[1:]}"
    if tail.startswith("R"):
        return f"{head}_L{tail[1:]}"
    return name


def marker_targets(landmark_points: np.ndarray) -> tuple[list[str], np.ndarray]:
    """Target positions of the named markers from the 68 landmark positions.

    landmark_points : (68, 3) Multi-PIE landmark positions in mm (+x = actor's left, +y up, +z out).
    Returns names (M,) in :func:`marker_names` order and targets (M, 3) in mm.
    """
    lm = np.asarray(landmark_points, dtype=np.float64)
    if lm.shape != (68, 3):
        raise InputError(f"marker targets need (68, 3) landmark positions, got {lm.shape}")
    names = marker_names()
    out = np.empty((len(names), 3))
    for m, name in enumerate(names):
        is_right = name not in MARKER_RECIPES
        weights, offset = MARKER_RECIPES[mirror_name(name) if is_right else name]
        idx = np.array(list(weights), dtype=np.int64)
        w = np.array(list(weights.values()))
        off = np.array(offset, dtype=np.float64)
        if is_right:
            idx = MULTIPIE_MIRROR[idx]
            off[0] = -off[0]
        out[m] = w @ lm[idx] + off
    return names, out


def snap_to_surface(
    vertices: np.ndarray,
    faces: np.ndarray,
    targets: np.ndarray,
    candidates: np.ndarray | None = None,
    min_normal_z: float = 0.15,
    depth_weight: float = 0.3,
) -> np.ndarray:
    """Vertex index nearest to each target, as seen from the front.

    Among the candidate vertices whose normal faces the viewer (``n_z > min_normal_z``), pick the one that
    minimizes ``dx^2 + dy^2 + depth_weight * dz^2`` (mm^2): targets built from chords between landmarks
    lie under the skin, so depth counts less than the position in the frontal view.

    vertices (V, 3) mm; faces (F, 3); targets (M, 3) mm; candidates (C,) vertex indices (default all).
    Returns (M,) int64 vertex indices.
    """
    v = np.asarray(vertices, dtype=np.float64)
    cand = np.arange(v.shape[0]) if candidates is None else np.asarray(candidates, dtype=np.int64)
    n = vertex_normals(v, faces)
    cand = cand[n[cand, 2] > min_normal_z]
    if cand.size == 0:
        raise InputError("no front-facing candidate vertices to place markers on")
    t = np.asarray(targets, dtype=np.float64)
    scale = np.array([1.0, 1.0, np.sqrt(depth_weight)])
    d2 = (((v[cand][None, :, :] - t[:, None, :]) * scale) ** 2).sum(-1)
    return cand[np.argmin(d2, axis=1)]


def marker_set_path(rig_name: str) -> Path:
    """Path of the marker-set JSON for ``rig_name`` (a bare name -> ``rigbuild/assets/marker_sets/<name>.json``;
    an existing ``.json`` path is used as is)."""
    p = Path(rig_name)
    if p.suffix == ".json" or os.sep in str(rig_name):
        return p
    return MARKER_DIR / f"{rig_name}.json"


def load_marker_set(rig_name: str) -> tuple[list[str], np.ndarray]:
    """Read a marker set.

    rig_name : a rig name (``"ict"`` -> ``rigbuild/assets/marker_sets/ict.json``) or a path to such a JSON file.
    Returns (names (M,), vertex indices (M,) int64), in the file's order.
    Raises :class:`InputError` if the file is absent or malformed.
    """
    path = marker_set_path(rig_name)
    if not path.is_file():
        known = sorted(p.stem for p in MARKER_DIR.glob("*.json")) if MARKER_DIR.is_dir() else []
        raise InputError(
            f"no marker set for rig '{rig_name}'",
            path=path,
            fix=f"use one of {known} or give a JSON file {{'rig': name, 'markers': {{name: vertex_index}}}}",
        )
    try:
        meta = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise InputError(f"not valid JSON ({e})", path=path, fix="regenerate the marker set") from None
    markers = meta.get("markers") if isinstance(meta, dict) else None
    if not isinstance(markers, dict) or not markers:
        raise InputError("field 'markers' missing or empty", path=path, fix="write {'markers': {name: vertex_index}}")
    names = [str(k) for k in markers]
    try:
        idx = np.array([int(markers[k]) for k in markers], dtype=np.int64)
    except (TypeError, ValueError):
        raise InputError("marker vertex indices must be integers", path=path, fix="fix field 'markers'") from None
    if idx.min() < 0:
        raise InputError("negative marker vertex index", path=path, fix="fix field 'markers'")
    return names, idx

"""Marker-to-vertex maps for characters, stored as data (``rigbuild/assets/marker_sets/<name>.json``).

A map file is ``{"rig": ..., "markers": {marker name: vertex id}, "contact_pairs": [[a, b], ...] (optional),
"method": how it was made}``. :func:`build_landmark_marker_map` makes one for a rig with Multi-PIE landmarks
from a marker layout's neutral frame: markers that sit on a landmark are paired with it, the layout is brought
to the rig by a similarity then a thin-plate RBF through those pairs, and every marker is snapped to the
nearest front-facing vertex of the rig's face region.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from rigbuild.errors import InputError
from rigbuild.geometry.rigid import fit_similarity
from rigbuild.io.atomic import write_json
from rigbuild.rig import Rig

MARKER_DATA_DIR = Path(__file__).resolve().parent.parent / "assets" / "marker_sets"

#: AnimFace marker -> Multi-PIE 68 landmark index (or pair of indices, averaged). Actor's left = rig +x.
ANIMFACE_LANDMARKS: dict[str, tuple[int, ...]] = {
    "Reye_Outside": (36,), "Reye_Inside": (39,), "Leye_Inside": (42,), "Leye_Outside": (45,),
    "Reye_Up": (37, 38), "Reye_Down": (40, 41), "Leye_Up": (43, 44), "Leye_Down": (46, 47),
    "Reyebrow_Outside": (17,), "Reyebrow_M": (19,), "Reyebrow_Inside": (21,),
    "Leyebrow_Inside": (22,), "Leyebrow_M": (24,), "Leyebrow_Outside": (26,),
    "NoseTop": (27,), "NoseHead": (30,),
    "Mouth_Rend": (48,), "Mouth_Up": (51,), "Mouth_Lend": (54,), "Mouth_Down": (57,),
}


def read_marker_map(path: str | os.PathLike) -> tuple[list[str], np.ndarray, np.ndarray | None]:
    """(names, vertex ids (M,), contact pairs (C, 2) of marker indices or None) from a map JSON."""
    path = Path(path)
    if not path.exists():
        raise InputError("marker map not found", path=path, fix="give the character a marker map JSON")
    try:
        doc = json.loads(path.read_text())
        markers = doc["markers"]
        names = list(markers)
        ids = np.array([int(markers[n]) for n in names], dtype=np.int64)
    except (KeyError, ValueError, TypeError) as e:
        raise InputError(f"malformed marker map ({e})", path=path,
                         fix='expected {"markers": {"<marker name>": <vertex id>, ...}}') from None
    pairs = doc.get("contact_pairs")
    if pairs:
        idx = {n: i for i, n in enumerate(names)}
        try:
            pairs = np.array([[idx[a], idx[b]] for a, b in pairs], dtype=np.int64)
        except KeyError as e:
            raise InputError(f"contact pair names unknown marker {e}", path=path) from None
    else:
        pairs = None
    return names, ids, pairs


def build_landmark_marker_map(
    names: Sequence[str],
    neutral: np.ndarray,
    rig: Rig,
    landmark_pairs: Mapping[str, Sequence[int]],
    min_normal_z: float = 0.0,
) -> np.ndarray:
    """Vertex id on ``rig`` for each marker of a layout given by its neutral frame (M, 3) (any units/frame).

    ``landmark_pairs``: marker name -> Multi-PIE landmark indices (averaged) on ``rig.landmarks``.
    """
    import igl

    from rigbuild.retarget.ribera import fit_thin_plate_rbf

    if rig.landmarks is None:
        raise InputError(f"rig '{rig.name}' has no landmarks")
    names = list(names)
    src_idx = [names.index(n) for n in landmark_pairs if n in names]
    if len(src_idx) < 6:
        raise InputError("fewer than 6 markers pair with landmarks", fix="extend the landmark pairs")
    dst = np.array([rig.neutral[rig.landmarks[list(landmark_pairs[names[i]])]].mean(0) for i in src_idx])
    src = np.asarray(neutral, float)
    s, R, t = fit_similarity(src[src_idx], dst)
    moved = s * src @ R.T + t
    rbf = fit_thin_plate_rbf(moved[src_idx], dst)
    target = rbf(moved)
    fv = rig.face_vertices
    normals = igl.per_vertex_normals(rig.neutral, rig.faces)
    cand = fv[normals[fv, 2] > min_normal_z]
    d = np.linalg.norm(rig.neutral[cand][None] - target[:, None], axis=2)
    ids = cand[np.argmin(d, axis=1)]
    return ids


def write_marker_map(path: str | os.PathLike, rig_name: str, names: Sequence[str], ids: np.ndarray,
                     method: str, contact_pairs: Sequence[tuple[str, str]] | None = None) -> None:
    """Write a marker map JSON (atomic)."""
    doc = {"rig": rig_name, "method": method, "markers": {n: int(v) for n, v in zip(names, ids)}}
    if contact_pairs:
        doc["contact_pairs"] = [list(p) for p in contact_pairs]
    write_json(path, doc)


ANIMFACE_CONTACT_PAIRS = [("Leye_Up", "Leye_Down"), ("Reye_Up", "Reye_Down"), ("Mouth_Up", "Mouth_Down"),
                          ("Mouth_UpL1", "Mouth_DownL"), ("Mouth_UpR1", "Mouth_DownR")]

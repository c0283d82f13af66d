"""ARKit-52 naming of a rig's shapes, from the committed map ``rigbuild/assets/arkit52.json``.

ARKit (``ARFaceAnchor.BlendShapeLocation``) names 52 shapes; ICT-FaceKit (and the procedural head, which uses
ICT's names) has 53, of which 13 are spelled as in ARKit. The map gives each ARKit shape the ICT shapes it is
made of: one shape renamed (``eyeBlink_L`` -> ``eyeBlinkLeft``) or the sum of the two halves ICT splits it
into (``browInnerUp_L`` + ``browInnerUp_R`` -> ``browInnerUp``; deltas add). ``tongueOut`` has no ICT
counterpart.
"""

from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path

import numpy as np

from rigbuild.rig import Rig

ARKIT_MAP = Path(__file__).resolve().parents[1] / "assets" / "arkit52.json"


@lru_cache(maxsize=1)
def arkit_map() -> tuple[tuple[str, ...], dict[str, tuple[str, ...]]]:
    """(the 52 ARKit names in Apple's order, ARKit name -> the ICT shapes it is the sum of)."""
    doc = json.loads(ARKIT_MAP.read_text())
    return tuple(doc["arkit52"]), {k: tuple(v) for k, v in doc["from_ict"].items()}


def arkit_rig(rig: Rig) -> tuple[Rig, dict]:
    """``rig`` with ARKit names: the ARKit shapes it can make, in Apple's order (each the sum of its sources'
    deltas; a shape already named as in ARKit is its own source), then the rig's shapes that no ARKit shape is
    made of, under their own names. Returns (rig, naming) with naming = ``{"names": "arkit", "arkit_sources":
    {arkit: [shapes]}, "arkit_missing": [ARKit names the rig cannot make], "no_arkit_counterpart": [rig shapes
    kept under their own names]}``."""
    order, sources = arkit_map()
    have = set(rig.shape_names)
    names: list[str] = []
    deltas: list[np.ndarray] = []
    used: dict[str, list[str]] = {}
    missing: list[str] = []
    for a in order:
        src = list(sources.get(a, ()))
        if not (src and all(s in have for s in src)):
            src = [a] if a in have else []
        if not src:
            missing.append(a)
            continue
        names.append(a)
        deltas.append(sum(rig.deltas[rig.shape_index(s)] for s in src))
        used[a] = src
    consumed = {s for src in used.values() for s in src}
    extra = [n for n in rig.shape_names if n not in consumed]
    names += extra
    deltas += [rig.deltas[rig.shape_index(n)] for n in extra]
    out = Rig(rig.neutral, np.stack(deltas) if deltas else np.zeros((0,) + rig.neutral.shape), names, rig.faces,
              rig.uvs, rig.face_uvs, rig.units, rig.name, rig.face_region, rig.landmarks, list(rig.marker_names),
              rig.marker_vertices)
    return out, {"names": "arkit", "arkit_sources": used, "arkit_missing": missing, "no_arkit_counterpart": extra}

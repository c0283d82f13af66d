"""Write rigbuild/assets/marker_sets/ict.json: the default marker set on the ICT-FaceKit template.

Reproducible: every marker is the recipe in :data:`rigbuild.assets.markers.MARKER_RECIPES` (a weighted sum of
the ICT template's 68 Multi-PIE landmarks plus an offset in mm), snapped to the nearest front-facing vertex of
the ICT face skin (vertices 0-9408) as seen from the front. The procedural head uses the same recipes, so
marker names correspond between the two rigs.

Usage: python scripts/dev/make_ict_markers.py [--out rigbuild/assets/marker_sets/ict.json]
(needs the ICT data: $RIGBUILD_DATA/ict-facekit/FaceXModel)
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from rigbuild.io.atomic import write_json
from rigbuild.io.rigs import ICT_FACE_VERTICES, read_ict_rig
from rigbuild.paths import ict_dir
from rigbuild.assets.markers import MARKER_DIR, marker_targets, snap_to_surface


def ict_markers(rig) -> dict[str, int]:
    """{name: vertex} for the ICT template rig (mm)."""
    names, targets = marker_targets(rig.neutral[rig.landmarks])
    face = np.arange(*ICT_FACE_VERTICES)
    idx = snap_to_surface(rig.neutral, rig.faces, targets, candidates=face)
    return {n: int(i) for n, i in zip(names, idx)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ict", default=str(ict_dir()), help="ICT FaceXModel folder")
    ap.add_argument("--out", default=str(MARKER_DIR / "ict.json"))
    args = ap.parse_args()
    rig = read_ict_rig(args.ict, expressions=["jawOpen"])  # only the neutral and landmarks are used
    markers = ict_markers(rig)
    if len(set(markers.values())) != len(markers):
        raise SystemExit("two markers snapped to the same vertex; adjust MARKER_RECIPES")
    write_json(args.out, {"rig": "ict", "markers": markers})
    print(f"wrote {len(markers)} markers to {Path(args.out)}")


if __name__ == "__main__":
    main()

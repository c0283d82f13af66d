"""Render one view of the ICT actor twice, as the clean world and as the realistic capture sees it, side by side
(README's picture): python scripts/dev/render_pair.py [--out docs/images/ict_clean_vs_realistic.jpg]"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))


def main() -> int:
    import cv2

    from rigbuild.io.rigs import load_rig
    from rigbuild.synth.capture import capture_face, capture_setup
    from rigbuild.synth.rig_layout import make_camera_rig
    from rigbuild.synth.session import synth_params

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "docs" / "images" / "ict_clean_vs_realistic.jpg"))
    ap.add_argument("--rig", default="ict")
    args = ap.parse_args()
    rig = load_rig(args.rig)
    centre = rig.neutral[rig.face_vertices].mean(0)
    cam = make_camera_rig(n_cameras=8, width=1280, height=960, distance_mm=500.0, target=centre)[3]
    dots = rig.neutral[rig.marker_vertices]
    images = []
    for block in ({}, {"appearance": "realistic", "lights": "studio", "camera": {"jpeg_quality": 92}}):
        setup = capture_setup(synth_params({"seed": 11, **block}), rig, [cam], centre, 1280)
        albedo = (25, 25, 25) if not block else np.full((len(dots), 3), 40, np.uint8)
        images.append(capture_face(cam, setup, rig.neutral, 11, None, dots, 1.5, albedo))
    pair = np.concatenate(images, axis=1)[120:840, :]  # the face, both views
    pair = cv2.resize(pair, (pair.shape[1] // 2, pair.shape[0] // 2), interpolation=cv2.INTER_AREA)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(args.out, np.ascontiguousarray(pair[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, 88])
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The landmark tables, made from renders of the template (``python -m rigbuild.track.landmark_table``):

- ``rigbuild/assets/face_landmarks/mediapipe_to_ibug68.json``: each iBUG / Multi-PIE 68 point as a non-negative
  combination (weights sum to 1) of at most :data:`CANDIDATES` face-mesh points. Derived here, not copied: the ICT
  template (realistic skin, studio lights) is rendered from near-frontal views in a few expressions, the face
  mesh network runs on each image, and for every 68 point (ICT-FaceKit's own Multi-PIE vertex list,
  ``Rig.landmarks``, with its README's jawline substitutes for points 0-7 and 9-16, projected) the weights
  over its nearest face-mesh points are the least-squares fit (NNLS) over all images, in units of the
  outer-eye-corner distance.
- ``rigbuild/assets/face_landmarks/ict_468.json``: each of the 468 face-mesh points as a point on the ICT
  neutral (triangle, barycentric, nearest vertex) with a reliability. Every render (wider views, same
  expressions) gives, per landmark, the surface point under its pixel (the renderer's triangle and barycentric
  buffers) carried back to the neutral through the same triangle; the table's point is the closest neutral
  surface point to their median and ``spread_mm`` their robust spread (1.4826 x median distance). Contour points
  (the face oval, the lips' inner line) slide along the skin with the view and the expression, so their spread
  is large; ``reliability = 1 / (1 + (spread_mm / 1 mm)^2)`` (an inverse-variance weight with a 1 mm floor).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from rigbuild.track.landmarks import LEFT_EYE_OUTER, N_LANDMARKS, RIGHT_EYE_OUTER

ASSET_DIR = Path(__file__).resolve().parent.parent / "assets" / "face_landmarks"
TABLE_68 = ASSET_DIR / "mediapipe_to_ibug68.json"
TABLE_ICT = ASSET_DIR / "ict_468.json"  # the ICT template's (table_path("ict"))
#: face-mesh candidates per 68 point (its nearest, by mean image distance)
CANDIDATES = 4
#: expressions rendered (ICT shape name -> weight); "neutral" has none
EXPRESSIONS = {
    "neutral": {},
    "jaw_open": {"jawOpen": 0.5},
    "smile": {"mouthSmile_L": 0.7, "mouthSmile_R": 0.7},
    "blink": {"eyeBlink_L": 0.7, "eyeBlink_R": 0.7},
    "brows_up": {"browInnerUp_L": 0.6, "browInnerUp_R": 0.6, "browOuterUp_L": 0.6, "browOuterUp_R": 0.6},
}
FRONTAL_VIEWS = ((-15, 0), (0, 0), (15, 0), (0, -10), (0, 10))
WIDE_VIEWS = ((-45, 0), (-30, 10), (-15, -10), (0, 0), (15, 10), (30, -10), (45, 0))
#: ICT-FaceKit README's jawline vertices that "substitute 0-7 / 9-16 in Multi PIE": they lie on the visible jaw
#: contour of a frontal view, where 2-D annotators put the jaw points (the default list's cheek points lie
#: inside the silhouette)
ICT_JAW_RIGHT = (1278, 1272, 12, 1834, 243, 781, 2199, 1447)
ICT_JAW_LEFT = (3661, 4390, 3022, 2484, 4036, 2253, 3490, 3496)


def ict_ibug68_vertices(rig) -> np.ndarray:
    """(68,) the ICT vertices of the iBUG 68 points: ``rig.landmarks`` with the README's jawline substitutes."""
    v = np.asarray(rig.landmarks, np.int64).copy()
    v[0:8], v[9:17] = ICT_JAW_RIGHT, ICT_JAW_LEFT
    return v


def ibug68_from_mediapipe(points: np.ndarray, table: dict | None = None) -> np.ndarray:
    """(..., 68, D) the 68 iBUG points from face-mesh points (..., 468, D) with the committed table."""
    t = table or load_table_68()
    idx, w = np.asarray(t["indices"]), np.asarray(t["weights"])
    return (np.asarray(points)[..., idx, :] * w[..., None]).sum(-2)


def load_table_68() -> dict:
    from rigbuild.errors import InputError

    if not TABLE_68.is_file():
        raise InputError("the 468 -> 68 landmark table is missing", path=TABLE_68,
                         fix="run `python -m rigbuild.track.landmark_table` (needs ICT-FaceKit) or reinstall rigbuild")
    return json.loads(TABLE_68.read_text())


def table_path(rig_name: str) -> Path:
    """The committed 468 -> template table of a template rig (``<name>_468.json``)."""
    return ASSET_DIR / f"{rig_name}_468.json"


def load_table(rig_name: str = "ict") -> dict:
    """The committed 468 -> template table of rig ``rig_name``: ``vertex`` (468,) nearest vertex, ``triangle``
    (468,) and ``faces`` (468, 3) its triangle (index, vertex ids), ``bary`` (468, 3), ``spread_mm``,
    ``reliability`` (468,), as numpy arrays. InputError with the command that makes it when absent."""
    from rigbuild.errors import InputError

    path = table_path(rig_name)
    if not path.is_file():
        raise InputError(f"no 468-landmark table for the template rig '{rig_name}'", path=path,
                         fix=f"run `python -m rigbuild.track.landmark_table --rig {rig_name} --skip 68` (renders the "
                             "template), or use registration.coarse: dots")
    d = json.loads(path.read_text())
    return {k: np.asarray(v) if isinstance(v, list) else v for k, v in d.items()}


def load_table_ict() -> dict:
    """:func:`load_table` of the ICT template."""
    return load_table("ict")


def fit_combination(P: np.ndarray, q: np.ndarray, candidates: int = CANDIDATES) -> tuple[np.ndarray, np.ndarray]:
    """Weights of one target point as a convex-like combination of face-mesh points.

    P : (S, 468, 2) face-mesh points per sample, q : (S, 2) the target per sample, both already normalized
    (e.g. by the eye-corner distance). Returns indices (candidates,) and weights (candidates,) >= 0 summing to 1
    (NNLS with a heavily weighted sum-to-one row), fitted over all samples.
    """
    from scipy.optimize import nnls

    near = np.argsort(np.linalg.norm(P - q[:, None, :], axis=2).mean(0))[:candidates]
    A = P[:, near, :].transpose(0, 2, 1).reshape(-1, candidates)
    b = q.reshape(-1)
    A = np.vstack([A, 100.0 * np.ones((1, candidates))])
    b = np.concatenate([b, [100.0]])
    w, _ = nnls(A, b)
    return near, w / w.sum()


def _sample_views(rig, head_fn, cameras, landmarker, expressions) -> list[dict]:
    """Render every expression through every camera; per image the face-mesh points, the projected 68 and the
    neutral-surface points under the landmarks (NaN where the pixel misses the mesh)."""
    from rigbuild.track.landmark_views import render_views

    base = None
    out = []
    ibug = ict_ibug68_vertices(rig) if rig.name == "ict" else rig.landmarks
    for name, weights in expressions.items():
        w = np.zeros(rig.n_shapes)
        for k, v in weights.items():
            w[rig.shape_index(k)] = v
        V = rig.evaluate(w)
        head = head_fn(V) if base is None else base.__class__(base.mesh.with_vertices(V), base.material, base.centre)
        base = base or head
        for cam, res in zip(cameras, render_views(head, cameras, with_geometry=True)):
            lm = landmarker(res.color)
            if lm is None:
                print(f"  {name} {cam.id}: no face", file=sys.stderr)
                continue
            P = lm.points[:, :2]
            ij = np.round(P).astype(int)
            inside = (ij[:, 0] >= 0) & (ij[:, 1] >= 0) & (ij[:, 0] < cam.width) & (ij[:, 1] < cam.height)
            surf = np.full((N_LANDMARKS, 3), np.nan)
            ii = np.flatnonzero(inside)
            tri = res.tri_id[ij[ii, 1], ij[ii, 0]]
            hit = tri >= 0
            f = head.mesh.faces[tri[hit]]
            surf[ii[hit]] = (rig.neutral[f] * res.bary[ij[ii[hit], 1], ij[ii[hit], 0]][:, :, None]).sum(1)
            out.append({"expr": name, "cam": cam.id, "mesh": P, "ibug": cam.project(V[ibug]), "surf": surf})
    return out


def build_table_68(samples: list[dict]) -> dict:
    """The 468 -> 68 table from frontal samples (see the module docstring)."""
    P = np.stack([s["mesh"] for s in samples])
    Q = np.stack([s["ibug"] for s in samples])
    scale = np.linalg.norm(P[:, RIGHT_EYE_OUTER] - P[:, LEFT_EYE_OUTER], axis=1)[:, None, None]
    o = P[:, [RIGHT_EYE_OUTER, LEFT_EYE_OUTER]].mean(1, keepdims=True)
    Pn, Qn = (P - o) / scale, (Q - o) / scale
    idx, wts, res = [], [], []
    for j in range(Q.shape[1]):
        i, w = fit_combination(Pn, Qn[:, j])
        idx.append(i.tolist())
        wts.append(np.round(w, 4).tolist())
        res.append(float(np.linalg.norm((Pn[:, i] * w[None, :, None]).sum(1) - Qn[:, j], axis=1).mean()))
    return {"indices": idx, "weights": wts, "fit_error_iod": np.round(res, 4).tolist(), "n_images": len(samples)}


def build_table_ict(rig, samples: list[dict]) -> dict:
    """The 468 -> template neutral table (ICT or any rig rendered the same way) from all samples (see the
    module docstring)."""
    from rigbuild.track.matches import closest_surface_points

    S = np.stack([s["surf"] for s in samples])  # (N, 468, 3)
    n = np.isfinite(S[..., 0]).sum(0)
    med = np.nanmedian(S, axis=0)
    spread = 1.4826 * np.nanmedian(np.linalg.norm(S - med[None], axis=2), axis=0)
    tri, bary, _ = closest_surface_points(med, rig.neutral, rig.faces)
    f = rig.faces[tri]
    vert = f[np.arange(len(f)), np.argmax(bary, 1)]
    return {"vertex": vert.tolist(), "triangle": tri.tolist(), "faces": f.tolist(), "bary": np.round(bary, 5).tolist(),
            "spread_mm": np.round(spread, 3).tolist(), "reliability": np.round(1 / (1 + spread ** 2), 4).tolist(),
            "n_samples": n.tolist(), "rig": rig.name, "n_images": len(samples)}


def _load_template(name: str):
    """The template to build a table for: ICT with the rendered expressions, or ``load_rig(name)``."""
    if name == "ict":
        from rigbuild.io.rigs import read_ict_rig
        from rigbuild.paths import ict_dir

        return read_ict_rig(ict_dir(), expressions=sorted({k for e in EXPRESSIONS.values() for k in e}))
    from rigbuild.io.rigs import load_rig

    return load_rig(name)


def main(argv: list[str] | None = None) -> int:
    """Build the tables (``--skip 68`` / ``--skip table`` leaves one as it is; ``--rig``: the template of the
    468 table; the 68 table is always fitted on ICT)."""
    import argparse

    ap = argparse.ArgumentParser(prog="python -m rigbuild.track.landmark_table", description=__doc__.split("\n")[0])
    ap.add_argument("--skip", action="append", default=[], choices=["68", "table"])
    ap.add_argument("--rig", default="ict", help="template rig of the 468 table (ict, procedural, a path)")
    a = ap.parse_args(argv)
    skip = set(a.skip)
    from rigbuild.io.atomic import write_json
    from rigbuild.track.landmark_views import sphere_cameras, template_head
    from rigbuild.track.landmarks import FaceLandmarker

    landmarker = FaceLandmarker()
    ASSET_DIR.mkdir(parents=True, exist_ok=True)
    if "table" not in skip:
        rig = _load_template(a.rig)
        expr = {k: e for k, e in EXPRESSIONS.items() if all(n in rig.shape_names for n in e)}
        wide = sphere_cameras(rig.neutral[rig.landmarks].mean(0), *zip(*WIDE_VIEWS))
        sall = _sample_views(rig, lambda V: template_head(rig, V), wide, landmarker, expr)
        tab = build_table_ict(rig, sall)
        tab["source"] = (f"python -m rigbuild.track.landmark_table --rig {a.rig}: {len(sall)} renders of the "
                         f"template, views {WIDE_VIEWS}, expressions {list(expr)}")
        write_json(table_path(rig.name), tab, indent=None)
        print(f"{rig.name} table: spread median {np.median(tab['spread_mm']):.2f} mm, "
              f"90th pct {np.percentile(tab['spread_mm'], 90):.2f} mm")
    if "68" not in skip:
        rig = _load_template("ict")
        frontal = sphere_cameras(rig.neutral[rig.landmarks].mean(0), *zip(*FRONTAL_VIEWS))
        s68 = _sample_views(rig, lambda V: template_head(rig, V), frontal, landmarker, EXPRESSIONS)
        t68 = build_table_68(s68)
        t68["source"] = ("python -m rigbuild.track.landmark_table: NNLS fit over renders of the ICT template "
                         f"({len(s68)} images, views {FRONTAL_VIEWS}, expressions {list(EXPRESSIONS)}) to "
                         "ICT-FaceKit's Multi-PIE 68 vertex list with the README's jawline substitutes")
        write_json(TABLE_68, t68, indent=None)
        e = np.asarray(t68["fit_error_iod"])
        print(f"68 table: mean fit error {e.mean():.4f} IOD (max {e.max():.4f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())

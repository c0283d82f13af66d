"""Tests of the procedural head rig (rigbuild.assets.head)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from rigbuild.assets.head import C0, procedural_head_rig
from rigbuild.assets.markers import MULTIPIE_MIRROR, mirror_name
from rigbuild.errors import InputError

ARKIT = {
    "browDown_L", "browDown_R", "browInnerUp_L", "browInnerUp_R", "browOuterUp_L", "browOuterUp_R",
    "cheekPuff_L", "cheekPuff_R", "cheekSquint_L", "cheekSquint_R", "eyeBlink_L", "eyeBlink_R",
    "eyeLookDown_L", "eyeLookDown_R", "eyeLookIn_L", "eyeLookIn_R", "eyeLookOut_L", "eyeLookOut_R",
    "eyeLookUp_L", "eyeLookUp_R", "eyeSquint_L", "eyeSquint_R", "eyeWide_L", "eyeWide_R", "jawForward",
    "jawLeft", "jawOpen", "jawRight", "mouthClose", "mouthDimple_L", "mouthDimple_R", "mouthFrown_L",
    "mouthFrown_R", "mouthFunnel", "mouthLeft", "mouthLowerDown_L", "mouthLowerDown_R", "mouthPress_L",
    "mouthPress_R", "mouthPucker", "mouthRight", "mouthRollLower", "mouthRollUpper", "mouthShrugLower",
    "mouthShrugUpper", "mouthSmile_L", "mouthSmile_R", "mouthStretch_L", "mouthStretch_R",
    "mouthUpperUp_L", "mouthUpperUp_R", "noseSneer_L", "noseSneer_R", "tongueOut",
}  # fmt: skip
REQUIRED = [
    "jawOpen", "jawLeft", "jawRight", "jawForward", "mouthSmile_L", "mouthSmile_R", "mouthFrown_L",
    "mouthFrown_R", "mouthPucker", "mouthFunnel", "mouthStretch_L", "mouthStretch_R", "mouthClose",
    "mouthRollLower", "cheekPuff_L", "cheekPuff_R", "eyeBlink_L", "eyeBlink_R", "eyeWide_L", "eyeWide_R",
    "eyeSquint_L", "eyeSquint_R", "browInnerUp_L", "browInnerUp_R", "browOuterUp_L", "browOuterUp_R",
    "browDown_L", "browDown_R", "noseSneer_L", "noseSneer_R",
]  # fmt: skip
MIRROR = np.array([-1.0, 1.0, 1.0])


@pytest.fixture(scope="module")
def rig():
    return procedural_head_rig()


@pytest.fixture(scope="module")
def mirror_map(rig):
    """Independent mirror map from positions: vertex j = mirror image of vertex i (KD-tree, < 1e-6 mm)."""
    dist, idx = cKDTree(rig.neutral).query(rig.neutral * MIRROR)
    return dist, idx


def _edges(faces):
    return np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])


def _loops(faces):
    """Boundary loops (lists of vertex ids) from the directed boundary edges."""
    e = _edges(faces)
    key = np.sort(e, 1)
    _, inv, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    bnd = e[cnt[inv.ravel()] == 1]
    nxt = dict(zip(bnd[:, 0].tolist(), bnd[:, 1].tolist()))
    loops, seen = [], set()
    for start in nxt:
        if start in seen:
            continue
        loop, v = [], start
        while v not in seen:
            seen.add(v)
            loop.append(v)
            v = nxt[v]
        loops.append(loop)
    return loops


def _angles(v, f):
    out = []
    for k in range(3):
        a = v[f[:, (k + 1) % 3]] - v[f[:, k]]
        b = v[f[:, (k + 2) % 3]] - v[f[:, k]]
        c = (a * b).sum(1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
        out.append(np.degrees(np.arccos(np.clip(c, -1, 1))))
    return np.stack(out, 1)


def _margins(v, loop):
    """Split an opening's loop at its extreme-x corners into (upper, lower) vertex paths."""
    loop = np.asarray(loop)
    a, b = int(np.argmin(v[loop, 0])), int(np.argmax(v[loop, 0]))
    i, j = sorted((a, b))
    p1 = loop[i : j + 1]
    p2 = np.concatenate([loop[j:], loop[: i + 1]])
    return (p1, p2) if v[p1, 1].mean() > v[p2, 1].mean() else (p2, p1)


def _point_polyline_distance(p, poly):
    """Distance of each point p (N, 3) to the polyline poly (M, 3)."""
    a, b = poly[:-1], poly[1:]
    ab = b - a
    t = np.clip(((p[:, None] - a[None]) * ab[None]).sum(-1) / (ab * ab).sum(-1)[None], 0, 1)
    q = a[None] + t[..., None] * ab[None]
    return np.linalg.norm(p[:, None] - q, axis=-1).min(1)


def _weights(rig, **w):
    x = np.zeros(rig.n_shapes)
    for k, val in w.items():
        x[rig.shape_index(k)] = val
    return x


# ---------------------------------------------------------------------------------------- geometry
def test_size_units_and_frame(rig):
    v = rig.neutral
    assert rig.units == "mm" and rig.name == "procedural"
    assert 5000 <= rig.n_vertices <= 20000
    head = v[v[:, 1] > -120]
    width = np.ptp(head[:, 0])
    assert 145.0 <= width <= 165.0
    chin = v[rig.face_region, 1].min()
    assert 220.0 <= v[:, 1].max() - chin <= 240.0
    # the face looks down +z: nose tip (landmark 30) is the frontmost landmark, eyes above the mouth
    lm = v[rig.landmarks]
    assert np.argmax(lm[:, 2]) == 30
    assert lm[36:48, 1].mean() > lm[48:68, 1].mean() + 50.0
    assert np.linalg.norm(v.mean(0)[[0, 2]]) < 25.0  # origin near the head centre


def test_resolution_scales_vertex_count():
    n1 = procedural_head_rig(resolution=1).n_vertices
    n2 = procedural_head_rig(resolution=2).n_vertices
    assert 5000 <= n1 < n2 <= 20000
    assert 1.6 < n2 / n1 < 2.2
    with pytest.raises(InputError):
        procedural_head_rig(resolution=7)


def test_faces_valid_manifold_oriented(rig):
    f = rig.faces
    assert f.min() >= 0 and f.max() < rig.n_vertices
    assert np.all((f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2]))
    assert np.unique(np.sort(f, 1), axis=0).shape[0] == f.shape[0]
    # consistent orientation: every directed edge occurs exactly once
    e = _edges(f)
    assert np.unique(e, axis=0).shape[0] == e.shape[0]
    # every undirected edge has one or two faces
    _, cnt = np.unique(np.sort(e, 1), axis=0, return_counts=True)
    assert set(np.unique(cnt).tolist()) == {1, 2}
    # one connected sphere with three holes: V - E + F = 2 - b = -1, all vertices used
    assert np.unique(f).size == rig.n_vertices
    assert rig.n_vertices - cnt.size + f.shape[0] == -1


def test_boundary_loops_are_the_three_openings(rig):
    v = rig.neutral
    loops = _loops(rig.faces)
    assert len(loops) == 3
    n_boundary_edges = (np.unique(np.sort(_edges(rig.faces), 1), axis=0, return_counts=True)[1] == 1).sum()
    assert sum(len(l) for l in loops) == n_boundary_edges
    centres = np.array([v[l].mean(0) for l in loops])
    order = np.argsort(centres[:, 1])
    mouth, eye_a, eye_b = (centres[i] for i in order)
    assert abs(mouth[0]) < 1e-6 and mouth[1] < eye_a[1] - 50.0
    assert abs(eye_a[1] - eye_b[1]) < 1e-6 and abs(eye_a[0] + eye_b[0]) < 1e-6 and abs(eye_a[0]) > 20.0
    widths = sorted(np.ptp(v[l, 0]) for l in loops)
    assert 22.0 < widths[0] <= widths[1] < 34.0  # eyes
    assert 40.0 < widths[2] < 60.0  # mouth


def test_no_degenerate_triangles(rig):
    v, f = rig.neutral, rig.faces
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    assert area.min() > 1.0  # mm^2
    ang = _angles(v, f).min(1)
    assert ang.min() > 12.0  # degrees
    assert np.percentile(ang, 5) > 30.0


def test_outward_normals(rig):
    v, f = rig.neutral, rig.faces
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    # star-shaped around C0: every face normal points away from C0
    assert np.all((n * (v[f].mean(1) - C0)).sum(1) > 0.0)
    vol = np.einsum("ij,ij->i", v[f[:, 0]] - C0, np.cross(v[f[:, 1]] - C0, v[f[:, 2]] - C0)).sum() / 6.0
    assert 2.5e6 < vol < 6e6  # mm^3, a head with a neck


def test_neutral_is_mirror_symmetric(rig, mirror_map):
    dist, idx = mirror_map
    assert dist.max() < 1e-6
    assert np.array_equal(idx[idx], np.arange(rig.n_vertices))


# ---------------------------------------------------------------------------------------- shapes
def test_shapes_arkit_named(rig):
    assert rig.n_shapes >= 20
    assert set(rig.shape_names) <= ARKIT
    assert set(REQUIRED) <= set(rig.shape_names)
    assert rig.deltas.shape == (rig.n_shapes, rig.n_vertices, 3)


def test_every_delta_local_and_nonzero(rig):
    v = rig.neutral
    back = v[:, 2] < -40.0
    for k, name in enumerate(rig.shape_names):
        mag = np.linalg.norm(rig.deltas[k], axis=1)
        assert mag.max() > 1.0, name
        assert mag.max() < 25.0, name
        assert mag[back].max() == 0.0, name
        moved = mag > 1e-9
        assert moved.mean() < 0.3, name
        if name.startswith("jaw"):
            # the jaw carries the skin under the chin along; the skull and the lower neck stay
            assert mag[(v[:, 1] > 0.0) | (v[:, 1] < -150.0)].max() == 0.0, name
        else:  # the motion sits on the face
            assert np.isin(np.flatnonzero(mag > 0.5), rig.face_region).mean() > 0.6, name


def test_left_right_mirror_symmetry(rig, mirror_map):
    _, idx = mirror_map
    names = rig.shape_names
    pairs = [(n, n[:-2] + "_R") for n in names if n.endswith("_L")] + [("jawLeft", "jawRight"), ("mouthLeft", "mouthRight")]
    assert len(pairs) >= 12
    for a, b in pairs:
        da, db = rig.deltas[rig.shape_index(a)], rig.deltas[rig.shape_index(b)]
        assert np.abs(da[idx] * MIRROR - db).max() < 1e-6, (a, b)
        assert np.linalg.norm(da, axis=1).max() > 1.0
    # the actor's left shapes move the +x side
    blink = np.linalg.norm(rig.deltas[rig.shape_index("eyeBlink_L")], axis=1)
    assert rig.neutral[blink > 0.5, 0].min() > 0.0
    unpaired = [n for n in names if not n.endswith(("_L", "_R")) and n not in dict(pairs) and n not in dict(pairs).values()]
    assert "jawOpen" in unpaired and "mouthPucker" in unpaired
    for n in unpaired:
        d = rig.deltas[rig.shape_index(n)]
        assert np.abs(d[idx] * MIRROR - d).max() < 1e-6, n


@pytest.mark.parametrize("side", ["L", "R"])
def test_blink_closes_the_eye(rig, side):
    v0 = rig.neutral
    loops = _loops(rig.faces)
    eyes = sorted((l for l in loops if v0[l, 1].mean() > v0[:, 1].mean()), key=lambda l: v0[l, 0].mean())
    loop = eyes[1] if side == "L" else eyes[0]
    upper, lower = _margins(v0, loop)
    gap0 = _point_polyline_distance(v0[upper], v0[lower]).max()
    assert gap0 > 6.0
    v1 = rig.evaluate(_weights(rig, **{f"eyeBlink_{side}": 1.0}))
    gap1 = _point_polyline_distance(v1[upper], v1[lower]).max()
    assert gap1 < 0.5
    # the upper lid does most of the closing (moves down), the lower lid moves a little
    assert (v1[upper, 1] - v0[upper, 1]).min() < -4.0
    assert np.abs(v1[lower] - v0[lower]).max() < 3.0
    # eyeWide opens it further
    vw = rig.evaluate(_weights(rig, **{f"eyeWide_{side}": 1.0}))
    assert _point_polyline_distance(vw[upper], vw[lower]).max() > gap0 + 2.0


def test_jaw_open_opens_mouth(rig):
    v0 = rig.neutral
    mouth = min(_loops(rig.faces), key=lambda l: v0[l, 1].mean())
    upper, lower = _margins(v0, mouth)

    def centre_gap(v):
        return v[upper[np.argmin(np.abs(v0[upper, 0]))], 1] - v[lower[np.argmin(np.abs(v0[lower, 0]))], 1]

    g0 = centre_gap(v0)
    assert 1.0 < g0 < 5.0
    v1 = rig.evaluate(_weights(rig, jawOpen=1.0))
    assert centre_gap(v1) - g0 > 10.0
    d = np.linalg.norm(v1 - v0, axis=1)
    assert 12.0 < d.max() < 22.0
    # upper lip and forehead stay; chin moves down and back
    assert d[upper[np.abs(v0[upper, 0]) < 15.0]].max() < 1.0  # the corners are shared and move half
    chin = rig.landmarks[8]
    assert v1[chin, 1] < v0[chin, 1] - 10.0 and v1[chin, 2] < v0[chin, 2]
    # mouthClose brings the lips together
    vc = rig.evaluate(_weights(rig, mouthClose=1.0))
    assert abs(centre_gap(vc)) < 0.2


# ---------------------------------------------------------------------------------------- regions, landmarks, markers
def test_face_region(rig):
    v = rig.neutral
    fr = rig.face_region
    assert 0.2 < fr.size / rig.n_vertices < 0.6
    assert np.all(v[fr, 2] > -10.0)  # no back of the head
    assert v[fr, 1].min() > -122.0  # no neck
    assert v[fr, 1].max() < 70.0  # brows and lower forehead, not the scalp


def test_landmarks(rig):
    lm = rig.landmarks
    assert lm.shape == (68,) and lm.min() >= 0
    assert np.unique(lm).size == 68
    assert np.isin(lm, rig.face_region).all()
    p = rig.neutral[lm]
    # Multi-PIE order: index 0 on the actor's right (-x), the mirror landmark is the mirror image
    assert p[0, 0] < -50 and p[16, 0] > 50 and abs(p[8, 0]) < 1e-6 and np.argmin(p[:17, 1]) == 8
    assert p[36, 0] < p[39, 0] < 0 < p[42, 0] < p[45, 0]
    assert p[48, 0] < p[60, 0] < p[64, 0] < p[54, 0]
    assert p[51, 1] > p[62, 1] > p[66, 1] > p[57, 1]
    assert np.abs(p[MULTIPIE_MIRROR] * MIRROR - p).max() < 1e-6


def test_markers(rig, mirror_map):
    _, idx = mirror_map
    names, mv = rig.marker_names, rig.marker_vertices
    assert 60 <= len(names) <= 100 and len(set(names)) == len(names)
    assert np.unique(mv).size == mv.size
    assert np.isin(mv, rig.face_region).all()
    pos = dict(zip(names, mv))
    for n in names:
        if n.endswith("_C"):
            assert abs(rig.neutral[pos[n], 0]) < 1e-6, n
        else:
            assert idx[pos[n]] == pos[mirror_name(n)], n
    for region in ("brow", "lid", "cheek", "nose", "lip", "jaw", "chin"):
        assert sum(region in n.lower() for n in names) >= 2, region
    # markers spread over the face: nearest-neighbour spacing between 4 and 25 mm
    m = rig.neutral[mv]
    d, _ = cKDTree(m).query(m, k=2)
    assert d[:, 1].min() > 2.5 and np.median(d[:, 1]) < 25.0


def test_uvs(rig):
    uv, fu, v, f = rig.uvs, rig.face_uvs, rig.neutral, rig.faces
    assert fu.shape == f.shape and fu.min() >= 0 and fu.max() < uv.shape[0]
    assert uv.min() >= 0.0 and uv.max() <= 1.0
    # Jacobian of the 3D -> UV map per triangle, in the triangle's own frame
    e1, e2 = v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]
    x = e1 / np.linalg.norm(e1, axis=1, keepdims=True)
    n = np.cross(e1, e2)
    y = np.cross(n / np.linalg.norm(n, axis=1, keepdims=True), x)
    Pm = np.stack([np.stack([(e1 * x).sum(1), (e1 * y).sum(1)], 1), np.stack([(e2 * x).sum(1), (e2 * y).sum(1)], 1)], 1)
    T = np.stack([uv[fu[:, 1]] - uv[fu[:, 0]], uv[fu[:, 2]] - uv[fu[:, 0]]], 1)
    J = np.linalg.solve(Pm, T)
    assert np.all(np.linalg.det(J) > 0)  # no flipped UV triangle
    s = np.linalg.svd(J, compute_uv=False)
    aniso = s[:, 0] / s[:, 1]
    face = np.isin(f, rig.face_region).all(1)
    assert np.percentile(aniso[face], 99) < 1.15 and aniso[face].max() < 1.3
    scale = np.sqrt(s[face, 0] * s[face, 1])
    assert np.percentile(scale, 95) / np.percentile(scale, 5) < 2.5


def test_seed_determinism_and_variation(rig):
    again = procedural_head_rig(seed=0)
    for a, b in [(rig.neutral, again.neutral), (rig.deltas, again.deltas), (rig.faces, again.faces),
                 (rig.uvs, again.uvs), (rig.landmarks, again.landmarks), (rig.marker_vertices, again.marker_vertices)]:  # fmt: skip
        assert np.array_equal(a, b)
    other = procedural_head_rig(seed=1)
    assert other.neutral.shape != rig.neutral.shape or np.abs(other.neutral - rig.neutral).max() > 1.0
    assert other.marker_names == rig.marker_names and other.shape_names == rig.shape_names

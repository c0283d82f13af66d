"""Hand-painted dots: stencil sites moved along the skin as a hand with a stencil places them.

A stencil gives the painter the sites (:func:`rigbuild.dots.painted_dot_vertices`: template vertices), but a
hand does not hit them exactly. :func:`place_painted_dots` moves each dot from its site along the actor's
neutral skin by a 2-D tangent offset ``~ N(0, sigma^2 I)`` (a straightest geodesic walk across the triangles,
so the dot stays on the skin whatever the curvature), drops a fraction of dots (forgotten), and gives each a
diameter and a paint darkness. Each dot is stored as (triangle, barycentric) on the actor's mesh, so it
moves with the skin: :func:`dot_centres` interpolates the deformed triangle of any frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rigbuild.geometry.mesh import vertex_normals


@dataclass
class PaintedDots:
    """Painted dots on a mesh, D of them.

    Attributes
    ----------
    triangles : (D,) int64 triangle of the actor mesh holding each dot.
    triangle_vertices : (D, 3) int64 the triangle's vertex ids (``faces[triangles]``).
    bary : (D, 3) float64 barycentric coordinates in that triangle (sum 1, non-negative).
    radius_mm : (D,) float64 dot radius, mm.
    albedo : (D, 3) uint8 RGB paint colour of each dot.
    site : (D,) int64 index into the ``site_vertices`` the dots were placed from.
    offset_mm : (D, 2) float64 tangent offset drawn for each dot (mm, in the site's tangent frame).
    walked_mm : (D,) float64 length walked along the skin (``|offset|`` unless the walk met a mesh border).
    missing_sites : (X,) int64 sites left unpainted.
    """

    triangles: np.ndarray
    triangle_vertices: np.ndarray
    bary: np.ndarray
    radius_mm: np.ndarray
    albedo: np.ndarray
    site: np.ndarray
    offset_mm: np.ndarray
    walked_mm: np.ndarray
    missing_sites: np.ndarray

    def __len__(self) -> int:
        return int(self.triangles.shape[0])

    def subset(self, index: np.ndarray) -> "PaintedDots":
        """The dots ``index`` (an index or boolean array over the D dots); ``missing_sites`` kept."""
        i = np.asarray(index)
        return PaintedDots(self.triangles[i], self.triangle_vertices[i], self.bary[i], self.radius_mm[i],
                           self.albedo[i], self.site[i], self.offset_mm[i], self.walked_mm[i],
                           self.missing_sites.copy())


def no_dots() -> PaintedDots:
    """An empty :class:`PaintedDots` (``dots: none``: an unpainted face)."""
    z = np.zeros(0, dtype=np.int64)
    return PaintedDots(z, np.zeros((0, 3), np.int64), np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3), np.uint8),
                       z.copy(), np.zeros((0, 2)), np.zeros(0), z.copy())


def dot_centres(painted: PaintedDots, vertices: np.ndarray) -> np.ndarray:
    """World centres of the dots on a deformed mesh: ``vertices`` (V, 3) -> (D, 3), or (F, V, 3) -> (F, D, 3),
    mm (barycentric interpolation of each dot's triangle)."""
    v = np.asarray(vertices, dtype=np.float64)
    corners = v[..., painted.triangle_vertices, :]  # (..., D, 3, 3)
    return np.einsum("...dkc,dk->...dc", corners, painted.bary)


def edge_neighbours(faces: np.ndarray) -> np.ndarray:
    """(F, 3) int64: the triangle across edge ``i`` of each triangle (edge ``i`` joins corners ``i`` and
    ``i + 1``; the corner opposite it is ``i + 2``), -1 on a border. On a non-manifold edge one of the other
    triangles is given."""
    f = np.asarray(faces, dtype=np.int64)
    F = f.shape[0]
    a = f.reshape(-1)
    b = np.roll(f, -1, axis=1).reshape(-1)
    key = np.minimum(a, b) * (int(f.max(initial=0)) + 1) + np.maximum(a, b)
    order = np.argsort(key, kind="stable")
    ks = key[order]
    nb = np.full(3 * F, -1, dtype=np.int64)
    same = ks[1:] == ks[:-1]
    i = np.flatnonzero(same)
    nb[order[i]] = order[i + 1] // 3
    nb[order[i + 1]] = order[i] // 3
    return nb.reshape(F, 3)


def _vertex_faces(n_vertices: int, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """CSR (offsets (V+1,), face ids) of the triangles around each vertex."""
    flat = faces.reshape(-1)
    order = np.argsort(flat, kind="stable")
    counts = np.bincount(flat, minlength=n_vertices)
    return np.concatenate([[0], np.cumsum(counts)]), order // 3


def tangent_frames(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents (N, 3), (N, 3) orthogonal to each unit normal (N, 3) and to each other."""
    n = np.asarray(normals, dtype=np.float64)
    helper = np.zeros_like(n)
    helper[np.arange(n.shape[0]), np.argmin(np.abs(n), axis=1)] = 1.0
    e1 = np.cross(n, helper)
    e1 /= np.maximum(np.linalg.norm(e1, axis=1, keepdims=True), 1e-300)
    return e1, np.cross(n, e1)


def _start_triangle(P: np.ndarray, faces: np.ndarray, fn: np.ndarray, around: np.ndarray, v: int,
                    d: np.ndarray) -> tuple[int, np.ndarray, np.ndarray]:
    """The triangle at vertex ``v`` whose corner wedge holds direction ``d`` (projected to its plane);
    returns (triangle, barycentric at v, unit direction in that triangle's plane)."""
    best, best_score, best_d = -1, -np.inf, d
    for f in around:
        tri = faces[f]
        j = int(np.flatnonzero(tri == v)[0])
        a, b = P[tri[(j + 1) % 3]] - P[v], P[tri[(j + 2) % 3]] - P[v]
        df = d - (d @ fn[f]) * fn[f]
        G = np.array([[a @ a, a @ b], [a @ b, b @ b]])
        try:
            al, be = np.linalg.solve(G, [a @ df, b @ df])
        except np.linalg.LinAlgError:
            continue
        score = min(al, be) / max(abs(al) + abs(be), 1e-300)
        if score > best_score:
            best, best_score, best_d = int(f), score, df
    bary = np.zeros(3)
    bary[int(np.flatnonzero(faces[best] == v)[0])] = 1.0
    return best, bary, best_d / max(np.linalg.norm(best_d), 1e-300)


def walk_on_surface(P: np.ndarray, faces: np.ndarray, neighbours: np.ndarray, fn: np.ndarray, tri: int,
                    bary: np.ndarray, d: np.ndarray, length: float, max_steps: int = 10000
                    ) -> tuple[int, np.ndarray, float]:
    """Walk ``length`` mm along the straightest geodesic from (``tri``, ``bary``) in unit direction ``d`` (in the
    triangle's plane), unfolding the direction about each edge crossed. Stops early at a mesh border.

    P (V, 3) mm, faces (F, 3), neighbours (F, 3) from :func:`edge_neighbours`, fn (F, 3) unit face normals.
    Returns (triangle, barycentric (3,), length walked).
    """
    b = np.asarray(bary, dtype=np.float64).copy()
    remaining = float(length)
    walked = 0.0
    for _ in range(max_steps):
        if remaining <= 0:
            break
        X = P[faces[tri]]
        e1, e2 = X[1] - X[0], X[2] - X[0]
        G = np.array([[e1 @ e1, e1 @ e2], [e1 @ e2, e2 @ e2]])
        al, be = np.linalg.solve(G, [e1 @ d, e2 @ d])
        db = np.array([-al - be, al, be])
        leaving = db < -1e-12
        s = np.full(3, np.inf)
        s[leaving] = np.maximum(b[leaving], 0.0) / -db[leaving]
        i = int(np.argmin(s))
        if s[i] >= remaining:
            b = b + remaining * db
            walked += remaining
            break
        b = b + s[i] * db
        b[i] = 0.0
        walked += s[i]
        remaining -= s[i]
        # corner i reached 0: the exit edge joins corners i + 1 and i + 2, i.e. edge index (i + 1) % 3
        edge = (i + 1) % 3
        g = int(neighbours[tri, edge])
        if g < 0:
            break  # mesh border: the dot stays on it
        va, vb = faces[tri, (i + 1) % 3], faces[tri, (i + 2) % 3]
        ba, bb = b[(i + 1) % 3], b[(i + 2) % 3]
        axis = P[vb] - P[va]
        axis /= max(np.linalg.norm(axis), 1e-300)
        n0, n1 = fn[tri], fn[g]
        ang = np.arctan2(np.cross(n0, n1) @ axis, n0 @ n1)
        K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        Rm = np.eye(3) + np.sin(ang) * K + (1 - np.cos(ang)) * K @ K
        d = Rm @ d
        d = d - (d @ n1) * n1
        d /= max(np.linalg.norm(d), 1e-300)
        nb = np.zeros(3)
        nb[int(np.flatnonzero(faces[g] == va)[0])] = ba
        nb[int(np.flatnonzero(faces[g] == vb)[0])] = bb
        b, tri = nb / nb.sum(), g
    b = np.clip(b, 0.0, None)
    return tri, b / b.sum(), walked


def place_painted_dots(
    actor_rig,
    site_vertices: np.ndarray,
    sigma_mm: float = 2.0,
    missing_fraction: float = 0.05,
    diameter_mm: tuple[float, float] = (2.0, 4.0),
    darkness: tuple[float, float] = (0.75, 0.95),
    seed: int = 0,
    keep_first: int = 0,
) -> PaintedDots:
    """Paint a dot near each stencil site on the actor's neutral skin.

    Parameters
    ----------
    actor_rig : the actor :class:`~rigbuild.rig.Rig` (its neutral and faces; same topology as the template).
    site_vertices : (S,) vertex ids of the stencil sites (e.g. ``painted_dot_vertices(template, spacing)``).
    sigma_mm : standard deviation (mm) of each tangent component of the hand's offset from the site (the
        ``dot_placement_sd_mm`` of the synthetic block). 0: every dot exactly at its site vertex
        (barycentric (1, 0, 0)).
    missing_fraction : fraction of sites left unpainted, ``round(missing_fraction * (S - keep_first))`` of them,
        drawn among sites ``keep_first ...`` (the first ``keep_first`` sites, e.g. the named markers, are
        always painted).
    diameter_mm : (lo, hi): each dot's diameter ~ U(lo, hi) mm (radius half of it).
    darkness : (lo, hi): each dot's paint absorbs a fraction ~ U(lo, hi) of the light; albedo
        ``round(255 * (1 - darkness))`` on R, G and B.
    seed : random seed (offsets, missing sites, sizes and darkness each have their own stream).

    Returns :class:`PaintedDots` with the painted dots in site order.
    """
    sites = np.asarray(site_vertices, dtype=np.int64).reshape(-1)
    if not np.isfinite(sigma_mm) or sigma_mm < 0:
        raise ValueError(f"dot placement sigma must be a non-negative number of mm, got {sigma_mm}")
    if not 0 <= missing_fraction < 1:
        raise ValueError(f"missing_fraction must be in [0, 1), got {missing_fraction}")
    if not 0 < diameter_mm[0] <= diameter_mm[1]:
        raise ValueError(f"diameter_mm must be 0 < lo <= hi, got {diameter_mm}")
    if not 0 <= darkness[0] <= darkness[1] <= 1:
        raise ValueError(f"darkness must be 0 <= lo <= hi <= 1, got {darkness}")
    S = sites.size
    if S == 0:
        return no_dots()
    P = np.asarray(actor_rig.neutral, dtype=np.float64)
    faces = np.asarray(actor_rig.faces, dtype=np.int64)
    offsets = np.random.default_rng([int(seed), 1]).normal(scale=float(sigma_mm), size=(S, 2))
    free = np.arange(min(int(keep_first), S), S)
    n_missing = int(round(missing_fraction * free.size))
    missing = np.sort(np.random.default_rng([int(seed), 2]).choice(free, size=n_missing, replace=False))
    painted = np.setdiff1d(np.arange(S), missing)
    diam = np.random.default_rng([int(seed), 3]).uniform(diameter_mm[0], diameter_mm[1], size=S)
    dark = np.random.default_rng([int(seed), 4]).uniform(darkness[0], darkness[1], size=S)

    fn = np.cross(P[faces[:, 1]] - P[faces[:, 0]], P[faces[:, 2]] - P[faces[:, 0]])
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)
    neighbours = edge_neighbours(faces)
    offs, vf = _vertex_faces(P.shape[0], faces)
    vn = vertex_normals(P, faces)
    e1, e2 = tangent_frames(vn[sites])
    tris = np.empty(painted.size, dtype=np.int64)
    bary = np.empty((painted.size, 3))
    walked = np.zeros(painted.size)
    for out, s in enumerate(painted):
        v = int(sites[s])
        around = vf[offs[v]:offs[v + 1]]
        if around.size == 0:
            raise ValueError(f"stencil site vertex {v} belongs to no triangle")
        length = float(np.hypot(*offsets[s]))
        if length == 0:
            tri = int(around[0])
            b = np.zeros(3)
            b[int(np.flatnonzero(faces[tri] == v)[0])] = 1.0
            tris[out], bary[out] = tri, b
            continue
        d = (offsets[s, 0] * e1[s] + offsets[s, 1] * e2[s]) / length
        tri, b, d = _start_triangle(P, faces, fn, around, v, d)
        tris[out], bary[out], walked[out] = walk_on_surface(P, faces, neighbours, fn, tri, b, d, length)
    albedo = np.repeat(np.round(255 * (1 - dark[painted]))[:, None], 3, axis=1).astype(np.uint8)
    return PaintedDots(triangles=tris, triangle_vertices=faces[tris], bary=bary, radius_mm=diam[painted] / 2,
                       albedo=albedo, site=painted, offset_mm=offsets[painted], walked_mm=walked,
                       missing_sites=missing)

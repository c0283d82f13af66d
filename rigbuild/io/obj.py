"""Minimal, fast Wavefront OBJ reading and writing (positions, UVs, polygon faces)."""

from __future__ import annotations

import io
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rigbuild.errors import InputError
from rigbuild.io.atomic import atomic_path


@dataclass
class ObjMesh:
    """vertices (V, 3); uvs (T, 2) or None; faces (F, 3) triangles; face_uvs (F, 3) or None;
    face_text: the file's ``f`` lines as written (bytes, one per line; a cheap same-face-list test before
    :func:`face_vertex_lists` parses them)."""

    vertices: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray | None = None
    face_uvs: np.ndarray | None = None
    face_text: bytes = b""


def face_vertex_lists(face_text: bytes) -> list[tuple[int, ...]]:
    """The vertex indices (as written, 1-based or negative) of every polygon in ``f`` lines ``face_text``."""
    return [tuple(int(c.split(b"/")[0]) for c in line.split()[1:]) for line in face_text.splitlines() if line.strip()]


def _floats(lines: list[bytes], ncols: int, path: Path) -> np.ndarray:
    if not lines:
        return np.zeros((0, ncols))
    # strip the 2-3 character tag and parse the rest in one go
    body = b"\n".join(l.split(None, 1)[1] for l in lines)
    arr = np.loadtxt(io.BytesIO(body), dtype=np.float64, ndmin=2, usecols=range(ncols))
    if not np.all(np.isfinite(arr)):
        raise InputError("non-finite coordinates", path=path)
    return arr


def read_obj(path: str | os.PathLike, positions_only: bool = False) -> ObjMesh:
    """Read an OBJ. Polygons are fan-triangulated; indices become 0-based.

    ``positions_only`` skips parsing faces and UVs (used for the many same-topology expression OBJs); the
    ``f`` lines are still kept as ``face_text`` so that a reader can check a shape's face list against its
    neutral's.
    """
    path = Path(path)
    if not path.exists():
        raise InputError("OBJ file not found", path=path)
    v, vt, f = [], [], []
    with open(path, "rb") as fh:
        for line in fh:
            if line.startswith(b"v "):
                v.append(line)
            elif line.startswith(b"f "):
                f.append(line)
            elif line.startswith(b"vt ") and not positions_only:
                vt.append(line)
    try:
        verts = _floats(v, 3, path)
    except ValueError as exc:
        raise InputError(f"malformed vertex line ({exc})", path=path) from None
    if verts.shape[0] == 0:
        raise InputError("no vertices ('v' lines) in OBJ", path=path, fix="check the file is a complete OBJ")
    face_text = b"".join(f)
    if positions_only:
        return ObjMesh(verts, np.zeros((0, 3), np.int64), face_text=face_text)
    uvs = _floats(vt, 2, path) if vt else None
    tri_v, tri_t = [], []
    has_uv = uvs is not None
    for line in f:
        corners = line.split()[1:]
        vi = [int(c.split(b"/")[0]) for c in corners]
        if has_uv:
            parts = [c.split(b"/") for c in corners]
            ti = [int(p[1]) if len(p) > 1 and p[1] else 0 for p in parts]
        for k in range(1, len(vi) - 1):
            tri_v.append((vi[0], vi[k], vi[k + 1]))
            if has_uv:
                tri_t.append((ti[0], ti[k], ti[k + 1]))
    faces = np.asarray(tri_v, dtype=np.int64).reshape(-1, 3)
    faces = np.where(faces > 0, faces - 1, faces + verts.shape[0])
    if faces.size and (faces.min() < 0 or faces.max() >= verts.shape[0]):
        raise InputError("face index outside the vertex list", path=path)
    face_uvs = None
    if has_uv and tri_t:
        face_uvs = np.asarray(tri_t, dtype=np.int64).reshape(-1, 3)
        face_uvs = np.where(face_uvs > 0, face_uvs - 1, face_uvs + uvs.shape[0])
        if face_uvs.min() < 0:
            face_uvs = None
    return ObjMesh(verts, faces, uvs, face_uvs, face_text)


def write_obj(
    path: str | os.PathLike,
    vertices: np.ndarray,
    faces: np.ndarray,
    uvs: np.ndarray | None = None,
    face_uvs: np.ndarray | None = None,
    header: str = "",
) -> None:
    """Write a triangle OBJ atomically (``%.6f`` positions). ``header`` lines become comments."""
    buf = io.StringIO()
    for line in header.splitlines():
        buf.write(f"# {line}\n")
    np.savetxt(buf, np.asarray(vertices), fmt="v %.6f %.6f %.6f")
    f1 = np.asarray(faces, dtype=np.int64) + 1
    if uvs is not None and face_uvs is not None:
        np.savetxt(buf, np.asarray(uvs), fmt="vt %.6f %.6f")
        t1 = np.asarray(face_uvs, dtype=np.int64) + 1
        both = np.stack([f1, t1], axis=2).reshape(-1, 6)
        np.savetxt(buf, both, fmt="f %d/%d %d/%d %d/%d")
    else:
        np.savetxt(buf, f1, fmt="f %d %d %d")
    with atomic_path(path) as tmp:
        tmp.write_text(buf.getvalue(), encoding="utf-8")

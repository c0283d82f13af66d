"""Binary little-endian PLY: point clouds (positions, normals, colours) and triangle meshes.

Written with numpy (no open3d needed); read back by :func:`read_ply` (which reads this writer's output
and other binary/ASCII PLYs with float/double/uchar/int vertex properties and list faces).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from rigbuild.errors import InputError
from rigbuild.io.atomic import atomic_path

_NP = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2", "ushort": "u2",
       "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4",
       "double": "f8", "float64": "f8"}


def write_ply(path: str | os.PathLike, vertices: np.ndarray, faces: np.ndarray | None = None,
              normals: np.ndarray | None = None, colors: np.ndarray | None = None) -> None:
    """Write vertices (V, 3) mm [+ normals (V, 3), colours (V, 3) float [0, 1] or uint8, faces (F, 3)]
    atomically as binary little-endian PLY (float32 positions/normals, uchar colours, int32 faces)."""
    V = np.asarray(vertices, np.float64).reshape(-1, 3)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    cols = [V.astype(np.float32)]
    if normals is not None:
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
        cols.append(np.asarray(normals, np.float32).reshape(-1, 3))
    if colors is not None:
        c = np.asarray(colors)
        if c.dtype != np.uint8:
            c = np.rint(np.clip(c, 0, 1) * 255).astype(np.uint8)
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
        cols.append(c.reshape(-1, 3))
    rec = np.empty(len(V), dtype=fields)
    k = 0
    for arr in cols:
        for j in range(3):
            rec[fields[k][0]] = arr[:, j]
            k += 1
    names = {"<f4": "float", "u1": "uchar"}
    header = ["ply", "format binary_little_endian 1.0", "comment rigbuild units mm", f"element vertex {len(V)}"]
    header += [f"property {names[t]} {n}" for n, t in fields]
    F = None if faces is None else np.asarray(faces, np.int64).reshape(-1, 3)
    if F is not None:
        header += [f"element face {len(F)}", "property list uchar int vertex_indices"]
    header.append("end_header")
    with atomic_path(path, suffix=".ply") as tmp:
        with open(tmp, "wb") as fh:
            fh.write(("\n".join(header) + "\n").encode("ascii"))
            fh.write(rec.tobytes())
            if F is not None:
                frec = np.empty(len(F), dtype=[("n", "u1"), ("i", "<i4", (3,))])
                frec["n"] = 3
                frec["i"] = F
                fh.write(frec.tobytes())


def read_ply(path: str | os.PathLike) -> dict:
    """Read a PLY -> dict ``vertices`` (V, 3) float64, ``faces`` (F, 3) int64 (triangles; polygons are
    fanned), and ``normals`` (V, 3) / ``colors`` (V, 3) uint8 when present."""
    path = Path(path)
    if not path.exists():
        raise InputError("PLY file not found", path=path)
    raw = path.read_bytes()
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise InputError("not a PLY file", path=path)
    body_start = raw.index(b"\n", end) + 1
    lines = raw[:end].decode("ascii", "replace").splitlines()
    fmt = next((l.split()[1] for l in lines if l.startswith("format")), "ascii")
    elements = []  # (name, count, [(prop, dtype) | ("list", count_t, item_t, name)])
    for l in lines:
        p = l.split()
        if not p:
            continue
        if p[0] == "element":
            elements.append((p[1], int(p[2]), []))
        elif p[0] == "property" and elements:
            if p[1] == "list":
                elements[-1][2].append(("list", _NP[p[2]], _NP[p[3]], p[4]))
            else:
                elements[-1][2].append((p[2], _NP[p[1]]))
    out: dict = {"vertices": np.zeros((0, 3)), "faces": np.zeros((0, 3), np.int64)}
    if fmt == "ascii":
        tokens = raw[body_start:].split()
        pos = 0
        for name, count, props in elements:
            if name == "vertex":
                nprop = len(props)
                arr = np.array(tokens[pos:pos + nprop * count], dtype=np.float64).reshape(count, nprop)
                pos += nprop * count
                cols = {p[0]: arr[:, k] for k, p in enumerate(props)}
                _vertex_fields(out, cols)
            elif name == "face":
                tris = []
                for _ in range(count):
                    n = int(tokens[pos])
                    idx = [int(t) for t in tokens[pos + 1:pos + 1 + n]]
                    pos += 1 + n
                    tris += [(idx[0], idx[k], idx[k + 1]) for k in range(1, n - 1)]
                out["faces"] = np.asarray(tris, np.int64).reshape(-1, 3)
        return out
    endian = "<" if fmt == "binary_little_endian" else ">"
    pos = body_start
    for name, count, props in elements:
        if all(p[0] != "list" for p in props):
            dt = np.dtype([(p[0], endian + p[1]) for p in props])
            arr = np.frombuffer(raw, dtype=dt, count=count, offset=pos)
            pos += dt.itemsize * count
            if name == "vertex":
                _vertex_fields(out, {n: arr[n].astype(np.float64) for n in dt.names})
        elif name == "face" and len(props) == 1:
            _, ct, it, _ = props[0]
            dt = np.dtype([("n", endian + ct), ("i", endian + it, (3,))])
            arr = np.frombuffer(raw, dtype=dt, count=count, offset=pos)
            if count and np.all(arr["n"] == 3):
                out["faces"] = arr["i"].astype(np.int64)
                pos += dt.itemsize * count
            else:
                raise InputError("only triangle faces are supported in binary PLY", path=path)
        else:
            raise InputError(f"unsupported PLY element '{name}'", path=path)
    return out


def _vertex_fields(out: dict, cols: dict) -> None:
    out["vertices"] = np.stack([cols["x"], cols["y"], cols["z"]], 1)
    if all(k in cols for k in ("nx", "ny", "nz")):
        out["normals"] = np.stack([cols["nx"], cols["ny"], cols["nz"]], 1)
    if all(k in cols for k in ("red", "green", "blue")):
        out["colors"] = np.stack([cols["red"], cols["green"], cols["blue"]], 1).astype(np.uint8)

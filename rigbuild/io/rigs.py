"""Reading and writing blendshape rigs.

Formats:

- ICT-FaceKit ``FaceXModel`` folder (full-shape OBJs in cm, ``vertex_indices.json``): :func:`read_ict_rig`.
- Generic OBJ folder: ``neutral.obj`` + one OBJ per shape (full shapes, same topology), optional
  ``rig.json`` with units / markers / face region: :func:`read_obj_folder_rig`, :func:`write_obj_folder_rig`.
- npz with the keys of ``ground_truth/actor_rig.npz`` (``neutral``, ``deltas``, ``shape_names``, ``faces``)
  plus optional extras: :func:`read_rig_npz`, :func:`write_rig_npz`.
- ``"procedural"``: the built-in procedural head (:mod:`rigbuild.assets.head`).

:func:`load_rig` picks the reader from a spec string. Every reader returns a :class:`Rig` in mm.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Sequence

import numpy as np

from rigbuild.errors import InputError
from rigbuild.io.atomic import atomic_path, save_npz, write_json
from rigbuild.io.obj import ObjMesh, face_vertex_lists, read_obj, write_obj
from rigbuild.rig import HEAD_FRAME_AXES, Rig

ICT_NEUTRAL = "generic_neutral_mesh.obj"
#: ICT vertex ranges (from its README): face skin and head/neck.
ICT_FACE_VERTICES = (0, 9409)
ICT_NARROW_FACE_VERTICES = (0, 6706)
ICT_HEAD_VERTICES = (0, 11248)


def _json_or_empty(path: Path) -> dict:
    return json.loads(path.read_text()) if path.exists() else {}


def ict_expression_names(folder: Path, meta: dict) -> list[str]:
    """The expressions an ICT folder's rig has: ``vertex_indices.json``'s ``expressions`` (``meta``), else every
    OBJ but the neutral and the identity modes."""
    return list(meta.get("expressions", [])) or sorted(
        p.stem for p in folder.glob("*.obj") if p.name != ICT_NEUTRAL and not p.stem.startswith("identity"))


def obj_folder_shape_names(folder: Path, meta: dict) -> list[str]:
    """The shapes of an OBJ-folder rig: ``rig.json``'s ``shape_names`` (``meta``), else every OBJ but the neutral."""
    return list(meta.get("shape_names") or sorted(p.stem for p in folder.glob("*.obj") if p.name != "neutral.obj"))


def read_shape_positions(path: Path, base: ObjMesh, neutral_name: str) -> np.ndarray:
    """Vertex positions (V, 3) of a shape OBJ ``path`` that must share the neutral ``base``'s topology: the
    same vertex count and the same face list (a shape exported with another vertex order has the count but
    not the faces). InputError naming the file otherwise."""
    mesh = read_obj(path, positions_only=True)
    fix = (f"export every shape with {neutral_name}'s vertex count and order (Blender: Keep Vertex Order; "
           "Maya: export the blendshape targets of the one base mesh)")
    if mesh.vertices.shape != base.vertices.shape:
        raise InputError(f"topology differs from {neutral_name}: {mesh.vertices.shape[0]} vs "
                         f"{base.vertices.shape[0]} vertices", path=path, fix=fix)
    if mesh.face_text != base.face_text:
        mine, theirs = face_vertex_lists(mesh.face_text), face_vertex_lists(base.face_text)
        if mine != theirs:
            first = next((i for i, (a, b) in enumerate(zip(mine, theirs)) if a != b), min(len(mine), len(theirs)))
            got = mine[first] if first < len(mine) else "none"
            want = theirs[first] if first < len(theirs) else "none"
            raise InputError(f"face list differs from {neutral_name}'s ({len(mine)} vs {len(theirs)} faces; face "
                             f"{first + 1}: vertices {got} vs {want}): the shape's vertices are in another order",
                             path=path, fix=fix)
    return mesh.vertices


def read_ict_rig(
    folder: str | os.PathLike,
    identity: Sequence[float] | None = None,
    expressions: Sequence[str] | None = None,
    units: str = "mm",
) -> Rig:
    """Read the ICT Face Model Light from its ``FaceXModel`` folder.

    Parameters
    ----------
    folder : the ``FaceXModel`` folder (``generic_neutral_mesh.obj``, expression OBJs, identityNNN.obj,
        ``vertex_indices.json``).
    identity : coefficients of the identity modes ``identity000.obj ...`` (as many as given); the
        neutral becomes ``neutral + sum_i c_i (identity_i - neutral)``. Expression deltas are unchanged.
    expressions : shape names to load (default: the 53 listed under ``expressions`` in
        ``vertex_indices.json``).
    units : output units (the files are in cm).

    Returns
    -------
    Rig with 26,719 vertices, triangulated faces, UVs, ``face_region`` = vertices 0-9408,
    ``landmarks`` = the 68 Multi-PIE vertex indices.
    """
    folder = Path(folder)
    neutral_path = folder / ICT_NEUTRAL
    if not neutral_path.exists():
        raise InputError(
            f"not an ICT FaceXModel folder (no {ICT_NEUTRAL})",
            path=folder,
            fix="point the rig at ict-facekit/FaceXModel (set $RIGBUILD_DATA)",
        )
    meta = _json_or_empty(folder / "vertex_indices.json")
    names = list(expressions) if expressions is not None else ict_expression_names(folder, meta)
    base = read_obj(neutral_path)
    neutral = base.vertices
    deltas = np.empty((len(names), neutral.shape[0], 3))
    for k, name in enumerate(names):
        p = folder / f"{name}.obj"
        if not p.exists():
            raise InputError(f"expression '{name}' not found", path=p, fix="check the shape name against the folder")
        deltas[k] = read_shape_positions(p, base, ICT_NEUTRAL) - neutral
    if identity is not None:
        for i, c in enumerate(identity):
            p = folder / f"identity{i:03d}.obj"
            if not p.exists():
                raise InputError(f"identity mode {i} not found", path=p, fix=f"use at most {i} identity coefficients")
            neutral = neutral + float(c) * (read_shape_positions(p, base, ICT_NEUTRAL) - base.vertices)
    landmarks = np.asarray(meta.get("idx_to_landmark_verts", []), dtype=np.int64)
    rig = Rig(
        neutral=neutral,
        deltas=deltas,
        shape_names=names,
        faces=base.faces,
        uvs=base.uvs,
        face_uvs=base.face_uvs,
        units="cm",
        name="ict",
        face_region=np.arange(*ICT_FACE_VERTICES),
        landmarks=landmarks if landmarks.size == 68 else None,
    )
    from rigbuild.assets.markers import load_marker_set, marker_set_path

    if marker_set_path("ict").exists():  # the ICT marker set is data shipped with rigbuild
        names, vids = load_marker_set("ict")
        rig = rig.with_markers(names, vids)
    return rig.to_units(units)


def read_obj_folder_rig(folder: str | os.PathLike, units: str | None = None) -> Rig:
    """Read a generic OBJ-folder rig: ``neutral.obj`` + ``<shape>.obj`` per shape (full shapes).

    An optional ``rig.json`` gives ``units`` (default mm), ``shape_names`` (order), ``face_region``,
    ``landmarks``, ``markers`` (``{name: vertex}``), ``name``.
    """
    folder = Path(folder)
    neutral_path = folder / "neutral.obj"
    if not neutral_path.exists():
        raise InputError("OBJ-folder rig needs neutral.obj", path=folder, fix="name the neutral mesh neutral.obj")
    meta = _json_or_empty(folder / "rig.json")
    base = read_obj(neutral_path)
    names = obj_folder_shape_names(folder, meta)
    deltas = np.empty((len(names), base.vertices.shape[0], 3))
    for k, name in enumerate(names):
        p = folder / f"{name}.obj"
        if not p.exists():
            raise InputError(f"shape '{name}' listed in rig.json has no OBJ", path=p)
        deltas[k] = read_shape_positions(p, base, "neutral.obj") - base.vertices
    markers = meta.get("markers", {})
    rig = Rig(
        neutral=base.vertices,
        deltas=deltas,
        shape_names=names,
        faces=base.faces,
        uvs=base.uvs,
        face_uvs=base.face_uvs,
        units=meta.get("units", "mm"),
        name=meta.get("name", folder.name),
        face_region=meta.get("face_region"),
        landmarks=meta.get("landmarks"),
        marker_names=list(markers.keys()),
        marker_vertices=list(markers.values()),
    )
    return rig if units is None else rig.to_units(units)


def write_obj_folder_rig(rig: Rig, folder: str | os.PathLike, extras: dict | None = None) -> None:
    """Write ``neutral.obj``, one full-shape OBJ per shape, and ``rig.json`` (units, names, markers, and
    ``extras``: more keys, e.g. the frame the rig was moved into)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    hdr = f"rigbuild rig '{rig.name}', units {rig.units}"
    write_obj(folder / "neutral.obj", rig.neutral, rig.faces, rig.uvs, rig.face_uvs, header=hdr)
    for name, d in zip(rig.shape_names, rig.deltas):
        write_obj(folder / f"{name}.obj", rig.neutral + d, rig.faces, rig.uvs, rig.face_uvs, header=f"{hdr}, shape {name}")
    write_json(
        folder / "rig.json",
        {
            "name": rig.name,
            "units": rig.units,
            "axes": HEAD_FRAME_AXES,
            "shape_names": rig.shape_names,
            "face_region": None if rig.face_region is None else rig.face_region.tolist(),
            "landmarks": None if rig.landmarks is None else rig.landmarks.tolist(),
            "markers": {n: int(v) for n, v in zip(rig.marker_names, rig.marker_vertices)},
            **(extras or {}),
        },
    )


def write_rig_npz(path: str | os.PathLike, rig: Rig, **extra) -> None:
    """Write a rig npz (keys ``neutral deltas shape_names faces`` + uvs, face_uvs, units, name,
    face_region, landmarks, marker_names, marker_vertices when present) atomically. float32 positions."""
    arrays = dict(
        neutral=rig.neutral.astype(np.float32),
        deltas=rig.deltas.astype(np.float32),
        shape_names=np.asarray(rig.shape_names, dtype=str),
        faces=rig.faces.astype(np.int32),
        units=np.asarray(rig.units),
        name=np.asarray(rig.name),
        marker_names=np.asarray(rig.marker_names, dtype=str),
        marker_vertices=rig.marker_vertices.astype(np.int32),
    )
    for key in ("uvs", "face_uvs", "face_region", "landmarks"):
        v = getattr(rig, key)
        if v is not None:
            arrays[key] = v
    arrays.update(extra)
    save_npz(path, **arrays)


def read_rig_npz(path: str | os.PathLike) -> Rig:
    """Read a rig npz written by :func:`write_rig_npz` (or any npz with the four required keys)."""
    path = Path(path)
    if not path.exists():
        raise InputError("rig npz not found", path=path)
    with np.load(path, allow_pickle=False) as z:
        missing = [k for k in ("neutral", "deltas", "shape_names", "faces") if k not in z]
        if missing:
            raise InputError(f"rig npz lacks keys {missing}", path=path)
        get = lambda k: z[k] if k in z else None  # noqa: E731
        return Rig(
            neutral=z["neutral"].astype(np.float64),
            deltas=z["deltas"].astype(np.float64),
            shape_names=[str(s) for s in z["shape_names"]],
            faces=z["faces"],
            uvs=get("uvs"),
            face_uvs=get("face_uvs"),
            units=str(z["units"]) if "units" in z else "mm",
            name=str(z["name"]) if "name" in z else path.stem,
            face_region=get("face_region"),
            landmarks=get("landmarks"),
            marker_names=[str(s) for s in z["marker_names"]] if "marker_names" in z else [],
            marker_vertices=z["marker_vertices"] if "marker_vertices" in z else np.zeros(0, np.int64),
        )


def load_rig(spec: str | os.PathLike, units: str = "mm", **kwargs) -> Rig:
    """Load a rig from a spec: ``"procedural"``, ``"ict"`` (``$RIGBUILD_DATA/ict-facekit/FaceXModel``),
    an ICT FaceXModel folder, an OBJ folder or an npz.

    Extra keyword arguments go to the reader (``identity=`` for ICT, ``seed=`` etc. for procedural).
    """
    s = str(spec)
    if s == "ict":
        from rigbuild.paths import ict_dir

        folder = ict_dir()
        if not (folder / ICT_NEUTRAL).exists():
            raise InputError("the ICT rig was requested but ICT-FaceKit is not there", path=folder,
                             fix="set RIGBUILD_DATA to the folder holding ict-facekit/")
        return read_ict_rig(folder, units=units, **kwargs)
    if s == "procedural":
        from rigbuild.assets.head import procedural_head_rig

        return procedural_head_rig(**kwargs).to_units(units)
    p = Path(s)
    if not p.exists():
        raise InputError(
            "rig not found",
            path=p,
            fix="give 'procedural', an ICT FaceXModel folder, an OBJ folder with neutral.obj, or a rig .npz",
        )
    if p.is_file() and p.suffix == ".npz":
        return read_rig_npz(p).to_units(units)
    if p.is_dir() and (p / ICT_NEUTRAL).exists():
        return read_ict_rig(p, units=units, **kwargs)
    if p.is_dir():
        return read_obj_folder_rig(p, units=units)
    raise InputError("unrecognized rig format", path=p, fix="use a folder of OBJs or a .npz")


def read_ict_identity_modes(folder: str | os.PathLike, n_modes: int, units: str = "mm") -> np.ndarray:
    """The first ``n_modes`` ICT identity modes as deltas (n_modes, V, 3) in ``units``."""
    from rigbuild.rig import UNIT_TO_MM

    folder = Path(folder)
    base_mesh = read_obj(folder / ICT_NEUTRAL, positions_only=True)
    base = base_mesh.vertices
    modes = []
    for i in range(n_modes):
        p = folder / f"identity{i:03d}.obj"
        if not p.exists():
            raise InputError(f"identity mode {i} not found", path=p, fix=f"use at most {i} identity modes")
        modes.append(read_shape_positions(p, base_mesh, ICT_NEUTRAL) - base)
    return np.asarray(modes) * (UNIT_TO_MM["cm"] / UNIT_TO_MM[units])


def rig_source_files(spec: str | os.PathLike) -> list[str]:
    """The files :func:`load_rig` reads for rig spec ``spec`` (for Snakemake ``input:``, so that editing a
    rig's files reruns the jobs that read it): an npz itself; an OBJ folder's ``neutral.obj``, ``rig.json`` and
    shape OBJs; the ICT folder's neutral, expression OBJs and ``vertex_indices.json`` (plus rigbuild's ICT
    marker set). ``procedural`` is code, not files: ``[]``. A spec that points nowhere gives ``[]`` (the DAG-start
    check names it)."""
    s = str(spec)
    if s == "procedural":
        return []
    if s == "ict":
        from rigbuild.paths import ict_dir

        s = str(ict_dir())
    p = Path(s)
    if p.is_file():
        return [str(p)]
    if not p.is_dir():
        return []
    if (p / ICT_NEUTRAL).exists():
        from rigbuild.assets.markers import marker_set_path

        names = ict_expression_names(p, _json_or_empty(p / "vertex_indices.json"))
        files = [p / ICT_NEUTRAL, *(p / f"{n}.obj" for n in names), p / "vertex_indices.json", marker_set_path("ict")]
    else:
        names = obj_folder_shape_names(p, _json_or_empty(p / "rig.json"))
        files = [p / "neutral.obj", *(p / f"{n}.obj" for n in names), p / "rig.json"]
    return [str(f) for f in files if f.exists()]


def resolve_rig_spec(spec: str | os.PathLike, base: str | os.PathLike) -> str:
    """A rig spec with a relative path made absolute against ``base`` (the workflow folder); ``procedural``,
    ``ict`` and absolute paths unchanged."""
    s = str(spec)
    if s in ("procedural", "ict") or Path(s).is_absolute():
        return s
    return str(Path(base) / s)

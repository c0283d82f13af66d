"""The internal blendshape rig representation shared by every stage.

A rig is a neutral mesh plus K additive shape deltas (delta blendshape model):
``vertices(w) = neutral + sum_k w_k * deltas[k]``.

Readers and writers for the formats (ICT FaceXModel folder, OBJ folder, npz, glTF) live in
:mod:`rigbuild.io.rigs`; the procedural head lives in :mod:`rigbuild.assets.head`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Sequence

import numpy as np

from rigbuild.errors import InputError

UNIT_TO_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0}
#: The head frame every rig file is written in: the template's frame (the ICT frame), which is glTF's too.
#: Its origin is the template head's centre.
HEAD_FRAME_AXES = "right-handed, +y up, +z towards the face's front (glTF convention)"


@dataclass
class Rig:
    """A delta blendshape rig.

    Attributes
    ----------
    neutral : (V, 3) float64, vertex positions in ``units``.
    deltas : (K, V, 3) float64, per-shape displacement from the neutral at weight 1.
    shape_names : K names (ARKit-style, e.g. ``jawOpen``, ``eyeBlink_L``).
    faces : (F, 3) int64 triangle vertex indices (quads are split on load).
    uvs : (T, 2) float64 texture coordinates, or None.
    face_uvs : (F, 3) int64 indices into ``uvs`` per triangle corner, or None.
    units : ``"mm"``, ``"cm"`` or ``"m"``.
    name : free text (``"ict"``, ``"procedural"``, a character name).
    face_region : (R,) int64 vertex indices of the skin of the face (metrics, fitting), or None = all.
    landmarks : (68,) int64 vertex indices of the Multi-PIE 68 landmarks, -1 where undefined, or None.
    marker_names : M marker names (the marker set is data, per rig), or empty.
    marker_vertices : (M,) int64 vertex index of each marker.
    """

    neutral: np.ndarray
    deltas: np.ndarray
    shape_names: list[str]
    faces: np.ndarray
    uvs: np.ndarray | None = None
    face_uvs: np.ndarray | None = None
    units: str = "mm"
    name: str = "rig"
    face_region: np.ndarray | None = None
    landmarks: np.ndarray | None = None
    marker_names: list[str] = field(default_factory=list)
    marker_vertices: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    def __post_init__(self) -> None:
        self.neutral = np.asarray(self.neutral, dtype=np.float64)
        self.deltas = np.asarray(self.deltas, dtype=np.float64)
        self.faces = np.asarray(self.faces, dtype=np.int64)
        self.shape_names = [str(s) for s in self.shape_names]
        self.marker_names = [str(s) for s in self.marker_names]
        self.marker_vertices = np.asarray(self.marker_vertices, dtype=np.int64).reshape(-1)
        if self.deltas.size == 0:
            self.deltas = self.deltas.reshape(0, self.neutral.shape[0], 3)
        for name in ("face_region", "landmarks", "face_uvs"):
            v = getattr(self, name)
            if v is not None:
                setattr(self, name, np.asarray(v, dtype=np.int64))
        if self.uvs is not None:
            self.uvs = np.asarray(self.uvs, dtype=np.float64)
        self.validate()

    # ------------------------------------------------------------------ checks
    def validate(self) -> None:
        """Raise :class:`InputError` if shapes or indices are inconsistent."""
        V = self.neutral.shape[0]
        if self.neutral.ndim != 2 or self.neutral.shape[1] != 3:
            raise InputError(f"rig '{self.name}': neutral must be (V, 3), got {self.neutral.shape}")
        if self.deltas.ndim != 3 or self.deltas.shape[1:] != (V, 3):
            raise InputError(f"rig '{self.name}': deltas must be (K, {V}, 3), got {self.deltas.shape}")
        if len(self.shape_names) != self.deltas.shape[0]:
            raise InputError(
                f"rig '{self.name}': {len(self.shape_names)} shape names for {self.deltas.shape[0]} deltas"
            )
        if len(set(self.shape_names)) != len(self.shape_names):
            dup = sorted({s for s in self.shape_names if self.shape_names.count(s) > 1})
            raise InputError(f"rig '{self.name}': duplicate shape names {dup}")
        if self.faces.ndim != 2 or self.faces.shape[1] != 3:
            raise InputError(f"rig '{self.name}': faces must be (F, 3) triangles, got {self.faces.shape}")
        if self.faces.size and (self.faces.min() < 0 or self.faces.max() >= V):
            raise InputError(f"rig '{self.name}': face indices outside [0, {V})")
        if self.units not in UNIT_TO_MM:
            raise InputError(f"rig '{self.name}': unknown units '{self.units}' (use mm, cm or m)")
        if len(self.marker_names) != self.marker_vertices.shape[0]:
            raise InputError(f"rig '{self.name}': marker names and marker vertices differ in length")
        if self.marker_vertices.size and (self.marker_vertices.min() < 0 or self.marker_vertices.max() >= V):
            raise InputError(f"rig '{self.name}': marker vertex indices outside [0, {V})")
        if not np.all(np.isfinite(self.neutral)) or not np.all(np.isfinite(self.deltas)):
            raise InputError(f"rig '{self.name}': non-finite vertex positions")

    # -------------------------------------------------------------- properties
    @property
    def n_vertices(self) -> int:
        return int(self.neutral.shape[0])

    @property
    def n_shapes(self) -> int:
        return int(self.deltas.shape[0])

    @property
    def face_vertices(self) -> np.ndarray:
        """(R,) vertex indices of the face region (all vertices when undefined)."""
        if self.face_region is None:
            return np.arange(self.n_vertices)
        return self.face_region

    def shape_index(self, name: str) -> int:
        """Index of shape ``name``; :class:`InputError` listing the known names if absent."""
        try:
            return self.shape_names.index(name)
        except ValueError:
            raise InputError(
                f"rig '{self.name}' has no shape '{name}'",
                fix=f"use one of: {', '.join(self.shape_names)}",
            ) from None

    # -------------------------------------------------------------- evaluation
    def evaluate(self, weights: np.ndarray) -> np.ndarray:
        """Vertices for weights.

        weights : (K,) or (F, K). Returns (V, 3) or (F, V, 3) in the rig's units.
        """
        w = np.asarray(weights, dtype=np.float64)
        if w.shape[-1] != self.n_shapes:
            raise InputError(f"rig '{self.name}': {w.shape[-1]} weights for {self.n_shapes} shapes")
        flat = self.deltas.reshape(self.n_shapes, -1)
        out = w @ flat
        return self.neutral + out.reshape(*w.shape[:-1], self.n_vertices, 3)

    def markers(self, vertices: np.ndarray | None = None) -> np.ndarray:
        """Marker positions (M, 3) (or (F, M, 3)) from ``vertices`` (default: the neutral)."""
        v = self.neutral if vertices is None else np.asarray(vertices)
        return v[..., self.marker_vertices, :]

    @property
    def metres_per_unit(self) -> float:
        """The rig's unit in metres (glTF positions are metres)."""
        return UNIT_TO_MM[self.units] / 1000.0

    # -------------------------------------------------------------- transforms
    def transformed(self, R: np.ndarray, t: np.ndarray) -> "Rig":
        """A copy moved rigidly: neutral ``R x + t`` (``t`` (3,) in the rig's units), deltas ``R d``."""
        R = np.asarray(R, dtype=np.float64)
        return replace(self, neutral=self.neutral @ R.T + np.asarray(t, dtype=np.float64),
                       deltas=self.deltas @ R.T)

    def to_units(self, units: str) -> "Rig":
        """A copy converted to ``units`` (``mm``, ``cm`` or ``m``)."""
        if units not in UNIT_TO_MM:
            raise InputError(f"unknown units '{units}' (use mm, cm or m)")
        s = UNIT_TO_MM[self.units] / UNIT_TO_MM[units]
        return replace(self, neutral=self.neutral * s, deltas=self.deltas * s, units=units)

    def subset(self, names: Sequence[str]) -> "Rig":
        """A copy with only the named shapes, in the given order."""
        idx = [self.shape_index(n) for n in names]
        return replace(self, deltas=self.deltas[idx], shape_names=list(names))

    def with_markers(self, names: Sequence[str], vertices: Sequence[int]) -> "Rig":
        """A copy with a marker set attached."""
        return replace(self, marker_names=list(names), marker_vertices=np.asarray(vertices, np.int64))

    def copy(self) -> "Rig":
        return replace(
            self,
            neutral=self.neutral.copy(),
            deltas=self.deltas.copy(),
            shape_names=list(self.shape_names),
            faces=self.faces.copy(),
            marker_names=list(self.marker_names),
            marker_vertices=self.marker_vertices.copy(),
        )


def head_frame_transform(template: Rig, neutral: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """The rigid capture-to-head transform of a neutral mesh ``neutral`` (V, 3) in the cameras' world (the
    template's units): ``(R (3, 3), t (3,), rms)`` with ``x_head = R x_capture + t``, the least-squares rigid fit
    of the face region (``template.face_vertices``) onto the template's neutral, and the fit's RMS distance. No
    scale: the actor keeps their size; the axes and the origin are the template's (:data:`HEAD_FRAME_AXES`)."""
    from rigbuild.geometry.rigid import fit_rigid_motion

    v = template.face_vertices
    x = np.asarray(neutral, dtype=np.float64)
    if x.shape != template.neutral.shape:
        raise InputError(f"neutral is {x.shape}, the template rig '{template.name}' is {template.neutral.shape}")
    R, t = fit_rigid_motion(x[v], template.neutral[v])
    rms = float(np.sqrt(np.mean(np.sum((x[v] @ R.T + t - template.neutral[v]) ** 2, axis=1))))
    return R, t, rms

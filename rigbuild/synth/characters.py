"""Target characters for retargeting tests: the template and stylized variants of it.

Stylized variants change the neutral's proportions strongly (large identity coefficients where the
rig has identity modes, non-uniform scaling, smooth warps). ``exaggerated`` and ``stylized`` carry the
template's expressions over by deformation transfer (Sumner and Popovic 2004), as a studio would build a
character rig with a transfer tool. ``sculpted`` does not: its shapes are re-sculpted per shape as an artist
would (:func:`sculpt_deltas`: region-wise exaggeration with the shape's own falloff and a progressive turn of
its direction) and carried to the stylized neutral by the warp's local linear map (no Poisson solve), so the
operator that the ``deformation`` scale matching and ``fit_guess: deformation`` invert did not make them.

A character of another topology is any other rig passed to :func:`make_character` (the procedural head as a
character for an ICT session, the ICT head for a procedural session: :func:`other_topology_rig`); with
``marker_names`` it carries the session's marker set by name, so retargeting can pair the markers.
"""

from __future__ import annotations

import os
from dataclasses import replace

import numpy as np

from rigbuild.errors import InputError
from rigbuild.rig import Rig
from rigbuild.synth.actor import smooth_random_field

CHARACTER_KINDS = ("template", "exaggerated", "stylized", "sculpted")

#: the rig of the other topology for each built-in template (``make_character`` target for a session)
OTHER_TOPOLOGY = {"ict": "procedural", "procedural": "ict"}


def other_topology_rig(template_rig: str) -> str:
    """The built-in rig spec of the other topology: ``"ict"`` -> ``"procedural"``, ``"procedural"`` -> ``"ict"``."""
    if template_rig not in OTHER_TOPOLOGY:
        raise InputError(f"no built-in rig of another topology for template rig '{template_rig}'",
                         fix=f"use one of {sorted(OTHER_TOPOLOGY)} or name the character's rig explicitly")
    return OTHER_TOPOLOGY[template_rig]


def _rotate_about(v: np.ndarray, axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rotate vectors v (N, 3) about the unit ``axis`` (3,) by per-vector angles (N,) radians (Rodrigues)."""
    c, s_ = np.cos(angle)[:, None], np.sin(angle)[:, None]
    return v * c + np.cross(axis[None], v) * s_ + axis[None] * (v @ axis)[:, None] * (1 - c)


def sculpt_deltas(neutral: np.ndarray, deltas: np.ndarray, seed: int = 0,
                  exaggeration: tuple[float, float] = (0.3, 0.8), turn_deg: tuple[float, float] = (10.0, 25.0),
                  falloff: tuple[float, float] = (0.5, 1.5)) -> tuple[np.ndarray, dict]:
    """Each shape re-sculpted in its own region: (K, V, 3) mm and the draws per shape.

    For shape k with displacement magnitude ``a_v = |delta_k(v)|``, the region's centre ``c_k`` (the
    ``a``-weighted mean of the neutral ``neutral`` (V, 3)) and RMS radius ``r_k``: a falloff
    ``phi(v) = exp(-|x_v - c_k|^2 / (2 (s_k r_k)^2))`` with its own width ``s_k ~ U(falloff)``; the delta is
    exaggerated by ``1 + e_k phi(v)``, ``e_k ~ U(exaggeration)``, and its direction turned about a random axis
    by ``theta_k phi(v)``, ``theta_k ~ U(turn_deg)`` degrees (most at the shape's core, fading outwards).
    Zero deltas stay zero. Deterministic per ``seed`` (one stream per shape).
    """
    P = np.asarray(neutral, dtype=np.float64)
    out = np.array(deltas, dtype=np.float64, copy=True)
    K = out.shape[0]
    draws = {"exaggeration": np.zeros(K), "turn_deg": np.zeros(K), "falloff": np.zeros(K)}
    for k in range(K):
        rng = np.random.default_rng([int(seed), k, 0x5C])
        e, th, sw = rng.uniform(*exaggeration), rng.uniform(*turn_deg), rng.uniform(*falloff)
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        a = np.linalg.norm(out[k], axis=1)
        if a.sum() <= 0:
            continue
        c = (a[:, None] * P).sum(0) / a.sum()
        r = np.sqrt((a * ((P - c) ** 2).sum(1)).sum() / a.sum())
        phi = np.exp(-((P - c) ** 2).sum(1) / (2 * (sw * max(r, 1e-9)) ** 2))
        out[k] = _rotate_about(out[k], axis, np.radians(th) * phi) * (1 + e * phi)[:, None]
        draws["exaggeration"][k], draws["turn_deg"][k], draws["falloff"][k] = e, th, sw
    return out, draws


def warp_linear_maps(reference: np.ndarray, target: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Per-vertex linear maps (V, 3, 3) of the warp ``reference -> target`` (same topology): the area-weighted
    mean of the deformation gradients of the triangles around each vertex (identity for an unused vertex)."""
    from rigbuild.geometry.deformation_transfer import deformation_gradients

    ref = np.asarray(reference, dtype=np.float64)
    T = deformation_gradients(ref, np.asarray(target, dtype=np.float64), faces)  # (F, 3, 3)
    area = 0.5 * np.linalg.norm(np.cross(ref[faces[:, 1]] - ref[faces[:, 0]], ref[faces[:, 2]] - ref[faces[:, 0]]), axis=1)
    V = ref.shape[0]
    J = np.zeros((V, 9))
    wsum = np.zeros(V)
    Tw = T.reshape(-1, 9) * area[:, None]
    for j in range(3):
        np.add.at(J, faces[:, j], Tw)
        np.add.at(wsum, faces[:, j], area)
    J = np.where(wsum[:, None] > 0, J / np.maximum(wsum, 1e-300)[:, None], np.eye(3).reshape(1, 9))
    return J.reshape(V, 3, 3)


def _with_marker_names(rig: Rig, marker_names) -> Rig:
    """``rig`` with its markers reordered (and restricted) to ``marker_names``; InputError for a missing name."""
    index = {n: i for i, n in enumerate(rig.marker_names)}
    missing = [n for n in marker_names if n not in index]
    if missing:
        raise InputError(f"character rig '{rig.name}' lacks the session's markers {missing}",
                         fix="give the character a marker set with the session's names (config characters: markers:)")
    return rig.with_markers(list(marker_names), [int(rig.marker_vertices[index[n]]) for n in marker_names])


def stylize_neutral(neutral: np.ndarray, kind: str, seed: int = 0, face_vertices: np.ndarray | None = None,
                    identity_modes: np.ndarray | None = None) -> np.ndarray:
    """A stylized neutral (V, 3) mm.

    ``exaggerated``: identity modes with large coefficients (|c| 2.5-3.5, when given) and non-uniform
    scaling (x 1.15, y 0.92, z 1.08 about the face centroid).
    ``stylized``: a cartoon warp: upper face (eyes and brows) enlarged 1.25x, lower face compressed to
    0.85x height, a 12 mm smooth bump field, and the whole head 1.3x wider than deep.
    """
    rng = np.random.default_rng(seed)
    fv = np.arange(neutral.shape[0]) if face_vertices is None else face_vertices
    c = neutral[fv].mean(0)
    p = neutral - c
    if kind == "exaggerated":
        out = neutral.copy()
        if identity_modes is not None and len(identity_modes):
            coeffs = rng.uniform(2.5, 3.5, size=len(identity_modes)) * rng.choice([-1, 1], size=len(identity_modes))
            out = out + np.tensordot(coeffs, identity_modes, axes=1)
        return c + (out - c) * np.array([1.15, 0.92, 1.08])
    if kind == "stylized":
        y = p[:, 1]
        eye_level = np.percentile(y[fv], 60)
        s_up = 1 + 0.25 * (0.5 + 0.5 * np.tanh((y - eye_level) / 15.0))
        s_down = 1 - 0.15 * (0.5 + 0.5 * np.tanh((eye_level - 40.0 - y) / 15.0))
        q = p.copy()
        q[:, 0] *= s_up * 1.3
        q[:, 1] = np.where(y > eye_level, eye_level + (y - eye_level) * s_up, eye_level + (y - eye_level) * s_down)
        q[:, 2] *= s_up
        radial = p / np.maximum(np.linalg.norm(p, axis=1, keepdims=True), 1e-9)
        q += 12.0 * smooth_random_field(neutral, rng)[:, None] * radial
        return c + q
    raise InputError(f"unknown character kind '{kind}'", fix=f"use one of {CHARACTER_KINDS}")


def make_character(template: Rig, kind: str, seed: int = 0,
                   identity_folder: str | os.PathLike | None = None, n_identity_modes: int = 5,
                   marker_names: list[str] | None = None) -> Rig:
    """A character rig from ``template``: ``"template"`` (a copy), ``"exaggerated"``, ``"stylized"`` or
    ``"sculpted"``.

    Expressions of ``exaggerated`` and ``stylized`` come from deformation transfer of the template's shapes
    onto the new neutral; ``sculpted`` has the ``stylized`` neutral and shapes from :func:`sculpt_deltas`
    carried by :func:`warp_linear_maps` (``J_v delta'_k(v)``), no deformation transfer. Markers, landmarks,
    face region and names are kept (same topology as ``template``, which may be another topology than the
    session's: see the module docstring). ``marker_names``: reorder the character's markers to these names
    (the session's marker set); InputError when the rig lacks one.
    """
    out = _make_character(template, kind, seed, identity_folder, n_identity_modes)
    return out if marker_names is None else _with_marker_names(out, marker_names)


def _make_character(template: Rig, kind: str, seed: int, identity_folder, n_identity_modes: int) -> Rig:
    if kind == "template":
        return replace(template.copy(), name="template")
    if kind == "sculpted":
        neutral = stylize_neutral(template.neutral, "stylized", seed, template.face_region)
        sculpt, _ = sculpt_deltas(template.neutral, template.deltas, seed)
        J = warp_linear_maps(template.neutral, neutral, template.faces)
        deltas = np.einsum("vij,kvj->kvi", J, sculpt)
        return replace(template.copy(), neutral=neutral, deltas=deltas, name=kind)
    modes = None
    if kind == "exaggerated" and identity_folder is not None:
        from rigbuild.io.rigs import read_ict_identity_modes

        modes = read_ict_identity_modes(identity_folder, n_identity_modes)
    neutral = stylize_neutral(template.neutral, kind, seed, template.face_region, modes)
    from rigbuild.geometry.deformation_transfer import deformation_transfer

    deltas = deformation_transfer(template.neutral, template.deltas, template.faces, neutral)
    return replace(template.copy(), neutral=neutral, deltas=deltas, name=kind)

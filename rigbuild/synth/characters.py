"""Target characters for retargeting tests: the template and stylized variants of it.

Stylized variants change the neutral's proportions strongly (large identity coefficients where the
rig has identity modes, non-uniform scaling, smooth warps) and carry the template's expressions over
by deformation transfer (Sumner and Popovic 2004), as a studio would build a character rig.
"""

from __future__ import annotations

import os
from dataclasses import replace

import numpy as np

from rigbuild.errors import InputError
from rigbuild.rig import Rig
from rigbuild.synth.actor import smooth_random_field

CHARACTER_KINDS = ("template", "exaggerated", "stylized")


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
                   identity_folder: str | os.PathLike | None = None, n_identity_modes: int = 5) -> Rig:
    """A character rig from ``template``: ``"template"`` (a copy), ``"exaggerated"`` or ``"stylized"``.

    Expressions of the variants come from deformation transfer of the template's shapes onto the new
    neutral; markers, landmarks, face region and names are kept (same topology).
    """
    if kind == "template":
        return replace(template.copy(), name="template")
    modes = None
    if kind == "exaggerated" and identity_folder is not None:
        from rigbuild.io.rigs import read_ict_identity_modes

        modes = read_ict_identity_modes(identity_folder, n_identity_modes)
    neutral = stylize_neutral(template.neutral, kind, seed, template.face_region, modes)
    from rigbuild.geometry.deformation_transfer import deformation_transfer

    deltas = deformation_transfer(template.neutral, template.deltas, template.faces, neutral)
    return replace(template.copy(), neutral=neutral, deltas=deltas, name=kind)

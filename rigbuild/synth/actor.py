"""Synthetic actors: a template rig changed into an actor's ground-truth rig.

The actor differs from the template in the ways the papers describe (Ma et al. 2016 sec. 3;
Ribera et al. 2017 sec. 1), each seeded and recorded in the returned ``info``:

- **identity**: the neutral changes (ICT identity modes when available, else a smooth proportion warp);
- **intensity**: each shape's range of motion is scaled by a factor in ``intensity_range`` (0.6-1.5x);
- **asymmetry**: each shape is stronger on one side: ``delta *= 1 + a_k tanh(x / 20 mm)``,
  ``a_k ~ U(-asymmetry, asymmetry)`` (x = lateral coordinate, +x = actor's left);
- **crosstalk**: a captured shape carries a little of another (``jawOpen`` carries some
  ``browInnerUp``; smiles carry cheek squint; blinks carry cheek squint; pucker carries funnel);
- **spatial warp**: each displacement field is modulated by a smooth random field
  ``1 + warp * f_k(x)`` and its directions turned by a small random rotation (<= 8 degrees).
"""

from __future__ import annotations

import os
from dataclasses import replace

import numpy as np

from rigbuild.rig import Rig

#: (captured shape, shape it leaks into it, fraction of crosstalk relative to ``crosstalk``)
CROSSTALK_PAIRS = [
    ("jawOpen", "browInnerUp_L", 1.0),
    ("jawOpen", "browInnerUp_R", 1.0),
    ("jawOpen", "browInnerUp", 1.0),
    ("mouthSmile_L", "cheekSquint_L", 1.5),
    ("mouthSmile_R", "cheekSquint_R", 1.5),
    ("eyeBlink_L", "cheekSquint_L", 0.5),
    ("eyeBlink_R", "cheekSquint_R", 0.5),
    ("mouthPucker", "mouthFunnel", 1.0),
]


def smooth_random_field(points: np.ndarray, rng: np.random.Generator, n_centres: int = 12,
                        length_scale: float | None = None) -> np.ndarray:
    """A smooth random scalar field sampled at ``points`` (N, 3): a sum of Gaussian bumps.

    Centres are drawn inside the points' bounding box; ``length_scale`` defaults to a quarter of the
    bounding-box diagonal. The result is normalized to zero mean and unit max-abs. Returns (N,).
    """
    lo, hi = points.min(0), points.max(0)
    if length_scale is None:
        length_scale = 0.25 * float(np.linalg.norm(hi - lo))
    centres = rng.uniform(lo, hi, size=(n_centres, 3))
    amps = rng.normal(size=n_centres)
    d2 = ((points[:, None, :] - centres[None]) ** 2).sum(-1)
    f = np.exp(-d2 / (2 * length_scale**2)) @ amps
    f -= f.mean()
    m = np.abs(f).max()
    return f / m if m > 0 else f


def random_rotation(rng: np.random.Generator, max_deg: float) -> np.ndarray:
    """A rotation about a random axis by an angle uniform in [-max_deg, max_deg]."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    a = np.radians(rng.uniform(-max_deg, max_deg))
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


def proportion_warp(vertices: np.ndarray, rng: np.random.Generator, strength: float = 0.06,
                    bump_mm: float = 4.0) -> np.ndarray:
    """A smooth identity change for rigs without identity modes: per-axis scaling by
    ``1 + U(-strength, strength)`` about the centroid plus a smooth radial bump field of amplitude
    ``bump_mm``. vertices (V, 3) mm -> (V, 3) mm."""
    c = vertices.mean(0)
    s = 1 + rng.uniform(-strength, strength, size=3)
    out = c + (vertices - c) * s
    radial = vertices - c
    radial /= np.maximum(np.linalg.norm(radial, axis=1, keepdims=True), 1e-9)
    return out + bump_mm * smooth_random_field(vertices, rng)[:, None] * radial


def make_actor_rig(
    template: Rig,
    seed: int = 0,
    identity: np.ndarray | None = None,
    identity_folder: str | os.PathLike | None = None,
    intensity_range: tuple[float, float] = (0.6, 1.5),
    asymmetry: float = 0.25,
    crosstalk: float = 0.08,
    warp: float = 0.15,
    max_tilt_deg: float = 8.0,
) -> tuple[Rig, dict]:
    """The actor's ground-truth rig derived from ``template`` (same topology and shape names).

    Parameters
    ----------
    template : the template rig (mm).
    seed : everything random derives from it.
    identity : ICT identity coefficients (default: 5 coefficients ~ N(0, 1) when ``identity_folder``
        is given).
    identity_folder : the ICT ``FaceXModel`` folder with ``identityNNN.obj``; without it the neutral
        gets :func:`proportion_warp`.
    intensity_range, asymmetry, crosstalk, warp, max_tilt_deg : see the module docstring.

    Returns
    -------
    actor : Rig named ``"actor"``; info : dict with ``intensity`` (K,), ``asymmetry`` (K,),
    ``crosstalk`` [(shape, source, amount)], ``identity`` coefficients, ``tilt_deg`` (K,).
    """
    rng = np.random.default_rng(seed)
    V = template.n_vertices
    info: dict = {"seed": seed}
    if identity_folder is not None:
        from rigbuild.io.rigs import read_ict_identity_modes

        coeffs = rng.normal(size=5) if identity is None else np.asarray(identity, float)
        modes = read_ict_identity_modes(identity_folder, len(coeffs))
        if modes.shape[1] != V:
            raise ValueError("identity modes do not match the template's vertex count")
        neutral = template.neutral + np.tensordot(coeffs, modes, axes=1)
        info["identity"] = coeffs.tolist()
    else:
        neutral = proportion_warp(template.neutral, rng)
        info["identity"] = "proportion_warp"

    K = template.n_shapes
    intensity = rng.uniform(*intensity_range, size=K)
    asym = rng.uniform(-asymmetry, asymmetry, size=K)
    x = template.neutral[:, 0] - np.median(template.neutral[template.face_vertices, 0])
    side = np.tanh(x / 20.0)
    deltas = np.empty_like(template.deltas)
    tilts = np.zeros(K)
    pts = template.neutral
    for k in range(K):
        field = smooth_random_field(pts, rng)
        ang_rng = np.random.default_rng([seed, k])
        Rk = random_rotation(ang_rng, max_tilt_deg)
        tilts[k] = np.degrees(np.arccos(np.clip((np.trace(Rk) - 1) / 2, -1, 1)))
        scale = intensity[k] * (1 + asym[k] * side) * (1 + warp * field)
        deltas[k] = (template.deltas[k] @ Rk.T) * scale[:, None]
    names = template.shape_names
    leaks = []
    for target, source, amount in CROSSTALK_PAIRS:
        if target in names and source in names:
            a = crosstalk * amount
            deltas[names.index(target)] += a * template.deltas[names.index(source)]
            leaks.append((target, source, a))
    info.update(intensity=intensity, asymmetry=asym, crosstalk=leaks, tilt_deg=tilts)
    actor = replace(template.copy(), neutral=neutral, deltas=deltas, name="actor")
    return actor, info

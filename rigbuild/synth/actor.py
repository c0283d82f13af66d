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
  ``1 + warp * f_k(x)`` and its directions turned by a small random rotation (<= 8 degrees);
- **expression novelty** (opt-in, ``expression_novelty``): each shape gains an actor-specific smooth
  displacement inside the shape's own region that no template shape spans (:func:`novel_displacement`);
- **identity range** (opt-in, ``identity_sigma``): ICT identity coefficients drawn up to a stated number of
  standard deviations instead of an unclipped N(0, 1).
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


def sample_identity(rng: np.random.Generator, n_modes: int, sigma: float,
                    distribution: str = "uniform") -> np.ndarray:
    """Identity coefficients (n_modes,) in units of each mode's standard deviation, bounded by ``sigma``.

    ``distribution``: ``"uniform"``: U(-sigma, sigma); ``"clipped_normal"``: N(0, 1) clipped to [-sigma, sigma].
    """
    if not np.isfinite(sigma) or sigma < 0:
        raise ValueError(f"identity_sigma must be a non-negative number, got {sigma}")
    if distribution == "uniform":
        return rng.uniform(-sigma, sigma, size=n_modes)
    if distribution == "clipped_normal":
        return np.clip(rng.normal(size=n_modes), -sigma, sigma)
    raise ValueError(f"unknown identity distribution '{distribution}' (use uniform or clipped_normal)")


def shape_region_weight(delta: np.ndarray, threshold: float = 0.02, full: float = 0.25) -> np.ndarray:
    """A smooth mask (V,) in [0, 1] of the region a shape moves: 0 where ``|delta| <= threshold * max|delta|``,
    1 where ``|delta| >= full * max|delta|``, a quintic smoothstep between. delta (V, 3)."""
    a = np.linalg.norm(delta, axis=1)
    m = a.max(initial=0.0)
    if m <= 0:
        return np.zeros(a.shape[0])
    x = np.clip((a / m - threshold) / (full - threshold), 0.0, 1.0)
    return x * x * x * (x * (6 * x - 15) + 10)


def novel_displacement(points: np.ndarray, delta: np.ndarray, span: np.ndarray, rng: np.random.Generator,
                       n_centres: int = 6, length_fraction: float = 0.5) -> tuple[np.ndarray, float]:
    """A smooth displacement (V, 3) inside ``delta``'s region, orthogonal to every field in ``span``.

    ``points`` (V, 3) mm; ``delta`` (V, 3) the shape whose region is used (:func:`shape_region_weight`, mask
    ``s``); ``span`` (K, V, 3) the fields it must be orthogonal to (the template's deltas). A smooth random
    vector field ``g`` (three :func:`smooth_random_field` components of ``n_centres`` bumps over the region,
    length scale ``length_fraction`` of the region's bounding-box diagonal) is projected in the ``s``-weighted inner product:
    ``n = s * (g - sum_j c_j d_j)`` with ``c`` solving ``sum_v s (g - D c) . d_j = 0`` for every ``j``, so ``n``
    is smooth, vanishes outside the region, and ``<n, d_j> = 0`` exactly for every template delta (over the
    whole mesh and over the region alike). Returned with unit Frobenius norm (zeros if the region is empty),
    and the fraction of its norm outside the span of ``span`` restricted to the region (1 up to round-off).
    """
    s = shape_region_weight(delta)
    region = np.flatnonzero(s > 0)
    out = np.zeros_like(points, dtype=np.float64)
    if region.size < 3:
        return out, 0.0
    P = points[region]
    ls = length_fraction * float(np.linalg.norm(P.max(0) - P.min(0)))
    g = np.stack([smooth_random_field(P, rng, n_centres=n_centres, length_scale=max(ls, 1e-9)) for _ in range(3)], 1)
    D = span[:, region].reshape(span.shape[0], -1).T  # (3R, K)
    w = np.sqrt(np.repeat(s[region], 3))
    c = np.linalg.lstsq(D * w[:, None], g.reshape(-1) * w, rcond=None)[0]
    n = s[region][:, None] * (g - (D @ c).reshape(-1, 3))
    norm = float(np.linalg.norm(n))
    if norm <= 0:
        return out, 0.0
    out[region] = n / norm
    return out, out_of_span_fraction(out[region].reshape(-1), D)


def out_of_span_fraction(x: np.ndarray, D: np.ndarray) -> float:
    """||x - proj_span(D) x|| / ||x|| for a vector x (N,) and the columns of D (N, K)."""
    nx = float(np.linalg.norm(x))
    if nx == 0:
        return 0.0
    c = np.linalg.lstsq(D, x, rcond=None)[0]
    return float(np.linalg.norm(x - D @ c) / nx)


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
    identity_sigma: float | None = None,
    identity_distribution: str = "uniform",
    n_identity_modes: int = 5,
    expression_novelty: tuple[float, float] | None = None,
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
    identity_sigma : None (default): ``n_identity_modes`` coefficients ~ N(0, 1), unbounded. A number:
        coefficients bounded by that many standard deviations (:func:`sample_identity` with
        ``identity_distribution`` ``"uniform"`` or ``"clipped_normal"``). Ignored when ``identity`` is given
        or without ``identity_folder``.
    n_identity_modes : how many ICT identity modes are drawn (when ``identity`` is None).
    expression_novelty : None (default): off. ``(lo, hi)``: each shape k gains
        ``f_k ||delta_k|| * n_k`` with ``f_k ~ U(lo, hi)`` and ``n_k`` the unit :func:`novel_displacement` in
        the shape's region, orthogonal to every template delta; ``delta_k`` is the shape after scaling and
        tilt (before crosstalk, which is added after as without novelty). E.g. ``(0.15, 0.30)``.

    Returns
    -------
    actor : Rig named ``"actor"``; info : dict with ``intensity`` (K,), ``asymmetry`` (K,),
    ``crosstalk`` [(shape, source, amount)], ``identity`` coefficients, ``tilt_deg`` (K,), and with novelty
    ``novelty_fraction`` (K,) (||novel|| / ||delta||) and ``novelty_out_of_span`` (K,).
    """
    rng = np.random.default_rng(seed)
    V = template.n_vertices
    info: dict = {"seed": seed}
    if identity_folder is not None:
        from rigbuild.io.rigs import read_ict_identity_modes

        if identity is not None:
            coeffs = np.asarray(identity, float)
        elif identity_sigma is None:
            coeffs = rng.normal(size=int(n_identity_modes))
        else:
            coeffs = sample_identity(rng, int(n_identity_modes), float(identity_sigma), identity_distribution)
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
    if expression_novelty is not None:
        lo, hi = (float(x) for x in expression_novelty)
        if not (0 <= lo <= hi):
            raise ValueError(f"expression_novelty must be 0 <= lo <= hi, got {expression_novelty}")
        frac = np.zeros(K)
        oos = np.zeros(K)
        for k in range(K):
            nrng = np.random.default_rng([seed, k, 19])  # own stream: the draws above are unchanged
            f_k = nrng.uniform(lo, hi)
            n_k, oos[k] = novel_displacement(pts, template.deltas[k], template.deltas, nrng)
            dn = float(np.linalg.norm(deltas[k]))
            deltas[k] = deltas[k] + f_k * dn * n_k
            frac[k] = f_k if np.any(n_k) else 0.0
        info.update(novelty_fraction=frac, novelty_out_of_span=oos)
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

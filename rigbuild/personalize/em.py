"""EM blendshape personalization (Ma et al. 2016, sections 3-3.1).

The objective over all fitting frames ``i`` (sequences of contiguous frames) is

    J = sum_i ||M_i (R_i (b_0 + d_0 + D w_i) + t_i - p_i)||^2                 (E_g, eq. 2)
        + lambda_s sum_i (1^T w_i)^2                                           (sparsity, eq. 4)
        + lambda_t sum_{i, i-1 contiguous} ||w_i - w_{i-1}||^2                 (temporal, eq. 4)
        + lambda_r E_r(d_0, D) + lambda_d E_d(d_0, D)                          (eq. 7, neutral update)

with ``0 <= w <= 1``. It is minimized by block-coordinate descent, each block exactly:

- *weights and rigid motion* (eq. 3-4), frame by frame: weighted Kabsch for ``(R_i, t_i)``
  (:mod:`.rigid`), then the box QP for ``w_i`` (:mod:`.weights`) with both temporal neighbours;
- *shapes and neutral* (eq. 5-7): one sparse solve (:mod:`.shapes`).

Every block step minimizes ``J`` over its variables with the others fixed, so ``J`` never increases;
EM stops when an iteration lowers it by less than ``tolerance`` (relative).
"""

from __future__ import annotations

import logging
import time
import warnings
from dataclasses import dataclass, field

import numpy as np

from rigbuild.errors import InputError, RigbuildError
from rigbuild.personalize.params import PersonalizeParams
from rigbuild.personalize.rigid import fit_frame_rigid, to_rig_frame
from rigbuild.personalize.shapes import ShapeUpdate
from rigbuild.personalize.weights import solve_box_qp, weight_qp
from rigbuild.progress import progress

log = logging.getLogger(__name__)


@dataclass
class PersonalizationResult:
    """neutral (V, 3) and deltas (K, V, 3) of the personalized rig (mm); per fitting frame: weights
    (F, K), rotations (F, 3, 3), translations (F, 3) (NaN for skipped frames), kept (F,) bool;
    objective: one dict per step (``iteration``, ``step``, ``total`` and each term);
    residual_initial_mm / residual_final_mm: fit residual of the kept frames with the D*-initialized rig
    and with the personalized rig, weighted by the confidence as in the data term E_g
    (``sqrt(sum M^2 d^2 / sum M^2)``, mm; the plain RMS when every confidence is 1);
    residual_initial_unweighted_mm / residual_final_unweighted_mm: the plain RMS over the confident
    vertices (vertices the tracker trusts little count fully); shape_scales (K,): the amplitude
    factor the ``rom_peak`` gauge applied to each shape (ones for ``gauge="none"``); initial_weights (F, K),
    initial_rotations (F, 3, 3), initial_translations (F, 3): the first weights step's fit with the D* rig
    (``neutral`` of the input, D* before any gauge; NaN for skipped frames), the fit the residual_initial_* are of."""

    neutral: np.ndarray
    deltas: np.ndarray
    weights: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray
    kept: np.ndarray
    objective: list[dict] = field(default_factory=list)
    residual_initial_mm: float = float("nan")
    residual_final_mm: float = float("nan")
    residual_initial_unweighted_mm: float = float("nan")
    residual_final_unweighted_mm: float = float("nan")
    n_free_variables: int = 0
    active_vertices: np.ndarray | None = None
    timings: dict = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    shape_scales: np.ndarray | None = None
    initial_weights: np.ndarray | None = None
    initial_rotations: np.ndarray | None = None
    initial_translations: np.ndarray | None = None


# ---------------------------------------------------------------------------- checks
def check_inputs(neutral: np.ndarray, initial_deltas: np.ndarray, frames: np.ndarray,
                 confidence: np.ndarray | None, shape_names: list[str] | None = None) -> np.ndarray:
    """Validate shapes and return the confidence (F, V) (ones when None). InputError on bad input."""
    V = neutral.shape[0]
    if frames.ndim != 3 or frames.shape[2] != 3:
        raise InputError(f"tracked frames must be (F, V, 3), got {frames.shape}")
    if frames.shape[1] != V:
        raise InputError(
            f"rig topology differs from the tracked meshes: the rig has {V} vertices, the tracked "
            f"meshes {frames.shape[1]}",
            fix="track with the template rig's topology (the same vertex count and order) or load the matching rig",
        )
    if initial_deltas.shape[1:] != (V, 3):
        raise InputError(f"initial shapes must be (K, {V}, 3), got {initial_deltas.shape}")
    names = shape_names or [f"shape {k}" for k in range(initial_deltas.shape[0])]
    zero = [names[k] for k in range(initial_deltas.shape[0]) if not np.any(initial_deltas[k])]
    if zero:
        raise InputError(
            f"all-zero shape(s) in the rig: {', '.join(zero)} (no displacement anywhere, so no weight or "
            "personalization is defined for them)",
            fix="remove these shapes from the template rig (Rig.subset) or fix their OBJ files",
        )
    if confidence is None:
        return np.ones(frames.shape[:2])
    confidence = np.asarray(confidence, dtype=np.float64)
    if confidence.shape != frames.shape[:2]:
        raise InputError(f"confidence must be (F, V) = {frames.shape[:2]}, got {confidence.shape}")
    if np.any(confidence < 0) or not np.all(np.isfinite(confidence)):
        raise InputError("confidence must be finite and non-negative")
    return confidence


def grow_ring(vertices: np.ndarray, faces: np.ndarray, n_vertices: int, rings: int) -> np.ndarray:
    """``vertices`` (ids) plus ``rings`` rings of face neighbours. Returns sorted unique ids."""
    sel = np.zeros(n_vertices, dtype=bool)
    sel[vertices] = True
    for _ in range(rings):
        touched = sel[faces].any(1)
        sel[faces[touched].ravel()] = True
    return np.flatnonzero(sel)


def contiguity(sequence_ids: np.ndarray | None, kept: np.ndarray) -> np.ndarray:
    """(F,) bool: frame i is contiguous with frame i-1 (same sequence, both kept)."""
    F = kept.shape[0]
    seq = np.zeros(F, dtype=np.int64) if sequence_ids is None else np.asarray(sequence_ids)
    prev = np.zeros(F, dtype=bool)
    prev[1:] = (seq[1:] == seq[:-1]) & kept[1:] & kept[:-1]
    return prev


# ---------------------------------------------------------------------------- the frame fit
class FrameFitter:
    """Weights + rigid motion of every frame for a fixed rig (Ma et al. eq. 3-4), block-coordinate.

    neutral_a (A, 3), deltas_a (K, A, 3): the rig on the active vertices; frames_a (F, A, 3) world mm;
    conf2 (F, A) squared confidences; prev_contig (F,) bool.
    """

    def __init__(self, params: PersonalizeParams, frames_a: np.ndarray, conf2: np.ndarray, prev_contig: np.ndarray,
                 kept: np.ndarray):
        self.p = params
        self.frames = frames_a
        self.conf2 = conf2
        self.prev = prev_contig
        self.next = np.zeros_like(prev_contig)
        self.next[:-1] = prev_contig[1:]
        self.kept = kept
        self.uniform_conf = bool(np.all(conf2[kept] == conf2[kept][:1]))
        self.conf = np.sqrt(conf2)
        self.qp_times: list[float] = []
        self.hi = 1.0  # upper bound of the weights (relaxed only to measure the ROM gauge)
        self.pinned = np.zeros(len(kept), dtype=bool)  # frames whose weights are fixed at 0 (neutral frames)

    def set_rig(self, neutral_a: np.ndarray, deltas_a: np.ndarray) -> None:
        self.n0 = neutral_a
        self.K = deltas_a.shape[0]
        self.D = deltas_a.reshape(self.K, -1)  # (K, 3A)
        self._grams: dict[int, np.ndarray] = {}
        if self.uniform_conf:
            m = np.repeat(self.conf2[np.flatnonzero(self.kept)[0]], 3)
            self._gram_all = (self.D * m) @ self.D.T
        # shapes with no motion on the confident vertices are unobservable: weight fixed to 0
        g = np.einsum("ka,fa->kf", (deltas_a**2).sum(-1), self.conf2[self.kept])
        self.observable = g.max(1) > 0

    def gram(self, i: int) -> np.ndarray:
        if self.uniform_conf:
            return self._gram_all
        if i not in self._grams:
            m = np.repeat(self.conf2[i], 3)
            self._grams[i] = (self.D * m) @ self.D.T
        return self._grams[i]

    def model(self, w: np.ndarray) -> np.ndarray:
        return self.n0 + (w @ self.D).reshape(-1, 3)

    def frame_energy(self, i: int, w: np.ndarray, R: np.ndarray, t: np.ndarray, nbrs: list) -> float:
        """Energy of frame i: data + lambda_s (1^T w)^2 + lambda_t sum_n ||w - w_n||^2 (w over all K)."""
        x = self.model(w) @ R.T + t
        e = float((self.conf2[i] * ((x - self.frames[i]) ** 2).sum(1)).sum())
        e += self.p.lambda_s * float(w.sum()) ** 2
        for wn in nbrs:
            e += self.p.lambda_t * float(((w - wn) ** 2).sum())
        return e

    def _gauss_newton(self, i: int, w0: np.ndarray, R0: np.ndarray, t0: np.ndarray, gram: np.ndarray,
                      nbrs_obs: list) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One joint step on (rotation, translation, weights): the rotation linearized about R0
        (``R = R0 exp([omega])``, ``t = t0 + R0 tau``), the six rigid unknowns eliminated (Schur
        complement), the weights from the exact box QP. Returns (w, R, t)."""
        obs = self.observable
        m = self.conf2[i][:, None]
        q = to_rig_frame(self.frames[i], R0, t0)  # target in the rig frame (A, 3)
        y0 = self.model(w0)
        base = self.n0 - q  # residual = base + D w + omega x y0 + tau
        eye = np.eye(3)
        cols = [np.cross(eye[j][None, :], y0) for j in range(3)] + [np.broadcast_to(eye[j], y0.shape) for j in range(3)]
        B = np.stack([c.ravel() for c in cols], 1)  # (3A, 6)
        m3 = np.repeat(self.conf2[i], 3)
        MB = m3[:, None] * B
        Hzz = B.T @ MB
        Do = self.D[obs]
        both = Do @ np.concatenate([MB, (m3 * base.ravel())[:, None]], axis=1)  # (Ko, 7)
        Hwz, gw = both[:, :6], both[:, 6]
        gz = MB.T @ base.ravel()
        Hzz_inv = np.linalg.inv(Hzz)
        H, f = weight_qp(gram - Hwz @ Hzz_inv @ Hwz.T, -(gw - Hwz @ Hzz_inv @ gz), self.p.lambda_s,
                         self.p.lambda_t, nbrs_obs)
        tq = time.perf_counter()
        wo = solve_box_qp(H, f, x0=np.minimum(w0[obs], self.hi), method=self.p.qp_method, hi=self.hi)
        self.qp_times.append(time.perf_counter() - tq)
        z = -Hzz_inv @ (Hwz.T @ wo + gz)
        w = np.zeros_like(w0)
        w[obs] = wo
        om = z[:3]
        ang = float(np.linalg.norm(om))
        K = np.array([[0, -om[2], om[1]], [om[2], 0, -om[0]], [-om[1], om[0], 0]])
        if ang > 1e-12:
            Rd = eye + np.sin(ang) / ang * K + (1 - np.cos(ang)) / ang**2 * K @ K
        else:
            Rd = eye + K
        return w, R0 @ Rd, t0 + R0 @ z[3:]

    def fit_frame(self, i: int, W: np.ndarray, R: np.ndarray, t: np.ndarray) -> None:
        """Minimize frame i's energy over (R_i, t_i, w_i) with the other frames fixed, in place.

        Joint Gauss-Newton steps (each kept only if it lowers the energy) until the weights and the
        rotation move less than ``weight_tol`` (at most ``inner_iterations``), then one exact block
        step of each: weighted Kabsch for (R, t), the box QP for w. Energy never increases."""
        p = self.p
        if self.pinned[i]:  # a neutral frame: weights 0, rigid motion only
            W[i] = 0.0
            R[i], t[i] = fit_frame_rigid(self.model(W[i]), self.frames[i], self.conf[i])
            return
        obs = self.observable
        m3 = np.repeat(self.conf2[i], 3)
        gram = self.gram(i)[np.ix_(obs, obs)]
        nbrs = []
        if self.prev[i]:
            nbrs.append(W[i - 1].copy())
        if self.next[i]:
            nbrs.append(W[i + 1].copy())
        nbrs_obs = [wn[obs] for wn in nbrs]
        e_cur = self.frame_energy(i, W[i], R[i], t[i], nbrs)
        for _ in range(p.inner_iterations):
            w_new, R_new, t_new = self._gauss_newton(i, W[i], R[i], t[i], gram, nbrs_obs)
            e_new = self.frame_energy(i, w_new, R_new, t_new, nbrs)
            if e_new >= e_cur:
                break
            dw = float(np.abs(w_new - W[i]).max())
            drot = float(np.abs(R_new - R[i]).max())
            W[i], R[i], t[i], e_cur = w_new, R_new, t_new, e_new
            if dw < p.weight_tol and drot < p.weight_tol:
                break
        R[i], t[i] = fit_frame_rigid(self.model(W[i]), self.frames[i], self.conf[i])
        r = to_rig_frame(self.frames[i], R[i], t[i]) - self.n0
        H, f = weight_qp(gram, (self.D @ (m3 * r.ravel()))[obs], p.lambda_s, p.lambda_t, nbrs_obs)
        w_start = W[i][obs].copy()
        tq = time.perf_counter()
        w_fin = solve_box_qp(H, f, x0=np.minimum(w_start, self.hi), method=p.qp_method, hi=self.hi)
        self.qp_times.append(time.perf_counter() - tq)
        W[i] = 0.0
        W[i, obs] = w_fin

    def sweep(self, W: np.ndarray, R: np.ndarray, t: np.ndarray, warm_start: bool = False) -> None:
        """One pass over the kept frames in order. ``warm_start``: a frame contiguous with the previous
        one starts from its solution (first pass only)."""
        for i in progress(np.flatnonzero(self.kept), "weight fits", unit="frame"):
            if warm_start and self.prev[i]:
                W[i], R[i], t[i] = W[i - 1], R[i - 1], t[i - 1]
            self.fit_frame(int(i), W, R, t)

    def terms(self, W: np.ndarray, R: np.ndarray, t: np.ndarray) -> dict:
        """E_g, E_s, E_t (unweighted by their lambdas) and the fit residual of the kept frames (mm):
        ``rms_mm`` weighted by the confidence as in E_g, ``sqrt(sum M^2 d^2 / sum M^2)`` (the data term
        the EM minimizes, per unit confidence), and ``rms_unweighted_mm`` over the confident vertices."""
        Eg = 0.0
        sq, n = 0.0, 0
        thr = self.p.confidence_threshold
        for i in np.flatnonzero(self.kept):
            x = self.model(W[i]) @ R[i].T + t[i]
            d2 = ((x - self.frames[i]) ** 2).sum(1)
            Eg += float((self.conf2[i] * d2).sum())
            c = self.conf2[i] > thr**2
            sq += float(d2[c].sum())
            n += int(c.sum())
        k = np.flatnonzero(self.kept)
        Es = float((W[k].sum(1) ** 2).sum())
        pc = np.flatnonzero(self.prev)
        Et = float(((W[pc] - W[pc - 1]) ** 2).sum())
        m2 = float(self.conf2[k].sum())
        return {"E_g": Eg, "E_s": Es, "E_t": Et, "rms_mm": float(np.sqrt(Eg / m2)) if m2 > 0 else 0.0,
                "rms_unweighted_mm": float(np.sqrt(sq / max(n, 1)))}


def fit_weights_and_rigid(neutral: np.ndarray, deltas: np.ndarray, frames: np.ndarray,
                          confidence: np.ndarray | None = None, sequence_ids: np.ndarray | None = None,
                          params: PersonalizeParams | None = None, vertices: np.ndarray | None = None,
                          sweeps: int = 10, neutral_mask: np.ndarray | None = None) -> dict:
    """Fit weights and rigid motion to frames with a fixed rig (used for held-out frames).

    neutral (V, 3), deltas (K, V, 3), frames (F, V, 3) mm; confidence (F, V) or None; vertices:
    restrict to these ids (default: confident vertices); neutral_mask (F,) bool: the actor's neutral frames
    (weights 0 with ``params.pin_neutral_frames``). Sweeps of block-coordinate descent until the energy drops
    by less than ``params.tolerance``. Returns dict with weights (F, K), rotations, translations, rms_mm
    (confidence-weighted, as :meth:`FrameFitter.terms`), rms_unweighted_mm, energy, kept.
    """
    p = (params or PersonalizeParams()).in_mm()
    conf = check_inputs(neutral, deltas, frames, confidence)
    if vertices is None:
        vertices = np.flatnonzero((conf > p.confidence_threshold).any(0))
    kept = (conf[:, vertices] > p.confidence_threshold).sum(1) >= min(p.min_confident_vertices, len(vertices))
    fit = FrameFitter(p, frames[:, vertices], conf[:, vertices] ** 2, contiguity(sequence_ids, kept), kept)
    fit.pinned = pinned_frames(neutral_mask, frames.shape[0], p)
    fit.set_rig(neutral[vertices], deltas[:, vertices])
    F, K = frames.shape[0], deltas.shape[0]
    W = np.zeros((F, K))
    R = np.repeat(np.eye(3)[None], F, 0)
    t = np.zeros((F, 3))
    prev = None
    for s in range(sweeps):
        fit.sweep(W, R, t, warm_start=s == 0)
        e = fit.terms(W, R, t)
        J = e["E_g"] + p.lambda_s * e["E_s"] + p.lambda_t * e["E_t"]
        if prev is not None and prev - J <= p.tolerance * abs(prev):
            break
        prev = J
    W[~kept] = np.nan
    return {"weights": W, "rotations": R, "translations": t, "rms_mm": e["rms_mm"],
            "rms_unweighted_mm": e["rms_unweighted_mm"], "energy": J, "kept": kept}


def pinned_frames(neutral_mask: np.ndarray | None, n_frames: int, params: PersonalizeParams) -> np.ndarray:
    """(F,) bool: the frames whose weights are fixed at 0 (``neutral_mask`` when ``pin_neutral_frames``)."""
    if neutral_mask is None or not params.pin_neutral_frames:
        return np.zeros(n_frames, dtype=bool)
    m = np.asarray(neutral_mask, dtype=bool).reshape(-1)
    if m.size != n_frames:
        raise InputError(f"neutral_mask has {m.size} entries for {n_frames} frames")
    return m


# ---------------------------------------------------------------------------- EM
def rom_peak_scales(weights: np.ndarray, observable: np.ndarray | None = None) -> np.ndarray:
    """(K,) the peak weight of each shape over ROM frames ``weights`` (F, K): the amplitude factor that
    makes the shape reach weight 1 at its peak (``rom_peak`` gauge). Shapes never used (peak 0) or
    not ``observable`` keep 1."""
    peak = np.nanmax(np.asarray(weights, dtype=np.float64), axis=0)
    ok = np.isfinite(peak) & (peak > 1e-6)
    if observable is not None:
        ok &= np.asarray(observable, bool)
    return np.where(ok, peak, 1.0)


def usable_frames(neutral: np.ndarray, initial_deltas: np.ndarray, frames: np.ndarray, confidence: np.ndarray | None,
                  shape_names: list[str] | None, fit_vertices: np.ndarray | None, p: PersonalizeParams
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """Checked inputs and the frames the EM fits.

    Returns frames (N, V, 3) mm with non-finite entries set to 0; conf (N, V), zero outside ``fit_vertices``,
    at non-finite positions and on skipped frames; confident (N, V) bool (``conf > confidence_threshold``
    before skipped frames are zeroed); kept (N,) bool (frames with at least ``min_confident_vertices``
    confident vertices); the warnings issued for skipped frames."""
    conf = check_inputs(neutral, initial_deltas, frames, confidence, shape_names).copy()
    V = neutral.shape[0]
    if fit_vertices is not None:
        keep_v = np.zeros(V, dtype=bool)
        keep_v[np.asarray(fit_vertices, dtype=np.int64)] = True
        conf[:, ~keep_v] = 0.0
    conf[~np.isfinite(frames).all(2)] = 0.0
    frames = np.where(np.isfinite(frames), frames, 0.0)
    msgs: list[str] = []

    confident = conf > p.confidence_threshold
    n_conf = confident.sum(1)
    kept = n_conf >= p.min_confident_vertices
    for i in np.flatnonzero(~kept):
        m = (f"frame {i}: only {int(n_conf[i])} confident vertices (< min_confident_vertices = "
             f"{p.min_confident_vertices}); skipped")
        warnings.warn(m, stacklevel=3)
        msgs.append(m)
    if kept.sum() == 0:
        raise InputError(
            f"no frame has at least {p.min_confident_vertices} confident vertices",
            fix="check the tracking confidences or lower params.personalize.min_confident_vertices",
        )
    conf[~kept] = 0.0
    return frames, conf, confident, kept, msgs


def local_support(initial_deltas: np.ndarray, names: list[str], support_tol_mm: float) -> np.ndarray:
    """(K, V) bool: where shape k may change. Shape k may change at vertex v only where
    ``|D*_kv| > support_tol_mm``; elsewhere it keeps D* (so D_kv = 0 wherever D*_kv = 0, and sub-threshold
    tails stay as transferred). A shape that moves less than support_tol_mm everywhere uses a quarter of
    its own peak instead (with a warning)."""
    mag = np.linalg.norm(initial_deltas, axis=2)
    peak = mag.max(axis=1)
    small = [names[k] for k in range(initial_deltas.shape[0]) if peak[k] <= support_tol_mm]
    if small:
        warnings.warn(f"shape(s) {', '.join(small)} move at most support_tol_mm = {support_tol_mm} mm; "
                      "their support is a quarter of their own peak", stacklevel=3)
    return mag > np.minimum(support_tol_mm, 0.25 * peak)[:, None]


class EMRun:
    """The state of one EM run on the active vertices: the rig change ``X`` (K+1, A, 3) from [0, D*], the
    per-frame weights ``W`` (N, K), rotations ``R`` (N, 3, 3) and translations ``t`` (N, 3), the objective
    record, and the time spent in the weights and shapes steps (s)."""

    def __init__(self, p: PersonalizeParams, neutral: np.ndarray, initial_deltas: np.ndarray, frames: np.ndarray,
                 conf: np.ndarray, kept: np.ndarray, active: np.ndarray, sequence_ids: np.ndarray | None,
                 neutral_mask: np.ndarray | None, initial_weights: np.ndarray | None,
                 initial_rigid: tuple[np.ndarray, np.ndarray] | None):
        self.p = p
        self.neutral = neutral
        self.Dstar = initial_deltas
        self.kept = kept
        self.kept_idx = np.flatnonzero(kept)
        self.active = active
        self.conf2 = conf[:, active] ** 2
        self.frames_a = frames[:, active]
        self.b0_a = neutral[active]
        self.Ds_a = initial_deltas[:, active]
        self.fit = FrameFitter(p, self.frames_a, self.conf2, contiguity(sequence_ids, kept), kept)
        self.fit.pinned = pinned_frames(neutral_mask, frames.shape[0], p)
        Nf, K = frames.shape[0], initial_deltas.shape[0]
        self.Nf = Nf
        self.W = np.zeros((Nf, K)) if initial_weights is None else np.clip(np.nan_to_num(initial_weights), 0, 1).copy()
        self.R = np.repeat(np.eye(3)[None], Nf, 0) if initial_rigid is None else np.array(initial_rigid[0], float)
        self.t = np.zeros((Nf, 3)) if initial_rigid is None else np.array(initial_rigid[1], float)
        self.X = np.zeros((K + 1, active.size, 3))
        self.objective: list[dict] = []
        self.shapes: ShapeUpdate | None = None
        self.scales = np.ones(K)
        self.t_w = self.t_s = self.t_setup = 0.0
        self.initial_fit: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def set_rig(self) -> None:
        self.fit.set_rig(self.b0_a + self.X[0], self.Ds_a + self.X[1:])

    def record(self, it: int, step: str) -> float:
        """Append the objective's row for EM step ``step`` of iteration ``it``; returns J."""
        p = self.p
        e = self.fit.terms(self.W, self.R, self.t)
        Er, Ed = self.shapes.regularizers(self.X) if self.shapes is not None else (0.0, 0.0)
        J = e["E_g"] + p.lambda_s * e["E_s"] + p.lambda_t * e["E_t"] + p.lambda_r * Er + p.lambda_d * Ed
        row = {"iteration": it, "step": step, "total": J, **e, "E_r": Er, "E_d": Ed, "lambda_s": p.lambda_s,
               "lambda_t": p.lambda_t, "lambda_r": p.lambda_r, "lambda_d": p.lambda_d}
        self.objective.append(row)
        log.info("EM %d %-7s J=%.6g E_g=%.6g rms=%.4f mm", it, step, J, e["E_g"], e["rms_mm"])
        return J

    def sweep(self, **kw) -> None:
        """One weights step over the kept frames (timed)."""
        t0 = time.perf_counter()
        self.fit.sweep(self.W, self.R, self.t, **kw)
        self.t_w += time.perf_counter() - t0

    def rom_peak_gauge(self) -> float:
        """The ROM reaches every shape at full intensity: measure each shape's peak weight with the box
        relaxed, scale D* (the prior of E_r / E_d) by it; the weights scale inversely (same fit). Returns J
        of the re-based objective."""
        self.fit.hi = self.p.gauge_max_weight
        self.sweep()
        self.fit.hi = 1.0
        self.scales = rom_peak_scales(self.W[self.kept_idx], self.fit.observable)
        self.Dstar = self.Dstar * self.scales[:, None, None]
        self.Ds_a = self.Dstar[:, self.active]
        self.W = np.minimum(self.W / self.scales[None, :], 1.0)
        self.set_rig()
        self.objective.clear()  # the objective is re-based: its E_r / E_d refer to the scaled D*
        return self.record(0, "gauge")

    def shapes_step(self) -> None:
        """The shape update (eq. 5-7) for the current weights and rigid motions."""
        kept_idx = self.kept_idx
        t0 = time.perf_counter()
        W_hat = np.concatenate([np.ones((self.Nf, 1)), self.W], axis=1)[kept_idx]
        rig_frame = np.stack([to_rig_frame(self.frames_a[i], self.R[i], self.t[i]) for i in kept_idx])
        residual = rig_frame - self.b0_a - np.einsum("fk,kac->fac", self.W[kept_idx], self.Ds_a, optimize=True)
        self.X = self.shapes.solve(W_hat, self.conf2[kept_idx], residual)
        if not self.p.update_neutral:
            self.X[0] = 0.0
        self.t_s += time.perf_counter() - t0

    def iterate(self, J: float, faces: np.ndarray, support: np.ndarray) -> None:
        """EM iterations (shapes step, then weights step) until J drops by less than ``tolerance``
        (relative) or ``max_iterations``; RigbuildError if J increases."""
        p = self.p
        t0 = time.perf_counter()
        self.shapes = ShapeUpdate(self.neutral, self.Dstar, faces, self.active, p.lambda_r, p.lambda_d,
                                  p.update_neutral, support)
        self.t_setup = time.perf_counter() - t0
        for it in progress(range(1, p.max_iterations + 1), "EM iterations", unit="iteration"):
            J_prev = J
            self.shapes_step()
            self.set_rig()
            J_shape = self.record(it, "shapes")
            self.sweep()
            J = self.record(it, "weights")
            if J_shape > J_prev * (1 + 1e-9) or J > J_shape * (1 + 1e-9):
                raise RigbuildError(f"EM objective increased at iteration {it}: {J_prev:.9g} -> {J_shape:.9g} -> {J:.9g}")
            if J_prev - J <= p.tolerance * abs(J_prev):
                break

    def result(self, residual_initial: float, residual_initial_unweighted: float, t_start: float,
               msgs: list[str]) -> PersonalizationResult:
        """The personalized rig on all vertices (the ``rom_peak`` gauge applied once more) and the fit."""
        kept = self.kept
        neutral_out = self.neutral.copy()
        neutral_out[self.active] += self.X[0]
        deltas_out = self.Dstar.copy()
        deltas_out[:, self.active] += self.X[1:]
        W = self.W
        scales = self.scales
        if self.p.gauge == "rom_peak":  # the personalized shapes, too, reach full intensity at their ROM peak
            final = rom_peak_scales(W[self.kept_idx], self.fit.observable)
            deltas_out *= final[:, None, None]
            W = W / final[None, :]
            scales = scales * final
        W_out, R_out, t_out = _nan_where_skipped(kept, W, self.R, self.t)
        W0, R0, t0 = _nan_where_skipped(kept, *(self.initial_fit or (self.W, self.R, self.t)))
        qp = np.asarray(self.fit.qp_times)
        objective = self.objective
        return PersonalizationResult(
            neutral=neutral_out,
            deltas=deltas_out,
            weights=W_out,
            rotations=R_out,
            translations=t_out,
            kept=kept,
            objective=objective,
            residual_initial_mm=residual_initial,
            residual_final_mm=objective[-1]["rms_mm"],
            residual_initial_unweighted_mm=residual_initial_unweighted,
            residual_final_unweighted_mm=objective[-1]["rms_unweighted_mm"],
            n_free_variables=self.shapes.n_vars,
            active_vertices=self.active,
            timings={"setup_s": self.t_setup, "weights_s": self.t_w, "shapes_s": self.t_s,
                     "total_s": time.perf_counter() - t_start,
                     "qp_median_ms": float(np.median(qp) * 1e3) if qp.size else float("nan"),
                     "system_nnz": self.shapes.nnz},
            warnings=msgs,
            shape_scales=scales,
            initial_weights=W0,
            initial_rotations=R0,
            initial_translations=t0,
        )


def _nan_where_skipped(kept: np.ndarray, *per_frame: np.ndarray) -> list[np.ndarray]:
    """Copies of per-frame arrays (F, ...) with the rows of skipped frames (``~kept``, (F,) bool) set to NaN."""
    return [np.where(kept.reshape(-1, *[1] * (a.ndim - 1)), a, np.nan) for a in per_frame]


def personalize(
    neutral: np.ndarray,
    initial_deltas: np.ndarray,
    faces: np.ndarray,
    frames: np.ndarray,
    confidence: np.ndarray | None = None,
    sequence_ids: np.ndarray | None = None,
    params: PersonalizeParams | None = None,
    shape_names: list[str] | None = None,
    fit_vertices: np.ndarray | None = None,
    initial_weights: np.ndarray | None = None,
    initial_rigid: tuple[np.ndarray, np.ndarray] | None = None,
    neutral_mask: np.ndarray | None = None,
) -> PersonalizationResult:
    """Personalize the blendshapes ``D*`` to tracked frames (Ma et al. 2016).

    Parameters
    ----------
    neutral : (V, 3) the actor's neutral b_0 (e.g. a tracked neutral frame), mm.
    initial_deltas : (K, V, 3) D*, the template shapes transferred onto ``neutral``
        (:func:`rigbuild.geometry.deformation_transfer.deformation_transfer`), mm.
    faces : (F, 3) template triangles.
    frames : (N, V, 3) tracked meshes in template topology, world mm.
    confidence : (N, V) per-vertex confidence in [0, 1] (M of eq. 1-2), or None for all ones.
    sequence_ids : (N,) sequence of each frame; consecutive frames of one sequence are contiguous
        (temporal smoothness). None: one sequence.
    params : :class:`PersonalizeParams`.
    shape_names : for messages.
    fit_vertices : (R,) vertex ids used for fitting (e.g. the face region); confidence elsewhere is 0.
    initial_weights, initial_rigid : optional (N, K) weights and ((N, 3, 3), (N, 3)) rigid motions to
        start from (e.g. a previous personalization). With both given, EM starts with a shapes step
        (``residual_initial_mm`` is then the fit with these weights); with weights only, the first
        weights step starts from them.
    neutral_mask : (N,) bool, the frames that show the actor's neutral (each ROM sequence's neutral frame):
        their weights stay 0 (``params.pin_neutral_frames``).

    Returns
    -------
    :class:`PersonalizationResult`. Raises InputError for mismatched topology, all-zero shapes or a bad
    parameter value; frames with fewer than ``min_confident_vertices`` confident vertices are skipped with a
    warning.
    """
    params = params or PersonalizeParams()
    params.check()
    p = params.in_mm()
    t_start = time.perf_counter()
    neutral = np.asarray(neutral, dtype=np.float64)
    Dstar = np.asarray(initial_deltas, dtype=np.float64)
    frames = np.asarray(frames, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    frames, conf, confident, kept, msgs = usable_frames(neutral, Dstar, frames, confidence, shape_names,
                                                        fit_vertices, p)
    names = shape_names or [f"shape{k}" for k in range(Dstar.shape[0])]
    support = local_support(Dstar, names, p.support_tol_mm)
    active = grow_ring(np.flatnonzero(confident[kept].any(0)), faces, neutral.shape[0], p.ring)

    em = EMRun(p, neutral, Dstar, frames, conf, kept, active, sequence_ids, neutral_mask, initial_weights,
               initial_rigid)
    em.set_rig()
    unobs = [names[k] for k in np.flatnonzero(~em.fit.observable)]
    if unobs:
        m = (f"shape(s) {', '.join(unobs)} do not move any confident vertex: their weights stay 0 and "
             "their shapes stay as transferred")
        warnings.warn(m, stacklevel=2)
        msgs.append(m)
    if initial_weights is None or initial_rigid is None:
        em.sweep(warm_start=initial_weights is None)
    J = em.record(0, "weights")
    em.initial_fit = (em.W.copy(), em.R.copy(), em.t.copy())
    residual_initial = em.objective[-1]["rms_mm"]
    residual_initial_unweighted = em.objective[-1]["rms_unweighted_mm"]
    if p.gauge == "rom_peak":
        J = em.rom_peak_gauge()
    em.iterate(J, faces, support)
    return em.result(residual_initial, residual_initial_unweighted, t_start, msgs)

"""Global bundle adjustment of a multi-camera rig observing a rigid planar board.

Unknowns: every camera's pose (Rodrigues vector + translation, world-to-camera), intrinsics
(fx, fy, cx, cy) and Brown distortion (k1, k2, p1, p2, k3), and every board pose (board-to-world).
The board's corner coordinates are fixed (mm, from ``BoardSpec``), which sets the metric scale; the
reference camera's pose is fixed, which sets the world frame. Residuals are reprojection errors in
pixels under a robust loss (scipy ``soft_l1``/``huber``/``cauchy``, scale ``f_scale`` px).

Solver choice (why, with the measurements: docs/decisions.md):

* a Levenberg-Marquardt of our own (the same robust losses, a dense Cholesky of the small normal matrix,
  a grouped central-difference Jacobian) rather than scipy ``least_squares`` (trf with lsmr steps), whose
  inexact steps make slow progress on this badly scaled problem (focal lengths ~1e3 next to distortion
  ~1e-1); ``benchmarks/bench_calibrate.py`` reruns both.
* pycolmap's bundle adjuster was not used: it optimizes free 3-D points and per-image poses, while here
  each corner belongs to a rigid board (one 6-DoF pose per instant) and each camera keeps one pose over
  all instants; expressing that needs a COLMAP rig with the board as the static scene. Its camera models
  also do not match ``Camera``: OPENCV has no k3 and FULL_OPENCV adds k4-k6 that cannot be held at 0.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from scipy.sparse import lil_matrix

from rigbuild.calibrate.params import ROBUST_LOSSES
from rigbuild.calibrate.rotations import rodrigues
from rigbuild.progress import progress

N_CAM = 15  # rx ry rz tx ty tz fx fy cx cy k1 k2 p1 p2 k3
N_BOARD = 6  # rx ry rz tx ty tz (board-to-world)
CAM_POSE = slice(0, 6)
FX, FY, CX, CY = 6, 7, 8, 9
TANGENTIAL = (12, 13)
K3_INDEX = 14


@dataclass
class Observations:
    """Corner observations of a rig session.

    cam : (N,) camera index; view : (N,) board-pose index; corner : (N,) corner id;
    uv : (N, 2) detected pixels (OpenCV pixel centres).
    """

    cam: np.ndarray
    view: np.ndarray
    corner: np.ndarray
    uv: np.ndarray

    def __len__(self) -> int:
        return int(self.cam.size)


@dataclass
class BundleResult:
    """cam_params (C, 15), board_params (V, 6), residuals (N, 2) px, plus solver diagnostics."""

    cam_params: np.ndarray
    board_params: np.ndarray
    residuals: np.ndarray
    rms_px: float
    initial_rms_px: float
    nfev: int
    status: int
    message: str
    seconds: float
    cam_sd: np.ndarray | None = None  # (C, 15) standard deviations of the camera unknowns (NaN = held)


def project(cam_params: np.ndarray, board_params: np.ndarray, obs: Observations,
            board_points: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) of each observation's board corner through its camera (Brown model).

    cam_params : (C, 15) ``[rvec, t, fx, fy, cx, cy, k1, k2, p1, p2, k3]`` world-to-camera, mm, px.
    board_params : (V, 6) ``[rvec, t]`` board-to-world, mm.
    board_points : (P, 3) board-frame corners, mm.
    """
    Rc = rodrigues(cam_params[:, 0:3])
    Rb = rodrigues(board_params[:, 0:3])
    P = board_points[obs.corner]
    Xw = np.einsum("nij,nj->ni", Rb[obs.view], P) + board_params[obs.view, 3:6]
    cp = cam_params[obs.cam]
    Xc = np.einsum("nij,nj->ni", Rc[obs.cam], Xw) + cp[:, 3:6]
    x = Xc[:, 0] / Xc[:, 2]
    y = Xc[:, 1] / Xc[:, 2]
    k1, k2, p1, p2, k3 = cp[:, 10], cp[:, 11], cp[:, 12], cp[:, 13], cp[:, 14]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([cp[:, 6] * xd + cp[:, 8], cp[:, 7] * yd + cp[:, 9]], axis=1)


#: ``robust_scale_px: auto``: the robust loss's scale in units of the corners' noise (:func:`robust_noise_px`)
AUTO_SCALE_SIGMAS = 3.0


def robust_noise_px(residuals: np.ndarray) -> float:
    """Per-coordinate noise, px, of 2-D residuals (N, 2) from their median: ``sqrt(median |r|^2 / (2 ln 2))``
    (|r|^2 / sigma^2 of Gaussian noise is chi-square with 2 degrees of freedom, median 2 ln 2); outliers
    do not inflate it."""
    sq = np.sum(np.asarray(residuals, np.float64).reshape(-1, 2) ** 2, axis=1)
    return float(np.sqrt(np.median(sq) / (2 * np.log(2)))) if len(sq) else float("nan")


def ray_angle_deg(rays: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(N,) angle, degrees, between viewing rays (N, 3) and unit board normals (N, 3) or (3,) (0 = face-on)."""
    cos = np.abs(np.sum(rays * normals, axis=-1)) / np.linalg.norm(rays, axis=-1)
    return np.degrees(np.arccos(np.clip(cos, 0.0, 1.0)))


def view_angles_deg(cam_params: np.ndarray, board_params: np.ndarray, obs: Observations,
                    board_points: np.ndarray) -> np.ndarray:
    """(N,) angle, degrees, between each observation's viewing ray and its board's normal (0 = seen
    face-on; the foreshortening that blurs a corner grows with it). Parameters as :func:`project`."""
    Rc = rodrigues(cam_params[:, 0:3])
    Rb = rodrigues(board_params[:, 0:3])
    Xw = np.einsum("nij,nj->ni", Rb[obs.view], board_points[obs.corner]) + board_params[obs.view, 3:6]
    centres = -np.einsum("nji,nj->ni", Rc[obs.cam], cam_params[obs.cam, 3:6])  # C = -R^T t
    return ray_angle_deg(Xw - centres, Rb[obs.view][:, :, 2])


def view_angle_weights(angles_deg: np.ndarray, residuals: np.ndarray, n_bins: int = 8,
                       min_per_bin: int = 50) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverse noise variance of each corner from how noisy corners seen at its angle are.

    The observations are split into ``n_bins`` bins of equal count by view angle (fewer bins when there are
    fewer than ``min_per_bin`` per bin); each bin's noise is the robust per-coordinate deviation of its
    residuals (N, 2) px (:func:`robust_noise_px`). Returns (weights (N,) = (sigma_ref / sigma_bin)^2, with sigma_ref the
    median over observations of their bin's sigma; bin edges (B + 1,) degrees; bin sigmas (B,) px).
    """
    a = np.asarray(angles_deg, np.float64)
    n = len(a)
    bins = int(max(1, min(n_bins, n // max(min_per_bin, 1))))
    edges = np.quantile(a, np.linspace(0, 1, bins + 1)) if n else np.zeros(bins + 1)
    idx = np.clip(np.searchsorted(edges, a, side="right") - 1, 0, bins - 1)
    r = np.asarray(residuals, np.float64)
    sigma = np.array([robust_noise_px(r[idx == b]) if np.any(idx == b) else np.nan for b in range(bins)])
    floor = np.nanmax(sigma) * 1e-3 if np.any(np.isfinite(sigma)) else 1.0
    sigma = np.where(np.isfinite(sigma), np.maximum(sigma, max(floor, 1e-6)), np.nanmax(sigma))
    s_obs = sigma[idx]
    ref = float(np.median(s_obs)) if n else 1.0
    return (ref / s_obs) ** 2, edges, sigma


def jacobian_sparsity(obs: Observations, n_cams: int, n_views: int, free: np.ndarray) -> lil_matrix:
    """(2N, n_free) structure: residual rows of observation i touch its camera's and its board's columns."""
    n_full = n_cams * N_CAM + n_views * N_BOARD
    full_to_free = -np.ones(n_full, dtype=np.int64)
    full_to_free[free] = np.arange(free.size)
    rows, cols = [], []
    n = len(obs)
    base = np.arange(n) * 2
    for j in range(N_CAM):
        cols.append(full_to_free[obs.cam * N_CAM + j])
        rows.append(base)
    for j in range(N_BOARD):
        cols.append(full_to_free[n_cams * N_CAM + obs.view * N_BOARD + j])
        rows.append(base)
    r = np.concatenate(rows)
    c = np.concatenate(cols)
    keep = c >= 0
    r, c = r[keep], c[keep]
    S = lil_matrix((2 * n, free.size), dtype=np.int8)
    S[r, c] = 1
    S[r + 1, c] = 1
    return S


def robust_weights(sq_err: np.ndarray, loss: str, f_scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Per-observation robust cost and IRLS weight for squared reprojection errors (N,) px^2.

    cost_i = f^2 rho(e_i^2 / f^2); weight_i = rho'(e_i^2 / f^2) (scipy's loss definitions), applied to the
    2-D error of one corner jointly, so the loss is isotropic in the image.
    """
    z = sq_err / f_scale ** 2
    if loss == "linear":
        rho, drho = z, np.ones_like(z)
    elif loss == "soft_l1":
        rho, drho = 2 * (np.sqrt(1 + z) - 1), 1 / np.sqrt(1 + z)
    elif loss == "huber":
        rho = np.where(z <= 1, z, 2 * np.sqrt(z) - 1)
        drho = np.where(z <= 1, 1.0, 1 / np.sqrt(np.maximum(z, 1e-300)))
    elif loss == "cauchy":
        rho, drho = np.log1p(z), 1 / (1 + z)
    else:
        raise ValueError(f"unknown robust loss '{loss}' (use one of {ROBUST_LOSSES})")
    return f_scale ** 2 * rho, drho


class _BundleProblem:
    """Residuals, grouped central-difference Jacobian and normal equations of one adjustment.

    full : (C * 15 + V * 6,) all unknowns (cameras then boards); free : indices of the unknowns solved for.
    """

    def __init__(self, obs: Observations, board_points: np.ndarray, C: int, V: int, free: np.ndarray,
                 tie: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
                 prior: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
                 obs_weight: np.ndarray | None = None):
        self.obs, self.board_points, self.C, self.V, self.free = obs, board_points, C, V, free
        # per-observation sqrt of the noise weight: residuals are whitened to px of the reference noise
        self.sqrt_w = None if obs_weight is None else np.sqrt(np.asarray(obs_weight, np.float64))[:, None]
        self.n = len(obs)
        self.nfev = 0
        self.tie = tie  # (fx index, fy index, fy / fx): fy follows fx (fixed aspect ratio)
        self.prior = prior  # (free-vector positions, prior values, sigmas): Gaussian prior terms
        full_to_free = -np.ones(C * N_CAM + V * N_BOARD, dtype=np.int64)
        full_to_free[free] = np.arange(free.size)
        # column of each (observation, local unknown): 15 camera unknowns then 6 board unknowns
        cols_full = np.concatenate([obs.cam[:, None] * N_CAM + np.arange(N_CAM),
                                    C * N_CAM + obs.view[:, None] * N_BOARD + np.arange(N_BOARD)], axis=1)
        self.cols = full_to_free[cols_full]  # (n, 21), -1 = fixed
        self.keep = self.cols >= 0

    def split(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        C, V = self.C, self.V
        return x[: C * N_CAM].reshape(C, N_CAM), x[C * N_CAM:].reshape(V, N_BOARD)

    def expand(self, x: np.ndarray) -> np.ndarray:
        """``x`` with the tied unknowns (fy of fixed-aspect cameras) set from the ones they follow."""
        if self.tie is None:
            return x
        x = x.copy()
        x[self.tie[1]] = x[self.tie[0]] * self.tie[2]
        return x

    def prior_terms(self, x: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        """Prior cost, its gradient (free,) and Hessian diagonal (free,) (Gauss-Newton scale, as the data)."""
        nf = self.free.size
        if self.prior is None:
            return 0.0, np.zeros(nf), np.zeros(nf)
        pos, x0, sigma = self.prior
        d = (x[self.free[pos]] - x0) / sigma
        g, h = np.zeros(nf), np.zeros(nf)
        np.add.at(g, pos, d / sigma)
        np.add.at(h, pos, 1 / sigma ** 2)
        return float(np.sum(d ** 2)), g, h

    def residuals(self, x: np.ndarray) -> np.ndarray:
        """(n, 2) reprojection residuals, px (times sqrt of the observation weights, when given)."""
        self.nfev += 1
        cp, bp = self.split(self.expand(x))
        r = project(cp, bp, self.obs, self.board_points) - self.obs.uv
        return r if self.sqrt_w is None else r * self.sqrt_w

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """(n, 2, 21) derivatives of each observation's residual w.r.t. its 21 local unknowns."""
        C, V, obs = self.C, self.V, self.obs
        J = np.empty((self.n, 2, N_CAM + N_BOARD))
        for j in range(N_CAM + N_BOARD):
            if j < N_CAM:
                idx = np.arange(C) * N_CAM + j
            else:
                idx = C * N_CAM + np.arange(V) * N_BOARD + (j - N_CAM)
            h = 1e-6 * np.maximum(1.0, np.abs(x[idx]))
            xp = x.copy()
            xp[idx] += h
            xm = x.copy()
            xm[idx] -= h
            hh = h[obs.cam] if j < N_CAM else h[obs.view]
            J[:, :, j] = (self.residuals(xp) - self.residuals(xm)) / (2 * hh[:, None])
        return J

    def normal_equations(self, x: np.ndarray, r: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``J^T W J`` (free x free) and ``J^T W r`` (free,) at ``x``."""
        cols, keep = self.cols, self.keep
        J = self.jacobian(x)
        Jw = J * w[:, None, None]
        # per observation 21 x 21 block of J^T W J and 21-vector of J^T W r, scattered into free unknowns
        blocks = np.einsum("nki,nkj->nij", Jw, J)
        grads = np.einsum("nki,nk->ni", Jw, r)
        ii = np.broadcast_to(cols[:, :, None], blocks.shape)
        jj = np.broadcast_to(cols[:, None, :], blocks.shape)
        m = keep[:, :, None] & keep[:, None, :]
        nf = self.free.size
        H = np.bincount(ii[m] * nf + jj[m], weights=blocks[m], minlength=nf * nf).reshape(nf, nf)
        g = np.bincount(cols[keep], weights=grads[keep], minlength=nf)
        return H, g


def _levenberg_marquardt(problem: _BundleProblem, full: np.ndarray, loss: str, f_scale_px: float,
                         max_iterations: int, tol: float) -> tuple[np.ndarray, float, int, str]:
    """Damped IRLS Gauss-Newton from ``full``; returns (solution, initial RMS px, status, message)."""
    free = problem.free
    r = problem.residuals(full)
    r_px = r if problem.sqrt_w is None else r / problem.sqrt_w
    initial_rms = float(np.sqrt(np.mean(np.sum(r_px ** 2, axis=1))))
    costs, w = robust_weights(np.sum(r ** 2, axis=1), loss, f_scale_px)
    cost = costs.sum() + problem.prior_terms(full)[0]
    lam = 1e-3
    rel = step = float("nan")
    status, message = 0, f"not converged after {max_iterations} iterations"
    for _ in progress(range(max_iterations), "bundle adjustment", unit="iteration"):
        H, g = problem.normal_equations(full, r, w)
        _, g_p, h_p = problem.prior_terms(full)
        H[np.diag_indices_from(H)] += h_p
        g = g + g_p
        diag = np.diag(H).copy()
        diag[diag <= 0] = 1.0
        improved = False
        while lam < 1e12:
            A = H + lam * np.diag(diag)
            try:
                L = np.linalg.cholesky(A)
                dx = -np.linalg.solve(L.T, np.linalg.solve(L, g))
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            trial = full.copy()
            trial[free] += dx
            r_t = problem.residuals(trial)
            costs_t, w_t = robust_weights(np.sum(r_t ** 2, axis=1), loss, f_scale_px)
            cost_t = costs_t.sum() + problem.prior_terms(trial)[0]
            if np.isfinite(cost_t) and cost_t < cost:
                improved = True
                rel = (cost - cost_t) / max(cost, 1e-300)
                step = np.linalg.norm(dx) / (np.linalg.norm(full[free]) + 1e-300)
                full, r, w, cost = trial, r_t, w_t, cost_t
                lam = max(lam / 10, 1e-12)
                break
            lam *= 10
        if not improved:
            status, message = 2, "no further decrease of the cost (converged to numerical precision)"
            break
        if rel < tol or step < tol:
            status, message = 1, f"converged (relative cost decrease {rel:.1e}, relative step {step:.1e})"
            break
    if status == 0:
        message += (f" (tolerance {tol:.0e}; last relative cost decrease {rel:.1e}, relative step {step:.1e}, "
                    f"damping {lam:.1e})")
    return full, initial_rms, status, message


def parameter_sd(problem: _BundleProblem, full: np.ndarray, loss: str, f_scale_px: float) -> np.ndarray:
    """(C, 15) standard deviations of the camera unknowns at the solution ``full`` (NaN = held).

    The Gauss-Newton posterior covariance ``(J^T W J / s^2 + P)^-1`` of the free unknowns: ``W`` the robust
    weights, ``s^2 = sum(w |r|^2) / (2 n - free)`` the residual variance per coordinate (px^2), ``P`` the priors'
    ``1 / sigma^2``. Without priors it is OpenCV's ``calibrateCameraExtended`` convention ``s^2 (J^T W J)^-1``.
    A tied fy (fixed aspect ratio) gets fx's deviation times the ratio. It says how well the board views (and
    priors) pin each unknown, for example a principal point from a few photos, not how far a biased model is
    from the truth. A variance that is not positive (a near-singular system) is NaN.
    """
    r = problem.residuals(full)
    _, w = robust_weights(np.sum(r ** 2, axis=1), loss, f_scale_px)
    A, _ = problem.normal_equations(full, r, w)
    dof = max(2 * problem.n - problem.free.size, 1)
    s2 = max(float(np.sum(w * np.sum(r ** 2, axis=1))) / dof, 1e-300)
    H = A / s2
    H[np.diag_indices_from(H)] += problem.prior_terms(full)[2]
    sd_full = np.full(full.size, np.nan)
    try:
        var = np.diag(np.linalg.inv(H))
        sd_full[problem.free] = np.where(var > 0, np.sqrt(np.abs(var)), np.nan)
    except np.linalg.LinAlgError:  # a gauge left free: no finite covariance
        pass
    if problem.tie is not None:
        fx, fy, ratio = problem.tie
        sd_full[fy] = sd_full[fx] * np.abs(ratio)
    return sd_full[: problem.C * N_CAM].reshape(problem.C, N_CAM)


def bundle_adjust(
    cam_params: np.ndarray,
    board_params: np.ndarray,
    obs: Observations,
    board_points: np.ndarray,
    fixed_pose_cams: tuple[int, ...] = (0,),
    fix_k3: bool = False,
    loss: str = "soft_l1",
    f_scale_px: float = 1.0,
    max_iterations: int = 100,
    tol: float = 1e-12,
    fixed: np.ndarray | None = None,
    tie_aspect: np.ndarray | None = None,
    prior_sigma: np.ndarray | None = None,
    obs_weight: np.ndarray | None = None,
) -> BundleResult:
    """Minimize robust reprojection error over all camera poses, intrinsics, distortion and board poses.

    Levenberg-Marquardt on the IRLS-weighted normal equations ``(J^T W J + lambda diag) dx = -J^T W r``.
    The Jacobian is sparse (each corner touches 15 camera and 6 board unknowns); it is built by central
    differences over column groups: unknown j of *all* cameras is perturbed at once (no residual depends on
    two cameras), likewise for boards, so one Jacobian costs 2 x (15 + 6) residual evaluations whatever
    the rig size. The normal matrix (unknowns x unknowns, 420 for 16 cameras x 30 poses) is solved densely
    by Cholesky. Iterates until the relative cost decrease or the relative step is below ``tol`` (status 1),
    or no step lowers the cost (status 2); status 0 = ``max_iterations`` reached first.

    cam_params (C, 15), board_params (V, 6): initial values (see :func:`project`).
    fixed_pose_cams : cameras whose pose is held (the world frame); their intrinsics stay free.
    fix_k3 : hold every camera's k3 at its initial value.
    loss, f_scale_px : robust loss (``linear``, ``soft_l1``, ``huber``, ``cauchy``) and its scale in px.
    fixed : (C, 15) bool, camera unknowns held at their initial values (known intrinsics, a principal point
        fixed at the centre, zero tangential distortion ...), on top of the above.
    tie_aspect : (C,) bool, cameras whose fy follows fx at the initial ratio fy / fx (fixed aspect ratio).
    prior_sigma : (C, 15) standard deviations of Gaussian priors at the initial values (inf = none),
        in the unknowns' units (px for fx..cy); a prior on a held unknown has no effect.
    obs_weight : (N,) relative inverse noise variance of each observation (:func:`view_angle_weights`), None =
        equal; residuals are scaled by its square root before the robust loss (``f_scale_px`` then refers to
        an observation of weight 1). The returned residuals and RMS stay plain pixels.
    """
    t0 = time.perf_counter()
    C, V = cam_params.shape[0], board_params.shape[0]
    full = np.concatenate([cam_params.ravel(), board_params.ravel()]).astype(np.float64)
    hold = np.zeros(full.size, dtype=bool)
    for c in fixed_pose_cams:
        hold[c * N_CAM: c * N_CAM + 6] = True
    if fix_k3:
        hold[np.arange(C) * N_CAM + K3_INDEX] = True
    if fixed is not None:
        hold[: C * N_CAM] |= np.asarray(fixed, dtype=bool).reshape(-1)
    tie = None
    if tie_aspect is not None and np.any(tie_aspect):
        cams = np.flatnonzero(tie_aspect)
        hold[cams * N_CAM + FY] = True
        tie = (cams * N_CAM + FX, cams * N_CAM + FY, full[cams * N_CAM + FY] / full[cams * N_CAM + FX])
    free = np.flatnonzero(~hold)
    prior = None
    if prior_sigma is not None:
        sig = np.full(full.size, np.inf)
        sig[: C * N_CAM] = np.asarray(prior_sigma, dtype=np.float64).reshape(-1)
        pos = np.flatnonzero(np.isfinite(sig[free]))
        if pos.size:
            prior = (pos, full[free[pos]].copy(), sig[free[pos]])
    problem = _BundleProblem(obs, board_points, C, V, free, tie, prior, obs_weight)
    full, initial_rms, status, message = _levenberg_marquardt(problem, full, loss, f_scale_px, max_iterations, tol)
    full = problem.expand(full)
    nfev, seconds = problem.nfev, time.perf_counter() - t0  # the solve's own (the covariance below is not)
    cam_sd = parameter_sd(problem, full, loss, f_scale_px)
    cp, bp = problem.split(full)
    res = project(cp, bp, obs, board_points) - obs.uv
    return BundleResult(cp.copy(), bp.copy(), res, float(np.sqrt(np.mean(np.sum(res ** 2, axis=1)))),
                        initial_rms, nfev, status, message, seconds, cam_sd)

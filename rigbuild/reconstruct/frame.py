"""One frame: images of all cameras -> filtered depth/confidence maps, oriented fused cloud, surface."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from rigbuild.camera import Camera
from rigbuild.errors import InputError
from rigbuild.reconstruct.consistency import stereo_consistency
from rigbuild.reconstruct.filter import _map_views, consistency_filter, views_within_angle
from rigbuild.reconstruct.fuse import (crop_mesh, keep_components, normalize_rows, pixel_normals, poisson_mesh, robust_bbox,
                                       tsdf_mesh, voxel_average)
from rigbuild.reconstruct.masks import image_problem, pinhole_foreground_mask
from rigbuild.reconstruct.params import ReconstructParams
from rigbuild.reconstruct.stereo import auto_depth_range, compute_depth_map, select_neighbours, to_gray_float, undistort_view


@dataclass
class FrameReconstruction:
    """Result of :func:`reconstruct_frame` (all world quantities in mm).

    cameras : pinhole cameras (distortion removed, same K, R, t) of the depth grids.
    depth : (N, H, W) float32 filtered camera z (0 = none); confidence : (N, H, W) float32 NCC in [0, 1]
        (0 where no depth); n_views : (N, H, W) uint8 agreeing views; mask : (N, H, W) bool foreground.
    points, normals : (P, 3) fused oriented cloud; colors : (P, 3) float in [0, 1] (RGB).
    mesh_vertices (V, 3), mesh_faces (F, 3) : the surface, cropped to the head / object.
    undistorted : per view the image resampled onto its pinhole grid (the grid of ``depth``), as given (dtype,
        channels).
    stats : coverage per view (fraction of foreground pixels with depth), ``stereo_consistency_mm`` and
        ``stereo_consistency_p90_mm`` (median and 90th percentile of the cross-view disagreement of the
        stereo's depth before filtering, :func:`rigbuild.reconstruct.consistency.stereo_consistency` over the
        filter's check views; NaN when no pair overlaps), counts and timings.
    """

    cameras: list[Camera]
    depth: np.ndarray
    confidence: np.ndarray
    n_views: np.ndarray
    mask: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    colors: np.ndarray
    mesh_vertices: np.ndarray
    mesh_faces: np.ndarray
    stats: dict = field(default_factory=dict)
    undistorted: list[np.ndarray] = field(default_factory=list)


def check_views(images: Sequence[np.ndarray | None], cameras: Sequence[Camera], names: Sequence[str] | None = None) -> list[str]:
    """Problems that make a frame unusable: one string per missing, mis-sized, black or saturated view."""
    problems = []
    for k, (img, cam) in enumerate(zip(images, cameras)):
        name = names[k] if names is not None else cam.id
        if img is None:
            problems.append(f"view {cam.id}: missing image {name}")
            continue
        if img.shape[0] != cam.height or img.shape[1] != cam.width:
            problems.append(f"view {cam.id}: image {name} is {img.shape[1]}x{img.shape[0]}, camera is "
                            f"{cam.width}x{cam.height}")
            continue
        why = image_problem(to_gray_float(img))
        if why:
            problems.append(f"view {cam.id}: image {name} is {why}")
    return problems


def _rgb01(img: np.ndarray) -> np.ndarray:
    a = np.asarray(img)
    scale = 255.0 if a.dtype == np.uint8 else (65535.0 if a.dtype == np.uint16 else 1.0)
    a = a.astype(np.float32) / scale
    if a.ndim == 2:
        return np.repeat(a[..., None], 3, axis=2)
    return a[..., ::-1][..., :3]  # OpenCV BGR -> RGB


def reconstruct_frame(images: Sequence[np.ndarray | None], cameras: Sequence[Camera], params: ReconstructParams,
                      names: Sequence[str] | None = None) -> FrameReconstruction:
    """Multi-view stereo of one frame.

    Parameters
    ----------
    images : per camera the original (distorted) image, (H, W) or (H, W, 3) BGR, uint8/uint16/float;
        None marks a missing view.
    cameras : calibrated cameras (mm), same order.
    names : per view a label for error messages (e.g. the image path).

    Raises
    ------
    InputError : a view is missing, mis-sized, all black or saturated (the caller applies ``on_bad_frame``).
    """
    problems = check_views(images, cameras, names)
    if problems:
        raise InputError("unusable frame: " + "; ".join(problems),
                         fix="re-export the frame's images or exclude the frame (on_bad_frame: skip)")
    t0, c0 = time.perf_counter(), time.process_time()
    und = [undistort_view(img, cam) for img, cam in zip(images, cameras)]
    pcams = [c for _, c in und]
    gray = [to_gray_float(u) for u, _ in und]
    sp = params.stereo
    masks = [pinhole_foreground_mask(img, cam, params.mask_threshold, dilate_px=params.mask_dilate_px,
                                     erode_px=params.mask_erode_px) for img, cam in zip(images, cameras)]
    nbrs = select_neighbours(pcams, sp.n_neighbours, sp.min_angle_deg, sp.max_angle_deg)
    t1, c1 = time.perf_counter(), time.process_time()
    def stereo_view(i: int):
        rng = sp.depth_range_mm or auto_depth_range(pcams[i], pcams, sp.auto_depth_radius_mm)
        return compute_depth_map(i, gray, pcams, nbrs[i], sp, mask=masks[i], depth_range=rng)

    results = _map_views(stereo_view, len(pcams), params.threads, desc="stereo depth maps")
    raw = [r.depth for r in results]
    scores = [r.score for r in results]
    t2, c2 = time.perf_counter(), time.process_time()
    check = views_within_angle(pcams, params.filter_max_angle_deg, params.filter_views)
    # the stereo's own depth (before the filter keeps what agrees): the stage's no-ground-truth gate
    agree = stereo_consistency(raw, pcams, check)
    cons = consistency_filter(raw, pcams, check, params.consistency_abs_mm, params.consistency_rel,
                              params.min_views, params.threads)
    def normals_and_colours(i: int):
        vv, uu = cons.pixels[i][:, 0], cons.pixels[i][:, 1]
        return pixel_normals(cons.point_maps[i], pcams[i], vv, uu), _rgb01(und[i][0])[vv, uu]

    nc = _map_views(normals_and_colours, len(pcams), params.threads)
    P = np.concatenate(cons.points) if nc else np.zeros((0, 3))
    N = np.concatenate([n for n, _ in nc]) if nc else np.zeros((0, 3))
    C = np.concatenate([c for _, c in nc]) if nc else np.zeros((0, 3))
    P, N, C = voxel_average(P, params.point_voxel_mm, N, C)
    N = normalize_rows(N)
    good = np.linalg.norm(N, axis=1) > 0
    if good.any():
        lo, hi = np.asarray(params.bbox_mm, float) if params.bbox_mm is not None else robust_bbox(P[good])
        good &= np.all((P >= lo) & (P <= hi), axis=1)
    P, N, C = P[good], N[good], C[good]
    t3, c3 = time.perf_counter(), time.process_time()
    if len(P) < 100:
        V, F = np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    else:
        bbox = (P.min(axis=0) - 5.0, P.max(axis=0) + 5.0)
        if params.surface == "tsdf":
            depths_in = [np.where(d > 0, d, 0).astype(np.float32) for d in cons.depth]
            V, F = tsdf_mesh(depths_in, pcams, bbox, params.tsdf_voxel_mm, params.tsdf_trunc_voxels)
        else:
            Ps, Ns = voxel_average(P, params.surface_voxel_mm, N)
            V, F = poisson_mesh(Ps, normalize_rows(Ns), params.poisson_depth, params.poisson_density_quantile,
                                params.poisson_scale)
        if params.crop_distance_mm > 0 and len(F):
            V, F = crop_mesh(V, F, Ps if params.surface == "poisson" else P, params.crop_distance_mm)
        elif len(F):
            V, F = keep_components(V, F, largest_only=True)  # the closed surface of the object
    t4, c4 = time.perf_counter(), time.process_time()
    depth = np.stack(cons.depth)
    conf = np.where(depth > 0, np.clip(np.stack(scores), 0, 1), 0).astype(np.float32)
    mask = np.stack(masks)
    fg = np.maximum(mask.sum(axis=(1, 2)), 1)
    coverage = (depth > 0).sum(axis=(1, 2)) / fg
    stats = {
        "coverage": {c.id: float(x) for c, x in zip(pcams, coverage)},
        "raw_coverage": {c.id: float((r > 0).sum() / f) for c, r, f in zip(pcams, raw, fg)},
        "neighbours": {c.id: [pcams[j].id for j in nb] for c, nb in zip(pcams, nbrs)},
        "stereo_consistency_mm": agree["median_mm"],
        "stereo_consistency_p90_mm": agree["p90_mm"],
        "n_points": int(len(P)),
        "n_mesh_vertices": int(len(V)),
        "n_mesh_faces": int(len(F)),
        "seconds": {"prepare": t1 - t0, "stereo": t2 - t1, "filter_fuse": t3 - t2, "surface": t4 - t3,
                    "total": t4 - t0},
        "cpu_seconds": {"prepare": c1 - c0, "stereo": c2 - c1, "filter_fuse": c3 - c2, "surface": c4 - c3,
                        "total": c4 - c0},
    }
    return FrameReconstruction(pcams, depth, conf, np.stack(cons.n_views), mask, P, N, C, V, F, stats,
                               [u for u, _ in und])

"""Parameters of the reconstruct stage (``config["params"]["reconstruct"]``): one typed definition, checked
at DAG start (:func:`rigbuild.params.validate_params`) and used by the runner (:mod:`rigbuild.reconstruct.stage`).

The config block is flat: :class:`StereoParams` fields and :class:`ReconstructParams` fields side by side.
Cheap to import (no OpenCV / open3d): rules/common.smk imports it before any job runs.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any, Mapping

from rigbuild.errors import InputError
from rigbuild.params import check_keys

WHERE = "params.reconstruct"
SURFACES = ("tsdf", "poisson")
ON_BAD_FRAME = ("skip", "fail")
INTERPOLATIONS = ("linear", "cubic")


@dataclass
class StereoParams:
    """Parameters of :func:`rigbuild.reconstruct.stereo.compute_depth_map` (the ``reconstruct`` config
    section uses the same names).

    n_neighbours : views matched against each reference view.
    min_angle_deg, max_angle_deg : allowed angle between optical axes of a reference and a neighbour.
    top_k : NCC averaged over the best ``top_k`` neighbours per pixel and hypothesis.
    levels : pyramid levels (1 = full resolution only); the sweep runs at level ``levels - 1``.
    window : NCC window side (odd), pixels, at every level.
    sweep_step_px : largest neighbour-image displacement between sweep planes at the coarsest level.
    refine_radius : hypotheses ``-R..R`` tested around the upsampled estimate on finer levels.
    refine_step_px : displacement between refinement hypotheses (pixels of that level).
    final_step_px : step of an extra sub-pixel pass at full resolution (0 = none).
    min_ncc : pixels whose best aggregated NCC is lower get no depth.
    min_texture : pixels whose reference-window standard deviation (0..1 intensities) is lower get no depth.
    depth_range_mm : (near, far) camera z range, or None for ``convergence point +- auto_depth_radius_mm``.
    auto_depth_radius_mm : half-size of the automatic depth range.
    interpolation : ``"linear"`` or ``"cubic"`` resampling of neighbour images.
    fill_sigma_px : on coarse levels, weak pixels are re-initialized from strong ones within about this
        Gaussian radius (pixels of that level) before refinement (0 = 3x3 median only).
    """

    n_neighbours: int = 2
    min_angle_deg: float = 5.0
    max_angle_deg: float = 50.0
    top_k: int = 1
    levels: int = 3
    window: int = 7
    sweep_step_px: float = 2.0
    refine_radius: int = 3
    refine_step_px: float = 0.5
    final_step_px: float = 0.0
    min_ncc: float = 0.5
    min_texture: float = 0.01
    depth_range_mm: tuple[float, float] | None = None
    auto_depth_radius_mm: float = 200.0
    interpolation: str = "linear"
    fill_sigma_px: float = 3.0

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None, source: str = "config params.reconstruct") -> "StereoParams":
        """Take the fields this class knows from ``d`` (other keys are ignored: the reconstruct block holds
        both classes' fields; :func:`from_config` rejects keys neither knows)."""
        d = dict(d or {})
        names = {f.name for f in fields(cls)}
        kw = {k: v for k, v in d.items() if k in names}
        if kw.get("depth_range_mm") is not None:
            rng = tuple(float(x) for x in kw["depth_range_mm"])
            if len(rng) != 2 or not 0 < rng[0] < rng[1]:
                raise InputError(f"depth_range_mm must be [near, far] with 0 < near < far, got {rng}", path=source)
            kw["depth_range_mm"] = rng
        p = cls(**kw)
        if p.window % 2 == 0 or p.window < 3:
            raise InputError(f"window must be odd and >= 3, got {p.window}", path=source)
        if p.interpolation not in INTERPOLATIONS:
            raise InputError(f"interpolation must be 'linear' or 'cubic', got {p.interpolation}", path=source)
        return p


@dataclass
class ReconstructParams:
    """All parameters of the stage (``config["params"]["reconstruct"]``; unknown keys are an error).

    stereo : :class:`StereoParams` (its fields are given flat in the config).
    mask_threshold : background threshold on the blurred grey image in [0, 1] (0 = no mask).
    mask_dilate_px, mask_erode_px : morphological close of the mask (see ``foreground_mask``).
    filter_max_angle_deg, filter_views : each view's depth is checked against at most ``filter_views``
        views whose optical axes are within ``filter_max_angle_deg`` (nearest first).
    consistency_abs_mm, consistency_rel : depth agreement tolerance ``abs + rel * z``.
    min_views : views (reference included) that must agree for a pixel to be kept.
    point_voxel_mm : voxel size of the fused point cloud (averaging); 0 keeps every fused pixel.
    surface : ``"tsdf"`` (open surface of the seen region) or ``"poisson"`` (closed surface).
    tsdf_voxel_mm, tsdf_trunc_voxels : TSDF resolution and truncation.
    poisson_depth, poisson_density_quantile : Poisson octree depth and density trimming (0 = closed).
    surface_voxel_mm : the fused points are averaged in voxels of this size before Poisson.
    poisson_scale : Poisson domain / point bounding box (>= 2 lets a closed surface close inside it).
    crop_distance_mm : mesh parts farther than this from the fused points are removed (0 = no crop: the
        largest component of the Poisson surface is kept, a closed surface of the object).
    bbox_mm : [[x0, y0, z0], [x1, y1, z1]] world box (head / object) points are cropped to; None = the
        robust bounding box of the fused points.
    on_bad_frame : ``"skip"`` (warn, record, go on) or ``"fail"`` (raise) for missing/black/saturated views.
    threads : views processed in parallel by stereo and filtering (the rule sets it to the job's cores
        unless the config gives it).
    """

    stereo: StereoParams = field(default_factory=StereoParams)
    mask_threshold: float = 0.08
    mask_dilate_px: int = 10
    mask_erode_px: int = 7
    filter_max_angle_deg: float = 70.0
    filter_views: int = 4
    consistency_abs_mm: float = 0.5
    consistency_rel: float = 0.002
    min_views: int = 2
    point_voxel_mm: float = 0.5
    surface: str = "poisson"
    tsdf_voxel_mm: float = 1.0
    tsdf_trunc_voxels: float = 4.0
    poisson_depth: int = 8
    surface_voxel_mm: float = 1.0
    poisson_scale: float = 1.1
    poisson_density_quantile: float = 0.0
    crop_distance_mm: float = 1.5
    bbox_mm: list | None = None
    on_bad_frame: str = "skip"
    threads: int = 2

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None, source: str = "config params.reconstruct") -> "ReconstructParams":
        """Flat dict (stereo fields and the fields above) -> params; unknown keys raise InputError with
        "did you mean"."""
        d = dict(d or {})
        own = {f.name for f in fields(cls)} - {"stereo"}
        st = {f.name for f in fields(StereoParams)}
        check_keys(d, own | st, WHERE)
        p = cls(stereo=StereoParams.from_dict({k: v for k, v in d.items() if k in st}, source),
                **{k: v for k, v in d.items() if k in own})
        if p.surface not in SURFACES:
            raise InputError(f"surface must be 'tsdf' or 'poisson', got {p.surface!r}", path=source)
        if p.on_bad_frame not in ON_BAD_FRAME:
            raise InputError(f"on_bad_frame must be 'skip' or 'fail', got {p.on_bad_frame!r}", path=source)
        if p.min_views < 1:
            raise InputError(f"min_views must be >= 1, got {p.min_views}", path=source)
        return p


def from_config(values: Mapping[str, Any] | None) -> ReconstructParams:
    """``config["params"]["reconstruct"]`` (flat, see module doc) -> :class:`ReconstructParams`."""
    return ReconstructParams.from_dict(values)

"""Parameters of the tracking stage (``config["params"]["track"]``): one typed definition, defaults here only.

:func:`from_config` builds :class:`TrackParams` from the config block and does all its checking (unknown
keys with "did you mean", nested blocks included, level names, flow presets, schedule lengths); it is cheap
(no OpenCV import), so ``rigbuild.params.validate_params`` runs it at DAG start.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping

from rigbuild.errors import InputError
from rigbuild.params import from_mapping

#: the tracking levels, coarse to fine
LEVELS = ("features", "sparse", "flow")
#: the frames the dense level measures flow from (:class:`FlowParams` ``sources``)
FLOW_SOURCES = ("previous", "anchor")
#: DIS optical-flow presets (:class:`FlowParams` ``preset``)
FLOW_PRESETS = ("ultrafast", "fast", "medium")


@dataclass
class ContrastDotParams:
    """The ``contrast`` dot detector (:func:`rigbuild.track.features.detect_dots`): peaks of the scale-normalized
    Laplacian-of-Gaussian (over ``scales_px``, px) of the contrast image ``C = 1 - I / B`` (I: brightest
    channel blurred by ``blur_sigma`` px; B: its grey closing by a ``background_px`` disc, the local skin).
    A peak is a dot when its estimated contrast reaches ``1 - darkness`` (the dot darker than ``darkness``
    times the skin around it) and ``noise_sigmas`` times the response's robust noise, the ratio of its
    principal curvatures is <= ``max_elongation`` and its blob (pixels darker than half its contrast) has
    [min_area, max_area] px. ``chroma`` > 0: the blob's darkest pixel must be less saturated than
    ``chroma`` times the skin (grey paint under white light; 0 = off)."""

    darkness: float = 0.85
    noise_sigmas: float = 3.5
    chroma: float = 0.0
    background_px: int = 15
    blur_sigma: float = 0.7
    scales_px: tuple[float, ...] = (1.0, 1.4, 2.0, 2.8)
    max_elongation: float = 3.0
    min_area: int = 3
    max_area: int = 400


DOT_DETECTORS = ("threshold", "contrast")


@dataclass
class DotParams:
    """Dot detection. ``detector``: ``threshold`` (a pixel is a dot pixel when its brightest channel is below
    ``darkness`` times the local background (max filter over ``background_px``) and its red-minus-blue is below
    ``chroma`` times the background; components with area in [min_area, max_area] px and fill ratio
    (area / bounding-box area) >= ``min_fill`` are dots: grey paint on a bright painted speckle) or
    ``contrast`` (:class:`ContrastDotParams`: dots of any hue under shading, highlights and a sensor)."""

    detector: str = "threshold"
    darkness: float = 0.35
    chroma: float = 0.12
    background_px: int = 15
    blur_sigma: float = 1.0
    min_area: int = 3
    max_area: int = 400
    min_fill: float = 0.35
    contrast: ContrastDotParams = field(default_factory=ContrastDotParams)


@dataclass
class SparseSchedule:
    """Per-round search radius (px, relative to a 1280-px-wide image), descriptor threshold (L2 on
    OpenCV's SIFT descriptors, ~0-700) and lambda. ``max_features``: the strongest keypoints kept per view
    (0 = all); SIFT runs on the box around the observed surface only, resized by ``image_scale`` (OpenCV's
    SIFT doubles its input for the first octave, so 0.5 detects at the image's own resolution; 1 costs 4x)."""

    radius_px: tuple[float, ...] = (24.0, 12.0, 6.0)
    descriptor_threshold: tuple[float, ...] = (180.0, 230.0, 280.0)
    lam: tuple[float, ...] = (1.0, 2.0, 4.0)
    ratio: float = 0.85
    contrast_threshold: float = 0.01
    edge_threshold: float = 12.0
    max_features: int = 3000
    image_scale: float = 0.75


@dataclass
class FlowParams:
    """grid_px: match spacing (relative to a 1280-px-wide image); preset: DIS preset name (one of
    :data:`FLOW_PRESETS`); fb_sigma_px: forward-backward error scale of the weights; max_fb_px: rejection;
    motion_step: motion-field (guide) sampling step in px; scale: image scale of the residual flow;
    patch_stride: DIS patch stride (px); sources: the frames the flow is measured from (``previous``: the
    previous tracked frame, ``anchor``: the neutral anchor frame, with ``anchor``), a subset of
    :data:`FLOW_SOURCES`. Flow from the previous frame chains: each frame inherits the previous frame's
    error along the skin; flow from the anchor does not chain."""

    grid_px: float = 8.0
    preset: str = "medium"
    fb_sigma_px: float = 0.5
    max_fb_px: float = 1.5
    motion_step: int = 4
    scale: float = 1.0
    patch_stride: int = 4
    sources: tuple[str, ...] = ("previous", "anchor")


@dataclass
class RegistrationParams:
    """Neutral registration (``params.track.registration``; :func:`rigbuild.track.register.register_neutral`).

    ray_labels_are_dots : the rays' ``marker`` field holds a dot index (converted to a marker index through
        the labeling) rather than a marker index.
    iterations : non-rigid iterations; lam_schedule : data weight lambda from the first to the last iteration
        (geometric); gate_schedule_mm : closest-point distance gate (mm) from the first to the last iteration.
    dot_weight, ray_weight : weights of the landmark-point and projective-ray terms.
    affine : after the similarity, refine the landmark alignment to an affine map (12 parameters, least
        squares on the labeled dots) before the non-rigid stage.
    point_to_plane : coupled point-to-plane closest-point term instead of point targets on the tangent planes
        (which hold vertices where the previous iterate put them).
    rotate_delta : rotate the Laplacian coordinates per vertex (ARAP-like) instead of the linear form.
    visibility_mm : with depth views, the closest-point term applies to vertices observed in at least one
        view within ``max(gate, visibility_mm)`` (unobserved vertices - mouth interior, nostrils, behind the
        ears - follow the Laplacian instead of snapping onto a nearby visible surface).
    relabel_at : iterations before which the dots are labeled again from the current mesh's markers (gate
        ``relabel_gate_mm``, mm); () keeps the first labeling.
    max_normal_angle_deg : closest points whose scan normal turns further than this (degrees) from the
        vertex normal are rejected (a neighbouring surface: the other lid, the eyeball, the inner lip).
    coarse : the coarse level. ``dots`` (default): the dots are labeled by aligning the template's painted dot
        vertices to them and each constrains its vertex. ``landmarks`` (Ma et al. 2016's landmark level): the
        triangulated face landmarks (:mod:`rigbuild.track.landmarks3d`) place the template (weighted similarity,
        then affine) and constrain their table surface points (``landmark_weight`` x the table's reliability);
        the dots are unlabeled features: each pulls the closest point of the current mesh (within the
        iteration's gate, weight ``feature_dot_weight``), never a fixed vertex; their labels (for the sequence
        tracker) are only read off the registered mesh at the end.
    feature_dot_weight : weight of an unlabeled dot at the ``landmarks`` level (a triangulated dot, false
        detections included, is no surer than a closest scan point nearby).
    landmark_min_reliability : landmarks below it do not take part in the initial alignment.
    stencil_prior_weight : ``landmarks`` level only: from the first ``relabel_at`` iteration on, each dot
        matched one to one (within ``stencil_gate_mm`` of the current mesh) to a stencil site (a painted dot
        vertex of the template) pulls that vertex with this weight: the hand paints near the site, so the
        stencil is a prior, weighted below the unlabeled-dot term; 0 = no prior.
    stencil_warp : after the non-rigid iterations, slide the mesh along its surface by this fraction of the smooth
        part of the dots' offsets from their stencil sites (dots matched one to one within ``stencil_gate_mm``,
        averaged by a Gaussian of ``stencil_smoothing_mm`` over the sites, wrong matches left out): a hand
        places each dot a few mm off its site in a random direction, so single dots are no correspondences, but
        their local mean is; the scan decides the normal direction. One step (repeated steps drift away again,
        docs/decisions.md); 0 = off (the papers' registration). At the ``landmarks``
        level the fitted landmarks take part in the mean as points of zero offset (weight
        ``stencil_landmark_weight`` x reliability), so that the eyelids and lips, where no dots are painted,
        keep what the landmarks gave them.
    dot_surface_points : ``dots`` level only: each detected dot on the skin is tracked from its own closest point
        on the registered neutral (within the last gate) instead of from its stencil vertex, as the ``landmarks``
        level always does; for a ``dot_weight`` low enough that the registration does not pin each vertex to its dot.
    dot_surface_stencil_gate_mm : which detected dots get a surface point (and are tracked): 0 = every dot within
        the last gate of the registered surface; > 0 = only the dots matched one to one to a stencil site of the
        registered neutral within this distance (mm). The stencil as a prior for which detections are painted
        dots: eyebrow hairs, lashes and irises are found as dots too, near the skin but far from any site.
    """

    ray_labels_are_dots: bool = True
    iterations: int = 12
    lam_schedule: tuple[float, float] = (0.02, 2.0)
    gate_schedule_mm: tuple[float, float] = (8.0, 2.0)
    dot_weight: float = 10.0
    ray_weight: float = 1.0
    affine: bool = True
    point_to_plane: bool = True
    rotate_delta: bool = False
    visibility_mm: float = 2.0
    relabel_at: tuple[int, ...] = (4, 8)
    relabel_gate_mm: float = 3.0
    max_normal_angle_deg: float = 30.0
    coarse: str = "dots"
    landmark_weight: float = 1.0
    landmark_min_reliability: float = 0.2
    stencil_prior_weight: float = 0.0
    feature_dot_weight: float = 1.0  # chosen on bench_track's registration scene (ICT actor seed 5, sigma 2 mm)
    stencil_gate_mm: float = 6.0
    stencil_warp: float = 0.0
    stencil_smoothing_mm: float = 30.0
    stencil_landmark_weight: float = 0.3
    dot_surface_stencil_gate_mm: float = 0.0
    dot_surface_points: bool = False


#: the neutral registration's coarse levels (:class:`RegistrationParams` ``coarse``)
COARSE_LEVELS = ("dots", "landmarks")
UNTRACKED = ("shapes", "attach")


@dataclass
class TrackParams:
    """Tracking parameters (``config["params"]["track"]``). Pixel sizes are for a 1280-px-wide image and
    scale with the image width.

    template_rig : the template rig to track with (``procedural``, ``ict``, a path); None: the session's
        ``template_rig``.
    registration : :class:`RegistrationParams` of the neutral registration.
    levels : which levels run (subset of :data:`LEVELS`, coarse to fine).
    dot_radius_px : dot assignment radii, one solve per radius (coarse to fine).
    dot_weight, lam_features : weight of a dot constraint and lambda of the dot-only solves.
    max_triangulation_rms_px : dots whose multi-view reprojection RMS exceeds it are dropped.
    dots : :class:`DotParams`; sparse : :class:`SparseSchedule`; flow : :class:`FlowParams`;
    lam_flow : lambda of the flow solves; flow_iterations : flow/solve rounds.
    anchor : match against the neutral anchor frame too; anchor_weight : relative weight of those matches.
    lost_residual_mm : a frame is lost when the weighted median constraint residual exceeds it;
    lost_min_matches : ... or when fewer image matches than this survive (per view on average);
    lost_min_dot_fraction : ... or when fewer painted dots than this fraction of those found on the anchor
        (neutral) frame are found.
    neutral_check_mm : the first frame of a sequence must fit the neutral rigidly within this (90th percentile
        of the residuals of the dots found within ``neutral_check_radius_px`` of the rigid neutral's projections,
        mm), with at least ``lost_min_dot_fraction`` of the anchor frame's dots found.
    rotation_iterations : Laplacian solves per dot radius, each re-fitting the per-vertex rotations of delta.
    constant_velocity : predict a frame by constant-velocity extrapolation (default: the previous frame).
    dot_consistency : a dot assignment whose displacement from the estimate differs from its mesh
        neighbours' (median of the ``dot_neighbours`` nearest dots along the surface) by more than this
        fraction of the dot spacing is dropped before the solve (after a large motion a coarse radius assigns
        dots to their neighbours' detections; the solve then follows them with a small residual, so the
        residual test alone does not see them); 0 disables.
    dot_flow : predict the dots of the coarse assignment by optical flow from the previous frame's images
        (:meth:`SequenceTracker.dot_flow_prediction`) instead of the previous mesh; dot_flow_scale : image
        scale of that flow.
    workers : threads that share the views of the image levels (SIFT, matching, flow, lifting); the
        snakemake rule passes its ``threads``.
    confidence_scale : the per-vertex confidence (:meth:`SequenceTracker.confidence`) reaches 1 - 1/e where
        the match weight on the vertex is this fraction of the frame's median.
    untracked : how the mesh parts outside the tracked skin (teeth, gums, tongue, eyeballs, lashes) follow:
        ``shapes`` posed by the template's expression shapes fitted to the tracked face under a rigid head motion
        (:mod:`rigbuild.track.complete`), ``attach`` moved with their nearest tracked vertices.
    """

    template_rig: str | None = None
    registration: RegistrationParams = field(default_factory=RegistrationParams)
    levels: tuple[str, ...] = LEVELS
    dot_radius_px: tuple[float, ...] = (60.0, 20.0, 8.0)
    dot_weight: float = 2.0
    lam_features: float = 1.0
    max_triangulation_rms_px: float = 2.5
    dots: DotParams = field(default_factory=DotParams)
    sparse: SparseSchedule = field(default_factory=SparseSchedule)
    flow: FlowParams = field(default_factory=FlowParams)
    lam_flow: float = 2.0
    flow_iterations: int = 1
    anchor: bool = True
    anchor_weight: float = 1.0
    lost_residual_mm: float = 1.0
    lost_min_matches: int = 30
    lost_min_dot_fraction: float = 0.6
    neutral_check_mm: float = 3.0
    neutral_check_radius_px: float = 20.0
    rotation_iterations: int = 2
    constant_velocity: bool = False
    workers: int = 1
    dot_consistency: float = 0.3
    dot_neighbours: int = 5
    dot_flow: bool = True
    dot_flow_scale: float = 0.5
    confidence_scale: float = 0.5
    untracked: str = "shapes"

    def template_for(self, spec) -> str:
        """The template rig spec to track with: ``template_rig``, else the session's (a SessionSpec)."""
        return self.template_rig or spec.template_rig


def _check(p: TrackParams) -> TrackParams:
    bad = [lv for lv in p.levels if lv not in LEVELS]
    if bad or not p.levels:
        raise InputError(f"unknown tracking levels {bad}" if bad else "params.track.levels is empty",
                         path="config params.track.levels", fix=f"use a subset of {list(LEVELS)}")
    if p.dots.detector not in DOT_DETECTORS:
        raise InputError(f"unknown dot detector '{p.dots.detector}'", path="config params.track.dots.detector",
                         fix=f"use one of {list(DOT_DETECTORS)}")
    if p.flow.preset not in FLOW_PRESETS:
        raise InputError(f"unknown flow preset '{p.flow.preset}'", path="config params.track.flow.preset",
                         fix=f"use one of {list(FLOW_PRESETS)}")
    bad = [s for s in p.flow.sources if s not in FLOW_SOURCES]
    if bad or not p.flow.sources:
        raise InputError(f"unknown flow sources {bad}" if bad else "params.track.flow.sources is empty",
                         path="config params.track.flow.sources", fix=f"use a subset of {list(FLOW_SOURCES)}")
    if p.registration.coarse not in COARSE_LEVELS:
        raise InputError(f"unknown coarse level '{p.registration.coarse}'",
                         path="config params.track.registration.coarse", fix=f"use one of {list(COARSE_LEVELS)}")
    for name in ("lam_schedule", "gate_schedule_mm"):
        v = getattr(p.registration, name)
        if len(v) != 2:
            raise InputError(f"params.track.registration.{name} has {len(v)} values", path="config",
                             fix="give [first, last]: the value at the first and at the last iteration")
    if not p.dot_radius_px:
        raise InputError("params.track.dot_radius_px is empty", path="config", fix="give one radius or more")
    if p.untracked not in UNTRACKED:
        raise InputError(f"unknown params.track.untracked '{p.untracked}'", path="config params.track.untracked",
                         fix=f"use one of {list(UNTRACKED)}")
    if p.registration.stencil_warp > 0 and not p.registration.stencil_smoothing_mm > 0:
        raise InputError(f"params.track.registration.stencil_smoothing_mm is {p.registration.stencil_smoothing_mm}",
                         path="config", fix="give the stencil warp's window in mm (> 0), or stencil_warp: 0")
    for name in ("neutral_check_mm", "neutral_check_radius_px"):
        if not getattr(p, name) > 0:
            raise InputError(f"params.track.{name} is {getattr(p, name)}", path="config",
                             fix="give a positive value")
    return p


def unpainted(p: TrackParams) -> TrackParams:
    """The parameters for an unpainted face (session ``dots: none``): the same tracker without the painted-dot
    level, registered to the neutral from face landmarks (``registration.coarse: landmarks``)."""
    from dataclasses import replace

    return replace(p, levels=tuple(lv for lv in p.levels if lv != "features"),
                   registration=replace(p.registration, coarse="landmarks"))


def from_config(values: Mapping[str, Any] | None) -> TrackParams:
    """:class:`TrackParams` from ``config["params"]["track"]`` (None or {} = the defaults).

    Raises InputError on an unknown key (with "did you mean", nested blocks too), unknown level names or
    flow presets and malformed schedules."""
    return _check(from_mapping(TrackParams, values, "params.track"))

"""Every hyper-parameter of GauSem, in typed dataclasses, read from ROS-format parameter YAML files.

The files in ``params/`` use the ROS 2 layout (``/**: ros__parameters: {section: {name: value}}``) so the nodes load
them with ``--params-file`` and the offline pipeline reads the very same files through :func:`load_config`. Nested
sections become dotted ROS parameter names (``tracking.adam.iterations``); :func:`flatten` and :func:`from_flat`
convert. A parameter that moved (:data:`RENAMED`) is an error under its old name, one that names the new name.
"""
from __future__ import annotations

import copy
import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

GAP_MODES = ("gaps", "always", "never")  # when a measure for missed camera frames applies (not "off": YAML reads an
# unquoted off as false)


def check_gap_mode(name: str, mode: str) -> None:
    """ValueError naming the parameter ``name`` unless ``mode`` is one of :data:`GAP_MODES`."""
    if mode not in GAP_MODES:
        raise ValueError(f"{name} must be one of {GAP_MODES}, got {mode!r}")


def gap_mode_applies(mode: str, gap: bool) -> bool:
    """Whether a :data:`GAP_MODES` setting applies to a frame (``gap``: camera frames were missed before it)."""
    return mode == "always" or (mode == "gaps" and gap)


@dataclass
class GaussNewtonTrackingConfig:
    """What only the Gauss-Newton tracker reads (``tracking.method: gauss_newton``; ``slam.direct_alignment``)."""

    pyramid_levels: int = 3  # at least this many image pyramid levels, ...
    coarsest_width: int = 80  # ... and more while the coarsest is wider than this (pixels): 640 wide, 4 levels
    renders_per_level: int = 2  # rounds per pyramid level (per_level: each on a model view rendered at the estimate)
    level_iterations: int = 8  # ... each of this many Gauss-Newton iterations
    min_step: float = 2e-5  # a level's iterations stop at a step |xi| below this (metres + radians)
    # "per_level": the model rendered at the estimate for every round on every level; "per_frame": once, at the start,
    # at full resolution, its pyramid made by downsampling, and again at the estimate only when that moved
    # rerender_motion (translation / median model depth + rotation in radians) from where it was rendered
    model_views: str = "per_frame"
    rerender_motion: float = 0.02
    full_resolution_points: str = "checkerboard"  # per_frame: the model pixels aligned at full resolution, "all" or
    # "checkerboard" (every other one: half the cost of the finest level)
    # per_frame: a start is kept instead of the estimate only when the estimate's cost exceeds the start's by more
    # than this fraction (the two costs differ by a few per cent on noisy frames where the estimate is the better pose)
    keep_start_margin: float = 0.2
    # more starts on the coarsest level: the prediction moved this far (metres) along each camera axis, both ways,
    # and turned this far (degrees) about each, where the feature start gives no pose (tracking.feature_start off, or
    # too few matches). search: "gaps" after skipped or lost frames (a live node slower than its camera), "always", or
    # "never"
    search: str = "gaps"
    search_translation: float = 0.03
    search_rotation_deg: float = 3.0
    # compare colour divided by its local mean (a Gaussian of sigma this fraction of the image width), blind to
    # vignetting, exposure and white balance (slam.photometric); 0: raw colour
    color_normalisation_width: float = 0.1
    fused: bool = True  # on CUDA, with Triton installed: a step's normal equations in one kernel launch
    # (slam.fused_alignment); false: torch's stream of kernels (the same maths)


@dataclass
class FeatureStartConfig:
    """A tracking start from ORB feature matches with the last good frame (``slam.feature_start``): a basin of
    convergence as wide as the features match, for the frames a live node skips."""

    mode: str = "gaps"  # "gaps" (after skipped or lost frames, as gauss_newton.search), "always" or "never"
    features: int = 500  # ORB keypoints per image
    fast_threshold: int = 5  # ORB's FAST corner threshold (grey levels)
    min_image_side: int = 240  # images with a shorter side are upscaled by an integer factor for ORB
    match_ratio: float = 0.8  # nearest / second-nearest Hamming distance below this
    max_reprojection_error: float = 3.0  # RANSAC PnP inlier bound, in pixels of the (upscaled) ORB image
    min_inliers: int = 15  # fewer PnP inliers: no start
    depth_noise: float = 0.01  # metres at 1 m (growing with z²): the frame's depth refines the PnP pose; 0: off


@dataclass
class AdamTrackingConfig:
    """What only the Adam tracker reads (``tracking.method: adam``: the paper's optimiser, through the renderer)."""

    iterations: int = 60
    lr_translation: float = 1e-2
    lr_rotation: float = 1e-2
    final_lr_fraction: float = 0.02  # learning rates decay exponentially to this fraction over the iterations
    # stop when the loss improved by less than this fraction over `patience` iterations
    convergence_tolerance: float = 1e-4
    patience: int = 10


@dataclass
class TrackingConfig:
    """Frame-to-model pose optimisation (paper Eq. 2): what either method reads, then each method's own section."""

    method: str = "gauss_newton"  # "gauss_newton" (coarse-to-fine IRLS) or "adam" (through the renderer)
    # the Gauss-Newton alignment's robust weighting, also behind the tracking-health Hessian under either method:
    huber_delta: float = 0.01  # |r| below this is weighted quadratically (IRLS floor of the L1 weights)
    max_depth_residual: float = 0.1  # metres; larger depth residuals are treated as occlusions
    max_depth_slope: float = 3.0  # observed depth slopes beyond this (~72 deg) are discontinuities
    w_color: float = 1.0
    w_depth: float = 0.5
    w_semantic: float = 0.5
    silhouette_threshold: float = 0.99
    # frame-to-keyframe where the map is thin: the newest keyframe's own depth and colour fill the model view's pixels
    # outside the silhouette ("async": in worker.mode async, where a keyframe's Gaussians are tracked against before
    # any optimisation; "always"; "never")
    keyframe_fill: str = "async"
    constant_velocity: bool = True
    gauss_newton: GaussNewtonTrackingConfig = field(default_factory=GaussNewtonTrackingConfig)
    feature_start: FeatureStartConfig = field(default_factory=FeatureStartConfig)
    adam: AdamTrackingConfig = field(default_factory=AdamTrackingConfig)


@dataclass
class MappingConfig:
    """Submap initialisation and keyframe-window bundle adjustment (paper Eq. 3-4)."""

    every: int = 5  # d_map: map (and take a keyframe) every this many frames, ...
    # ... and (coverage_keyframes: "gaps" after skipped or lost frames, as tracking.gauss_newton.search, "always" or
    # "never") whenever what tracking aligns against (the map's silhouette, and the newest keyframe where
    # tracking.keyframe_fill applies) covers less than min_coverage of the view
    coverage_keyframes: str = "gaps"
    min_coverage: float = 0.6
    keyframes: str = "every"  # "every" (every-th frame, as above) or "motion": by need (slam.keyframes), when the view
    # moved keyframe_motion (translation / median depth + rotation in radians) from the last keyframe's, or
    # max_keyframe_interval frames after the last keyframe; the coverage rule applies to both
    keyframe_motion: float = 0.15
    max_keyframe_interval: int = 30
    iterations: int = 30
    init_iterations: int = 200  # the paper uses 1000 on a GPU
    window: int = 8  # keyframes sampled from the most recent this many (plus the current frame)
    init_samples_fraction: float = 1.0  # N_tot as a fraction of the image area
    sampling_gamma: float = 0.5  # n_c proportional to A_c ** gamma
    init_opacity: float = 0.5
    init_radius_scale: float = 1.0  # new Gaussians get radius init_radius_scale * depth / focal (the paper: 1)
    w_color: float = 1.0
    w_depth: float = 1.0
    w_semantic: float = 0.5
    ssim_lambda: float = 0.8  # L = lambda * L1 + (1 - lambda) * (1 - SSIM)  (Eq. 4)
    optimise_poses: bool = True
    lr_means: float = 1e-3
    lr_log_radii: float = 5e-3
    lr_opacity: float = 5e-2
    lr_colors: float = 5e-3
    lr_semantics: float = 5e-3
    lr_pose: float = 5e-4
    densify_silhouette_threshold: float = 0.5  # tau_sil
    densify_depth_margin: float = 0.05  # metres; new Gaussians where rendered depth lies this far behind the measurement
    densify_color_error: float = 0.01  # beside a lattice coarser than one pixel, after a keyframe's optimisation:
    # one-pixel Gaussians where the map covers the view but its colour residual, less its mean over the lattice
    # spacing (the part finer than the lattice), exceeds this (mean absolute, colours in [0, 1]); 0: off
    prune_opacity: float = 0.005
    prune_radius: float = 0.5  # metres
    prune_weight: float = 0.0  # a closed submap drops Gaussians adding less than this many pixels' weight to all its
    # keyframes' views together (hidden or outside them); 0: keeps them
    density_width: int = 256  # new Gaussians as dense as in an image this wide: spawned width / density_width pixels
    # apart (at least 1), that many pixels' footprint in radius (slam.densification); 0: one per pixel at any size (the
    # paper). 256: one per pixel up to 256 wide, 2.5 pixels apart at 640x480


@dataclass
class SubmapConfig:
    """Spatial-semantic submap allocation (paper §III-A)."""

    policy: str = "semantic"  # "semantic" (overlap AND class KL) or "motion" (LoopSplat's 0.5 m / 50 deg rule)
    max_overlap: float = 0.5
    overlap: str = "iou"  # r_olap: "iou" (frustum vs submap volume) or "view" (fraction of the frustum inside)
    min_class_kl: float = 0.4
    min_keyframes: int = 4  # hysteresis: a submap keeps at least this many keyframes (semantic policy; 1 = off)
    fallback_without_classes: bool = False  # semantic policy on data without classes (every pixel one class: the
    # class KL is 0): true lets the motion rule below decide; false keeps one submap (off: on TUM fr1/rpy the motion
    # rule's 3 submaps cost accuracy, 3.10 against 1.97 cm)
    motion_translation: float = 0.5
    motion_rotation_deg: float = 50.0
    boundary_iterations: int = 20  # boundary local BA on a submap that is closed: mapper iterations ...
    boundary_window: int = 4  # ... over its last this many keyframes
    memory_budget_mb: float = 256.0  # inactive submaps in CPU memory up to this; least recently used beyond go to disk
    cache_dir: str = ""  # where spilled submaps go (a private folder inside it); "" = the system temp folder


@dataclass
class SemanticsConfig:
    segmenter: str = "labels"  # "labels" (class ids with the data), "ade20k" (the shared pretrained model) or "dinov2"
    dinov2_weights: str = ""
    head_weights: str = ""
    ade20k_model: str = ""  # the ade20k segmenter's .tflite file ("": $GAUSEM_SHARED_MODELS, ../shared/models)
    segmenter_threads: int = 1  # CPU threads of the ade20k segmenter
    descriptor: str = "auto"  # "auto", "dinov2" or "fallback"


@dataclass
class RegistrationConfig:
    """Semantic-Guided Registration of two submaps (paper §III-B, Eq. 5-6) and its acceptance test."""

    top_k: int = 10  # descriptor pairs of the coarse step (Eq. 5), of which those agreeing with the loop pair ...
    consensus_translation: float = 0.3  # ... on T within this (metres) ...
    consensus_rotation_deg: float = 15.0  # ... and this are used
    views: int = 4  # fine step: at most this many distinct source keyframes of the top pairs
    lambda_sem: float = 1.0
    lambda_feat: float = 0.5
    feature_channels: int = 8  # fine step: Eq. 6's dense features on this many principal directions (0: none)
    # depth residual weight in the Gauss-Newton fine step and the keyframe alignment of intra-submap loops (Eq. 6 has
    # none; 0 drops it); as tracking's: with 0.5 the colour term biased the loops' relative poses on real frames
    # (benchmarks/loop_edges.py)
    w_depth: float = 5.0
    downsample: int = 2  # the fine step renders at the keyframe resolution divided by this
    pyramid_levels: int = 3  # at least this many pyramid levels, and more while the coarsest is wider than ...
    coarsest_width: int = 40  # ... this at the keyframe resolution (this over downsample in the fine step), pixels
    renders_per_level: int = 1  # target re-renders (re-linearisations) per pyramid level
    iterations: int = 10  # Gauss-Newton iterations per view and pyramid level
    silhouette_threshold: float = 0.95  # pixels rendered with a lower alpha are not compared
    max_depth_residual: float = 0.1  # metres: larger depth differences are occlusions, not overlap
    max_semantic_residual: float = 0.3  # L1 over RGB: semantic colours closer than this are the same class
    min_overlap: float = 0.2  # accept when the target renders at least this fraction of the source views ...
    min_fitness: float = 0.8  # ... and agrees in depth and class on at least this fraction of that overlap
    max_spread_translation: float = 0.025  # metres: accept when the per-view estimates agree this well ...
    max_spread_rotation_deg: float = 1.0  # ... and this well
    sigma_translation: float = 0.01  # floors of the loop-edge standard deviations (metres, radians)
    sigma_rotation: float = 0.005


@dataclass
class BowConfig:
    """Place recognition without weights (``slam.loop.words``, ``slam.loop.verification``): a bag of binary ORB
    words with a vocabulary built online, and geometric verification of a candidate before registration."""

    features: int = 500  # ORB keypoints per keyframe
    fast_threshold: int = 5  # ORB's FAST corner threshold (grey levels); low: weakly textured images keep features
    min_image_side: int = 240  # images with a shorter side are upscaled by an integer factor for ORB
    word_radius: int = 40  # bits: a descriptor this close (Hamming) to a word is that word, else a new word
    min_score: float = 0.05  # candidates: tf-idf L1 similarity at least this (in [0, 1]) ...
    min_relative_score: float = 0.75  # ... and at least this fraction of the best keyframe's score (DBoW2-style) ...
    candidates: int = 3  # ... the best this many (after the landmark re-ranking) are verified, in order
    match_ratio: float = 0.8  # feature matches: nearest / second-nearest Hamming distance below this
    max_reprojection_error: float = 3.0  # RANSAC PnP inlier bound, in pixels of the (upscaled) ORB image
    min_inliers: int = 20  # a verified candidate has at least this many PnP inliers ...
    min_overlap: float = 0.2  # ... and under their pose this fraction of the match keyframe's depth lands in the
    min_fitness: float = 0.7  # query's view, agreeing in depth (registration.max_depth_residual) on this fraction
    depth_noise: float = 0.01  # metres at 1 m (growing with z²): the query's depth refines the PnP pose; 0: off


@dataclass
class LoopConfig:
    """Semantic-aware loop closure (paper §III-C, Algorithm 1)."""

    enabled: bool = True  # ablation "w/o loop closure" when false
    # "auto": the semantic image's global descriptor when it is DINOv2 (weights given), else "bow" (the images' bag of
    # ORB words, verified geometrically); "descriptor": the global descriptor of semantics.descriptor (Algorithm 1)
    place_recognition: str = "auto"
    keyframe_every: int = 5  # d_k: mapping keyframes whose frame index is a multiple of this enter the database
    check_every: int = 6
    # true: at the end of a run (``finish``), check the loop keyframes stored since the last check, whose turn never
    # came (off: the loop it closed on 7-Scenes cost accuracy, its edge being centimetres off; docs/decisions.md)
    check_at_end: bool = False
    max_descriptor_distance: float = 0.2  # loop candidates: DINOv2 CLS distance below this (paper)
    max_fallback_descriptor_distance: float = 0.35  # ... colour-layout fallback distance below this (its own scale)
    exclude_recent: int = 6
    # > 0: past keyframes whose estimated camera centre lies within this many metres of the keyframe's, looking within
    # proximity_max_angle_deg of its direction, are loop candidates too, at every keyframe (0: descriptors only)
    proximity_radius: float = 0.0
    proximity_max_angle_deg: float = 30.0
    robust_kernel: str = "huber"
    odometry_sigma_translation: float = 0.01  # pose-graph odometry edges per keyframe step (metres, radians)
    odometry_sigma_rotation: float = 0.005
    max_correction_sigmas: float = 4.0  # reject loops implying a larger jump than this many odometry sigmas
    remap_iterations_per_keyframe: int = 10  # mapping with fixed poses after an intra-submap loop, per displaced keyframe
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)
    bow: BowConfig = field(default_factory=BowConfig)

    def place_recognition_for(self, descriptor_kind: str) -> str:
        """What finds loop candidates with global descriptors of ``descriptor_kind``: "bow", or that kind ("dinov2",
        "fallback"). ``place_recognition`` "auto" picks the descriptor when it is DINOv2, else "bow"."""
        if self.place_recognition not in ("auto", "descriptor", "bow"):
            raise ValueError(f"loop.place_recognition must be auto, descriptor or bow, got {self.place_recognition!r}")
        if self.place_recognition == "bow" or (self.place_recognition == "auto" and descriptor_kind != "dinov2"):
            return "bow"
        return descriptor_kind

    def descriptor_threshold(self, kind: str) -> float:
        """The loop-candidate distance threshold for signatures of this kind ("dinov2", "fallback" or "bow", whose
        distance is 1 - score)."""
        thresholds = {"dinov2": self.max_descriptor_distance, "fallback": self.max_fallback_descriptor_distance,
                      "bow": 1.0 - self.bow.min_score}
        if kind not in thresholds:
            raise ValueError(f"unknown descriptor kind {kind!r}; expected one of {', '.join(thresholds)}")
        return thresholds[kind]


@dataclass
class RefinementConfig:
    """Two-stage global map refinement after the last frame (paper §III-C; ``slam.refinement``), with or without loop
    closure. Stage 1's feature weight is ``loop.registration.lambda_feat``; stage 2 registers with
    ``loop.registration``."""

    enabled: bool = True  # ablation "w/o global refinement" when false
    iterations_per_keyframe: int = 10  # both stages
    w_depth: float = 1.0  # lambda_D of L_map in stage 1 (the mapping keeps mapping.w_depth)
    final_lr_means_fraction: float = 1.0  # stage 1: the centres' learning rate decays to this fraction
    final_lr_pose_fraction: float = 1.0  # ... and the keyframe poses' to this one


@dataclass
class RelocalisationConfig:
    """Placing a frame against the map without the motion model: after a tracking loss, or a restart (a loaded
    session); and what follows when that keeps failing."""

    candidates: int = 5  # start poses: the last tracked pose plus this many keyframes nearest by global descriptor
    inlier_depth: float = 0.05  # metres: a pixel is an inlier when the map renders there within this of its depth ...
    inlier_alpha: float = 0.5  # ... with at least this silhouette (opacity)
    min_inlier_fraction: float = 0.6  # accept the best start when this fraction of the valid-depth pixels are inliers
    new_segment_after: int = 5  # at this many failed relocalisations in a row, the frame (with depth enough for a
    # map: health.degraded_valid_depth) starts a new, disconnected tracking segment at the last good pose, which a
    # loop to the old map merges with it (0: never; the frames are dropped until one is relocalised)


@dataclass
class HealthConfig:
    """Per-frame tracking health (``slam.health``): ok / degraded / lost. A lost frame is not mapped and the next
    frames are relocalised. Defaults are conservative: clean sequences stay ok or degraded, never lost."""

    inlier_depth: float = 0.05  # metres: a silhouette pixel is an inlier when its rendered depth is this close ...
    inlier_color: float = 0.15  # ... or, without valid depth, its rendered colour (mean absolute difference, 0..1)
    window: int = 30  # recent frames behind the residual's median/MAD and the typical motion
    min_history: int = 5  # frames before the residual z-score and the pose jump are judged
    min_translation: float = 0.01  # metres: floor of the typical per-frame translation that scales the pose jump
    min_rotation: float = 1.0  # degrees: floor of the typical per-frame rotation
    degraded_inlier_fraction: float = 0.7  # degraded below this inlier fraction ...
    lost_inlier_fraction: float = 0.3  # ... lost below this one
    degraded_residual_z: float = 5.0  # degraded when the tracking residual's robust z-score exceeds this
    degraded_condition: float = 8.0  # degraded when log10 of the (depth-scaled) Hessian's condition number exceeds this
    degraded_jump: float = 5.0  # degraded when the pose departs from the motion model by this many typical motions ...
    lost_jump: float = 15.0  # ... lost beyond this many
    degraded_valid_depth: float = 0.3  # degraded below this fraction of pixels with valid depth ...
    lost_valid_depth: float = 0.05  # ... lost below this one
    degraded_coverage: float = 0.3  # degraded when what tracking aligns against covers less than this fraction of the
    # image at the pose (benchmarks/results/health_160x120.json: the worst tracked frames of the noisy walk, 0.21-0.26)
    lost_coverage: float = 0.001  # ... lost below this one (no map in view, as after a camera jumped off it; thin
    # maps, e.g. 80x60 ones mapped for a few iterations, cover 1-5 % of a view and track well)
    recovery_inlier_fraction: float = 0.3  # after a loss, relocalisation accepts from this inlier fraction (its own)
    recovery_residual_z: float = 20.0  # ... and only with a residual z-score (against the frames before) up to this


@dataclass
class DepthFilterConfig:
    """Edge-preserving smoothing of each frame's depth before tracking and mapping (``slam.depth_filter``)."""

    enabled: bool = True
    spatial_sigma: float = 0.01  # fraction of the image width (1.6 pixels at 160x120, 6.4 at 640x480)
    range_sigma: float = 0.005  # metres at 1 m range, growing with range squared like the sensor's noise
    # whose depth: "all" frames' before tracking; "keyframes": only a keyframe's, after tracking, before it is mapped
    # (the tracker aligns the raw depth and the filter costs nothing on other frames); "async": keyframes' in
    # worker.mode async (a tracker on the camera's clock), all frames' in sync
    frames: str = "async"


@dataclass
class VignettingConfig:
    """The camera's radial brightness falloff V(r) = exp(a r^2), divided out of each frame's colour before tracking and
    mapping (``slam.vignetting``); r: distance from the principal point over the half diagonal."""

    calibrate: bool = True  # estimate a online from pairs of keyframes; false: keep ``initial``
    initial: float = 0.0  # a at start, and the estimate's prior (a known calibration; -0.29: corners at 75 %)
    min_coverage: float = 0.1  # a keyframe pair is used when at least this fraction of the pixels are points both see


@dataclass
class WorkerConfig:
    """Where the back end runs (``slam.worker``): ``sync`` maps each keyframe before the next frame is tracked
    (deterministic; offline runs and benchmarks), ``async`` on a mapping thread beside the tracker (live use)."""

    mode: str = "sync"  # "sync" or "async"
    queue_size: int = 2  # keyframes waiting for the worker; a newer one supersedes the newest waiting beyond this
    min_iteration_fraction: float = 0.25  # while a newer keyframe waits, an optimisation stops after this fraction
    tracker_threads: int = 0  # async: torch intra-op threads of the tracker (0: half the cores, rounded up) ...
    threads: int = 0  # ... and of the worker (0: half the cores)
    publish_every: int = 20  # async: a new submap's first optimisation publishes its Gaussians every this many steps
    idle_iterations: int = 10  # async: while no keyframe waits, the worker goes on optimising the newest keyframes'
    # window in rounds of this many steps (anytime mapping; 0: off) ...
    max_idle_iterations: int = 300  # ... at most this many per newest keyframe (a camera at rest leaves the core free)
    first_opacity: float = 0.9  # async: a new submap's Gaussians start this opaque, so that the tracker can track
    # against them before any optimisation (at 0.5 the map reaches its 0.99 silhouette only after some 40-80 steps)


WORKER_MODES = ("sync", "async")


@dataclass
class GridConfig:
    """The 2D occupancy grid for navigation (``maps.occupancy``): cells holding opaque Gaussians between two heights
    above the floor are occupied, cells the keyframes' depth rays crossed between those heights are free."""

    resolution: float = 0.05  # metres per cell
    min_height: float = 0.1  # metres above the floor: the band whose Gaussians occupy a cell ...
    max_height: float = 1.5  # ... up to this height (a robot's height)
    occupied_opacity: float = 0.5  # Gaussians at least this opaque occupy their cell
    floor_class: str = "floor"  # the class whose Gaussians give the floor plane; "" or absent from the class table:
    # the dominant plane within max_tilt_deg of the cameras' up, below them
    max_tilt_deg: float = 30.0  # the floor's normal within this angle of the keyframes' mean image-up direction
    plane_threshold: float = 0.03  # metres: a Gaussian this close to a plane supports it
    pixel_stride: int = 2  # free space: every this-many-th pixel of each keyframe's depth, both ways, casts a ray
    max_range: float = 5.0  # metres: rays clear free space this far at most


@dataclass
class SlamConfig:
    backend: str = "auto"  # renderer back-end: "auto", "torch", "cpu" or "gsplat"
    device: str = "auto"  # "auto" (CUDA when available), "cpu" or "cuda"
    seed: int = 0
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
    submaps: SubmapConfig = field(default_factory=SubmapConfig)
    semantics: SemanticsConfig = field(default_factory=SemanticsConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)
    refinement: RefinementConfig = field(default_factory=RefinementConfig)
    relocalisation: RelocalisationConfig = field(default_factory=RelocalisationConfig)
    health: HealthConfig = field(default_factory=HealthConfig)
    depth_filter: DepthFilterConfig = field(default_factory=DepthFilterConfig)
    vignetting: VignettingConfig = field(default_factory=VignettingConfig)
    worker: WorkerConfig = field(default_factory=WorkerConfig)
    grid: GridConfig = field(default_factory=GridConfig)


@dataclass
class SensorConfig:
    """A Kinect-v1-like RGB-D sensor for the synthetic generator's noisy variants (``gausem_core.data.sensor``).

    Not part of :class:`SlamConfig` (it describes the data, not the system). Each effect has an on/off flag; the
    defaults are those of a Kinect v1 (structured light, 640x480) where a source gives them, marked "assumed" where
    none does. Pixel quantities of the depth sensor are in its own 640-pixel-wide IR image, whatever the render size.
    """

    # --- depth ---
    range_dropout: bool = True
    min_range: float = 0.5  # metres; nearer readings are missing (Kinect v1 range 0.5-5 m, Khoshelham & Elberink 2012)
    max_range: float = 4.5  # metres; farther readings are missing (ibid.: useful range ends at about 4-5 m)
    dropout_start: float = 3.5  # metres; the chance of a missing reading rises linearly from 0 here to 1 at max_range
    # (assumed: the projected pattern's return falls with range, so correlation fails more often far away)
    grazing_holes: bool = True
    max_incidence_deg: float = 75.0  # no reading where the ray meets the surface more obliquely than this (Nguyen,
    # Izadi & Lovell 2012: the axial noise grows sharply beyond about 70 deg)
    edge_holes: bool = True
    edge_band: float = 3.0  # IR pixels on each side of a depth discontinuity without readings, on average (assumed:
    # about half the 9x9 correlation window of the Kinect's disparity matching, Konolige & Mihelich 2011)
    depth_jump: float = 0.05  # neighbouring depths differing by more than this fraction are a discontinuity
    projector_shadows: bool = True
    baseline: float = 0.075  # metres, IR projector along +x of the IR camera (Konolige & Mihelich 2011: 7.5 cm)
    axial_noise: bool = True
    # sigma_z = a + b (z - z0)^2 + c theta^2 / (sqrt(z) (pi/2 - theta)^2), z in metres, theta the incidence angle
    # (Nguyen, Izadi & Lovell 2012, fitted on a Kinect v1; the quadratic growth with range as in Khoshelham &
    # Elberink 2012)
    axial_noise_a: float = 0.0012
    axial_noise_b: float = 0.0019
    axial_noise_z0: float = 0.4
    axial_noise_c: float = 0.0001
    disparity_quantisation: bool = True
    ir_focal: float = 580.0  # IR pixels of focal length at 640x480 (Konolige & Mihelich 2011: about 580)
    ir_width: int = 640  # the IR image's width, which scales edge_band to the render
    disparity_step: float = 0.125  # IR pixels; the Kinect reports disparity in 1/8 pixel (Konolige & Mihelich 2011)
    # --- colour ---
    motion_blur: bool = True
    exposure_time: float = 0.015  # seconds (assumed: indoor auto-exposure of a 30 Hz RGB camera, 10-30 ms)
    blur_samples: int = 5  # sub-frame renders averaged over the exposure, centred on the frame's pose
    vignetting: bool = True
    vignetting_corner: float = 0.75  # relative brightness in the image corners; falloff 1 - (1 - this) r^2 with r
    # the distance from the centre over the half diagonal (assumed: of the order of the 20-40 % corner falloff that
    # Alexandrov et al. 2016 measured on PrimeSense RGB cameras)
    auto_exposure: bool = True
    exposure_target: float = 0.37  # mean luminance the exposure aims at (the clean default walk's average, measured,
    # so exposure varies around the clean renders rather than shifting them)
    exposure_rate: float = 0.2  # per frame, fraction of the log-gain error corrected (lag; assumed: settles in ~0.5 s)
    min_gain: float = 0.25
    max_gain: float = 4.0
    white_balance: bool = True
    white_balance_strength: float = 0.3  # fraction (in log) of the grey-world correction applied (assumed)
    white_balance_rate: float = 0.05  # per frame, slower than exposure (assumed)
    shot_noise: bool = True
    full_well: float = 4000.0  # electrons at full scale and unit gain (assumed: small-pixel CMOS, 2-3 um pixels)
    read_noise: float = 1.0  # 8-bit levels of Gaussian read noise after the gain (assumed)


# old name -> new name of the parameters that moved into each tracking method's own section and the refinement's
RENAMED = {
    **{f"tracking.{name}": f"tracking.gauss_newton.{name}"
       for name in ("pyramid_levels", "renders_per_level", "level_iterations", "color_normalisation_width")},
    **{f"tracking.{name}": f"tracking.adam.{name}" for name in ("iterations", "lr_translation", "lr_rotation",
                                                                "final_lr_fraction", "convergence_tolerance",
                                                                "patience")},
    "loop.global_refinement": "refinement.enabled",
    **{f"loop.refine_{name}": f"refinement.{name}" for name in ("iterations_per_keyframe", "w_depth",
                                                                "final_lr_means_fraction", "final_lr_pose_fraction")},
}


def reject_renamed(names: Iterable[str]) -> None:
    """ValueError naming each old parameter name among ``names`` with its new name (see :data:`RENAMED`)."""
    moved = [f"'{name}' is now '{RENAMED[name]}'" for name in names if name in RENAMED]
    if moved:
        raise ValueError(f"renamed parameter{'s' if len(moved) > 1 else ''}: {', '.join(moved)}")


def flatten(cfg: Any, prefix: str = "") -> dict[str, Any]:
    """Dataclass tree -> {"tracking.adam.iterations": 40, ...} (ROS parameter names)."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if dataclasses.is_dataclass(value):
            out.update(flatten(value, f"{prefix}{f.name}."))
        else:
            out[f"{prefix}{f.name}"] = value
    return out


def from_flat(values: dict[str, Any], base: SlamConfig | None = None) -> SlamConfig:
    """Apply dotted-name values onto a config (defaults when ``base`` is None); unknown and old (renamed) names are
    an error."""
    reject_renamed(values)
    cfg = copy.deepcopy(base) if base else SlamConfig()
    known = flatten(cfg)
    for name, value in values.items():
        if name not in known:
            raise ValueError(f"unknown parameter '{name}' (known: {', '.join(sorted(known))})")
        *path, leaf = name.split(".")
        node = cfg
        for part in path:
            node = getattr(node, part)
        setattr(node, leaf, _coerce(name, value, known[name]))
    return cfg


def load_config(path: str | Path | None = None, overrides: dict[str, Any] | None = None) -> SlamConfig:
    """Read a ROS-format params YAML (``/**: ros__parameters: ...``); ``overrides`` are dotted names on top."""
    values: dict[str, Any] = {}
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"parameter file {path} does not exist")
        doc = yaml.safe_load(path.read_text()) or {}
        for node_name, body in doc.items():
            if not isinstance(body, dict) or "ros__parameters" not in body:
                raise ValueError(f"{path}: '{node_name}' has no 'ros__parameters' section (ROS 2 params layout expected)")
            values.update(dotted_names(body["ros__parameters"]))
        values = {k: v for k, v in values.items() if k.split(".")[0] in _sections()}
    values.update(overrides or {})
    return from_flat(values)


def _sections() -> set[str]:
    return {f.name for f in dataclasses.fields(SlamConfig)}


def dotted_names(d: dict, prefix: str = "") -> dict[str, Any]:
    """A nested parameter tree's leaves by their dotted names (``{"a": {"b": 1}}`` -> ``{"a.b": 1}``)."""
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(dotted_names(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def _coerce(name: str, value: Any, default: Any) -> Any:
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise ValueError(f"parameter '{name}' must be true/false, got {value!r}")
        return value
    if isinstance(default, (int, float)) and not isinstance(value, bool) and isinstance(value, (int, float)):
        if isinstance(default, int) and not float(value).is_integer():
            raise ValueError(f"parameter '{name}' must be an integer, got {value!r}")
        return type(default)(value)
    if isinstance(default, str) and isinstance(value, str):
        return value
    if isinstance(default, str) and isinstance(value, bool):
        raise ValueError(f"parameter '{name}' must be a string, got {value!r} (YAML reads unquoted on/off/yes/no as "
                         "true/false: quote the value)")
    raise ValueError(f"parameter '{name}' must be of type {type(default).__name__}, got {value!r}")

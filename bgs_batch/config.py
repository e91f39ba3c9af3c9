"""All settings of a SLAM run in one typed place, presets as data, ``--set key=value`` overrides.

Field defaults are the paper's and the authors' settings (the ``paper`` preset); the ``cpu``
preset overrides a few of them for a 2-core machine. Where the paper and the authors' code
disagree, the field says which one it follows and the other is one override away.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from bgs_batch.errors import BgsError


class ConfigError(BgsError):
    """A preset name or a ``--set`` override is invalid."""

    exit_code = 2


@dataclass
class UncertaintyConfig:
    """Predictive variance (paper §III-A, §III-D; docs/method.md §2-4)."""

    initial_logit: float = -7.0  # r_i; v_i = softplus(r_i) ≈ 9.1e-4
    map_floor: float = 1e-3  # added to the rendered V_C, V_D
    unobserved_alpha: float = 0.6  # pixels with A below this are "unobserved" ...
    unobserved_variance: float = 100.0  # ... and get this variance (no gradient)
    full_grad: bool = False  # False: the authors' gradient (T_i² held constant)
    sensor_hidden: int = 32  # channels of the sensor-noise network
    sensor_min: float = 1e-4  # softplus output + this floor
    sensor_initial: float = 0.0  # untrained output; 0: PyTorch's default init (the authors')
    sensor_lr: float = 1e-4  # Adam, trained in mapping only
    sensor_downscale: int = 1  # CPU lever: evaluate the network this many times coarser
    # "none": the network predicts σ²_sensor,D itself (the paper). "nguyen": σ²_sensor,D is
    # Nguyen et al.'s (2012) Kinect noise model of the measured depth, σ = a + b(z − z0)² +
    # c/√z · θ²/(π/2 − θ)² with θ the surface's tilt from the depth's local slope, plus the
    # frame's mean of the network's depth output: the physics ranks the pixels, the network
    # learns the level (docs/method.md §3; the `cpu` preset's choice, docs/experiments.md)
    sensor_prior: Literal["none", "nguyen"] = "none"
    nguyen_a: float = 0.0012  # m
    nguyen_b: float = 0.0019  # m⁻¹
    nguyen_z0: float = 0.4  # m
    nguyen_c: float = 0.0001  # m^1.5
    # At the end of a run, fit each frozen submap's r_i (Adam at `refine_lr`) and the sensor
    # network by NLL_C + NLL_D (Eq. 13, 14) over the submap's keyframes for this many passes,
    # the geometry and colours fixed (0: off, as the authors' SLAM). Why: within mapping's
    # budget r_i hardly moves (see mapping.lr_uncertainty), and the authors measure AUSE on a
    # map re-trained with the NLL for 30k iterations; this gives the map term its iterations
    refine_passes: int = 0
    refine_lr: float = 0.05
    # At the end of a run (after the refinement), fit the gains a, b of Σ_D's map term and of
    # its sensor term's per-pixel part by the Gaussian NLL (Eq. 14) of the keyframes' depth
    # residuals, without the floors, which hide the two parts' relative scale from the NLL;
    # the reports use σ²_sensor,D (that part × b) + a·V_D + floor (`slam.calibration`)
    calibrate: bool = False
    calibration_pixels: int = 500_000  # at most this many residuals, spread over the keyframes


@dataclass
class TrackingConfig:
    """Uncertainty-normalised L1 tracking (paper Eq. 15-17; docs/method.md §6)."""

    iterations: int = 200
    rot_lr: float = 0.002
    trans_lr: float = 0.01
    lambda_color: float = 900.0
    lambda_depth: float = 900.0
    # "paper":   λ_c Σ|r_C|/√Σ_C + λ_d Σ|r_D|/√Σ_D
    # "authors": 0.6 Σ|r_C|/√(λ_c Σ_C) + 0.4 Σ|r_D|/√(λ_d Σ_D)
    loss_form: Literal["paper", "authors"] = "paper"
    authors_color_weight: float = 0.6
    downscale: int = 1  # track on images downsampled by this factor
    coarse_levels: int = 0  # extra pyramid levels (×2 each) optimised coarse to fine first
    coarse_fraction: float = 0.0  # share of the iterations spent on the coarse levels
    # Adam stops when the best loss improved by less than this share of it over
    # `early_stop_patience` iterations (0 disables); Gauss-Newton when its model predicts the
    # next step gains less than this share
    early_stop_rel: float = 0.0
    early_stop_patience: int = 0
    # each finer level's rates are this many times the coarser one's (1: the same everywhere),
    # since Adam's first steps are about lr in size whatever is left to correct; no preset uses
    # it: more precise frame to frame, worse over a sequence (docs/experiments.md)
    level_lr_factor: float = 1.0
    # LoopSplat's init_err_ratio: a frame whose loss at the initial pose exceeds this many times
    # the median best loss of the frames tracked before (both at the coarsest level) gets twice
    # the iterations on every level (0 disables); off, as in the authors' code, since it did
    # not help on fr1/rpy (docs/experiments.md)
    init_err_ratio: float = 0.0
    # Where the pose update's rotation turns the camera: about the point on the optical axis at
    # this fraction of the frame's median measured depth (exp(ξ) conjugated by that shift).
    # 0: the camera centre, the left perturbation exp(ξ)·w2c of the paper's and LoopSplat's
    # trackers. About the centre, a turn and a sideways shift move the image alike, and Adam's
    # per-coordinate steps (1 cm against 0.11°) explain a fast turn by a shift first, then creep
    # along that valley; about a point in the scene a rotation moves the image mostly by
    # parallax, so the two trade less. No preset uses it: the drift over a sequence did not
    # fall (docs/experiments.md)
    pivot_depth_ratio: float = 0.0
    # Start each frame from the constant-velocity pose refined by dense RGB-D registration of
    # the measured frame to the map rendered there (`registration`), falling back to constant
    # velocity when it is not trusted; the paper's loss still decides the pose (docs/method.md §6)
    warm_start: bool = False
    # after a trusted warm start: this many iterations at tracking resolution only (0: the
    # usual pyramid and budget)
    warm_iterations: int = 0
    # how the pose descends the loss: "adam" (the paper's and LoopSplat's Adam at trans_lr /
    # rot_lr, with early stopping) or "gauss_newton" (trust-region steps from the renderer's
    # exact gradient and the image-motion normal matrix, `slam.pose_jacobian`), used after a
    # trusted warm start only: from a start far off (3° without one) it can settle centimetres
    # away where Adam's fixed-size steps walk back, so such frames keep Adam
    optimizer: Literal["adam", "gauss_newton"] = "adam"
    gn_converged: float = 1e-4  # stop once a step's |ξ| (m and rad) is this small


@dataclass
class RegistrationConfig:
    """Tracking's warm start: the measured frame registered to the rendered map by Gauss-Newton
    on point-to-plane and photometric residuals (`bgs_batch.slam.tracking.registration`)."""

    downscale: int = 2  # relative to the tracking resolution (the refinement sees that one)
    coarsest_width: int = 24  # px: halve the tracking resolution until this narrow, then go
    # coarse to fine (a wide basin at the top; 160 px wide frames get 4 levels, 320 px 5)
    iterations: int = 10  # Gauss-Newton steps per level at most ...
    converged: float = 1e-5  # ... fewer once a step's |ξ| (m and rad) is this small
    max_distance: float = 0.07  # m; a point further from the rendered surface is not associated
    min_alpha: float = 0.9  # rendered pixels with less alpha are not map (no surface there)
    min_fitness: float = 0.5  # share of the frame's depth associated; below: constant velocity
    max_shift: float = 0.1  # m from the constant-velocity pose ...
    max_turn_deg: float = 10.0  # ... and degrees: a larger correction is not trusted


@dataclass
class MappingConfig:
    """Keyframe mapping: L_3DGS + γ(NLL_C + NLL_D) (paper Eq. 12-14; docs/method.md §5)."""

    iterations: int = 100
    new_submap_iterations: int = 100
    current_frame_share: float = 0.4  # probability of sampling the current keyframe
    gamma: float = 1e-3  # paper; the authors' code uses 1e-4
    ssim_weight: float = 0.2
    pruning_threshold: float = 0.5  # opacity, pruned at half and at the end of a round
    downscale: int = 1
    lr_means: float = 1e-4
    lr_colors: float = 2.5e-3
    lr_opacity: float = 0.05
    lr_scales: float = 5e-3
    lr_rotations: float = 1e-3
    # the authors' feature_lr for r_i; v_i hardly learns at it in the cpu budget, but faster
    # rates cost tracking more than they help the ranking (docs/experiments.md), so the
    # end-of-run refinement (uncertainty.refine_passes) trains it instead
    lr_uncertainty: float = 2.5e-3


@dataclass
class SeedingConfig:
    """Where new Gaussians come from (LoopSplat's rules, docs/method.md §5)."""

    new_submap_points: int = 100_000  # uniform random pixels of a submap's first frame
    new_submap_gradient_points: int = 50_000  # sampled ∝ colour gradient magnitude
    new_frame_points: int = 30_000  # cap for later keyframes
    alpha_threshold: float = 0.6  # later keyframes: seed where A < this ...
    depth_error_factor: float = 40.0  # ... or depth error > factor × median error
    min_distance: float = 0.01  # m; candidates closer to an existing Gaussian are dropped
    depth_push: float = 1.005  # seeds sit 0.5 % behind the surface
    initial_opacity: float = 0.5


@dataclass
class SubmapConfig:
    """When a new submap starts (LoopSplat's rule, docs/method.md §8)."""

    mode: Literal["motion", "interval"] = "motion"
    max_translation: float = 0.5  # m from the submap's first frame
    max_rotation_deg: float = 50.0
    # "angle": the rotation angle itself (axis-order free; never below any single Euler angle,
    # so it switches no later); "euler": any of roll, pitch, yaw of R = R_z R_y R_x exceeds
    # the threshold, LoopSplat's test (fewer submaps, so fewer loops: docs/experiments.md)
    rotation_measure: Literal["angle", "euler"] = "angle"
    every: int = 50  # frames, for mode "interval"


@dataclass
class KeyframeConfig:
    """Predictive-surprise keyframe selection (paper §III-C)."""

    mode: Literal["surprise", "every"] = "surprise"
    threshold: float = 0.0  # K
    max_gap: int = 5  # fallback: a keyframe at least every N frames


# --- loop closure -----------------------------------------------------------------------------
@dataclass
class LoopClosureConfig:
    """Loop closure over submaps (docs/method.md §8; `bgs_batch.slam.loop_closure`).

    At every submap switch: ORB bag-of-words place recognition over keyframes (the vocabulary is
    learnt online, no weights are downloaded), geometric verification (3-D/3-D RANSAC on depth),
    render-based registration weighted by the predictive uncertainty (ICP as fallback), Open3D
    pose-graph optimisation and rigid correction of submaps and poses.
    """

    enabled: bool = True
    descriptor: Literal["orb", "netvlad"] = "orb"  # netvlad: not supported yet (clear error)
    netvlad_weights: str = ""  # user-supplied NetVLAD weights file, for descriptor=netvlad
    final: bool = False  # also close loops after the last frame (LoopSplat's lc.final)
    # the trajectory's loop correction: "rigid" (LoopSplat's: each submap's frames move with
    # its submap, so the difference of two neighbours' corrections is a jump between two
    # frames) or "continuous" (interpolated between the submaps' centre frames, as a pose
    # graph over every frame would spread it; `loop_closure.correction.continuous_poses`)
    trajectory_correction: Literal["rigid", "continuous"] = "rigid"
    # place recognition (LoopSplat: skipped below 4 submaps, min_interval 3 on TUM)
    min_submaps: int = 4  # finished submaps before detection starts
    min_interval: int = 3  # a candidate is more than this many submaps older than the query
    self_similarity: float = 0.5  # threshold: a query keyframe's k-th best similarity to the n
    # other keyframes of its submap, k = max(int(n · this), 1) (≈ median; LoopSplat's value)
    max_candidates: int = 2  # best candidate submaps registered per switch
    orb_features: int = 500  # per keyframe, on the input image
    orb_patch: int = 31  # patch size and border of ORB (smaller for tiny images)
    orb_levels: int = 4
    orb_scale: float = 1.2
    orb_fast_threshold: int = 20
    vocabulary_words: int = 256  # binary k-majority clusters, trained on descriptors seen so far
    vocabulary_iterations: int = 8
    vocabulary_samples: int = 20_000  # descriptors used per training (evenly spaced)
    vocabulary_growth: float = 2.0  # retrain when the descriptors seen grew by this factor
    # geometric verification: descriptor matches of keyframe pairs, rigid RANSAC on depth
    verify_pairs: int = 3  # most similar keyframe pairs tried per candidate
    match_ratio: float = 0.8  # Lowe's ratio test on Hamming distances (and mutual best)
    ransac_iterations: int = 256
    ransac_threshold: float = 0.05  # m, 3-D inlier distance
    min_inliers: int = 15
    min_inlier_ratio: float = 0.25
    overlap_radius: float = 0.1  # m; overlap gate on Gaussian centres (LoopSplat: 0.32 m) ...
    min_overlap: float = 0.2  # ... share of query centres near the candidate's (LoopSplat 0.2)
    # render-based registration: query keyframes tracked in the candidate submap (Tracker loss)
    viewpoints: int = 2  # query keyframes localised and fused
    # uncertainty: Σ|r|/√Σ with our predictive variances; uniform: a constant variance instead
    # (LoopSplat's unweighted L1, for comparison)
    weighting: Literal["uncertainty", "uniform"] = "uncertainty"
    iterations: int = 40  # from the RANSAC estimate: a few cm off, fewer than tracking
    rot_lr: float = 0.015  # LoopSplat: 3 × base lr 5e-3
    trans_lr: float = 0.005
    downscale: int = 1  # relative to the mapping resolution
    coarse_levels: int = 1
    coarse_fraction: float = 0.4
    early_stop_rel: float = 1e-3
    early_stop_patience: int = 5
    min_coverage: float = 0.3  # share of valid-depth pixels the candidate renders (alpha gate)
    inlier_depth: float = 0.05  # m; a covered pixel agrees when |D̂ − D| is below this ...
    min_depth_inliers: float = 0.6  # ... and this share of covered pixels must agree
    max_disagreement_m: float = 0.1  # a viewpoint this far from the RANSAC estimate diverged
    max_disagreement_deg: float = 5.0
    # geometric fallback: point-to-plane ICP on Gaussian centres
    icp_max_distance: float = 0.05  # m
    icp_iterations: int = 30
    icp_min_fitness: float = 0.3
    icp_max_rmse: float = 0.02  # m
    icp_normal_neighbours: int = 16
    max_points: int = 20_000  # Gaussian centres per submap for ICP, overlap and information
    # pose graph (Open3D, Levenberg-Marquardt; LoopSplat's values)
    max_correspondence_distance: float = 0.03  # m; information matrices and line process
    edge_prune_threshold: float = 0.25
    preference_loop_closure: float = 5.0  # Open3D reconstruction system, registration loops
    information_prior: float = 1.0  # added to every edge's information diagonal (no overlap)
    # evaluation lever (tests, bench/loop_closure.py): odometry drift injected at every submap
    # switch, a rotation about the world y axis through the camera plus a shift along its x
    # axis; works with loop closure on or off; keep 0 for real runs
    inject_drift_deg: float = 0.0
    inject_drift_m: float = 0.0


# --- end loop closure ----------------------------------------------------------------------------


@dataclass
class SmoothingConfig:
    """Fixed-interval smoothing of the reported trajectory (`bgs_batch.slam.smoothing`): a
    constant-velocity model whose noise ratio is the tracked trajectory's own maximum-likelihood
    value, searched over log10(q / r) (q in units²/s³, r in units²) on this grid."""

    enabled: bool = False
    log_ratio_min: float = -2.0  # a smooth path even at 1 s scales ...
    log_ratio_max: float = 10.0  # ... to no smoothing at 30 frames/s (q·dt³/3 ≫ r)
    log_ratio_step: float = 0.25


@dataclass
class GlobalMapConfig:
    """The end-of-run global map (docs/method.md §8c; `bgs_batch.slam.global_map`): the
    corrected submaps merged where each owns the surface, then optimised at the reported poses
    on every frame but the held-out ones, by the mapping loss (Eq. 12-14)."""

    # over the training frames, in a seeded random order, one Adam step per visit (0: the
    # merged map as it is); the reference systems train their merged map 10k-30k iterations
    passes: float = 2.0
    # every N-th frame that is not a keyframe is held out of the stage and scored by `bgs eval`
    # on views the map never trained on (0: none held out)
    hold_out_every: int = 8
    downscale: int = 1  # render at input resolution / this (1: full resolution)
    # merge: a Gaussian lies on another submap's surface where that submap's rendered depth is
    # within this share of the Gaussian's own depth, and covers it where its alpha reaches ...
    merge_depth_tolerance: float = 0.05
    merge_min_alpha: float = 0.9
    # at the end, Gaussians below this opacity go (Gaussian-SLAM's global refinement value)
    pruning_threshold: float = 0.005
    checkpoint_every: int = 100  # visits between the job's checkpoints (and on a stop signal)


@dataclass
class ReadoutEstimationConfig:
    """The rolling-shutter readout estimated from the first frames when the store does not know
    the camera (`bgs convert … --readout auto`; `bgs_batch.slam.readout`, docs/method.md §6)."""

    frames: int = 120  # the first frames searched for turns
    pairs: int = 8  # frame pairs scored, those whose turning differs most
    min_pairs: int = 4  # fewer informative pairs: no estimate (a global shutter is kept)
    max_gap: int = 8  # frames between the two of a pair
    # rad/s by which a pair's angular velocities differ at least: the shear a readout leaves
    # differs only between frames that turn differently
    min_turn_change: float = 0.1
    candidates: int = 11  # readouts scored, evenly from 0 to one frame interval
    # the frames are registered at the largest integer downscale leaving this many pixels
    # across (after the crop): 640 → 320, fr1's 540 → 270, 320 → 320; at 160 px the
    # estimate came out 16 % low on the synthetic hard room, at 320 px 7 % (docs/experiments.md)
    min_width: int = 256
    # no estimate when the pairs' mean cost (each normalised by its minimum) varies by less
    # than this over the candidates (the frames cannot tell the readouts apart), or when the
    # standard error of the pairs' own minima exceeds this share of a frame interval
    min_contrast: float = 0.2
    max_standard_error: float = 0.1


@dataclass
class Config:
    """A whole SLAM run."""

    seed: int = 0
    # threads of the numba kernels; results never depend on it (torch always runs two,
    # `jobs.run.TORCH_THREADS`)
    threads: int = 2
    # pixels removed at every image border before anything else; None: the store's recommended
    # crop (`bgs inspect` shows it; the reference systems' crop for the camera, else 0)
    crop_edge: int | None = None
    max_depth: float = 10.0  # m; deeper readings are treated as invalid
    # Move each depth image to its colour image's time (the store's /depth_timestamp) by the
    # camera's constant-velocity motion over the gap: unsynchronised sensors (Kinect v1, TUM
    # fr1) pair images up to 20 ms apart, up to two degrees of turn at fr1/rpy's speed
    # (`slam.depth_timing`, docs/method.md §6). The gap is the stamps' difference minus
    # `depth_time_lag`, the seconds by which the driver stamps depth later after capture than
    # colour. Off in both presets: TUM's stamps are arrival times whose lag is not known well
    # enough to help on recordings nobody tuned on (docs/experiments.md)
    align_depth_time: bool = False
    depth_time_lag: float = 0.0
    # Seconds over which the camera reads its rows out, top to bottom; each frame is moved to one
    # instant by the camera's constant-velocity motion before it is tracked and mapped
    # (`slam.rolling_shutter`, docs/method.md §6). 0: a global shutter, as the paper assumes;
    # None: the store's value (`bgs inspect` shows it; the converter's for the camera, else 0),
    # estimated from the frames when the store says "unknown" (`readout_estimation`)
    rolling_shutter_readout: float | None = 0.0
    # The depth image's readout, when the depth sensor reads out otherwise than the colour one
    # (a RealSense D435: global-shutter depth, rolling-shutter colour). None: the store's
    # (`bgs inspect`), or `rolling_shutter_readout` when that is set (--set)
    depth_rolling_shutter_readout: float | None = None
    checkpoint_every: int = 10  # frames between job checkpoints (and on SIGTERM/SIGUSR1/SIGINT)
    uncertainty: UncertaintyConfig = field(default_factory=UncertaintyConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
    seeding: SeedingConfig = field(default_factory=SeedingConfig)
    submaps: SubmapConfig = field(default_factory=SubmapConfig)
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    loop_closure: LoopClosureConfig = field(default_factory=LoopClosureConfig)
    smoothing: SmoothingConfig = field(default_factory=SmoothingConfig)
    global_map: GlobalMapConfig = field(default_factory=GlobalMapConfig)
    readout_estimation: ReadoutEstimationConfig = field(default_factory=ReadoutEstimationConfig)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class Range:
    """The values a numeric setting accepts: finite, at least `low` (above it when
    `low_open`), at most `high`."""

    low: float = -math.inf
    high: float = math.inf
    low_open: bool = False

    def admits(self, value: float) -> bool:
        above = value > self.low if self.low_open else value >= self.low
        return math.isfinite(value) and above and value <= self.high

    def describe(self) -> str:
        low = "" if self.low == -math.inf else f"{'>' if self.low_open else '>='} {self.low:g}"
        high = "" if self.high == math.inf else f"<= {self.high:g}"
        return "a finite number" + (f" {low}" if low else "") + (
            f"{' and ' if low else ' '}{high}" if high else "")


ANY = Range()
COUNT = Range(1)  # iterations, sizes, factors: at least one
NON_NEGATIVE = Range(0)  # 0 usually switches the thing off
POSITIVE = Range(0, low_open=True)  # rates, distances, scales
SHARE = Range(0, 1)  # fractions, probabilities, alphas
ANGLE_DEG = Range(0, 180, low_open=True)
# Every numeric setting and what it accepts; `check` refuses the rest before a run starts
# (tests/test_config.py walks every field with NaN, inf, 0 and -1).
RANGES: dict[str, Range] = {
    "seed": Range(0, 2**32 - 1),
    "threads": Range(1, 512),
    "crop_edge": NON_NEGATIVE,  # and leaving the coarsest level a pixel (`check_crop`, per store)
    "max_depth": Range(0.1, 1000),  # m: no depth camera reads nearer than 0.1 m
    "depth_time_lag": Range(-1, 1),  # s; either sensor may lag the other
    "rolling_shutter_readout": Range(0, 1),  # s
    "depth_rolling_shutter_readout": Range(0, 1),  # s
    "checkpoint_every": COUNT,
    "uncertainty.initial_logit": ANY,
    "uncertainty.map_floor": POSITIVE,
    "uncertainty.unobserved_alpha": SHARE,
    "uncertainty.unobserved_variance": POSITIVE,
    "uncertainty.sensor_hidden": COUNT,
    "uncertainty.sensor_min": POSITIVE,
    "uncertainty.sensor_initial": NON_NEGATIVE,
    "uncertainty.sensor_lr": POSITIVE,
    "uncertainty.sensor_downscale": COUNT,
    "uncertainty.nguyen_a": POSITIVE,
    "uncertainty.nguyen_b": NON_NEGATIVE,
    "uncertainty.nguyen_z0": NON_NEGATIVE,
    "uncertainty.nguyen_c": NON_NEGATIVE,
    "uncertainty.refine_passes": NON_NEGATIVE,
    "uncertainty.refine_lr": POSITIVE,
    "uncertainty.calibration_pixels": COUNT,
    "tracking.iterations": COUNT,
    "tracking.rot_lr": POSITIVE,
    "tracking.trans_lr": POSITIVE,
    "tracking.lambda_color": POSITIVE,
    "tracking.lambda_depth": POSITIVE,
    "tracking.authors_color_weight": SHARE,
    "tracking.downscale": COUNT,
    "tracking.coarse_levels": Range(0, 6),
    "tracking.coarse_fraction": SHARE,
    "tracking.early_stop_rel": NON_NEGATIVE,
    "tracking.early_stop_patience": NON_NEGATIVE,
    "tracking.level_lr_factor": POSITIVE,
    "tracking.init_err_ratio": NON_NEGATIVE,
    "tracking.pivot_depth_ratio": NON_NEGATIVE,
    "tracking.warm_iterations": NON_NEGATIVE,
    "tracking.gn_converged": POSITIVE,
    "registration.downscale": COUNT,
    "registration.coarsest_width": Range(8),
    "registration.iterations": COUNT,
    "registration.converged": POSITIVE,
    "registration.max_distance": POSITIVE,
    "registration.min_alpha": SHARE,
    "registration.min_fitness": SHARE,
    "registration.max_shift": POSITIVE,
    "registration.max_turn_deg": ANGLE_DEG,
    "mapping.iterations": COUNT,
    "mapping.new_submap_iterations": COUNT,
    "mapping.current_frame_share": SHARE,
    "mapping.gamma": NON_NEGATIVE,
    "mapping.ssim_weight": SHARE,
    "mapping.pruning_threshold": SHARE,
    "mapping.downscale": COUNT,
    "mapping.lr_means": POSITIVE,
    "mapping.lr_colors": POSITIVE,
    "mapping.lr_opacity": POSITIVE,
    "mapping.lr_scales": POSITIVE,
    "mapping.lr_rotations": POSITIVE,
    "mapping.lr_uncertainty": POSITIVE,
    "seeding.new_submap_points": COUNT,
    "seeding.new_submap_gradient_points": NON_NEGATIVE,
    "seeding.new_frame_points": NON_NEGATIVE,
    "seeding.alpha_threshold": SHARE,
    "seeding.depth_error_factor": POSITIVE,
    "seeding.min_distance": NON_NEGATIVE,
    "seeding.depth_push": Range(0.5, 2),
    "seeding.initial_opacity": Range(0, 1, low_open=True),
    "submaps.max_translation": POSITIVE,
    "submaps.max_rotation_deg": ANGLE_DEG,
    "submaps.every": COUNT,
    "keyframes.threshold": ANY,  # K compares with a log-likelihood: any sign
    "keyframes.max_gap": COUNT,
    "loop_closure.min_submaps": NON_NEGATIVE,
    "loop_closure.min_interval": NON_NEGATIVE,
    "loop_closure.self_similarity": SHARE,
    "loop_closure.max_candidates": COUNT,
    "loop_closure.orb_features": COUNT,
    "loop_closure.orb_patch": Range(3),
    "loop_closure.orb_levels": COUNT,
    "loop_closure.orb_scale": Range(1, low_open=True),
    "loop_closure.orb_fast_threshold": COUNT,
    "loop_closure.vocabulary_words": Range(2),
    "loop_closure.vocabulary_iterations": COUNT,
    "loop_closure.vocabulary_samples": COUNT,
    "loop_closure.vocabulary_growth": Range(1, low_open=True),
    "loop_closure.verify_pairs": COUNT,
    "loop_closure.match_ratio": Range(0, 1, low_open=True),
    "loop_closure.ransac_iterations": COUNT,
    "loop_closure.ransac_threshold": POSITIVE,
    "loop_closure.min_inliers": Range(3),
    "loop_closure.min_inlier_ratio": SHARE,
    "loop_closure.overlap_radius": POSITIVE,
    "loop_closure.min_overlap": SHARE,
    "loop_closure.viewpoints": COUNT,
    "loop_closure.iterations": COUNT,
    "loop_closure.rot_lr": POSITIVE,
    "loop_closure.trans_lr": POSITIVE,
    "loop_closure.downscale": COUNT,
    "loop_closure.coarse_levels": Range(0, 6),
    "loop_closure.coarse_fraction": SHARE,
    "loop_closure.early_stop_rel": NON_NEGATIVE,
    "loop_closure.early_stop_patience": NON_NEGATIVE,
    "loop_closure.min_coverage": SHARE,
    "loop_closure.inlier_depth": POSITIVE,
    "loop_closure.min_depth_inliers": SHARE,
    "loop_closure.max_disagreement_m": POSITIVE,
    "loop_closure.max_disagreement_deg": ANGLE_DEG,
    "loop_closure.icp_max_distance": POSITIVE,
    "loop_closure.icp_iterations": COUNT,
    "loop_closure.icp_min_fitness": SHARE,
    "loop_closure.icp_max_rmse": POSITIVE,
    "loop_closure.icp_normal_neighbours": Range(3),
    "loop_closure.max_points": COUNT,
    "loop_closure.max_correspondence_distance": POSITIVE,
    "loop_closure.edge_prune_threshold": SHARE,
    "loop_closure.preference_loop_closure": POSITIVE,
    "loop_closure.information_prior": NON_NEGATIVE,
    "loop_closure.inject_drift_deg": ANY,  # a test lever: either direction
    "loop_closure.inject_drift_m": ANY,
    "smoothing.log_ratio_min": ANY,
    "smoothing.log_ratio_max": ANY,  # and above the minimum (`check`)
    "smoothing.log_ratio_step": POSITIVE,
    "global_map.passes": Range(0, 1000),
    "global_map.hold_out_every": NON_NEGATIVE,
    "global_map.downscale": COUNT,
    "global_map.merge_depth_tolerance": POSITIVE,
    "global_map.merge_min_alpha": SHARE,
    "global_map.pruning_threshold": SHARE,
    "global_map.checkpoint_every": COUNT,
    "readout_estimation.frames": COUNT,
    "readout_estimation.pairs": COUNT,
    "readout_estimation.min_pairs": COUNT,
    "readout_estimation.max_gap": Range(2),
    "readout_estimation.min_turn_change": POSITIVE,
    "readout_estimation.candidates": Range(3),
    "readout_estimation.min_width": COUNT,
    "readout_estimation.min_contrast": NON_NEGATIVE,
    "readout_estimation.max_standard_error": POSITIVE,
}


PRESETS: dict[str, dict[str, Any]] = {
    # the paper's and the authors' settings: full resolution, 200 tracking / 100 mapping iterations
    "paper": {},
    # tuned for a 2-core CPU: reduced resolution, fewer iterations, coarse-to-fine tracking
    "cpu": {
        "tracking.iterations": 60,
        "tracking.downscale": 2,
        "tracking.coarse_levels": 1,
        "tracking.coarse_fraction": 0.4,
        "tracking.early_stop_rel": 1e-4,
        "tracking.early_stop_patience": 10,
        # start from the frame registered to the rendered map; a trusted start is refined at
        # tracking resolution only (docs/method.md §6; measured in docs/experiments.md)
        "tracking.warm_start": True,
        "tracking.warm_iterations": 20,
        # and refined by Gauss-Newton steps on the paper's loss instead of Adam's fixed-size ones
        "tracking.optimizer": "gauss_newton",
        "mapping.iterations": 40,
        "mapping.new_submap_iterations": 60,
        "mapping.downscale": 2,
        "uncertainty.sensor_downscale": 4,  # the network at 80×60: ~90 → ~20 ms per mapping step
        # start the network at the map floor's scale, not at softplus(0) ≈ 0.69, from which the
        # NLL saturates it at the 1e-4 floor for good (docs/experiments.md)
        "uncertainty.sensor_initial": 1e-3,
        # the depth noise's known physics ranks the pixels (Nguyen et al. 2012) and the network
        # learns the frame's level: an untrained network ranks nothing (docs/experiments.md)
        "uncertainty.sensor_prior": "nguyen",
        # at the end, fit the frozen submaps' r_i and the sensor network by the NLL: the map
        # term gets the iterations mapping cannot give it; tracking is over by then
        "uncertainty.refine_passes": 15,
        # then set the two parts of Σ_D against each other by the NLL, without the floors that
        # hide their scales from it (docs/method.md §4; measured in docs/experiments.md)
        "uncertainty.calibrate": True,
        # a batch run is read at the end: also close loops from the last submap (LoopSplat's
        # lc.final, off in its configs)
        "loop_closure.final": True,
        # and look for loops two submaps back instead of four: LoopSplat's TUM values guard an
        # online run against false loops, and geometric verification and the render-based
        # gates check every candidate here
        "loop_closure.min_interval": 1,
        # spread each loop correction along the frames instead of stepping at submap switches
        "loop_closure.trajectory_correction": "continuous",
        "loop_closure.min_submaps": 2,
        # report every pose given the frames after it too (a batch run has them all): a
        # constant-velocity smoother at the tracked trajectory's own maximum-likelihood noise
        "smoothing.enabled": True,
        # rows read at their own instants moved to the frame's: a Kinect-class camera turning
        # at fr1/rpy's speed otherwise shows a pose biased along the turn (docs/experiments.md)
        "rolling_shutter_readout": None,
        "seeding.new_submap_points": 30_000,
        "seeding.new_submap_gradient_points": 15_000,
        "seeding.new_frame_points": 10_000,
    },
}
DEFAULT_PRESET = "cpu"


def load_config(preset: str = DEFAULT_PRESET, overrides: list[str] | None = None) -> Config:
    """The preset's config with ``key=value`` overrides applied (``tracking.iterations=50``)."""
    if preset not in PRESETS:
        raise ConfigError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    config = Config()
    for key, value in PRESETS[preset].items():
        set_value(config, key, value)
    for item in overrides or []:
        key, sep, text = item.partition("=")
        if not sep:
            raise ConfigError(f"--set {item!r}: expected key=value, e.g. tracking.iterations=50")
        set_value(config, key.strip(), parse_value(config, key.strip(), text.strip()))
    check(config)
    return config


def override_notes(config: Config, overrides: list[str]) -> list[str]:
    """What a user who set these keys should know: settings the rest of the config makes
    inert, in part or whole (printed by `bgs run`)."""
    keys = {item.partition("=")[0].strip() for item in overrides}
    notes = []
    t = config.tracking
    if "tracking.iterations" in keys and t.warm_start and t.warm_iterations:
        notes.append(f"tracking.iterations={t.iterations} applies only to frames whose warm start "
                     "is not trusted (usually few); the others are refined with "
                     f"tracking.warm_iterations={t.warm_iterations}")  # fmt: skip
    return notes


def check(config: Config) -> None:
    """Refuse values a run cannot start from, naming the key, the value and what is allowed:
    every numeric setting against `RANGES`, then combinations."""
    for key, value in _flatten(config.to_dict()).items():
        bounds = RANGES.get(key)
        if bounds is None or value is None or isinstance(value, bool | str):
            continue
        if not bounds.admits(value):
            raise ConfigError(f"{key}={value} is out of range: it must be {bounds.describe()}")
    u = config.uncertainty
    if u.sensor_initial and u.sensor_initial <= u.sensor_min:
        raise ConfigError(f"uncertainty.sensor_initial={u.sensor_initial} must exceed "
                          f"uncertainty.sensor_min={u.sensor_min} (or be 0 for the default init)")
    lc = config.loop_closure
    if lc.enabled and lc.descriptor == "netvlad":
        raise ConfigError(
            "loop_closure.descriptor=netvlad is not supported yet (NetVLAD inference is not "
            f"implemented; weights file: {lc.netvlad_weights or 'none given'}); use "
            "loop_closure.descriptor=orb, which needs no weights"
        )
    sm = config.smoothing
    if sm.log_ratio_max < sm.log_ratio_min:
        raise ConfigError(f"smoothing.log_ratio_max={sm.log_ratio_max} is below "
                          f"smoothing.log_ratio_min={sm.log_ratio_min}")


def for_store(config: Config, store: StoreFacts) -> tuple[Config, dict[str, str]]:
    """The config with the store's values filled in where it leaves them open (None), and where
    each such value came from (for ``config.json``)."""
    resolved, sources = config, {}
    for key, value in (("crop_edge", store.crop_edge),
                       ("rolling_shutter_readout", store.rolling_shutter_readout)):  # fmt: skip
        if getattr(config, key) is not None:
            sources[key] = f"set (--set {key}=…)"
        elif math.isnan(value):  # a readout the store does not know stays open: `needs_readout`
            sources[key] = (f"estimated from the frames, as {store.path.name} does not know it "
                            "(readout.json; `bgs status`)")  # fmt: skip
        else:
            resolved = dataclasses.replace(resolved, **{key: value})
            sources[key] = f"the store's value ({store.path.name}; `bgs inspect`)"
    key = "depth_rolling_shutter_readout"
    if config.depth_rolling_shutter_readout is not None:
        sources[key] = f"set (--set {key}=…)"
    elif config.rolling_shutter_readout is not None:  # set by hand: the depth follows
        resolved = dataclasses.replace(resolved, **{key: config.rolling_shutter_readout})
        sources[key] = "rolling_shutter_readout's (set)"
    elif math.isnan(store.depth_rolling_shutter_readout):
        sources[key] = sources["rolling_shutter_readout"] if math.isnan(
            store.rolling_shutter_readout) else "estimated from the frames (readout.json)"
    else:
        resolved = dataclasses.replace(resolved, **{key: store.depth_rolling_shutter_readout})
        sources[key] = f"the store's value ({store.path.name}; `bgs inspect`)"
    return resolved, sources


def needs_readout(config: Config) -> bool:
    """True when a run must estimate a rolling-shutter readout from its frames: the config
    leaves it to a store that does not know it (`for_store`)."""
    return config.rolling_shutter_readout is None or config.depth_rolling_shutter_readout is None


def separate_readouts(config: Config) -> bool:
    """True when the depth image is read out otherwise than the colour image (or its readout is
    known where the colour's is not), so that the two are rectified each with its own motion
    (`frames.prepare_frame`)."""
    depth = config.depth_rolling_shutter_readout
    return depth is not None and depth != config.rolling_shutter_readout


class StoreFacts(typing.Protocol):
    """What `for_store` reads of a frame store (`bgs_batch.store.FrameStore`)."""

    path: Path
    crop_edge: int
    rolling_shutter_readout: float
    depth_rolling_shutter_readout: float


def coarsest_factor(config: Config) -> int:
    """The largest downscale a run applies to its (cropped) input: the sensor network's input,
    tracking's coarsest pyramid level, the global stage's resolution."""
    m, t = config.mapping, config.tracking
    return max(m.downscale * config.uncertainty.sensor_downscale,
               t.downscale * 2**t.coarse_levels, config.global_map.downscale)  # fmt: skip


def check_crop(config: Config, width: int, height: int) -> None:
    """Refuse a crop (``crop_edge``, resolved) that leaves a `width` × `height` image less than
    one pixel a side at the coarsest level the run computes on (`coarsest_factor`)."""
    crop, factor = config.crop_edge or 0, coarsest_factor(config)
    side = min(width, height) - 2 * crop
    if side < factor:
        left = f"{width - 2 * crop}x{height - 2 * crop}" if side > 0 else "nothing"
        raise ConfigError(
            f"crop_edge={crop} leaves {left} of the {width}x{height} images, less than the "
            f"{factor} px a side the run's coarsest level (input / {factor}) needs; use --set "
            f"crop_edge=N with N <= {max(0, (min(width, height) - factor) // 2)}"
        )


def config_from_dict(data: dict[str, Any]) -> Config:
    """Rebuild a config saved with `Config.to_dict` (e.g. from a job's ``job.json``)."""
    config = Config()
    for key, value in _flatten(data).items():
        set_value(config, key, value)
    return config


def _flatten(data: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in data.items():
        if isinstance(value, dict):
            out |= _flatten(value, f"{prefix}{key}.")
        else:
            out[f"{prefix}{key}"] = value
    return out


def _field(config: Config, key: str) -> tuple[Any, dataclasses.Field]:
    """The dataclass owning `key` and its field, or a ConfigError listing valid keys."""
    owner: Any = config
    parts = key.split(".")
    for i, part in enumerate(parts):
        fields = {f.name: f for f in dataclasses.fields(owner)}
        if part not in fields:
            valid = ", ".join(sorted(f"{'.'.join(parts[:i] + [n])}" for n in fields))
            raise ConfigError(f"unknown config key {key!r}; valid keys here: {valid}")
        if i == len(parts) - 1:
            return owner, fields[part]
        owner = getattr(owner, part)
        if not dataclasses.is_dataclass(owner):
            raise ConfigError(f"unknown config key {key!r}: {'.'.join(parts[: i + 1])} is a value")
    raise AssertionError("unreachable")


def parse_value(config: Config, key: str, text: str) -> Any:
    """Convert the text of an override to the field's type."""
    owner, f = _field(config, key)
    kind = typing.get_type_hints(type(owner))[f.name]
    if dataclasses.is_dataclass(getattr(owner, f.name)):
        raise ConfigError(f"{key} is a section; set one of its fields, e.g. {key}.<field>=…")
    optional = type(None) in typing.get_args(kind)
    if optional:
        if text.lower() == "none":
            return None
        kind = next(k for k in typing.get_args(kind) if k is not type(None))
    try:
        if typing.get_origin(kind) is Literal:
            if text not in typing.get_args(kind):
                raise ValueError(f"choose one of {', '.join(typing.get_args(kind))}")
            return text
        if kind is bool:
            if text.lower() not in ("true", "false", "1", "0", "yes", "no"):
                raise ValueError("expected true or false")
            return text.lower() in ("true", "1", "yes")
        if kind in (int, float, str):
            return kind(text)
    except ValueError as err:
        raise ConfigError(f"--set {key}={text}: {err}") from None
    raise ConfigError(f"--set {key}: unsupported field type {kind}")


def set_value(config: Config, key: str, value: Any) -> None:
    owner, f = _field(config, key)
    setattr(owner, f.name, value)

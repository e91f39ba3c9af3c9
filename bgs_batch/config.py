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


def setting(default: Any, *accepts_and_doc: Any) -> Any:
    """A setting's one declaration: ``setting(default, [accepts,] doc)``, with the `Range` a
    numeric setting accepts and a one-line doc (`RANGES` and ``bgs settings`` read them)."""
    *accepts, doc = accepts_and_doc
    return field(default=default, metadata={"accepts": accepts[0] if accepts else None,
                                            "doc": doc})  # fmt: skip


@dataclass
class UncertaintyConfig:
    """Predictive variance (paper §III-A, §III-D; docs/method.md §2-4)."""

    initial_logit: float = setting(
        -7.0, ANY, "starting r_i of a new Gaussian; its variance v_i = softplus(r_i) ≈ 9.1e-4")
    map_floor: float = setting(1e-3, POSITIVE, "added to the rendered map variances V_C, V_D")
    unobserved_alpha: float = setting(
        0.6, SHARE, "pixels whose rendered alpha A is below this are unobserved")
    unobserved_variance: float = setting(
        100.0, POSITIVE, "the map variance of an unobserved pixel (no gradient)")
    full_grad: bool = setting(
        False, "differentiate T_i² in V too (False: the authors' gradient, T_i² held constant)")
    sensor_hidden: int = setting(32, COUNT, "channels of the sensor-noise network")
    sensor_min: float = setting(1e-4, POSITIVE, "floor added to the network's softplus output")
    sensor_initial: float = setting(
        0.0, NON_NEGATIVE, "the untrained network's output (0: PyTorch's default init, the "
        "authors')")
    sensor_lr: float = setting(
        1e-4, POSITIVE, "Adam's rate for the sensor network (trained in mapping only)")
    sensor_downscale: int = setting(
        1, COUNT, "evaluate the network this many times coarser than mapping (a CPU lever)")
    # "none": the network predicts σ²_sensor,D itself (the paper). "nguyen": σ²_sensor,D is
    # Nguyen et al.'s (2012) Kinect noise model of the measured depth, σ = a + b(z − z0)² +
    # c/√z · θ²/(π/2 − θ)² with θ the surface's tilt from the depth's local slope, plus the
    # frame's mean of the network's depth output: the physics ranks the pixels, the network
    # learns the level (docs/method.md §3; the `cpu` preset's choice, docs/experiments.md)
    sensor_prior: Literal["none", "nguyen"] = setting(
        "none", "σ²_sensor,D from the network alone ('none', the paper) or Nguyen et al.'s Kinect "
        "model times the network's frame level ('nguyen')")
    nguyen_a: float = setting(0.0012, POSITIVE, "Nguyen's constant term a (m)")
    nguyen_b: float = setting(0.0019, NON_NEGATIVE, "Nguyen's quadratic term b (m⁻¹)")
    nguyen_z0: float = setting(0.4, NON_NEGATIVE, "Nguyen's reference distance z0 (m)")
    nguyen_c: float = setting(0.0001, NON_NEGATIVE, "Nguyen's tilt term c (m^1.5)")
    # At the end of a run, fit each frozen submap's r_i (Adam at `refine_lr`) and the sensor
    # network by NLL_C + NLL_D (Eq. 13, 14) over the submap's keyframes for this many passes,
    # the geometry and colours fixed (0: off, as the authors' SLAM). Why: within mapping's
    # budget r_i hardly moves (see mapping.lr_uncertainty), and the authors measure AUSE on a
    # map re-trained with the NLL for 30k iterations; this gives the map term its iterations
    refine_passes: int = setting(
        0, NON_NEGATIVE, "end-of-run passes fitting each frozen submap's r_i and the sensor network"
        " by the NLL (0: off)")
    refine_lr: float = setting(
        0.05, POSITIVE, "Adam's rate for r_i in the end-of-run refinement (and the global stage)")
    # At the end of a run (after the refinement), fit the gains a, b of Σ_D's map term and of
    # its sensor term's per-pixel part by the Gaussian NLL (Eq. 14) of the keyframes' depth
    # residuals, without the floors, which hide the two parts' relative scale from the NLL;
    # the reports use σ²_sensor,D (that part × b) + a·V_D + floor (`slam.calibration`)
    calibrate: bool = setting(
        False, "fit the gains of Σ_D's map and sensor parts by the NLL at the end of a run")
    calibration_pixels: int = setting(
        500_000, COUNT, "depth residuals the calibration uses at most, spread over the keyframes")


@dataclass
class TrackingConfig:
    """Uncertainty-normalised L1 tracking (paper Eq. 15-17; docs/method.md §6)."""

    iterations: int = setting(
        200, COUNT, "Adam iterations per frame (doubled for a frame that starts far off)")
    rot_lr: float = setting(0.002, POSITIVE, "Adam's rate for the pose's rotation (rad)")
    trans_lr: float = setting(0.01, POSITIVE, "Adam's rate for the pose's translation (m)")
    lambda_color: float = setting(
        900.0, POSITIVE, "λ_c, the colour term's weight in the tracking loss")
    lambda_depth: float = setting(
        900.0, POSITIVE, "λ_d, the depth term's weight in the tracking loss")
    loss_form: Literal["paper", "authors"] = setting(
        "paper", "the tracking loss as the paper writes it ('paper') or as the authors' code "
        "computes it ('authors')")
    authors_color_weight: float = setting(
        0.6, SHARE, "the colour term's share w in the 'authors' loss form")
    downscale: int = setting(1, COUNT, "track on images downsampled by this factor")
    coarse_levels: int = setting(
        0, Range(0, 6), "extra pyramid levels (×2 each) optimised coarse to fine first")
    coarse_fraction: float = setting(
        0.0, SHARE, "share of the iterations spent on the coarse levels")
    # Adam stops when the best loss improved by less than this share of it over
    # `early_stop_patience` iterations (0 disables); Gauss-Newton when its model predicts the
    # next step gains less than this share
    early_stop_rel: float = setting(
        0.0, NON_NEGATIVE, "stop once the loss improves by less than this share (0: never early)")
    early_stop_patience: int = setting(
        0, NON_NEGATIVE, "iterations over which Adam's improvement is measured")
    # each finer level's rates are this many times the coarser one's (1: the same everywhere),
    # since Adam's first steps are about lr in size whatever is left to correct; no preset uses
    # it: more precise frame to frame, worse over a sequence (docs/experiments.md)
    level_lr_factor: float = setting(
        1.0, POSITIVE, "each finer pyramid level's rates are this many times the coarser one's")
    # LoopSplat's init_err_ratio: a frame whose loss at the initial pose exceeds this many times
    # the median best loss of the frames tracked before (both at the coarsest level) gets twice
    # the iterations on every level (0 disables); off, as in the authors' code, since it did
    # not help on fr1/rpy (docs/experiments.md)
    init_err_ratio: float = setting(
        0.0, NON_NEGATIVE, "a frame starting at this many times the median loss gets twice the "
        "iterations (0: off)")
    # Where the pose update's rotation turns the camera: about the point on the optical axis at
    # this fraction of the frame's median measured depth (exp(ξ) conjugated by that shift).
    # 0: the camera centre, the left perturbation exp(ξ)·w2c of the paper's and LoopSplat's
    # trackers. About the centre, a turn and a sideways shift move the image alike, and Adam's
    # per-coordinate steps (1 cm against 0.11°) explain a fast turn by a shift first, then creep
    # along that valley; about a point in the scene a rotation moves the image mostly by
    # parallax, so the two trade less. No preset uses it: the drift over a sequence did not
    # fall (docs/experiments.md)
    pivot_depth_ratio: float = setting(
        0.0, NON_NEGATIVE, "turn the camera about the optical axis at this share of the median "
        "depth (0: about its centre)")
    # Start each frame from the constant-velocity pose refined by dense RGB-D registration of
    # the measured frame to the map rendered there (`registration`), falling back to constant
    # velocity when it is not trusted; the paper's loss still decides the pose (docs/method.md §6)
    warm_start: bool = setting(
        False, "start from the constant-velocity pose corrected by dense registration to the "
        "rendered map")
    warm_iterations: int = setting(
        0, NON_NEGATIVE, "iterations after a trusted warm start, at tracking resolution only (0: "
        "the usual budget)")
    # how the pose descends the loss: "adam" (the paper's and LoopSplat's Adam at trans_lr /
    # rot_lr, with early stopping) or "gauss_newton" (trust-region steps from the renderer's
    # exact gradient and the image-motion normal matrix, `slam.pose_jacobian`), used after a
    # trusted warm start only: from a start far off (3° without one) it can settle centimetres
    # away where Adam's fixed-size steps walk back, so such frames keep Adam
    optimizer: Literal["adam", "gauss_newton"] = setting(
        "adam", "how the pose descends the loss after a trusted warm start: 'adam' or "
        "'gauss_newton'")
    gn_converged: float = setting(
        1e-4, POSITIVE, "Gauss-Newton stops once a step's |ξ| (m and rad) is this small")


@dataclass
class RegistrationConfig:
    """Tracking's warm start: the measured frame registered to the rendered map by Gauss-Newton
    on point-to-plane and photometric residuals (`bgs_batch.slam.tracking.registration`)."""

    downscale: int = setting(2, COUNT, "registration resolution relative to tracking's")
    coarsest_width: int = setting(
        24, Range(8), "halve the resolution until this narrow (px), then go coarse to fine")
    iterations: int = setting(10, COUNT, "Gauss-Newton steps per pyramid level at most")
    converged: float = setting(
        1e-5, POSITIVE, "stop a level once a step's |ξ| (m and rad) is this small")
    max_distance: float = setting(
        0.07, POSITIVE, "a point further than this from the rendered surface is not associated (m)")
    min_alpha: float = setting(
        0.9, SHARE, "rendered pixels with less alpha are not map (no surface there)")
    min_fitness: float = setting(
        0.5, SHARE, "share of the frame's depth that must associate, else constant velocity")
    max_shift: float = setting(
        0.1, POSITIVE, "a correction moving the camera further than this is not trusted (m)")
    max_turn_deg: float = setting(
        10.0, ANGLE_DEG, "a correction turning the camera more than this is not trusted (degrees)")


@dataclass
class MappingConfig:
    """Keyframe mapping: L_3DGS + γ(NLL_C + NLL_D) (paper Eq. 12-14; docs/method.md §5)."""

    iterations: int = setting(100, COUNT, "optimisation iterations per keyframe")
    new_submap_iterations: int = setting(100, COUNT, "iterations for a submap's first keyframe")
    current_frame_share: float = setting(
        0.4, SHARE, "probability of sampling the current keyframe in an iteration")
    gamma: float = setting(
        1e-3, NON_NEGATIVE, "γ, the NLL terms' weight (the paper's; the authors' code uses 1e-4)")
    ssim_weight: float = setting(0.2, SHARE, "the SSIM term's share of L_3DGS's colour loss")
    pruning_threshold: float = setting(
        0.5, SHARE, "Gaussians below this opacity are pruned at half and at the end of a round")
    downscale: int = setting(1, COUNT, "map on images downsampled by this factor")
    lr_means: float = setting(1e-4, POSITIVE, "Adam's rate for the Gaussians' centres")
    lr_colors: float = setting(2.5e-3, POSITIVE, "Adam's rate for the Gaussians' colours")
    lr_opacity: float = setting(0.05, POSITIVE, "Adam's rate for the Gaussians' opacity logits")
    lr_scales: float = setting(5e-3, POSITIVE, "Adam's rate for the Gaussians' log scales")
    lr_rotations: float = setting(1e-3, POSITIVE, "Adam's rate for the Gaussians' rotations")
    # the authors' feature_lr for r_i; v_i hardly learns at it in the cpu budget, but faster
    # rates cost tracking more than they help the ranking (docs/experiments.md), so the
    # end-of-run refinement (uncertainty.refine_passes) trains it instead
    lr_uncertainty: float = setting(
        2.5e-3, POSITIVE, "Adam's rate for the Gaussians' r_i (the authors' feature_lr)")


@dataclass
class SeedingConfig:
    """Where new Gaussians come from (LoopSplat's rules, docs/method.md §5)."""

    new_submap_points: int = setting(
        100_000, COUNT, "uniform random pixels seeded in a submap's first frame")
    new_submap_gradient_points: int = setting(
        50_000, NON_NEGATIVE, "pixels seeded there in proportion to the colour gradient")
    new_frame_points: int = setting(30_000, NON_NEGATIVE, "seeds at most in a later keyframe")
    alpha_threshold: float = setting(
        0.6, SHARE, "later keyframes seed where the rendered alpha is below this")
    depth_error_factor: float = setting(
        40.0, POSITIVE, "... or where the depth error exceeds this many times the median error")
    min_distance: float = setting(
        0.01, NON_NEGATIVE, "candidates closer than this to an existing Gaussian are dropped (m)")
    depth_push: float = setting(
        1.005, Range(0.5, 2), "seeds sit this factor of their depth away (1.005: 0.5 % behind the "
        "surface, LoopSplat's)")
    initial_opacity: float = setting(0.5, Range(0, 1, low_open=True), "opacity of a new Gaussian")
    flatness: float = setting(
        1.0, Range(0.01, 1), "a new Gaussian's scale across the measured surface, as a share of "
        "its scale along it (1: isotropic)")


@dataclass
class SubmapConfig:
    """When a new submap starts (LoopSplat's rule, docs/method.md §8)."""

    mode: Literal["motion", "interval"] = setting(
        "motion", "start a new submap after enough motion ('motion') or every N frames "
        "('interval')")
    max_translation: float = setting(
        0.5, POSITIVE, "motion mode: a new submap beyond this distance from the submap's first "
        "frame (m)")
    max_rotation_deg: float = setting(
        50.0, ANGLE_DEG, "motion mode: ... or beyond this turn from it (degrees)")
    # "angle": the rotation angle itself (axis-order free; never below any single Euler angle,
    # so it switches no later); "euler": any of roll, pitch, yaw of R = R_z R_y R_x exceeds
    # the threshold, LoopSplat's test (fewer submaps, so fewer loops: docs/experiments.md)
    rotation_measure: Literal["angle", "euler"] = setting(
        "angle", "the turn as one rotation angle ('angle') or any Euler angle ('euler', "
        "LoopSplat's)")
    every: int = setting(50, COUNT, "interval mode: frames per submap")


@dataclass
class KeyframeConfig:
    """Predictive-surprise keyframe selection (paper §III-C)."""

    mode: Literal["surprise", "every"] = setting(
        "surprise", "keyframes by predictive surprise ('surprise', the paper's) or every frame "
        "('every')")
    threshold: float = setting(0.0, ANY, "K: a frame whose surprise exceeds this is a keyframe")
    max_gap: int = setting(5, COUNT, "a keyframe at least every this many frames")


# --- loop closure -----------------------------------------------------------------------------
@dataclass
class LoopClosureConfig:
    """Loop closure over submaps (docs/method.md §8; `bgs_batch.slam.loop_closure`).

    At every submap switch: ORB bag-of-words place recognition over keyframes (the vocabulary is
    learnt online, no weights are downloaded), geometric verification (3-D/3-D RANSAC on depth),
    render-based registration weighted by the predictive uncertainty (ICP as fallback), Open3D
    pose-graph optimisation and rigid correction of submaps and poses.
    """

    enabled: bool = setting(True, "close loops between submaps")
    descriptor: Literal["orb", "netvlad"] = setting(
        "orb", "place recognition descriptor: 'orb' (learnt online) or 'netvlad' (not supported "
        "yet)")
    netvlad_weights: str = setting(
        "", "a NetVLAD weights file of the user's, for descriptor=netvlad")
    final: bool = setting(False, "also close loops after the last frame (LoopSplat's lc.final)")
    # the trajectory's loop correction: "rigid" (LoopSplat's: each submap's frames move with
    # its submap, so the difference of two neighbours' corrections is a jump between two
    # frames) or "continuous" (interpolated between the submaps' centre frames, as a pose
    # graph over every frame would spread it; `loop_closure.correction.continuous_poses`)
    trajectory_correction: Literal["rigid", "continuous"] = setting(
        "rigid", "frames move with their submap's correction ('rigid', LoopSplat's) or interpolated"
        " between submaps ('continuous')")
    # place recognition (LoopSplat: skipped below 4 submaps, min_interval 3 on TUM)
    min_submaps: int = setting(4, NON_NEGATIVE, "finished submaps before detection starts")
    min_interval: int = setting(
        3, NON_NEGATIVE, "a candidate is more than this many submaps older than the query")
    self_similarity: float = setting(
        0.5, SHARE, "a query keyframe's similarity threshold: its k-th best to the n others of its "
        "submap, k = max(int(n · this), 1)")
    max_candidates: int = setting(2, COUNT, "best candidate submaps registered per switch")
    orb_features: int = setting(500, COUNT, "ORB features per keyframe, on the input image")
    orb_patch: int = setting(31, Range(3), "ORB's patch size and border (px)")
    orb_levels: int = setting(4, COUNT, "ORB's pyramid levels")
    orb_scale: float = setting(1.2, Range(1, low_open=True), "ORB's pyramid scale factor")
    orb_fast_threshold: int = setting(20, COUNT, "ORB's FAST corner threshold")
    vocabulary_words: int = setting(
        256, Range(2), "words of the binary vocabulary (k-majority clusters of the descriptors "
        "seen)")
    vocabulary_iterations: int = setting(8, COUNT, "k-majority iterations per training")
    vocabulary_samples: int = setting(
        20_000, COUNT, "descriptors used per training (evenly spaced)")
    vocabulary_growth: float = setting(
        2.0, Range(1, low_open=True), "retrain once the descriptors seen grew by this factor")
    # geometric verification: descriptor matches of keyframe pairs, rigid RANSAC on depth
    verify_pairs: int = setting(3, COUNT, "most similar keyframe pairs verified per candidate")
    match_ratio: float = setting(
        0.8, Range(0, 1, low_open=True), "Lowe's ratio test on Hamming distances (and mutual best)")
    ransac_iterations: int = setting(256, COUNT, "rigid RANSAC iterations per keyframe pair")
    ransac_threshold: float = setting(0.05, POSITIVE, "RANSAC's 3-D inlier distance (m)")
    min_inliers: int = setting(15, Range(3), "RANSAC inliers a verified pair needs")
    min_inlier_ratio: float = setting(0.25, SHARE, "share of the matches that must be inliers")
    overlap_radius: float = setting(
        0.1, POSITIVE, "overlap gate: a query centre this near a candidate's counts (m; LoopSplat "
        "0.32)")
    min_overlap: float = setting(0.2, SHARE, "overlap gate: share of query centres that must count")
    # render-based registration: query keyframes tracked in the candidate submap (Tracker loss)
    viewpoints: int = setting(2, COUNT, "query keyframes localised in the candidate and fused")
    weighting: Literal["uncertainty", "uniform"] = setting(
        "uncertainty", "registration residuals over our predictive σ ('uncertainty') or a constant "
        "one ('uniform', LoopSplat's L1)")
    iterations: int = setting(
        40, COUNT, "registration iterations per viewpoint, from the RANSAC estimate")
    rot_lr: float = setting(
        0.015, POSITIVE, "registration's Adam rate for rotation (LoopSplat: 3 × 5e-3)")
    trans_lr: float = setting(0.005, POSITIVE, "registration's Adam rate for translation")
    downscale: int = setting(1, COUNT, "registration resolution relative to mapping's")
    coarse_levels: int = setting(1, Range(0, 6), "registration's extra coarse pyramid levels")
    coarse_fraction: float = setting(
        0.4, SHARE, "share of registration iterations on the coarse levels")
    early_stop_rel: float = setting(
        1e-3, NON_NEGATIVE, "registration stops once its loss improves by less than this share")
    early_stop_patience: int = setting(
        5, NON_NEGATIVE, "iterations over which that improvement is measured")
    min_coverage: float = setting(
        0.3, SHARE, "share of valid-depth pixels the candidate must render (alpha gate)")
    inlier_depth: float = setting(
        0.05, POSITIVE, "a covered pixel agrees when |D̂ − D| is below this (m)")
    min_depth_inliers: float = setting(0.6, SHARE, "share of covered pixels that must agree")
    max_disagreement_m: float = setting(
        0.1, POSITIVE, "a viewpoint this far from the RANSAC estimate diverged (m)")
    max_disagreement_deg: float = setting(
        5.0, ANGLE_DEG, "... or turned this far from it (degrees)")
    # geometric fallback: point-to-plane ICP on Gaussian centres
    icp_max_distance: float = setting(0.05, POSITIVE, "ICP fallback's correspondence distance (m)")
    icp_iterations: int = setting(30, COUNT, "ICP fallback's iterations")
    icp_min_fitness: float = setting(0.3, SHARE, "ICP fallback's fitness an accepted loop needs")
    icp_max_rmse: float = setting(
        0.02, POSITIVE, "ICP fallback's inlier RMSE an accepted loop stays below (m)")
    icp_normal_neighbours: int = setting(16, Range(3), "neighbours for the ICP fallback's normals")
    max_points: int = setting(
        20_000, COUNT, "Gaussian centres per submap for ICP, overlap and information")
    # pose graph (Open3D, Levenberg-Marquardt; LoopSplat's values)
    max_correspondence_distance: float = setting(
        0.03, POSITIVE, "pose graph: distance for information matrices and the line process (m)")
    edge_prune_threshold: float = setting(
        0.25, SHARE, "pose graph: loop edges weighted below this are pruned")
    preference_loop_closure: float = setting(
        5.0, POSITIVE, "pose graph: weight of loop edges against odometry")
    information_prior: float = setting(
        1.0, NON_NEGATIVE, "added to every edge's information diagonal (no overlap)")
    # evaluation lever (tests, bench/loop_closure.py): odometry drift injected at every submap
    # switch, a rotation about the world y axis through the camera plus a shift along its x
    # axis; works with loop closure on or off; keep 0 for real runs
    inject_drift_deg: float = setting(
        0.0, ANY, "test lever: odometry drift injected at every submap switch, turn about world y "
        "(degrees; 0 for real runs)")
    inject_drift_m: float = setting(0.0, ANY, "test lever: ... and shift along the camera's x (m)")


# --- end loop closure ----------------------------------------------------------------------------


@dataclass
class SmoothingConfig:
    """Fixed-interval smoothing of the reported trajectory (`bgs_batch.slam.smoothing`): a
    constant-velocity model whose noise ratio is the tracked trajectory's own maximum-likelihood
    value, searched over log10(q / r) (q in units²/s³, r in units²) on this grid."""

    enabled: bool = setting(
        False, "smooth the reported trajectory at the tracked trajectory's own maximum-likelihood "
        "noise")
    log_ratio_min: float = setting(
        -2.0, ANY, "the smoother's noise-ratio grid, log10(q / r): from here (a smooth path at 1 s "
        "scales)")
    log_ratio_max: float = setting(10.0, ANY, "... to here (no smoothing at 30 frames/s)")
    log_ratio_step: float = setting(0.25, POSITIVE, "... in these steps")


@dataclass
class GlobalMapConfig:
    """The end-of-run global map (docs/method.md §8c; `bgs_batch.slam.global_map`): the
    corrected submaps merged where each owns the surface, then optimised at the reported poses
    on every frame but the held-out ones, by the mapping loss (Eq. 12-14)."""

    passes: float = setting(
        2.0, Range(0, 1000), "passes over the training frames, one Adam step per visit (0: the "
        "merged map as it is)")
    hold_out_every: int = setting(
        8, NON_NEGATIVE, "every N-th frame that is not a keyframe is held out and scored (0: none)")
    downscale: int = setting(1, COUNT, "render at input resolution / this (1: full resolution)")
    merge_depth_tolerance: float = setting(
        0.05, POSITIVE, "merge: another submap has a Gaussian's surface within this share of its "
        "depth")
    merge_min_alpha: float = setting(
        0.9, SHARE, "merge: ... where that submap's rendered alpha reaches this")
    pruning_threshold: float = setting(
        0.005, SHARE, "at the end, Gaussians below this opacity go (Gaussian-SLAM's value)")
    checkpoint_every: int = setting(
        100, COUNT, "visits between the job's checkpoints (and on a stop signal)")


@dataclass
class ReadoutEstimationConfig:
    """The rolling-shutter readout estimated from the first frames when the store does not know
    the camera (`bgs convert … --readout auto`; `bgs_batch.slam.readout`, docs/method.md §6)."""

    frames: int = setting(120, COUNT, "the first frames searched for turns")
    pairs: int = setting(8, COUNT, "frame pairs scored, those whose turning differs most")
    min_pairs: int = setting(
        4, COUNT, "fewer informative pairs: no estimate (a global shutter is kept)")
    max_gap: int = setting(8, Range(2), "frames between the two of a pair at most")
    min_turn_change: float = setting(
        0.1, POSITIVE, "a pair's angular velocities differ at least this much (rad/s)")
    candidates: int = setting(11, Range(3), "readouts scored, evenly from 0 to one frame interval")
    # the frames are registered at the largest integer downscale leaving this many pixels
    # across (after the crop): 640 → 320, fr1's 540 → 270, 320 → 320; at 160 px the
    # estimate came out 16 % low on the synthetic hard room, at 320 px 7 % (docs/experiments.md)
    min_width: int = setting(
        256, COUNT, "register the frames at the largest downscale leaving this many pixels across")
    # no estimate when the pairs' mean cost (each normalised by its minimum) varies by less
    # than this over the candidates (the frames cannot tell the readouts apart), or when the
    # standard error of the pairs' own minima exceeds this share of a frame interval
    min_contrast: float = setting(
        0.2, NON_NEGATIVE, "no estimate when the pairs' cost varies less than this share")
    max_standard_error: float = setting(
        0.1, POSITIVE, "no estimate when its standard error exceeds this share of a frame interval")


@dataclass
class ColourOffsetConfig:
    """The colour camera's rotation and focal length against the depth camera's, which the run
    undoes by resampling each colour image onto the depth camera (`bgs_batch.slam.colour_offset`,
    docs/method.md §6): set by hand, or estimated from the first frames when ``estimate``."""

    # the colour camera as seen from the depth camera: a rotation vector in degrees ...
    rotation_x_deg: float = setting(
        0.0, Range(-10, 10), "the colour camera's rotation vector, x (°; by hand or estimated)")
    rotation_y_deg: float = setting(
        0.0, Range(-10, 10), "the colour camera's rotation vector, y (°; by hand or estimated)")
    rotation_z_deg: float = setting(
        0.0, Range(-10, 10), "the colour camera's rotation vector, z (°; by hand or estimated)")
    focal_ratio: float = setting(
        1.0, Range(0.5, 2), "the colour camera's focal length over the depth camera's")
    estimate: bool = setting(
        False, "estimate the four from the first frames, unless they are set (--set)")
    frames: int = setting(60, Range(3), "the first frames the estimate uses")
    pair_gap: int = setting(6, COUNT, "frames between the two of a pair")
    pair_stride: int = setting(5, COUNT, "frames between the first frames of two pairs")
    min_pairs: int = setting(4, Range(2), "fewer pairs: no estimate (the images stay as they are)")
    min_width: int = setting(
        256, COUNT, "register and compare the frames at the largest downscale leaving this many "
        "pixels across")
    # a colour camera further off than a mounting error is a wrong calibration, not an offset;
    # a fit beyond it has run to views that hide most samples (TUM's frames: focal ratio 1.98)
    max_rotation_deg: float = setting(
        5.0, Range(0, 10, low_open=True), "a fitted rotation beyond this about any axis is no "
        "offset (°): no estimate")
    max_focal_change: float = setting(
        0.2, Range(0, 0.5, low_open=True), "... nor a focal ratio further than this from 1")
    # the estimate is kept only where the pairs agree and it stands out of their spread: on
    # registered synthetic rooms the pairs agree to 0.1° and the estimate is below it; on real
    # registered Kinect frames the pairs disagree by degrees (docs/experiments.md)
    max_standard_error_deg: float = setting(
        0.25, POSITIVE, "no estimate when the pairs' rotations scatter more (standard error, °)")
    max_focal_standard_error: float = setting(
        0.005, POSITIVE, "... or their focal ratios (standard error)")
    min_rotation_deg: float = setting(
        0.25, NON_NEGATIVE, "a smaller rotation is kept as none (°) ...")
    min_focal_change: float = setting(
        0.005, NON_NEGATIVE, "... and a focal ratio closer to 1 as 1")
    significance: float = setting(
        3.0, POSITIVE, "an estimate is kept when it exceeds this many standard errors")


@dataclass
class Config:
    """A whole SLAM run."""

    seed: int = setting(
        0, Range(0, 2**32 - 1), "the run's random seed (sampling, seeding, the global stage's "
        "order)")
    threads: int = setting(2, Range(1, 512), "numba kernel threads; results never depend on it")
    crop_edge: int | None = setting(
        None, NON_NEGATIVE, "pixels removed at every image border first (None: the store's "
        "recommended crop)")
    max_depth: float = setting(10.0, Range(0.1, 1000), "deeper readings are invalid (m)")
    # Move each depth image to its colour image's time (the store's /depth_timestamp) by the
    # camera's constant-velocity motion over the gap: unsynchronised sensors (Kinect v1, TUM
    # fr1) pair images up to 20 ms apart, up to two degrees of turn at fr1/rpy's speed
    # (`slam.depth_timing`, docs/method.md §6). The gap is the stamps' difference minus
    # `depth_time_lag`, the seconds by which the driver stamps depth later after capture than
    # colour. Off in both presets: TUM's stamps are arrival times whose lag is not known well
    # enough to help on recordings nobody tuned on (docs/experiments.md)
    align_depth_time: bool = setting(
        False, "move each depth image to its colour image's time stamp by the camera's motion")
    depth_time_lag: float = setting(
        0.0, Range(-1, 1), "seconds by which the driver stamps depth later after capture than "
        "colour")
    # Seconds over which the camera reads its rows out, top to bottom; each frame is moved to one
    # instant by the camera's constant-velocity motion before it is tracked and mapped
    # (`slam.rolling_shutter`, docs/method.md §6). 0: a global shutter, as the paper assumes;
    # None: the store's value (`bgs inspect` shows it; the converter's for the camera, else 0),
    # estimated from the frames when the store says "unknown" (`readout_estimation`)
    rolling_shutter_readout: float | None = setting(
        0.0, Range(0, 1), "seconds the camera reads its rows over (0: global shutter; None: the "
        "store's, estimated when unknown)")
    # The depth image's readout, when the depth sensor reads out otherwise than the colour one
    # (a RealSense D435: global-shutter depth, rolling-shutter colour). None: the store's
    # (`bgs inspect`), or `rolling_shutter_readout` when that is set (--set)
    depth_rolling_shutter_readout: float | None = setting(
        None, Range(0, 1), "the depth image's readout, when it differs from colour's (None: the "
        "store's, or rolling_shutter_readout's when set)")
    # A rolling-shutter frame is first rectified with the last frame interval's velocity (it is
    # not tracked yet); once tracked, its own interval gives a closer one: rectify it again with
    # that and track it again from its pose (docs/experiments.md, "Tracking")
    rectify_again: bool = setting(
        False, "rectify a rolling-shutter frame again once tracked, and track it again")
    checkpoint_every: int = setting(
        10, COUNT, "frames between job checkpoints (and on SIGTERM/SIGUSR1/SIGINT)")
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
    colour_offset: ColourOffsetConfig = field(default_factory=ColourOffsetConfig)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def _settings(section: type, prefix: str = "") -> dict[str, dataclasses.Field]:
    """Every setting of a config class by its dotted key, sections walked in order."""
    found: dict[str, dataclasses.Field] = {}
    for f in dataclasses.fields(section):
        if dataclasses.is_dataclass(f.default_factory):
            found |= _settings(f.default_factory, f"{prefix}{f.name}.")
        else:
            found[prefix + f.name] = f
    return found


SETTINGS = _settings(Config)  # key → its field (default, `Range`, doc in the metadata)
# Every numeric setting and what it accepts (`setting`); `check` refuses the rest before a run
# starts (tests/test_config.py walks every field with NaN, inf, 0 and -1)
RANGES: dict[str, Range] = {key: f.metadata["accepts"] for key, f in SETTINGS.items()
                            if f.metadata["accepts"] is not None}  # fmt: skip


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
        # term gets the iterations mapping cannot give it; tracking is over by then (8 passes
        # at twice the rate rank as 15 did, in half the time: docs/experiments.md)
        "uncertainty.refine_passes": 8,
        "uncertainty.refine_lr": 0.1,
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
        "rectify_again": True,
        "seeding.new_submap_points": 30_000,
        "seeding.new_submap_gradient_points": 15_000,
        "seeding.new_frame_points": 10_000,
        # seeds on the measured surface, as discs across its normal: their depth planes render
        # the surface's depth without the bias that pushing seeds behind it offset in part
        # (docs/method.md §1, §5)
        "seeding.depth_push": 1.0,
        "seeding.flatness": 0.1,
        # a colour camera that does not sit on its depth camera is found from the first frames
        # and resampled onto it; registered cameras are kept as they are (docs/method.md §6)
        "colour_offset.estimate": True,
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
    # the sensor variances, evaluated at mapping resolution, block-average onto each tracking level
    tracking_scale, mapping_scale = config.tracking.downscale, config.mapping.downscale
    if tracking_scale % mapping_scale:
        raise ConfigError(f"tracking.downscale={tracking_scale} must be a multiple of "
                          f"mapping.downscale={mapping_scale}; set both (e.g. "
                          f"mapping.downscale={tracking_scale})")


def for_store(config: Config, store: StoreFacts) -> tuple[Config, dict[str, str]]:
    """The config with the store's values filled in where it leaves them open (None), and where
    each such value came from (for ``config.json``); a store whose depth is registered to colour
    by calibration turns the colour offset's estimate off."""
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
    if needs_colour_offset(config) and store.depth_registered:
        # a calibrated registration leaves nothing for the frames to tell
        offset = dataclasses.replace(config.colour_offset, estimate=False)
        resolved = dataclasses.replace(resolved, colour_offset=offset)
        sources["colour_offset.estimate"] = (f"off: {store.path.name} holds depth registered to "
                                             "colour with the cameras' calibration")  # fmt: skip
    return resolved, sources


def colour_offset_set(config: Config) -> bool:
    """True when the config moves the colour image onto the depth camera (an offset set by hand,
    or filled in from the run's estimate)."""
    c = config.colour_offset
    return (c.rotation_x_deg, c.rotation_y_deg, c.rotation_z_deg, c.focal_ratio) != (0, 0, 0, 1)


def needs_colour_offset(config: Config) -> bool:
    """True when a run must estimate the colour camera's offset from its frames."""
    return config.colour_offset.estimate and not colour_offset_set(config)


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
    depth_registered: bool


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


def accepted_values(key: str) -> str:
    """What ``--set key=…`` accepts, in words (``bgs settings``)."""
    owner, f = _field(Config(), key)
    kind = typing.get_type_hints(type(owner))[f.name]
    optional = type(None) in typing.get_args(kind)
    if optional:
        kind = next(k for k in typing.get_args(kind) if k is not type(None))
    if typing.get_origin(kind) is Literal:
        words = "one of " + ", ".join(typing.get_args(kind))
    elif kind is bool:
        words = "true or false"
    elif kind is str:
        words = "text"
    else:
        accepts = f.metadata["accepts"]
        words = ("an integer" if kind is int else "a number") + (
            accepts.describe().removeprefix("a finite number") if accepts else "")
    return words + (", or none" if optional else "")


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

"""The method: uncertainty-aware Gaussian-splatting SLAM (BayesianGS-SLAM on a LoopSplat backbone).

`Slam` (`pipeline`) consumes a sequence frame by frame. Before the first frame, a camera the
store does not know has its rolling-shutter readout estimated from the first frames
(`readout`), and a colour camera that does not sit on its depth camera its offset
(`colour_offset`; each colour image is then resampled onto the depth camera,
`colour_registration`). The camera's constant-velocity motion, and the motions each frame was
prepared with, are kept by `camera_motion`; what the run records per frame (stage seconds, poses
and motions in the log) by `run_record`; what a checkpoint holds by `run_state`. Per frame:

1. frame → levels (`frames`): crop the border, clip far depth, move the depth image to the
   colour image's instant (`depth_timing`) and a rolling shutter's rows to one instant
   (`rolling_shutter`, its per-pixel loops in `rolling_shutter_kernels`), build the input and
   mapping resolutions;
2. track (`tracking`): the camera pose from a constant-velocity guess corrected by dense
   registration, refined on the uncertainty-normalised L1 of colour and depth (Eq. 15-17;
   `losses.tracking_loss`, fused kernels in `loss_kernels`) against the active submap's render
   (`bgs_batch.render`);
3. keyframe? (`keyframes`): predictive surprise S = Σ ½[(Ĉ − C)²/Σ + log Σ] of colour and depth
   above its threshold (Eq. 9; `losses.surprise_scores`), with Σ the predictive variance of
   Eq. 10-11 (`losses.predictive_variance`): learned sensor noise (`sensor_noise`, §III-A) plus
   the opacity-induced map variance;
4. map (`mapping`): seed Gaussians where the map is thin (`seeding`), then optimise the submap
   (`gaussian_map`, `adam`), the per-Gaussian variances and the sensor network on the keyframes
   by L_3DGS + γ(NLL_C + NLL_D) (Eq. 12-14; SSIM's Gaussian filter is the kernel in `blur`);
5. submap? (`submaps`): after enough motion the submap is frozen to disk and a new one starts;
6. loop closure (`loop_closure`): the finished submap is matched against older ones, registered
   and a pose graph corrects submaps and poses.

At the end of a run (`end_of_run`, conducted by `Slam.finish` and `Slam.trajectory`) each
frozen submap's variances and the sensor network are refined by the NLL (Eq. 13, 14) with the
geometry fixed, and Σ_D's two parts get their gains (`calibration`); the reported trajectory is
smoothed (`smoothing`); then the global stage (`global_map`, `Slam.global_stage`) merges the
submaps where each owns the surface and optimises the merged map at the reported poses on every
frame but the held-out ones.
"""

from bgs_batch.slam.pipeline import Slam

__all__ = ["Slam"]

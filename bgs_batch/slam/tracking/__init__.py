"""Tracking: the camera pose of each frame against the active submap (Eq. 15-17; docs/method.md
§6).

1. start (`registration`): the constant-velocity pose, corrected by dense RGB-D registration of
   the measured frame to the map rendered there (point-to-plane and photometric Gauss-Newton;
   its residuals and normal equations are numba kernels in `registration_kernels`);
2. refine (`tracker`): the uncertainty-normalised L1 of colour and depth against the submap's
   render, by Adam, or by Gauss-Newton steps whose curvature is the image-motion normal matrix
   of `pose_jacobian`; the lowest-loss pose is kept with its predictive-surprise scores.

`Tracker` (`tracker`) runs both; `constant_velocity` gives the start's guess.
"""

from bgs_batch.slam.tracking.tracker import Tracker, constant_velocity

__all__ = ["Tracker", "constant_velocity"]

"""Depth measured at another instant than colour, moved to the colour image's instant.

A Kinect v1 streams colour and depth unsynchronised, so a recording pairs each colour image with
the depth image nearest in time: in TUM RGB-D's fr1 sequences up to 20 ms apart, and the gap
wanders from frame to frame. A camera turning at 60°/s moves 1.2° in 20 ms, about 10 px at
640×480, so colour and depth then show the scene from two poses, and the tracker, which explains
both by one pose, settles on a compromise that jitters with the gap. Each depth image is instead
reprojected into the colour camera, using the camera's motion over the gap: the constant-velocity
motion of the previous frame interval, scaled to the gap (docs/method.md §6).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def interval_motion(c2w_before: np.ndarray, c2w_after: np.ndarray, fraction: float
                    ) -> np.ndarray:  # fmt: skip
    """The camera's motion over `fraction` of the interval from `c2w_before` to `c2w_after`, in
    its own frame: ``M^fraction`` with ``M = c2w_before⁻¹ c2w_after``, rotation by slerp and
    translation linear (as TUM's ground truth is interpolated). Negative fractions go back.

    A point ``p`` in the camera at time ``t + fraction·Δt`` is ``M^fraction p`` in the camera at
    time ``t`` when the camera keeps the velocity it had over the interval.
    """
    motion = np.linalg.inv(c2w_before) @ c2w_after
    out = np.eye(4)
    rotvec = Rotation.from_matrix(motion[:3, :3]).as_rotvec()
    out[:3, :3] = Rotation.from_rotvec(rotvec * fraction).as_matrix()
    out[:3, 3] = motion[:3, 3] * fraction
    return out


def warp_depth(depth: np.ndarray, intrinsics: np.ndarray, motion: np.ndarray) -> np.ndarray:
    """The depth image as the camera moved by `motion` (a point p of `depth`'s camera is
    ``motion @ p`` in the new one) would have measured it: every valid reading unprojected,
    moved and projected, its depth carried to the nearest pixel centre along the surface;
    where several land on one pixel the nearest surface wins, and pixels nothing lands on
    are invalid (0). Float32 metres in and out.

    Rounding to the nearest pixel alone would err by up to half a pixel's depth change on
    slanted surfaces, as much as a small gap's motion; inverse depth is affine in the pixel
    coordinates on a plane, so it is carried to the pixel centre by its local slope in the
    source image (`_surface_slopes`), which a near-identity motion hardly changes.
    """
    height, width = depth.shape
    valid = depth > 0
    inverse = np.where(valid, 1.0 / np.where(valid, depth, 1.0), 0.0)
    slope_u, slope_v = _surface_slopes(inverse, valid)
    v, u = np.nonzero(valid)
    z = depth[v, u].astype(np.float64)
    fx, fy, cx, cy = intrinsics[0, 0], intrinsics[1, 1], intrinsics[0, 2], intrinsics[1, 2]
    points = np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z])
    moved = motion[:3, :3] @ points + motion[:3, 3:4]
    with np.errstate(divide="ignore", invalid="ignore"):
        u_new = fx * moved[0] / moved[2] + cx
        v_new = fy * moved[1] / moved[2] + cy
        u_pix, v_pix = np.rint(u_new), np.rint(v_new)
        inverse_new = (1.0 / moved[2] + slope_u[v, u] * (u_pix - u_new)
                       + slope_v[v, u] * (v_pix - v_new))  # fmt: skip
        keep = ((moved[2] > 0) & (inverse_new > 0) & (u_pix >= 0) & (u_pix < width)
                & (v_pix >= 0) & (v_pix < height))  # fmt: skip
    target = v_pix[keep].astype(np.int64) * width + u_pix[keep].astype(np.int64)
    z_new = 1.0 / inverse_new[keep]
    order = np.lexsort((z_new, target))  # by pixel, nearest first
    target, z_new = target[order], z_new[order]
    first = np.ones(len(target), bool)
    first[1:] = target[1:] != target[:-1]
    out = np.zeros(height * width, np.float32)
    out[target[first]] = z_new[first]
    return out.reshape(height, width)


def _surface_slopes(inverse: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel, the slope of inverse depth along u and v: of the two one-sided differences
    the smaller when they agree in sign, else 0 (minmod), so that a depth edge or a hole next
    to a pixel does not tilt its surface."""
    slopes = []
    for axis in (1, 0):
        step = np.diff(inverse, axis=axis)
        step_ok = np.diff(valid.astype(np.int8), axis=axis) == 0
        step = np.where(step_ok & np.delete(valid, 0, axis=axis), step, 0.0)
        pad = [(0, 0), (0, 0)]
        pad[axis] = (1, 0)
        back = np.pad(step, pad)  # inverse[i] - inverse[i-1]
        pad[axis] = (0, 1)
        ahead = np.pad(step, pad)  # inverse[i+1] - inverse[i]
        agree = np.sign(back) == np.sign(ahead)
        slopes.append(np.where(agree, np.sign(back) * np.minimum(abs(back), abs(ahead)), 0.0))
    return slopes[0], slopes[1]


def depth_motion(c2w_before2: np.ndarray, c2w_before: np.ndarray, interval: float,
                 depth_offset: float) -> np.ndarray | None:  # fmt: skip
    """The warp (`warp_depth`'s `motion`) that moves a depth image taken `depth_offset` seconds
    after its colour image to the colour image's time, assuming the camera keeps the velocity
    it had from `c2w_before2` to `c2w_before`, `interval` seconds apart. None when there is
    nothing to move (taken together, or no interval to take a velocity from)."""
    if depth_offset == 0 or not interval > 0:
        return None
    return interval_motion(c2w_before2, c2w_before, depth_offset / interval)

"""An evaluation lever: odometry drift injected at submap switches (tests, bench).

Real tracking on clean synthetic data barely drifts, so loop closure would have nothing to
correct. Perturbing the first pose of every new submap moves that whole submap (it is mapped
and tracked from that pose), which is the piecewise-rigid drift a submap pose graph models.
"""

from __future__ import annotations

import numpy as np

WORLD_AXIS = 1  # rotate about the world y axis (the first camera's "down": a yaw drift)


def inject_drift(c2w: np.ndarray, degrees: float, metres: float) -> np.ndarray:
    """`c2w` turned by `degrees` about the world y axis through its centre, then moved
    `metres` along its own x axis. Zero drift returns the pose unchanged (same object)."""
    if degrees == 0 and metres == 0:
        return c2w
    angle = np.radians(degrees)
    axis = np.zeros(3)
    axis[WORLD_AXIS] = 1.0
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rot = np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k
    out = c2w.copy()
    out[:3, :3] = rot @ c2w[:3, :3]
    out[:3, 3] = c2w[:3, 3] + metres * out[:3, 0]
    return np.ascontiguousarray(out)

"""Static transform lookup over a tree of ROS frames (``/tf_static``, ``/tf``, RealSense ``tf/0``).

An edge ``parent → child`` holds ``T_parent_child``, the transform taking points expressed in the
child frame into the parent frame (the ROS ``TransformStamped`` convention). A lookup walks the
tree in either direction, inverting edges as needed.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np

from bgs_batch.geometry import pose_matrix


def vector3(msg: Any) -> np.ndarray:
    """(x, y, z) of a ``geometry_msgs`` Vector3 or Point."""
    return np.array([msg.x, msg.y, msg.z], np.float64)


def quaternion(msg: Any) -> np.ndarray:
    """Unit (x, y, z, w) of a ``geometry_msgs/Quaternion`` (normalised: recorders round them)."""
    quat = np.array([msg.x, msg.y, msg.z, msg.w], np.float64)
    return quat / np.linalg.norm(quat)


def transform_matrix(transform: Any) -> np.ndarray:
    """4x4 matrix of a ``geometry_msgs/Transform`` (translation + xyzw quaternion)."""
    return pose_matrix(vector3(transform.translation), quaternion(transform.rotation))


def frame_name(frame_id: str) -> str:
    """Frame ids without ROS1's optional leading slash, so ``/camera`` and ``camera`` match."""
    return frame_id.lstrip("/")


class TransformTree:
    """Rigid transforms between named frames; the first transform seen for an edge wins."""

    def __init__(self) -> None:
        self._edges: dict[str, dict[str, np.ndarray]] = {}

    def add(self, parent: str, child: str, parent_from_child: np.ndarray) -> None:
        parent, child = frame_name(parent), frame_name(child)
        if child in self._edges.get(parent, {}):
            return
        self._edges.setdefault(parent, {})[child] = parent_from_child
        self._edges.setdefault(child, {})[parent] = np.linalg.inv(parent_from_child)

    def add_message(self, tf_message: Any) -> None:
        """Add every transform of a ``tf2_msgs/TFMessage``."""
        for stamped in tf_message.transforms:
            self.add(
                stamped.header.frame_id, stamped.child_frame_id, transform_matrix(stamped.transform)
            )

    def __len__(self) -> int:
        return sum(len(children) for children in self._edges.values()) // 2

    def lookup(self, target: str, source: str) -> np.ndarray | None:
        """``T_target_source`` (source-frame points into the target frame), or None if unlinked."""
        target, source = frame_name(target), frame_name(source)
        if target == source:
            return np.eye(4)
        found: dict[str, np.ndarray] = {source: np.eye(4)}  # frame -> T_frame_source
        queue = deque([source])
        while queue:
            frame = queue.popleft()
            for neighbour, frame_from_neighbour in self._edges.get(frame, {}).items():
                if neighbour not in found:
                    found[neighbour] = np.linalg.inv(frame_from_neighbour) @ found[frame]
                    if neighbour == target:
                        return found[neighbour]
                    queue.append(neighbour)
        return None

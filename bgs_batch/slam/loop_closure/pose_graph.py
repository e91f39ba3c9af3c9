"""The pose graph over submaps: information matrices and Open3D's global optimisation.

Nodes are per-submap corrections X_k (submap frame as it was mapped → corrected world). An
edge (source s, target t, transform Z) states X_t⁻¹ X_s = Z, i.e. Z maps points of submap s's
frame into submap t's (Open3D's convention). Odometry edges join consecutive submaps and are
certain; loop edges are `uncertain`, so the line process can down-weight them and
`edge_prune_threshold` can drop them (Choi et al. 2015, as in Open3D and LoopSplat).

Information matrices follow Open3D's `get_information_matrix_from_point_clouds` (rows
[-[x]× | I] of every target point x matched within the correspondence distance), computed here
with a fixed summation order (Open3D sums per OpenMP thread), plus a small isotropic prior so an
edge between submaps that share no surface cannot make the system singular.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bgs_batch.config import LoopClosureConfig
from bgs_batch.geometry import kd_tree

REFERENCE_NODE = 0  # the first submap defines the world frame
DOF = 6


@dataclass(frozen=True)
class Edge:
    source: int
    target: int
    transform: np.ndarray  # (4, 4): source frame → target frame
    information: np.ndarray  # (6, 6), Open3D order (rotation, translation)
    loop: bool  # uncertain and prunable


def information(source: np.ndarray, target: np.ndarray, transform: np.ndarray,
                max_distance: float, prior: float) -> np.ndarray:  # fmt: skip
    """6×6 information of aligning `source` (n, 3) to `target` (m, 3) by `transform`."""
    out = prior * np.eye(DOF)
    if len(source) == 0 or len(target) == 0:
        return out
    moved = source @ transform[:3, :3].T + transform[:3, 3]
    dist, idx = kd_tree(target).query(moved, distance_upper_bound=max_distance)
    x = target[idx[np.isfinite(dist)]]
    if len(x) == 0:
        return out
    zero, one = np.zeros(len(x)), np.ones(len(x))
    rows = np.stack([
        np.stack([zero, x[:, 2], -x[:, 1], one, zero, zero], 1),
        np.stack([-x[:, 2], zero, x[:, 0], zero, one, zero], 1),
        np.stack([x[:, 1], -x[:, 0], zero, zero, zero, one], 1),
    ]).reshape(-1, DOF)  # fmt: skip
    return out + np.einsum("ki,kj->ij", rows, rows)


def spread_loop(corrections: np.ndarray, edge: Edge) -> np.ndarray:
    """Initial node poses that satisfy a new loop edge, its discrepancy spread along the chain.

    The loop says X_s = X_t Z. The world transform D that would move submap s there is
    applied in growing fractions (rotation vector and translation scaled by
    (k − t)/(s − t)) to the submaps t+1 … s. The line process weighs a loop edge by its
    residual where the optimisation starts: from the plain corrections a true loop closing a
    large drift would look like an outlier and be pruned. From here it is judged by how well
    the whole graph can agree with it.
    """
    from scipy.spatial.transform import Rotation  # on first use, as `kd_tree`

    out = corrections.copy()
    s, t = edge.source, edge.target
    drift = out[t] @ edge.transform @ np.linalg.inv(out[s])
    rotvec = Rotation.from_matrix(drift[:3, :3]).as_rotvec()
    for k in range(t + 1, s + 1):
        share = (k - t) / (s - t)
        step = np.eye(4)
        step[:3, :3] = Rotation.from_rotvec(share * rotvec).as_matrix()
        step[:3, 3] = share * drift[:3, 3]
        out[k] = step @ out[k]
    return out


@dataclass(frozen=True)
class Optimised:
    poses: np.ndarray  # (S, 4, 4) corrections after optimisation
    kept_loops: list[tuple[int, int]]  # (source, target) of the loop edges that survived


def optimise(initial: np.ndarray, edges: list[Edge], cfg: LoopClosureConfig) -> Optimised:
    """Levenberg-Marquardt over the graph from `initial` node poses; node 0 keeps its pose."""
    import open3d as o3d  # ~1 s to import: only when a loop is closed, not on every job start

    graph = o3d.pipelines.registration.PoseGraph()
    for pose in initial:
        graph.nodes.append(o3d.pipelines.registration.PoseGraphNode(pose))
    for e in edges:
        graph.edges.append(o3d.pipelines.registration.PoseGraphEdge(
            e.source, e.target, e.transform, e.information, uncertain=e.loop))  # fmt: skip
    option = o3d.pipelines.registration.GlobalOptimizationOption(
        max_correspondence_distance=cfg.max_correspondence_distance,
        edge_prune_threshold=cfg.edge_prune_threshold,
        preference_loop_closure=cfg.preference_loop_closure,
        reference_node=REFERENCE_NODE,
    )
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        o3d.pipelines.registration.global_optimization(
            graph,
            o3d.pipelines.registration.GlobalOptimizationLevenbergMarquardt(),
            o3d.pipelines.registration.GlobalOptimizationConvergenceCriteria(),
            option,
        )
    poses = np.stack([np.asarray(node.pose) for node in graph.nodes])
    kept = [(e.source_node_id, e.target_node_id) for e in graph.edges if e.uncertain]
    return Optimised(poses, kept)

"""Loop closure over submaps (LoopSplat's, with our uncertainty; docs/method.md §8).

At every submap switch the finished submap is the *query*:

1. place recognition (`place_recognition`): ORB features of every keyframe (`features`), a
   binary bag-of-words vocabulary learnt online (`vocabulary`), LoopSplat's rule "similarity
   above the query submap's own median self-similarity, at least a few submaps apart";
2. geometric verification (`verification`): descriptor matches with depth, rigid RANSAC;
3. registration (`submap_registration`): query keyframes tracked in the candidate submap's
   Gaussians with the uncertainty-normalised tracking loss, gated by rendered overlap, fused;
   point-to-plane ICP (`icp`) when rendering fails;
4. pose graph (`pose_graph`): Open3D Levenberg-Marquardt over per-submap corrections, loop
   edges prunable; the result corrects submap files, the poses and the current frame
   (`correction`).

`LoopCloser` (`closer`) runs this and holds the state a checkpoint needs. `drift` is an
evaluation lever that injects odometry drift; `evaluation` checks a finished job's loops
against ground truth (tests and benches only: the SLAM never reads ground truth).
"""

from bgs_batch.slam.loop_closure.closer import LoopCloser
from bgs_batch.slam.loop_closure.drift import inject_drift

__all__ = ["LoopCloser", "inject_drift"]

"""`LoopCloser`: detection, registration, pose graph and correction at every submap switch.

Frames. Every submap k has the frame it was mapped in ("raw"; its keyframe poses and
Gaussians as frozen) and a cumulative correction C_k (raw → current world), C_0 = I. A new
submap is mapped in the current world, so submap k's raw frame maps into submap k−1's raw
frame by C_{k−1}⁻¹ as C_{k−1} stood when k was finished (the odometry edge). Loop edges are
stored raw → raw too, so no edge ever needs recomputing after a correction, and the pose graph
starts from the current corrections.

State (checkpointed, tensors only): keyframe features, the vocabulary, per-submap corrections,
odometry edges and loop edges. Word lists and bag-of-words vectors are derived and rebuilt.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from bgs_batch.config import Config
from bgs_batch.slam.frames import Level
from bgs_batch.slam.loop_closure import place_recognition, vocabulary
from bgs_batch.slam.loop_closure.correction import camera_shift, load_raw, write_correction
from bgs_batch.slam.loop_closure.features import DESCRIPTOR_BYTES, KeyframeFeatures, extract
from bgs_batch.slam.loop_closure.icp import subsample
from bgs_batch.slam.loop_closure.pose_graph import DOF, Edge, information, optimise, spread_loop
from bgs_batch.slam.loop_closure.submap_registration import SubmapRegistration, overlap
from bgs_batch.slam.loop_closure.verification import Verification, verify
from bgs_batch.slam.mapping import Keyframe
from bgs_batch.slam.sensor_noise import SensorNoiseNet
from bgs_batch.slam.submaps import SubmapRecord

VOCABULARY_STREAM, RANSAC_STREAM = 1, 2  # independent random streams derived from the seed
POSE_ROWS = 3  # poses in reports: the top 3×4, row-major (as log.jsonl's "pose")
UNCHANGED = 1e-12  # a correction that moved less than this is not applied (nothing to rewrite)


@dataclass(frozen=True)
class LoopEdge:
    query: int
    candidate: int
    transform: np.ndarray  # query raw frame → candidate raw frame
    information: np.ndarray  # (6, 6)


def _pose_row(matrix: np.ndarray) -> list[float]:
    return [float(x) for x in matrix[:POSE_ROWS].ravel()]


class LoopCloser:
    """Loop closure of one SLAM run; `Slam` calls `add_keyframe` and `on_submap_finished`."""

    def __init__(self, cfg: Config) -> None:
        self.cfg = cfg
        self.features: list[KeyframeFeatures] = []
        self.vocabulary = np.zeros((0, DESCRIPTOR_BYTES), np.uint8)
        self.trained_on = 0
        self.corrections: list[np.ndarray] = []  # per finished submap: raw → world
        # per submap, also the active one: the tracked chain's frame → the world that submap
        # was built in (the corrections of the newest frames before it began)
        self.world_offsets: list[np.ndarray] = [np.eye(4)]
        self.odometry: list[Edge] = []  # submap k → k−1, for k ≥ 1
        self.loops: list[LoopEdge] = []
        self.registration = SubmapRegistration(cfg)
        self._words: list[np.ndarray] = []  # per feature row, for the current vocabulary

    # ------------------------------------------------------------------ per keyframe

    def add_keyframe(self, frame: int, submap: int, level: Level, c2w: np.ndarray) -> None:
        """Remember a keyframe's features (`level`: the input-resolution frame)."""
        if self.cfg.loop_closure.enabled:
            self.features.append(extract(frame, submap, level, c2w, self.cfg.loop_closure))

    # ------------------------------------------------------------------ per submap switch

    def on_submap_finished(
        self,
        submaps: list[SubmapRecord],
        keyframes: list[Keyframe],
        poses: list[np.ndarray],
        sensor: SensorNoiseNet,
    ) -> dict[str, Any] | None:
        """Close loops from the submap just frozen (`submaps[-1]`, mapped from `keyframes`).

        May correct `poses` in place and rewrite submap files. Returns the log report, or None
        when detection did not run (disabled, or too few submaps).
        """
        lc = self.cfg.loop_closure
        if not lc.enabled:
            return None
        q = len(submaps) - 1
        centres = {q: self._centres(submaps[q])}
        self.corrections.append(np.eye(4))
        self.world_offsets.append(self.world_offsets[-1].copy())  # the next submap's
        if q > 0:
            centres[q - 1] = self._centres(submaps[q - 1])
            to_previous = np.linalg.inv(self.corrections[q - 1])
            self.odometry.append(Edge(q, q - 1, to_previous, self._information(
                centres[q], centres[q - 1], to_previous), loop=False))  # fmt: skip
        if len(submaps) < lc.min_submaps:
            return None
        self._train_if_due()
        vectors = vocabulary.bow_vectors(self._word_lists(), len(self.vocabulary))
        submap_of = np.array([f.submap for f in self.features])
        found = place_recognition.candidates(vectors, submap_of, q, lc.self_similarity,
                                             lc.min_interval, lc.verify_pairs)  # fmt: skip
        report: dict[str, Any] = {"query": q, "candidates": [
            [c.submap, round(c.similarity, 4)] for c in found]}  # fmt: skip
        loops, rejected = [], []
        for cand in found[: lc.max_candidates]:
            outcome = self._try_candidate(q, cand, submaps, keyframes, sensor, vectors, centres)
            (loops if "transform" in outcome else rejected).append(outcome)
        report["loops"] = [{k: v for k, v in o.items() if k != "transform"} for o in loops]
        report["rejected"] = rejected
        report["optimised"] = bool(loops)
        if loops:
            report |= self._optimise_and_correct(submaps, poses, self.loops[-len(loops)])
        return report

    def _try_candidate(
        self,
        q: int,
        cand: place_recognition.Candidate,
        submaps: list[SubmapRecord],
        keyframes: list[Keyframe],
        sensor: SensorNoiseNet,
        vectors: np.ndarray,
        centres: dict[int, np.ndarray],
    ) -> dict[str, Any]:
        """Verify and register one candidate; a loop edge is stored when it succeeds."""
        lc = self.cfg.loop_closure
        c = cand.submap
        rng = np.random.default_rng((self.cfg.seed, RANSAC_STREAM, q, c))
        best: tuple[Verification, int, int] | None = None
        for row_q, row_c in cand.pairs:
            result = verify(self.features[row_q], self.features[row_c], lc, rng)
            if result is not None and (best is None or result.inliers > best[0].inliers):
                best = (result, row_q, row_c)
        if best is None:
            return {"submap": c, "stage": "verification"}
        verdict, row_q, row_c = best
        fq, fc = self.features[row_q], self.features[row_c]
        init = fc.c2w @ verdict.a_to_b @ np.linalg.inv(fq.c2w)  # query raw → candidate raw
        if c not in centres:
            centres[c] = self._centres(submaps[c])
        shared = overlap(subsample(centres[q], lc.max_points),
                         subsample(centres[c], lc.max_points), init, lc.overlap_radius)  # fmt: skip
        if shared < lc.min_overlap:
            return {"submap": c, "stage": "overlap", "overlap": round(shared, 4)}
        views = self._viewpoints(q, c, keyframes, vectors)
        reg = self.registration.register(views, sensor, load_raw(submaps[c].path), centres[q],
                                         init)  # fmt: skip
        summary = {"submap": c, "inliers": verdict.inliers, "overlap": round(shared, 4),
                   "viewpoints": [[v.frame, round(v.coverage, 3), round(v.agreement, 3),
                                   v.accepted] for v in reg.viewpoints]}  # fmt: skip
        if reg.transform is None:
            return {**summary, "stage": "registration"}
        info = self._information(centres[q], centres[c], reg.transform)
        self.loops.append(LoopEdge(q, c, reg.transform, info))
        return {**summary, "method": reg.method, "transform": reg.transform}

    def _viewpoints(self, q: int, c: int, keyframes: list[Keyframe], vectors: np.ndarray
                    ) -> list[Keyframe]:  # fmt: skip
        """The query keyframes most similar to the candidate submap (LoopSplat's top-k)."""
        rows_q = [i for i, f in enumerate(self.features) if f.submap == q]
        rows_c = [i for i, f in enumerate(self.features) if f.submap == c]
        best = (vectors[rows_q] @ vectors[rows_c].T).max(1)
        order = np.argsort(-best, kind="stable")[: self.cfg.loop_closure.viewpoints]
        by_frame = {k.frame: k for k in keyframes}
        return [by_frame[self.features[rows_q[i]].frame] for i in order]

    def _optimise_and_correct(self, submaps: list[SubmapRecord], poses: list[np.ndarray],
                              newest: LoopEdge) -> dict[str, Any]:  # fmt: skip
        """Pose-graph optimisation (from the corrections with `newest`'s discrepancy spread
        along its chain), then corrections of submap files and poses."""
        edges = self.odometry + [Edge(e.query, e.candidate, e.transform, e.information, True)
                                 for e in self.loops]  # fmt: skip
        start = spread_loop(np.stack(self.corrections),
                            Edge(newest.query, newest.candidate, newest.transform,
                                 newest.information, True))  # fmt: skip
        result = optimise(start, edges, self.cfg.loop_closure)
        deltas = [x @ np.linalg.inv(c) for x, c in zip(result.poses, self.corrections,
                                                        strict=True)]  # fmt: skip
        changed = [bool(np.abs(x - c).max() > UNCHANGED) for x, c in zip(
            result.poses, self.corrections, strict=True)]  # fmt: skip
        shifts = []
        for k, record in enumerate(submaps):
            if not changed[k]:
                continue
            self.corrections[k] = result.poses[k]
            write_correction(record.path, self.corrections[k])
            shifts.append(camera_shift(deltas[k], poses[record.first_frame]))
            for i in range(record.first_frame, record.last_frame + 1):
                poses[i] = np.ascontiguousarray(deltas[k] @ poses[i])
        if changed[-1]:
            for i in range(submaps[-1].last_frame + 1, len(poses)):  # the new submap's frames
                poses[i] = np.ascontiguousarray(deltas[-1] @ poses[i])
            self.world_offsets[-1] = deltas[-1] @ self.world_offsets[-1]
        return {"loop_edges": len(self.loops), "pruned": len(self.loops) - len(result.kept_loops),
                "corrected_submaps": len(shifts), "max_shift_m": max(shifts, default=0.0),
                "correction": _pose_row(deltas[-1] if changed[-1] else np.eye(4))}  # fmt: skip

    def chain_corrections(self, submaps: int) -> np.ndarray:
        """Per submap (`submaps` of them), the correction that moved its frames from the
        tracked chain of poses to where they are now (`correction.continuous_poses`)."""
        return np.stack([(self.corrections[k] if k < len(self.corrections) else np.eye(4))
                         @ self.world_offsets[k] for k in range(submaps)])  # fmt: skip

    # ------------------------------------------------------------------ helpers

    def _centres(self, record: SubmapRecord) -> np.ndarray:
        return load_raw(record.path)["means"].numpy().astype(np.float64)

    def _information(self, source: np.ndarray, target: np.ndarray, transform: np.ndarray
                     ) -> np.ndarray:  # fmt: skip
        lc = self.cfg.loop_closure
        return information(
            subsample(source, lc.max_points),
            subsample(target, lc.max_points),
            transform,
            lc.max_correspondence_distance,
            lc.information_prior,
        )

    def _train_if_due(self) -> None:
        """(Re)train the vocabulary when the descriptors seen grew by the growth factor."""
        lc = self.cfg.loop_closure
        total = sum(len(f.descriptors) for f in self.features)
        if len(self.vocabulary) and total < lc.vocabulary_growth * self.trained_on:
            return
        descriptors = np.concatenate([f.descriptors for f in self.features])
        rng = np.random.default_rng((self.cfg.seed, VOCABULARY_STREAM))
        self.vocabulary = vocabulary.train(
            descriptors, lc.vocabulary_words, lc.vocabulary_iterations, lc.vocabulary_samples, rng
        )
        self.trained_on = total
        self._words = []

    def _word_lists(self) -> list[np.ndarray]:
        for f in self.features[len(self._words) :]:
            self._words.append(vocabulary.assign(f.descriptors, self.vocabulary))
        return self._words

    # ------------------------------------------------------------------ checkpoints

    def state_dict(self) -> dict[str, Any]:
        """Tensors and plain values only (``torch.load(weights_only=True)``)."""
        f = self.features
        sizes = [len(x.descriptors) for x in f]

        def stack(items: list[np.ndarray], shape: tuple[int, ...], dtype: Any) -> torch.Tensor:
            return torch.from_numpy(np.stack(items) if items else np.zeros((0, *shape), dtype))

        def cat(items: list[np.ndarray], width: int, dtype: Any) -> torch.Tensor:
            return torch.from_numpy(np.concatenate(items) if items else np.zeros((0, width), dtype))

        return {
            "frames": torch.tensor([x.frame for x in f], dtype=torch.int64),
            "submaps": torch.tensor([x.submap for x in f], dtype=torch.int64),
            "c2w": stack([x.c2w for x in f], (4, 4), np.float64),
            "offsets": torch.from_numpy(np.cumsum([0, *sizes]).astype(np.int64)),
            "descriptors": cat([x.descriptors for x in f], DESCRIPTOR_BYTES, np.uint8),
            "points": cat([x.points for x in f], 3, np.float32),
            "vocabulary": torch.from_numpy(self.vocabulary.copy()),
            "trained_on": self.trained_on,
            "corrections": stack(self.corrections, (4, 4), np.float64),
            "world_offsets": stack(self.world_offsets, (4, 4), np.float64),
            "odometry": stack([e.transform for e in self.odometry], (4, 4), np.float64),
            "odometry_info": stack(
                [e.information for e in self.odometry], (DOF, DOF), np.float64
            ),  # fmt: skip
            "loop_query": torch.tensor([e.query for e in self.loops], dtype=torch.int64),
            "loop_candidate": torch.tensor([e.candidate for e in self.loops], dtype=torch.int64),
            "loop_transform": stack([e.transform for e in self.loops], (4, 4), np.float64),
            "loop_info": stack([e.information for e in self.loops], (DOF, DOF), np.float64),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        offsets = state["offsets"].numpy()
        desc, points = state["descriptors"].numpy(), state["points"].numpy()
        self.features = [
            KeyframeFeatures(int(frame), int(submap), np.ascontiguousarray(c2w),
                             np.ascontiguousarray(desc[a:b]), np.ascontiguousarray(points[a:b]))
            for frame, submap, c2w, a, b in zip(state["frames"].tolist(),
                                                state["submaps"].tolist(),
                                                state["c2w"].numpy(), offsets[:-1], offsets[1:],
                                                strict=True)
        ]  # fmt: skip
        self.vocabulary = np.ascontiguousarray(state["vocabulary"].numpy())
        self.trained_on = int(state["trained_on"])
        self.corrections = [np.ascontiguousarray(c) for c in state["corrections"].numpy()]
        worlds = state.get("world_offsets")  # absent in older checkpoints: none recorded
        self.world_offsets = ([np.eye(4)] * (len(self.corrections) + 1) if worlds is None else
                              [np.ascontiguousarray(w) for w in worlds.numpy()])  # fmt: skip
        self.odometry = [Edge(k + 1, k, np.ascontiguousarray(t), np.ascontiguousarray(i), False)
                         for k, (t, i) in enumerate(zip(state["odometry"].numpy(),
                                                        state["odometry_info"].numpy(),
                                                        strict=True))]  # fmt: skip
        self.loops = [LoopEdge(int(a), int(b), np.ascontiguousarray(t), np.ascontiguousarray(i))
                      for a, b, t, i in zip(state["loop_query"].tolist(),
                                            state["loop_candidate"].tolist(),
                                            state["loop_transform"].numpy(),
                                            state["loop_info"].numpy(), strict=True)]  # fmt: skip
        self._words = []

"""Loop closure end to end on synthetic sequences: ATE with and without it, loops
where ground truth has them, none without a revisit, and resume across a correction."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from bgs_batch.config import load_config
from bgs_batch.slam.loop_closure.correction import transform_params
from bgs_batch.slam.loop_closure.evaluation import accepted_loops, is_true_loop, submap_frames
from bgs_batch.store import FrameStore
from bgs_batch.trajectory_files import read_tum
from converters.synthetic import SynthConfig, synthesize
from converters.tum import convert_tum
from jobs.run import TIMING_FIELDS, run_job
from outputs.jobfiles import FinishedJob

SIZE = {"width": 160, "height": 120, "seed": 1, "fps": 10.0, "speed": 0.2}
LOOP = SynthConfig(frames=41, loop=True, path_radius=0.1, **SIZE)  # two laps of 20 frames
OPEN = SynthConfig(frames=25, turn_rate=0.8, **SIZE)  # half a lap, turning 100°: no revisit
SETTINGS = [
    "submaps.mode=interval", "submaps.every=8",  # submap 2 holds frames 16-23, 20 ≈ 0
    "loop_closure.min_submaps=3", "loop_closure.min_interval=1",  # few submaps here
    "loop_closure.orb_patch=15", "loop_closure.orb_fast_threshold=10",  # 160×120 images
    "loop_closure.inject_drift_deg=2.0", "loop_closure.inject_drift_m=0.02",
    "checkpoint_every=5",
    "smoothing.enabled=false",  # trajectory.txt as corrected, to compare with the submap files
]  # fmt: skip
FIRST_LOOP_FRAME = 24  # the switch that finishes submap 2 closes the first loop (2 → 0)
MAX_ATE_RATIO = 0.6


def make_store(root: Path, synth: SynthConfig) -> Path:
    folder = synthesize(root / "seq", synth)
    return convert_tum(folder, root / "seq.h5")


def read_log(job: Path) -> list[dict]:
    return [json.loads(line) for line in (job / "log.jsonl").read_text().splitlines()]


def ground_truth(store: Path) -> np.ndarray:
    with FrameStore(store) as opened:
        return np.linalg.inv(opened.poses_gt[0]) @ opened.poses_gt


@pytest.fixture(scope="module")
def loop_case(tmp_path_factory):
    root = tmp_path_factory.mktemp("loop")
    store = make_store(root, LOOP)
    on = run_job(store, root / "on", load_config("cpu", SETTINGS))
    off = run_job(
        store, root / "off", load_config("cpu", [*SETTINGS, "loop_closure.enabled=false"])
    )
    return store, root / "on", on, off


@pytest.mark.slow
def test_loop_closure_cuts_the_drift(loop_case):
    _, _, on, off = loop_case
    assert on.ate_rmse_m <= MAX_ATE_RATIO * off.ate_rmse_m, (on.ate_rmse_m, off.ate_rmse_m)
    assert on.stage_seconds["loop_closure"] > 0
    assert off.stage_seconds["loop_closure"] < 0.1 * on.stage_seconds["loop_closure"]


@pytest.mark.slow
def test_loops_are_found_where_they_are_and_recorded(loop_case):
    store, job, _, _ = loop_case
    events = read_log(job)
    loops = accepted_loops(events)
    frames, gt = submap_frames(events), ground_truth(store)
    assert loops and loops[0] == (FIRST_LOOP_FRAME, 2, 0), loops
    assert all(is_true_loop(gt, frames[q], frames[c]) for _, q, c in loops)
    report = events[FIRST_LOOP_FRAME]["loop_closure"]
    assert report["optimised"] and report["loops"][0]["method"] in ("render", "icp")
    assert len(report["correction"]) == 12 and report["max_shift_m"] > 0

    # every corrected submap file holds raw + corrected Gaussians and its correction (the r_i
    # of the corrected ones refined at the end of the run); the cpu preset's trajectory is the
    # logged (as-tracked) pose moved by its submap's correction at each submap's centre frame
    # and before the first and after the last centre, and in between spread along the frames
    # (`continuous_poses`). (Its largest step is not smaller here by design: the injected drift
    # is a step in the odometry, which a rigid correction removes at the switch and the
    # continuous one spreads over the neighbouring frames.)
    _, trajectory = read_tum(job / "trajectory.txt")
    rigid = np.full_like(trajectory, np.nan)
    corrected = 0
    for k, path in enumerate(sorted((job / "submaps").glob("*.pt"))):
        data = torch.load(path, weights_only=True)
        correction = data["correction"].numpy() if "correction" in data else np.eye(4)
        if "correction" in data:
            corrected += 1
            moved = transform_params(data["raw_params"], correction)
            refined = moved.pop("uncertainty_logits"), data["params"]["uncertainty_logits"]
            assert all(torch.equal(moved[n], data["params"][n]) for n in moved)
            assert not torch.equal(*refined)  # the cpu preset refines them
        for i in frames[k]:
            logged = np.vstack([np.reshape(events[i]["pose"], (3, 4)), [0, 0, 0, 1]])
            rigid[i] = correction @ logged
    assert corrected >= 2
    centres = [(min(f) + max(f)) / 2 for _, f in sorted(frames.items())]
    held = [i for i in range(len(trajectory))
            if i in centres or i <= centres[0] or i >= centres[-1]]  # fmt: skip
    np.testing.assert_allclose(trajectory[held], rigid[held], atol=1e-6)
    assert not np.allclose(trajectory, rigid, atol=1e-6)  # spread, not stepped
    # the exports render the map from the poses it was made with: the rigid ones
    np.testing.assert_allclose(FinishedJob(job).mapped_poses(), rigid, rtol=0, atol=1e-12)


@pytest.mark.slow
def test_no_loop_without_a_revisit(tmp_path):
    store = make_store(tmp_path, OPEN)
    run_job(store, tmp_path / "job", load_config("cpu", SETTINGS))
    events = read_log(tmp_path / "job")
    frames, gt = submap_frames(events), ground_truth(store)
    queries = [e["loop_closure"]["query"] for e in events if "loop_closure" in e]
    assert queries, "detection never ran"
    assert not any(is_true_loop(gt, frames[q], frames[c])  # the path really has no revisit
                   for q in queries for c in range(q - 1))  # fmt: skip
    assert accepted_loops(events) == []


@pytest.mark.slow
def test_resume_across_a_loop_closure_equals_uninterrupted(loop_case, tmp_path):
    store, reference, _, _ = loop_case
    job, cfg = tmp_path / "job", load_config("cpu", SETTINGS)

    def stop_after_the_first_loop(event):
        if event["frame"] == FIRST_LOOP_FRAME:  # files corrected, newest checkpoint older
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_job(store, job, cfg, on_frame=stop_after_the_first_loop)
    assert any("correction" in torch.load(p, weights_only=True)
               for p in (job / "submaps").glob("*.pt"))  # fmt: skip
    run_job(store, job, cfg)
    assert (job / "trajectory.txt").read_bytes() == (reference / "trajectory.txt").read_bytes()
    names = sorted(p.name for p in (reference / "submaps").iterdir())
    assert sorted(p.name for p in (job / "submaps").iterdir()) == names
    for name in names:
        ours = torch.load(job / "submaps" / name, weights_only=True)
        theirs = torch.load(reference / "submaps" / name, weights_only=True)
        assert ours.keys() == theirs.keys()
        for key in ("params", "raw_params"):
            if key in theirs:
                assert all(torch.equal(ours[key][n], theirs[key][n]) for n in theirs[key])
    strip = TIMING_FIELDS
    assert [{k: v for k, v in e.items() if k not in strip} for e in read_log(job)] == [
        {k: v for k, v in e.items() if k not in strip} for e in read_log(reference)
    ]

"""The global stage (`bgs_batch.slam.global_map`): which frames it trains on, the order of its
visits, the ownership merge; and on a synthetic room, a run whose global map renders frames it
never trained on better than the merge alone, read back as a user would (``global.ply`` at the
poses of ``trajectory.txt``)."""

import json

import numpy as np
import pytest
import torch

from bgs_batch.config import GlobalMapConfig, load_config
from bgs_batch.render import Camera, Gaussians, render
from bgs_batch.slam.frames import prepare_frame
from bgs_batch.slam.global_map import (
    Ownership,
    SubmapView,
    split_frames,
    visit_order,
)
from bgs_batch.store import FrameStore
from bgs_batch.trajectory_files import read_tum
from converters.synthetic import SynthConfig, synthesize
from converters.tum import convert_tum
from jobs.run import GLOBAL_MAP_FILE, run_job
from outputs.export import ExportOptions, export_job
from outputs.image_metrics import psnr
from outputs.jobfiles import FinishedJob
from outputs.ply import read_ply


def test_every_nth_frame_but_keyframes_is_held_out_and_the_rest_trains():
    split = split_frames(20, keyframes={0, 3, 8, 12}, every=4)
    assert split.held_out == [4, 16]  # 8 and 12 are keyframes: never held out
    assert split.training == [i for i in range(20) if i not in (4, 16)]
    assert split_frames(5, {0}, every=0).held_out == []


def test_visits_are_seeded_permutations_of_the_training_frames():
    order = visit_order([1, 2, 5, 7], passes=2.5, seed=3)
    assert len(order) == 10
    assert sorted(order[:4]) == sorted(order[4:8]) == [1, 2, 5, 7]
    assert order == visit_order([1, 2, 5, 7], passes=2.5, seed=3)
    assert order != visit_order([1, 2, 5, 7], passes=2.5, seed=4)
    assert visit_order([], 2.0, 0) == []


CAMERA = Camera(fx=50.0, fy=50.0, cx=50.0, cy=50.0, width=100, height=100)


def view_from(submap: int, x: float, depth: np.ndarray | float = 1.0) -> SubmapView:
    """A keyframe of `submap` at (x, 0, 0) looking along +z at a wall 1 m away (or `depth`)."""
    w2c = np.eye(4)
    w2c[0, 3] = -x
    depth = np.broadcast_to(np.asarray(depth, float), (100, 100))
    return SubmapView(submap, w2c, CAMERA, np.ones((100, 100)), depth.copy())


def wall(x0: float, x1: float, z: float = 1.0) -> np.ndarray:
    xs = np.linspace(x0, x1, 40)  # no point exactly where the two views tie
    return np.stack([xs, np.zeros_like(xs), np.full_like(xs, z)], 1)


def test_the_more_centrally_seen_copy_of_a_surface_stays_and_no_part_is_lost():
    # two submaps, cameras 0.5 m apart, both see the wall from x = -0.5 to 1; each made its
    # copy of what its keyframe saw: the shared part x in [0, 0.5] is doubled
    a, b = wall(-0.5, 0.5), wall(0.0, 1.0)
    ownership = Ownership([a, b], GlobalMapConfig())
    for view in (view_from(0, 0.0), view_from(1, 0.5)):
        ownership.add(view)
    keep_a, keep_b = ownership.keep(0), ownership.keep(1)
    # a camera sees a point more centrally than the other exactly on its side of x = 0.25
    np.testing.assert_array_equal(keep_a, a[:, 0] <= 0.25)
    np.testing.assert_array_equal(keep_b, b[:, 0] >= 0.25)
    kept = np.concatenate([a[keep_a, 0], b[keep_b, 0]])
    assert kept.min() == -0.5 and kept.max() == 1.0 and np.diff(np.sort(kept)).max() < 0.03


def test_a_gaussian_behind_another_submap_s_surface_is_not_a_copy_of_it():
    behind = wall(0.0, 0.2, z=1.5)  # submap 1 has something 0.5 m behind submap 0's wall
    ownership = Ownership([wall(-0.5, 0.5), behind], GlobalMapConfig())
    ownership.add(view_from(0, 0.0))
    ownership.add(view_from(1, 0.5, depth=1.5))
    assert ownership.keep(1).all()


# ---------------------------------------------------------------- a run on a synthetic room

FRAMES, SIZE = 24, (96, 72)
SETTINGS = ["tracking.iterations=8", "mapping.iterations=4", "mapping.new_submap_iterations=8",
            "seeding.new_submap_points=2000", "seeding.new_submap_gradient_points=500",
            "seeding.new_frame_points=500", "keyframes.max_gap=3", "submaps.max_rotation_deg=6",
            "global_map.hold_out_every=4", "global_map.passes=4"]  # fmt: skip


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """(store, {passes: job}) of one synthetic room run with the global stage and without."""
    root = tmp_path_factory.mktemp("global")
    folder = synthesize(root / "room", SynthConfig(frames=FRAMES, width=SIZE[0],
                                                   height=SIZE[1], seed=11))  # fmt: skip
    store = convert_tum(folder, root / "room.h5")
    jobs, reported = {}, []
    for passes in (0, 4):
        job = root / f"passes{passes}"
        run_job(store, job, load_config("cpu", [*SETTINGS, f"global_map.passes={passes}"]),
                on_visit=lambda done, total, p=passes: reported.append((p, done, total)))
        export_job(job, ExportOptions(uncertainty=False, renders=False, report=False))
        jobs[passes] = job
    return store, jobs, reported


def metrics(job):
    return json.loads((job / "outputs" / "metrics.json").read_text())["global_map"]


@pytest.mark.slow
def test_the_stage_renders_frames_it_never_trained_on_better_than_the_merge(runs):
    _, jobs, _ = runs
    merged, optimised = (metrics(jobs[p]) for p in (0, 4))
    assert merged["held_out_frames"] == optimised["held_out_frames"] != []
    before, after = (m["held_out"]["rendering"] for m in (merged, optimised))
    assert after["psnr_db"] > before["psnr_db"] + 1.0, (before, after)
    assert after["ssim"] > before["ssim"]
    assert after["depth_l1_cm"] < before["depth_l1_cm"]


@pytest.mark.slow
def test_held_out_frames_never_enter_the_stage(runs):
    _, jobs, _ = runs
    record = torch.load(jobs[4] / GLOBAL_MAP_FILE, weights_only=True)
    visits = np.array(record["visits_per_frame"])
    held = record["held_out_frames"]
    keyframes = [e.frame for e in FinishedJob(jobs[4]).events if e.keyframe]
    assert held and not set(held) & set(keyframes)
    assert (visits[held] == 0).all()
    assert (visits[record["training_frames"]] == 4).all()  # 4 passes: each frame 4 times
    assert visits.sum() == record["visits"] == 4 * (FRAMES - len(held))
    reported = runs[2]  # what `bgs run`'s progress bar shows: every visit, of the right total
    assert [(done, total) for p, done, total in reported] == [
        (k, record["visits"]) for k in range(1, record["visits"] + 1)]


@pytest.mark.slow
def test_global_ply_at_the_trajectory_s_poses_is_what_eval_scores(runs):
    """A user's check: read global.ply and trajectory.txt, render the held-out frames."""
    store, jobs, _ = runs
    job = jobs[4]
    export_job(job, ExportOptions(trajectory=False, uncertainty=False, renders=False,
                                  metrics=False, report=False))  # fmt: skip
    splats = read_ply(job / "outputs" / "ply" / "global.ply")
    gaussians = Gaussians(*(torch.from_numpy(a) for a in (
        splats.means, splats.log_scales, splats.quats, splats.opacity_logits, splats.colors,
        np.log(np.expm1(splats.uncertainty)))))  # fmt: skip
    _, poses = read_tum(job / "trajectory.txt")
    finished = FinishedJob(job)
    scored = {row["frame"]: row["psnr_db"]
              for row in metrics(job)["held_out"]["rendering"]["per_frame"]}  # fmt: skip
    assert scored
    with FrameStore(store) as frames:
        for index, expected in scored.items():
            event = finished.events[index]
            full, _ = prepare_frame(frames[index], frames.intrinsics, finished.config,
                                    event.depth_motion, event.readout_motion)  # fmt: skip
            w2c = torch.from_numpy(np.linalg.inv(poses[index])).float()
            with torch.no_grad():
                out = render(gaussians, w2c, full.camera)
            assert psnr(out.color.clamp(0, 1), full.rgb) == pytest.approx(expected, abs=1e-3)

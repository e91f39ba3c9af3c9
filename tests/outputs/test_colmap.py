"""The hand-off to the splat trainers (`outputs.colmap`): read back as its users read it, with
pycolmap and as nerfstudio's transforms.json, on a synthetic room with exact ground truth and on
real fr1/rpy frames."""

import json
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
from click.testing import CliRunner

from bgs_batch.cli import main
from bgs_batch.metrics import align_rigid
from bgs_batch.store import FrameStore
from bgs_batch.trajectory_files import read_tum
from converters.synthetic import SynthConfig, synthesize
from converters.tum import TumOptions, convert_tum
from outputs.colmap import DEPTH_AGREEMENT, DEPTH_UNITS_PER_M, OPENGL_FROM_OPENCV
from outputs.jobfiles import FinishedJob

SETTINGS = ["tracking.iterations=8", "mapping.iterations=4", "mapping.new_submap_iterations=8",
            "seeding.new_submap_points=2000", "seeding.new_submap_gradient_points=500",
            "seeding.new_frame_points=500", "keyframes.max_gap=3",
            "global_map.passes=1"]  # fmt: skip


def bgs(*args):
    return CliRunner().invoke(main, ["-q", *map(str, args)])


def run_and_export(store, job, *export_args):
    sets = sum((["--set", s] for s in SETTINGS), [])
    assert bgs("run", store, "--job-dir", job, "--no-export", *sets).exit_code == 0
    result = bgs("export", job, "--colmap", "--nerfstudio", *export_args)
    assert result.exit_code == 0, result.output
    return job / "outputs" / "colmap"


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    """A synthetic room (exact ground truth, crop 0) run and handed off: (store, job, folder)."""
    root = tmp_path_factory.mktemp("colmap")
    folder = synthesize(root / "room", SynthConfig(frames=12, width=96, height=72, seed=3))
    store = convert_tum(folder, root / "room.h5")
    job = root / "job"
    return store, job, run_and_export(store, job, "--text")


def pose_of(image: pycolmap.Image) -> np.ndarray:
    """Camera-to-world (4×4) of a COLMAP image."""
    return np.linalg.inv(np.vstack([image.cam_from_world().matrix(), [0, 0, 0, 1]]))


def frame_of(image: pycolmap.Image) -> int:
    return int(image.name.removeprefix("frame_").removesuffix(".png"))


def check_model(job, folder, sample=150):
    """Everything a COLMAP reader and a nerfstudio loader need to agree on (the issue's checks)."""
    model = pycolmap.Reconstruction(str(folder / "sparse" / "0"))
    keyframes = [e.frame for e in FinishedJob(job).events if e.keyframe]
    assert model.num_cameras() == 1 and model.num_images() == len(keyframes)
    assert sorted(frame_of(image) for image in model.images.values()) == keyframes
    _, trajectory = read_tum(job / "trajectory.txt")
    for image in model.images.values():
        np.testing.assert_allclose(pose_of(image), trajectory[frame_of(image)], atol=1e-6)
    assert model.num_points3D() > 100
    camera = model.camera(1)
    transforms = json.loads((folder / "transforms.json").read_text())
    by_name = {f["file_path"].split("/")[-1]: f for f in transforms["frames"]}
    assert set(by_name) == {image.name for image in model.images.values()}
    rng = np.random.default_rng(0)
    for point_id in rng.choice(sorted(model.points3D), sample, replace=False):
        point = model.point3D(point_id)
        for element in point.track.elements:
            image = model.image(element.image_id)
            xyz = image.cam_from_world() * point.xyz
            u, v = camera.img_from_cam(xyz[None])[0]
            # where the exported depth image puts a surface: the point's own depth, that pixel
            depth = cv2.imread(str(folder / "depths" / image.name), cv2.IMREAD_UNCHANGED)
            reading = depth[int(v), int(u)] / DEPTH_UNITS_PER_M
            assert abs(reading - xyz[2]) <= DEPTH_AGREEMENT * xyz[2] + 1 / DEPTH_UNITS_PER_M
            assert np.hypot(*(np.array([u, v]) - image.points2D[element.point2D_idx].xy)) < 1e-3
            # nerfstudio: OpenGL camera-to-world, the same pixel
            gl = np.linalg.inv(np.array(by_name[image.name]["transform_matrix"])) @ [*point.xyz, 1]
            u_gl = transforms["fl_x"] * gl[0] / -gl[2] + transforms["cx"]
            v_gl = -transforms["fl_y"] * gl[1] / -gl[2] + transforms["cy"]
            assert np.hypot(u_gl - u, v_gl - v) < 1e-3
    return model


@pytest.mark.slow
def test_a_colmap_reader_and_a_nerfstudio_loader_read_the_room(room):
    store, job, folder = room
    model = check_model(job, folder)
    assert (folder / "sparse" / "0" / "images.txt").is_file()  # --text
    assert pycolmap.Reconstruction(str(folder / "sparse" / "0")).num_images() == model.num_images()
    image = next(iter(model.images.values()))
    colour = cv2.imread(str(folder / "images" / image.name))
    assert colour.shape == (72, 96, 3)
    with FrameStore(store) as frames:  # crop 0, no rolling shutter: the stored frame itself
        np.testing.assert_array_equal(colour[..., ::-1], frames[frame_of(image)].rgb)
    assert json.loads((folder / "transforms.json").read_text())["ply_file_path"] == "sparse_pc.ply"
    assert (folder / "sparse_pc.ply").stat().st_size > 0


@pytest.mark.slow
def test_the_exported_poses_are_the_trajectory_and_near_the_ground_truth(room):
    store, job, folder = room
    model = pycolmap.Reconstruction(str(folder / "sparse" / "0"))
    images = sorted(model.images.values(), key=frame_of)
    centres = np.stack([pose_of(image)[:3, 3] for image in images])
    with FrameStore(store) as frames:
        truth = frames.poses_gt[[frame_of(image) for image in images], :3, 3]
    rot, trans, _ = align_rigid(centres, truth)
    error = np.sqrt(np.mean(np.sum((centres @ rot.T + trans - truth) ** 2, axis=1)))
    ate = json.loads((job / "summary.json").read_text())["ate_rmse_m"]
    assert error < 2 * ate + 1e-3  # the keyframes' share of the job's own error


@pytest.mark.slow
def test_the_camera_reproduces_the_store_s_rays_after_the_crop(tmp_path):
    folder = synthesize(tmp_path / "room", SynthConfig(frames=8, width=96, height=72, seed=5))
    store = convert_tum(folder, tmp_path / "room.h5")
    job = tmp_path / "job"
    sets = sum((["--set", s] for s in [*SETTINGS, "crop_edge=6"]), [])
    assert bgs("run", store, "--job-dir", job, "--no-export", *sets).exit_code == 0
    assert bgs("export", job, "--colmap").exit_code == 0
    camera = pycolmap.Reconstruction(str(job / "outputs/colmap/sparse/0")).camera(1)
    assert (camera.width, camera.height) == (96 - 12, 72 - 12)
    with FrameStore(store) as frames:
        k = frames.intrinsics
    rows, cols = np.mgrid[0:60:7, 0:84:9]
    centres = np.stack([cols.ravel() + 0.5, rows.ravel() + 0.5], 1)  # COLMAP: pixel centres
    rays = camera.cam_from_img(centres)
    store_rays = np.stack([(cols.ravel() + 6 - k[0, 2]) / k[0, 0],  # OpenCV: centres at integers
                           (rows.ravel() + 6 - k[1, 2]) / k[1, 1]], 1)  # fmt: skip
    np.testing.assert_allclose(rays, store_rays, atol=1e-9)


@pytest.mark.slow
def test_all_frames_or_every_nth_and_nothing_left_of_an_earlier_export(room, tmp_path):
    _, job, _ = room
    copy = tmp_path / "job"
    shutil.copytree(job, copy)
    assert bgs("export", copy, "--colmap", "--frames", "all", "--stride", "3").exit_code == 0
    model = pycolmap.Reconstruction(str(copy / "outputs/colmap/sparse/0"))
    assert sorted(frame_of(image) for image in model.images.values()) == [0, 3, 6, 9]
    assert len(list((copy / "outputs/colmap/images").iterdir())) == 4  # the old 5 went whole
    assert not (copy / "outputs/colmap/transforms.json").exists()


@pytest.mark.slow
def test_bad_jobs_and_a_folder_of_the_user_s_are_one_line_and_nothing_is_written(room, tmp_path):
    store, job, _ = room
    copy = tmp_path / "job"
    shutil.copytree(job, copy)
    shutil.rmtree(copy / "outputs")
    (copy / "outputs" / "colmap").mkdir(parents=True)
    (copy / "outputs" / "colmap" / "my_notes.txt").write_text("mine")
    result = bgs("export", copy, "--colmap")
    assert result.exit_code == 4 and "my_notes.txt" in result.output, result.output
    assert sorted(p.name for p in (copy / "outputs" / "colmap").iterdir()) == ["my_notes.txt"]
    (copy / "outputs" / "colmap" / "my_notes.txt").unlink()
    unfinished = tmp_path / "unfinished"
    shutil.copytree(job, unfinished)
    (unfinished / "summary.json").unlink()
    result = bgs("export", unfinished, "--colmap")
    assert result.exit_code == 3 and "summary.json" in result.output
    gone = tmp_path / "gone.h5"
    shutil.copy(store, gone)
    record = json.loads((copy / "job.json").read_text())
    record["store"]["path"] = str(gone)
    (copy / "job.json").write_text(json.dumps(record))
    gone.unlink()
    result = bgs("export", copy, "--colmap")
    assert result.exit_code == 3 and "--store" in result.output
    assert not [p for p in (copy / "outputs").rglob("*") if p.name != "colmap"]


@pytest.mark.slow
def test_real_frames_reproject_onto_their_depth_images(tum_excerpt, tmp_path):
    store = convert_tum(tum_excerpt, tmp_path / "fr1.h5", TumOptions(max_frames=12))
    job = tmp_path / "job"
    folder = run_and_export(store, job)
    model = check_model(job, folder, sample=300)
    assert model.compute_mean_track_length() > 1.5  # a point is seen from several frames
    assert (np.array(json.loads((folder / "transforms.json").read_text())["frames"][0][
        "transform_matrix"]) @ OPENGL_FROM_OPENCV)[3, 3] == 1  # fmt: skip


def test_importing_pycolmap_keeps_the_stop_signal_handlers():
    """pycolmap's glog hooks SIGTERM on import; a job stopped during its export must still stop
    cleanly (the handler of `stop_requests` runs, the process goes on)."""
    code = ("import os, signal, time\n"
            "from jobs.preemption import stop_requests\n"
            "with stop_requests() as stop:\n"
            "    import outputs.colmap\n"
            "    os.kill(os.getpid(), signal.SIGTERM)\n"
            "    time.sleep(0.2)\n"
            "    print('stop', stop.requested)\n")  # fmt: skip
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120, cwd=Path(__file__).parents[2])  # fmt: skip
    assert done.returncode == 0, done.stderr[-500:]
    assert f"stop {int(signal.SIGTERM)}" in done.stdout

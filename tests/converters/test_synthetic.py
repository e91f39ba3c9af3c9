"""Tests of the synthetic TUM-layout sequence generator (converters/synthetic.py)."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bgs_batch.errors import InputError, Interrupted, OutputExistsError
from bgs_batch.geometry import pose_matrix
from converters.synthetic import (
    EFFECTS,
    RoomRenderer,
    SynthConfig,
    camera_path,
    camera_poses,
    motion_config,
    sensor_timing,
    synthesize,
)

SMALL = {"frames": 30, "width": 160, "height": 120, "seed": 3}


@pytest.fixture(scope="module")
def open_seq(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return synthesize(tmp_path_factory.mktemp("open") / "seq", SynthConfig(**SMALL))


@pytest.fixture(scope="module")
def loop_seq(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return synthesize(tmp_path_factory.mktemp("loop") / "seq", SynthConfig(**SMALL, loop=True))


def read_list(path: Path) -> list[list[str]]:
    """The data lines of a TUM list file, split into fields."""
    return [line.split() for line in path.read_text().splitlines() if not line.startswith("#")]


def poses(seq: Path) -> np.ndarray:
    """Camera-to-world 4x4 matrices from groundtruth.txt."""
    gt = np.array(read_list(seq / "groundtruth.txt"), dtype=np.float64)
    return pose_matrix(gt[:, 1:4], gt[:, 4:8])


def depths(seq: Path) -> list[np.ndarray]:
    """Depth images in metres (0 = invalid), in list order."""
    return [
        cv2.imread(str(seq / name), cv2.IMREAD_UNCHANGED) / 5000.0
        for _, name in read_list(seq / "depth.txt")
    ]


def files(seq: Path) -> dict[str, bytes]:
    """Every file of a sequence by relative path, for byte-exact comparison."""
    return {str(p.relative_to(seq)): p.read_bytes() for p in sorted(seq.rglob("*")) if p.is_file()}


def sigma(z: np.ndarray) -> np.ndarray:
    """Kinect v1 depth noise model the generator claims to follow."""
    return 0.0012 + 0.0019 * (z - 0.4) ** 2


def test_tum_layout(open_seq: Path) -> None:
    assert [p.name for p in open_seq.parent.iterdir()] == ["seq"]  # no temp dir left behind
    assert sorted(p.name for p in open_seq.iterdir()) == [
        "calibration.txt",
        "depth",
        "depth.txt",
        "depth_sigma",
        "groundtruth.txt",
        "readout.txt",  # 0: a global shutter, known (not left to `bgs run` to estimate)
        "rgb",
        "rgb.txt",
    ]
    assert float((open_seq / "readout.txt").read_text()) == 0.0
    headers = {
        "rgb.txt": ("# color images", "# timestamp filename"),
        "depth.txt": ("# depth maps", "# timestamp filename"),
        "groundtruth.txt": ("# ground truth trajectory", "# timestamp tx ty tz qx qy qz qw"),
    }
    for name, (first, third) in headers.items():
        lines = (open_seq / name).read_text().splitlines()
        assert (lines[0], lines[2]) == (first, third) and lines[1].startswith("# file:")
        assert len(lines) == 3 + SMALL["frames"]

    rgb, depth, gt = (read_list(open_seq / n) for n in ("rgb.txt", "depth.txt", "groundtruth.txt"))
    stamps = np.array([float(s) for s, _ in rgb])
    np.testing.assert_allclose(np.diff(stamps), 1 / 30, atol=2e-6)
    np.testing.assert_allclose([float(s) for s, _ in depth], stamps + 0.004, atol=2e-6)
    assert [row[0] for row in gt] == [s for s, _ in rgb]  # one exact pose per RGB stamp
    for (stamp, name), (_, depth_name) in zip(rgb, depth, strict=True):
        assert len(stamp.split(".")[1]) == 6 and name == f"rgb/{stamp}.png"
        image = cv2.imread(str(open_seq / name), cv2.IMREAD_UNCHANGED)
        depth_image = cv2.imread(str(open_seq / depth_name), cv2.IMREAD_UNCHANGED)
        assert image.shape == (120, 160, 3) and image.dtype == np.uint8
        assert depth_image.shape == (120, 160) and depth_image.dtype == np.uint16
    calib = [float(x) for x in (open_seq / "calibration.txt").read_text().split()]
    assert calib == [131.25, 131.25, 79.5, 59.5]


def test_depth_sigma_is_the_noise_model_of_each_valid_reading(open_seq: Path) -> None:
    """depth_sigma/ holds, per depth image, σ of the noise drawn at each valid reading: the
    model at the true depth, which the noisy reading is within a few σ of."""
    from converters.synthetic import read_depth_sigma

    depth_names = [name for _, name in read_list(open_seq / "depth.txt")]
    for frame, name in enumerate(depth_names):
        depth = cv2.imread(str(open_seq / name), cv2.IMREAD_UNCHANGED) / 5000.0
        simulated = read_depth_sigma(open_seq, frame)
        assert simulated.shape == depth.shape and simulated.dtype == np.float32
        assert np.array_equal(simulated > 0, depth > 0)
        valid = depth > 0
        difference = np.abs(simulated[valid] - sigma(depth[valid]))
        relative = difference / simulated[valid]
        assert np.median(relative) < 0.01 and relative.max() < 0.2


def test_the_depth_image_is_taken_at_its_own_time_stamp(tmp_path: Path) -> None:
    """depth.txt stamps each depth image `depth_delay` after its colour image, and the image is
    the view from where the camera is then (as Kinect v1's free-running streams are), not from
    the colour image's pose: the noise-free depth from the later pose is the closer one."""
    config = SynthConfig(**{**SMALL, "frames": 3}, depth_delay=0.015, shake_rate=2.0)
    seq = synthesize(tmp_path / "seq", config)
    stamps = [float(t) for t, _ in read_list(seq / "depth.txt")]
    colour_stamps = [float(t) for t, _ in read_list(seq / "rgb.txt")]
    np.testing.assert_allclose(np.subtract(stamps, colour_stamps), 0.015, atol=2e-6)
    renderer = RoomRenderer(config)
    path = camera_path(config)
    measured = depths(seq)[2]
    errors = []
    for frame in (2.0, 2.0 + 0.015 * config.fps):
        _, z, valid = renderer._shade(path(np.array([frame]))[0])
        both = valid & (measured > 0)
        errors.append(np.median(np.abs(measured[both] - z[both])))
    assert errors[1] < 0.5 * errors[0], errors  # only its own pose explains it to the noise


def test_deterministic_per_seed(open_seq: Path, tmp_path: Path) -> None:
    again = synthesize(tmp_path / "again", SynthConfig(**SMALL))
    assert files(again) == files(open_seq)
    other = files(synthesize(tmp_path / "other", SynthConfig(**{**SMALL, "seed": 4})))
    assert other["groundtruth.txt"] != files(open_seq)["groundtruth.txt"]
    ours = files(open_seq)
    rgb_names = [n for n in ours if n.startswith("rgb/")]
    assert all(other[n] != ours[n] for n in rgb_names)


def test_depth_is_the_exact_face_distance_not_embrees_approximation() -> None:
    # Embree's hit distance differs in its last bits between instruction sets; the renderer
    # recomputes it in float64 from the face hit, so it agrees with Embree to float precision
    # and matches the closed form of a camera facing the floor
    from converters.synthetic import RoomRenderer

    config = SynthConfig(**SMALL)
    renderer = RoomRenderer(config)
    looking_down = np.diag([1.0, -1.0, -1.0, 1.0])  # camera z along world -z, 1.3 m above the floor
    looking_down[:3, 3] = [0.0, 0.0, 1.3]
    rays = renderer.rays_cam @ looking_down[:3, :3].T.astype(np.float32)
    origin = np.broadcast_to(looking_down[:3, 3].astype(np.float32), rays.shape)
    import open3d as o3d

    embree = renderer.scene.cast_rays(o3d.core.Tensor(np.concatenate([origin, rays], -1)))
    t = embree["t_hit"].numpy()
    hit = np.isfinite(t)
    normal = embree["primitive_normals"].numpy()
    axis = np.abs(normal).argmax(-1)
    outward = np.take_along_axis(normal, axis[..., None], -1)[..., 0] > 0
    box = embree["geometry_ids"].numpy().astype(np.int64)
    z = renderer._distance(box, outward, axis, origin, rays, hit)
    assert np.allclose(z[hit], t[hit], rtol=1e-5)
    floor = hit & (box == 0) & (axis == 2)
    assert floor.sum() > 0 and np.all(z[floor] == np.float32(1.3))


def test_poses_are_rigid_and_smooth(open_seq: Path) -> None:
    gt = np.array(read_list(open_seq / "groundtruth.txt"), dtype=np.float64)
    np.testing.assert_allclose(np.linalg.norm(gt[:, 4:8], axis=1), 1.0, atol=1e-8)
    assert all(
        len(field.split(".")[1]) >= 6
        for row in read_list(open_seq / "groundtruth.txt")
        for field in row[1:]
    )
    mats = poses(open_seq)
    rot = mats[:, :3, :3]
    np.testing.assert_allclose(
        rot @ rot.transpose(0, 2, 1), np.broadcast_to(np.eye(3), rot.shape), atol=1e-8
    )
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-8)
    # TUM-handheld-like motion: 0.1-0.6 m/s and 5-60 deg/s on average.
    speed = np.linalg.norm(np.diff(mats[:, :3, 3], axis=0), axis=1).mean() * 30
    relative = np.einsum("nji,njk->nik", rot[:-1], rot[1:])
    cos = (np.trace(relative, axis1=1, axis2=2) - 1) / 2
    turn = np.degrees(np.arccos(np.clip(cos, -1, 1))).mean() * 30
    assert 0.1 < speed < 0.6 and 5 < turn < 60
    assert (mats[:, 2, 3] > 0.5).all() and (mats[:, 2, 3] < 2.5).all()  # inside the room


def reprojected_agreement(seq: Path, k: int, shift: float = 0.0) -> float:
    """Share of frame-0 depth pixels that, moved to frame k with GT, match frame k's depth."""
    fx, fy, cx, cy = (float(x) for x in (seq / "calibration.txt").read_text().split())
    mats, depth = poses(seq), depths(seq)
    mats[k, :3, 3] += shift * mats[k, :3, 2]  # optionally move frame k along its optical axis
    v, u = np.nonzero(depth[0])
    z = depth[0][v, u]
    cam0 = np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z, np.ones_like(z)])
    cam_k = np.linalg.inv(mats[k]) @ mats[0] @ cam0
    uk = np.rint(fx * cam_k[0] / cam_k[2] + cx).astype(int)
    vk = np.rint(fy * cam_k[1] / cam_k[2] + cy).astype(int)
    height, width = depth[0].shape
    inside = (cam_k[2] > 0) & (uk >= 0) & (uk < width) & (vk >= 0) & (vk < height)
    predicted, observed = cam_k[2][inside], depth[k][vk[inside], uk[inside]]
    seen = observed > 0
    assert seen.sum() > 0.3 * depth[0].size  # the views overlap substantially
    error = np.abs(predicted[seen] - observed[seen])
    return float(np.mean(error < 4 * np.sqrt(2) * sigma(observed[seen]) + 0.002))


def test_ground_truth_matches_rendered_depth(open_seq: Path) -> None:
    assert reprojected_agreement(open_seq, k=15) > 0.95
    assert reprojected_agreement(open_seq, k=15, shift=0.1) < 0.2  # the check is sensitive


def test_loop_returns_to_start_and_open_path_does_not(open_seq: Path, loop_seq: Path) -> None:
    loop = poses(loop_seq)
    assert np.linalg.norm(loop[-1, :3, 3] - loop[0, :3, 3]) < 1e-6
    np.testing.assert_allclose(loop[-1, :3, :3], loop[0, :3, :3], atol=1e-6)
    assert np.linalg.norm(loop[len(loop) // 2, :3, 3] - loop[0, :3, 3]) > 0.03  # it did move
    open_path = poses(open_seq)
    later = np.linalg.norm(open_path[len(open_path) // 2 :, :3, 3] - open_path[0, :3, 3], axis=1)
    assert later.min() > 0.1


def test_depth_noise_grows_like_kinect(loop_seq: Path) -> None:
    # The loop's first and last frames share a pose: their difference is pure sensor noise.
    first, last = depths(loop_seq)[0], depths(loop_seq)[-1]
    both = (first > 0) & (last > 0)
    z, diff = first[both], (last - first)[both]
    assert np.abs(diff).max() > 0  # independent noise draws
    edges = np.quantile(z, [0.0, 0.33, 0.67, 1.0])
    measured, expected = [], []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        d = diff[(z >= lo) & (z < hi)]
        measured.append(1.4826 * np.median(np.abs(d - np.median(d))))  # robust std
        expected.append(np.sqrt(2) * sigma((lo + hi) / 2))
    assert measured == sorted(measured)
    np.testing.assert_allclose(measured, expected, rtol=0.35)


def test_depth_holes_and_range(open_seq: Path) -> None:
    for depth in depths(open_seq):
        assert 0.02 < np.mean(depth == 0) < 0.15
        valid = depth[depth > 0]
        assert valid.min() >= 0.3 and valid.max() <= 8.0
        assert np.median(valid) > 0.5 and np.median(valid) < 4.0


def test_images_are_richly_textured(open_seq: Path) -> None:
    """Photometric tracking needs gradients everywhere: few blocks are flat beyond sensor noise."""
    for _, name in read_list(open_seq / "rgb.txt")[::10]:
        grey = cv2.cvtColor(cv2.imread(str(open_seq / name)), cv2.COLOR_BGR2GRAY).astype(float)
        smooth = cv2.GaussianBlur(grey, (0, 0), 1.0)
        blocks = smooth.reshape(120 // 10, 10, 160 // 10, 10).std(axis=(1, 3))
        assert np.mean(blocks > 2.0) > 0.8


@pytest.mark.parametrize(
    "change",
    [
        {"frames": 1},
        {"width": 8},
        {"height": 0},
        {"fps": 0.0},
        {"seed": -1},
        {"depth_delay": 0.02},
        {"hole_fraction": 0.7},
        {"depth_range": (0.3, 20.0)},
        {"exposure": 1.5},
        {"readout": -0.1},
        {"depth_readout": 1.5},
        {"shake_rate": -1.0},
        {"exposure": 0.5, "exposure_samples": 1},
    ],
)
def test_bad_config_is_input_error(change: dict, tmp_path: Path) -> None:
    with pytest.raises(InputError):
        synthesize(tmp_path / "seq", SynthConfig(**{**SMALL, **change}))
    assert list(tmp_path.iterdir()) == []


def test_existing_output_needs_overwrite(tmp_path: Path) -> None:
    out = tmp_path / "seq"
    out.mkdir()
    (out / "rgb.txt").write_text("# an older sequence\n")
    (out / "stale.txt").write_text("old")
    config = SynthConfig(**{**SMALL, "frames": 2})
    with pytest.raises(OutputExistsError, match="--overwrite") as error:
        synthesize(out, config)
    assert str(out) in str(error.value) and (out / "stale.txt").exists()
    assert synthesize(out, config, overwrite=True) == out
    assert not (out / "stale.txt").exists() and (out / "groundtruth.txt").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["seq"]  # no temp or backup dirs left


def test_overwrite_never_deletes_a_foreign_directory(tmp_path: Path) -> None:
    (tmp_path / "precious.txt").write_text("keep me")
    with pytest.raises(OutputExistsError, match="not a TUM sequence"):
        synthesize(tmp_path, SynthConfig(**{**SMALL, "frames": 2}), overwrite=True)
    assert [p.name for p in tmp_path.iterdir()] == ["precious.txt"]


def test_interrupted_run_leaves_nothing(tmp_path: Path) -> None:
    calls = []

    def progress(done: int, total: int) -> None:
        calls.append((done, total))
        if done == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        synthesize(tmp_path / "seq", SynthConfig(**{**SMALL, "frames": 5}), progress=progress)
    assert calls == [(1, 5), (2, 5), (3, 5)]
    assert list(tmp_path.iterdir()) == []


def test_sigterm_leaves_nothing(tmp_path: Path) -> None:
    def progress(done: int, total: int) -> None:
        if done == 2:
            os.kill(os.getpid(), signal.SIGTERM)

    handler = signal.getsignal(signal.SIGTERM)
    with pytest.raises(Interrupted) as error:
        synthesize(tmp_path / "seq", SynthConfig(**{**SMALL, "frames": 5}), progress=progress)
    assert error.value.exit_code == 128 + signal.SIGTERM
    assert list(tmp_path.iterdir()) == []
    assert signal.getsignal(signal.SIGTERM) is handler  # restored


# ---------------------------------------------------------------- motions and sensor effects


def angular_speeds(c2w: np.ndarray, fps: float) -> np.ndarray:
    """Rotation rate (rad/s) between consecutive poses."""
    relative = np.einsum("nji,njk->nik", c2w[:-1, :3, :3], c2w[1:, :3, :3])
    cos = np.clip((np.trace(relative, axis1=1, axis2=2) - 1) / 2, -1, 1)
    return np.arccos(cos) * fps


def test_shake_turns_like_tum_fr1_rpy_and_the_other_motions_do_not() -> None:
    rates = {motion: angular_speeds(camera_poses(motion_config(motion, frames=300, seed=11)), 30)
             for motion in ("handheld", "walk", "shake")}  # fmt: skip
    assert 0.8 < np.median(rates["shake"]) < 2.5 and rates["shake"].max() < 4.0
    assert np.median(rates["handheld"]) < 0.6 and np.median(rates["walk"]) < 0.6
    # over 3 s, before the room caps the speed of an open path
    travel = {motion: np.linalg.norm(np.diff(camera_poses(motion_config(
        motion, frames=90, seed=11))[:, :3, 3], axis=0), axis=1).sum() * 30 / 89
        for motion in ("handheld", "walk", "shake")}  # fmt: skip
    assert travel["walk"] > 1.4 * travel["handheld"] > 4 * travel["shake"]  # 0.5, 0.3, 0.08


def test_the_path_between_frames_is_continuous_and_exact_at_frames() -> None:
    config = motion_config("shake", frames=20, seed=5)
    path = camera_path(config)
    frames = camera_poses(config)
    assert np.array_equal(path(np.arange(20.0)), frames)
    halfway = path(np.array([7.5]))[0]
    assert np.abs(halfway[:3, 3] - (frames[7, :3, 3] + frames[8, :3, 3]) / 2).max() < 2e-3


def test_rolling_shutter_reads_rows_in_turn_and_blur_spans_the_exposure() -> None:
    rows, instants = sensor_timing(SynthConfig(height=120, **EFFECTS["rolling_shutter"]))
    assert rows.shape == (120, 1) and rows[0, 0] == -0.45 and rows[-1, 0] == 0.45
    assert np.array_equal(instants, [0.0])
    rows, instants = sensor_timing(SynthConfig(**EFFECTS["blur"]))
    assert rows is None and np.allclose(instants, [-0.25, -0.125, 0, 0.125, 0.25])


def _sharpness(seq: Path) -> float:
    """Mean squared Laplacian of the grey images: lower when blurred."""
    grey = [cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in sorted((seq / "rgb").glob("*.png"))]
    values = [cv2.Laplacian(g.astype(np.float32), cv2.CV_32F).var() for g in grey]
    return float(np.mean(values))


def test_blur_rolling_shutter_and_holes_change_what_the_sensor_sees(tmp_path: Path) -> None:
    small = {**SMALL, "frames": 6}
    sharp = synthesize(tmp_path / "sharp", motion_config("shake", **small))
    hard = synthesize(tmp_path / "hard", motion_config(
        "shake", ("blur", "rolling_shutter", "holes"), **small))  # fmt: skip
    assert _sharpness(hard) < 0.8 * _sharpness(sharp)
    assert (poses(hard) == poses(sharp)).all()  # the same path: ground truth at the time stamp
    holes = [np.mean(cv2.imread(str(f), cv2.IMREAD_UNCHANGED) == 0)
             for f in sorted((hard / "depth").glob("*.png"))]  # fmt: skip
    assert min(holes) > 0.15
    # the rolling shutter moves the depth of the top and bottom rows, not of the middle ones
    def depth(seq: Path, k: int) -> np.ndarray:
        return cv2.imread(str(sorted((seq / "depth").glob("*.png"))[k]), cv2.IMREAD_UNCHANGED)
    skewed = synthesize(tmp_path / "skewed", motion_config("shake", ("rolling_shutter",), **small))
    both = (depth(sharp, 3) > 0) & (depth(skewed, 3) > 0)
    change = np.abs(depth(sharp, 3).astype(np.float64) - depth(skewed, 3)) * both
    h = change.shape[0]
    assert change[: h // 8].mean() > 5 * change[h // 2 - 4 : h // 2 + 4].mean()
    # a global-shutter depth beside the rolling colour (a RealSense D435): the depth image is
    # the sharp sequence's, the colour image the skewed one's, and readout.txt says both
    mixed = synthesize(tmp_path / "mixed", motion_config(
        "shake", ("rolling_shutter", "global_shutter_depth"), **small))  # fmt: skip
    assert np.array_equal(depth(mixed, 3), depth(sharp, 3))
    def rgb(seq: Path, k: int) -> np.ndarray:
        return cv2.imread(str(sorted((seq / "rgb").glob("*.png"))[k]))
    assert np.array_equal(rgb(mixed, 3), rgb(skewed, 3))
    assert [float(x) for x in (mixed / "readout.txt").read_text().split()] == [0.03, 0.0]
    assert [float(x) for x in (skewed / "readout.txt").read_text().split()] == [0.03]


def test_a_misregistered_colour_camera_sees_the_room_from_its_own_pose(tmp_path: Path) -> None:
    """`--misregister`: the depth images are the registered room's; each depth point projected
    into the colour camera (its offset pose and longer focal length) finds the colour the
    registered camera saw at that point, while the same pixel does not."""
    small = {**SMALL, "frames": 2}
    registered = synthesize(tmp_path / "reg", motion_config("handheld", **small))
    effect = motion_config("handheld", ("misregister",), **small)
    moved = synthesize(tmp_path / "mis", effect)
    def image(seq: Path, folder: str) -> np.ndarray:
        return cv2.imread(str(sorted((seq / folder).glob("*.png"))[0]), cv2.IMREAD_UNCHANGED)
    depth = image(moved, "depth").astype(np.float64) / effect.depth_scale
    assert np.array_equal(image(moved, "depth"), image(registered, "depth"))
    fx, fy, cx, cy = effect.intrinsics
    v, u = np.mgrid[: effect.height, : effect.width].astype(np.float64)
    points = np.stack([(u - cx) / fx * depth, (v - cy) / fy * depth, depth], -1)
    offset = effect.colour_offset
    rotation = Rotation.from_rotvec(np.radians(offset[:3])).as_matrix()
    in_colour = (points - offset[3:]) @ rotation  # depth camera → colour camera
    f = effect.colour_focal_ratio
    cu = fx * f * in_colour[..., 0] / in_colour[..., 2] + cx
    cv = fy * f * in_colour[..., 1] / in_colour[..., 2] + cy
    sampled = cv2.remap(image(moved, "rgb"), cu.astype(np.float32), cv.astype(np.float32),
                        cv2.INTER_LINEAR).astype(np.float64)  # fmt: skip
    truth = image(registered, "rgb").astype(np.float64)
    inner = (depth > 0) & (cu > 2) & (cu < effect.width - 3) & (cv > 2) & (cv < effect.height - 3)
    projected = np.median(np.abs(sampled - truth)[inner])
    same_pixel = np.median(np.abs(image(moved, "rgb").astype(np.float64) - truth)[inner])
    assert projected < 4 and same_pixel > 3 * projected

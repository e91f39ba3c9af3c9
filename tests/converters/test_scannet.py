"""ScanNet conversion: an export folder and the .sens it came from give identical stores; invalid
poses become NaN; bad input is refused with a clear message and nothing written."""

from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from bgs_batch.cli import main
from bgs_batch.geometry import pose_matrix
from bgs_batch.store import FrameStore
from converters.scannet import COLOR_RESIZE
from converters.sens import SENS_VERSION, write_sens

COLOR_SIZE, DEPTH_SIZE = (200, 150), (80, 60)  # small stand-ins for 1296x968 and 640x480
FRAMES = 12  # two-digit names check the natural sort
INVALID_POSE = 3


def make_scene(seed: int = 0, frames_count: int = FRAMES, depth_size=DEPTH_SIZE) -> dict:
    """Random smooth frames: JPEG colour bytes, uint16 depth, float32 poses and intrinsics."""
    rng = np.random.default_rng(seed)
    w, h = COLOR_SIZE
    frames = []
    for i in range(frames_count):
        coarse = rng.integers(0, 256, (h // 10, w // 10, 3), np.uint8)
        color = cv2.imencode(".jpg", cv2.resize(coarse, COLOR_SIZE))[1].tobytes()
        depth = rng.integers(500, 4000, depth_size[::-1]).astype(np.uint16)
        depth[0, :5] = 0
        angle = 0.1 * i
        pose = pose_matrix([0.1 * i, 0.0, 1.5], [0, np.sin(angle / 2), 0, np.cos(angle / 2)])
        if i == INVALID_POSE:
            pose[:] = -np.inf
        frames.append((color, depth, pose.astype(np.float32)))
    k_color = np.array([[1170, 0, 647, 0], [0, 1170, 483, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    k_depth = np.array([[577.6, 0, 318.9, 0], [0, 578.7, 242.7, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    return {
        "frames": frames,
        "k_color": k_color.astype(np.float32),
        "k_depth": k_depth.astype(np.float32),
    }


def _matrix_text(matrix: np.ndarray) -> str:
    """Exact text of float32 values (repr of their float64 value), one row per line."""
    return "\n".join(" ".join(repr(float(v)) for v in row) for row in matrix) + "\n"


def write_export(root: Path, scene: dict) -> Path:
    for sub in ("color", "depth", "pose", "intrinsic"):
        (root / sub).mkdir(parents=True)
    for i, (color, depth, pose) in enumerate(scene["frames"]):
        (root / "color" / f"{i}.jpg").write_bytes(color)
        cv2.imwrite(str(root / "depth" / f"{i}.png"), depth)
        (root / "pose" / f"{i}.txt").write_text(_matrix_text(pose))
    (root / "intrinsic" / "intrinsic_depth.txt").write_text(_matrix_text(scene["k_depth"]))
    (root / "intrinsic" / "intrinsic_color.txt").write_text(_matrix_text(scene["k_color"]))
    return root


def write_scene_sens(path: Path, scene: dict, version: int = SENS_VERSION) -> Path:
    write_sens(path, scene["frames"], scene["k_color"], scene["k_depth"], COLOR_SIZE)
    if version != SENS_VERSION:
        with open(path, "r+b") as fh:
            fh.write(struct.pack("<I", version))
    return path


def convert(path: Path, out: Path, *args: str):
    return CliRunner().invoke(main, ["-q", "convert", "scannet", str(path), "-o", str(out), *args])


def assert_refused(result, out: Path, *needles: str) -> None:
    assert result.exit_code == 3, result.output
    for needle in needles:
        assert needle in result.output, result.output
    assert not out.exists() and not Path(f"{out}.tmp").exists()


@pytest.fixture
def scene():
    return make_scene()


def test_export_folder_and_sens_give_identical_stores(scene, tmp_path):
    folder_h5, sens_h5 = tmp_path / "folder.h5", tmp_path / "sens.h5"
    result = convert(write_export(tmp_path / "scene0000_00", scene), folder_h5)
    assert result.exit_code == 0, result.output
    result = convert(write_scene_sens(tmp_path / "scene0000_00.sens", scene), sens_h5)
    assert result.exit_code == 0, result.output
    with FrameStore(folder_h5) as a, FrameStore(sens_h5) as b:
        assert len(a) == len(b) == FRAMES and (a.width, a.height) == DEPTH_SIZE
        assert a.depth_scale == b.depth_scale == 1000
        assert a.attrs["sequence"] == b.attrs["sequence"] == "scene0000_00"
        assert np.array_equal(a.intrinsics, b.intrinsics)
        assert np.allclose(a.intrinsics, scene["k_depth"][:3, :3])
        assert np.array_equal(a.timestamps, b.timestamps)
        assert np.allclose(a.timestamps, np.arange(FRAMES) / 30)
        assert np.array_equal(a.poses_gt, b.poses_gt, equal_nan=True)
        assert np.isnan(a.poses_gt[INVALID_POSE]).all()
        assert a.provenance["gt_frames"] == FRAMES - 1
        expected_pose = scene["frames"][10][2].astype(np.float64)
        assert np.allclose(a.poses_gt[10], expected_pose, atol=1e-6)  # natural order: 10 after 9
        for i, (color, depth, _) in enumerate(scene["frames"]):
            bgr = cv2.imdecode(np.frombuffer(color, np.uint8), cv2.IMREAD_COLOR)
            rgb = cv2.resize(bgr, DEPTH_SIZE, interpolation=COLOR_RESIZE)[..., ::-1]
            assert np.array_equal(a.read_rgb(i), rgb) and np.array_equal(b.read_rgb(i), rgb)
            assert np.array_equal(a.read_depth_raw(i), depth)
            assert np.array_equal(b.read_depth_raw(i), depth)


def test_the_reference_crop_is_recorded_for_640x480_frames(scene, tmp_path):
    full = make_scene(frames_count=2, depth_size=(640, 480))
    for source in (write_export(tmp_path / "scene0001_00", full),
                   write_scene_sens(tmp_path / "scene0001_00.sens", full)):  # fmt: skip
        out = tmp_path / f"{source.name}.h5"
        assert convert(source, out).exit_code == 0
        with FrameStore(out) as store:
            assert store.crop_edge == 12 and "ScanNet" in store.provenance["crop_edge_source"]
    assert convert(write_export(tmp_path / "small", scene), tmp_path / "small.h5").exit_code == 0
    with FrameStore(tmp_path / "small.h5") as store:  # 80x60 stand-ins: no reference crop
        assert store.crop_edge == 0


def test_stride_and_max_frames(scene, tmp_path):
    out = tmp_path / "s.h5"
    path = write_scene_sens(tmp_path / "s.sens", scene)
    assert convert(path, out, "--stride", "5", "--max-frames", "2").exit_code == 0
    with FrameStore(out) as store:
        assert np.allclose(store.timestamps, [0, 5 / 30])
        assert store.provenance["frames_in_source"] == FRAMES


def test_sens_with_wrong_version(scene, tmp_path):
    path = write_scene_sens(tmp_path / "old.sens", scene, version=3)
    out = tmp_path / "out.h5"
    assert_refused(convert(path, out), out, str(path), "version 3", "version 4")


def test_truncated_sens(scene, tmp_path):
    path = write_scene_sens(tmp_path / "cut.sens", scene)
    path.write_bytes(path.read_bytes()[:-100])
    out = tmp_path / "out.h5"
    assert_refused(convert(path, out), out, str(path), "truncated")


def test_corrupt_jpeg_in_export(scene, tmp_path):
    folder = write_export(tmp_path / "scene", scene)
    bad = folder / "color" / "7.jpg"
    bad.write_bytes(bad.read_bytes()[:50])
    out = tmp_path / "out.h5"
    assert_refused(convert(folder, out), out, str(bad), "--skip-bad-frames")
    result = convert(folder, out, "--skip-bad-frames")
    assert result.exit_code == 0, result.output
    assert len(FrameStore(out)) == FRAMES - 1


def test_not_a_scene(tmp_path):
    out = tmp_path / "out.h5"
    (tmp_path / "empty").mkdir()
    assert_refused(convert(tmp_path / "empty", out), out, "intrinsic_depth.txt is missing")


def test_the_readout_is_left_to_bgs_run_unless_given(scene, tmp_path):
    source = write_scene_sens(tmp_path / "r.sens", scene)
    assert convert(source, tmp_path / "default.h5").exit_code == 0
    with FrameStore(tmp_path / "default.h5") as store:  # ScanNet names no readout: estimated
        assert np.isnan(store.rolling_shutter_readout)
        assert np.isnan(store.depth_rolling_shutter_readout)
        assert "estimates it" in store.provenance["rolling_shutter_readout_source"]
    told = tmp_path / "told.h5"  # rolling colour, global-shutter depth
    assert convert(source, told, "--readout", "0.03", "--depth-readout", "0").exit_code == 0
    with FrameStore(told) as store:
        assert store.rolling_shutter_readout == pytest.approx(0.03)
        assert store.depth_rolling_shutter_readout == 0
        assert store.provenance["rolling_shutter_readout_source"] == "--readout"
    bad = tmp_path / "bad.h5"
    assert convert(source, bad, "--readout", "-1").exit_code == 2
    assert not bad.exists()

"""Shared fixtures: tiny TUM-layout folders made on the fly, and the real data in ../shared/data."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bgs_batch.geometry import matrix_to_quat_xyzw

SHARED_DATA = Path(
    os.environ.get("BGS_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data")
)
TUM_EXCERPT = SHARED_DATA / "tum_rgbd" / "rgbd_dataset_freiburg1_rpy"
T0 = 1305031229.5


def tum_header(title: str, columns: str) -> str:
    return f"# {title}\n# file: 'test.bag'\n# {columns}\n"


def make_tum_folder(
    root: Path,
    frames: int = 6,
    size: tuple[int, int] = (32, 24),
    *,
    name: str = "rgbd_dataset_freiburg1_test",
    gt: bool = True,
    seed: int = 0,
    distinct: bool = True,
) -> Path:
    """Write a small, valid TUM folder with random images; return it.

    RGB at 30 Hz, depth 3 ms later, GT at 100 Hz around a slow, known motion. With
    `distinct=False` every frame repeats the first one's images (fast to make when long).
    """
    rng = np.random.default_rng(seed)
    folder = root / name
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    w, h = size
    rgb_lines, depth_lines = [], []
    for i in range(frames):
        t = T0 + i / 30
        rgb_file, depth_file = folder / f"rgb/{t:.6f}.png", folder / f"depth/{t + 0.003:.6f}.png"
        if distinct or i == 0:
            rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
            depth = rng.integers(2500, 20000, (h, w), dtype=np.uint16)
            depth[0, :4] = 0
            cv2.imwrite(str(rgb_file), rgb[..., ::-1])
            cv2.imwrite(str(depth_file), depth)
            first = rgb_file, depth_file
        else:
            shutil.copyfile(first[0], rgb_file)
            shutil.copyfile(first[1], depth_file)
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png\n")
        depth_lines.append(f"{t + 0.003:.6f} depth/{t + 0.003:.6f}.png\n")
    (folder / "rgb.txt").write_text(tum_header("color images", "timestamp filename")
                                    + "".join(rgb_lines))  # fmt: skip
    (folder / "depth.txt").write_text(tum_header("depth maps", "timestamp filename")
                                      + "".join(depth_lines))  # fmt: skip
    if gt:
        times = T0 - 0.5 + np.arange(int((frames / 30 + 1) * 100)) / 100
        (folder / "groundtruth.txt").write_text(
            tum_header("ground truth trajectory", "timestamp tx ty tz qx qy qz qw")
            + "".join(f"{t:.4f} {' '.join(f'{v:.6f}' for v in gt_pose(t))}\n" for t in times)
        )
    return folder


def gt_pose(t: float) -> np.ndarray:
    """The known motion of `make_tum_folder`: translation and yaw linear in time."""
    s = t - T0
    angle = 0.3 * s
    rot = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0],
                    [0, 0, 1]])  # fmt: skip
    return np.concatenate([[1.0 + 0.2 * s, -0.1 * s, 0.5], matrix_to_quat_xyzw(rot)])


def rigid_pose(rotvec_deg, translation) -> np.ndarray:
    """A 4×4 pose from a rotation vector (degrees) and a translation."""
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix()
    pose[:3, 3] = translation
    return pose


@pytest.fixture
def tum_folder(tmp_path: Path) -> Path:
    return make_tum_folder(tmp_path)


@pytest.fixture
def tum_excerpt() -> Path:
    if not (TUM_EXCERPT / "rgb.txt").is_file():
        pytest.skip(f"real TUM excerpt not found at {TUM_EXCERPT} (set BGS_SHARED_DATA)")
    return TUM_EXCERPT

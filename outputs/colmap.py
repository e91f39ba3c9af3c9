"""The hand-off to the tools people train splats with: a COLMAP model and nerfstudio's
``transforms.json`` beside the frames as the run saw them (docs/outputs.md).

``JOB/outputs/colmap/``::

    images/frame_NNNNNN.png   colour as the run saw it: undistorted by the converter, its border
                              cropped, rolling-shutter rows moved to the frame's instant
    depths/frame_NNNNNN.png   depth aligned to images/, 16-bit millimetres (0: no reading)
    sparse/0/                 cameras, images, points3D (.bin; .txt with --text), written and
                              read by pycolmap: one PINHOLE camera, the world-to-camera poses of
                              trajectory.txt, the global map's surface as points with tracks
    transforms.json           nerfstudio's layout (--nerfstudio): camera-to-world in OpenGL
    sparse_pc.ply             axes, depth files, the points as nerfstudio's initial cloud

Two conventions are where hand-written conversions go wrong. COLMAP and nerfstudio put the
centre of the first pixel at (0.5, 0.5) where OpenCV and the run put it at (0, 0), so their
principal point is the run's plus half a pixel. COLMAP stores world-to-camera poses in OpenCV
axes (x right, y down, z forward); nerfstudio camera-to-world in OpenGL axes (y up, z back).

A point of ``points3D`` is a Gaussian centre of the global map (opaque ones, one per 1 cm voxel,
at most `MAX_POINTS`); its track lists the exported frames whose depth image puts a surface
where it is (within `DEPTH_AGREEMENT`), at the pixel it projects to. Points no exported frame
sees are left out.
"""

from __future__ import annotations

import json
import signal
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from bgs_batch.atomic import atomic_dir
from bgs_batch.errors import OutputExistsError
from bgs_batch.render import Camera
from bgs_batch.slam.frames import Level, prepare_frame
from bgs_batch.store import FrameStore
from jobs.preemption import STOP_SIGNALS
from outputs.colormap import rgb_to_bgr8, write_png
from outputs.jobfiles import FinishedJob


def _import_pycolmap():  # noqa: ANN202 - a module
    """pycolmap, without the crash handler its glog installs on import for SIGTERM: it would
    replace Python's, so a job stopped by Slurm during an export would die with a stack dump
    instead of stopping cleanly (exit 75)."""
    handlers = {s: signal.getsignal(s) for s in STOP_SIGNALS}
    import pycolmap

    if threading.current_thread() is threading.main_thread():
        for number, handler in handlers.items():
            if handler is not None:
                signal.signal(number, handler)
    return pycolmap


pycolmap = _import_pycolmap()

COLMAP_DIR = "colmap"
IMAGES, DEPTHS, SPARSE = "images", "depths", "sparse/0"
TRANSFORMS, POINT_CLOUD = "transforms.json", "sparse_pc.ply"
WRITTEN = {"images", "depths", "sparse", TRANSFORMS, POINT_CLOUD}  # what an export leaves there
MAX_POINTS = 100_000  # about what structure from motion gives the 3DGS trainers to start from
POINT_VOXEL_M = 0.01  # one point per voxel: the map's own seeding distance
MIN_OPACITY = 0.5  # fainter Gaussians are not surface (the SLAM prunes below it)
DEPTH_AGREEMENT = 0.05  # a frame sees a point where its depth is within 5 % of the point's
DEPTH_UNITS_PER_M = 1000.0  # 16-bit millimetres: nerfstudio's default depth scale
UINT16_MAX = 65535
PIXEL_CENTRE = 0.5  # the first pixel's centre: (0.5, 0.5) in COLMAP and nerfstudio
OPENGL_FROM_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])  # camera axes: y and z flipped
CAMERA_ID = 1


def file_name(frame: int) -> str:
    return f"frame_{frame:06d}.png"


@dataclass(frozen=True)
class MapPoints:
    """The points of ``points3D``: world positions (float64) and colours (uint8 RGB)."""

    xyz: np.ndarray
    rgb: np.ndarray

    @classmethod
    def from_map(cls, params: dict[str, torch.Tensor]) -> MapPoints:
        """The opaque Gaussians' centres, the most opaque one per `POINT_VOXEL_M` voxel, at most
        `MAX_POINTS` (evenly spread over the map's order)."""
        opacity = torch.sigmoid(params["opacity_logits"]).numpy()
        xyz = params["means"].numpy().astype(np.float64)
        rgb = np.clip(np.round(params["colors"].numpy() * 255), 0, 255).astype(np.uint8)
        order = np.flatnonzero((opacity >= MIN_OPACITY) & np.all(np.isfinite(xyz), axis=1))
        order = order[np.argsort(-opacity[order], kind="stable")]
        voxels = np.floor(xyz[order] / POINT_VOXEL_M).astype(np.int64)
        _, first = np.unique(voxels, axis=0, return_index=True)
        keep = np.sort(order[first])
        if len(keep) > MAX_POINTS:
            keep = keep[np.linspace(0, len(keep) - 1, MAX_POINTS).round().astype(np.int64)]
        return cls(xyz[keep], rgb[keep])


def colmap_camera(camera: Camera) -> pycolmap.Camera:
    """The PINHOLE camera of the exported images, in COLMAP's pixel convention."""
    params = [camera.fx, camera.fy, camera.cx + PIXEL_CENTRE, camera.cy + PIXEL_CENTRE]
    return pycolmap.Camera(model="PINHOLE", width=camera.width, height=camera.height,
                           params=params, camera_id=CAMERA_ID)  # fmt: skip


def observe(points: MapPoints, c2w: np.ndarray, depth: np.ndarray, camera: Camera
            ) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """The points a frame sees (indices) and where, in COLMAP's pixel coordinates [k,2]: in the
    image, in front of the camera, and where the frame's depth reading agrees."""
    w2c = np.linalg.inv(c2w)
    cam = points.xyz @ w2c[:3, :3].T + w2c[:3, 3]
    z = cam[:, 2]
    front = z > 0
    u = np.where(front, camera.fx * cam[:, 0] / np.where(front, z, 1) + camera.cx, -1.0)
    v = np.where(front, camera.fy * cam[:, 1] / np.where(front, z, 1) + camera.cy, -1.0)
    col, row = np.rint(u).astype(np.int64), np.rint(v).astype(np.int64)
    inside = front & (col >= 0) & (col < camera.width) & (row >= 0) & (row < camera.height)
    index = np.flatnonzero(inside)
    reading = depth[row[index], col[index]]
    seen = (reading > 0) & (np.abs(reading - z[index]) <= DEPTH_AGREEMENT * z[index])
    index = index[seen]
    return index, np.stack([u[index], v[index]], 1) + PIXEL_CENTRE


@dataclass(frozen=True)
class Handoff:
    """What `export_handoff` wrote."""

    folder: Path
    images: int
    points: int
    observations: int


def check_folder(folder: Path) -> None:
    """Refuse to replace a folder that holds files an export did not write (a user's own)."""
    foreign = sorted(p.name for p in folder.iterdir() if p.name not in WRITTEN) if (
        folder.is_dir()) else []  # fmt: skip
    if foreign:
        raise OutputExistsError(f"{folder} holds files bgs export did not write "
                                f"({', '.join(foreign[:3])}); move them away or delete the folder, "
                                "then export again")  # fmt: skip


def export_handoff(job: FinishedJob, store: FrameStore, frames: list[int], text: bool = False,
                   nerfstudio: bool = False, progress: Callable[[int], None] | None = None
                   ) -> Handoff:  # fmt: skip
    """Write ``outputs/colmap`` for `frames` (module docstring), replacing an earlier export
    whole; `progress(1)` after each frame."""
    folder = job.outputs / COLMAP_DIR
    check_folder(folder)
    _, poses = job.trajectory()
    points = MapPoints.from_map(job.global_map.params)
    cfg = job.config
    names, camera, model = [], None, ModelBuilder(points)
    with atomic_dir(folder) as tmp:
        for sub in (IMAGES, DEPTHS):
            (tmp / sub).mkdir()
        for index in frames:
            event = job.events[index]
            full: Level = prepare_frame(store[index], store.intrinsics, cfg, event.depth_motion,
                                        *event.readouts)[0]  # fmt: skip
            camera = full.camera
            depth = full.depth[..., 0].numpy()
            write_png(tmp / IMAGES / file_name(index), rgb_to_bgr8(full.rgb.numpy()))
            millimetres = np.clip(np.round(depth * DEPTH_UNITS_PER_M), 0, UINT16_MAX)
            write_png(tmp / DEPTHS / file_name(index), millimetres.astype(np.uint16))
            names.append(file_name(index))
            model.add_view(names[-1], poses[index], camera,
                           *observe(points, poses[index], depth, camera))  # fmt: skip
            if progress is not None:
                progress(1)
        reconstruction = model.reconstruction
        (tmp / SPARSE).mkdir(parents=True)
        reconstruction.write(str(tmp / SPARSE))
        if text:
            reconstruction.write_text(str(tmp / SPARSE))
        if nerfstudio:
            reconstruction.export_PLY(str(tmp / POINT_CLOUD))
            write_transforms(tmp / TRANSFORMS, camera, names, poses[frames])
    return Handoff(folder, len(names), reconstruction.num_points3D(),
                   reconstruction.compute_num_observations())  # fmt: skip


class ModelBuilder:
    """The COLMAP model, built one view at a time (memory: pycolmap's, not a Python copy of
    every observation): one camera, an image per view at its pose (world-to-camera), and each
    point the first time an image sees it, its track growing with every later one."""

    def __init__(self, points: MapPoints) -> None:
        self.points = points
        self.reconstruction = pycolmap.Reconstruction()
        self.point_ids = np.zeros(len(points.xyz), np.int64)  # 0: not in the model yet

    def add_view(self, name: str, c2w: np.ndarray, camera: Camera, index: np.ndarray,
                 pixels: np.ndarray) -> None:  # fmt: skip
        """One frame: its image, the points it sees (`observe`) and where."""
        model = self.reconstruction
        if model.num_cameras() == 0:
            model.add_camera_with_trivial_rig(colmap_camera(camera))
        image_id = model.num_images() + 1
        w2c = np.linalg.inv(c2w)
        image = pycolmap.Image(name=name, keypoints=pixels, camera_id=CAMERA_ID,
                               image_id=image_id)  # fmt: skip
        model.add_image_with_trivial_frame(
            image, pycolmap.Rigid3d(pycolmap.Rotation3d(w2c[:3, :3]), w2c[:3, 3]))
        for point2d, point in enumerate(index.tolist()):
            element = pycolmap.TrackElement(image_id, point2d)
            if self.point_ids[point]:
                model.add_observation(int(self.point_ids[point]), element)
            else:
                self.point_ids[point] = model.add_point3D(
                    self.points.xyz[point], pycolmap.Track([element]), self.points.rgb[point])


def write_transforms(path: Path, camera: Camera, names: list[str], c2w: np.ndarray) -> None:
    """nerfstudio's ``transforms.json``: the COLMAP camera's intrinsics (OPENCV model with no
    distortion) and each frame's camera-to-world pose in OpenGL axes."""
    frames = [{"file_path": f"{IMAGES}/{name}", "depth_file_path": f"{DEPTHS}/{name}",
               "transform_matrix": (pose @ OPENGL_FROM_OPENCV).tolist(), "colmap_im_id": k}
              for k, (name, pose) in enumerate(zip(names, c2w, strict=True), 1)]  # fmt: skip
    document = {
        "camera_model": "OPENCV",
        "fl_x": camera.fx, "fl_y": camera.fy,
        "cx": camera.cx + PIXEL_CENTRE, "cy": camera.cy + PIXEL_CENTRE,
        "w": camera.width, "h": camera.height,
        "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
        "ply_file_path": POINT_CLOUD,
        "frames": frames,
    }  # fmt: skip
    path.write_text(json.dumps(document, indent=2) + "\n")

"""TUM RGB-D folders (``rgb.txt``, ``depth.txt``, ``groundtruth.txt``) → frame store.

File formats follow the TUM RGB-D benchmark: list files of ``timestamp filename`` lines with ``#``
comments, 16-bit depth PNGs with 5000 units per metre (other sensors' exports in this layout often
use millimetres: ``depth_scale``), and ``timestamp tx ty tz qx qy qz qw`` ground truth
(camera-to-world of the colour camera's optical centre). Folders in the ETH3D SLAM layout carry
their pinhole intrinsics in ``calibration.txt`` (``fx fy cx cy``); ``bgs synth`` adds
``readout.txt`` (the seconds over which its rolling shutter reads the rows out) when it has one.

The defaults give what the reference systems feed their SLAM: images of a freiburg1/2 camera are
undistorted with its published coefficients, and the store records the border crop those
systems use for the camera, which ``bgs run`` applies unless told otherwise; the store also
records the camera's rolling-shutter readout, which the `cpu` preset corrects.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from bgs_batch.errors import InputError
from bgs_batch.geometry import interpolate_poses
from bgs_batch.store import MAX_READOUT_S, READOUT_UNKNOWN, StoreMeta
from converters import image_codec
from converters.association import associate, association_summary
from converters.image_codec import ImageDecodeError
from converters.pipeline import SourceFrame, write_store

TUM_DEPTH_SCALE = 5000.0
QUATERNION_NORM_TOLERANCE = 1e-2  # TUM prints 4 decimals; anything further off is corrupt
TUM_IMAGE_SIZE = (640, 480)  # the size the published calibrations (and their crops) are for
PLAUSIBLE_MEDIAN_DEPTH_M = (0.1, 20.0)  # RGB-D sensors; outside it, the depth scale is wrong
DEPTH_SAMPLES = 3  # depth images whose median the scale check reads (first, middle, last)
# The TUM cameras (Kinect v1 in fr1/fr2, Asus Xtion in fr3) are PrimeSense-class rolling-shutter
# CMOS cameras; their rows are taken as read out over 0.9 of the 30 Hz frame interval, the value
# `bgs synth --rolling-shutter` simulates (Kerl et al., ICCV 2015, simulate 28 ms for such a
# camera). A physical assumption, not a value fitted to a recording (docs/conversion-defaults.md)
KINECT_READOUT_S = 0.9 / 30
READOUT_FILE = "readout.txt"  # `bgs synth`: the simulated readout in seconds


@dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics (fx, fy, cx, cy), OpenCV distortion (k1, k2, p1, p2, k3) and the border
    (pixels per side) the reference systems crop from this camera's images, with their names."""

    intrinsics: tuple[float, float, float, float]
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    crop_edge: int = 0
    crop_edge_source: str = ""
    readout: float = 0.0  # s over which the rows are read out (0: global shutter)
    depth_readout: float | None = None  # the depth image's, when it differs (None: the same)
    registered: bool = False  # the recordings register depth to colour with its calibration

    @property
    def matrix(self) -> np.ndarray:
        fx, fy, cx, cy = self.intrinsics
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


# Published calibration of the TUM RGB-D colour cameras (vision.in.tum.de, "File Formats"), and
# the crops of the reference systems' TUM camera blocks: fr1 50 px and fr2 8 px in LoopSplat's
# and the BayesianGS authors' configs; fr3, whose published images are already undistorted, 8 px
# in SplaTAM's (LoopSplat crops fr3 by 50 px because it reuses the fr1 calibration there)
# The benchmark's depth images are registered to the colour camera by the Kinect's driver
# (OpenNI) with its factory calibration ("File Formats": "the depth images are already
# registered w.r.t. the corresponding RGB images").
TUM_CAMERAS: dict[str, Camera] = {
    "freiburg1": Camera((517.3, 516.5, 318.6, 255.3), (0.2624, -0.9531, -0.0054, 0.0026, 1.1633),
                        50, "LoopSplat's and BayesianGS's TUM fr1 camera", KINECT_READOUT_S,
                        registered=True),
    "freiburg2": Camera((520.9, 521.0, 325.1, 249.7), (0.2312, -0.7849, -0.0033, -0.0001, 0.9172),
                        8, "LoopSplat's and BayesianGS's TUM fr2 camera", KINECT_READOUT_S,
                        registered=True),
    "freiburg3": Camera((535.4, 539.2, 320.1, 247.6), crop_edge=8,
                        crop_edge_source="SplaTAM's TUM fr3 camera", readout=KINECT_READOUT_S,
                        registered=True),
}  # fmt: skip


@dataclass(frozen=True)
class TumOptions:
    """Choices of a TUM conversion; every one is recorded in the store's provenance."""

    tolerance: float = 0.02  # s, max |t_rgb - t_depth| for an association
    gt_max_gap: float = 0.1  # s, max spacing of the two GT samples bracketing a frame
    intrinsics: tuple[float, float, float, float] | None = None  # overrides detection
    distortion: tuple[float, float, float, float, float] | None = None  # overrides detection
    # s, rolling-shutter readout, overrides detection; READOUT_UNKNOWN: `bgs run` estimates it
    readout: float | None = None
    depth_readout: float | None = None  # s, the depth image's when it differs; overrides
    undistort: bool = True  # with known, non-zero distortion; False stores the raw images
    depth_scale: float = TUM_DEPTH_SCALE  # units per metre of the depth PNGs
    stride: int = 1
    max_frames: int | None = None


def read_file_list(path: Path) -> tuple[np.ndarray, list[str]]:
    """Parse a TUM list file into strictly increasing timestamps and file names."""
    if not path.is_file():
        raise InputError(f"{path} is missing; a TUM RGB-D folder needs rgb.txt and depth.txt")
    stamps: list[float] = []
    names: list[str] = []
    for number, line in _data_lines(path):
        fields = line.split()
        if len(fields) != 2:
            raise InputError(f"{path}:{number}: expected 'timestamp filename', got {line!r}")
        stamp = _parse_float(fields[0], path, number)
        if stamps and stamp <= stamps[-1]:
            kind = "duplicate" if stamp == stamps[-1] else "decreasing"
            raise InputError(
                f"{path}:{number}: {kind} timestamp {fields[0]}; timestamps must strictly "
                "increase: sort the file and remove repeated lines"
            )
        stamps.append(stamp)
        names.append(fields[1])
    if not stamps:
        raise InputError(f"{path} lists no frames")
    return np.asarray(stamps), names


def read_groundtruth(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Parse ``groundtruth.txt`` into (times, translations (N, 3), unit quaternions xyzw (N, 4))."""
    rows = []
    for number, line in _data_lines(path):
        fields = line.split()
        if len(fields) != 8:
            raise InputError(f"{path}:{number}: expected 'timestamp tx ty tz qx qy qz qw'")
        row = [_parse_float(x, path, number) for x in fields]
        if not np.all(np.isfinite(row)):
            raise InputError(
                f"{path}:{number}: {' '.join(fields)} holds a value that is not a finite "
                "number; the file is corrupt: restore it from the dataset or delete it to "
                "convert without GT"
            )
        norm = np.linalg.norm(row[4:])
        if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
            raise InputError(
                f"{path}:{number}: quaternion {fields[4:]} has norm {norm:.4f}, not 1; the file "
                "is corrupt: restore it from the dataset or delete it to convert without GT"
            )
        if rows and row[0] <= rows[-1][0]:
            raise InputError(f"{path}:{number}: timestamps must strictly increase")
        rows.append(row)
    if not rows:
        raise InputError(f"{path} holds no poses; delete it to convert without ground truth")
    data = np.asarray(rows)
    quats = data[:, 4:] / np.linalg.norm(data[:, 4:], axis=1, keepdims=True)
    return data[:, 0], data[:, 1:4], quats


def _data_lines(path: Path):
    """(line number, text) of the data lines; "utf-8-sig": a BOM some editors put first is not
    part of the first line."""
    with open(path, encoding="utf-8-sig", errors="replace") as fh:
        for number, line in enumerate(fh, 1):
            line = line.strip()
            if line and not line.startswith("#"):
                yield number, line


def _parse_float(text: str, path: Path, number: int) -> float:
    try:
        return float(text)
    except ValueError:
        raise InputError(f"{path}:{number}: {text!r} is not a number") from None


def detect_camera(folder: Path, options: TumOptions) -> tuple[Camera, dict[str, str]]:
    """Pick intrinsics, distortion and readout: options > ``calibration.txt`` (and
    ``readout.txt``) > freiburg name. The reference crop comes with a published calibration
    only, not with ``--intrinsics``; the readout is the sensor's, whatever its intrinsics."""
    found: Camera | None = None
    source = ""
    calibration = folder / "calibration.txt"
    name = re.search(r"freiburg([123])", folder.resolve().name)
    if calibration.is_file():
        values = [_parse_float(x, calibration, 1) for x in calibration.read_text().split()]
        if len(values) != 4:
            raise InputError(f"{calibration}: expected one line 'fx fy cx cy'")
        found, source = Camera(tuple(values)), "calibration.txt"
    elif name:
        key = f"freiburg{name.group(1)}"
        found, source = TUM_CAMERAS[key], f"{key} (published TUM calibration)"
    if options.intrinsics is None and found is None:
        raise InputError(
            f"cannot tell the camera of {folder}: its name has no freiburg1/2/3 and it has no "
            "calibration.txt; pass --intrinsics FX FY CX CY (and --distortion if needed)"
        )
    intrinsics = options.intrinsics or found.intrinsics
    distortion = options.distortion or (found.distortion if found else Camera.distortion)
    provenance = {
        "intrinsics_source": "--intrinsics" if options.intrinsics else source,
        "distortion_source": "--distortion" if options.distortion else (source or "none (zero)"),
    }
    readouts, provenance["rolling_shutter_readout_source"] = _readout(folder, options, found,
                                                                      source)  # fmt: skip
    if options.depth_readout is not None:
        readouts = (readouts[0], float(options.depth_readout))
        provenance["depth_rolling_shutter_readout_source"] = "--depth-readout"
    camera = Camera(tuple(map(float, intrinsics)), tuple(map(float, distortion)),
                    readout=readouts[0], depth_readout=readouts[1])  # fmt: skip
    if found is not None and options.intrinsics is None:  # the calibration's crop comes along
        camera = replace(camera, crop_edge=found.crop_edge, crop_edge_source=found.crop_edge_source)
    if found is not None and found.registered:  # the recording's, whatever intrinsics are passed
        camera = replace(camera, registered=True)
        provenance["depth_registered_source"] = f"{source}: registered by the Kinect's driver"
    return camera, provenance


def _readout(folder: Path, options: TumOptions, found: Camera | None, source: str
             ) -> tuple[tuple[float, float | None], str]:  # fmt: skip
    """The rolling-shutter readouts (s) of the colour and the depth image (None: the colour
    image's) and where they came from: ``--readout`` > ``readout.txt`` (one number, or the
    colour's and the depth's) > the published camera's > unknown (`bgs run` estimates it)."""
    if options.readout is not None:
        if math.isnan(options.readout):
            return (READOUT_UNKNOWN, None), "--readout auto: `bgs run` estimates it from the frames"
        return (float(options.readout), None), "--readout"
    path = folder / READOUT_FILE
    if path.is_file():
        values = [_parse_float(x, path, 1) for x in path.read_text().split()]
        if len(values) not in (1, 2) or not all(0 <= v < MAX_READOUT_S for v in values):
            raise InputError(f"{path}: expected seconds, >= 0 and below {MAX_READOUT_S}: the "
                             "readout of both images, or of the colour then the depth image")
        return (values[0], values[1] if len(values) == 2 else None), READOUT_FILE
    if found is not None and found.readout:
        return (found.readout, None), f"{source}: PrimeSense-class rolling shutter"
    return (READOUT_UNKNOWN, None), ("unknown camera: `bgs run` estimates it from the frames "
                                     "(pass --readout SECONDS, or 0 for a global shutter)")


@dataclass(frozen=True)
class _Undistorter:
    """Consistent undistortion of colour (bilinear) and depth (nearest: no mixed depths)."""

    map_x: np.ndarray
    map_y: np.ndarray

    @classmethod
    def build(cls, camera: Camera, size: tuple[int, int]) -> _Undistorter:
        k = camera.matrix
        map_x, map_y = cv2.initUndistortRectifyMap(
            k, np.asarray(camera.distortion), None, k, size, cv2.CV_32FC1
        )
        return cls(map_x, map_y)

    def __call__(self, rgb: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        rgb = cv2.remap(rgb, self.map_x, self.map_y, cv2.INTER_LINEAR, borderValue=0)
        depth = cv2.remap(depth, self.map_x, self.map_y, cv2.INTER_NEAREST, borderValue=0)
        return rgb, depth


def _read_image(path: Path, kind: str) -> np.ndarray:
    try:
        image = image_codec.read(path, cv2.IMREAD_UNCHANGED, f"{kind} image")
    except ImageDecodeError as err:
        raise InputError(f"{err}; restore it from the dataset or pass --skip-bad-frames to "
                         "drop the frame") from None  # fmt: skip
    if kind == "rgb":
        if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] not in (3, 4):
            raise InputError(f"{path}: expected an 8-bit colour image, got {image.dtype} "
                             f"{image.shape}")  # fmt: skip
        return cv2.cvtColor(image, cv2.COLOR_BGRA2RGB if image.shape[2] == 4 else cv2.COLOR_BGR2RGB)
    if image.dtype != np.uint16 or image.ndim != 2:
        raise InputError(f"{path}: expected a 16-bit single-channel depth PNG, got "
                         f"{image.dtype} {image.shape}")  # fmt: skip
    return image


def load_pair(
    rgb_path: Path, depth_path: Path, undistort: _Undistorter | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Decode one RGB-D pair (RGB uint8, depth uint16 in 1/5000 m), undistorted if asked."""
    rgb, depth = _read_image(rgb_path, "rgb"), _read_image(depth_path, "depth")
    if rgb.shape[:2] != depth.shape:
        raise InputError(
            f"{rgb_path} is {rgb.shape[1]}x{rgb.shape[0]} but {depth_path} is "
            f"{depth.shape[1]}x{depth.shape[0]}; TUM depth must be registered to colour pixel "
            "for pixel: use the dataset's registered depth"
        )
    if undistort is None:
        return rgb, depth
    if rgb.shape[:2] != undistort.map_x.shape:
        h, w = undistort.map_x.shape
        raise InputError(
            f"{rgb_path}: size {rgb.shape[1]}x{rgb.shape[0]} differs from the first frame's "
            f"{w}x{h}; a store holds one camera: convert the parts separately or drop the odd "
            "frames"
        )
    return undistort(rgb, depth)


@dataclass(frozen=True)
class TumPlan:
    """Everything decided before decoding: which frames, their poses, the store metadata and the
    lines a user should read (what the association dropped, warnings)."""

    frames: list[SourceFrame]
    meta: StoreMeta
    notes: tuple[str, ...] = ()

    @property
    def count(self) -> int:
        return len(self.frames)


def plan_tum(folder: Path, options: TumOptions) -> TumPlan:
    """Read the list files, associate and interpolate GT; decode only the few images that fix
    the image size and check the depth scale.

    Missing or unreadable images surface when their frame is decoded (naming the file), so
    ``--skip-bad-frames`` can drop them.
    """
    folder = Path(folder)
    _check_options(folder, options)
    pairs = _Pairs.read(folder, options)
    gt_file = folder / "groundtruth.txt"
    poses = None
    if gt_file.is_file():
        poses = interpolate_poses(*read_groundtruth(gt_file), pairs.stamps, options.gt_max_gap)

    camera, camera_provenance = detect_camera(folder, options)
    size = _image_size(pairs.files)
    # a published calibration holds for the camera's own image size only
    fits = options.distortion is not None or size == TUM_IMAGE_SIZE
    applied = options.undistort and any(camera.distortion) and fits
    undistort = _Undistorter.build(camera, size) if applied else None
    crop_edge, crop_source = _reference_crop(camera, size)
    median_depth = _median_depth(pairs.files, options.depth_scale)

    frames = [
        SourceFrame(
            name=f"{rgb.relative_to(folder)} + {depth.relative_to(folder)}",
            timestamp=float(t),
            pose_gt=None if poses is None or not np.all(np.isfinite(poses[k])) else poses[k],
            load=partial(load_pair, rgb, depth, undistort),
            depth_timestamp=float(t_depth),
        )
        for k, ((rgb, depth), t, t_depth) in enumerate(
            zip(pairs.files, pairs.stamps, pairs.depth_stamps, strict=True))
    ]
    provenance = {
        **pairs.provenance(options),
        "depth_scale_source": (
            "TUM convention (5000 units per metre)"
            if options.depth_scale == TUM_DEPTH_SCALE else "--depth-scale"
        ),
        "depth_median_m": median_depth,
        "undistort": bool(applied),
        "crop_edge_source": crop_source,
        **camera_provenance,
        **_gt_provenance(poses, options.gt_max_gap),
    }  # fmt: skip
    meta = StoreMeta(
        source_format="tum",
        source_path=str(folder.resolve()),
        sequence=folder.resolve().name,
        intrinsics=camera.matrix,
        depth_scale=options.depth_scale,
        distortion=camera.distortion,
        distortion_applied=bool(applied),
        has_gt=poses is not None,
        crop_edge=crop_edge,
        rolling_shutter_readout=camera.readout,
        depth_rolling_shutter_readout=camera.depth_readout,
        depth_registered=camera.registered,
        provenance=provenance,
    )
    notes = (pairs.summary, *_depth_scale_warnings(median_depth, options.depth_scale))
    return TumPlan(frames, meta, notes)


def _check_options(folder: Path, options: TumOptions) -> None:
    """Refuse a missing folder and impossible options before any file is read."""
    if not folder.is_dir():
        raise InputError(f"{folder} is not a folder; pass a TUM RGB-D sequence folder")
    if options.stride < 1 or (options.max_frames is not None and options.max_frames < 1):
        raise InputError("--stride and --max-frames must be at least 1")
    if not options.depth_scale > 0:
        raise InputError(f"--depth-scale must be positive, got {options.depth_scale}")
    readout = options.readout
    if readout is not None and not (math.isnan(readout) or 0 <= readout < MAX_READOUT_S):
        raise InputError(f"--readout must be auto, or >= 0 and below {MAX_READOUT_S} s, got "
                         f"{readout}")  # fmt: skip
    depth = options.depth_readout
    if depth is not None and not 0 <= depth < MAX_READOUT_S:
        raise InputError(f"--depth-readout must be >= 0 and below {MAX_READOUT_S} s, got {depth}")


@dataclass(frozen=True)
class _Pairs:
    """The associated (colour, depth) files that will be converted, after stride and limit."""

    rgb_t: np.ndarray  # every listed colour timestamp
    depth_t: np.ndarray  # every listed depth timestamp
    associated: int  # pairs before stride and limit
    chosen: np.ndarray  # (N, 2) indices into the two lists
    files: list[tuple[Path, Path]]
    summary: str  # the line `bgs convert` prints about what the association dropped

    @classmethod
    def read(cls, folder: Path, options: TumOptions) -> _Pairs:
        rgb_t, rgb_names = read_file_list(folder / "rgb.txt")
        depth_t, depth_names = read_file_list(folder / "depth.txt")
        associated = associate(rgb_t, depth_t, options.tolerance)
        if len(associated) == 0:
            raise InputError(
                f"{folder}: no RGB frame has a depth frame within {options.tolerance} s; check "
                "that rgb.txt and depth.txt belong to the same recording, or raise --tolerance"
            )
        chosen = associated[:: options.stride][: options.max_frames]
        files = [(folder / rgb_names[i], folder / depth_names[j]) for i, j in chosen.tolist()]
        summary = association_summary(rgb_t, depth_t, options.tolerance, len(associated))
        return cls(rgb_t, depth_t, len(associated), chosen, files, summary)

    @property
    def stamps(self) -> np.ndarray:
        """The frames' timestamps: their colour images'."""
        return self.rgb_t[self.chosen[:, 0]]

    @property
    def depth_stamps(self) -> np.ndarray:
        """When the frames' depth images were taken (the store keeps them: tracking moves each
        depth image to its colour image's time, `bgs_batch.slam.depth_timing`)."""
        return self.depth_t[self.chosen[:, 1]]

    def provenance(self, options: TumOptions) -> dict[str, Any]:
        diffs = np.abs(self.stamps - self.depth_stamps)
        return {
            "association": "order-preserving one-to-one, most pairs then least summed |dt|",
            "association_tolerance_s": options.tolerance,
            "association_max_diff_s": float(diffs.max()),
            "rgb_listed": len(self.rgb_t),
            "depth_listed": len(self.depth_t),
            "associated": self.associated,
            "stride": options.stride,
            "max_frames": options.max_frames,
        }


def _gt_provenance(poses: np.ndarray | None, max_gap: float) -> dict[str, Any]:
    """Where the ground truth came from and how many frames have it (nothing without it)."""
    if poses is None:
        return {}
    return {
        "gt_source": "groundtruth.txt",
        "gt_interpolation": f"linear position, slerp rotation, bracket <= {max_gap} s",
        "gt_frames": int(np.all(np.isfinite(poses), axis=(1, 2)).sum()),
    }


def convert_tum(folder: Path, output: Path, options: TumOptions | None = None,
                **write_options: Any) -> Path:  # fmt: skip
    """Plan and write a TUM folder's frame store in one call (`bgs convert tum` as a function);
    `write_options` go to `write_store`. Returns the store's path."""
    plan = plan_tum(folder, options or TumOptions())
    return write_store(plan.frames, output, plan.meta, **write_options).path


def _image_size(files: list[tuple[Path, Path]]) -> tuple[int, int]:
    """(width, height) of the first readable colour image (the store checks the others)."""
    first = next((pair for pair in files if pair[0].is_file()), files[0])
    h, w = _read_image(first[0], "rgb").shape[:2]
    return w, h


def _reference_crop(camera: Camera, size: tuple[int, int]) -> tuple[int, str]:
    """The border the reference systems crop for this camera, and why (0 when there is none)."""
    if not camera.crop_edge:
        return 0, "none: no reference crop for this camera"
    if size != TUM_IMAGE_SIZE:
        native, actual = "x".join(map(str, TUM_IMAGE_SIZE)), "x".join(map(str, size))
        return 0, f"none: {camera.crop_edge_source} crops {native} images, these are {actual}"
    return camera.crop_edge, camera.crop_edge_source


def _depth_scale_warnings(median_depth: float | None, scale: float) -> list[str]:
    """A warning when the sampled median depth is implausible for an RGB-D sensor."""
    low, high = PLAUSIBLE_MEDIAN_DEPTH_M
    if median_depth is None or low <= median_depth <= high:
        return []
    return [f"warning: the depth images' median is {median_depth:.3g} m at --depth-scale "
            f"{scale:g} (units per metre); RGB-D sensors see {low:g}-{high:g} m: TUM uses "
            "5000, most RealSense, Azure Kinect and OpenLORIS exports 1000 (millimetres)"]


def _median_depth(files: list[tuple[Path, Path]], scale: float) -> float | None:
    """Median valid depth (m) of a few depth images spread over the sequence, None if none of
    them can be read (those frames fail, named, when they are converted)."""
    picks = np.linspace(0, len(files) - 1, min(DEPTH_SAMPLES, len(files))).round().astype(int)
    values = []
    for k in sorted(set(picks.tolist())):
        depth = cv2.imread(str(files[k][1]), cv2.IMREAD_UNCHANGED)
        if depth is not None and depth.dtype == np.uint16 and np.any(depth):
            values.append(float(np.median(depth[depth > 0])) / scale)
    return float(np.median(values)) if values else None

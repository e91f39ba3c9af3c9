"""Synthetic RGB-D sequences in TUM layout: a procedurally textured room rendered by ray casting.

The scene is an axis-aligned room (z up, floor at z = 0, centred on the z axis) with seeded
furniture-like boxes along its walls and small clutter on their tops, built as Open3D triangle
meshes in one ``RaycastingScene``. Colour comes from a procedural texture evaluated at each ray's
hit point (multi-octave value noise, stripes and checkers mixed per surface, low-pass filtered by
the pixel footprint so it does not alias) under Lambertian shading from a ceiling light. Depth gets
the Kinect v1 noise model, quantisation and holes. Everything is drawn from ``numpy`` generators
keyed by the seed, so a seed gives byte-identical files, and is vectorised over pixels.

The output is exactly a TUM RGB-D directory (``rgb/``, ``depth/``, ``rgb.txt``, ``depth.txt``,
``groundtruth.txt``) plus ``calibration.txt`` (``fx fy cx cy``, the ETH3D convention),
``readout.txt`` for a rolling shutter (the rows' readout in seconds, recorded by the converter) and
``depth_sigma/``: per depth image, the standard deviation of the noise drawn for each reading
(16-bit PNG, same name as the depth image, ``DEPTH_SIGMA_SCALE`` units per metre), the truth
against which a sensor-noise model can be scored (`read_depth_sigma`). Ground
truth is the exact camera-to-world pose of each rendered frame (OpenCV camera axes: x right,
y down, z forward); depth is registered to the colour camera and rendered from the same pose, its
time stamps are offset only so that readers must associate the two streams.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import open3d as o3d
from scipy.spatial.transform import Rotation

from bgs_batch.atomic import atomic_dir
from bgs_batch.errors import InputError, OutputExistsError
from bgs_batch.geometry import matrix_to_quat_xyzw
from bgs_batch.signals import interruptible
from converters.image_codec import read, write_png
from converters.tum import READOUT_FILE

# Independent random streams derived from the seed (the second entry of the generator key).
_SCENE_STREAM, _PATH_STREAM, _SENSOR_STREAM, _SHAKE_STREAM = 0, 1, 2, 3
# Plane coordinates of a hit on a face whose normal is along axis k: the other two axes.
_PLANE_AXES = np.array([[1, 2], [0, 2], [0, 1]])
_TUM_HEADER = "# {what}\n# file: 'synthetic (bgs synth, seed {seed})'\n# {columns}\n"
_SIZE_LIMITS = (16, 8192)  # image width and height, pixels
_CURVE_SAMPLES = 4096  # for measuring the length and reach of the camera path
_GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))  # turn between noise octaves: lattices never align
_GOLDEN_STEP = 0x9E3779B9  # 2^32 / golden ratio: seed step between octaves (well spread)
DEPTH_SIGMA_DIR = "depth_sigma"
DEPTH_SIGMA_SCALE = 100_000.0  # units per metre: 10 µm steps, up to 0.65 m


@dataclass(frozen=True)
class FurnitureKind:
    """Size ranges (min, max) in metres of one kind of box standing against a wall."""

    name: str
    width: tuple[float, float]
    depth: tuple[float, float]
    height: tuple[float, float]
    legs: bool = False  # a table: a thin top on four legs instead of a solid block


FURNITURE_KINDS = (
    FurnitureKind("cabinet", width=(0.6, 1.2), depth=(0.4, 0.6), height=(0.7, 1.1)),
    FurnitureKind("shelf", width=(0.6, 1.0), depth=(0.3, 0.4), height=(1.5, 2.1)),
    FurnitureKind("table", width=(0.9, 1.5), depth=(0.6, 0.8), height=(0.72, 0.78), legs=True),
)


@dataclass(frozen=True)
class SynthConfig:
    """What to render; every constant of the scene, camera path and sensor model is a field.

    Lengths in metres, angles in radians, times in seconds, colours in [0, 1].
    """

    frames: int = 60
    width: int = 320
    height: int = 240
    seed: int = 0
    loop: bool = False  # the path is a closed curve: the last frame is taken at the first pose
    fps: float = 30.0

    # Time stamps: RGB at start_time + i / fps, depth taken depth_delay later (TUM's streams
    # are not synchronous either: readers associate by nearest time stamp, and the SLAM moves
    # each depth image to its colour image's time).
    start_time: float = 1_700_000_000.0
    depth_delay: float = 0.004

    # Camera: Kinect v1 / TUM focal length, scaled with the image width; principal point centred.
    focal_at_640: float = 525.0
    # Path: a seeded sum of low-frequency harmonics around the room centre, scaled to the speed of
    # TUM handheld sequences (0.2-0.4 m/s, 15-30 deg/s) but kept within path_radius, so very long
    # sequences move more slowly. The look direction sweeps yaw / pitch / roll sinusoidally.
    speed: float = 0.3
    turn_rate: float = 0.4  # mean yaw rate
    path_radius: float = 0.7  # keeps the camera >= 0.5 m from furniture
    path_harmonics: int = 3
    path_ellipse: tuple[float, float] = (0.3, 0.7)  # minor / major axis of the first harmonic
    path_wobble: float = 0.15  # scale of the higher harmonics (and height), relative to major
    eye_height: float = 1.4
    pitch: float = 0.3  # mean downward tilt
    swing_weights: tuple[float, float, float] = (1.0, 0.3, 0.1)  # yaw, pitch, roll amplitudes ...
    swing_limits: tuple[float, float, float] = (1.2, 0.25, 0.08)  # ... and their caps
    # Shaking (0: none): on top of the path, each of yaw / pitch / roll gets two seeded
    # sinusoids of shake_hz frequencies whose rates add up to about shake_rate (rad/s) times the
    # axis weight, as a hand shaking the camera the way TUM fr1/rpy does (about 1 rad/s).
    shake_rate: float = 0.0
    shake_hz: tuple[float, float] = (0.4, 1.2)
    shake_weights: tuple[float, float, float] = (1.0, 1.0, 0.6)

    # Sensor timing, as fractions of the frame interval (0: an ideal global shutter with an
    # instantaneous exposure). The ground-truth pose is the camera's at the frame's time stamp,
    # which is the middle of the exposure of the middle row.
    exposure: float = 0.0  # motion blur: colour averaged over this long an exposure ...
    exposure_samples: int = 5  # ... sampled at this many instants
    readout: float = 0.0  # rolling shutter: the rows are read out top to bottom over this long
    # the depth image's readout when its sensor reads out otherwise (a RealSense D435: global
    # depth, rolling colour); None: as the colour image's
    depth_readout: float | None = None
    # The colour camera beside the depth camera, never registered to it (what one published set
    # of intrinsics hides): its pose in the depth camera's frame (rotation vector in degrees,
    # translation in m) and its focal length over the depth camera's. The ground truth, the
    # depth image and calibration.txt are the depth camera's
    colour_offset: tuple[float, float, float, float, float, float] = (0.0,) * 6
    colour_focal_ratio: float = 1.0

    # Scene: room size (x, y, z), furniture per wall, clutter boxes on top of each piece.
    room_size: tuple[float, float, float] = (5.0, 4.0, 2.7)
    furniture: tuple[FurnitureKind, ...] = FURNITURE_KINDS
    items_per_wall: tuple[int, int] = (1, 2)
    corner_margin: float = 0.7  # no furniture this close to a corner
    table_top: float = 0.04  # thickness of a table top ...
    table_leg: float = 0.05  # ... and width of its legs
    clutter_per_top: tuple[int, int] = (0, 3)
    clutter_size: tuple[float, float] = (0.08, 0.3)

    # Texture: fbm value noise (largest wavelength, octaves), stripes and checkers mixed with
    # seeded weights per face; detail finer than texture_min_pixels pixels fades to its mean.
    texture_wavelength: float = 0.8
    texture_octaves: int = 6
    texture_persistence: float = 0.8  # amplitude ratio of successive octaves (rich fine detail)
    noise_share: float = 0.4  # at least this share of every face's mix is noise (no flat bands)
    stripe_period: tuple[float, float] = (0.05, 0.25)
    stripe_warp: float = 1.5  # wood-grain distortion of the stripes by the noise, in periods
    tile_size: tuple[float, float] = (0.15, 0.5)
    texture_contrast: float = 1.5
    texture_min_pixels: float = 2.0
    # Per-face palette: two tones of one hue (HSV value ranges of the dark and light tone).
    saturation: tuple[float, float] = (0.1, 0.6)
    dark_value: tuple[float, float] = (0.2, 0.45)
    light_value: tuple[float, float] = (0.65, 0.95)
    light_hue_shift: float = 40.0  # degrees of hue between the two tones, at most
    # Shading: Lambertian, one point light under the ceiling plus ambient light.
    light_position: tuple[float, float, float] = (0.4, -0.3, 2.4)
    ambient: float = 0.35
    rgb_noise: float = 1.5  # sensor noise sigma, 8-bit levels

    # Depth: Kinect v1 axial noise sigma(z) = a + b (z - z0)^2 (Nguyen et al. 2012), TUM's
    # 5000 units per metre, invalid outside the range, at grazing incidence and in blob holes.
    depth_scale: float = 5000.0
    noise_a: float = 0.0012
    noise_b: float = 0.0019
    noise_z0: float = 0.4
    depth_range: tuple[float, float] = (0.3, 8.0)
    max_incidence: float = math.radians(78.0)  # no return at more grazing angles
    hole_fraction: float = 0.03
    hole_blobs: int = 12  # resolution of the hole field across the image width (blob size)

    @property
    def intrinsics(self) -> tuple[float, float, float, float]:
        """Pinhole intrinsics ``(fx, fy, cx, cy)`` in pixels (pixel centres at integers)."""
        focal = self.focal_at_640 * self.width / 640.0
        return focal, focal, (self.width - 1) / 2.0, (self.height - 1) / 2.0

    def depth_sigma(self, z: np.ndarray) -> np.ndarray:
        """Standard deviation (m) of Kinect v1 axial depth noise at distance z (m).

        Nguyen, Izadi, Lovell, "Modeling Kinect Sensor Noise for Improved 3D Reconstruction
        and Tracking", 3DIMPVT 2012: sigma_z = 0.0012 + 0.0019 (z - 0.4)^2 for 10-60 degrees.
        """
        return self.noise_a + self.noise_b * (np.asarray(z) - self.noise_z0) ** 2


# Named camera motions and sensor effects (`bgs synth --motion`, `--blur`, ...), as the
# SynthConfig fields they set.
MOTIONS: dict[str, dict[str, Any]] = {
    "handheld": {},  # TUM handheld speeds: 0.3 m/s, sweeping the room at about 0.4 rad/s
    "walk": {"speed": 0.5, "turn_rate": 0.15, "swing_weights": (1.0, 0.1, 0.03)},
    "shake": {"speed": 0.08, "turn_rate": 0.1, "shake_rate": 2.0},  # like TUM fr1/rpy
}
EFFECTS: dict[str, dict[str, Any]] = {
    "blur": {"exposure": 0.5},  # half the frame interval, as indoor auto-exposure gives
    "rolling_shutter": {"readout": 0.9},  # Kinect-class sensors read out over most of a frame
    "global_shutter_depth": {"depth_readout": 0.0},  # a RealSense D435's depth
    # a colour camera 6 mm beside the depth camera, turned by about 1.6°, its focal length 3 %
    # longer: a pair of cameras published with one set of intrinsics
    "misregister": {"colour_offset": (0.4, 1.5, 0.3, 0.006, -0.002, 0.001),
                    "colour_focal_ratio": 1.03},
    "holes": {"hole_fraction": 0.15, "hole_blobs": 6},  # large dropouts, as on dark or shiny
}


def motion_config(motion: str = "handheld", effects: tuple[str, ...] = (), **fields: Any
                  ) -> SynthConfig:  # fmt: skip
    """A SynthConfig with a named motion and sensor effects (`MOTIONS`, `EFFECTS`) applied."""
    if motion not in MOTIONS:
        raise InputError(f"unknown motion {motion!r}; choose one of {', '.join(MOTIONS)}")
    settings = dict(MOTIONS[motion])
    for effect in effects:
        settings.update(EFFECTS[effect])
    return SynthConfig(**{**settings, **fields})


def validate(config: SynthConfig) -> None:
    """Raise InputError naming the first setting that cannot produce a sensible sequence."""

    def require(ok: bool, message: str) -> None:
        if not ok:
            raise InputError(f"invalid synthetic sequence setting: {message}")

    require(config.frames >= 2, f"--frames must be at least 2, got {config.frames}")
    low, high = _SIZE_LIMITS
    require(
        low <= config.width <= high and low <= config.height <= high,
        f"--size must be between {low}x{low} and {high}x{high}, got {config.width}x{config.height}",
    )
    require(0 <= config.seed < 2**63, f"--seed must be a non-negative integer, got {config.seed}")
    require(math.isfinite(config.fps) and config.fps > 0, f"fps must be > 0, got {config.fps}")
    half_frame = 0.5 / config.fps
    require(
        0 <= config.depth_delay < half_frame,
        f"depth_delay must be in [0, {half_frame:g}) s (half a frame), got {config.depth_delay}",
    )
    require(min(config.room_size) > 0, f"room_size must be positive, got {config.room_size}")
    require(
        0 < config.depth_range[0] < config.depth_range[1] <= 65535 / config.depth_scale,
        f"depth_range must fit 16-bit PNG at {config.depth_scale:g} units/m, "
        f"got {config.depth_range}",
    )
    require(
        0 <= config.hole_fraction < 0.5,
        f"hole_fraction must be in [0, 0.5), got {config.hole_fraction}",
    )
    require(config.speed >= 0 and config.turn_rate >= 0, "speed and turn_rate must be >= 0")
    require(config.shake_rate >= 0, f"shake_rate must be >= 0, got {config.shake_rate}")
    require(
        0 <= config.exposure <= 1 and 0 <= config.readout <= 1,
        f"exposure and readout must be in [0, 1] frame intervals, got {config.exposure} and "
        f"{config.readout}",
    )
    require(
        0.5 <= config.colour_focal_ratio <= 2 and all(map(math.isfinite, config.colour_offset)),
        f"colour_focal_ratio must be in [0.5, 2] and colour_offset finite, got "
        f"{config.colour_focal_ratio} and {config.colour_offset}",
    )
    require(
        config.depth_readout is None or 0 <= config.depth_readout <= 1,
        f"depth_readout must be in [0, 1] frame intervals, got {config.depth_readout}",
    )
    require(config.exposure_samples >= 2, "exposure_samples must be at least 2")


# ---------------------------------------------------------------------------------------------
# Scene


def _furniture_boxes(config: SynthConfig, rng: np.random.Generator) -> list[np.ndarray]:
    """Seeded furniture along the four walls (plus clutter on tops) as (2, 3) [lo, hi] boxes."""
    half = np.asarray(config.room_size[:2]) / 2.0
    boxes = []
    for along, side in ((0, -1.0), (0, 1.0), (1, -1.0), (1, 1.0)):
        across = 1 - along
        count = rng.integers(config.items_per_wall[0], config.items_per_wall[1] + 1)
        start = -half[along] + config.corner_margin
        slot = 2.0 * (half[along] - config.corner_margin) / count
        for i in range(count):
            kind = config.furniture[rng.integers(len(config.furniture))]
            width = min(rng.uniform(*kind.width), slot)
            depth, height = rng.uniform(*kind.depth), rng.uniform(*kind.height)
            centre = start + i * slot + rng.uniform(width / 2, slot - width / 2)
            lo, hi = np.zeros(3), np.full(3, height)
            lo[along], hi[along] = centre - width / 2, centre + width / 2
            lo[across], hi[across] = sorted((side * half[across], side * (half[across] - depth)))
            boxes += _table(lo, hi, config) if kind.legs else [np.stack([lo, hi])]
            boxes += _clutter(lo, hi, config, rng)
    return boxes


def _table(lo: np.ndarray, hi: np.ndarray, config: SynthConfig) -> list[np.ndarray]:
    """A table filling the box [lo, hi]: a top slab and four legs at the corners."""
    top = np.stack([np.r_[lo[:2], hi[2] - config.table_top], hi])
    legs = []
    for x in (lo[0], hi[0] - config.table_leg):
        for y in (lo[1], hi[1] - config.table_leg):
            leg_lo = np.array([x, y, 0.0])
            leg_hi = leg_lo + [config.table_leg, config.table_leg, hi[2] - config.table_top]
            legs.append(np.stack([leg_lo, leg_hi]))
    return [top, *legs]


def _clutter(
    lo: np.ndarray, hi: np.ndarray, config: SynthConfig, rng: np.random.Generator
) -> list[np.ndarray]:
    """Small boxes standing on the top face of the box [lo, hi]."""
    boxes = []
    for _ in range(rng.integers(config.clutter_per_top[0], config.clutter_per_top[1] + 1)):
        size = np.minimum(rng.uniform(*config.clutter_size, size=3), np.r_[hi[:2] - lo[:2], 1.0])
        base = np.r_[rng.uniform(lo[:2], hi[:2] - size[:2]), hi[2]]
        boxes.append(np.stack([base, base + size]))
    return boxes


def _face_table(count: int, config: SynthConfig, rng: np.random.Generator) -> dict:
    """Seeded texture parameters of `count` faces (six per box: normal axis x sign).

    Each face of the room (box 0) has its own palette; a furniture box has one for all faces.
    """
    hue = rng.uniform(0.0, 360.0, count)
    shift = rng.uniform(-config.light_hue_shift, config.light_hue_shift, count)
    sat = rng.uniform(*config.saturation, count)
    tones = [
        np.stack([hue, sat, rng.uniform(*config.dark_value, count)], -1),
        np.stack([(hue + shift) % 360.0, sat, rng.uniform(*config.light_value, count)], -1),
    ]
    dark, light = (cv2.cvtColor(t[None].astype(np.float32), cv2.COLOR_HSV2RGB)[0] for t in tones)
    face = np.arange(count)
    owner = np.where(face < 6, face, face - face % 6)
    return {
        "dark": dark[owner],
        "light": light[owner],
        "seed": rng.integers(0, 2**32, count, dtype=np.uint32),
        "mix": (  # weights of noise, stripes, checker
            config.noise_share * np.eye(3)[0]
            + (1.0 - config.noise_share) * rng.dirichlet(np.ones(3), count)
        ).astype(np.float32),
        "stripe_angle": rng.uniform(0.0, np.pi, count).astype(np.float32),
        "stripe_period": rng.uniform(*config.stripe_period, count).astype(np.float32),
        "tile": rng.uniform(*config.tile_size, count).astype(np.float32),
    }


# ---------------------------------------------------------------------------------------------
# Camera path


def camera_poses(config: SynthConfig) -> np.ndarray:
    """Camera-to-world poses (frames, 4, 4) of the seeded smooth path (OpenCV camera axes)."""
    return camera_path(config)(np.arange(config.frames, dtype=np.float64))


def camera_path(config: SynthConfig) -> Callable[[np.ndarray], np.ndarray]:
    """The seeded camera path as a function of time: frame positions (any shape, in frames, so
    ``2.5`` is half-way between frames 2 and 3) to camera-to-world poses (..., 4, 4).

    Position and look angles are harmonics of a phase running round a closed curve. A loop goes
    round a whole number of laps (more when one lap within path_radius is too short for the
    speed), so the last pose is the first; an open path goes half a lap, where the dominant first
    harmonic ends far from the start (long open paths therefore move more slowly). Shaking
    (`SynthConfig.shake_rate`) adds faster rotations on top.
    """
    rng = np.random.default_rng((config.seed, _PATH_STREAM))
    duration = (config.frames - 1) / config.fps

    # Harmonic k has coefficients ~ 1/k^2 (smooth); the first is an ellipse of major axis 1.
    order = np.arange(1, config.path_harmonics + 1)
    coeffs = rng.normal(size=(2, 3, order.size)) * config.path_wobble / order**2  # cos|sin, xyz, k
    direction = rng.uniform(0.0, 2.0 * np.pi)
    major = np.array([np.cos(direction), np.sin(direction), 0.0])
    minor = np.array([-major[1], major[0], 0.0]) * rng.uniform(*config.path_ellipse)
    coeffs[0, :, 0], coeffs[1, :, 0] = major, minor

    def curve(phi: np.ndarray) -> np.ndarray:
        angles = phi[..., None] * order
        return np.cos(angles) @ coeffs[0].T + np.sin(angles) @ coeffs[1].T

    def length(laps: float) -> float:
        dense = curve(np.linspace(0.0, 2.0 * np.pi * laps, _CURVE_SAMPLES))
        return float(np.linalg.norm(np.diff(dense, axis=0), axis=1).sum())

    one_lap = curve(np.linspace(0.0, 2.0 * np.pi, _CURVE_SAMPLES))
    reach = np.linalg.norm(one_lap[:, :2], axis=1).max()
    max_scale = config.path_radius / reach
    travel = config.speed * duration
    laps = max(1, math.ceil(travel / (max_scale * length(1)))) if config.loop else 0.5
    scale = min(travel / length(laps), max_scale)

    # Yaw / pitch / roll: sinusoids whose yaw amplitude gives the mean turn rate (mean |d/dt| of
    # A sin is 4 A laps / duration), capped per axis.
    amplitude = config.turn_rate * duration / (4.0 * laps)
    swing = np.minimum(amplitude * np.asarray(config.swing_weights), config.swing_limits)
    offsets = rng.uniform(0.0, 2.0 * np.pi, 3)
    heading = rng.uniform(0.0, 2.0 * np.pi)
    shake = _shake(config) if config.shake_rate > 0 else None

    def poses(frame: np.ndarray) -> np.ndarray:
        phase = 2.0 * np.pi * laps * _path_fraction(frame, config.frames)
        position = scale * curve(phase) + [0.0, 0.0, config.eye_height]
        yaw, pitch, roll = swing.reshape(3, *(1,) * phase.ndim) * np.sin(
            phase + offsets.reshape(3, *(1,) * phase.ndim)
        )
        yaw = yaw + heading
        pitch = pitch + config.pitch
        if shake is not None:
            d_yaw, d_pitch, d_roll = shake(frame / config.fps)
            yaw, pitch, roll = yaw + d_yaw, pitch + d_pitch, roll + d_roll
        return _look_poses(position, yaw, pitch, roll)

    return poses


def _path_fraction(frame: np.ndarray, frames: int) -> np.ndarray:
    """How far along the path frame position `frame` is, 0 at the first frame and 1 at the last;
    bit for bit ``np.linspace(0, 1, frames)`` at whole frames."""
    fraction = np.asarray(frame, np.float64) * (1.0 / (frames - 1))
    return np.where(frame == frames - 1, 1.0, fraction)


def _shake(config: SynthConfig) -> Callable[[np.ndarray], np.ndarray]:
    """Seeded yaw, pitch and roll offsets (3, ...) as a function of time in seconds: per axis
    two sinusoids whose peak rates add up to shake_rate times the axis weight."""
    rng = np.random.default_rng((config.seed, _SHAKE_STREAM))
    hz = rng.uniform(*config.shake_hz, size=(3, 2))
    phase = rng.uniform(0.0, 2.0 * np.pi, size=(3, 2))
    rate = config.shake_rate * np.asarray(config.shake_weights)[:, None] / 2.0
    amplitude = rate / (2.0 * np.pi * hz)  # peak rate of A sin(2 pi f t) is 2 pi f A

    def offsets(t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, np.float64)[None, None]
        shape = (3, 2, *(1,) * (t.ndim - 2))
        waves = amplitude.reshape(shape) * np.sin(
            2.0 * np.pi * hz.reshape(shape) * t + phase.reshape(shape)
        )
        return waves.sum(axis=1)

    return offsets


def _look_poses(
    position: np.ndarray, yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray
) -> np.ndarray:
    """Camera-to-world poses (..., 4, 4) looking along yaw (about world z, up) and pitch (down),
    rolled about the viewing axis (OpenCV camera axes)."""
    forward = np.stack(
        [np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), -np.sin(pitch)], -1
    )
    right = np.stack([np.sin(yaw), -np.cos(yaw), np.zeros_like(yaw)], -1)  # forward x world up
    down = np.cross(forward, right)
    cos_r, sin_r = np.cos(roll)[..., None], np.sin(roll)[..., None]
    poses = np.broadcast_to(np.eye(4), (*yaw.shape, 4, 4)).copy()
    poses[..., :3, 0] = cos_r * right + sin_r * down
    poses[..., :3, 1] = cos_r * down - sin_r * right
    poses[..., :3, 2] = forward
    poses[..., :3, 3] = position
    return poses


# ---------------------------------------------------------------------------------------------
# Rendering


def _hash(ix: np.ndarray, iy: np.ndarray, seed: np.ndarray) -> np.ndarray:
    """Uniform [0, 1) values hashed from integer lattice points (lowbias32 integer mixer)."""
    h = (ix * np.uint32(0x8DA6B343)) ^ (iy * np.uint32(0xD8163841)) ^ seed
    h ^= h >> np.uint32(16)
    h *= np.uint32(0x7FEB352D)
    h ^= h >> np.uint32(15)
    h *= np.uint32(0x846CA68B)
    h ^= h >> np.uint32(16)
    return h.astype(np.float32) * np.float32(2.0**-32)


def _value_noise(u: np.ndarray, v: np.ndarray, seed: np.ndarray) -> np.ndarray:
    """Smoothly interpolated lattice noise in [0, 1) with unit feature size."""
    fu, fv = np.floor(u), np.floor(v)
    iu, iv = fu.astype(np.int64).astype(np.uint32), fv.astype(np.int64).astype(np.uint32)
    su, sv = u - fu, v - fv
    su, sv = su * su * (3 - 2 * su), sv * sv * (3 - 2 * sv)
    one = np.uint32(1)
    bottom = _hash(iu, iv, seed) * (1 - su) + _hash(iu + one, iv, seed) * su
    top = _hash(iu, iv + one, seed) * (1 - su) + _hash(iu + one, iv + one, seed) * su
    return bottom * (1 - sv) + top * sv


class RoomRenderer:
    """Ray-casts the seeded scene and shades / corrupts frames; one instance per sequence."""

    def __init__(self, config: SynthConfig) -> None:
        self.config = config
        rng = np.random.default_rng((config.seed, _SCENE_STREAM))
        half = np.asarray(config.room_size) * [0.5, 0.5, 1.0]
        room = np.stack([half * [-1.0, -1.0, 0.0], half])
        self.scene = o3d.t.geometry.RaycastingScene()
        boxes = [room, *_furniture_boxes(config, rng)]
        self.bounds = np.asarray(boxes, np.float64)  # (box, lo/hi, axis)
        for lo, hi in boxes:
            box = o3d.geometry.TriangleMesh.create_box(*(hi - lo)).translate(lo)
            self.scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(box))
        self.faces = _face_table(6 * len(boxes), config, rng)
        self.rays_cam = _rays(config, 1.0)  # z = 1
        self.ray_length = np.linalg.norm(self.rays_cam, axis=-1)  # rotations keep it
        self.light = np.asarray(config.light_position, np.float32)
        # the colour camera's rays and its pose in the depth camera's frame, when apart
        self.colour = None
        if config.colour_offset != (0.0,) * 6 or config.colour_focal_ratio != 1.0:
            offset = np.eye(4)
            offset[:3, :3] = Rotation.from_rotvec(np.radians(config.colour_offset[:3])).as_matrix()
            offset[:3, 3] = config.colour_offset[3:]
            self.colour = (_rays(config, config.colour_focal_ratio), offset)

    def render(
        self, exposure: list[np.ndarray], depth_pose: np.ndarray, rng: np.random.Generator
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """RGB (H, W, 3) uint8 averaged over the camera-to-world poses of `exposure` (motion
        blur), depth (H, W) uint16 seen from `depth_pose`, and the standard deviation (H, W) of
        the noise drawn for each depth reading (m, 0 where invalid). A pose is (4, 4), or
        (H, 1, 4, 4) for one pose per image row (rolling shutter)."""
        cfg = self.config
        depth_view, z, valid = self._shade(depth_pose)
        if self.colour is None:
            views = [depth_view if pose is depth_pose else self._shade(pose)[0]
                     for pose in exposure]  # fmt: skip
        else:  # seen by the colour camera, beside the depth camera
            rays, offset = self.colour
            views = [self._shade(pose @ offset, rays)[0] for pose in exposure]
        colour = sum(views[1:], views[0]) / np.float32(len(views)) if len(views) > 1 else views[0]
        noise = rng.standard_normal(colour.shape, dtype=np.float32)
        rgb = np.clip(np.rint(colour + cfg.rgb_noise * noise), 0, 255).astype(np.uint8)
        return rgb, *self._depth(z.astype(np.float64), valid, rng)

    def _shade(self, pose: np.ndarray, rays: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
        """Noise-free colour (H, W, 3) in 8-bit levels, depth (m) and depth validity from `pose`
        (through the depth camera's rays, or `rays`)."""
        cfg = self.config
        rays = self.rays_cam if rays is None else rays
        rotation = pose[..., :3, :3].astype(np.float32)
        # elementwise, not a BLAS product: the same rays on every CPU
        dirs = sum(rays[..., k, None] * rotation[..., :, k] for k in range(3))
        origin = np.broadcast_to(pose[..., :3, 3].astype(np.float32), dirs.shape)
        hit = self.scene.cast_rays(o3d.core.Tensor(np.concatenate([origin, dirs], -1)))
        hit_ok = np.isfinite(hit["t_hit"].numpy())
        normal = hit["primitive_normals"].numpy()
        axis = np.abs(normal).argmax(-1)
        box = hit["geometry_ids"].numpy().astype(np.int64)
        outward = np.take_along_axis(normal, axis[..., None], -1)[..., 0] > 0
        face = np.where(hit_ok, 6 * box + 2 * axis + outward, 0)
        z = self._distance(box, outward, axis, origin, dirs, hit_ok)
        point = origin + z[..., None] * dirs
        length = self.ray_length if rays is self.rays_cam else np.linalg.norm(rays, axis=-1)
        normal_dot_ray = np.einsum("...i,...i->...", normal, dirs) / length
        cos_incidence = np.abs(normal_dot_ray)

        cos_grazing = np.float32(np.cos(cfg.max_incidence))  # beyond it depth is invalid anyway
        footprint = z / (cfg.intrinsics[0] * np.maximum(cos_incidence, cos_grazing))
        uv = np.take_along_axis(point, _PLANE_AXES[axis], -1)
        albedo = self._albedo(face, uv[..., 0], uv[..., 1], footprint)
        to_light = self.light - point
        to_light /= np.linalg.norm(to_light, axis=-1, keepdims=True)
        facing = normal * -np.sign(normal_dot_ray)[..., None]  # the side the camera sees
        diffuse = np.clip(np.einsum("...i,...i->...", facing, to_light), 0.0, 1.0)
        shade = (cfg.ambient + (1.0 - cfg.ambient) * diffuse) * hit_ok
        colour = 255.0 * albedo * shade[..., None]
        return colour, z, hit_ok & (cos_incidence >= cos_grazing)

    def _distance(
        self, box: np.ndarray, outward: np.ndarray, axis: np.ndarray, origin: np.ndarray,
        dirs: np.ndarray, hit_ok: np.ndarray,
    ) -> np.ndarray:  # fmt: skip
        """Distance along each ray to the axis-aligned face Embree found (0 where none): the
        rays' camera z components are 1, so it is the depth. Computed here in float64 rather
        than taken from Embree, whose kernels (and their reciprocal approximations) differ per
        instruction set, so that a seed gives the same depth images on every CPU."""
        box = np.where(hit_ok, box, 0)
        plane = self.bounds[box, outward.astype(np.int64), axis]
        along = np.take_along_axis(dirs, axis[..., None], -1)[..., 0].astype(np.float64)
        start = np.take_along_axis(origin, axis[..., None], -1)[..., 0].astype(np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            distance = (plane - start) / along
        return np.where(hit_ok, distance, 0.0).astype(np.float32)

    def _albedo(
        self, face: np.ndarray, u: np.ndarray, v: np.ndarray, footprint: np.ndarray
    ) -> np.ndarray:
        """Procedural surface colour at plane coordinates (u, v) of each pixel's face."""
        cfg, faces = self.config, self.faces

        def fade(pattern: np.ndarray, wavelength: np.ndarray | float) -> np.ndarray:
            """Blend pattern detail to its mean where it is finer than the pixel footprint."""
            keep = np.clip(wavelength / (cfg.texture_min_pixels * footprint) - 1.0, 0.0, 1.0)
            return 0.5 + keep * (pattern - 0.5)

        seed = faces["seed"][face]
        noise = np.zeros_like(u)
        weights = cfg.texture_persistence ** np.arange(cfg.texture_octaves)
        for octave, weight in enumerate((weights / weights.sum()).tolist()):
            wavelength = cfg.texture_wavelength * 0.5**octave
            octave_seed = seed + np.uint32(_GOLDEN_STEP * octave % 2**32)
            cos, sin = math.cos(octave * _GOLDEN_ANGLE), math.sin(octave * _GOLDEN_ANGLE)
            layer = _value_noise(
                (cos * u - sin * v) / wavelength, (sin * u + cos * v) / wavelength, octave_seed
            )
            noise += weight * fade(layer, wavelength)

        angle, period = faces["stripe_angle"][face], faces["stripe_period"][face]
        across = (u * np.cos(angle) + v * np.sin(angle)) / period + cfg.stripe_warp * noise
        stripes = fade(0.5 + 0.5 * np.sin(2.0 * np.pi * across), period)
        tile = faces["tile"][face]
        checker = fade((np.floor(u / tile) + np.floor(v / tile)) % 2, tile)

        mix = faces["mix"][face]
        level = mix[..., 0] * noise + mix[..., 1] * stripes + mix[..., 2] * checker
        level = np.clip(0.5 + cfg.texture_contrast * (level - 0.5), 0.0, 1.0)[..., None]
        return faces["dark"][face] * (1.0 - level) + faces["light"][face] * level

    def _depth(self, z: np.ndarray, valid: np.ndarray, rng: np.random.Generator
               ) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
        """Kinect-like 16-bit depth: noisy, quantised, 0 where invalid, out of range or in holes;
        and the noise's standard deviation (m, 0 where the depth is 0).

        Holes are the top hole_fraction of a smooth random field: a few irregular blobs.
        """
        cfg = self.config
        sigma = cfg.depth_sigma(z)
        noisy = z + sigma * rng.standard_normal(z.shape)
        cells = (max(2, round(cfg.hole_blobs * cfg.height / cfg.width)), cfg.hole_blobs)
        size = (cfg.width, cfg.height)
        field = cv2.resize(rng.standard_normal(cells), size, interpolation=cv2.INTER_CUBIC)
        holes = field > np.quantile(field, 1.0 - cfg.hole_fraction)
        valid = valid & (z >= cfg.depth_range[0]) & (z <= cfg.depth_range[1]) & ~holes
        return (np.where(valid, np.rint(noisy * cfg.depth_scale), 0).astype(np.uint16),
                np.where(valid, sigma, 0.0))  # fmt: skip


# ---------------------------------------------------------------------------------------------
# Output


def synthesize(
    out_dir: Path,
    config: SynthConfig,
    *,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> Path:
    """Write a TUM-layout sequence to out_dir and return out_dir.

    Frames are rendered and written one at a time (memory does not grow with length) into a
    sibling temporary directory that replaces out_dir only when complete, so an interrupted
    (SIGINT / SIGTERM raise ``Interrupted``) or failed run leaves nothing behind.
    ``progress(done, total)`` is called after each frame.
    """
    validate(config)
    out_dir = Path(out_dir)
    _check_replaceable(out_dir, overwrite)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    with interruptible() as interruption, atomic_dir(out_dir) as tmp:
        _write_sequence(tmp, config, progress, interruption.check)
        _check_replaceable(out_dir, overwrite)  # again: it may have appeared while rendering
        interruption.check()  # the last chance before the folder is committed
    return out_dir


def _write_sequence(
    root: Path, config: SynthConfig, progress: Callable[[int, int], None] | None,
    check_interrupted: Callable[[], None] = lambda: None,
) -> None:
    """Render every frame into root and write the TUM list, ground-truth and calibration files."""
    (root / "rgb").mkdir()
    (root / "depth").mkdir()
    (root / DEPTH_SIGMA_DIR).mkdir()
    renderer = RoomRenderer(config)
    path = camera_path(config)
    poses = path(np.arange(config.frames, dtype=np.float64))
    rows, instants = sensor_timing(config)
    depth_rows = rows if config.depth_readout is None else _rows(config, config.depth_readout)
    depth_lag = config.depth_delay * config.fps  # in frames
    rgb_lines, depth_lines, gt_lines = [], [], []
    for i, pose in enumerate(poses):
        check_interrupted()
        row_times = 0.0 if rows is None else rows
        depth_row_times = 0.0 if depth_rows is None else depth_rows
        # the depth image is taken at its own time stamp, depth_delay after the colour image's
        depth_pose = (pose if depth_rows is None and not depth_lag
                      else path(i + depth_lag + depth_row_times))  # fmt: skip
        shared = depth_rows is rows and not depth_lag  # colour at t = 0 is read as depth is
        exposure = [depth_pose if t == 0 and shared else path(i + t + row_times)
                    for t in instants]  # fmt: skip
        rng = np.random.default_rng((config.seed, _SENSOR_STREAM, i))
        rgb, depth, sigma = renderer.render(exposure, depth_pose, rng)
        time = config.start_time + i / config.fps
        stamp, depth_stamp = f"{time:.6f}", f"{time + config.depth_delay:.6f}"
        write_png(root / f"rgb/{stamp}.png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        write_png(root / f"depth/{depth_stamp}.png", depth)
        write_png(root / f"{DEPTH_SIGMA_DIR}/{depth_stamp}.png", encode_depth_sigma(sigma))
        rgb_lines.append(f"{stamp} rgb/{stamp}.png\n")
        depth_lines.append(f"{depth_stamp} depth/{depth_stamp}.png\n")
        values = np.r_[pose[:3, 3], matrix_to_quat_xyzw(pose[:3, :3])]
        gt_lines.append(f"{stamp} " + " ".join(f"{x:.9f}" for x in values) + "\n")
        if progress is not None:
            progress(i + 1, config.frames)

    lists = {
        "rgb.txt": ("color images", "timestamp filename", rgb_lines),
        "depth.txt": ("depth maps", "timestamp filename", depth_lines),
        "groundtruth.txt": ("ground truth trajectory", "timestamp tx ty tz qx qy qz qw", gt_lines),
    }
    for name, (what, columns, lines) in lists.items():
        header = _TUM_HEADER.format(what=what, seed=config.seed, columns=columns)
        (root / name).write_text(header + "".join(lines))
    (root / "calibration.txt").write_text(" ".join(f"{x:.9f}" for x in config.intrinsics) + "\n")
    # seconds (0: a global shutter), which `bgs convert tum` records for `bgs run`: the colour
    # image's, and the depth image's when it reads out otherwise
    readouts = [config.readout] + ([] if config.depth_readout is None else [config.depth_readout])
    (root / READOUT_FILE).write_text(" ".join(f"{r / config.fps:.9f}" for r in readouts) + "\n")


def encode_depth_sigma(sigma: np.ndarray) -> np.ndarray:
    """σ (m) as the 16-bit image of ``depth_sigma/`` (rounded, clipped to its range)."""
    return np.clip(np.rint(sigma * DEPTH_SIGMA_SCALE), 0, np.iinfo(np.uint16).max).astype(np.uint16)


def read_depth_sigma(sequence: Path, frame: int) -> np.ndarray:
    """The simulated depth-noise σ (m, float32 [H,W], 0 where invalid) of depth image `frame`
    (0-based, in the order of ``depth.txt``) of a `synthesize`d sequence."""
    sequence = Path(sequence)
    names = [line.split()[1] for line in (sequence / "depth.txt").read_text().splitlines()
             if line and not line.startswith("#")]  # fmt: skip
    image = read(sequence / DEPTH_SIGMA_DIR / Path(names[frame]).name, cv2.IMREAD_UNCHANGED,
                 "depth sigma image")  # fmt: skip
    return image.astype(np.float32) / np.float32(DEPTH_SIGMA_SCALE)


def sensor_timing(config: SynthConfig) -> tuple[np.ndarray | None, np.ndarray]:
    """When, relative to a frame's time stamp and in frames, each image row is read (H, 1;
    None for a global shutter) and the instants the colour exposure averages over."""
    rows = _rows(config, config.readout)
    instants = np.zeros(1)
    if config.exposure > 0:
        instants = np.linspace(-0.5, 0.5, config.exposure_samples) * config.exposure
    return rows, instants


def _rays(config: SynthConfig, focal_ratio: float) -> np.ndarray:
    """Each pixel's viewing ray (H, W, 3) at z = 1, for a focal length `focal_ratio` times the
    configured one."""
    fx, fy, cx, cy = config.intrinsics
    v, u = np.mgrid[: config.height, : config.width].astype(np.float32)
    fx, fy = fx * focal_ratio, fy * focal_ratio
    return np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], -1)


def _rows(config: SynthConfig, readout: float) -> np.ndarray | None:
    """When each row is read (H, 1; frames) over a readout of `readout` frames (None: 0)."""
    return (np.linspace(-0.5, 0.5, config.height) * readout)[:, None] if readout > 0 else None


def _check_replaceable(out_dir: Path, overwrite: bool) -> None:
    """Refuse an existing out_dir unless overwriting, and never replace what is not a sequence.

    The second rule keeps a slip like ``bgs synth ~ --overwrite`` from deleting a home directory.
    """
    if not (out_dir.exists() or out_dir.is_symlink()):
        return
    if not overwrite:
        raise OutputExistsError(f"{out_dir} already exists; pass --overwrite to replace it")
    if out_dir.is_dir() and any(out_dir.iterdir()) and not (out_dir / "rgb.txt").exists():
        raise OutputExistsError(
            f"{out_dir} is not a TUM sequence (no rgb.txt), so --overwrite will not delete it; "
            "choose another output directory or remove it yourself"
        )

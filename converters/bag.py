"""ROS1 ``.bag``, ROS2 ``.db3`` and ``.mcap`` recordings → frame store, streamed.

Two passes over the bag keep memory bounded for any size: the first (`bag_index`) reads header
stamps, camera infos and transforms; then topics are chosen, RGB and depth associated by header
stamp (greedy one-to-one, TUM ``associate.py`` semantics) and depth registration planned; the
second pass streams the chosen messages, holding only pairs still waiting for their partner, and
hands raw bytes to the pipeline's workers, which deserialise, decode and register them. The bag
is opened once for both passes (opening a file-compressed ``.db3`` decompresses it).
"""

from __future__ import annotations

import weakref
from collections.abc import Callable, Iterable, Iterator
from contextlib import closing
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from bgs_batch.errors import InputError
from bgs_batch.geometry import interpolate_poses
from bgs_batch.store import StoreMeta
from converters.association import associate, association_summary
from converters.bag_index import (
    BAG_ERRORS,
    NS_PER_S,
    BagIndex,
    CameraInfo,
    ImageTopic,
    bag_error,
    index_bag,
    open_reader,
)
from converters.bag_readers import BagReader
from converters.pipeline import SourceFrame
from converters.readout import readout_source, stored_readout
from converters.registration import DepthRegistration
from converters.ros_images import (
    COLOR,
    DEPTH,
    DEPTH_UNITS_PER_METRE,
    MONO,
    ImageDecodeError,
    decode_color,
    decode_depth,
)

STORED_DISTORTION_TERMS = 5  # the store keeps OpenCV's k1 k2 p1 p2 k3
FLOAT32_DIGITS = 7  # significant digits of a float32, e.g. RealSense's "Depth Units" option
INTRINSICS_TOLERANCE = 1e-6  # relative: equal CameraInfo K means depth is already registered


@dataclass(frozen=True)
class BagOptions:
    """Choices of a bag conversion; every one is recorded in the store's provenance."""

    rgb_topic: str | None = None  # None: auto-detect
    depth_topic: str | None = None
    info_topic: str | None = None  # colour CameraInfo
    depth_info_topic: str | None = None
    pose_topic: str | None = None  # optional ground truth
    pose_frame: str | None = None  # child frame, when the pose topic is TF
    tolerance: float = 0.02  # s, max |t_rgb - t_depth| for an association
    gt_max_gap: float = 0.1  # s, max spacing of the two GT samples bracketing a frame
    depth_scale: float | None = None  # units per metre of 16-bit depth; None: detect
    # s over which the colour (and the depth) image's rows are read out; a bag names no
    # readout, so the default leaves it to `bgs run` to estimate (READOUT_UNKNOWN)
    readout: float | None = None
    depth_readout: float | None = None  # the depth image's, when it differs (None: the same)
    stride: int = 1
    max_frames: int | None = None


@dataclass(frozen=True)
class BagPlan:
    """What to convert: a lazy stream of frames (a second pass over the bag) and the metadata."""

    frames: Iterable[SourceFrame]
    count: int
    meta: StoreMeta
    notes: tuple[str, ...] = ()  # for the user: what the association dropped


def plan_bag(path: Path, options: BagOptions) -> BagPlan:
    """Index the bag, choose topics, associate, plan registration and GT; decode nothing yet.

    The bag stays open for the second pass, which closes it when it ends (or, if it never runs,
    when the plan is dropped).
    """
    path = Path(path)
    if options.stride < 1 or (options.max_frames is not None and options.max_frames < 1):
        raise InputError("--stride and --max-frames must be at least 1")
    reader = open_reader(path)
    try:
        return _plan(path, options, reader)
    except BaseException:
        reader.close()
        raise


def _plan(path: Path, options: BagOptions, reader: BagReader) -> BagPlan:
    index = index_bag(reader, path, options.pose_topic, options.pose_frame)
    rgb, depth, rgb_info, depth_info = _choose_topics(index, path, options)
    pairs, provenance, association_note = _associate(index, rgb, depth, options)
    stamps = np.asarray(rgb.stamps, np.int64)[pairs[:, 0]] / NS_PER_S
    camera = index.camera_infos[rgb_info]
    depth_scale, scale_source = _depth_scale(index, depth, options)
    registration, registration_provenance = _plan_registration(
        index, rgb, depth, camera, depth_info, depth_scale
    )
    poses, gt_provenance = _ground_truth(index, options, stamps)
    provenance.update(
        storage=index.storage,
        rgb_topic=rgb.describe(),
        depth_topic=depth.describe(),
        topic_choice=", ".join(
            f"{name} {'given' if given else 'auto-detected'}"
            for name, given in (("rgb", options.rgb_topic), ("depth", options.depth_topic))
        ),
        info_topic=rgb_info,
        depth_info_topic=depth_info,
        intrinsics_source=f"CameraInfo on {rgb_info}",
        distortion_model=camera.model,
        distortion_dropped=list(camera.distortion[STORED_DISTORTION_TERMS:]),
        depth_scale_source=scale_source,
        stride=options.stride,
        max_frames=options.max_frames,
        rolling_shutter_readout_source=readout_source(options.readout, "a bag names no "
                                                                        "readout"),
        **registration_provenance,
        **gt_provenance,
    )
    meta = StoreMeta(
        source_format="bag",
        source_path=str(path.resolve()),
        sequence=path.resolve().stem,
        intrinsics=camera.matrix,
        depth_scale=depth_scale,
        distortion=(camera.distortion + (0.0,) * STORED_DISTORTION_TERMS)[:STORED_DISTORTION_TERMS],
        has_gt=poses is not None,
        rolling_shutter_readout=stored_readout(options.readout),
        depth_rolling_shutter_readout=options.depth_readout,
        # registered here, with the recorded extrinsic, or by the driver (the depth image has
        # its own CameraInfo, equal to the colour's); otherwise nobody says: `bgs run` checks
        depth_registered=registration is not None or depth_info not in (None, rgb_info),
        provenance=provenance,
    )
    # the reader's deserialiser keeps its registered types after the reader is closed
    decoder = PairDecoder(path, rgb, depth, registration, reader.deserialize)
    frames = _stream_frames(reader, path, rgb, depth, pairs, stamps, poses, decoder)
    weakref.finalize(frames, reader.close)  # a second pass that never starts
    return BagPlan(frames, len(pairs), meta, (association_note,))


def _choose_topics(
    index: BagIndex, path: Path, options: BagOptions
) -> tuple[ImageTopic, ImageTopic, str, str | None]:
    """The colour and depth image topics and their CameraInfo topics (the colour one must exist:
    it gives the intrinsics)."""
    rgb = choose_image_topic(index, COLOR, options.rgb_topic)
    depth = choose_image_topic(index, DEPTH, options.depth_topic)
    rgb_info = choose_camera_info(index, rgb.topic, depth.topic, options.info_topic, "--info-topic")
    if rgb_info is None:
        raise InputError(
            f"{path}: no CameraInfo topic belongs to {rgb.topic}, so the "
            "intrinsics are unknown; pass --info-topic"
        )
    depth_info = choose_camera_info(
        index, depth.topic, rgb.topic, options.depth_info_topic, "--depth-info-topic"
    )
    return rgb, depth, rgb_info, depth_info


def choose_image_topic(index: BagIndex, role: str, requested: str | None) -> ImageTopic:
    """The colour or depth topic: as requested, else the only candidate (explained if not)."""
    option = "--rgb-topic" if role == COLOR else "--depth-topic"
    listing = "; ".join(t.describe() for t in index.images.values())
    if requested is not None:
        image = index.images.get(requested)
        if image is None or image.role is None or (image.role == DEPTH) != (role == DEPTH):
            raise InputError(
                f"{index.path}: {option} {requested} {_what_topic_holds(index, requested)}; "
                f"image topics: {listing or 'none'}"
            )
        return image
    if not index.images:
        raise InputError(
            f"{index.path} has no image topics (sensor_msgs/Image or CompressedImage), so it "
            f"holds no RGB-D data; its topics: {', '.join(sorted(index.topic_types)) or 'none'}"
        )
    roles = (COLOR, MONO) if role == COLOR else (DEPTH,)  # mono (e.g. infrared) only as fallback
    for wanted in roles:
        candidates = [t for t in index.images.values() if t.role == wanted]
        if len(candidates) == 1:
            return candidates[0]
        if candidates:
            names = "; ".join(t.describe() for t in candidates)
            raise InputError(
                f"{index.path}: {len(candidates)} {role} image topics "
                f"could be meant: {names}; choose one with {option}"
            )
    raise InputError(
        f"{index.path}: no {role} image topic found among: {listing}; name it with {option}"
    )


def _what_topic_holds(index: BagIndex, topic: str) -> str:
    if topic in index.images:
        return f"holds {index.images[topic].encoding!r} images"
    kind = index.topic_types.get(topic)
    return f"is a {kind} topic" if kind else "is not in the bag"


def choose_camera_info(
    index: BagIndex, image_topic: str, other_topic: str, requested: str | None, option: str
) -> str | None:
    """The CameraInfo topic of an image topic: as requested, else the one sharing the longest
    namespace with it (``/cam/color/image_raw`` ↔ ``/cam/color/camera_info``) among those that
    do not fit the other image topic (RGB vs depth) better."""
    if requested is not None:
        if requested not in index.camera_infos:
            infos = ", ".join(index.camera_infos) or "none"
            raise InputError(
                f"{index.path}: {requested} is not a CameraInfo topic with "
                f"messages; CameraInfo topics: {infos}"
            )
        return requested
    scores = {}
    for info in index.camera_infos:
        mine, other = _shared_prefix(info, image_topic), _shared_prefix(info, other_topic)
        if mine > 0 and mine >= other:
            scores[info] = mine
    best = max(scores.values(), default=0)
    winners = [t for t, score in scores.items() if score == best]
    if len(winners) > 1:
        raise InputError(
            f"{index.path}: CameraInfo topics {', '.join(winners)} fit "
            f"{image_topic} equally well; choose one with {option}"
        )
    return winners[0] if winners else None


def _shared_prefix(info_topic: str, image_topic: str) -> int:
    """Leading namespace segments a CameraInfo topic shares with an image topic."""
    a = info_topic.strip("/").split("/")[:-1]
    b = image_topic.strip("/").split("/")
    count = 0
    for x, y in zip(a, b, strict=False):
        if x != y:
            break
        count += 1
    return count


def _associate(
    index: BagIndex, rgb: ImageTopic, depth: ImageTopic, options: BagOptions
) -> tuple[np.ndarray, dict[str, Any], str]:
    """Pairs of message ordinals (rgb, depth) in RGB-time order, their provenance and the line
    that tells the user what was dropped."""
    if rgb.topic == depth.topic:
        raise InputError(f"{index.path}: RGB and depth topic are both {rgb.topic}")
    rgb_ns, depth_ns = np.asarray(rgb.stamps, np.int64), np.asarray(depth.stamps, np.int64)
    _, rgb_first = np.unique(rgb_ns, return_index=True)  # sorted; repeated stamps kept once
    depth_order = np.argsort(depth_ns, kind="stable")
    rgb_s, depth_s = rgb_ns[rgb_first] / NS_PER_S, depth_ns[depth_order] / NS_PER_S
    matched = associate(rgb_s, depth_s, options.tolerance)
    if len(matched) == 0:
        gap = np.abs(rgb_ns[:, None] - depth_ns[None, :]).min() / NS_PER_S
        raise InputError(
            f"{index.path}: no {rgb.topic} frame has a {depth.topic} frame within "
            f"{options.tolerance} s (closest pair: {gap:.4f} s apart); raise --tolerance if "
            "the streams are just loosely synchronised"
        )
    pairs = np.stack([rgb_first[matched[:, 0]], depth_order[matched[:, 1]]], axis=1)
    diffs = np.abs(rgb_ns[pairs[:, 0]] - depth_ns[pairs[:, 1]]) / NS_PER_S
    provenance = {
        "association": "order-preserving one-to-one by header stamp, most pairs then least "
        "summed |dt|",
        "association_tolerance_s": options.tolerance,
        "association_max_diff_s": float(diffs.max()),
        "rgb_messages": len(rgb_ns),
        "depth_messages": len(depth_ns),
        "rgb_repeated_stamps_dropped": len(rgb_ns) - len(rgb_first),
        "associated": len(pairs),
    }
    note = association_summary(rgb_s, depth_s, options.tolerance, len(matched),
                               "RGB messages", "depth message")  # fmt: skip
    return pairs[:: options.stride][: options.max_frames], provenance, note


def _depth_scale(index: BagIndex, depth: ImageTopic, options: BagOptions) -> tuple[float, str]:
    """Units per metre of the stored depth, and where that number came from."""
    if DEPTH_UNITS_PER_METRE.get(depth.pixel_encoding) == 1.0:
        return 1.0, f"{depth.pixel_encoding}: float metres (REP 118)"
    if options.depth_scale is not None:
        return options.depth_scale, "--depth-scale"
    if index.depth_unit_m:
        scale = float(f"{1.0 / index.depth_unit_m:.{FLOAT32_DIGITS}g}")
        return scale, f"RealSense 'Depth Units' option ({1.0 / scale:g} m)"
    return DEPTH_UNITS_PER_METRE["16UC1"], "REP 118: 16-bit depth in millimetres"


def _plan_registration(
    index: BagIndex,
    rgb: ImageTopic,
    depth: ImageTopic,
    rgb_info: CameraInfo,
    depth_info_topic: str | None,
    units_per_metre: float,
) -> tuple[DepthRegistration | None, dict]:
    """Registration of depth into the colour camera, when the two cameras differ."""
    depth_info = index.camera_infos.get(depth_info_topic) if depth_info_topic else None
    same = depth_info is None or (
        depth_info.size == rgb_info.size
        and np.allclose(depth_info.matrix, rgb_info.matrix, rtol=INTRINSICS_TOLERANCE)
    )
    if same:
        reason = "no depth CameraInfo" if depth_info is None else "identical CameraInfo"
        rgb_size, depth_size = rgb.size or rgb_info.size, depth.size or rgb_info.size
        if rgb_size != depth_size:
            raise InputError(
                f"{index.path}: {rgb.topic} is {rgb_size[0]}x{rgb_size[1]} but {depth.topic} is "
                f"{depth_size[0]}x{depth_size[1]} and {reason} says how to register them; "
                "record the depth CameraInfo (and /tf_static), or use registered depth topics"
            )
        return None, {"registration": f"none: depth already in the colour camera ({reason})"}
    extrinsic, source = _extrinsic(index, rgb, depth, rgb_info, depth_info)
    registration = DepthRegistration(
        depth_info.matrix,
        depth_info.size,
        rgb_info.matrix,
        rgb_info.size,
        extrinsic,
        units_per_metre,
    )
    return registration, {
        "registration": "depth re-projected into the colour camera (forward splat, z-buffer)",
        "registration_extrinsic_source": source,
        "registration_color_from_depth": np.round(extrinsic, 9).tolist(),
        "depth_intrinsics": np.round(depth_info.matrix, 6).tolist(),
    }


def _extrinsic(
    index: BagIndex,
    rgb: ImageTopic,
    depth: ImageTopic,
    rgb_info: CameraInfo,
    depth_info: CameraInfo,
) -> tuple[np.ndarray, str]:
    """``T_colour_depth`` from the RealSense tf/0 topics or the TF tree, named by its source."""
    color_frame = index.stream_frame(rgb.topic) or rgb_info.frame_id
    depth_frame = index.stream_frame(depth.topic) or depth_info.frame_id
    if color_frame and depth_frame:
        found = index.transforms.lookup(color_frame, depth_frame)
        if found is not None:
            return found, f"transform {depth_frame} -> {color_frame} (TF / RealSense tf/0)"
    raise InputError(
        f"{index.path}: depth ({depth.topic}) has other intrinsics than colour ({rgb.topic}) "
        f"but no transform links their frames ({depth_frame or '?'} -> {color_frame or '?'}); "
        "record /tf_static with the camera's extrinsics, or use registered depth topics"
    )


def _ground_truth(
    index: BagIndex, options: BagOptions, stamps: np.ndarray
) -> tuple[np.ndarray | None, dict]:
    """Poses of the pose topic interpolated to the frame stamps (NaN where not bracketed)."""
    if options.pose_topic is None:
        return None, {}
    if options.pose_topic not in index.topic_types:
        raise InputError(f"{index.path}: pose topic {options.pose_topic} is not in the bag")
    if not index.pose_samples:
        raise InputError(
            f"{index.path}: pose topic {options.pose_topic} has no usable poses"
            + (f" of frame {options.pose_frame}" if options.pose_frame else "")
        )
    samples = sorted(index.pose_samples, key=lambda s: s[0])
    times = np.array([s[0] for s in samples]) / NS_PER_S
    keep = np.concatenate([[True], np.diff(times) > 0])
    translations = np.stack([s[1] for s in samples])[keep]
    quats = np.stack([s[2] for s in samples])[keep]
    poses = interpolate_poses(times[keep], translations, quats, stamps, options.gt_max_gap)
    return poses, {
        "gt_source": options.pose_topic
        + (f" ({options.pose_frame})" if options.pose_frame else ""),
        "gt_interpolation": f"linear position, slerp rotation, bracket <= {options.gt_max_gap} s",
        "gt_frames": int(np.all(np.isfinite(poses), axis=(1, 2)).sum()),
    }


@dataclass(frozen=True)
class PairDecoder:
    """Deserialise, decode and (if needed) register one RGB-D pair; runs in worker threads."""

    bag: Path
    rgb: ImageTopic
    depth: ImageTopic
    registration: DepthRegistration | None
    deserialize: Callable[[bytes | memoryview, str], Any]

    def __call__(self, rgb_raw: bytes, depth_raw: bytes, name: str) -> tuple[np.ndarray, ...]:
        try:
            rgb = decode_color(self.rgb.msgtype, self.deserialize(rgb_raw, self.rgb.msgtype))
            depth = decode_depth(
                self.depth.msgtype, self.deserialize(depth_raw, self.depth.msgtype)
            )
            if self.registration is not None:
                depth = self.registration(depth)
        except (ImageDecodeError, ValueError, *BAG_ERRORS) as err:
            raise InputError(
                f"{self.bag}: {name}: {err}; pass --skip-bad-frames to drop such frames"
            ) from err
        if rgb.shape[:2] != depth.shape:
            raise InputError(
                f"{self.bag}: {name}: colour is {rgb.shape[1]}x{rgb.shape[0]} but depth is "
                f"{depth.shape[1]}x{depth.shape[0]}; record the depth CameraInfo and "
                "/tf_static so depth can be registered, or use registered depth topics"
            )
        return rgb, depth


def _stream_frames(
    reader: BagReader,
    path: Path,
    rgb: ImageTopic,
    depth: ImageTopic,
    pairs: np.ndarray,
    stamps: np.ndarray,
    poses: np.ndarray | None,
    decoder: PairDecoder,
) -> Iterator[SourceFrame]:
    """Second pass: yield the associated pairs in order, as soon as both halves were read;
    closes the reader."""
    rgb_wanted = {int(i): k for k, i in enumerate(pairs[:, 0])}
    depth_wanted = {int(j): k for k, j in enumerate(pairs[:, 1])}

    def frame(k: int, rgb_raw: bytes, depth_raw: bytes) -> SourceFrame:
        i, j = pairs[k]
        name = (
            f"{rgb.topic} @ {rgb.stamps[i] / NS_PER_S:.6f} s + "
            f"{depth.topic} @ {depth.stamps[j] / NS_PER_S:.6f} s"
        )
        pose = None if poses is None or not np.all(np.isfinite(poses[k])) else poses[k]
        return SourceFrame(name, float(stamps[k]), pose, partial(decoder, rgb_raw, depth_raw, name),
                           float(depth.stamps[j] / NS_PER_S))  # fmt: skip

    with closing(reader):
        connections = [c for c in reader.connections if c.topic in (rgb.topic, depth.topic)]
        seen = {rgb.topic: 0, depth.topic: 0}
        halves: dict[int, dict[str, bytes]] = {}
        next_k = 0
        try:
            for conn, _, raw in reader.messages(connections=connections):
                ordinal = seen[conn.topic]
                seen[conn.topic] += 1
                k = (rgb_wanted if conn.topic == rgb.topic else depth_wanted).get(ordinal)
                if k is None:
                    continue
                # a copy: a view (ROS1) would keep its whole decompressed chunk alive
                halves.setdefault(k, {})[conn.topic] = bytes(raw)
                while len(halves.get(next_k, ())) == 2:
                    pair = halves.pop(next_k)
                    yield frame(next_k, pair[rgb.topic], pair[depth.topic])
                    next_k += 1
                if next_k == len(pairs):
                    return
        except BAG_ERRORS as err:
            raise bag_error(path, err) from err
    raise InputError(
        f"{path}: the bag ended before frame {next_k} of {len(pairs)}; it changed "
        "while being converted"
    )

"""Open ROS1/ROS2 bags, and index one in a first pass without decoding any pixels.

The index holds what the converter must decide before streaming frames: each image topic's kind,
encoding and header stamps, the cameras' ``CameraInfo``, the static transforms (``/tf_static``,
``/tf`` and the RealSense SDK's per-stream ``…/tf/0``) and, when asked for, a pose topic.
Image stamps are read straight from the serialised header, so indexing costs one read of the
bag and no image deserialisation (and, for sqlite3 bags, no read of the pixels at all).
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.serde import SerdeError

from bgs_batch.errors import InputError
from converters.bag_readers import (
    MCAP_SUFFIX,
    ROS2_METADATA,
    STAMP_OFFSET,
    BagReader,
    BagReadError,
    Ros1Bag,
    Ros2Bag,
)
from converters.ros_images import (
    DEPTH,
    IMAGE,
    IMAGE_TYPES,
    depth_encoding,
    image_role,
    original_encoding,
)
from converters.ros_tf import TransformTree, frame_name, quaternion, transform_matrix, vector3

log = logging.getLogger(__name__)

ROS1_SUFFIX = ".bag"
DB3_SUFFIX = ".db3"
ROS2_SUFFIXES = (DB3_SUFFIX, MCAP_SUFFIX)
# what reading a damaged bag raises: storage, deserialisation, header stamps, and what the
# libraries' parsers raise on bytes that are no bag at all (a header that is not text, a length
# that does not fit)
BAG_ERRORS = (BagReadError, SerdeError, struct.error, ValueError, OverflowError, IndexError)

CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
TF_TOPICS = ("/tf_static", "/tf")
TRANSFORM = "geometry_msgs/msg/Transform"
REALSENSE_TF_SUFFIX = "/tf/0"  # RealSense SDK recordings: a stream's extrinsic
REALSENSE_IMAGE_SUFFIX = "/image/data"
REALSENSE_DEPTH_UNITS = "/option/Depth Units/value"  # std_msgs/Float32, metres per unit

CDR_LITTLE_ENDIAN = 1  # byte 1 of the CDR encapsulation header (see bag_readers.STAMP_OFFSET)
NS_PER_S = 1_000_000_000

# (position, orientation) of every supported pose message type
POSE_TYPES = {
    "geometry_msgs/msg/PoseStamped": lambda m: (m.pose.position, m.pose.orientation),
    "geometry_msgs/msg/PoseWithCovarianceStamped": lambda m: (
        m.pose.pose.position,
        m.pose.pose.orientation,
    ),
    "nav_msgs/msg/Odometry": lambda m: (m.pose.pose.position, m.pose.pose.orientation),
    "geometry_msgs/msg/TransformStamped": lambda m: (m.transform.translation, m.transform.rotation),
}


def bag_error(path: Path, err: Exception) -> InputError:
    """The message for a bag rosbags cannot read: usually a recorder that crashed."""
    return InputError(
        f"{path}: cannot read the bag ({err}); it is damaged or truncated (e.g. the recorder "
        "crashed): re-index it (`rosbag reindex` for ROS1, `ros2 bag reindex` for ROS2) or "
        "record it again"
    )


@contextmanager
def open_bag(path: Path) -> Iterator[BagReader]:
    """`open_reader` as a context manager: the reader is closed on leaving."""
    reader = open_reader(path)
    try:
        yield reader
    finally:
        reader.close()


def open_reader(path: Path) -> BagReader:
    """An open reader of a ROS1 ``.bag``, a ROS2 ``.db3``/``.mcap`` or a ROS2 bag folder.

    A bare ROS2 file next to its ``metadata.yaml`` is opened through its folder, which is the
    only way to read message-compressed bags. A truncated MCAP is salvaged instead.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path} does not exist; pass a .bag, .db3, .mcap or ROS2 bag folder")
    if path.suffix in ROS2_SUFFIXES and (path.parent / ROS2_METADATA).is_file():
        path = path.parent
    elif not (path.suffix in (ROS1_SUFFIX, *ROS2_SUFFIXES) or (path / ROS2_METADATA).is_file()):
        raise InputError(
            f"{path} is not a ROS bag: pass a ROS1 .bag, a ROS2 .db3 or .mcap "
            f"file, or a ROS2 bag folder holding {ROS2_METADATA}"
        )
    try:
        if path.suffix == ROS1_SUFFIX:
            return Ros1Bag(path)
        reader = _sqlite_bag(path)
        return Ros2Bag(path) if reader is None else reader
    except BAG_ERRORS as err:
        return _salvage(path, err)


def _sqlite_bag(path: Path) -> BagReader | None:
    """A reader of a bare ``.db3`` or of a sqlite3 bag folder; None for other ROS2 bags."""
    bare = path.suffix == DB3_SUFFIX and path.is_file()
    if not bare and (not path.is_dir() or any(path.glob(f"*{MCAP_SUFFIX}*"))):
        return None  # MCAP: AnyReader reads its metadata.yaml itself
    from converters.bag_sqlite import SQLITE_STORAGE, Ros2Sqlite, read_metadata  # as Ros2Bag

    if bare:
        return Ros2Sqlite(path)
    metadata = read_metadata(path)
    if metadata.get("storage_identifier") != SQLITE_STORAGE:
        return None
    return Ros2Sqlite(path, metadata)


def _salvage(path: Path, err: Exception) -> BagReader:
    """The intact part of a truncated MCAP; any other unreadable bag is an error."""
    files = [path] if path.suffix == MCAP_SUFFIX else sorted(path.glob(f"*{MCAP_SUFFIX}"))
    if len(files) == 1:
        from converters.mcap_salvage import SalvagedMcap  # rarely needed: imported on demand

        salvaged = SalvagedMcap(files[0])
        if salvaged.connections:
            log.warning("%s: %s; converting the messages of its intact chunks", files[0], err)
            return salvaged
    raise bag_error(path, err) from err


def header_stamp_ns(raw: bytes | memoryview, ros2: bool) -> int:
    """``header.stamp`` in ns of a serialised stamped message, read without deserialising it."""
    little = not ros2 or raw[1] == CDR_LITTLE_ENDIAN
    sec, nsec = struct.unpack_from("<iI" if little else ">iI", raw, STAMP_OFFSET)
    return sec * NS_PER_S + nsec


@dataclass
class ImageTopic:
    """An image topic: its kind (colour, depth, mono), first-message facts and header stamps."""

    topic: str
    msgtype: str
    role: str | None
    encoding: str  # Image.encoding, or CompressedImage.format
    pixel_encoding: str  # the raw pixels' encoding: rgb8, 16UC1, ... ("" for plain JPEG/PNG)
    frame_id: str
    size: tuple[int, int] | None  # (width, height); None for compressed images
    stamps: list[int] = field(default_factory=list)  # header stamps, ns, in bag order

    def describe(self) -> str:
        kind = "Image" if self.msgtype == IMAGE else "CompressedImage"
        return f"{self.topic} ({kind} {self.encoding!r}, {len(self.stamps)} messages)"


@dataclass(frozen=True)
class CameraInfo:
    """The parts of a ``sensor_msgs/CameraInfo`` the store needs."""

    matrix: np.ndarray  # 3x3
    distortion: tuple[float, ...]
    model: str
    size: tuple[int, int]  # (width, height)
    frame_id: str

    @classmethod
    def from_message(cls, msg: Any) -> CameraInfo:
        """Accepts ROS1 (``K``, ``D``) and ROS2 (``k``, ``d``) field names."""
        k = getattr(msg, "k", None)
        d = getattr(msg, "d", None)
        k = msg.K if k is None else k
        d = msg.D if d is None else d
        return cls(
            np.asarray(k, np.float64).reshape(3, 3),
            tuple(map(float, d)),
            msg.distortion_model,
            (int(msg.width), int(msg.height)),
            msg.header.frame_id,
        )


@dataclass
class BagIndex:
    """Everything learnt from the first pass over a bag."""

    path: Path
    storage: str
    topic_types: dict[str, str]
    images: dict[str, ImageTopic] = field(default_factory=dict)
    camera_infos: dict[str, CameraInfo] = field(default_factory=dict)
    transforms: TransformTree = field(default_factory=TransformTree)
    depth_unit_m: float | None = None  # RealSense "Depth Units" option
    # (stamp ns, translation (3,), quaternion xyzw (4,)) of the pose topic, in bag order
    pose_samples: list[tuple[int, np.ndarray, np.ndarray]] = field(default_factory=list)

    def stream_frame(self, topic: str) -> str | None:
        """The frame of an image topic: its RealSense stream, else its header's frame_id."""
        stream = topic.removesuffix(REALSENSE_IMAGE_SUFFIX)
        if stream != topic and stream + REALSENSE_TF_SUFFIX in self.topic_types:
            return frame_name(stream)
        return self.images[topic].frame_id or None


def index_bag(
    reader: BagReader,
    path: Path,
    pose_topic: str | None = None,
    pose_frame: str | None = None,
) -> BagIndex:
    """Read the bag once: image stamps, camera infos, transforms and the optional pose topic."""
    index = BagIndex(path, reader.storage, {c.topic: c.msgtype for c in reader.connections})
    wanted = [c for c in reader.connections if _is_indexed(c, pose_topic)]
    images = [c for c in wanted if c.msgtype in IMAGE_TYPES and c.topic != pose_topic]
    try:
        for conn, _, raw in reader.messages(connections=wanted, header_only=images):
            _index_message(index, reader, conn, raw, pose_topic, pose_frame)
    except BAG_ERRORS as err:
        raise bag_error(path, err) from err
    return index


def _is_indexed(conn: Any, pose_topic: str | None) -> bool:
    return (
        conn.msgtype in (*IMAGE_TYPES, CAMERA_INFO)
        or conn.topic in TF_TOPICS
        or conn.topic == pose_topic
        or (conn.msgtype == TRANSFORM and conn.topic.endswith(REALSENSE_TF_SUFFIX))
        or conn.topic.endswith(REALSENSE_DEPTH_UNITS)
    )


def _index_message(
    index: BagIndex,
    reader: BagReader,
    conn: Any,
    raw: bytes | memoryview,
    pose_topic: str | None,
    pose_frame: str | None,
) -> None:
    topic, msgtype = conn.topic, conn.msgtype
    if msgtype in IMAGE_TYPES:
        image = index.images.get(topic)
        if image is None:
            msg = reader.deserialize(raw, msgtype)
            size = (int(msg.width), int(msg.height)) if msgtype == IMAGE else None
            role = image_role(msgtype, msg)
            pixels = (depth_encoding if role == DEPTH else original_encoding)(msgtype, msg)
            encoding = msg.encoding if msgtype == IMAGE else msg.format
            image = index.images[topic] = ImageTopic(
                topic, msgtype, role, encoding, pixels, msg.header.frame_id, size
            )
        image.stamps.append(header_stamp_ns(raw, reader.is2))
    if topic == pose_topic:
        index.pose_samples.extend(_poses(reader.deserialize(raw, msgtype), msgtype, pose_frame))
    if msgtype == CAMERA_INFO and topic not in index.camera_infos:
        index.camera_infos[topic] = CameraInfo.from_message(reader.deserialize(raw, msgtype))
    elif topic in TF_TOPICS and msgtype == TF_MESSAGE:
        index.transforms.add_message(reader.deserialize(raw, msgtype))
    elif msgtype == TRANSFORM:  # RealSense: T_stream_reference, the reference being the device
        stream = topic.removesuffix(REALSENSE_TF_SUFFIX)
        device = stream.split("/")[1]
        index.transforms.add(stream, device, transform_matrix(reader.deserialize(raw, msgtype)))
    elif topic.endswith(REALSENSE_DEPTH_UNITS):
        index.depth_unit_m = float(reader.deserialize(raw, msgtype).data)


def _poses(msg: Any, msgtype: str, pose_frame: str | None) -> list[tuple[int, Any, Any]]:
    """(stamp ns, translation, quaternion) samples of a pose message; for TF those of one frame."""
    if msgtype == TF_MESSAGE:
        if pose_frame is None:
            raise InputError("a TF pose topic needs --pose-frame CHILD_FRAME (the tracked body)")
        return [
            (
                _stamp_ns(t.header),
                vector3(t.transform.translation),
                quaternion(t.transform.rotation),
            )
            for t in msg.transforms
            if frame_name(t.child_frame_id) == frame_name(pose_frame)
        ]
    if msgtype not in POSE_TYPES:
        raise InputError(
            f"pose topic type {msgtype} is not supported; use one of "
            f"{', '.join([*POSE_TYPES, TF_MESSAGE])}"
        )
    position, orientation = POSE_TYPES[msgtype](msg)
    return [(_stamp_ns(msg.header), vector3(position), quaternion(orientation))]


def _stamp_ns(header: Any) -> int:
    return header.stamp.sec * NS_PER_S + header.stamp.nanosec

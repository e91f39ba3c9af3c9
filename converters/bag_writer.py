"""Record RGB-D frames as ROS bags (ROS1 ``.bag``, ROS2 sqlite3 or MCAP) with rosbags' writers.

The tests and the benchmark use it to re-record real frames in every encoding the bag converter
reads; messages are built from the writer's own type store, so they are valid by construction.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from rosbags import rosbag1, rosbag2
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.msg import get_types_from_msg
from rosbags.typesys.store import Typestore

from converters.bag_index import NS_PER_S
from converters.ros_images import (
    COMPRESSED_DEPTH_HEADER,
    COMPRESSED_IMAGE,
    IMAGE,
    INVERSE_DEPTH_FORMAT,
)

WriteFn = Callable[[str, str, Any, int], None]  # (topic, msgtype, message, log time ns)
STORAGES = ("ros1", "sqlite3", "mcap")
TF_MESSAGE_DEF = "geometry_msgs/TransformStamped[] transforms"  # absent from rosbags' ROS1 store
ROS2_BAG_VERSION = 9
# compressedDepth 32FC1 quantisation, v = A / depth + B, with the transport's defaults
# (depth_quantization 100, depth_max 10 m): A = q (q + 1), B = 1 - A / depth_max.
DEPTH_QUANTIZATION, DEPTH_MAX_M = 100.0, 10.0
QUANT_A = DEPTH_QUANTIZATION * (DEPTH_QUANTIZATION + 1.0)
QUANT_B = 1.0 - QUANT_A / DEPTH_MAX_M


class RosMessages:
    """Builds the messages of one bag, in ROS1 or ROS2 flavour, and hands them to `write`."""

    def __init__(self, typestore: Typestore, write: WriteFn, ros1: bool) -> None:
        self.ts, self.write, self.ros1 = typestore, write, ros1

    def header(self, stamp_ns: int, frame: str) -> Any:
        t = self.ts.types
        sec, nanosec = divmod(stamp_ns, NS_PER_S)
        stamp = t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)
        extra = {"seq": 0} if self.ros1 else {}
        return t["std_msgs/msg/Header"](stamp=stamp, frame_id=frame, **extra)

    def image(
        self,
        topic: str,
        stamp_ns: int,
        frame: str,
        pixels: np.ndarray,
        encoding: str,
        big_endian: bool = False,
    ) -> None:
        data = pixels.astype(pixels.dtype.newbyteorder(">" if big_endian else "<"))
        msg = self.ts.types[IMAGE](
            header=self.header(stamp_ns, frame),
            height=pixels.shape[0],
            width=pixels.shape[1],
            encoding=encoding,
            is_bigendian=int(big_endian),
            step=pixels[0].nbytes,
            data=np.frombuffer(data.tobytes(), np.uint8),
        )
        self.write(topic, IMAGE, msg, stamp_ns)

    def compressed(self, topic: str, stamp_ns: int, frame: str, fmt: str, data: bytes) -> None:
        msg = self.ts.types[COMPRESSED_IMAGE](
            header=self.header(stamp_ns, frame), format=fmt, data=np.frombuffer(data, np.uint8)
        )
        self.write(topic, COMPRESSED_IMAGE, msg, stamp_ns)

    def camera_info(
        self,
        topic: str,
        stamp_ns: int,
        frame: str,
        k: np.ndarray,
        size: tuple[int, int],
        d: tuple[float, ...] = (0.0,) * 5,
    ) -> None:
        """A ``plumb_bob`` CameraInfo; ROS1 spells its matrices D K R P, ROS2 d k r p."""
        t = self.ts.types
        k = np.asarray(k, np.float64)
        projection = np.hstack([k, np.zeros((3, 1))])  # unrectified: P = [K | 0]
        values = (np.asarray(d, np.float64), k.ravel(), np.eye(3).ravel(), projection.ravel())
        names = ("D", "K", "R", "P") if self.ros1 else ("d", "k", "r", "p")
        matrices = dict(zip(names, values, strict=True))
        roi = t["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        )
        msg = t["sensor_msgs/msg/CameraInfo"](
            header=self.header(stamp_ns, frame),
            height=size[1],
            width=size[0],
            distortion_model="plumb_bob",
            binning_x=0,
            binning_y=0,
            roi=roi,
            **matrices,
        )
        self.write(topic, "sensor_msgs/msg/CameraInfo", msg, stamp_ns)

    def pose(self, topic: str, stamp_ns: int, xyz: np.ndarray, quat: np.ndarray) -> None:
        t = self.ts.types
        pose = t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](*map(float, xyz)),
            orientation=t["geometry_msgs/msg/Quaternion"](*map(float, quat)),
        )
        msg = t["geometry_msgs/msg/PoseStamped"](header=self.header(stamp_ns, "world"), pose=pose)
        self.write(topic, "geometry_msgs/msg/PoseStamped", msg, stamp_ns)

    def transform(
        self,
        stamp_ns: int,
        parent: str,
        child: str,
        xyz: np.ndarray,
        quat: np.ndarray,
        topic: str = "/tf_static",
    ) -> None:
        """A ``tf2_msgs/TFMessage`` with one transform (``T_parent_child``), static by default."""
        t = self.ts.types
        transform = t["geometry_msgs/msg/Transform"](
            translation=t["geometry_msgs/msg/Vector3"](*map(float, xyz)),
            rotation=t["geometry_msgs/msg/Quaternion"](*map(float, quat)),
        )
        stamped = t["geometry_msgs/msg/TransformStamped"](
            header=self.header(stamp_ns, parent), child_frame_id=child, transform=transform
        )
        msg = t["tf2_msgs/msg/TFMessage"](transforms=[stamped])
        self.write(topic, "tf2_msgs/msg/TFMessage", msg, stamp_ns)


@contextmanager
def bag_writer(
    path: Path, storage: str, compression: str | None = None, ros2_mode: str = "message"
) -> Iterator[RosMessages]:
    """Yield `RosMessages` writing a ROS1 .bag ('ros1') or ROS2 bag folder ('sqlite3', 'mcap').

    `compression`: 'lz4' or 'bz2' chunks for ROS1, 'zstd' for ROS2, which compresses each
    message or, with `ros2_mode` 'file', each storage file.
    """
    ros1 = storage == "ros1"
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if ros1:
        ts.register(get_types_from_msg(TF_MESSAGE_DEF, "tf2_msgs/msg/TFMessage"))
        writer = rosbag1.Writer(path)
        if compression:
            writer.set_compression(rosbag1.Writer.CompressionFormat[compression.upper()])
    else:
        plugin = {"sqlite3": rosbag2.StoragePlugin.SQLITE3, "mcap": rosbag2.StoragePlugin.MCAP}
        writer = rosbag2.Writer(path, version=ROS2_BAG_VERSION, storage_plugin=plugin[storage])
        if compression:
            fmt = rosbag2.CompressionFormat[compression.upper()]
            writer.set_compression(rosbag2.CompressionMode[ros2_mode.upper()], fmt)
    connections: dict[str, Any] = {}

    def write(topic: str, msgtype: str, msg: Any, stamp_ns: int) -> None:
        if topic not in connections:
            connections[topic] = writer.add_connection(topic, msgtype, typestore=ts)
        raw = ts.serialize_ros1(msg, msgtype) if ros1 else ts.serialize_cdr(msg, msgtype)
        writer.write(connections[topic], stamp_ns, raw)

    with writer:
        yield RosMessages(ts, write, ros1)


def compressed_depth(depth: np.ndarray, encoding: str) -> bytes:
    """A compressed_depth_image_transport payload: 12-byte header, then a 16-bit PNG of the
    millimetres (16UC1) or of the quantised inverse depth (32FC1 metres, 0 = invalid)."""
    if encoding == "32FC1":
        with np.errstate(divide="ignore"):
            values = np.where(depth > 0, np.rint(QUANT_A / depth + QUANT_B), 0).astype(np.uint16)
    else:
        values = depth
    header = COMPRESSED_DEPTH_HEADER.pack(INVERSE_DEPTH_FORMAT, QUANT_A, QUANT_B)
    return header + cv2.imencode(".png", values)[1].tobytes()


RGB_TOPIC, DEPTH_TOPIC = "/camera/rgb/image_color", "/camera/depth/image"
RGB_CODECS = ("rgb8", "bgr8", "png", "jpg")
DEPTH_CODECS = ("16UC1", "32FC1", "16UC1 compressedDepth", "32FC1 compressedDepth")


def record_rgbd(
    bag: RosMessages,
    stamps_ns: tuple[int, int],
    rgb: np.ndarray,
    depth: np.ndarray,
    codecs: tuple[str, str],
    units_per_metre: float,
    frame_id: str,
) -> None:
    """Record one RGB-D pair: colour as raw ``rgb8``/``bgr8`` or PNG/JPEG, depth (uint16 in
    `units_per_metre`) as raw ``16UC1`` (big-endian, to exercise byte order) or ``32FC1``
    metres, or as ``compressedDepth`` of either. Compressed topics get the transport suffixes."""
    rgb_codec, depth_codec = codecs
    rgb_ns, depth_ns = stamps_ns
    if rgb_codec in ("rgb8", "bgr8"):
        pixels = rgb if rgb_codec == "rgb8" else rgb[..., ::-1]
        bag.image(RGB_TOPIC, rgb_ns, frame_id, pixels, rgb_codec)
    else:
        data = cv2.imencode(f".{rgb_codec}", rgb[..., ::-1])[1].tobytes()
        fmt = f"rgb8; {rgb_codec} compressed bgr8"
        bag.compressed(f"{RGB_TOPIC}/compressed", rgb_ns, frame_id, fmt, data)
    encoding, _, compressed = depth_codec.partition(" ")
    values = depth
    if encoding == "32FC1":
        values = np.where(depth > 0, depth / np.float32(units_per_metre), np.nan).astype(np.float32)
    if compressed:
        fmt = f"{encoding}; compressedDepth png"
        payload = compressed_depth(np.nan_to_num(values), encoding)
        bag.compressed(f"{DEPTH_TOPIC}/compressedDepth", depth_ns, frame_id, fmt, payload)
    else:
        bag.image(DEPTH_TOPIC, depth_ns, frame_id, values, encoding, big_endian=encoding == "16UC1")

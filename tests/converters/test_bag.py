"""Bag conversion: the real RealSense bag, TUM frames re-recorded as ROS1/ROS2/MCAP bags in every
image encoding, the decoders on their own, registration, and every bad input."""

from __future__ import annotations

import math
import shutil
import sqlite3
import tempfile
from contextlib import contextmanager
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner
from conftest import SHARED_DATA, TUM_EXCERPT
from mcap.writer import Writer as McapWriter
from rosbags.rosbag1 import Reader as Ros1Reader
from rosbags.typesys import Stores, get_typestore

from bgs_batch.cli import main
from bgs_batch.store import FrameStore
from converters.bag_index import open_bag
from converters.bag_readers import (
    HEADER_STAMP_END,
    OP_CONNECTION,
    OP_MSG_DATA,
    BagReadError,
    Ros1Bag,
    _message_data,
)
from converters.bag_sqlite import IDL_SEPARATOR, Ros2Sqlite, _Definition, _parse
from converters.bag_writer import (
    QUANT_A,
    RosMessages,
    bag_writer,
    compressed_depth,
    record_rgbd,
)
from converters.ros_images import COMPRESSED_IMAGE, IMAGE, decode_color, decode_depth
from converters.tum import TUM_CAMERAS, TumOptions, plan_tum

REALSENSE_BAG = (
    SHARED_DATA / "ros1_bag/librealsense/unit-tests/resources/single_depth_color_640x480.bag"
)
TUM_FRAMES = 30
TUM_DEPTH_SCALE = 5000.0  # TUM PNG units, kept as 16UC1 so depth round-trips to the unit
RGB_FRAME, DEPTH_FRAME = "rgb_optical", "depth_optical"


@contextmanager
def chunked_mcap_writer(path: Path, chunk_size: int):
    """Yield `RosMessages` writing a ROS2 MCAP of many small chunks with the mcap package."""
    ts = get_typestore(Stores.ROS2_HUMBLE)
    with open(path, "wb") as fh:
        writer = McapWriter(fh, chunk_size=chunk_size)
        writer.start(profile="ros2", library="bgs-batch tests")
        channels = {}

        def write(topic: str, msgtype: str, msg, stamp_ns: int) -> None:
            if topic not in channels:
                msgdef = ts.generate_msgdef(msgtype, ros_version=2)[0]
                schema = writer.register_schema(msgtype, "ros2msg", msgdef.encode())
                channels[topic] = writer.register_channel(topic, "cdr", schema)
            writer.add_message(channels[topic], stamp_ns, ts.serialize_cdr(msg, msgtype), stamp_ns)

        yield RosMessages(ts, write, ros1=False)
        writer.finish()


def encode(image: np.ndarray, ext: str) -> bytes:
    return cv2.imencode(ext, image)[1].tobytes()


# --- TUM frames re-recorded as bags -----------------------------------------------------------


@pytest.fixture(scope="module")
def tum_frames():
    """The first 30 associated TUM frames: stamps (ns), RGB, depth (5000/m) and GT samples."""
    excerpt = TUM_EXCERPT
    if not (excerpt / "rgb.txt").is_file():
        pytest.skip(f"real TUM excerpt not found at {excerpt} (set BGS_SHARED_DATA)")
    plan = plan_tum(excerpt, TumOptions(max_frames=TUM_FRAMES))
    frames = []
    for frame in plan.frames:
        rgb_name, depth_name = frame.name.split(" + ")
        rgb, depth = frame.load()
        frames.append((_ns(Path(rgb_name).stem), _ns(Path(depth_name).stem), rgb, depth))
    gt = np.loadtxt(excerpt / "groundtruth.txt")
    first, last = frames[0][0] / 1e9 - 0.1, frames[-1][0] / 1e9 + 0.1
    return excerpt, frames, gt[(gt[:, 0] > first) & (gt[:, 0] < last)]


def _ns(stamp: str) -> int:
    seconds, fraction = stamp.split(".")
    return int(seconds) * 10**9 + int(fraction.ljust(9, "0"))


def write_tum_bag(
    path: Path, storage: str, tum_frames, rgb_codec: str, depth_codec: str, compression: str | None
) -> Path:
    """Record the TUM frames with the given encodings, fr1 CameraInfo and PoseStamped GT."""
    _, frames, gt = tum_frames
    camera = TUM_CAMERAS["freiburg1"]
    with bag_writer(path, storage, compression) as bag:
        info = ("/camera/rgb/camera_info", frames[0][0], RGB_FRAME)
        bag.camera_info(*info, camera.matrix, (640, 480), camera.distortion)
        for row in gt:
            bag.pose("/mocap/pose", _ns(f"{row[0]:.4f}"), row[1:4], row[4:])
        for rgb_ns, depth_ns, rgb, depth in frames:
            codecs = (rgb_codec, depth_codec)
            record_rgbd(bag, (rgb_ns, depth_ns), rgb, depth, codecs, TUM_DEPTH_SCALE, RGB_FRAME)
    return path


def convert(path: Path, out: Path, *args: str):
    return CliRunner().invoke(main, ["-q", "convert", "bag", str(path), "-o", str(out), *args])


def assert_fails(result, *needles: str) -> None:
    assert result.exit_code == 3, result.output
    for needle in needles:
        assert needle in result.output, result.output


@pytest.fixture(scope="module")
def tum_store(tum_frames, tmp_path_factory):
    """The TUM conversion of the same 30 frames, the reference every bag is compared with."""
    out = tmp_path_factory.mktemp("tum") / "tum.h5"
    args = f"-q convert tum {tum_frames[0]} -o {out} --max-frames {TUM_FRAMES}".split()
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    return out


@pytest.mark.slow
@pytest.mark.parametrize(
    ("storage", "rgb_codec", "depth_codec", "compression"),
    [
        ("ros1", "rgb8", "16UC1", "lz4"),  # big-endian depth
        ("sqlite3", "png", "16UC1 compressedDepth", "zstd"),  # compressed messages
        ("mcap", "bgr8", "32FC1", None),
        ("mcap", "jpg", "32FC1 compressedDepth", None),
    ],
)
def test_tum_frames_round_trip_through_bags(
    tum_frames, tum_store, tmp_path, storage, rgb_codec, depth_codec, compression
):
    name = "rec.bag" if storage == "ros1" else "rec"
    bag = write_tum_bag(tmp_path / name, storage, tum_frames, rgb_codec, depth_codec, compression)
    source = bag / "rec.db3" if storage == "sqlite3" else bag  # a bare file beside its yaml
    out = tmp_path / "bag.h5"
    result = convert(
        source, out, "--depth-scale", str(TUM_DEPTH_SCALE), "--pose-topic", "/mocap/pose"
    )
    assert result.exit_code == 0, result.output
    with FrameStore(out) as ours, FrameStore(tum_store) as ref:
        assert len(ours) == len(ref) == TUM_FRAMES
        assert np.allclose(ours.timestamps, ref.timestamps, rtol=0, atol=1e-6)  # ns vs text
        assert np.allclose(ours.intrinsics, ref.intrinsics)
        assert np.allclose(ours.attrs["distortion"], ref.attrs["distortion"])
        assert np.allclose(ours.poses_gt, ref.poses_gt, atol=1e-6)  # stamps differ by < 1 µs
        assert ours.provenance["topic_choice"] == "rgb auto-detected, depth auto-detected"
        for i in range(TUM_FRAMES):
            rgb, expected = ours.read_rgb(i), ref.read_rgb(i)
            if rgb_codec == "jpg":
                assert np.abs(rgb.astype(int) - expected).mean() < 3
            else:
                assert np.array_equal(rgb, expected)
            depth, units = ours.read_depth_raw(i), ref.read_depth_raw(i)
            if depth_codec.startswith("16UC1"):
                assert ours.depth_scale == 5000 and np.array_equal(depth, units)
            elif depth_codec == "32FC1":
                assert depth.dtype == np.float32 and np.array_equal(np.rint(depth * 5000), units)
            else:  # quantised inverse depth: error grows with depth², ~1 mm/m² at these settings
                valid = units > 0
                assert np.array_equal(depth > 0, valid)
                metres = units[valid] / 5000
                assert np.all(np.abs(depth[valid] - metres) <= metres**2 / QUANT_A + 1e-5)


# --- the real RealSense bag -------------------------------------------------------------------


@pytest.fixture
def realsense_bag() -> Path:
    if not REALSENSE_BAG.is_file():
        pytest.skip(f"real RealSense bag not found at {REALSENSE_BAG} (set BGS_SHARED_DATA)")
    return REALSENSE_BAG


@pytest.mark.slow
def test_realsense_bag_registers_depth_into_colour(realsense_bag, tmp_path):
    out = tmp_path / "rs.h5"
    assert_fails(convert(realsense_bag, out), "0.1016 s apart", "--tolerance")
    result = convert(realsense_bag, out, "--tolerance", "0.15")
    assert result.exit_code == 0, result.output
    with FrameStore(out) as store:
        assert len(store) == 1 and (store.width, store.height) == (640, 480)
        assert np.allclose(
            store.intrinsics[[0, 1, 0, 1], [0, 1, 2, 2]],
            [613.2037, 613.4193, 319.9388, 239.1830],
            atol=1e-3,
        )
        assert store.depth_scale == 1000
        registered = store.read_depth_raw(0)
        provenance = store.provenance
        assert math.isnan(store.rolling_shutter_readout)  # a bag names no readout: estimated
        assert math.isnan(store.depth_rolling_shutter_readout)
    assert "re-projected" in provenance["registration"]
    assert "RealSense" in provenance["depth_scale_source"]
    assert "estimates it" in provenance["rolling_shutter_readout_source"]
    told = tmp_path / "told.h5"  # a D435: rolling colour, global-shutter depth
    result = convert(realsense_bag, told, "--tolerance", "0.15", "--readout", "auto",
                     "--depth-readout", "0")  # fmt: skip
    assert result.exit_code == 0, result.output
    with FrameStore(told) as store:
        assert math.isnan(store.rolling_shutter_readout)
        assert store.depth_rolling_shutter_readout == 0
    assert convert(realsense_bag, tmp_path / "bad.h5", "--readout", "-1").exit_code == 2
    # the colour camera sees the middle of the wider depth view: nearly every pixel gets depth
    assert (registered > 0).mean() > 0.9

    # round trip: lift registered pixels back into the depth camera; unoccluded ones must land
    # on a raw depth pixel of the same depth (to the 1 mm unit)
    raw = _realsense_first_depth(realsense_bag)
    color_from_depth = np.asarray(provenance["registration_color_from_depth"])
    depth_k = np.asarray(provenance["depth_intrinsics"])
    v, u = np.nonzero(registered)
    z = registered[v, u] / 1000.0
    points = np.linalg.inv(store.intrinsics) @ np.stack([u, v, np.ones_like(u)]) * z
    points = np.linalg.inv(color_from_depth) @ np.vstack([points, np.ones_like(z)])
    u, v = np.rint(depth_k @ (points[:3] / points[2])).astype(int)[:2]
    inside = (u >= 0) & (u < raw.shape[1]) & (v >= 0) & (v < raw.shape[0])
    source = raw[v[inside], u[inside]].astype(float)
    close = np.abs(source - points[2][inside] * 1000) <= 1.0
    assert close.mean() > 0.9


def _realsense_first_depth(path: Path) -> np.ndarray:
    from rosbags.highlevel import AnyReader

    with AnyReader([path]) as reader:
        depth = [c for c in reader.connections if c.topic.endswith("Depth_0/image/data")]
        _, _, raw = next(reader.messages(connections=depth))
        return decode_depth(IMAGE, reader.deserialize(raw, IMAGE))


# --- the ROS1 reader ----------------------------------------------------------------------------


@pytest.mark.parametrize("compression", [None, "lz4", "bz2"])
def test_ros1_reader_matches_rosbags(tmp_path, compression):
    """Same messages, bytes and order (receive time, then connection) as rosbags' AnyReader, over
    several chunks and with depth received before the colour frame written ahead of it."""
    from rosbags.highlevel import AnyReader

    path = tmp_path / "order.bag"
    rng = np.random.default_rng(0)
    with bag_writer(path, "ros1", compression) as bag:  # > 1 MB: several chunks
        bag.camera_info("/cam/color/camera_info", 1, RGB_FRAME, np.eye(3), (128, 96))
        for i in range(40):
            stamp = 10**9 + i * 33_000_000
            rgb = rng.integers(0, 256, (96, 128, 3), np.uint8)
            bag.image("/cam/color/image_raw", stamp, RGB_FRAME, rgb, "rgb8")
            depth = np.full((96, 128), i, np.uint16)
            bag.image("/cam/depth/image_raw", stamp - 5_000_000, RGB_FRAME, depth, "16UC1")
            bag.transform(stamp, "world", "cam", (i, 0, 0), (0, 0, 0, 1), topic="/tf")

    with Ros1Reader(path) as plain:
        assert len(plain.chunks) > 1

    def listing(messages) -> list[tuple[str, int, bytes]]:
        return [(conn.topic, time, bytes(raw)) for conn, time, raw in messages]

    ours = Ros1Bag(path)
    try:
        images = [c for c in ours.connections if c.topic.endswith("image_raw")][::-1]
        with AnyReader([path]) as ref:
            ref_images = [c for c in ref.connections if c.topic.endswith("image_raw")][::-1]
            assert listing(ours.messages()) == listing(ref.messages())
            assert listing(ours.messages(images)) == listing(ref.messages(ref_images))
            _, _, raw = next(ours.messages(images[1:]))
            _, _, ref_raw = next(ref.messages(ref_images[1:]))
            ours_msg = ours.deserialize(raw, IMAGE)
            assert np.array_equal(ours_msg.data, ref.deserialize(ref_raw, IMAGE).data)
    finally:
        ours.close()

    fresh = Ros1Bag(path)  # types are registered on first use, which may come after close
    color = next(c for c in fresh.connections if c.topic == "/cam/color/image_raw")
    _, _, raw = next(fresh.messages([color]))
    raw = bytes(raw)
    fresh.close()
    assert np.array_equal(fresh.deserialize(raw, IMAGE).data, ours_msg.data)


# --- the ROS2 sqlite3 reader ------------------------------------------------------------------


@pytest.mark.parametrize("compression", [None, "message", "file"])
def test_sqlite_reader_matches_rosbags(tmp_path, compression):
    """Same messages, bytes and order as rosbags' AnyReader for plain, message- and
    file-compressed bags; header-only reads keep the first message of a topic whole."""
    from rosbags.highlevel import AnyReader

    folder = tmp_path / "rec"
    _tiny_bag(folder, "sqlite3", compression=compression and "zstd", ros2_mode=compression)

    def listing(messages) -> list[tuple[str, int, bytes]]:
        return [(conn.topic, time, bytes(raw)) for conn, time, raw in messages]

    with open_bag(folder) as ours, AnyReader([folder]) as ref:
        assert isinstance(ours, Ros2Sqlite)
        assert listing(ours.messages()) == listing(ref.messages())
        images = [c for c in ours.connections if c.msgtype == IMAGE]
        whole = listing(ours.messages(images))
        heads = listing(ours.messages(images, header_only=images))
        info = next(c for c in ours.connections if c.msgtype.endswith("CameraInfo"))
        _, _, raw = next(ours.messages([info]))
    assert [h[:2] for h in heads] == [w[:2] for w in whole]
    for topic in {t for t, _, _ in whole}:
        mine = [h[2] for h in heads if h[0] == topic]
        full = [w[2] for w in whole if w[0] == topic]
        assert mine[0] == full[0]  # the first one whole: the index reads its encoding and size
        cut = len(full[1]) if compression == "message" else HEADER_STAMP_END
        assert all(h == w[:cut] for h, w in zip(mine[1:], full[1:], strict=True))
    assert ours.deserialize(raw, info.msgtype).width == 8  # works after close
    out = tmp_path / "out.h5"
    result = convert(folder, out)
    assert result.exit_code == 0, result.output
    with FrameStore(out) as store:
        assert len(store) == 3 and store.provenance["storage"] == "ROS2 sqlite3"
        assert store.read_depth_raw(2)[0, 0] == 1000


def test_db3_plan_opens_the_bag_once(tmp_path, monkeypatch):
    """A file-compressed bag is decompressed once for both passes, which may run in another
    thread; the copy goes when the second pass ends, or when a plan is dropped unused."""
    from concurrent.futures import ThreadPoolExecutor

    from converters.bag import BagOptions, plan_bag

    folder = _tiny_bag(tmp_path / "rec", "sqlite3", compression="zstd", ros2_mode="file")
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))
    plan = plan_bag(folder, BagOptions())
    assert [p.name for p in scratch.glob("*/*")] == ["rec.db3"]
    with ThreadPoolExecutor(1) as pool:
        assert pool.submit(lambda: len([f.load() for f in plan.frames])).result() == 3
    assert not any(scratch.iterdir())
    unused = plan_bag(folder, BagOptions())
    assert [p.name for p in scratch.glob("*/*")] == ["rec.db3"]
    del unused
    assert not any(scratch.iterdir())


def test_db3_read_ahead_stops_with_its_pass(tmp_path, monkeypatch):
    """Rows are read on a helper thread a bounded number of messages ahead; it ends when its
    pass ends, is abandoned or the reader closes, and its errors reach the consumer in order."""
    import threading

    import converters.bag_sqlite as bag_sqlite

    def helpers() -> int:
        return sum(t.name == "db3-read-ahead" for t in threading.enumerate())

    monkeypatch.setattr(bag_sqlite, "READ_AHEAD_MESSAGES", 1)
    folder = _tiny_bag(tmp_path / "rec", "sqlite3")
    with open_bag(folder) as reader:
        everything = [(c.topic, t, raw) for c, t, raw in reader.messages()]
        assert helpers() == 0
        abandoned = reader.messages()
        assert next(abandoned)[1] == everything[0][1]
        assert helpers() == 1
        abandoned.close()
        assert helpers() == 0
        unfinished = reader.messages()
        next(unfinished)
    assert helpers() == 0  # closing the reader stopped it
    assert reader._read_aheads == set()

    def failing():
        yield from everything[:2]
        raise sqlite3.OperationalError("disk I/O error")

    got = []
    with pytest.raises(sqlite3.OperationalError, match="disk I/O"):
        got.extend(bag_sqlite._ReadAhead(failing()))
    assert got == everything[:2]


def test_conversion_keeps_frame_buffers_in_heap(tmp_path):
    """On glibc the pipeline raises malloc's mmap and trim thresholds once, so megabyte frame
    buffers are reused rather than faulted in afresh every frame (see converters.pipeline)."""
    import platform
    import resource

    from converters.pipeline import keep_frame_buffers_in_heap

    glibc = platform.libc_ver()[0] == "glibc"
    assert keep_frame_buffers_in_heap() is glibc
    assert keep_frame_buffers_in_heap() is glibc  # idempotent
    if not glibc:
        pytest.skip("mallopt thresholds are glibc's")
    # buffers each a little bigger than any freed before, as ISA-L's output grows: glibc's own
    # thresholds would map (and fault in) every one of them afresh, ~8000 faults in all
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for k in range(20):
        np.ones((1 << 20) + k * (64 << 10), np.uint8)
    assert resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults < 2000


def test_db3_idl_definitions():
    """rosbag2 records a type's IDL alone or, with the IDLs it uses, each after a header."""
    a = "module pkg { module msg { struct A { int32 value; }; }; };"
    b = "module pkg { module msg { struct B { pkg::msg::A a; double x; }; }; };"
    assert list(_parse("pkg/msg/A", _Definition("ros2idl", a, ""))) == ["pkg/msg/A"]
    several = "".join(
        f"{IDL_SEPARATOR}IDL: pkg/msg/{n}\n{idl}\n" for n, idl in (("B", b), ("A", a))
    )
    assert sorted(_parse("pkg/msg/B", _Definition("ros2idl", several, ""))) == [
        "pkg/msg/A",
        "pkg/msg/B",
    ]
    with pytest.raises(BagReadError, match="unknown encoding 'unknown'"):
        _parse("pkg/msg/A", _Definition("unknown", a, ""))


def test_bare_db3_without_metadata(tmp_path):
    folder = _tiny_bag(tmp_path / "rec", "sqlite3")
    bare = shutil.copy(folder / "rec.db3", tmp_path / "moved.db3")
    result = convert(bare, tmp_path / "out.h5")
    assert result.exit_code == 0, result.output
    assert len(FrameStore(tmp_path / "out.h5")) == 3


def _db3(tmp_path: Path, sql: str = "", compression: str | None = None) -> Path:
    """A small sqlite3 bag folder, its database changed by `sql`."""
    folder = _tiny_bag(tmp_path / "bad", "sqlite3", compression=compression)
    if sql:
        with sqlite3.connect(folder / "bad.db3") as db:
            db.executescript(sql)
        db.close()
    return folder


@pytest.mark.parametrize(
    ("damage", "needles"),
    [
        ("garbage", ["cannot read the bag", "not a readable sqlite3 database"]),
        ("truncated", ["cannot read the bag", "malformed"]),
        ("DROP TABLE topics;", ["not a rosbag2 database"]),
        ("DROP TABLE message_definitions;", ["holds no message definitions"]),
        ("UPDATE message_definitions SET type_description_hash = 'RIHS01_0';", ["hash"]),
        ("UPDATE topics SET serialization_format = 'json';", ["'json', not cdr"]),
        ("missing file", ["database files that are missing", "bad.db3"]),
        ("lz4", ["compression format 'lz4' is not supported"]),
        ("corrupt zstd", ["cannot be decompressed"]),
        ("yaml: [", ["cannot read", "metadata.yaml"]),
        (
            "rosbag2_bagfile_information: {version: 9, storage_identifier: sqlite3}",
            ["missing or invalid", "relative_file_paths"],
        ),
    ],
)
def test_bad_db3_is_reported(tmp_path, damage, needles):
    sql = damage if damage.endswith(";") else ""
    folder = _db3(tmp_path, sql, "zstd" if damage == "lz4" else None)
    db3, yaml = folder / "bad.db3", folder / "metadata.yaml"
    if damage == "garbage":
        db3.write_bytes(b"not sqlite" * 1000)
    elif damage == "truncated":
        db3.write_bytes(db3.read_bytes()[: db3.stat().st_size // 2])
    elif damage == "missing file":
        db3.unlink()
    elif damage == "lz4":
        yaml.write_text(
            yaml.read_text().replace("compression_format: zstd", "compression_format: lz4")
        )
    elif damage.startswith(("yaml", "rosbag2")):
        yaml.write_text(damage)
    elif damage == "corrupt zstd":
        yaml.write_text(
            yaml.read_text()
            .replace("compression_format: ''", "compression_format: zstd")
            .replace("compression_mode: ''", "compression_mode: message")
        )
    out = tmp_path / "out.h5"
    assert_fails(convert(folder, out), str(folder), *needles)
    _assert_no_output(out)


def _record(op: int, data: bytes) -> bytes:
    """A ROS1 bag record: header of length-prefixed ``name=value`` fields, then the data."""
    fields = b"".join(
        len(f).to_bytes(4, "little") + f for f in (b"conn=" + bytes(4), b"op=" + bytes([op]))
    )
    return len(fields).to_bytes(4, "little") + fields + len(data).to_bytes(4, "little") + data


def test_ros1_chunk_records():
    """A chunk may repeat a connection record before a message; anything else is an error."""
    chunk = memoryview(_record(OP_CONNECTION, b"topic=/x") + _record(OP_MSG_DATA, b"payload"))
    assert bytes(_message_data(chunk, 0)) == b"payload"
    with pytest.raises(BagReadError, match="type 5"):
        _message_data(memoryview(_record(5, b"")), 0)
    with pytest.raises(BagReadError, match="past the end"):
        _message_data(chunk[:-1], 0)


# --- registration via /tf_static, decoders ----------------------------------------------------


def test_depth_from_another_camera_is_registered_via_tf_static(tmp_path):
    """Half-resolution depth of a wall 1.5 m away, seen from 5 cm to the colour camera's right:
    registration fills the colour image except the strip only the colour camera sees."""
    k = np.array([[80.0, 0, 31.5], [0, 80.0, 23.5], [0, 0, 1]])
    depth_k = k * [[0.5], [0.5], [1]]
    depth_k[:2, 2] = (31.5 - 0.5) / 2, (23.5 - 0.5) / 2  # pixel (2i, 2j) ↔ depth pixel (i, j)
    rgb = np.random.default_rng(1).integers(0, 256, (48, 64, 3), np.uint8)
    with bag_writer(tmp_path / "reg", "sqlite3") as bag:
        bag.transform(0, "base", RGB_FRAME, (0, 0, 0), (0, 0, 0, 1))
        bag.transform(0, "base", DEPTH_FRAME, (0.05, 0, 0), (0, 0, 0, 1))
        bag.camera_info("/cam/color/camera_info", 1, RGB_FRAME, k, (64, 48))
        bag.camera_info("/cam/depth/camera_info", 1, DEPTH_FRAME, depth_k, (32, 24))
        for i in range(2):
            bag.image("/cam/color/image_raw", 10**9 + i, RGB_FRAME, rgb, "rgb8")
            wall = np.full((24, 32), 1500, np.uint16)
            bag.image("/cam/depth/image_raw", 10**9 + i, DEPTH_FRAME, wall, "mono16")
    out = tmp_path / "reg.h5"
    result = convert(tmp_path / "reg", out)
    assert result.exit_code == 0, result.output
    with FrameStore(out) as store:
        depth = store.read_depth_raw(0)
        assert store.provenance["depth_info_topic"] == "/cam/depth/camera_info"
        assert "depth_optical -> rgb_optical" in store.provenance["registration_extrinsic_source"]
        assert store.depth_registered  # with the recorded extrinsic: no offset left to estimate
    shift = 80 * 0.05 / 1.5  # colour pixels: the wall's depth pixels land this far right
    assert np.all(depth[:, : int(shift) - 1] == 0) and np.all(depth[:, int(shift) + 1 :] == 1500)


def test_ground_truth_from_tf(tmp_path):
    bag = tmp_path / "tf.bag"
    with bag_writer(bag, "ros1") as rec:
        rec.camera_info("/cam/color/camera_info", 1, RGB_FRAME, np.eye(3) * [10, 10, 1], (8, 6))
        for i in range(4):
            stamp = 10**9 + i * 50_000_000
            rec.transform(stamp - 1, "world", "/camera", (i, 0, 0), (0, 0, 0, 1), topic="/tf")
            rec.transform(stamp - 1, "world", "other", (9, 9, 9), (0, 0, 0, 1), topic="/tf")
            rec.image(
                "/cam/color/image_raw", stamp, RGB_FRAME, np.zeros((6, 8, 3), np.uint8), "rgb8"
            )
            rec.image("/cam/depth/image_raw", stamp, RGB_FRAME, np.ones((6, 8), np.uint16), "16UC1")
    out = tmp_path / "out.h5"
    assert_fails(convert(bag, out, "--pose-topic", "/tf"), "--pose-frame")
    result = convert(bag, out, "--pose-topic", "/tf", "--pose-frame", "camera")
    assert result.exit_code == 0, result.output
    with FrameStore(out) as store:  # no depth CameraInfo: nobody says depth sits on colour
        assert not store.depth_registered and "depth_registered" not in store.attrs
    with FrameStore(out) as store:
        poses = store.poses_gt
        assert store.provenance["gt_source"] == "/tf (camera)"
    assert np.isnan(poses[-1]).all()  # after the last sample: not bracketed
    assert np.allclose(poses[:3, 0, 3], [0, 1, 2], atol=1e-6)
    assert np.allclose(poses[:3, :3, :3], np.eye(3))


class _Msg:
    def __init__(self, **fields) -> None:
        self.__dict__.update(fields)


def _raw(pixels: np.ndarray, encoding: str, pad: int = 0, big: bool = False) -> _Msg:
    rows = pixels.astype(pixels.dtype.newbyteorder(">" if big else "<")).reshape(
        pixels.shape[0], -1
    )
    padded = np.concatenate([rows.view(np.uint8), np.zeros((len(rows), pad), np.uint8)], axis=1)
    return _Msg(
        height=pixels.shape[0],
        width=pixels.shape[1],
        encoding=encoding,
        step=padded.shape[1],
        is_bigendian=int(big),
        data=padded.ravel(),
    )


def test_decoders_cover_every_encoding():
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (5, 7, 3), np.uint8)
    alpha = np.full((5, 7, 1), 9, np.uint8)
    cases = {
        "rgb8": rgb,
        "bgr8": rgb[..., ::-1],
        "rgba8": np.concatenate([rgb, alpha], 2),
        "bgra8": np.concatenate([rgb[..., ::-1], alpha], 2),
    }
    for encoding, pixels in cases.items():
        assert np.array_equal(decode_color(IMAGE, _raw(pixels, encoding, pad=3)), rgb), encoding
    gray = rgb[..., 0]
    assert np.array_equal(decode_color(IMAGE, _raw(gray, "mono8")), np.dstack([gray] * 3))
    png = _Msg(format="png", data=encode(rgb[..., ::-1], ".png"))
    assert np.array_equal(decode_color(COMPRESSED_IMAGE, png), rgb)

    depth = rng.integers(0, 4000, (5, 7)).astype(np.uint16)
    for encoding in ("16UC1", "mono16"):
        msg = _raw(depth, encoding, pad=2, big=True)
        assert np.array_equal(decode_depth(IMAGE, msg), depth)
    metres = np.array([[1.5, np.nan, -1.0, np.inf]], np.float32)
    assert decode_depth(IMAGE, _raw(metres, "32FC1")).tolist() == [[1.5, 0, 0, 0]]
    msg = _Msg(format="16UC1; compressedDepth", data=compressed_depth(depth, "16UC1"))
    assert np.array_equal(decode_depth(COMPRESSED_IMAGE, msg), depth)


# --- bad input --------------------------------------------------------------------------------


def _tiny_bag(
    path: Path,
    storage: str = "ros1",
    *,
    rgb_topics=("/cam/color/image_raw",),
    depth_size=(8, 6),
    rgb_payload=None,
    compression: str | None = None,
    ros2_mode: str | None = None,
) -> Path:
    """A small valid bag (3 frames of 8x6), or one broken in a single, named way."""
    rgb = np.full((6, 8, 3), 100, np.uint8)
    with bag_writer(path, storage, compression, ros2_mode or "message") as bag:
        bag.camera_info("/cam/color/camera_info", 1, RGB_FRAME, np.eye(3) * [10, 10, 1], (8, 6))
        for i in range(3):
            stamp = 10**9 + i * 33_000_000
            for topic in rgb_topics:
                if rgb_payload is None:
                    bag.image(topic, stamp, RGB_FRAME, rgb, "rgb8")
                else:
                    bag.compressed(topic, stamp, RGB_FRAME, "jpeg", rgb_payload(i, rgb))
            depth = np.full(depth_size[::-1], 1000, np.uint16)
            bag.image("/cam/depth/image_raw", stamp + 1_000_000, DEPTH_FRAME, depth, "16UC1")
    return path


def _assert_no_output(out: Path) -> None:
    assert not out.exists() and not Path(f"{out}.tmp").exists()


def test_truncated_bag_is_reported(tmp_path):
    bag = _tiny_bag(tmp_path / "rec.bag")
    assert convert(bag, tmp_path / "ok.h5").exit_code == 0
    data = bag.read_bytes()
    bag.write_bytes(data[: len(data) * 6 // 10])
    out = tmp_path / "out.h5"
    assert_fails(convert(bag, out), str(bag), "truncated", "reindex")
    _assert_no_output(out)


def test_corrupt_ros1_chunk_is_reported(tmp_path):
    bag = _tiny_bag(tmp_path / "rec.bag", compression="bz2")
    with Ros1Reader(bag) as reader:
        chunk = next(iter(reader.chunks.values()))
    data = bytearray(bag.read_bytes())
    middle = chunk.datapos + chunk.datasize // 2
    data[middle : middle + 8] = bytes(8)  # bz2's block CRC no longer matches
    bag.write_bytes(bytes(data))
    out = tmp_path / "out.h5"
    assert_fails(convert(bag, out), str(bag), "cannot be decompressed", "reindex")
    _assert_no_output(out)


def test_truncated_mcap_is_salvaged(tmp_path):
    path = tmp_path / "crashed.mcap"
    rgb = np.random.default_rng(0).integers(0, 256, (24, 32, 3), np.uint8)  # incompressible
    with chunked_mcap_writer(path, chunk_size=4096) as bag:
        bag.camera_info("/cam/color/camera_info", 1, RGB_FRAME, np.eye(3) * [10, 10, 1], (32, 24))
        for i in range(20):
            stamp = 10**9 + i * 33_000_000
            bag.image("/cam/color/image_raw", stamp, RGB_FRAME, rgb, "rgb8")
            bag.image(
                "/cam/depth/image_raw",
                stamp,
                RGB_FRAME,
                np.full((24, 32), i + 1, np.uint16),
                "16UC1",
            )
    data = path.read_bytes()
    path.write_bytes(data[: len(data) * 6 // 10])
    out = tmp_path / "out.h5"
    result = convert(path, out)
    assert result.exit_code == 0, result.output
    with FrameStore(out) as store:
        assert 5 < len(store) < 20 and "salvaged" in store.provenance["storage"]
        assert [store.read_depth_raw(i)[0, 0] for i in range(len(store))] == list(
            range(1, len(store) + 1)
        )


def test_bag_without_images(tmp_path):
    with bag_writer(tmp_path / "empty.bag", "ros1") as bag:
        bag.camera_info("/cam/camera_info", 1, RGB_FRAME, np.eye(3), (8, 6))
    out = tmp_path / "out.h5"
    assert_fails(
        convert(tmp_path / "empty.bag", out), "empty.bag has no image topics", "/cam/camera_info"
    )
    _assert_no_output(out)


def test_ambiguous_topics_need_a_choice(tmp_path):
    bag = _tiny_bag(tmp_path / "two", "mcap", rgb_topics=("/left/image_raw", "/right/image_raw"))
    out = tmp_path / "out.h5"
    assert_fails(
        convert(bag, out),
        "2 colour image topics",
        "/left/image_raw",
        "/right/image_raw",
        "--rgb-topic",
    )
    _assert_no_output(out)
    wrong = convert(bag, out, "--rgb-topic", "/cam/depth/image_raw")
    assert_fails(wrong, "--rgb-topic /cam/depth/image_raw holds '16UC1' images")
    result = convert(
        bag, out, "--rgb-topic", "/right/image_raw", "--info-topic", "/cam/color/camera_info"
    )
    assert result.exit_code == 0, result.output
    assert FrameStore(out).provenance["topic_choice"] == "rgb given, depth auto-detected"


def test_mismatched_resolutions(tmp_path):
    bag = _tiny_bag(tmp_path / "res.bag", depth_size=(4, 3))
    out = tmp_path / "out.h5"
    assert_fails(convert(bag, out), "res.bag", "8x6", "4x3", "CameraInfo")
    _assert_no_output(out)


def test_corrupt_jpeg_fails_or_is_skipped(tmp_path):
    def payload(i: int, rgb: np.ndarray) -> bytes:
        data = encode(rgb, ".jpg")
        return data[: len(data) // 3] if i == 1 else data

    bag = _tiny_bag(tmp_path / "jpeg.bag", rgb_payload=payload, compression="bz2")
    out = tmp_path / "out.h5"
    assert_fails(convert(bag, out), "jpeg.bag", "truncated JPEG", "--skip-bad-frames")
    _assert_no_output(out)
    result = convert(bag, out, "--skip-bad-frames")
    assert result.exit_code == 0, result.output
    assert len(FrameStore(out)) == 2

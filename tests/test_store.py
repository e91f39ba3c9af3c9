import zlib

import h5py
import numpy as np
import pytest

from bgs_batch.errors import InputError, OutputExistsError
from bgs_batch.store import (
    FrameStore,
    FrameStoreWriter,
    StoreMeta,
    encode_frame,
    temp_path,
)

K = np.array([[50.0, 0, 16], [0, 50.0, 12], [0, 0, 1]])


def meta(**kw):
    return StoreMeta("test", "/nowhere", "seq", K, 5000.0, has_gt=True,
                     provenance={"choice": 1}, **kw)  # fmt: skip


def random_frames(n, h=24, w=32, dtype=np.uint16, seed=0):
    rng = np.random.default_rng(seed)
    for i in range(n):
        rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        if dtype == np.uint16:
            depth = rng.integers(0, 60000, (h, w), dtype=np.uint16)
        else:
            depth = rng.uniform(0.1, 5, (h, w)).astype(np.float32)
        pose = np.eye(4)
        pose[:3, 3] = [i, 0, 0]
        yield rgb, depth, 100.0 + i / 30, (None if i == 1 else pose)


def write(path, frames, **kw):
    with FrameStoreWriter(path, meta(**kw)) as writer:
        for rgb, depth, t, pose in frames:
            writer.append(encode_frame(rgb, depth, t, pose))
        return writer.finish()


@pytest.mark.parametrize("dtype", [np.uint16, np.float32])
def test_round_trip_bitwise(tmp_path, dtype):
    frames = list(random_frames(5, dtype=dtype))
    path = write(tmp_path / "s.h5", frames)
    assert not temp_path(path).exists()
    with FrameStore(path) as store, h5py.File(path) as raw:
        assert len(store) == 5 and (store.width, store.height) == (32, 24)
        assert np.array_equal(store.intrinsics, K)
        assert store.provenance == {"choice": 1}
        for (rgb, depth, t, pose), frame, i in zip(frames, store, range(5), strict=True):
            assert frame.index == i and frame.timestamp == t
            assert np.array_equal(frame.rgb, rgb)
            assert np.array_equal(store.read_depth_raw(i), depth)
            # plain h5py (HDF5's own gzip+shuffle filters) reads the same bytes: files are portable
            assert np.array_equal(raw["rgb"][i], rgb) and np.array_equal(raw["depth"][i], depth)
            expected = depth.astype(np.float32) / 5000 if dtype == np.uint16 else depth
            assert frame.depth.dtype == np.float32 and np.array_equal(frame.depth, expected)
            assert (frame.pose_gt is None) == (pose is None)
            if pose is not None:
                assert np.array_equal(frame.pose_gt, pose)
        assert np.isnan(store.poses_gt[1]).all()
        assert raw["rgb"].chunks == (1, 24, 32, 3) and raw["rgb"].compression == "gzip"
        # depth taken with the colour: no /depth_timestamp, and no offset to move it by
        assert "depth_timestamp" not in raw and store.depth_timestamps is None
        assert frame.depth_timestamp is None and frame.depth_time_offset == 0.0


def test_depth_timestamps_are_kept_where_the_recording_has_them(tmp_path):
    """A frame without its own depth time stamp was taken with its colour image."""
    frames = list(random_frames(3))
    path = tmp_path / "s.h5"
    with FrameStoreWriter(path, meta()) as writer:
        for k, (rgb, depth, t, pose) in enumerate(frames):
            writer.append(encode_frame(rgb, depth, t, pose, depth_timestamp=None if k == 1
                                       else t + 0.01 * (k - 1)))  # fmt: skip
        writer.finish()
    with FrameStore(path) as store:
        offsets = [frame.depth_time_offset for frame in store]
        assert store.depth_timestamps.dtype == np.float64
    np.testing.assert_allclose(offsets, [-0.01, 0.0, 0.01], atol=1e-9)


@pytest.mark.parametrize("dtype", [np.uint16, np.float32])
def test_depth_chunks_hold_hdf5_shuffled_bytes(tmp_path, dtype):
    """Our shuffle puts the bytes in the order HDF5's own shuffle filter does."""
    _, depth, _, _ = next(random_frames(1, h=7, w=13, dtype=dtype))
    with h5py.File(tmp_path / "ref.h5", "w") as f:
        ds = f.create_dataset("d", data=depth[None], chunks=(1, 7, 13), compression="gzip",
                              shuffle=True)  # fmt: skip
        hdf5_shuffled = zlib.decompress(ds.id.read_direct_chunk((0, 0, 0))[1])
    ours = encode_frame(np.zeros((7, 13, 3), np.uint8), depth, 0.0).depth_chunk
    assert zlib.decompress(ours) == hdf5_shuffled


def test_indexing_and_ordered_subsets(tmp_path):
    path = write(tmp_path / "s.h5", random_frames(7))
    with FrameStore(path) as store:
        assert store[-1].index == 6
        assert [f.index for f in store.frames([5, 0, 3])] == [5, 0, 3]
        with pytest.raises(IndexError):
            store[7]


def test_reads_stores_written_by_other_tools(tmp_path):
    """A store with another filter (lzf, several frames per chunk) goes through h5py's reader."""
    path = write(tmp_path / "s.h5", random_frames(3))
    with h5py.File(path, "a") as f:
        rgb, depth = f["rgb"][()], f["depth"][()]
        del f["rgb"], f["depth"]
        f.create_dataset("rgb", data=rgb, compression="lzf", chunks=(2, 24, 32, 3))
        f.create_dataset("depth", data=depth, chunks=(3, 24, 32))
    with FrameStore(path) as store:
        assert np.array_equal(store[2].rgb, rgb[2])
        assert np.array_equal(store.read_depth_raw(1), depth[1])


def test_exception_leaves_nothing(tmp_path):
    path = tmp_path / "s.h5"
    with pytest.raises(RuntimeError), FrameStoreWriter(path, meta()) as writer:
        rgb, depth, t, pose = next(random_frames(1))
        writer.append(encode_frame(rgb, depth, t, pose))
        raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_empty_and_mismatched_frames_refused(tmp_path):
    path = tmp_path / "s.h5"
    with pytest.raises(InputError, match="no frames"), FrameStoreWriter(path, meta()) as w:
        w.finish()
    with pytest.raises(InputError, match="differs from the first frame"), \
            FrameStoreWriter(path, meta()) as w:  # fmt: skip
        w.append(encode_frame(*next(random_frames(1))[:3]))
        w.append(encode_frame(*next(random_frames(1, h=20))[:3]), "odd.png")
    assert list(tmp_path.iterdir()) == []


def test_existing_output_refused_unless_overwrite(tmp_path):
    path = write(tmp_path / "s.h5", random_frames(2))
    with pytest.raises(OutputExistsError, match="--overwrite"):
        FrameStoreWriter(path, meta())
    with FrameStoreWriter(path, meta(), overwrite=True) as w:
        w.append(encode_frame(*next(random_frames(1, seed=9))[:3]))
        w.finish()
    assert len(FrameStore(path)) == 1


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        (lambda f: f.attrs.__delitem__("depth_scale"), "missing attributes: depth_scale"),
        (lambda f: f["timestamp"].__setitem__(1, 0.0), "not strictly increasing"),
        (lambda f: f["pose_gt"].__setitem__((0, 0, 0), 3.0), "not rigid"),
        (lambda f: f.__delitem__("intrinsics"), "missing dataset /intrinsics"),
        (lambda f: f.attrs.__setitem__("provenance", "{"), "not JSON"),
        (lambda f: f.create_dataset("depth_timestamp", data=[1.0, np.nan, 2.0]), "not finite"),
        (lambda f: f.create_dataset("depth_timestamp", data=[1.0, 2.0]), "float64 \\[3\\]"),
        (lambda f: f.attrs.__setitem__("rolling_shutter_readout", -0.01), "rolling_shutter"),
        (lambda f: f.attrs.__setitem__("rolling_shutter_readout", np.inf), "rolling_shutter"),
        (lambda f: f.attrs.__setitem__("depth_registered", "no"), "depth_registered 'no'"),
    ],
)
def test_validation_names_the_problem(tmp_path, damage, message):
    path = write(tmp_path / "s.h5", random_frames(3))
    with h5py.File(path, "a") as f:
        damage(f)
    with pytest.raises(InputError, match=message) as err:
        FrameStore(path)
    assert str(path) in str(err.value) and "bgs convert" in str(err.value)


def test_unreadable_files(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        FrameStore(tmp_path / "nope.h5")
    path = write(tmp_path / "s.h5", random_frames(3))
    truncated = tmp_path / "t.h5"
    truncated.write_bytes(path.read_bytes()[:2000])
    with pytest.raises(InputError, match="truncated"):
        FrameStore(truncated)

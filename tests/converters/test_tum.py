"""TUM conversion: correctness on made-up and real data, and every bad input the issue lists."""

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner
from conftest import gt_pose, make_tum_folder

from bgs_batch.cli import main
from bgs_batch.geometry import pose_matrix
from bgs_batch.store import FrameStore, temp_path


def convert(folder, out, *args):
    result = CliRunner().invoke(main, ["-q", "convert", "tum", str(folder), "-o", str(out), *args])
    return result


def assert_fails(result, code, *needles):
    assert result.exit_code == code, result.output
    for needle in needles:
        assert needle in result.output, result.output


def test_converts_pixels_timestamps_and_interpolated_gt(tum_folder, tmp_path):
    out = tmp_path / "seq.h5"
    result = convert(tum_folder, out, "--no-undistort")
    assert result.exit_code == 0, result.output
    with FrameStore(out) as store:
        assert len(store) == 6 and store.depth_scale == 5000
        fx_fy_cx_cy = store.intrinsics[[0, 1, 0, 1], [0, 1, 2, 2]]
        assert np.allclose(fx_fy_cx_cy, [517.3, 516.5, 318.6, 255.3])
        assert store.provenance["intrinsics_source"].startswith("freiburg1")
        assert store.attrs["source_format"] == "tum"
        names = sorted((tum_folder / "rgb").iterdir())
        for frame, name in zip(store, names, strict=True):
            assert np.array_equal(frame.rgb, cv2.imread(str(name))[..., ::-1])
            assert frame.timestamp == float(name.stem)
            # GT is sampled at 100 Hz from a constant-rate motion: lerp + slerp are exact
            assert np.allclose(frame.pose_gt, pose_matrix(*np.split(gt_pose(frame.timestamp), [3])),
                               atol=2e-6)  # fmt: skip
        # each depth image's own time stamp is kept (the SLAM moves it to the colour's time)
        depth_names = sorted((tum_folder / "depth").iterdir())
        assert store.depth_timestamps.tolist() == [float(name.stem) for name in depth_names]
        depth0 = cv2.imread(str(depth_names[0]), -1)
        assert np.array_equal(store.read_depth_raw(0), depth0)
        assert store[0].depth[0, 0] == 0


def test_stride_max_frames_and_no_gt(tmp_path):
    folder = make_tum_folder(tmp_path, frames=9, gt=False)
    out = tmp_path / "s.h5"
    assert convert(folder, out, "--stride", "2", "--max-frames", "3").exit_code == 0
    with FrameStore(out) as store:
        assert len(store) == 3 and not store.has_gt
        assert np.allclose(np.diff(store.timestamps), 2 / 30, atol=1e-5)
        assert store.provenance["associated"] == 9


def test_camera_choice_precedence(tmp_path):
    folder = make_tum_folder(tmp_path, name="my_room")
    assert_fails(convert(folder, tmp_path / "a.h5"), 3, "--intrinsics", "calibration.txt")
    assert not (tmp_path / "a.h5").exists()
    (folder / "calibration.txt").write_text("100 101 15.5 11.5\n")
    assert convert(folder, tmp_path / "b.h5").exit_code == 0
    assert FrameStore(tmp_path / "b.h5").intrinsics[0, 0] == 100
    args = ["--intrinsics", "1", "2", "3", "4", "--distortion", "0.1", "0", "0", "0", "0"]
    assert convert(folder, tmp_path / "c.h5", *args).exit_code == 0
    store = FrameStore(tmp_path / "c.h5")
    assert store.intrinsics[1, 1] == 2 and store.attrs["distortion"][0] == 0.1
    assert store.provenance["intrinsics_source"] == "--intrinsics"


def test_undistort_rgb_and_depth_consistently(tmp_path):
    tum_folder = make_tum_folder(tmp_path, frames=2, size=(640, 480))  # the calibration's size
    out = tmp_path / "u.h5"
    assert convert(tum_folder, out).exit_code == 0  # freiburg1: undistorted by default
    with FrameStore(out) as store:
        assert bool(store.attrs["distortion_applied"]) and store.provenance["undistort"]
        raw = cv2.imread(str(sorted((tum_folder / "depth").iterdir())[0]), -1)
        stored = store.read_depth_raw(0)
        # nearest-neighbour remap invents no depth values (no mixing across edges)
        assert set(np.unique(stored)) - {0} <= set(np.unique(raw))
        assert not np.array_equal(stored, raw)
        # colour went through the same map: it matches cv2.undistort of the source image
        k, dist = store.intrinsics, np.asarray(store.attrs["distortion"])
        source = cv2.imread(str(sorted((tum_folder / "rgb").iterdir())[0]))[..., ::-1]
        inner = np.s_[4:-4, 4:-4]
        expected = cv2.undistort(np.ascontiguousarray(source), k, dist)
        error = np.abs(store[0].rgb[inner].astype(int) - expected[inner])
        # cv2.undistort interpolates with 1/32 fixed-point weights: up to 255/32 on pure noise
        assert error.max() <= 8 and error.mean() < 1.5


# ---------------------------------------------------------------- bad input, one test each


def test_missing_list_file(tum_folder, tmp_path):
    (tum_folder / "depth.txt").unlink()
    assert_fails(convert(tum_folder, tmp_path / "s.h5"), 3, "depth.txt is missing")
    assert not (tmp_path / "s.h5").exists()


def test_missing_referenced_image_and_skip(tum_folder, tmp_path):
    victim = sorted((tum_folder / "rgb").iterdir())[2]
    victim.unlink()
    assert_fails(convert(tum_folder, tmp_path / "s.h5"), 3, str(victim), "--skip-bad-frames")
    assert not (tmp_path / "s.h5").exists()
    result = convert(tum_folder, tmp_path / "s.h5", "--skip-bad-frames")
    assert result.exit_code == 0 and "5 frames, 1 skipped" in result.output
    assert FrameStore(tmp_path / "s.h5").provenance["skipped_frames"][0]["frame"].startswith(
        f"rgb/{victim.name}"
    )


@pytest.mark.parametrize("damage", ["truncate", "garbage"])
def test_unreadable_png(tum_folder, tmp_path, damage):
    victim = sorted((tum_folder / "depth").iterdir())[3]
    data = victim.read_bytes()
    victim.write_bytes(data[: len(data) // 2] if damage == "truncate" else b"not a png")
    reason = "truncated PNG" if damage == "truncate" else "corrupt or truncated"
    assert_fails(convert(tum_folder, tmp_path / "s.h5"), 3, str(victim), reason,
                 "--skip-bad-frames")  # fmt: skip
    assert list(tmp_path.glob("s.h5*")) == []
    result = convert(tum_folder, tmp_path / "s.h5", "--skip-bad-frames")
    assert result.exit_code == 0 and "1 skipped" in result.output


def test_a_truncated_jpeg_is_refused_not_stored_grey(tum_folder, tmp_path):
    """OpenCV decodes half a JPEG into an image with grey rows; the converter must not."""
    victims = sorted((tum_folder / "rgb").iterdir())
    for victim in victims:  # a sequence with JPEG colour (the content decides, not the name)
        image = cv2.imread(str(victim))
        victim.write_bytes(cv2.imencode(".jpg", image)[1].tobytes())
    data = victims[2].read_bytes()
    victims[2].write_bytes(data[: len(data) // 2])
    assert_fails(convert(tum_folder, tmp_path / "s.h5"), 3, str(victims[2]), "truncated JPEG",
                 "--skip-bad-frames")  # fmt: skip
    assert list(tmp_path.glob("s.h5*")) == []
    result = convert(tum_folder, tmp_path / "s.h5", "--skip-bad-frames")
    assert result.exit_code == 0 and "1 skipped" in result.output
    skipped = FrameStore(tmp_path / "s.h5").provenance["skipped_frames"]
    assert [s["frame"].split()[0] for s in skipped] == [f"rgb/{victims[2].name}"]


def test_rgb_depth_size_mismatch(tum_folder, tmp_path):
    victim = sorted((tum_folder / "depth").iterdir())[1]
    cv2.imwrite(str(victim), np.ones((10, 10), np.uint16))
    assert_fails(convert(tum_folder, tmp_path / "s.h5"), 3, str(victim), "registered")
    assert list(tmp_path.glob("s.h5*")) == []


def test_frame_size_changes_mid_sequence(tum_folder, tmp_path):
    rgb = sorted((tum_folder / "rgb").iterdir())[4]
    depth = sorted((tum_folder / "depth").iterdir())[4]
    cv2.imwrite(str(rgb), np.zeros((12, 16, 3), np.uint8))
    cv2.imwrite(str(depth), np.zeros((12, 16), np.uint16))
    assert_fails(convert(tum_folder, tmp_path / "s.h5"), 3, rgb.name, "first frame")


def test_zero_associations(tum_folder, tmp_path):
    lines = (tum_folder / "depth.txt").read_text().splitlines()
    shifted = [ln if ln.startswith("#") else f"{float(ln.split()[0]) + 100:.6f} {ln.split()[1]}"
               for ln in lines]  # fmt: skip
    (tum_folder / "depth.txt").write_text("\n".join(shifted))
    assert_fails(convert(tum_folder, tmp_path / "s.h5"), 3, "no RGB frame", "--tolerance")


@pytest.mark.parametrize("kind", ["duplicate", "decreasing"])
def test_non_monotonic_timestamps(tum_folder, tmp_path, kind):
    lines = (tum_folder / "rgb.txt").read_text().splitlines()
    lines.insert(5, lines[4] if kind == "duplicate" else lines[3])
    (tum_folder / "rgb.txt").write_text("\n".join(lines))
    assert_fails(convert(tum_folder, tmp_path / "s.h5"), 3, "rgb.txt:6", kind)


def test_bad_gt_quaternion(tum_folder, tmp_path):
    lines = (tum_folder / "groundtruth.txt").read_text().splitlines()
    fields = lines[10].split()
    lines[10] = " ".join(fields[:4] + ["0.5", "0.5", "0.5", "0.9"])
    (tum_folder / "groundtruth.txt").write_text("\n".join(lines))
    assert_fails(convert(tum_folder, tmp_path / "s.h5"), 3, "groundtruth.txt:11", "norm")


def test_output_exists(tum_folder, tmp_path):
    out = tmp_path / "s.h5"
    out.write_text("precious")
    assert_fails(convert(tum_folder, out), 4, "--overwrite")
    assert out.read_text() == "precious"
    assert convert(tum_folder, out, "--overwrite").exit_code == 0
    assert len(FrameStore(out)) == 6


def test_not_a_folder(tmp_path):
    assert_fails(convert(tmp_path / "nope", tmp_path / "s.h5"), 3, "is not a folder")


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_interrupted_conversion_leaves_nothing(tmp_path, signum):
    folder = make_tum_folder(tmp_path, frames=400, size=(640, 480), distinct=False)
    out = tmp_path / "s.h5"
    bgs = Path(sys.executable).with_name("bgs")
    proc = subprocess.Popen([bgs, "-q", "convert", "tum", folder, "-o", out, "--workers", "1"],
                            stderr=subprocess.PIPE, text=True)  # fmt: skip
    deadline = time.monotonic() + 60
    while not temp_path(out).exists() and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.005)
    assert proc.poll() is None, "conversion finished before it could be interrupted"
    os.kill(proc.pid, signum)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signum, err
    assert "interrupted" in err
    assert not out.exists() and not temp_path(out).exists()


# ---------------------------------------------------------------- the real TUM excerpt


@pytest.mark.slow
def test_real_fr1_rpy_excerpt(tum_excerpt, tmp_path):
    out = tmp_path / "fr1.h5"
    converted = convert(tum_excerpt, out, "--no-undistort")
    assert converted.exit_code == 0
    assert "240 RGB images, 240 associated (each with a depth image within 0.02 s)" in (
        converted.output
    )
    result = CliRunner().invoke(main, ["inspect", str(out), "--json"])
    assert result.exit_code == 0
    summary = json.loads(result.output)
    assert summary["frames"] == 240 and (summary["width"], summary["height"]) == (640, 480)
    assert summary["gt_coverage_percent"] == 100.0
    assert 76 < summary["depth_valid_percent"] < 79  # data/README: about 77 %
    assert summary["provenance"]["depth_median_m"] == pytest.approx(1.0, abs=0.5)
    with FrameStore(out) as store:
        first = store[0]
        assert np.array_equal(first.rgb, cv2.imread(str(tum_excerpt / "rgb/1305031229.528748.png"))
                              [..., ::-1])  # fmt: skip
        # GT is within one 100 Hz sample of the nearest raw pose (hand-held motion, < 1 cm/10 ms)
        gt = np.loadtxt(tum_excerpt / "groundtruth.txt")
        nearest = gt[np.argmin(np.abs(gt[:, 0] - first.timestamp))]
        assert np.linalg.norm(first.pose_gt[:3, 3] - nearest[1:4]) < 0.01


def test_a_freiburg1_folder_is_undistorted_and_recommends_the_reference_crop(tum_excerpt, tmp_path):
    out = tmp_path / "fr1.h5"
    assert convert(tum_excerpt, out, "--max-frames", "2").exit_code == 0
    with FrameStore(out) as store:
        assert store.crop_edge == 50 and bool(store.attrs["distortion_applied"])
        assert "fr1" in store.provenance["crop_edge_source"]
        raw = cv2.imread(str(tum_excerpt / "rgb/1305031229.528748.png"))[..., ::-1]
        assert not np.array_equal(store[0].rgb, raw)
    shown = CliRunner().invoke(main, ["inspect", str(out)])
    assert shown.exit_code == 0 and "50 px per border" in shown.output
    raw_out = tmp_path / "raw.h5"
    assert convert(tum_excerpt, raw_out, "--max-frames", "2", "--no-undistort").exit_code == 0
    with FrameStore(raw_out) as store:
        assert store.crop_edge == 50 and not store.attrs["distortion_applied"]


@pytest.mark.parametrize(("name", "crop"), [("freiburg1", 50), ("freiburg2", 8), ("freiburg3", 8)])
def test_each_tum_camera_recommends_its_reference_crop_at_640x480(tmp_path, name, crop):
    folder = make_tum_folder(tmp_path, frames=2, size=(640, 480), name=f"rgbd_dataset_{name}_x")
    assert convert(folder, tmp_path / "s.h5").exit_code == 0
    with FrameStore(tmp_path / "s.h5") as store:
        assert store.crop_edge == crop
        assert bool(store.attrs["distortion_applied"]) == (name != "freiburg3")


def test_no_crop_nor_undistortion_for_other_sizes_or_given_intrinsics(tum_folder, tmp_path):
    # the published fr1 calibration is for 640x480 images; these are 32x24
    assert convert(tum_folder, tmp_path / "small.h5").exit_code == 0
    with FrameStore(tmp_path / "small.h5") as store:
        assert store.crop_edge == 0 and "640x480" in store.provenance["crop_edge_source"]
        assert not store.attrs["distortion_applied"]
    given = ["--distortion", "0.1", "0", "0", "0", "0", "--intrinsics", "20", "20", "16", "12"]
    assert convert(tum_folder, tmp_path / "d.h5", *given).exit_code == 0
    with FrameStore(tmp_path / "d.h5") as store:  # coefficients given for these images: applied
        assert store.attrs["distortion_applied"]
    big = make_tum_folder(tmp_path / "big", frames=2, size=(640, 480))
    given = convert(big, tmp_path / "given.h5", "--intrinsics", "500", "500", "320", "240")
    assert given.exit_code == 0
    with FrameStore(tmp_path / "given.h5") as store:
        assert store.crop_edge == 0


def test_the_rolling_shutter_readout_comes_from_the_camera_a_file_or_the_option(tmp_path):
    fr1 = make_tum_folder(tmp_path / "a", frames=2)  # a freiburg1 name: the Kinect's readout
    assert convert(fr1, tmp_path / "fr1.h5").exit_code == 0
    with FrameStore(tmp_path / "fr1.h5") as store:
        assert store.rolling_shutter_readout == pytest.approx(0.03)
        assert "rolling shutter" in store.provenance["rolling_shutter_readout_source"]
        assert store.depth_registered  # the benchmark's driver registered depth to colour
        assert "registered" in store.provenance["depth_registered_source"]
    shown = CliRunner().invoke(main, ["inspect", str(tmp_path / "fr1.h5")])
    assert "rows read out over 30.0 ms" in shown.output
    shown = CliRunner().invoke(main, ["inspect", "--json", str(tmp_path / "fr1.h5")])
    assert json.loads(shown.output)["depth_registered"] is True
    assert convert(fr1, tmp_path / "gs.h5", "--readout", "0").exit_code == 0
    with FrameStore(tmp_path / "gs.h5") as store:  # 0: global shutter, no attribute written
        assert store.rolling_shutter_readout == 0 and "rolling_shutter_readout" not in store.attrs
    other = make_tum_folder(tmp_path / "b", frames=2, name="my_camera")
    (other / "calibration.txt").write_text("20 20 16 12\n")
    assert convert(other, tmp_path / "other.h5").exit_code == 0
    with FrameStore(tmp_path / "other.h5") as store:  # an unknown camera: the run estimates it
        assert math.isnan(store.rolling_shutter_readout)
        assert not store.depth_registered  # and checks its colour camera's offset
        assert "estimates it" in store.provenance["rolling_shutter_readout_source"]
    shown = CliRunner().invoke(main, ["inspect", str(tmp_path / "other.h5")])
    assert "unknown: `bgs run` estimates" in " ".join(shown.output.split())
    shown = CliRunner().invoke(main, ["inspect", "--json", str(tmp_path / "other.h5")])
    assert json.loads(shown.output)["rolling_shutter_readout"] is None
    assert json.loads(shown.output)["depth_registered"] is False
    (other / "readout.txt").write_text("0.03 0\n")  # `bgs synth --global-shutter-depth`
    assert convert(other, tmp_path / "mixed.h5").exit_code == 0
    with FrameStore(tmp_path / "mixed.h5") as store:  # colour rolling, depth taken at once
        assert store.rolling_shutter_readout == pytest.approx(0.03)
        assert store.depth_rolling_shutter_readout == 0
    assert convert(other, tmp_path / "d435.h5", "--readout", "auto", "--depth-readout", "0"
                   ).exit_code == 0  # fmt: skip
    with FrameStore(tmp_path / "d435.h5") as store:
        assert math.isnan(store.rolling_shutter_readout)
        assert store.depth_rolling_shutter_readout == 0
        assert store.provenance["depth_rolling_shutter_readout_source"] == "--depth-readout"
    shown = CliRunner().invoke(main, ["inspect", str(tmp_path / "d435.h5")]).output
    shown = " ".join(shown.split())
    assert "depth shutter │ global" in shown
    (other / "readout.txt").unlink()
    with FrameStore(tmp_path / "fr1.h5") as store:  # one readout: the depth image's is the same
        assert store.depth_rolling_shutter_readout == store.rolling_shutter_readout
        assert "depth_rolling_shutter_readout" not in store.attrs
    assert convert(fr1, tmp_path / "auto.h5", "--readout", "auto").exit_code == 0
    with FrameStore(tmp_path / "auto.h5") as store:  # a known camera, told to estimate
        assert math.isnan(store.rolling_shutter_readout)
        assert store.provenance["rolling_shutter_readout_source"].startswith("--readout auto")
    (other / "readout.txt").write_text("0.025\n")
    assert convert(other, tmp_path / "file.h5").exit_code == 0
    with FrameStore(tmp_path / "file.h5") as store:
        assert store.rolling_shutter_readout == pytest.approx(0.025)
        assert store.provenance["rolling_shutter_readout_source"] == "readout.txt"


@pytest.mark.parametrize(("text", "option", "code"), [
    ("-0.01", None, 3), ("0.01 0.02 0.03", None, 3), ("0.01 -1", None, 3), ("fast", None, 3),
    (None, "1.5", 2), (None, "-1", 2), (None, "fast", 2), (None, "nan", 2)])  # fmt: skip
def test_a_bad_readout_is_refused_and_writes_nothing(tmp_path, text, option, code):
    folder = make_tum_folder(tmp_path / "a", frames=2)
    if text is not None:
        (folder / "readout.txt").write_text(text)
    result = convert(folder, tmp_path / "s.h5", *(["--readout", option] if option else []))
    assert result.exit_code == code and "readout" in result.output
    assert "Traceback" not in result.output and not list(tmp_path.glob("s.h5*"))


def test_depth_scale_is_stored_and_an_implausible_median_warns(tum_folder, tmp_path):
    # the folder's depth is 0.5-4 m at 5000 per metre; read as millimetres it is 2.5-20 m
    result = convert(tum_folder, tmp_path / "mm.h5", "--depth-scale", "1000")
    assert result.exit_code == 0, result.output
    with FrameStore(tmp_path / "mm.h5") as store:
        assert store.depth_scale == 1000
        assert store.provenance["depth_scale_source"] == "--depth-scale"
        assert store.read_depth(0).max() == pytest.approx(store.read_depth_raw(0).max() / 1000)
    assert "warning" not in result.output
    wrong = convert(tum_folder, tmp_path / "wrong.h5", "--depth-scale", "100")
    assert wrong.exit_code == 0
    assert "warning: the depth images' median is" in wrong.output and "1000" in wrong.output
    assert_fails(convert(tum_folder, tmp_path / "z.h5", "--depth-scale", "0"), 2, "--depth-scale")


def test_the_summary_names_rgb_images_without_depth(tum_folder, tmp_path):
    lines = (tum_folder / "depth.txt").read_text().splitlines(keepends=True)
    (tum_folder / "depth.txt").write_text("".join(lines[:4] + lines[5:]))  # depth of frame 1 gone
    result = convert(tum_folder, tmp_path / "s.h5")
    assert result.exit_code == 0, result.output
    assert "6 RGB images, 5 associated (1 without a depth image within 0.02 s;" in result.output


@pytest.mark.parametrize("value", ["auto", "-0.1", "2", "x"])
def test_a_bad_depth_readout_exits_2_and_writes_nothing(tmp_path, value):
    folder = make_tum_folder(tmp_path / "a", frames=2)
    result = convert(folder, tmp_path / "s.h5", "--depth-readout", value)
    assert result.exit_code == 2 and "--depth-readout" in result.output
    assert not list(tmp_path.glob("s.h5*"))

"""Conversion and read-back speed of the frame store, side by side with plain PNG decoding.

Usage: .venv/bin/python bench/convert.py [--tum DIR] [--repeats 3] [--only tum|scannet|bags]

Runs on the real TUM fr1/rpy excerpt in ../shared/data (or any TUM folder); all numbers come
from one run, so the ratios hold even on a noisy machine. Prints a table and one summary line.
Targets: conversion >= 80 % of the single-thread OpenCV decode rate of the same
PNGs, peak RSS growth 60 -> 240 frames < 50 MB, read-back >= 150 frames/s.

One row pair per further format, made from the same real frames: ScanNet (.sens and
exported folder: colour upscaled to 1296x968 JPEG, depth in mm) and bags (ROS1 with lz4 chunks,
ROS2 sqlite3, ROS2 MCAP: JPEG colour and compressedDepth PNG, as robots record). Each pair is the
single-thread decode-only rate of those frames (reading the container included) and the full
conversion (index pass, decode, deflate, write; 2 workers; timed after the imports, as the TUM
row), with the peak RSS of converting a 60-frame and a 240-frame input: target >= 80 % of
decode, RSS growth < 50 MB. CPU ms/frame are printed too: unlike frames/s they do not depend
on what else the machine runs (conversion can beat one decoding thread only when its two
workers get two cores).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import h5py
import numpy as np

from bgs_batch.store import FrameStore
from converters.bag_index import open_bag
from converters.bag_writer import DEPTH_TOPIC, RGB_TOPIC, bag_writer, record_rgbd
from converters.ros_images import decode_color, decode_depth
from converters.scannet import ScanNetOptions, plan_scannet
from converters.sens import write_sens
from converters.tum import TUM_CAMERAS, TumOptions, plan_tum

from status_page import recorded

BENCH_DIR = Path(__file__).resolve().parent
SHARED_DATA = BENCH_DIR.parents[1] / "shared" / "data"
DEFAULT_TUM = SHARED_DATA / "tum_rgbd" / "rgbd_dataset_freiburg1_rpy"
TARGET_CONVERT_RATIO = 0.8
TARGET_RSS_GROWTH_MB = 50
TARGET_READ_FPS = 150

# Runs one conversion in a fresh interpreter and reports its own peak RSS.
_CHILD = """
import json, sys, time
from pathlib import Path
from converters.pipeline import write_store
from converters.tum import TumOptions, plan_tum
from peak_memory import peak_rss_mb
folder, out, frames = Path(sys.argv[1]), Path(sys.argv[2]), int(sys.argv[3])
plan = plan_tum(folder, TumOptions(max_frames=frames))
start = time.perf_counter()
report = write_store(plan.frames, out, plan.meta, overwrite=True)
print(json.dumps({"seconds": time.perf_counter() - start, "frames": report.frames,
                  "peak_rss_mb": peak_rss_mb()}))
"""

# Runs plan + conversion of a ScanNet scene or a bag in a fresh interpreter.
_CHILD_FORMAT = """
import json, sys, time
from pathlib import Path
from converters.pipeline import write_store
from converters.bag import BagOptions, plan_bag
from converters.scannet import ScanNetOptions, plan_scannet
from peak_memory import peak_rss_mb
kind, source, out = sys.argv[1], Path(sys.argv[2]), Path(sys.argv[3])
# timed from here, as the TUM child: the interpreter's imports are start-up, not throughput
start, cpu = time.perf_counter(), time.process_time()
if kind == "scannet":
    plan = plan_scannet(source, ScanNetOptions())
else:
    plan = plan_bag(source, BagOptions())
report = write_store(plan.frames, out, plan.meta, overwrite=True)
print(json.dumps({"seconds": time.perf_counter() - start, "frames": report.frames,
                  "cpu_s": time.process_time() - cpu, "peak_rss_mb": peak_rss_mb()}))
"""
SCANNET_COLOR_SIZE = (1296, 968)  # ScanNet's colour camera; depth stays 640x480
BAG_STORAGES = {"ROS1 .bag (lz4)": ("ros1", "lz4"), "ROS2 .db3": ("sqlite3", None),
                "ROS2 .mcap": ("mcap", None)}  # fmt: skip
BAG_CODECS = ("jpg", "16UC1 compressedDepth")
MM_PER_TUM_UNIT = 1000 / 5000
ONLY_CHOICES = ("tum", "scannet", "bags")  # --only: the TUM PNG rows, or one group of format rows


def decode_rate(pairs: list[tuple[Path, Path]], threads: int) -> float:
    """Frames/s of decoding both PNGs of every pair with OpenCV, nothing else."""

    def decode(pair: tuple[Path, Path]) -> None:
        cv2.imread(str(pair[0]), cv2.IMREAD_UNCHANGED)
        cv2.imread(str(pair[1]), cv2.IMREAD_UNCHANGED)

    start = time.perf_counter()
    if threads == 1:
        for pair in pairs:
            decode(pair)
    else:
        with ThreadPoolExecutor(threads) as pool:
            list(pool.map(decode, pairs))
    return len(pairs) / (time.perf_counter() - start)


def run_child(code: str, *args: object) -> dict:
    """Run `code` in a fresh interpreter that can import this folder's modules; its JSON line."""
    path = os.pathsep.join(filter(None, [str(BENCH_DIR), os.environ.get("PYTHONPATH")]))
    env = {**os.environ, "PYTHONPATH": path}
    result = subprocess.run([sys.executable, "-c", code, *map(str, args)], check=True,
                            capture_output=True, text=True, env=env)  # fmt: skip
    return json.loads(result.stdout)


def convert_in_child(folder: Path, out: Path, frames: int) -> dict:
    return run_child(_CHILD, folder, out, frames)


def read_rates(path: Path) -> tuple[float, float]:
    """Frames/s of FrameStore iteration (prefetching) and of plain single-thread h5py reads."""
    with FrameStore(path) as store:
        start = time.perf_counter()
        n = sum(1 for _ in store)
        ours = n / (time.perf_counter() - start)
    with h5py.File(path) as f:
        start = time.perf_counter()
        for i in range(n):
            f["rgb"][i], f["depth"][i]
        plain = n / (time.perf_counter() - start)
    return ours, plain


def load_tum_frames(plan) -> list[tuple[int, int, np.ndarray, np.ndarray]]:  # noqa: ANN001
    """(rgb ns, depth ns, RGB, depth in TUM units) of every planned TUM frame."""
    frames = []
    for frame in plan.frames:
        rgb_name, depth_name = (Path(name).stem for name in frame.name.split(" + "))
        rgb, depth = frame.load()
        frames.append((round(float(rgb_name) * 1e9), round(float(depth_name) * 1e9), rgb, depth))
    return frames


def make_format_inputs(frames: list, root: Path, only: str | None = None) -> dict[str, Path]:
    """The frames as a ScanNet .sens and export folder and as bags, named by format (only the
    ScanNet or the bag ones when `only` says so)."""
    root.mkdir(parents=True, exist_ok=True)
    inputs = {} if only == "bags" else make_scannet(frames, root)
    if only != "scannet":
        inputs.update(make_bags(frames, root))
    return inputs


def make_scannet(frames: list, root: Path) -> dict[str, Path]:
    """The frames as a ScanNet export folder and .sens file (colour upscaled to JPEG)."""
    scene = []
    folder = root / "scene"
    for sub in ("color", "depth", "pose", "intrinsic"):
        (folder / sub).mkdir(parents=True)
    for i, (_, _, rgb, depth) in enumerate(frames):
        color = cv2.resize(rgb[..., ::-1], SCANNET_COLOR_SIZE, interpolation=cv2.INTER_LINEAR)
        jpeg = cv2.imencode(".jpg", color)[1].tobytes()
        millimetres = np.rint(depth * MM_PER_TUM_UNIT).astype(np.uint16)
        scene.append((jpeg, millimetres, np.eye(4)))
        (folder / "color" / f"{i}.jpg").write_bytes(jpeg)
        cv2.imwrite(str(folder / "depth" / f"{i}.png"), millimetres)
        np.savetxt(folder / "pose" / f"{i}.txt", np.eye(4))
    k4 = np.eye(4)
    k4[:3, :3] = TUM_CAMERAS["freiburg1"].matrix
    np.savetxt(folder / "intrinsic" / "intrinsic_depth.txt", k4)
    sens = write_sens(root / "scene.sens", scene, k4, k4, SCANNET_COLOR_SIZE)
    return {"ScanNet folder": folder, "ScanNet .sens": sens}


def make_bags(frames: list, root: Path) -> dict[str, Path]:
    """The frames recorded as a bag of every storage (JPEG colour, compressedDepth PNG)."""
    inputs = {}
    for name, (storage, compression) in BAG_STORAGES.items():
        path = root / ("rec.bag" if storage == "ros1" else f"rec_{storage}")
        with bag_writer(path, storage, compression) as bag:
            bag.camera_info("/camera/rgb/camera_info", frames[0][0], "rgb",
                            TUM_CAMERAS["freiburg1"].matrix, (640, 480))  # fmt: skip
            for rgb_ns, depth_ns, rgb, depth in frames:
                record_rgbd(bag, (rgb_ns, depth_ns), rgb, depth, BAG_CODECS, 5000.0, "rgb")
        inputs[name] = path
    return inputs


def format_decode(name: str, source: Path) -> tuple[float, float]:
    """Frames/s and CPU ms/frame of reading and decoding every frame of a format input, one thread,
    nothing else."""
    start, cpu = time.perf_counter(), time.process_time()
    if name.startswith("ScanNet"):
        plan = plan_scannet(source, ScanNetOptions())
        for frame in plan.frames:
            frame.load()
        frames = plan.count
    else:
        frames = 0
        with open_bag(source) as reader:
            for conn, _, raw in reader.messages():
                msg = reader.deserialize(raw, conn.msgtype)
                if conn.topic.startswith(RGB_TOPIC):
                    decode_color(conn.msgtype, msg)
                    frames += 1
                elif conn.topic.startswith(DEPTH_TOPIC):
                    decode_depth(conn.msgtype, msg)
    seconds, cpu = time.perf_counter() - start, time.process_time() - cpu
    return frames / seconds, 1000 * cpu / frames


def format_convert_in_child(name: str, source: Path, out: Path) -> dict:
    kind = "scannet" if name.startswith("ScanNet") else "bag"
    return run_child(_CHILD_FORMAT, kind, source, out)


def format_rows(
    frames: list, short: int, repeats: int, tmp: Path, only: str | None = None
) -> tuple[list, list[str], bool]:
    """Row pairs, summary items and whether every format target was met."""
    long_inputs = make_format_inputs(frames, tmp / "long", only)
    short_inputs = make_format_inputs(frames[:short], tmp / "short", only)
    rows, summary, ok = [], [], True
    for name, source in long_inputs.items():
        decodes, runs = [], []
        for _ in range(repeats):  # alternating, so both sides see the same machine load
            decodes.append(format_decode(name, source))
            runs.append(format_convert_in_child(name, source, tmp / "format.h5"))
        decode, decode_cpu = max(decodes)
        convert = max(r["frames"] / r["seconds"] for r in runs)
        convert_cpu = min(1000 * r["cpu_s"] / r["frames"] for r in runs)
        small = format_convert_in_child(name, short_inputs[name], tmp / "format_short.h5")
        growth = runs[0]["peak_rss_mb"] - small["peak_rss_mb"]
        ratio = convert / decode
        ok &= ratio >= TARGET_CONVERT_RATIO and growth < TARGET_RSS_GROWTH_MB
        rows += [
            (f"{name}: decode only, 1 thread", f"{decode:.1f} frames/s",
             f"reference; CPU {decode_cpu:.1f} ms/frame"),
            (f"{name}: convert, 2 workers", f"{convert:.1f} frames/s",
             f"{ratio:.2f}x decode (target >= {TARGET_CONVERT_RATIO}); CPU "
             f"{convert_cpu:.1f} ms/frame (decode + deflate + write); peak RSS "
             f"{small['peak_rss_mb']:.0f} -> {runs[0]['peak_rss_mb']:.0f} MB for "
             f"{short} -> {len(frames)} frames ({growth:+.1f}, target < {TARGET_RSS_GROWTH_MB})"),
        ]  # fmt: skip
        summary.append(f"{name} {ratio:.2f}x/{growth:+.0f} MB")
    return rows, summary, ok


def tum_rows(tum: Path, plan, repeats: int, tmp: Path) -> tuple[list, str, bool]:  # noqa: ANN001
    """TUM PNG rows, their summary and whether every target was met."""
    n = len(plan.frames)
    pairs = [(tum / f.name.split(" + ")[0], tum / f.name.split(" + ")[1])
             for f in plan.frames]  # fmt: skip
    png_mb = sum(p.stat().st_size for pair in pairs for p in pair) / 2**20
    out = tmp / "seq.h5"
    decode_1 = max(decode_rate(pairs, 1) for _ in range(repeats))
    decode_2 = max(decode_rate(pairs, 2) for _ in range(repeats))
    runs = [convert_in_child(tum, out, n) for _ in range(repeats)]
    convert = max(r["frames"] / r["seconds"] for r in runs)
    store_mb = out.stat().st_size / 2**20
    reads = [read_rates(out) for _ in range(repeats)]
    read_ours, read_plain = (max(r[k] for r in reads) for k in range(2))
    short = convert_in_child(tum, tmp / "short.h5", min(60, n))
    long = convert_in_child(tum, tmp / "long.h5", n)
    growth = long["peak_rss_mb"] - short["peak_rss_mb"]
    ratio = convert / decode_1
    rows = [
        ("decode PNGs only, OpenCV, 1 thread", f"{decode_1:.1f} frames/s", "reference"),
        ("decode PNGs only, OpenCV, 2 threads", f"{decode_2:.1f} frames/s", "context"),
        ("convert (decode+deflate+write), 2 workers", f"{convert:.1f} frames/s",
         f"{ratio:.2f}x decode-1t (target >= {TARGET_CONVERT_RATIO}); "
         f"{convert / decode_2:.2f}x decode-2t"),
        (f"peak RSS converting {min(60, n)} frames", f"{short['peak_rss_mb']:.0f} MB", ""),
        (f"peak RSS converting {n} frames", f"{long['peak_rss_mb']:.0f} MB",
         f"growth {growth:+.1f} MB (target < {TARGET_RSS_GROWTH_MB})"),
        ("store size / source PNG size", f"{store_mb:.1f} / {png_mb:.1f} MB",
         f"ratio {store_mb / png_mb:.2f}"),
        ("read back, FrameStore iteration", f"{read_ours:.1f} frames/s",
         f"target >= {TARGET_READ_FPS}"),
        ("read back, plain h5py single thread", f"{read_plain:.1f} frames/s", "context"),
    ]  # fmt: skip
    summary = (f"convert {convert:.0f} fps = {ratio:.2f}x decode; RSS growth {growth:+.0f} MB; "
               f"read {read_ours:.0f} fps; size ratio {store_mb / png_mb:.2f}")  # fmt: skip
    ok = (ratio >= TARGET_CONVERT_RATIO and growth < TARGET_RSS_GROWTH_MB
          and read_ours >= TARGET_READ_FPS)  # fmt: skip
    return rows, summary, ok


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tum", type=Path, default=DEFAULT_TUM, help="TUM sequence folder")
    parser.add_argument("--repeats", type=int, default=3, help="best of N for each timing")
    parser.add_argument("--only", choices=ONLY_CHOICES, help="run only these rows (default: all)")
    args = parser.parse_args()
    if not (args.tum / "rgb.txt").is_file():
        sys.exit(f"no TUM folder at {args.tum}; pass --tum DIR")

    plan = plan_tum(args.tum, TumOptions())
    n = len(plan.frames)
    rows, summary, ok = [], [], True
    with tempfile.TemporaryDirectory() as tmp:
        if args.only in (None, "tum"):
            tum, tum_summary, ok = tum_rows(args.tum, plan, args.repeats, Path(tmp))
            rows += tum
            summary.append(tum_summary)
        if args.only != "tum":
            frames = load_tum_frames(plan)
            extra, format_summary, format_ok = format_rows(
                frames, min(60, n), args.repeats, Path(tmp), args.only
            )
            rows += extra
            summary.append(f"formats {', '.join(format_summary)}")
            ok &= format_ok

    print(f"bench/convert.py: {args.tum.name}, {n} frames, best of {args.repeats}")
    width = max(len(r[0]) for r in rows)
    for name, value, note in rows:
        print(f"  {name:<{width}}  {value:>20}  {note}")
    print(f"SUMMARY {'; '.join(summary)}; {'all targets met' if ok else 'TARGET MISSED'}")


if __name__ == "__main__":
    with recorded("convert"):
        main()

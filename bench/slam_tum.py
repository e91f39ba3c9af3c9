"""SLAM accuracy and speed on the real TUM fr1/rpy excerpt, side by side with Open3D's dense SLAM.

Usage: .venv/bin/python bench/slam_tum.py [--tum DIR] [--frames N] [--every-frames M]
       [--paper-frames P]

The store is converted and run with the defaults, which give the reference systems' TUM fr1
camera settings (undistorted, 50 px cropped at every border); Open3D reads the same undistorted
store. Rows, all from one run: Open3D's frame-to-model TSDF SLAM (voxel 1 cm, the classical CPU
baseline; in a child process, so that the peak RSS and the speed are bgs's own); bgs `cpu`
preset (surprise keyframes); the keyframe check on the first M frames, a `cpu` run with
surprise keyframes against one mapping every frame (mapping every frame is ~3x slower; both
runs see the same M frames and differ only in `keyframes.mode`, so loop closures that the full
run finds later, and that move its early submaps, do not enter the ratio); bgs `paper` preset
on the first P frames. Targets: ATE ≤ 2.5 cm, ≥ 0.5 fps, keyframes ≤ 35 % with ATE
≤ 1.15× every-frame, peak RSS ≤ 4 GiB. Prints a table and one SUMMARY line.
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import tempfile
from pathlib import Path

from baseline import open3d_dense_slam

from bgs_batch.config import load_config
from bgs_batch.metrics import ate
from bgs_batch.store import FrameStore
from converters.tum import TumOptions, convert_tum
from jobs.run import run_job
from outputs.export import ExportOptions, export_job

from status_page import recorded

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
DEFAULT_TUM = SHARED_DATA / "tum_rgbd" / "rgbd_dataset_freiburg1_rpy"
TARGET_ATE_M = 0.025
TARGET_FPS = 0.5
TARGET_KEYFRAME_SHARE = 0.35
TARGET_EVERY_RATIO = 1.15
TARGET_RSS_GB = 4.0


AUSE_LABELS = {
    "predictive": "full predictive Sigma_D = sensor + map (ours)",
    "map": "map-only (opacity-induced) variance",
    "sensor": "sensor-only variance",
    "varsplat": "VarSplat-style (colour map variance reused for depth)",
}


def depth_ause(job: Path) -> dict[str, float]:
    """Depth AUSE-MAE (raw units) of the four uncertainties, from the job's `bgs eval`."""
    export_job(job, ExportOptions(ply=False, uncertainty=False, renders=False, report=False))
    metrics = json.loads((job / "outputs" / "metrics.json").read_text())
    by_variance = metrics["uncertainty"]["ause_mae_depth_by_variance"]
    return {name: by_variance[name]["ause_raw"] for name in AUSE_LABELS}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tum", type=Path, default=DEFAULT_TUM)
    parser.add_argument("--frames", type=int, default=240)
    parser.add_argument("--every-frames", type=int, default=60)
    parser.add_argument("--paper-frames", type=int, default=30)
    args = parser.parse_args()
    if not (args.tum / "rgb.txt").is_file():
        sys.exit(f"no TUM folder at {args.tum}; pass --tum DIR")

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        store_path = convert_tum(args.tum, Path(tmp) / "seq.h5", TumOptions(max_frames=args.frames))
        with FrameStore(store_path) as store:
            n = len(store)
            gt = store.poses_gt[:, :3, 3]
        poses, seconds, _ = open3d_dense_slam(store_path, n)
        o3d_ate = ate(poses[:, :3, 3], gt)["rmse"]
        o3d_fps = n / seconds
        rows.append(("Open3D dense SLAM (TSDF 1 cm)", n, o3d_ate, o3d_fps, None))

        runs = {}
        every_frames = min(args.every_frames, n)
        for name, preset, sets, frames in (
            ("bgs cpu", "cpu", [], n),
            ("bgs cpu, keyframes", "cpu", [], every_frames),
            ("bgs cpu, map every frame", "cpu", ["keyframes.mode=every"], every_frames),
            ("bgs paper", "paper", [], min(args.paper_frames, n)),
        ):
            job = Path(tmp) / name.replace(" ", "_").replace(",", "")
            cfg = load_config(preset, sets)
            summary = run_job(store_path, job, cfg, max_frames=frames)
            runs[name] = summary
            rows.append((name, frames, summary.ate_rmse_m, summary.fps, summary.keyframes))
            if name == "bgs cpu":
                ause = depth_ause(job)
    rss_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20

    print(f"bench/slam_tum.py: {args.tum.name}, {n} frames")
    print(f"  {'system':<30} {'frames':>6} {'ATE cm':>8} {'fps':>7} {'s/frame':>8} "
          f"{'keyframes':>10} {'fps / Open3D':>12}")  # fmt: skip
    for name, frames, err, fps, kf in rows:
        kf_text = "-" if kf is None else f"{kf} ({kf / frames:.0%})"
        print(f"  {name:<30} {frames:>6} {err * 100:>8.2f} {fps:>7.2f} {1 / fps:>8.2f} "
              f"{kf_text:>10} {fps / o3d_fps:>12.2f}")  # fmt: skip
    cpu, every = runs["bgs cpu"], runs["bgs cpu, map every frame"]
    keyframed = runs["bgs cpu, keyframes"]
    share = cpu.keyframes / cpu.frames
    ratio = keyframed.ate_rmse_m / every.ate_rmse_m
    print(
        f"  keyframe share {share:.0%} (target <= {TARGET_KEYFRAME_SHARE:.0%}); on the first "
        f"{every.frames} frames surprise keyframes {keyframed.ate_rmse_m * 100:.2f} cm vs every "
        f"frame {every.ate_rmse_m * 100:.2f} cm = {ratio:.2f}x (target <= {TARGET_EVERY_RATIO}); "
        f"peak RSS {rss_gb:.2f} GiB"
    )
    print("  depth AUSE-MAE (raw, m) on the cpu run's keyframes, by uncertainty:")
    for variance, value in ause.items():
        print(f"    {variance:<12} {value:.4f}  {AUSE_LABELS[variance]}")
    ause_ok = all(ause["predictive"] < v for k, v in ause.items() if k != "predictive")
    print(f"  predictive lowest: {'yes' if ause_ok else 'NO'}")
    ok = (ause_ok and cpu.ate_rmse_m <= TARGET_ATE_M and cpu.fps >= TARGET_FPS
          and share <= TARGET_KEYFRAME_SHARE and ratio <= TARGET_EVERY_RATIO
          and rss_gb <= TARGET_RSS_GB)  # fmt: skip
    print(
        f"SUMMARY cpu preset ATE {cpu.ate_rmse_m * 100:.2f} cm at {cpu.fps:.2f} fps "
        f"({cpu.fps / o3d_fps:.2f}x Open3D, whose ATE is {o3d_ate * 100:.2f} cm); "
        f"keyframes {share:.0%}; {'all targets met' if ok else 'TARGET MISSED'}"
    )


if __name__ == "__main__":
    with recorded("slam_tum"):
        main()

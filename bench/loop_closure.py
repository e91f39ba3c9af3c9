"""Loop closure on a synthetic loop: ATE with and without it, and what it costs.

Usage: .venv/bin/python bench/loop_closure.py [--frames 90] [--size 160x120] [--drift-deg 1]

Synthesises a room sequence whose camera goes round the same closed path several times (`bgs
synth --loop` with a small path radius), injects odometry drift at every submap switch
(`loop_closure.inject_drift_deg/_m`) and runs the `cpu` preset with submaps every few frames:
without loop closure; with it; with it but a registration that weighs every pixel alike
(`loop_closure.weighting=uniform`, LoopSplat's unweighted loss) instead of by our predictive
variances; and with it on an open path of the same length (half a lap: whatever it accepts
must be a real revisit of a view). "edge cm" is the mean error of the loop edges (from the
last checkpoint) at the query submap's first camera against ground truth, each submap's first
frame taken as its reference. All numbers come from one run. Targets: ATE with loop
closure <= 0.6x without, loop-closure time <= 15 % of the run, loops found on the loop, no
false loop anywhere (a loop is true when ground truth has views of the two submaps within
0.3 m and 30 degrees). Prints a table and one SUMMARY line.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np

from bgs_batch.config import load_config
from bgs_batch.slam.loop_closure.evaluation import accepted_loops, is_true_loop, submap_frames
from bgs_batch.store import FrameStore
from converters.synthetic import SynthConfig, synthesize
from converters.tum import convert_tum
from jobs.checkpoint import load_latest
from jobs.run import RunSummary, run_job

from status_page import recorded

FPS = 10.0  # a handheld pace of 2.5 cm per frame at the default speed
SPEED = 0.25  # m/s
LOOP_RADIUS = 0.2  # m; the path then takes two laps
OPEN_RADIUS = 0.7  # the default room path: half a lap, no revisit
SUBMAP_EVERY = 8  # frames per submap
SMALL_IMAGE_ORB = ["loop_closure.orb_patch=15", "loop_closure.orb_fast_threshold=10"]
TARGET_ATE_RATIO = 0.6
TARGET_TIME_SHARE = 0.15


def make_store(root: Path, frames: int, size: tuple[int, int], seed: int, radius: float,
               loop: bool) -> Path:  # fmt: skip
    folder = synthesize(root / "seq", SynthConfig(frames=frames, width=size[0], height=size[1],
                                                  seed=seed, loop=loop, fps=FPS, speed=SPEED,
                                                  path_radius=radius))  # fmt: skip
    return convert_tum(folder, root / "seq.h5")


def run(store: Path, job: Path, sets: list[str]) -> tuple[RunSummary, list[dict]]:
    summary = run_job(store, job, load_config("cpu", sets))
    events = [json.loads(line) for line in (job / "log.jsonl").read_text().splitlines()]
    return summary, events


def loop_check(events: list[dict], gt: np.ndarray) -> tuple[int, int]:
    """(accepted loop edges, how many of them are true)."""
    loops = accepted_loops(events)
    frames = submap_frames(events)
    true = sum(is_true_loop(gt, frames[q], frames[c]) for _, q, c in loops)
    return len(loops), true


def loop_edge_error(job: Path, events: list[dict], gt: np.ndarray) -> float:
    """Mean camera error (m) of the loop edges in the job's last checkpoint (NaN: none)."""
    latest = load_latest(job)
    if latest is None:
        return float("nan")
    state = latest[1]["slam"]["loop_closure"]
    first: dict[int, int] = {}
    for e in events:
        first.setdefault(e["submap"], e["frame"])

    def logged(i: int) -> np.ndarray:
        return np.vstack([np.reshape(events[i]["pose"], (3, 4)), [0.0, 0.0, 0.0, 1.0]])

    truth = {k: gt[f] @ np.linalg.inv(logged(f)) for k, f in first.items()}  # raw → true world
    errors = []
    for q, c, measured in zip(state["loop_query"].tolist(), state["loop_candidate"].tolist(),
                              state["loop_transform"].numpy(), strict=True):  # fmt: skip
        exact = np.linalg.inv(truth[c]) @ truth[q]
        camera = logged(first[q])
        errors.append(np.linalg.norm((measured @ camera)[:3, 3] - (exact @ camera)[:3, 3]))
    return float(np.mean(errors)) if errors else float("nan")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=90)
    parser.add_argument("--size", default="160x120")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--drift-deg", type=float, default=1.0)
    parser.add_argument("--drift-m", type=float, default=0.01)
    args = parser.parse_args()
    size = tuple(int(x) for x in args.size.split("x"))
    common = ["submaps.mode=interval", f"submaps.every={SUBMAP_EVERY}", *SMALL_IMAGE_ORB,
              f"loop_closure.inject_drift_deg={args.drift_deg}",
              f"loop_closure.inject_drift_m={args.drift_m}"]  # fmt: skip

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        store = make_store(root / "loop", args.frames, size, args.seed, LOOP_RADIUS, True)
        with FrameStore(store) as opened:
            gt = np.linalg.inv(opened.poses_gt[0]) @ opened.poses_gt
        results = {}
        for name, extra in (("without loop closure", ["loop_closure.enabled=false"]),
                            ("with loop closure", []),
                            ("with loop closure, uniform", ["loop_closure.weighting=uniform"])
                            ):  # fmt: skip
            job = root / name.replace(" ", "_").replace(",", "")
            summary, events = run(store, job, [*common, *extra])
            results[name] = (summary, events)
            rows.append((name, summary, *loop_check(events, gt),
                         loop_edge_error(job, events, gt)))  # fmt: skip
        open_store = make_store(root / "open", args.frames, size, args.seed, OPEN_RADIUS, False)
        with FrameStore(open_store) as opened:
            open_gt = np.linalg.inv(opened.poses_gt[0]) @ opened.poses_gt
        summary, events = run(open_store, root / "open_job", common)
        rows.append(("open path, with loop closure", summary, *loop_check(events, open_gt),
                     loop_edge_error(root / "open_job", events, open_gt)))  # fmt: skip

    print(f"bench/loop_closure.py: synthetic room, {args.frames} frames {args.size}, submaps "
          f"every {SUBMAP_EVERY}, drift {args.drift_deg} deg + {args.drift_m * 100:.0f} cm "
          f"per submap")  # fmt: skip
    print(f"  {'run':<30} {'ATE cm':>7} {'s':>7} {'LC s':>6} {'LC share':>8} {'loops':>5} "
          f"{'true':>5} {'false':>5} {'edge cm':>7}")  # fmt: skip
    for name, s, loops, true, edge in rows:
        lc = s.stage_seconds["loop_closure"]
        print(f"  {name:<30} {s.ate_rmse_m * 100:>7.2f} {s.seconds:>7.1f} {lc:>6.1f} "
              f"{lc / s.seconds:>8.1%} {loops:>5} {true:>5} {loops - true:>5} "
              f"{edge * 100:>7.2f}")  # fmt: skip
    off, on = results["without loop closure"][0], results["with loop closure"][0]
    uniform = results["with loop closure, uniform"][0]
    ratio = on.ate_rmse_m / off.ate_rmse_m
    share = on.stage_seconds["loop_closure"] / on.seconds
    _, _, loops, true, _ = rows[1]
    false = sum(n - t for _, _, n, t, _ in rows)
    ok = (ratio <= TARGET_ATE_RATIO and share <= TARGET_TIME_SHARE and loops > 0
          and false == 0)  # fmt: skip
    print(
        f"SUMMARY loop closure ATE {on.ate_rmse_m * 100:.2f} cm vs {off.ate_rmse_m * 100:.2f} "
        f"cm without ({ratio:.2f}x, target <= {TARGET_ATE_RATIO}; unweighted registration "
        f"{uniform.ate_rmse_m * 100:.2f} cm); {share:.1%} of the run "
        f"(target <= {TARGET_TIME_SHARE:.0%}); {true}/{loops} loops true, {false} false loops "
        f"in all runs; {'all targets met' if ok else 'TARGET MISSED'}"
    )


if __name__ == "__main__":
    with recorded("loop_closure"):
        main()

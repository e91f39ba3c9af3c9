"""The README's first picture: a frame the global stage held out, as the camera saw it, beside
``global.ply`` rendered at ``trajectory.txt``'s pose (what `bgs eval` scores).

Usage: .venv/bin/python scripts/held_out_figure.py JOB OUT.png [--frame N]

JOB is a finished `bgs run` job directory (the README's picture: the fr1/rpy excerpt in
``../shared/data`` run with the defaults); without --frame the held-out frame whose PSNR is the
median of the job's held-out frames is shown, so the picture is neither the best nor the worst.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

from bgs_batch.store import FrameStore
from outputs.colormap import grid, rgb_to_bgr8, tile, write_png
from outputs.image_metrics import psnr
from outputs.jobfiles import FinishedJob
from outputs.uncertainty import UncertaintyRenderer


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("job", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--frame", type=int, help="a held-out frame [default: the median one]")
    args = parser.parse_args()
    job = FinishedJob(args.job)
    held_out = job.global_map.held_out_frames
    if not held_out or (args.frame is not None and args.frame not in held_out):
        sys.exit(f"held_out_figure.py: pick one of the held-out frames {held_out}")
    with FrameStore(job.store_path()) as store:
        renderer = UncertaintyRenderer(job, store, 1, global_map=True)
        items = [renderer.frame(i) for i in ([args.frame] if args.frame is not None else held_out)]
    scores = [psnr(torch.from_numpy(i.rendered_rgb), torch.from_numpy(i.measured_rgb))
              for i in items]  # fmt: skip
    item = items[int(np.argsort(scores)[len(scores) // 2])]
    score = scores[items.index(item)]
    write_png(args.out, grid([[
        tile(rgb_to_bgr8(item.measured_rgb), f"camera, frame {item.frame} (held out)"),
        tile(rgb_to_bgr8(item.rendered_rgb), f"global.ply at trajectory.txt, {score:.1f} dB"),
    ]]))  # fmt: skip
    print(f"wrote {args.out}: frame {item.frame}, PSNR {score:.2f} dB")


if __name__ == "__main__":
    main()

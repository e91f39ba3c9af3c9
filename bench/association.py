"""RGB-depth association on the real TUM pieces: frames kept and the largest |dt| of a kept pair,
for TUM's greedy nearest-first matching (`associate.py`) and ours (order-preserving, most pairs).

Usage: .venv/bin/python bench/association.py [--data DIR]

Reads only the list files. Prints a table and one SUMMARY line.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from converters.association import associate
from converters.tum import read_file_list

from status_page import recorded

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "tum_rgbd"
TOLERANCES = (0.02, 0.04, 0.08)


def greedy(first: np.ndarray, second: np.ndarray, tolerance: float) -> np.ndarray:
    """TUM's associate.py: every pair within `tolerance`, nearest first, each stamp used once."""
    gaps = np.abs(first[:, None] - second[None, :])
    i, j = np.nonzero(gaps <= tolerance)
    used_first, used_second, pairs = set(), set(), []
    for k in np.lexsort((j, i, gaps[i, j])):
        if i[k] not in used_first and j[k] not in used_second:
            used_first.add(i[k])
            used_second.add(j[k])
            pairs.append((i[k], j[k]))
    return np.asarray(sorted(pairs), np.int64).reshape(-1, 2)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=SHARED_DATA)
    args = parser.parse_args()
    folders = sorted(p.parent for p in args.data.rglob("rgb.txt"))
    if not folders:
        sys.exit(f"no TUM folders below {args.data}; pass --data DIR")
    print(f"  {'sequence':<40} {'tol s':>5} {'greedy kept':>12} {'max dt ms':>9} "
          f"{'ours kept':>10} {'max dt ms':>9}")  # fmt: skip
    lost = {"greedy": 0, "ours": 0}
    for folder in folders:
        rgb, _ = read_file_list(folder / "rgb.txt")
        depth, _ = read_file_list(folder / "depth.txt")
        for tolerance in TOLERANCES:
            row = []
            for name, match in (("greedy", greedy), ("ours", associate)):
                pairs = match(rgb, depth, tolerance)
                gap = np.abs(rgb[pairs[:, 0]] - depth[pairs[:, 1]]).max() * 1e3
                row += [f"{len(pairs)}/{len(rgb)}", f"{gap:.1f}"]
                if tolerance == TOLERANCES[0]:
                    lost[name] += len(rgb) - len(pairs)
            print(f"  {folder.name:<40} {tolerance:>5} {row[0]:>12} {row[1]:>9} {row[2]:>10} "
                  f"{row[3]:>9}")  # fmt: skip
    print(f"SUMMARY at the default {TOLERANCES[0]} s: greedy drops {lost['greedy']} RGB frames, "
          f"ours {lost['ours']}, over {len(folders)} sequences")


if __name__ == "__main__":
    with recorded("association"):
        main()

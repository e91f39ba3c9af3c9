"""Checkpoints of a running job: atomic, checksummed, the newest two kept (docs/usage.md).

A checkpoint is one file ``checkpoints/<frames done>-<end-of-run steps>-<sha256 prefix>.pt``
(the steps are 0 while frames are processed, then 1 + the global stage's visits done) written with
`bgs_batch.atomic`, so a crash never leaves a half-written file under a final name, and a file
damaged later (truncated copy, full disk) fails its checksum and is skipped in favour of the
previous one. Contents are tensors and plain values: ``torch.load(weights_only=True)``.
"""

from __future__ import annotations

import hashlib
import io
import logging
from pathlib import Path
from typing import Any

import torch

from bgs_batch import atomic

CHECKPOINT_DIR = "checkpoints"
KEEP = 2
DIGEST_CHARS = 16

log = logging.getLogger(__name__)


def write_checkpoint(job_dir: Path, frames_done: int, state: dict[str, Any],
                     end_steps: int = 0) -> Path:  # fmt: skip
    """Write the state after `frames_done` frames and `end_steps` steps of the run's end (see
    the module docstring); keep only the newest `KEEP` checkpoints."""
    folder = job_dir / CHECKPOINT_DIR
    folder.mkdir(exist_ok=True)
    buffer = io.BytesIO()
    torch.save({"frames_done": frames_done, "state": state}, buffer)
    data = buffer.getvalue()
    digest = hashlib.sha256(data).hexdigest()[:DIGEST_CHARS]
    path = folder / f"{frames_done:08d}-{end_steps:08d}-{digest}.pt"
    atomic.write_bytes(path, data)  # e.g. disk full: the previous checkpoints stay intact
    for old in sorted(folder.glob("*.pt"))[:-KEEP]:
        old.unlink()
    return path


def load_latest(job_dir: Path) -> tuple[int, dict[str, Any]] | None:
    """(frames done, state) of the newest valid checkpoint, or None; damaged ones are reported."""
    for path in sorted((job_dir / CHECKPOINT_DIR).glob("*.pt"), reverse=True):
        data = path.read_bytes()
        digest = path.stem.rsplit("-", 1)[-1]
        if hashlib.sha256(data).hexdigest()[:DIGEST_CHARS] != digest:
            log.warning("checkpoint %s is damaged (checksum mismatch); using an older one", path)
            continue
        payload = torch.load(io.BytesIO(data), weights_only=True)
        return int(payload["frames_done"]), payload["state"]
    return None

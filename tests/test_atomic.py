"""The one all-or-nothing writer: old or new output, never half, durable, and no debris."""

import errno
import os
from pathlib import Path

import pytest

from bgs_batch import atomic
from bgs_batch.atomic import TEMP_PREFIX, atomic_dir, atomic_file


def _debris(folder: Path) -> list[str]:
    return [p.name for p in folder.iterdir() if p.name.startswith(TEMP_PREFIX)]


def test_a_file_keeps_the_old_content_on_failure_and_takes_the_new_on_success(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError), atomic_file(target) as tmp:
        tmp.write_text("half")
        raise RuntimeError("crash")
    assert target.read_text() == "old"
    with atomic_file(target) as tmp:
        tmp.write_text("new")
    assert target.read_text() == "new"
    assert _debris(tmp_path) == []
    assert target.stat().st_mode & 0o077 != 0  # usual permissions, not mkstemp's 0600


def test_a_folder_is_replaced_as_a_whole(tmp_path):
    folder = tmp_path / "dir"
    folder.mkdir()
    (folder / "stale.png").write_text("x")
    with pytest.raises(RuntimeError), atomic_dir(folder) as tmp:
        (tmp / "a.png").write_text("half")
        raise RuntimeError("crash")
    assert sorted(p.name for p in folder.iterdir()) == ["stale.png"]
    with atomic_dir(folder) as tmp:
        (tmp / "a.png").write_text("new")
    assert sorted(p.name for p in folder.iterdir()) == ["a.png"]  # no earlier file lingers
    assert _debris(tmp_path) == []


def test_a_symlinked_folder_is_replaced_and_its_target_left_alone(tmp_path):
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "keep.txt").write_text("x")
    link = tmp_path / "out"
    link.symlink_to(elsewhere)
    with atomic_dir(link) as tmp:
        (tmp / "new.txt").write_text("y")
    assert not link.is_symlink() and (link / "new.txt").exists()
    assert (elsewhere / "keep.txt").read_text() == "x"
    assert _debris(tmp_path) == []


def test_a_full_disk_at_the_rename_keeps_the_old_file_and_removes_the_temporary(
    tmp_path, monkeypatch
):
    target = tmp_path / "state.pt"
    target.write_bytes(b"old")

    def full(*_args):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "replace", full)
    with pytest.raises(OSError, match="No space"):
        atomic.write_bytes(target, b"new")
    assert target.read_bytes() == b"old"
    assert _debris(tmp_path) == []


def test_the_data_is_flushed_before_the_rename_and_the_folder_after_it(tmp_path, monkeypatch):
    events: list[tuple[str, str]] = []
    real_replace, real_fsync = os.replace, atomic.fsync_path
    monkeypatch.setattr(os, "replace", lambda a, b: (events.append(("replace", Path(b).name)),
                                                      real_replace(a, b))[1])  # fmt: skip
    monkeypatch.setattr(atomic, "fsync_path", lambda p: (events.append(("fsync", Path(p).name)),
                                                         real_fsync(p))[1])  # fmt: skip
    atomic.write_text(tmp_path / "job.json", "{}")
    names = [name for _, name in events]
    assert [kind for kind, _ in events] == ["fsync", "replace", "fsync"]
    assert names[0].startswith(TEMP_PREFIX) and names[1:] == ["job.json", tmp_path.name]

    events.clear()
    with atomic_dir(tmp_path / "ply") as tmp:
        (tmp / "map.ply").write_text("ply")
    kinds = [kind for kind, _ in events]
    assert ("fsync", "map.ply") in events
    assert kinds.index("replace") > events.index(("fsync", "map.ply"))
    assert events[-1] == ("fsync", tmp_path.name)


def test_the_same_torch_object_gives_the_same_bytes_under_any_name(tmp_path):
    import torch

    state = {"weight": torch.arange(6.0).reshape(2, 3), "step": torch.tensor(7)}
    atomic.save_torch(state, tmp_path / "a.pt")
    atomic.save_torch(state, tmp_path / "sensor_net.pt")
    assert (tmp_path / "a.pt").read_bytes() == (tmp_path / "sensor_net.pt").read_bytes()
    loaded = torch.load(tmp_path / "a.pt", weights_only=True)
    assert torch.equal(loaded["weight"], state["weight"]) and _debris(tmp_path) == []

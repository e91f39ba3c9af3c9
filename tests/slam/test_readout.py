"""The rolling-shutter readout estimated from the frames (`bgs_batch.slam.readout`): recovered on
synthetic rooms whose readout `bgs synth` simulates, none on a global shutter or a static camera,
made once per job and kept across a resume."""

import json
import math
import os
import signal

import numpy as np
import pytest

import jobs.run
from bgs_batch.config import for_store, load_config
from bgs_batch.slam.readout import estimate_readout
from bgs_batch.store import FrameStore
from converters.synthetic import motion_config, synthesize
from converters.tum import TumOptions, convert_tum
from jobs.preemption import Preempted
from jobs.run import READOUT_FILE, run_job
from jobs.status import job_status
from outputs.jobfiles import FinishedJob

SIMULATED_S = 0.9 / 30  # `bgs synth --rolling-shutter`: 0.9 of a 30 Hz frame


def synthetic_store(root, motion, effects, seed, readout=math.nan, frames=40, depth=None):
    config = motion_config(motion, effects, frames=frames, width=320, height=240, seed=seed)
    folder = synthesize(root / motion, config)
    options = TumOptions(readout=readout, depth_readout=depth)
    return convert_tum(folder, root / f"{motion}.h5", options)


def estimate(store_path):
    """As `bgs run` estimates it: the readouts the store leaves open (`for_store`)."""
    with FrameStore(store_path) as store:
        cfg, _ = for_store(load_config("cpu"), store)
        return estimate_readout(store.__getitem__, store.timestamps, store.intrinsics, cfg)


@pytest.mark.slow
@pytest.mark.parametrize(("motion", "effects", "depth", "truth"), [
    ("handheld", ("rolling_shutter",), None, SIMULATED_S),
    ("shake", ("rolling_shutter",), None, SIMULATED_S),
    # a RealSense D435-like camera: the colour readout, with the depth's known to be 0
    ("shake", ("rolling_shutter", "global_shutter_depth"), 0.0, SIMULATED_S),
    ("shake", (), None, 0.0)])  # fmt: skip
def test_the_simulated_readout_is_recovered(tmp_path, motion, effects, depth, truth):
    found = estimate(synthetic_store(tmp_path, motion, effects, seed=31, depth=depth))
    assert found.seconds is not None, found.reason
    assert abs(found.seconds - truth) <= 0.15 * SIMULATED_S, found
    assert found.standard_error < 0.1 * SIMULATED_S and len(found.pairs) >= 4
    assert all(0 < k < j < 39 for k, j in found.pairs)  # both have neighbours for a velocity


def test_a_static_camera_says_unknown(tmp_path):
    store_path = synthetic_store(tmp_path, "handheld", ("rolling_shutter",), seed=32, frames=12)
    with FrameStore(store_path) as store:
        first = store[0]
        cfg = load_config("cpu")
        found = estimate_readout(lambda i: first, store.timestamps, store.intrinsics, cfg)
    assert found.seconds is None and found.pairs == []
    assert "did not turn enough" in found.reason


def test_too_few_frames_say_unknown(tmp_path):
    found = estimate(synthetic_store(tmp_path, "handheld", (), seed=33, frames=2))
    assert found.seconds is None and "too few" in found.reason


@pytest.mark.slow
def test_a_job_estimates_once_records_it_and_a_rerun_keeps_it(tmp_path, monkeypatch):
    store = synthetic_store(tmp_path, "shake", ("rolling_shutter",), seed=34, frames=24)
    cfg = load_config("cpu", ["tracking.iterations=8", "mapping.iterations=4",
                              "mapping.new_submap_iterations=8", "global_map.passes=1"])
    summary = run_job(store, tmp_path / "job", cfg, max_frames=24)
    recorded = json.loads((tmp_path / "job" / READOUT_FILE).read_text())
    assert summary.readout == recorded and recorded["seconds"] is not None
    assert abs(recorded["seconds"] - SIMULATED_S) <= 0.2 * SIMULATED_S
    sources = json.loads((tmp_path / "job" / "config.json").read_text())["sources"]
    assert sources["rolling_shutter_readout"].startswith("estimated from the frames")
    assert job_status(tmp_path / "job").readout == recorded["reason"]
    events = [json.loads(x) for x in (tmp_path / "job" / "log.jsonl").read_text().splitlines()]
    assert any(e.get("readout_motion") for e in events)  # the frames were rectified

    def again(*_args):
        raise AssertionError("estimated twice")

    monkeypatch.setattr("jobs.run.estimate_readout", again)
    (tmp_path / "job" / "summary.json").unlink()  # as if stopped before its end
    assert run_job(store, tmp_path / "job", cfg, max_frames=24).readout == recorded
    monkeypatch.undo()
    (tmp_path / "job" / READOUT_FILE).write_text("{")  # damaged by hand
    assert job_status(tmp_path / "job").readout is None  # no traceback
    (tmp_path / "job" / "summary.json").unlink()
    assert run_job(store, tmp_path / "job", cfg, max_frames=24).readout == recorded  # again
    assert json.loads((tmp_path / "job" / READOUT_FILE).read_text()) == recorded


def test_a_stop_during_the_estimate_keeps_it_and_stops_before_the_first_frame(
        tmp_path, monkeypatch):  # fmt: skip
    store = synthetic_store(tmp_path, "shake", ("rolling_shutter",), seed=35, frames=8)
    real = jobs.run.estimate_readout

    def stopped(*args):
        found = real(*args)
        os.kill(os.getpid(), signal.SIGTERM)
        return found

    monkeypatch.setattr(jobs.run, "estimate_readout", stopped)
    cfg = load_config("cpu", ["global_map.passes=0"])
    with pytest.raises(Preempted, match="after the readout estimate"):
        run_job(store, tmp_path / "job", cfg)
    assert (tmp_path / "job" / READOUT_FILE).exists()
    assert not (tmp_path / "job" / "log.jsonl").exists()  # no frame was tracked


@pytest.mark.slow
def test_a_depth_read_out_apart_gets_its_own_motion_in_the_log_and_the_exports(tmp_path):
    config = motion_config("shake", ("rolling_shutter",), frames=8, width=160, height=120,
                           seed=36)  # fmt: skip
    folder = synthesize(tmp_path / "seq", config)
    (folder / "readout.txt").write_text("0.03 0.012\n")  # colour and depth read out apart
    store = convert_tum(folder, tmp_path / "s.h5")
    cfg = load_config("cpu", ["tracking.iterations=4", "mapping.iterations=2",
                              "mapping.new_submap_iterations=4", "global_map.passes=0"])
    run_job(store, tmp_path / "job", cfg)
    events = [json.loads(x) for x in (tmp_path / "job" / "log.jsonl").read_text().splitlines()]
    assert "first_depth_readout_motion" in events[1] and "first_readout_motion" in events[1]
    assert all("depth_readout_motion" in e and "readout_motion" in e for e in events[1:])
    colour, depth = (np.array(events[3][key]) for key in ("readout_motion", "depth_readout_motion"))
    # the same velocity over 12 ms instead of 30: the rotation angle scales with the readout
    angle = [np.arccos((np.trace(m.reshape(3, 4)[:, :3]) - 1) / 2) for m in (colour, depth)]
    assert angle[1] == pytest.approx(angle[0] * 0.012 / 0.03, rel=1e-6)
    read = FinishedJob(tmp_path / "job").events
    assert read[0].depth_readout_motion is not None  # the first keyframe, as re-mapped
    assert read[3].readouts[1] is not None

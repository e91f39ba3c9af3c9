"""The rolling-shutter readout estimated from the frames (`bgs_batch.slam.readout`): recovered on
synthetic rooms whose readout `bgs synth` simulates, none on a global shutter or a static camera,
made once per job and kept across a resume."""

import dataclasses
import json
import math
import os
import signal

import pytest

import jobs.run
from bgs_batch.config import load_config
from bgs_batch.slam.readout import estimate_readout
from bgs_batch.store import FrameStore
from converters.synthetic import motion_config, synthesize
from converters.tum import TumOptions, convert_tum
from jobs.preemption import Preempted
from jobs.run import READOUT_FILE, run_job
from jobs.status import job_status

SIMULATED_S = 0.9 / 30  # `bgs synth --rolling-shutter`: 0.9 of a 30 Hz frame


def synthetic_store(root, motion, effects, seed, readout=math.nan, frames=40):
    config = motion_config(motion, effects, frames=frames, width=320, height=240, seed=seed)
    folder = synthesize(root / motion, config)
    return convert_tum(folder, root / f"{motion}.h5", TumOptions(readout=readout))


def estimate(store_path, **settings):
    cfg = load_config("cpu")
    cfg = dataclasses.replace(cfg, readout_estimation=dataclasses.replace(
        cfg.readout_estimation, **settings))  # fmt: skip
    with FrameStore(store_path) as store:
        return estimate_readout(store.__getitem__, store.timestamps, store.intrinsics, cfg)


@pytest.mark.slow
@pytest.mark.parametrize(("motion", "effects", "truth"), [
    ("handheld", ("rolling_shutter",), SIMULATED_S),
    ("shake", ("rolling_shutter",), SIMULATED_S),
    ("shake", (), 0.0)])  # fmt: skip
def test_the_simulated_readout_is_recovered(tmp_path, motion, effects, truth):
    found = estimate(synthetic_store(tmp_path, motion, effects, seed=31))
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

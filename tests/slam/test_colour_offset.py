"""The colour camera's offset from the depth camera (`bgs_batch.slam.colour_offset`,
`colour_registration`): undone exactly where it is known, recovered on a synthetic room whose
colour camera `bgs synth --misregister` turns and zooms, none on a registered room, made once per
job and seen by the exports."""

import dataclasses
import json
import shutil
from types import SimpleNamespace

import h5py
import numpy as np
import pytest
import torch

from bgs_batch.config import ColourOffsetConfig, for_store, load_config, needs_colour_offset
from bgs_batch.slam.colour_offset import estimate_colour_offset
from bgs_batch.slam.colour_registration import register_colour
from bgs_batch.store import FrameStore
from converters.synthetic import EFFECTS, motion_config, synthesize
from converters.tum import TumOptions, convert_tum
from jobs.run import COLOUR_OFFSET_FILE, run_job
from jobs.status import job_status
from outputs.jobfiles import FinishedJob

# `bgs synth --misregister`: the colour camera's pose in the depth camera's frame, as a rotation
# vector (°), and its focal length; the offset that undoes it turns the other way
SIMULATED = EFFECTS["misregister"]
TRUE_ROTATION = -np.array(SIMULATED["colour_offset"][:3])
TRUE_FOCAL = SIMULATED["colour_focal_ratio"]
SEED = 7606  # the validation suite's reg/misreg rooms


@pytest.fixture(scope="module")
def rooms(tmp_path_factory):
    """The same handheld room seen by a registered and by a misregistered colour camera."""
    root = tmp_path_factory.mktemp("rooms")
    stores = {}
    for name, effects in (("reg", ()), ("misreg", ("misregister",))):
        config = motion_config("handheld", effects, frames=60, width=320, height=240, seed=SEED)
        stores[name] = convert_tum(synthesize(root / name, config), root / f"{name}.h5",
                                   TumOptions())  # fmt: skip
    return stores


def estimate(store_path, settings=()):
    with FrameStore(store_path) as store:
        cfg, _ = for_store(load_config("cpu", list(settings)), store)
        return estimate_colour_offset(store.__getitem__, store.timestamps, store.intrinsics, cfg)


@pytest.mark.slow
def test_the_known_offset_puts_the_colour_on_the_registered_camera_s_pixels(rooms):
    with FrameStore(rooms["reg"]) as reg, FrameStore(rooms["misreg"]) as misreg:
        x, y, z = TRUE_ROTATION
        offset = ColourOffsetConfig(rotation_x_deg=x, rotation_y_deg=y, rotation_z_deg=z,
                                    focal_ratio=TRUE_FOCAL)  # fmt: skip
        inner = (slice(20, -20), slice(20, -20))  # the borders leave the colour image
        for i in (5, 25):
            truth = reg[i].rgb.astype(np.float64)[inner]
            before = np.abs(misreg[i].rgb.astype(np.float64)[inner] - truth).mean()
            moved = register_colour(misreg[i].rgb, misreg.intrinsics, offset)
            after = np.abs(moved.astype(np.float64)[inner] - truth).mean()
            assert after < before / 3, (before, after)  # the 6 mm shift is not modelled
        assert np.array_equal(register_colour(reg[5].rgb, reg.intrinsics, ColourOffsetConfig()),
                              reg[5].rgb)  # fmt: skip


@pytest.mark.slow
def test_the_offset_is_recovered_and_a_registered_camera_left_alone(rooms):
    found = estimate(rooms["misreg"])
    assert found.rotation_deg is not None, found.reason
    assert np.abs(np.array(found.rotation_deg) - TRUE_ROTATION).max() < 0.5, found.reason
    assert abs(found.focal_ratio - TRUE_FOCAL) < 0.01, found.reason
    assert found.standard_error_deg < 0.25 and "colour camera offset" in found.reason
    registered = estimate(rooms["reg"])  # found at ~0.1°, within the pairs' spread, or not found
    assert registered.rotation_deg is None and registered.focal_ratio is None
    assert "used as they are" in registered.reason or "sits on" in registered.reason


@pytest.mark.slow
def test_a_fit_beyond_a_mounting_offset_is_no_estimate(rooms):
    """With the plausible offsets narrowed to ±0.5°, the misregistered room's 1.5° turn is
    refused by name, and the images stay as they are."""
    found = estimate(rooms["misreg"], ["colour_offset.max_rotation_deg=0.5"])
    assert found.rotation_deg is None and "no mounting offset (beyond ±0.5°" in found.reason


def test_too_few_frames_give_no_estimate(rooms):
    with FrameStore(rooms["reg"]) as store:
        cfg, _ = for_store(load_config("cpu"), store)
        found = estimate_colour_offset(store.__getitem__, store.timestamps[:12],
                                       store.intrinsics, cfg)  # fmt: skip
    assert found.rotation_deg is None and "too few" in found.reason


@pytest.mark.slow
def test_a_run_estimates_once_records_it_and_the_exports_see_it(rooms, tmp_path):
    tiny = ["mapping.iterations=4", "mapping.new_submap_iterations=8", "tracking.iterations=8",
            "global_map.passes=0"]  # fmt: skip
    job = tmp_path / "job"
    summary = run_job(rooms["misreg"], job, load_config("cpu", tiny), max_frames=60)
    recorded = json.loads((job / COLOUR_OFFSET_FILE).read_text())
    assert summary.colour_offset == recorded and recorded["rotation_deg"] is not None
    offset = FinishedJob(job).config.colour_offset
    assert (offset.rotation_y_deg, offset.focal_ratio) == (recorded["rotation_deg"][1],
                                                           recorded["focal_ratio"])  # fmt: skip
    assert "colour camera offset" in job_status(job).colour_offset
    # a damaged record is estimated again, to the same value
    (job / COLOUR_OFFSET_FILE).write_text("{")
    (job / "summary.json").unlink()
    run_job(rooms["misreg"], job, load_config("cpu", tiny), max_frames=60)
    assert json.loads((job / COLOUR_OFFSET_FILE).read_text()) == recorded
    # the paper preset uses the images as they are; a hand-set offset is not estimated again
    paper = tmp_path / "paper"
    run_job(rooms["misreg"], paper, load_config("paper", [*tiny, "tracking.iterations=2"]),
            max_frames=3)  # fmt: skip
    assert not (paper / COLOUR_OFFSET_FILE).exists()
    hand = load_config("cpu", [*tiny, "colour_offset.rotation_y_deg=-1.5"])
    run_job(rooms["misreg"], tmp_path / "hand", hand, max_frames=3)
    assert not (tmp_path / "hand" / COLOUR_OFFSET_FILE).exists()
    assert dataclasses.asdict(FinishedJob(tmp_path / "hand").config.colour_offset)[
        "rotation_y_deg"] == -1.5
    # a store whose depth the recording registered to colour (TUM, aligned bag topics) is
    # taken at its word: nothing to estimate, and config.json says why
    registered = tmp_path / "registered.h5"
    shutil.copy(rooms["misreg"], registered)
    with h5py.File(registered, "a") as f:
        f.attrs["depth_registered"] = True
    run_job(registered, tmp_path / "reg", load_config("cpu", tiny), max_frames=3)
    assert not (tmp_path / "reg" / COLOUR_OFFSET_FILE).exists()
    sources = json.loads((tmp_path / "reg" / "config.json").read_text())["sources"]
    assert "registered" in sources["colour_offset.estimate"]


def test_a_registered_store_turns_the_estimate_off_unless_the_offset_is_set_by_hand(tmp_path):
    def facts(registered):
        return SimpleNamespace(path=tmp_path / "s.h5", crop_edge=0, rolling_shutter_readout=0.0,
                               depth_rolling_shutter_readout=0.0, depth_registered=registered)

    store = facts(True)
    cfg, sources = for_store(load_config("cpu"), store)
    assert not needs_colour_offset(cfg) and "s.h5" in sources["colour_offset.estimate"]
    cfg, sources = for_store(load_config("cpu"), facts(False))
    assert needs_colour_offset(cfg) and "colour_offset.estimate" not in sources
    hand = load_config("cpu", ["colour_offset.rotation_x_deg=0.5"])
    cfg, sources = for_store(hand, store)  # the hand-set offset stays applied
    assert cfg.colour_offset == hand.colour_offset and "colour_offset.estimate" not in sources


def test_the_estimator_moves_each_image_by_its_own_readout(tmp_path):
    """Its views are rectified as the run rectifies frames: a depth image read out with the
    colour one moves with it (left as read, the two would disagree like a turned colour camera),
    a global-shutter depth image stays as read."""
    from bgs_batch.slam.colour_offset import _rectified_views
    from bgs_batch.slam.readout import FrameViews

    config = motion_config("shake", ("rolling_shutter",), frames=6, width=160, height=120,
                           seed=7)  # fmt: skip
    store_path = convert_tum(synthesize(tmp_path / "seq", config), tmp_path / "seq.h5",
                             TumOptions())  # fmt: skip
    with FrameStore(store_path) as store:
        both, _ = for_store(load_config("cpu"), store)
        assert both.rolling_shutter_readout == both.depth_rolling_shutter_readout > 0
        mixed = dataclasses.replace(both, depth_rolling_shutter_readout=0.0)
        raw = FrameViews(store.__getitem__, store.intrinsics, both,
                         both.colour_offset.min_width).view(store[2])  # fmt: skip
        for cfg, depth_moves in ((both, True), (mixed, False)):
            view = _rectified_views(store.__getitem__, store.timestamps, store.intrinsics, cfg,
                                    len(store))[2]  # fmt: skip
            assert not torch.equal(view.gray, raw.gray)
            assert torch.equal(view.depth, raw.depth) is not depth_moves

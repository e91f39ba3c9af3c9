"""Exports of a real (tiny) SLAM run: the end-of-run export, metrics.json, the report, the
uncertainty HDF5 file and PNGs, `bgs eval` / `bgs export` options and their errors."""

import base64
import json
import re
import shutil

import cv2
import h5py
import numpy as np
import pytest
import torch
from click.testing import CliRunner

from bgs_batch.cli import main
from bgs_batch.config import load_config
from bgs_batch.slam.frames import prepare_frame
from bgs_batch.store import FrameStore
from converters.pipeline import write_store
from converters.synthetic import SynthConfig, synthesize
from converters.tum import TumOptions, convert_tum, plan_tum
from outputs.ause import colour_sparsification
from outputs.jobfiles import FinishedJob
from outputs.lpips import Lpips
from outputs.uncertainty import UncertaintyRenderer
from outputs.uncertainty_images import QUANTITIES

SIZE = (96, 72)
FRAMES = 8
TINY = ["tracking.iterations=8", "mapping.iterations=4", "mapping.new_submap_iterations=8",
        "seeding.new_submap_points=2000", "seeding.new_submap_gradient_points=500",
        "seeding.new_frame_points=500", "keyframes.max_gap=3",
        # the synthetic depth is taken 4 ms after the colour: the exports must prepare the
        # frames as the run did, depth moved to the colour's time
        "align_depth_time=true"]  # fmt: skip


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def run_args(store, job, *extra):
    return ["-q", "run", store, "--job-dir", job, *sum((["--set", s] for s in TINY), []), *extra]


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """(store, job) of a tiny synthetic run made by `bgs run`, so exported at its end."""
    root = tmp_path_factory.mktemp("export")
    folder = synthesize(root / "seq", SynthConfig(frames=FRAMES, width=SIZE[0], height=SIZE[1],
                                                  seed=2))  # fmt: skip
    store = convert_tum(folder, root / "seq.h5")
    job = root / "job"
    result = run(*run_args(store, job))
    assert result.exit_code == 0, result.output
    return store, job


@pytest.fixture
def copy(finished, tmp_path):
    """A private copy of the finished job (tests that change or break it)."""
    store, job = finished
    shutil.copytree(job, tmp_path / "job")
    return store, tmp_path / "job"


def events(job):
    return [json.loads(line) for line in (job / "log.jsonl").read_text().splitlines()]


def keyframes(job):
    return [e["frame"] for e in events(job) if e["keyframe"]]


def test_run_exports_once_by_default(finished):
    store, job = finished
    out = job / "outputs"
    for name in ("ply/global.ply", "trajectory/gt.tum", "trajectory/estimate_aligned.tum",
                 "uncertainty.h5", "metrics.json", "report.html"):  # fmt: skip
        assert (out / name).is_file(), name
    assert not (out / "renders").exists()  # the end-of-run export skips the PNG renders
    assert not [p for p in out.rglob("*") if p.name.startswith(".tmp-")]
    before = (out / "metrics.json").stat().st_mtime_ns
    again = run(*run_args(store, job))
    assert again.exit_code == 0 and "up to date" in again.output
    assert (out / "metrics.json").stat().st_mtime_ns == before


def test_the_cpu_preset_reports_the_noise_its_smoother_estimated(finished):
    _, job = finished
    fit = json.loads((job / "summary.json").read_text())["trajectory_smoothing"]
    assert set(fit) == {"position_log10_ratio", "position_noise_m", "rotation_log10_ratio",
                        "rotation_noise_deg"}  # fmt: skip
    assert 0 < fit["position_noise_m"] < 0.05 and 0 < fit["rotation_noise_deg"] < 5
    # the exports render the map from the poses it was made with, not the smoothed ones
    finished_job = FinishedJob(job)
    logged = np.stack([e.c2w for e in finished_job.events])
    np.testing.assert_array_equal(finished_job.mapped_poses(), logged)  # no loop correction
    assert not np.allclose(finished_job.trajectory()[1], logged, atol=1e-6)


def test_metrics_json_states_values_and_conventions(finished):
    _, job = finished
    metrics = json.loads((job / "outputs/metrics.json").read_text())
    summary = json.loads((job / "summary.json").read_text())
    ate = metrics["ate"]
    assert ate["available"] and ate["frames"] == FRAMES
    assert ate["rigid"]["rmse_cm"] == pytest.approx(summary["ate_rmse_m"] * 100, rel=1e-6)
    assert ate["with_scale"]["rmse_cm"] <= ate["rigid"]["rmse_cm"] + 1e-9
    assert ate["rigid"]["max_cm"] >= ate["rigid"]["rmse_cm"] > 0

    rendering = metrics["rendering"]
    assert [row["frame"] for row in rendering["per_frame"]] == keyframes(job)
    assert rendering["frames"] == summary["keyframes"]
    assert 10 < rendering["psnr_db"] < 80 and 0 < rendering["ssim"] <= 1
    assert rendering["ms_ssim"] is None and "160" in rendering["ms_ssim_note"]
    assert rendering["depth_l1_cm"] > 0 and rendering["lpips"] is None

    unc = metrics["uncertainty"]
    assert len(unc["fractions"]) == 100 and unc["fractions"][1] == 0.01
    assert sorted(unc["ause_mae_depth_by_variance"]) == ["map", "predictive", "sensor", "varsplat"]
    for result in [unc["ause_mae_color"], *unc["ause_mae_depth_by_variance"].values()]:
        assert len(result["oracle"]) == len(result["by_uncertainty"]) == 100
        assert result["oracle"][0] == pytest.approx(result["by_uncertainty"][0])  # all kept
        assert result["ause_raw"] >= 0 and 0 <= result["ause_normalised"] <= 1
    assert unc["ause_mae_depth"] == unc["ause_mae_depth_by_variance"]["predictive"]

    runs = metrics["run"]
    assert (runs["frames"], runs["keyframes"], runs["mapping_calls"]) == (
        FRAMES, summary["keyframes"], summary["mapping_calls"])  # fmt: skip
    assert sum(runs["keyframe_reasons"].values()) == summary["keyframes"]
    assert sum(s["seconds"] for s in runs["stages"].values()) == pytest.approx(summary["seconds"])
    assert metrics["resolution"] == {"downscale": 2, "mapping_downscale": 2,
                                     "width": SIZE[0] // 2, "height": SIZE[1] // 2}  # fmt: skip
    assert {"ate", "ause", "psnr", "ssim", "ms_ssim", "depth_l1", "lpips", "frames",
            "resolution", "timing"} <= set(metrics["conventions"])  # fmt: skip


def test_ause_in_metrics_follows_from_the_hdf5_file(finished):
    """The HDF5 file holds everything the colour AUSE needs, and agrees with metrics.json."""
    _, job = finished
    rows = json.loads((job / "outputs/metrics.json").read_text())["rendering"]["per_frame"]
    with h5py.File(job / "outputs/uncertainty.h5", "r") as f:
        for k, row in enumerate(rows):
            assert f["frame"][k] == row["frame"]
            valid = np.isfinite(f["error/depth"][k])
            error = f["error/color"][k][..., None]
            result = colour_sparsification(
                error, np.zeros_like(error), f["variance/color"][k][..., None], valid[..., None]
            )
            assert result.ause_raw == pytest.approx(row["ause_color_raw"], rel=1e-5)


def test_report_is_self_contained_with_decodable_images(finished):
    _, job = finished
    page = (job / "outputs/report.html").read_text()
    sources = re.findall(r'src="([^"]*)"', page)
    assert sources and all(s.startswith("data:image/png;base64,") for s in sources)
    for source in sources:
        data = np.frombuffer(base64.b64decode(source.split(",", 1)[1]), np.uint8)
        assert cv2.imdecode(data, cv2.IMREAD_COLOR) is not None
    pngs = sorted(p.name for p in (job / "outputs/report").iterdir())
    assert {"trajectory_top.png", "trajectory_axes.png", "ate_over_time.png", "ause_color.png",
            "ause_depth.png", "keyframes.png", "timing.png"} <= set(pngs)  # fmt: skip
    gallery = [name for name in pngs if name.startswith("frame_")]
    assert 1 <= len(gallery) <= 4 and len(sources) == len(pngs)
    for text in ("ATE rmse (rigid)", "AUSE-MAE depth [m], predictive, raw", "Conventions"):
        assert text in page


def test_uncertainty_h5_and_pngs_of_the_run(finished):
    store, job = finished
    cfg = load_config("cpu", TINY).uncertainty
    frames = keyframes(job)
    with h5py.File(job / "outputs/uncertainty.h5", "r") as f:
        assert list(f["frame"][:]) == frames and f["keyframe"][:].all()
        stamps = {e["frame"]: e["timestamp"] for e in events(job)}
        np.testing.assert_allclose(f["timestamp"][:], [stamps[i] for i in frames])
        assert f["variance/depth"].shape == (len(frames), SIZE[1] // 2, SIZE[0] // 2)
        for kind in ("color", "depth"):
            total, part_map = f[f"variance/{kind}"][:], f[f"variance/{kind}_map"][:]
            sensor = f[f"variance/{kind}_sensor"][:]
            np.testing.assert_allclose(total, part_map + sensor, rtol=1e-6)
            assert (sensor >= cfg.sensor_min).all() and (part_map >= cfg.map_floor).all()
        unobserved = f["render/alpha"][:] < cfg.unobserved_alpha
        assert (f["variance/depth_map"][:][unobserved] == cfg.unobserved_variance).all()
        assert (f["variance/depth_map"][:][~unobserved] < cfg.unobserved_variance).all()
    for quantity in QUANTITIES:
        names = sorted(p.name for p in (job / "outputs/uncertainty" / quantity).iterdir())
        assert names == [f"{i:06d}.png" for i in frames]


def test_renderer_prepares_frames_as_the_slam_and_upsamples_the_sensor_term(finished):
    store, job = finished
    finished_job = FinishedJob(job)
    cfg = finished_job.config
    with FrameStore(store) as opened:
        frame = opened[3]
        # the run moved the depth to the colour's time, and logged how
        motion = finished_job.events[3].depth_motion
        assert cfg.align_depth_time and frame.depth_time_offset > 0 and motion is not None
        as_mapped = prepare_frame(frame, opened.intrinsics, cfg, motion)[0].depth[..., 0].numpy()
        as_stored = prepare_frame(frame, opened.intrinsics, cfg)[0].depth[..., 0].numpy()
        full = UncertaintyRenderer(finished_job, opened, downscale=1).frame(3)
        np.testing.assert_array_equal(full.measured_depth, as_mapped)
        assert not np.array_equal(full.measured_depth, as_stored)
        coarse = UncertaintyRenderer(finished_job, opened).frame(3)
    assert full.var_depth.shape == (SIZE[1], SIZE[0])
    # the network's colour map has a value per sensor_downscale block of the mapping level, the
    # depth prior one per mapping pixel: each is repeated onto the finer grid, never resampled
    m, s = cfg.mapping.downscale, cfg.uncertainty.sensor_downscale
    assert cfg.uncertainty.sensor_prior == "nguyen"
    for sensor, block in ((full.var_color_sensor, m * s), (full.var_depth_sensor, m)):
        repeated = np.repeat(np.repeat(sensor[::block, ::block], block, 0), block, 1)
        np.testing.assert_array_equal(sensor, repeated[: SIZE[1], : SIZE[0]])
    # the SLAM's sensor values, only repeated onto the finer grid
    np.testing.assert_array_equal(np.unique(full.var_depth_sensor),
                                  np.unique(coarse.var_depth_sensor))  # fmt: skip


def test_eval_is_deterministic_and_takes_lpips_weights(copy):
    _, job = copy
    shutil.rmtree(job / "outputs")
    assert run("-q", "eval", job, "--no-report").exit_code == 0
    assert not (job / "outputs/report.html").exists()
    first = (job / "outputs/metrics.json").read_bytes()
    assert run("-q", "eval", job, "--no-report").exit_code == 0
    assert (job / "outputs/metrics.json").read_bytes() == first

    torch.manual_seed(0)
    model = Lpips("alex")
    for head in model.heads:
        head.weight.data.abs_()
    state = {k: v for k, v in model.state_dict().items() if k not in ("shift", "scale")}
    state = {k.replace("heads.", "lin").replace(".weight", ".model.1.weight")
             if k.startswith("heads.") else k: v for k, v in state.items()}  # fmt: skip
    torch.save(state, job / "lpips_random.pth")
    result = run("-q", "eval", job, "--lpips-weights", job / "lpips_random.pth")
    assert result.exit_code == 0, result.output
    rendering = json.loads((job / "outputs/metrics.json").read_text())["rendering"]
    assert rendering["lpips"] > 0 and rendering["lpips_net"] == "alex"
    assert (job / "outputs/report.html").is_file()


def test_export_frame_selection_and_renders(copy):
    _, job = copy
    result = run("-q", "export", job, "--uncertainty", "--renders", "--frames", "all",
                 "--stride", "3")  # fmt: skip
    assert result.exit_code == 0, result.output
    with h5py.File(job / "outputs/uncertainty.h5", "r") as f:
        assert list(f["frame"][:]) == [0, 3, 6]
        assert list(f["keyframe"][:]) == [e["keyframe"] for e in events(job)][::3]
    for kind in ("rgb", "depth"):
        names = sorted(p.name for p in (job / "outputs/renders" / kind).iterdir())
        assert names == ["000000.png", "000003.png", "000006.png"]
    assert (job / "outputs/metrics.json").is_file()  # other outputs stay as they were
    first = (job / "outputs/uncertainty.h5").read_bytes()
    assert run("-q", "export", job, "--uncertainty", "--frames", "all", "--stride", "3"
               ).exit_code == 0  # fmt: skip
    assert (job / "outputs/uncertainty.h5").read_bytes() == first  # deterministic, no timestamps


def test_broken_jobs_exit_3_naming_the_file_and_leave_outputs_alone(copy, tmp_path):
    store, job = copy
    out = job / "outputs"
    listing = sorted(str(p.relative_to(out)) for p in out.rglob("*"))
    h5_bytes = (out / "uncertainty.h5").read_bytes()

    (job / "sensor_net.pt").rename(job / "sensor_net.bak")
    result = run("export", job)
    assert result.exit_code == 3 and "sensor_net.pt" in result.output
    (job / "sensor_net.bak").rename(job / "sensor_net.pt")

    record = json.loads((job / "job.json").read_text())
    record["store"]["path"] = str(tmp_path / "moved.h5")
    (job / "job.json").write_text(json.dumps(record))
    result = run("eval", job)
    assert result.exit_code == 3 and "--store" in result.output and "moved.h5" in result.output
    other = tmp_path / "other"
    other_folder = synthesize(other / "seq", SynthConfig(frames=3, width=32, height=24, seed=4))
    plan = plan_tum(other_folder, TumOptions())
    wrong = write_store(plan.frames, other / "s.h5", plan.meta).path
    result = run("eval", job, "--store", wrong)  # another recording: its content says so
    assert result.exit_code == 5 and "is not the frame store" in result.output
    result = run("eval", job, "--store", store, "--downscale", "3")
    assert result.exit_code == 3 and "mapping.downscale" in result.output

    lines = (job / "log.jsonl").read_text().splitlines()
    (job / "log.jsonl").write_text("\n".join(lines[:2] + ["{torn"] + lines[3:]) + "\n")
    result = run("export", job, "--uncertainty", "--store", store)
    assert result.exit_code == 3 and "log.jsonl line 3" in result.output

    assert sorted(str(p.relative_to(out)) for p in out.rglob("*")) == listing
    assert (out / "uncertainty.h5").read_bytes() == h5_bytes


def test_no_export_and_help(finished, tmp_path):
    store, _ = finished
    job = tmp_path / "job"
    result = run(*run_args(store, job, "--no-export", "--max-frames", "2"))
    assert result.exit_code == 0, result.output
    assert (job / "summary.json").is_file() and not (job / "outputs").exists()
    for command in ("export", "eval"):
        helped = run(command, "--help")
        assert helped.exit_code == 0 and "Example" in helped.output
    assert "--no-export" in run("run", "--help").output

"""Σ_D's gains fitted at the end of a run (`bgs_batch.slam.calibration`)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from bgs_batch.config import load_config
from bgs_batch.slam.calibration import fit_depth_gains
from bgs_batch.slam.sensor_noise import DepthGains, SensorNoiseNet
from bgs_batch.store import FrameStore
from converters.synthetic import motion_config, synthesize
from converters.tum import convert_tum
from jobs.run import run_job
from outputs.jobfiles import FinishedJob
from outputs.uncertainty import UncertaintyRenderer, select_frames


def draws(map_gain: float, sensor_gain: float, level: float, n: int = 200_000, seed: int = 0):
    """Residuals drawn from N(0, c + a·V + b·S) with V, S spread over decades like the parts'."""
    rng = np.random.default_rng(seed)
    map_var = np.where(rng.random(n) < 0.3, 10 ** rng.uniform(-7, -3, n), 0.0)  # 0: one surface
    sensor_var = 10 ** rng.uniform(-6, -4, n)
    residual = rng.normal(size=n) * np.sqrt(level + map_gain * map_var + sensor_gain * sensor_var)
    return residual, map_var, sensor_var


def test_the_fit_recovers_the_gains_residuals_were_drawn_with():
    """A maximum-likelihood oracle: 200k draws of known gains are fitted to within 4 %."""
    for map_gain, sensor_gain in ((40.0, 0.25), (2.0, 50.0)):
        gains = fit_depth_gains(*draws(map_gain, sensor_gain, level=1e-6))
        assert gains.map == pytest.approx(map_gain, rel=0.04), gains
        assert gains.sensor == pytest.approx(sensor_gain, rel=0.04), gains


def test_the_fit_is_deterministic_and_has_nothing_to_fit_without_residuals():
    data = draws(10.0, 1.0, level=1e-6, n=20_000)
    assert fit_depth_gains(*data) == fit_depth_gains(*data)
    empty = np.zeros(0)
    assert fit_depth_gains(empty, empty, empty) == DepthGains()
    zeros = np.zeros(5)
    assert fit_depth_gains(zeros, np.ones(5), np.ones(5)) == DepthGains()


def test_the_sensor_gain_scales_the_per_pixel_part_only(store30_level):
    """With the Nguyen prior σ²_sensor,D = network mean + b·physics; at gain 1 it is the
    ungained variance bit for bit; a state saved before the gains existed loads with gains 1."""
    level = store30_level
    for prior in ("nguyen", "none"):
        u = load_config("cpu", [f"uncertainty.sensor_prior={prior}"]).uncertainty
        net = SensorNoiseNet.from_config(u)
        with torch.no_grad():
            colour, depth = net(level, u.sensor_downscale)
            net.set_gains(DepthGains(map=3.0, sensor=0.5))
            colour_g, depth_g = net(level, u.sensor_downscale)
        assert torch.equal(colour, colour_g)
        if prior == "nguyen":
            physics = net.depth_physics(level)
            expected = (depth - physics) + 0.5 * physics
            assert torch.allclose(depth_g, expected, rtol=1e-6, atol=1e-12)
        else:
            assert torch.allclose(depth_g, 0.5 * depth, rtol=1e-6, atol=0)
        assert net.gains == DepthGains(map=3.0, sensor=0.5)
        old = {k: v for k, v in net.state_dict().items() if k != "depth_gains"}
        fresh = SensorNoiseNet.from_config(u)
        fresh.load_state_dict(old)
        assert fresh.gains == DepthGains()


@pytest.fixture(scope="module")
def store30_level(tmp_path_factory):
    from bgs_batch.slam.frames import prepare_frame

    root = tmp_path_factory.mktemp("calibration_level")
    folder = synthesize(root / "seq", motion_config("walk", frames=2, width=160, height=120,
                                                    seed=3))  # fmt: skip
    with FrameStore(convert_tum(folder, root / "seq.h5")) as store:
        cfg = load_config("cpu")
        return prepare_frame(store[0], store.intrinsics, cfg)[1]


@pytest.mark.slow
def test_a_calibrated_run_reports_the_gained_variance_and_ranks_depth_errors_better(tmp_path):
    """End to end on a synthetic walk: the run fits gains away from 1 and saves them with the
    network; the reported Σ_D is b·σ²_sensor,D's per-pixel part + its level + a·V_D + floor;
    the trajectory is that of the uncalibrated run bit for bit; and the calibrated Σ_D ranks
    the keyframes' depth errors better than the uncalibrated one."""
    from outputs.ause import depth_sparsification

    folder = synthesize(tmp_path / "seq", motion_config("walk", frames=24, width=160,
                                                        height=120, seed=11))  # fmt: skip
    store_path = convert_tum(folder, tmp_path / "seq.h5")
    runs = {}
    for calibrate in (False, True):
        cfg = load_config("cpu", [f"uncertainty.calibrate={calibrate}"])
        run_job(store_path, tmp_path / f"job{calibrate}", cfg)
        runs[calibrate] = FinishedJob(tmp_path / f"job{calibrate}")
    assert ((tmp_path / "jobTrue/trajectory.txt").read_bytes()
            == (tmp_path / "jobFalse/trajectory.txt").read_bytes())  # fmt: skip
    with FrameStore(store_path) as store:
        renderers = {c: UncertaintyRenderer(job, store) for c, job in runs.items()}
        gains = renderers[True].sensor.gains
        assert renderers[False].sensor.gains == DepthGains()
        assert gains.map != pytest.approx(1.0, rel=0.1) and gains.sensor != 1.0, gains
        ause = {True: [], False: []}
        u = runs[True].config.uncertainty
        for index in select_frames(runs[True]):
            frames = {c: r.frame(index) for c, r in renderers.items()}
            f = frames[True]
            observed = f.valid & (f.var_depth_map < u.unobserved_variance)
            v = f.var_depth_map[observed] - u.map_floor  # a·V_D
            total = f.var_depth_sensor[observed] + v + u.map_floor
            assert np.allclose(f.var_depth[observed], total, rtol=1e-5, atol=1e-9)
            assert np.allclose(v, gains.map * (frames[False].var_depth_map[observed]
                                               - u.map_floor), rtol=1e-4, atol=1e-8)  # fmt: skip
            for c, fr in frames.items():
                ause[c].append(depth_sparsification(fr.rendered_depth, fr.measured_depth,
                                                    fr.var_depth).ause_raw)  # fmt: skip
        assert np.mean(ause[True]) < np.mean(ause[False]), ause

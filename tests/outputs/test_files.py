"""Export building blocks without a SLAM run: atomic writes, the HDF5 layout, colour maps,
images, LPIPS weight loading and the shared-oracle depth AUSE."""

import math

import cv2
import h5py
import numpy as np
import pytest
import torch

from bgs_batch.config import UncertaintyConfig
from bgs_batch.errors import InputError
from bgs_batch.render import Camera
from outputs.ause import depth_sparsification, depth_sparsifications
from outputs.colormap import NAN_COLOUR, VARIANCE_MAP, Scale, colorize, tile
from outputs.lpips import Lpips, load_lpips
from outputs.uncertainty import FrameUncertainty
from outputs.uncertainty_h5 import IMAGES, SCALARS, UncertaintyWriter, read_frame
from outputs.uncertainty_images import (
    QUANTITIES,
    RENDER_DEPTH_SCALE,
    ImageScales,
    panel,
    write_quantities,
    write_renders,
)


def fake_frame(index: int, h: int = 12, w: int = 16, seed: int = 0) -> FrameUncertainty:
    rng = np.random.default_rng(seed + index)

    def image(*shape, low=0.0, high=1.0):
        return rng.uniform(low, high, (h, w, *shape)).astype(np.float32)

    depth = image(low=0.5, high=3.0)
    depth[0, :3] = 0.0  # invalid readings
    sensor_c, map_c = image(low=1e-4, high=1e-2), image(low=1e-3, high=1e-1)
    sensor_d, map_d = image(low=1e-4, high=1e-2), image(low=1e-3, high=1e-1)
    alpha = image()
    return FrameUncertainty(
        frame=index, timestamp=100.0 + index / 30, keyframe=index % 2 == 0, submap=0,
        downscale=2, camera=Camera(50.0, 50.0, w / 2, h / 2, w, h),
        measured_rgb=image(3), measured_depth=depth, rendered_rgb=image(3),
        rendered_depth=np.maximum(depth + image(low=-0.05, high=0.05), 0), alpha=alpha,
        var_color=sensor_c + map_c, var_color_map=map_c, var_color_sensor=sensor_c,
        var_depth=sensor_d + map_d, var_depth_map=map_d, var_depth_sensor=sensor_d,
    )  # fmt: skip


# ---------------------------------------------------------------- HDF5 layout


def test_uncertainty_h5_layout(tmp_path):
    frames = [fake_frame(i) for i in (0, 4, 9)]
    path = tmp_path / "u.h5"
    with UncertaintyWriter(path, len(frames), 12, 16, {"downscale": 2}) as writer:
        for item in frames:
            writer.add(item)
    with h5py.File(path, "r") as f:
        assert set(IMAGES) | set(SCALARS) <= {n for n in _names(f)}
        for name in IMAGES:
            ds = f[name]
            assert ds.dtype == np.float32 and ds.chunks == (1, *ds.shape[1:])
            assert ds.shape[:3] == (3, 12, 16) and ds.compression == "gzip" and ds.shuffle
            assert ds.attrs["units"] and ds.attrs["description"]
        assert f["render/color"].shape == (3, 12, 16, 3)
        assert list(f["frame"][:]) == [0, 4, 9]
        np.testing.assert_allclose(f["timestamp"][:], [100.0, 100 + 4 / 30, 100.3])
        assert list(f["keyframe"][:]) == [True, True, False]
        assert f.attrs["downscale"] == 2 and "conventions" in f.attrs
    stored = read_frame(path, 1)
    np.testing.assert_array_equal(stored["variance/depth"], frames[1].var_depth)
    np.testing.assert_array_equal(stored["render/color"], frames[1].rendered_rgb)
    error = stored["error/depth"]
    assert np.isnan(error[0, :3]).all() and np.isfinite(error[1:]).all()
    np.testing.assert_allclose(stored["error/color"], frames[1].error_color)


def _names(f):
    names = []
    f.visit(names.append)
    return names


def test_writer_refuses_a_short_file(tmp_path):
    with pytest.raises(ValueError, match="1 of 2"), \
            UncertaintyWriter(tmp_path / "u.h5", 2, 12, 16, {}) as writer:  # fmt: skip
        writer.add(fake_frame(0))


# ---------------------------------------------------------------- colour maps and images


def test_colorize_clips_and_marks_nan():
    scale = Scale(1e-3, 1e1, True, "m^2", VARIANCE_MAP)
    values = np.array([[1e-6, 1e-3, 1e-1, 1e1, 1e3, np.nan]])
    bgr = colorize(values, scale)
    assert (bgr[0, 0] == bgr[0, 1]).all() and (bgr[0, 3] == bgr[0, 4]).all()  # clipped ends
    assert not (bgr[0, 1] == bgr[0, 3]).all()
    assert tuple(bgr[0, 5]) == NAN_COLOUR
    assert list(scale.tick_values()) == pytest.approx([1e-3, 1e-2, 1e-1, 1e0, 1e1])
    fitted = Scale.fitted_log(np.array([0.002, 0.05, 0.3]), "", VARIANCE_MAP, (0, 100))
    assert (fitted.low, fitted.high) == pytest.approx((1e-3, 1.0))
    assert Scale.fitted_log(np.array([np.nan, 0.0]), "", VARIANCE_MAP, (0, 100)) is None


def test_tiles_have_a_colour_bar_and_small_images_are_enlarged():
    scale = Scale(0.0, 1.0, False, "m", VARIANCE_MAP)
    image = colorize(np.linspace(0, 1, 12 * 16).reshape(12, 16), scale)
    with_bar, without = tile(image, "t", scale), tile(image, "t")
    assert with_bar.shape == without.shape and with_bar.shape[0] > 240
    assert (with_bar != without).any()  # the bar and its labels are drawn


def test_quantity_pngs_renders_and_panel(tmp_path):
    item = fake_frame(3)
    scales = ImageScales(UncertaintyConfig())
    files = write_quantities(item, tmp_path / "u", scales)
    assert sorted(p.parent.name for p in files) == sorted(QUANTITIES)
    assert all(cv2.imread(str(p)) is not None for p in files)
    variance = scales("variance", item)
    assert variance.log and variance.low <= 1e-4 and variance.high >= 1e-1
    assert scales("variance", fake_frame(4, seed=9)) is variance  # fixed after the first frame
    rgb, depth = write_renders(item, tmp_path / "r")
    stored = cv2.imread(str(depth), cv2.IMREAD_UNCHANGED)
    assert stored.dtype == np.uint16
    np.testing.assert_allclose(stored / RENDER_DEPTH_SCALE, item.rendered_depth, atol=1e-4)
    assert cv2.imread(str(rgb)).shape == (12, 16, 3)
    assert panel(item, scales).ndim == 3


# ---------------------------------------------------------------- AUSE sharing the oracle


def test_depth_sparsifications_equal_one_by_one():
    item = fake_frame(1)
    together = depth_sparsifications(item.rendered_depth, item.measured_depth,
                                     item.depth_variances())  # fmt: skip
    assert sorted(together) == ["map", "predictive", "sensor", "varsplat"]
    for name, variance in item.depth_variances().items():
        alone = depth_sparsification(item.rendered_depth, item.measured_depth, variance)
        assert together[name].ause_raw == alone.ause_raw
        np.testing.assert_array_equal(together[name].oracle, alone.oracle)
    oracle = depth_sparsifications(
        item.rendered_depth,
        item.measured_depth,
        {"oracle": np.abs(item.rendered_depth - item.measured_depth)},
    )
    assert oracle["oracle"].ause_raw == 0.0


# ---------------------------------------------------------------- LPIPS from supplied weights


def _lpips_state(net: str, seed: int = 0) -> dict[str, torch.Tensor]:
    """Weights in lpips's own layout (net.sliceK.I.*, linK.model.1.weight), random."""
    torch.manual_seed(seed)
    model = Lpips(net)
    taps = (0, *model.taps)
    state = {}
    for k in range(len(model.taps)):
        for i in range(taps[k], taps[k + 1]):
            layer = model.features[i]
            if isinstance(layer, torch.nn.Conv2d):
                state[f"net.slice{k + 1}.{i}.weight"] = torch.randn_like(layer.weight) * 0.05
                state[f"net.slice{k + 1}.{i}.bias"] = torch.zeros_like(layer.bias)
        state[f"lin{k}.model.1.weight"] = model.heads[k].weight.detach().abs()
    return state


def test_lpips_loads_lpips_and_torchvision_layouts(tmp_path):
    state = _lpips_state("alex")
    torch.save(state, tmp_path / "lpips_alex.pth")
    model = load_lpips([tmp_path / "lpips_alex.pth"])
    assert model.net == "alex"
    a, b = torch.rand(64, 64, 3), torch.rand(64, 64, 3)
    assert float(model(a, a)) == 0.0
    assert float(model(a, b)) > 0.0
    # the same weights as a torchvision backbone file plus lpips's head file
    backbone = {k.replace(k.split(".")[0] + "." + k.split(".")[1], "features", 1): v
                for k, v in state.items() if k.startswith("net.")}  # fmt: skip
    heads = {k: v for k, v in state.items() if k.startswith("lin")}
    torch.save(backbone, tmp_path / "alexnet.pth")
    torch.save(heads, tmp_path / "alex.pth")
    split = load_lpips([tmp_path / "alexnet.pth", tmp_path / "alex.pth"])
    assert math.isclose(float(split(a, b)), float(model(a, b)), rel_tol=1e-6)


def test_lpips_errors_name_the_problem(tmp_path):
    torch.save({k: v for k, v in _lpips_state("vgg").items() if not k.startswith("lin")},
               tmp_path / "vgg16.pth")  # fmt: skip
    with pytest.raises(InputError, match="vgg LPIPS weights lack heads"):
        load_lpips([tmp_path / "vgg16.pth"])
    (tmp_path / "junk.pth").write_bytes(b"not torch")
    with pytest.raises(InputError, match="junk.pth"):
        load_lpips([tmp_path / "junk.pth"])
    torch.save({"x": torch.zeros(1)}, tmp_path / "other.pth")
    with pytest.raises(InputError, match="no backbone"):
        load_lpips([tmp_path / "other.pth"])

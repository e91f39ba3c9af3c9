"""The sensor-noise network and its physical depth prior (paper §III-D; docs/method.md §3)."""

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from scipy.stats import spearmanr

from bgs_batch.config import load_config
from bgs_batch.render import Camera
from bgs_batch.slam.frames import Level
from bgs_batch.slam.sensor_noise import NguyenDepthNoise, SensorNoiseNet

NGUYEN = NguyenDepthNoise()
CAMERA = Camera(fx=200.0, fy=200.0, cx=15.5, cy=11.5, width=32, height=24)


def level(h=10, w=7, seed=0, depth=None) -> Level:
    """A random frame (colour in [0,1], depth in [0.5, 1.5] m) or the given depth [H,W]."""
    g = torch.Generator().manual_seed(seed)
    if depth is not None:
        h, w = depth.shape
    rgb = torch.rand(h, w, 3, generator=g, dtype=torch.float64)
    d = torch.rand(h, w, 1, generator=g, dtype=torch.float64) + 0.5
    d = d if depth is None else depth[..., None]
    return Level(rgb, d, Camera(200.0, 200.0, (w - 1) / 2, (h - 1) / 2, w, h))


def sigma(z: float, theta: float = 0.0) -> float:
    """Nguyen et al. 2012, Eq. 3 (m)."""
    grazing = 0.0001 / math.sqrt(z) * theta**2 / (math.pi / 2 - theta) ** 2
    return 0.0012 + 0.0019 * (z - 0.4) ** 2 + grazing


def test_network_shapes_floor_and_gradients():
    torch.manual_seed(0)
    net = SensorNoiseNet(hidden=8).double()
    assert len([m for m in net.modules() if isinstance(m, torch.nn.Conv2d)]) == 8
    frame = level()
    var_c, var_d = net(frame)
    assert var_c.shape == var_d.shape == (10, 7, 1)
    assert (var_c > 1e-4).all() and (var_d > 1e-4).all()
    (var_c.sum() + var_d.sum()).backward()
    assert all(p.grad is not None for p in net.parameters())
    with torch.no_grad():  # the floor holds however negative the head's output
        net.head.bias.fill_(-1e3)
        assert torch.allclose(net(frame)[0], torch.tensor(1e-4, dtype=torch.float64))


def test_network_initial_output():
    """`initial` sets the head's bias so that the untrained net predicts about that variance
    (closed form: softplus(b) + floor = initial); it must exceed the floor."""
    torch.manual_seed(0)
    net = SensorNoiseNet(hidden=8, floor=1e-4, initial=1e-3).double()
    assert torch.allclose(F.softplus(net.head.bias) + 1e-4, torch.tensor(1e-3, dtype=torch.float64))
    for var in (v.detach() for v in net(level())):  # default-initialised weights: under 10x
        assert float(var.min()) > 1e-4 and float(var.max()) < 1e-2
        assert float(var.median()) == pytest.approx(1e-3, rel=0.5)
    with pytest.raises(ValueError, match="must exceed the floor"):
        SensorNoiseNet(floor=1e-3, initial=1e-3)


def test_network_at_a_coarser_scale():
    torch.manual_seed(0)
    net = SensorNoiseNet(hidden=8).double()
    frame = level(9, 7)
    var_c, var_d = net(frame, 2)
    assert var_c.shape == var_d.shape == (9, 7, 1)
    blocks = (t[:8, :6].reshape(4, 2, 3, 2, -1).mean((1, 3)) for t in (frame.rgb, frame.depth))
    coarse = Level(*blocks, frame.camera.scaled(0.5))
    coarse_c, _ = net(coarse)
    assert torch.equal(var_c[2:4, 4:6, 0], coarse_c[1:2, 2:3, 0].expand(2, 2))
    assert torch.equal(var_c[8, :, 0], var_c[7, :, 0])  # edge rows replicate


def test_nguyen_model_on_a_plane_facing_the_camera_is_the_axial_term():
    depth = torch.full((24, 32), 2.0, dtype=torch.float64)
    variance = NGUYEN.variance(depth[..., None], CAMERA)[..., 0]
    assert torch.allclose(variance, torch.tensor(sigma(2.0) ** 2, dtype=torch.float64), rtol=1e-12)


@pytest.mark.parametrize("degrees", [30.0, 45.0, 70.0])
def test_nguyen_model_on_a_tilted_plane(degrees):
    """A plane through (0, 0, 1.5 m) turned by θ about the camera's y axis: Z = z_c / (1 −
    (u − cx) tanθ / fx); at the principal point the slope gives θ and σ is Eq. 3 at θ."""
    theta = math.radians(degrees)
    u = torch.arange(32, dtype=torch.float64) - CAMERA.cx
    depth = (1.5 / (1 - u * math.tan(theta) / CAMERA.fx)).expand(24, 32)
    variance = NGUYEN.variance(depth[..., None].contiguous(), CAMERA)[..., 0]
    centre = variance[12, 15:17].mean()  # the two columns around cx = 15.5
    assert float(centre) == pytest.approx(sigma(1.5, theta) ** 2, rel=2e-3)
    assert (variance[:, 1:-1] > sigma(1.0) ** 2).all()


def test_nguyen_model_at_a_depth_edge_and_holes():
    """At a step from 1 to 3 m, θ → π/2 would give σ of kilometres: σ is capped at half the
    neighbourhood's range (1 m); invalid pixels get finite, positive values; a pixel whose
    neighbours are all invalid keeps the axial term."""
    depth = torch.full((24, 32), 1.0, dtype=torch.float64)
    depth[:, 16:] = 3.0
    depth[5, :] = 0.0
    depth[20, 3] = 0.0
    depth[9:12, 24:27] = 0.0
    depth[10, 25] = 2.5
    variance = NGUYEN.variance(depth[..., None], CAMERA)[..., 0]
    assert torch.isfinite(variance).all() and (variance > 0).all()
    assert float(variance[14, 15]) == pytest.approx(1.0)  # Eq. 3 at 89.7°: σ ≈ 2.4 m
    theta = math.atan(1.0 * CAMERA.fx / 3.0)  # the 3 m side: 89.1°, σ ≈ 0.64 m, not capped
    assert float(variance[14, 16]) == pytest.approx(sigma(3.0, theta) ** 2, rel=1e-9)
    assert float(variance[14, 3]) == pytest.approx(sigma(1.0) ** 2, rel=1e-12)
    assert float(variance[14, 28]) == pytest.approx(sigma(3.0) ** 2, rel=1e-12)
    assert float(variance[10, 25]) == pytest.approx(sigma(2.5) ** 2, rel=1e-12)
    assert float(variance[5, 3]) == pytest.approx(sigma(NGUYEN.z0) ** 2)  # invalid


def test_prior_network_adds_the_frames_learned_level_to_the_prior():
    """With a prior, σ²_sensor,D = the mean of the plain network's depth map + the prior: the
    network's level learns (here from `initial`, through its depth head) and the physics ranks
    the pixels exactly (Spearman 1 with Nguyen's σ, across depths 0.5-5 m and an edge); colour
    is as without a prior."""
    depth = torch.linspace(0.5, 4.0, 32, dtype=torch.float64).expand(24, 32).contiguous()
    depth[:, 20:] += 1.0
    frame = level(depth=depth)
    prior = NGUYEN.variance(frame.depth, frame.camera)
    torch.manual_seed(0)
    plain = SensorNoiseNet(hidden=8, floor=1e-4, initial=1e-3).double()
    torch.manual_seed(0)
    net = SensorNoiseNet(hidden=8, floor=1e-4, initial=1e-3, prior=NGUYEN).double()
    plain_c, plain_d = plain(frame, 2)
    var_c, var_d = net(frame, 2)
    assert torch.equal(var_c, plain_c)
    assert torch.allclose(var_d, plain_d.mean() + prior, rtol=1e-12, atol=0)
    assert float(plain_d.detach().mean()) == pytest.approx(1e-3, rel=0.5)
    ranks = spearmanr(var_d.detach().flatten().numpy(), prior.flatten().numpy()).statistic
    assert ranks == pytest.approx(1.0)
    var_d.sum().backward()  # ∂Σ/∂b_D = mean(softplus'(raw_D)) per pixel
    assert float(net.head.bias.grad[1]) > 0 and float(net.head.bias.grad[0]) == 0


def test_the_prior_is_computed_once_per_depth_image():
    """Mapping evaluates a keyframe many times: the physics is cached per depth tensor (the same
    values), and the entry goes with the tensor."""
    torch.manual_seed(0)
    net = SensorNoiseNet(hidden=8, floor=1e-4, initial=1e-3, prior=NGUYEN).double()
    frame = level(24, 32)
    first = net.depth_physics(frame)
    assert torch.equal(first, NGUYEN.variance(frame.depth, frame.camera))
    assert net.depth_physics(frame) is first and len(net._physics) == 1
    assert torch.equal(net(frame)[1], net(frame)[1])
    other = level(24, 32, seed=1)
    assert not torch.equal(net.depth_physics(other), first)
    del frame, first, other
    assert net._physics == {}


def test_the_settings_choose_the_sensor_model():
    assert SensorNoiseNet.from_config(load_config("paper").uncertainty).prior is None
    assert SensorNoiseNet.from_config(load_config("cpu").uncertainty).prior == NGUYEN
    plain = load_config("cpu", ["uncertainty.sensor_prior=none"])
    assert SensorNoiseNet.from_config(plain.uncertainty).prior is None
    custom = load_config("cpu", ["uncertainty.sensor_prior=nguyen", "uncertainty.nguyen_b=0.003"])
    assert SensorNoiseNet.from_config(custom.uncertainty).prior.b == 0.003


def test_prior_ranks_the_simulated_noise_of_a_synthetic_frame():
    """On a `bgs synth` room the prior's σ ranks the per-pixel σ of the noise that was drawn
    (Spearman ≥ 0.8, the bar of `bench/validate.py`), from the noisy depth alone."""
    from converters.synthetic import RoomRenderer, SynthConfig, camera_poses

    config = SynthConfig(frames=4, width=160, height=120, seed=5)
    pose = camera_poses(config)[2]
    _, depth, simulated = RoomRenderer(config).render([pose], pose, np.random.default_rng(0))
    metres = torch.from_numpy(depth.astype(np.float64) / config.depth_scale)
    camera = Camera(*config.intrinsics, width=160, height=120)
    predicted = NGUYEN.variance(metres[..., None], camera)[..., 0].sqrt().numpy()
    valid = depth > 0
    assert spearmanr(predicted[valid], simulated[valid])[0] >= 0.8

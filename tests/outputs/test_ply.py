"""PLY export: INRIA 3DGS layout read independently with plyfile, round trip, merging submaps."""

import numpy as np
import pytest
from plyfile import PlyData

from bgs_batch.errors import InputError
from outputs.ply import PROPERTIES, SH_C0, Splats, read_ply, write_ply

INRIA_ORDER = [
    "x",
    "y",
    "z",
    "nx",
    "ny",
    "nz",
    "f_dc_0",
    "f_dc_1",
    "f_dc_2",
    "opacity",
    "scale_0",
    "scale_1",
    "scale_2",
    "rot_0",
    "rot_1",
    "rot_2",
    "rot_3",
    "uncertainty",
]


def random_params(n, seed=0, offset=(0.0, 0.0, 0.0)):
    rng = np.random.default_rng(seed)
    return {
        "means": rng.normal(size=(n, 3)) + offset,
        "log_scales": rng.normal(-4, 1, (n, 3)),
        "quats": rng.normal(size=(n, 4)),
        "opacity_logits": rng.normal(size=n),
        "colors": rng.uniform(size=(n, 3)),
        "uncertainty_logits": rng.normal(-7, 2, n),
    }


def splats_at(points):
    params = random_params(len(points))
    params["means"] = np.asarray(points, np.float64)
    return Splats.from_params(params)


def test_plyfile_reads_the_exact_inria_layout(tmp_path):
    params = random_params(50)
    path = tmp_path / "map.ply"
    assert write_ply(path, Splats.from_params(params)) == 50
    ply = PlyData.read(str(path))
    assert ply.text is False and ply.byte_order == "<"
    assert [e.name for e in ply.elements] == ["vertex"]
    vertex = ply["vertex"]
    assert [p.name for p in vertex.properties] == INRIA_ORDER == list(PROPERTIES)
    assert {p.val_dtype for p in vertex.properties} == {"f4"}
    col = {name: vertex[name] for name in INRIA_ORDER}
    np.testing.assert_allclose(
        np.stack([col["x"], col["y"], col["z"]], 1), params["means"], rtol=1e-6
    )
    np.testing.assert_array_equal(np.stack([col["nx"], col["ny"], col["nz"]], 1), 0)
    f_dc = np.stack([col[f"f_dc_{i}"] for i in range(3)], 1)
    np.testing.assert_allclose(f_dc, (params["colors"] - 0.5) / SH_C0, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(col["opacity"], params["opacity_logits"], rtol=1e-6)
    np.testing.assert_allclose(
        np.stack([col[f"scale_{i}"] for i in range(3)], 1), params["log_scales"], rtol=1e-6
    )
    np.testing.assert_allclose(
        np.stack([col[f"rot_{i}"] for i in range(4)], 1), params["quats"], rtol=1e-6
    )  # w first, unnormalised
    np.testing.assert_allclose(
        col["uncertainty"], np.log1p(np.exp(params["uncertainty_logits"])), rtol=1e-5
    )


def test_round_trip_and_non_finite_rows_dropped(tmp_path):
    params = random_params(20)
    params["means"][3, 1] = np.nan
    params["log_scales"][7, 0] = np.inf
    original = Splats.from_params(params)
    path = tmp_path / "map.ply"
    assert write_ply(path, original) == 18
    back = read_ply(path)
    expected = original.select(np.setdiff1d(np.arange(20), [3, 7]))
    for name in ("means", "log_scales", "quats", "opacity_logits", "uncertainty"):
        np.testing.assert_array_equal(getattr(back, name), getattr(expected, name), err_msg=name)
    np.testing.assert_allclose(back.colors, expected.colors, atol=1e-6)


def test_reader_rejects_other_layouts(tmp_path):
    path = tmp_path / "ascii.ply"
    path.write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n0\n")
    with pytest.raises(InputError, match="bgs export"):
        read_ply(path)

import pytest

from bgs_batch.config import PRESETS, Config, ConfigError, config_from_dict, load_config


def test_paper_preset_is_the_papers_settings():
    config = load_config("paper")
    assert config == Config()
    assert config.tracking.iterations == 200 and config.mapping.iterations == 100
    assert config.tracking.lambda_color == config.tracking.lambda_depth == 900
    assert config.mapping.gamma == 1e-3 and config.keyframes.max_gap == 5
    assert config.keyframes.threshold == 0 and config.uncertainty.initial_logit == -7


def test_cpu_preset_and_overrides():
    config = load_config("cpu", ["tracking.iterations=17", "keyframes.mode=every",
                                 "uncertainty.full_grad=true", "mapping.gamma=1e-4"])  # fmt: skip
    assert config.tracking.iterations == 17 and config.keyframes.mode == "every"
    assert config.uncertainty.full_grad is True and config.mapping.gamma == 1e-4
    assert config.mapping.iterations == PRESETS["cpu"]["mapping.iterations"]


def test_round_trip_through_dict():
    config = load_config("cpu", ["seed=3"])
    assert config_from_dict(config.to_dict()) == config


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("tracking.iterashuns=3", "unknown config key 'tracking.iterashuns'"),
        ("tracking.iterations=many", "invalid literal"),
        ("keyframes.mode=sometimes", "choose one of surprise, every"),
        ("uncertainty.full_grad=maybe", "expected true or false"),
        ("tracking=3", "is a section"),
        ("seed", "expected key=value"),
        ("seed.x=1", "is a value"),
        ("uncertainty.sensor_initial=1e-5", "must exceed uncertainty.sensor_min"),
    ],
)
def test_bad_overrides_are_explained(override, message):
    with pytest.raises(ConfigError, match=message):
        load_config("cpu", [override])


def test_unknown_preset():
    with pytest.raises(ConfigError, match="choose one of paper, cpu"):
        load_config("gpu")


def test_refinement_settings_are_checked():
    for bad in ("uncertainty.refine_passes=-1", "uncertainty.refine_lr=0"):
        with pytest.raises(ConfigError, match="refine_passes"):
            load_config("cpu", [bad])


def test_a_pivot_behind_the_camera_is_refused():
    with pytest.raises(ConfigError, match="pivot_depth_ratio=-0.5 must be >= 0"):
        load_config("cpu", ["tracking.pivot_depth_ratio=-0.5"])


@pytest.mark.parametrize("override", ["registration.downscale=0", "registration.coarsest_width=4",
                                      "registration.iterations=0", "registration.min_fitness=1.5",
                                      "tracking.warm_iterations=-1"])  # fmt: skip
def test_warm_start_settings_are_checked(override):
    with pytest.raises(ConfigError, match=override.split("=")[0].replace(".", r"\.")):
        load_config("cpu", [override])

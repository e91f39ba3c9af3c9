import dataclasses
import typing

import pytest

from bgs_batch.config import (
    PRESETS,
    RANGES,
    SETTINGS,
    Config,
    ConfigError,
    accepted_values,
    config_from_dict,
    load_config,
)


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
        ("smoothing.log_ratio_max=-5", "is below smoothing.log_ratio_min=-2"),
        ("tracking.downscale=1", "tracking.downscale=1 must be a multiple of mapping.downscale=2"),
    ],
)
def test_bad_overrides_are_explained(override, message):
    with pytest.raises(ConfigError, match=message):
        load_config("cpu", [override])


def test_unknown_preset():
    with pytest.raises(ConfigError, match="choose one of paper, cpu"):
        load_config("gpu")


def _numeric_keys() -> list[tuple[str, type]]:
    """Every int and float setting of `Config` (dotted key, type)."""

    def walk(cls, prefix=""):
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            kind = hints[f.name]
            if dataclasses.is_dataclass(kind):
                yield from walk(kind, f"{prefix}{f.name}.")
            else:
                kind = next((k for k in typing.get_args(kind) if k is not type(None)), kind)
                if kind in (int, float):
                    yield f"{prefix}{f.name}", kind

    return list(walk(Config))


def test_every_numeric_setting_states_its_range_and_every_setting_its_doc():
    keys = {key for key, _ in _numeric_keys()}
    assert keys == set(RANGES), (keys ^ set(RANGES))
    assert set(SETTINGS) >= keys and len(SETTINGS) > len(keys)  # and the switches and choices
    undocumented = [key for key, f in SETTINGS.items() if len(f.metadata["doc"]) < 10]
    assert undocumented == []
    for preset in PRESETS:  # and every preset lies within them
        load_config(preset)


@pytest.mark.parametrize(("key", "kind"), _numeric_keys())
def test_nan_inf_zero_and_minus_one_are_refused_or_in_range(key, kind):
    bounds = RANGES[key]
    for text in ("nan", "inf", "-inf", "0", "-1"):
        if kind is int and text in ("nan", "inf", "-inf"):
            with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
                load_config("cpu", [f"{key}={text}"])  # not an integer
            continue
        value = kind(text)
        if bounds.admits(value):
            try:
                load_config("cpu", [f"{key}={text}"])
            except ConfigError as err:  # a combination rule may still refuse it, by name
                assert key.split(".")[-1] in str(err)
        else:
            with pytest.raises(ConfigError, match=rf"{key.replace('.', r'.')}={text}.* out of "
                                                  rf"range: it must be a finite number"):
                load_config("cpu", [f"{key}={text}"])


@pytest.mark.parametrize("override", ["tracking.iterations=-5", "checkpoint_every=0",
                                      "keyframes.max_gap=-3", "tracking.lambda_color=-1",
                                      "mapping.iterations=-1", "max_depth=nan", "mapping.gamma=nan",
                                      "tracking.rot_lr=inf", "mapping.lr_means=-1",
                                      "mapping.downscale=0", "seed=-1", "threads=0",
                                      "registration.min_fitness=1.5"])  # fmt: skip
def test_the_reported_nonsense_settings_are_refused(override):
    with pytest.raises(ConfigError, match="out of range"):
        load_config("cpu", [override])


def test_what_a_setting_accepts_reads_as_english():
    assert accepted_values("tracking.iterations") == "an integer >= 1"
    assert accepted_values("mapping.ssim_weight") == "a number >= 0 and <= 1"
    assert accepted_values("crop_edge") == "an integer >= 0, or none"
    assert accepted_values("tracking.optimizer") == "one of adam, gauss_newton"
    assert accepted_values("smoothing.enabled") == "true or false"
    assert accepted_values("keyframes.threshold") == "a number"


def test_a_range_reads_as_english():
    assert RANGES["tracking.iterations"].describe() == "a finite number >= 1"
    assert RANGES["mapping.ssim_weight"].describe() == "a finite number >= 0 and <= 1"
    assert RANGES["tracking.rot_lr"].describe() == "a finite number > 0"
    assert RANGES["keyframes.threshold"].describe() == "a finite number"

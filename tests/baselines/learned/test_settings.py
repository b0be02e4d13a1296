"""A setting's value as a --config file or --set writes it: read into the type its flag reads."""

from __future__ import annotations

import pytest

from ee_formation_env.baselines.learned.config import TrainConfig
from ee_formation_env.baselines.learned.settings import parse_assignment, read_settings_file

SETTINGS = {setting.name: setting for setting in TrainConfig.settings()}


@pytest.mark.parametrize("text, value", [
    ("total_timesteps=400k", 400_000), ("total_timesteps=5M", 5_000_000), ("n_envs=8", 8), ("gamma=0.9", 0.9),
    ("residual_gate=False", False), ("gravity_compensation=true", True), ("gamma=null", None),
    ("imitate=none", "none"), ("obs_features=log-error", "log-error"), ("scenario=my=file.yaml", "my=file.yaml"),
])
def test_a_set_is_parsed_as_its_flag_reads_it(text, value):
    name = text.partition("=")[0]
    assert parse_assignment(text, SETTINGS) == (name, value)


def test_a_file_holds_typed_values_or_strings_as_the_flags_write_them(tmp_path):
    path = tmp_path / "settings.yaml"
    path.write_text("total_timesteps: 400k\nn_envs: 8\nresidual_scale: 1\nscenario: {name: x}\nimitate: null\n")
    assert read_settings_file(path, SETTINGS) == {"total_timesteps": 400_000, "n_envs": 8, "residual_scale": 1,
                                                  "scenario": {"name": "x"}, "imitate": None}
    path.write_text("reference: zero\n")
    with pytest.raises(ValueError, match=f"--config {path}: reference: expected one of gradient, approx_jacobian, "
                                         "adaptive_jacobian, got 'zero'"):
        read_settings_file(path, SETTINGS)
    path.write_text("total_timesteps: 1.5\n")
    with pytest.raises(ValueError, match="total_timesteps: expected an integer or null, got 1.5"):
        read_settings_file(path, SETTINGS)

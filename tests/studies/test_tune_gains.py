"""The gain tuner (studies/tune_gains.py): seeded and reproducible, the defaults its first trial, constraints
that make a faster but costlier set lose, and a file the library reads back."""

from __future__ import annotations

import json

import pytest

pytest.importorskip("optuna")

from ee_formation_env.baselines.metrics import EpisodeMetrics  # noqa: E402
from ee_formation_env.baselines.reference import tuned  # noqa: E402
from studies import tune_gains  # noqa: E402


def test_a_short_tuning_is_seeded_starts_from_the_defaults_and_writes_a_file_the_library_reads(tmp_path, monkeypatch):
    monkeypatch.setattr(tuned, "TUNED_DIR", tmp_path / "tuned")
    monkeypatch.setattr(tune_gains, "RESULTS", tmp_path / "lab")
    monkeypatch.setattr(tune_gains, "HORIZON_SECONDS", 3.0)
    first = tune_gains.tune("planar_square", "gradient", trials=3, episodes=2, sampler_seed=0)
    again = tune_gains.tune("planar_square", "gradient", trials=3, episodes=2, sampler_seed=0)
    assert [h["point"] for h in first["history"]] == [h["point"] for h in again["history"]]
    record = first["record"]
    assert first["history"][0]["point"] == tune_gains.default_point("gradient", False, "planar_square")
    assert first["history"][0]["settling_time_1mm"] == record["default"]["settling_time_1mm"]  # trial 0 = defaults
    assert record["tuning_seeds"] == [tuned.TUNING_SEEDS[0], tuned.TUNING_SEEDS[1]] and record["trials"] == 3
    path = tune_gains.write_tuned("planar_square", {"gradient": record})
    assert path == tmp_path / "tuned" / "planar_square.json"
    assert tuned.load_tuned("planar_square", "gradient").point == json.loads(json.dumps(record["point"]))
    assert tune_gains.write_history("planar_square", "gradient", first["history"]).is_file()


def _episode(settle_1mm, energy, saturation=0.0, contacts=0, success=True):
    return EpisodeMetrics(success=success, final_formation_error=0.0, settling_time=0.5, control_energy=energy,
                          peak_torque=1.0, saturation_fraction=saturation, min_singularity_margin=0.1,
                          contact_steps=contacts, centroid_drift=0.0, mean_return=1.0, sim_time=settle_1mm + 1.0,
                          success_1mm=True, settling_time_1mm=settle_1mm, steady_worst_edge_error=1e-6)


def test_a_faster_set_that_breaks_a_constraint_scores_worse_than_the_default():
    default_episodes = [_episode(2.0, 1000.0, saturation=0.01)]
    default = tune_gains.figures(default_episodes)
    base = tune_gains.objective_value(default_episodes, default, 12.0)
    assert base == 2.0 and tune_gains.feasible(default_episodes, default)
    assert tune_gains.objective_value([_episode(1.0, 1400.0, saturation=0.01)], default, 12.0) == 1.0
    for broken in (_episode(1.0, 1600.0), _episode(1.0, 1000.0, saturation=0.5), _episode(1.0, 1000.0, contacts=1),
                   _episode(1.0, 1000.0, success=False)):
        assert not tune_gains.feasible([broken], default)
        assert tune_gains.objective_value([broken], default, 12.0) > base

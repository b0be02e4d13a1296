"""The algorithm registry: the one list of learning algorithms that every consumer reads, their hyperparameters as
checked YAML, and a variant registered here (one YAML file, one registry entry) trained through ``train.py``."""

from __future__ import annotations

import ast
import json
from pathlib import Path

import pytest

from ee_formation_env.baselines.learned.algorithms import (BUILTIN_ALGORITHMS, PACKAGE_DIR, Algorithm, algorithm,
                                                           algorithm_names, register_algorithm, unregister_algorithm)
from ee_formation_env.baselines.learned.config import TrainConfig

REPO = Path(__file__).resolve().parents[3]
NAMES = {entry.name for entry in BUILTIN_ALGORITHMS}


def spelled_lists(source: str) -> list[str]:
    """The literal tuples, lists, sets and dicts (keys) of ``source`` holding two or more algorithm names."""
    found = []
    for node in ast.walk(ast.parse(source)):
        items = node.keys if isinstance(node, ast.Dict) else getattr(node, "elts", None)
        if isinstance(node, (ast.Tuple, ast.List, ast.Set, ast.Dict)) and items is not None:
            names = [item.value for item in items if isinstance(item, ast.Constant) and item.value in NAMES]
            if len(names) >= 2:
                found.append(ast.unparse(node)[:80])
    return found


def test_no_module_but_the_registry_spells_the_list_of_algorithms():
    assert spelled_lists('classes = {"ppo": PPO, "sac": SAC}\nALGORITHMS = ("mappo", "ippo", "masac")') == [
        "{'ppo': PPO, 'sac': SAC}", "('mappo', 'ippo', 'masac')"]  # the check sees the old spellings
    registry = REPO / "baselines" / "learned" / "algorithms.py"
    sources = [path for folder in ("ee_formation_env", "baselines", "studies", "benchmarks")
               for path in sorted((REPO / folder).rglob("*.py")) if path != registry]
    spelled = {str(path.relative_to(REPO)): found for path in [*sources, REPO / "train.py"]
               if (found := spelled_lists(path.read_text(encoding="utf-8")))}
    assert not spelled, f"lists of algorithms outside algorithms.py: {spelled}"


def test_the_cli_and_the_checks_read_the_registry():
    algo = next(setting for setting in TrainConfig.settings() if setting.name == "algo")
    assert list(algo.choices) == ["ppo", "sac"]  # the ones train.py's backends train
    assert algorithm_names("benchmarl") == ("mappo", "ippo", "masac")
    assert [name for name in algorithm_names() if algorithm(name).on_policy] == ["ppo", "mappo", "ippo"]
    with pytest.raises(ValueError, match=r"^algo: expected one of \['ppo', 'sac', 'mappo', 'ippo', 'masac'\], "
                                         r"got 'td3'$"):
        algorithm("td3")
    with pytest.raises(ValueError, match=r"^algorithm: expected one of \['mappo', 'ippo', 'masac'\], got 'ppo'$"):
        algorithm("ppo", "algorithm", ("benchmarl",))
    with pytest.raises(ValueError, match="algorithm: 'sac' is already registered"):
        register_algorithm(Algorithm("sac", ("sb3",), False, "SAC", "algorithm_conf/sac.yaml"))
    with pytest.raises(SystemExit):
        TrainConfig.from_args(["--algo", "mappo"])  # BenchMARL's: not train.py's
    with pytest.raises(ValueError, match="^--backend rllib supports --algo ppo only$"):
        TrainConfig().with_settings({"algo": "sac", "backend": "rllib", "n_workers": 0}).resolved()


def test_every_algorithm_has_its_hyperparameter_file_in_the_package():
    for entry in BUILTIN_ALGORITHMS:
        assert entry.hyperparameter_path.is_file(), entry
        assert entry.hyperparameter_path.is_relative_to(PACKAGE_DIR)


@pytest.fixture
def variant(tmp_path):
    """``ppo-small``: SB3's PPO with its own hyperparameters, registered for the test only."""
    path = tmp_path / "ppo-small.yaml"
    path.write_text("gae_lambda: 0.9\nclip_range: 0.1\nbatch_size: 32\n")
    entry = register_algorithm(Algorithm("ppo-small", ("sb3",), True, "PPO", str(path)))
    try:
        yield entry
    finally:
        unregister_algorithm(entry.name)


@pytest.mark.parametrize("text, message", [
    ("gae_lambda: 0.9\nclip_rnage: 0.1\n", r"ppo-small.yaml: clip_rnage: unknown key for PPO \(accepted: .*"),
    ("batch_size: 32.5\n", r"ppo-small.yaml: batch_size: expected a value of the type of 64, got 32.5"),
    ("normalize_advantage: 1\n", r"ppo-small.yaml: normalize_advantage: expected a value of the type of True"),
    ("n_steps: 64\n", r"ppo-small.yaml: n_steps: unknown key for PPO"),  # the run's own setting
    ("- 1\n", r"ppo-small.yaml: expected a mapping of hyperparameters, got list"),
    ("a: [\n", r"ppo-small.yaml: unreadable hyperparameters"),
])
def test_a_faulty_hyperparameter_file_names_the_file_and_the_key(variant, text, message):
    pytest.importorskip("stable_baselines3")
    from ee_formation_env.baselines.learned.sb3_backend import build_sb3_model, sb3_hyperparameters

    variant.hyperparameter_path.write_text(text)
    with pytest.raises(ValueError, match=message):
        sb3_hyperparameters(variant)
    args = TrainConfig.from_args(["--algo", "ppo-small", "--n-workers", "0", "--no-progress"])
    with pytest.raises(ValueError, match=message):  # read before any env starts
        build_sb3_model(args, None)


def test_the_shipped_hyperparameters_reach_sb3():
    pytest.importorskip("stable_baselines3")
    from ee_formation_env.baselines.learned.sb3_backend import build_sb3_model

    flags = ["--mode", "torque", "--recipe", "none", "--n-envs", "1", "--n-workers", "0", "--no-progress"]
    sac = build_sb3_model(TrainConfig.from_args([*flags, "--algo", "sac"]), None)
    try:
        assert (sac.learning_rate, sac.buffer_size, sac.batch_size, sac.learning_starts) == (3e-4, 200_000, 256, 2_000)
        assert (sac.train_freq.frequency, sac.gradient_steps) == (1, 1)
    finally:
        sac.get_env().close()
    ppo = build_sb3_model(TrainConfig.from_args([*flags, "--n-steps", "64"]), None)
    try:  # one copy of 4 agents: 256 agent steps per update, the minibatch capped at them
        assert (ppo.gae_lambda, ppo.clip_range(1.0), ppo.batch_size, ppo.vf_coef, ppo.ent_coef,
                ppo.max_grad_norm) == (0.95, 0.2, 256, 0.5, 0.0, 0.5)
    finally:
        ppo.get_env().close()


def test_a_variant_is_one_yaml_file_and_one_entry_and_trains_through_train_py(variant, tmp_path):
    pytest.importorskip("stable_baselines3")
    from ee_formation_env.baselines.cli import train_command
    from ee_formation_env.baselines.learned.sb3_backend import build_sb3_model

    flags = ["--algo", "ppo-small", "--mode", "torque", "--recipe", "none", "--n-envs", "1", "--n-workers", "0",
             "--n-steps", "64", "--no-progress"]
    model = build_sb3_model(TrainConfig.from_args(flags), None)
    try:
        assert (model.gae_lambda, model.clip_range(1.0), model.batch_size) == (0.9, 0.1, 32)
    finally:
        model.get_env().close()
    run_dir = tmp_path / "run"
    assert train_command([*flags, "--total-timesteps", "256", "--out", str(run_dir), "--eval-episodes", "1",
                          "--eval-seconds", "0.1", "--eval-workers", "0"]) == 0
    assert json.loads((run_dir / "config.json").read_text())["algo"] == "ppo-small"
    assert json.loads((run_dir / "model" / "policy.json").read_text())["algo"] == "ppo-small"
    assert json.loads((run_dir / "comparison.json").read_text())["results"]["learned"]["episodes"] == 1

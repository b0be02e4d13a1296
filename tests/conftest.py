"""Shared fixtures: an env factory that closes every env it made, and scenario helpers."""

from __future__ import annotations

import os
import platform
from importlib.metadata import version
from pathlib import Path


def _same_float_kernels_on_every_x86_machine() -> None:
    """Pin the float paths that are chosen per CPU when numpy and torch load: OpenBLAS's kernels (the matmuls of
    the observations), numpy's SIMD ceiling, torch's kernel dispatch and MKL's code path. The pinned digests are bit-level; without this an AVX-512 machine
    computes other last bits than an AVX2 one (docs/physics.md, "The same bits on another machine")."""
    if platform.machine() not in ("x86_64", "AMD64"):
        return
    try:
        flags = Path("/proc/cpuinfo").read_text().split()
    except OSError:
        return
    if "avx2" not in flags or "fma" not in flags:
        return  # a machine without Haswell's instructions cannot run its kernels
    os.environ.setdefault("OPENBLAS_CORETYPE", "Haswell")
    major, minor = (int(part) for part in version("numpy").split(".")[:2])
    avx512 = ("X86_V4 AVX512_ICL AVX512_SPR" if (major, minor) >= (2, 4) else
              "AVX512F AVX512CD AVX512_KNL AVX512_KNM AVX512_SKX AVX512_CLX AVX512_CNL AVX512_ICL AVX512_SPR")
    os.environ.setdefault("NPY_DISABLE_CPU_FEATURES", avx512)
    # torch picks its kernels per CPU too (the training digests): its own dispatch ceiling, and for its matrix
    # products MKL's code path that gives the same bits on every x86 vendor (MKL's "compatible" branch).
    os.environ.setdefault("ATEN_CPU_CAPABILITY", "avx2")
    os.environ.setdefault("MKL_CBWR", "COMPATIBLE")


_same_float_kernels_on_every_x86_machine()  # before numpy is imported, here or by any test module

import copy  # noqa: E402
from typing import Any, Callable

import numpy as np
import pytest

import ee_formation_env
from ee_formation_env.scenario import builtin_scenario

#: Short episodes keep the suite fast; every test that needs more asks for it explicitly.
SHORT = 0.5


@pytest.fixture
def make_env() -> Callable[..., ee_formation_env.FormationEnv]:
    """``make_env(scenario, render_mode=None, **overrides)``: a FormationEnv closed at teardown."""
    envs: list[Any] = []

    def factory(scenario: Any = "planar_square", render_mode: str | None = None, **overrides: Any):
        overrides.setdefault("episode_seconds", SHORT)
        env = ee_formation_env.parallel_env(scenario, render_mode=render_mode, **overrides)
        envs.append(env)
        return env

    yield factory
    for env in envs:
        env.close()


@pytest.fixture
def closer() -> Callable[[Any], Any]:
    """``closer(obj)`` registers any object with a ``close()`` for teardown and returns it."""
    objects: list[Any] = []

    def register(obj: Any) -> Any:
        objects.append(obj)
        return obj

    yield register
    for obj in objects:
        obj.close()


def scenario_dict(name: str = "planar_square", **changes: Any) -> dict[str, Any]:
    """A fresh plain-data copy of a built-in scenario with top-level keys replaced."""
    data = copy.deepcopy(builtin_scenario(name))
    data.update(changes)
    return data


def read_state(arm: Any) -> tuple[np.ndarray, np.ndarray]:
    """Joint positions (rad) and velocities (rad/s) of an env arm's chain joints, as arrays."""
    positions, velocities = arm.read_state_lists()
    return np.array(positions), np.array(velocities)


def apply_torques(arm: Any, torques: list[float]) -> None:
    """Joint torques (N m) on an env arm for the next physics step only (what the env's stepper sends)."""
    import pybullet

    body, joints, forces = arm.torque_command(torques)
    pybullet.setJointMotorControlArray(body, joints, pybullet.TORQUE_CONTROL, forces=forces,
                                       physicsClientId=arm.world.client)


def nominal_initial_q(env: Any, agent: str) -> np.ndarray:
    """The scenario's initial joint positions of ``agent`` (rad), before reset noise, as the env's task holds them."""
    return env.task.initial_q[env.task.agent_index(agent)].copy()


def random_actions(env: Any, rng: np.random.Generator, agents: list[str] | None = None,
                   scale: float = 1.0) -> dict[str, np.ndarray]:
    """A uniform [-scale, scale] action per agent from a numpy generator (reproducible streams)."""
    agents = env.agents if agents is None else agents
    return {a: (scale * rng.uniform(-1.0, 1.0, env.action_space(a).shape)).astype(np.float32) for a in agents}


def two_planar_arms(**changes: Any) -> dict[str, Any]:
    """Two planar arms with bases 3 m apart, one displacement edge, dim 2.

    Arm 1 is arm 0 turned by pi about z. Both upper arms point up (+y), the forearms lean toward each other:
    the end-effectors start 0.2 m apart at (1.398, 2.044) and (1.602, 2.044), without contact. Opening
    the elbows (joint 2 torque +/- for arm 0/1, :data:`CLOSING`) makes the forearms collide.
    """
    data = {
        "arms": [
            {"robot": "planar_2link", "base_position": [0.0, 0.0, 0.0], "initial_q": [np.pi / 2, -1.2]},
            {"robot": "planar_2link", "base_position": [3.0, 0.0, 0.0], "base_rpy": [0.0, 0.0, np.pi],
             "initial_q": [-np.pi / 2, 1.2]},
        ],
        "edges": [[0, 1]],
        "shape": [[0.0, 0.0], [1.0, 0.0]],
        "formation": "displacement",
        "dim": 2,
        "gravity": [0.0, 0.0, -9.81],
        "initial_q_noise": 0.0,
    }
    data.update(changes)
    return data


#: Actions that drive the two arms of :func:`two_planar_arms` into each other.
CLOSING = {"arm_0": np.array([0.0, 0.3], np.float32), "arm_1": np.array([0.0, -0.3], np.float32)}


def mixed_team() -> dict[str, Any]:
    """A planar_2link arm and a KUKA iiwa in one displacement formation: agents with different spaces."""
    return {
        "arms": [{"robot": "planar_2link", "base_position": [0, 0, 0], "initial_q": [0.0, 1.0]},
                 {"urdf": "kuka_iiwa/model.urdf", "ee_link": "lbr_iiwa_link_7", "base_position": [1.0, 0, 0],
                  "initial_q": [0, 0.5, 0, -1.2, 0, 0.6, 0]}],
        "edges": [[0, 1]], "shape": [[0, 0, 0], [0.2, 0, 0]], "formation": "displacement", "dim": 3,
        "arm_collisions": False,  # the planar arm's first link starts through the kuka's base
    }


def tiny_benchmarl_config(save_folder: Any) -> Any:
    """BenchMARL's ExperimentConfig for a smoke test: 2 iterations of 40 frames on 2 copies, one epoch, no
    evaluation, loggers, JSON or checkpoint (needs the torchrl extra)."""
    from benchmarl.experiment import ExperimentConfig

    config = ExperimentConfig.get_from_yaml()
    config.max_n_iters, config.max_n_frames = 2, None
    config.on_policy_collected_frames_per_batch = 40
    config.on_policy_n_envs_per_worker = 2
    config.on_policy_n_minibatch_iters = 1
    config.on_policy_minibatch_size = 20
    config.evaluation, config.render, config.loggers, config.create_json = False, False, [], False
    config.checkpoint_at_end = False
    config.save_folder = str(save_folder)
    return config


@pytest.fixture
def open_loop(make_env) -> Callable[..., tuple[Any, list[tuple[Any, Any, Any]]]]:
    """``open_loop(scenario, steps=15, seed=2, **overrides)``: an env (``make_env``'s) reset with ``seed`` and
    stepped ``steps`` times with seeded random torques (the same whatever the overrides change), and the
    record ``[(observations, rewards, infos), ...]`` from the reset on (rewards None at the reset)."""

    def run(scenario: Any, steps: int = 15, seed: int = 2, **overrides: Any):
        env = make_env(scenario, **overrides)
        observations, infos = env.reset(seed=seed)
        rng = np.random.default_rng(0)
        record = [(observations, None, infos)]
        for _ in range(steps):
            actions = {a: rng.uniform(-0.3, 0.3, env.action_space(a).shape).astype(np.float32) for a in env.agents}
            observations, rewards, _, _, infos = env.step(actions)
            record.append((observations, rewards, infos))
        return env, record

    return run


@pytest.fixture
def lockstep(make_env, closer) -> Callable[..., int]:
    """``lockstep(scenario, overrides, steps=25, check=None)``: a batched env of two copies (seeds 5 and 9) and
    two single envs reset with those seeds, driven by the same random actions through their autoresets
    (``overrides`` should make episodes short); asserts that every copy's observations (and final
    observations) and rewards are the single env's bit for bit, calls ``check(batched, singles, k)`` after
    each step (after a single env's reset where its episode ended) for what a test compares besides, and
    returns how many episodes ended."""

    def run(scenario: Any, overrides: dict[str, Any], steps: int = 25,
            check: Callable[[Any, list[Any], int], None] | None = None) -> int:
        seeds = [5, 9]
        batched = closer(ee_formation_env.vector_env(scenario, num_envs=2, **overrides))
        singles = [make_env(scenario, **overrides) for _ in seeds]
        result = batched.reset_arrays(seed=seeds)
        agents = batched.possible_agents
        for k, single in enumerate(singles):
            observations, _ = single.reset(seed=seeds[k])
            assert result.observations[k].tobytes() == np.concatenate([observations[a] for a in agents]).tobytes()
        slices = batched.joint_slices
        rng = np.random.default_rng(1)
        ends = 0
        for _ in range(steps):
            actions = rng.uniform(-0.5, 0.5, (2, batched.n_joints)).astype(np.float32)
            result = batched.step_arrays(actions)
            for k, single in enumerate(singles):
                observations, rewards, *_ = single.step({a: actions[k, part] for a, part in zip(agents, slices)})
                final = np.concatenate([observations[a] for a in agents])
                assert result.infos["final_observation"][k].tobytes() == final.tobytes()
                assert result.rewards[k].tolist() == [rewards[a] for a in agents]
                if not single.agents:
                    ends += 1
                    observations, _ = single.reset()
                assert result.observations[k].tobytes() == np.concatenate([observations[a] for a in agents]).tobytes()
                if check is not None:
                    check(batched, singles, k)
        return ends

    return run


#: A tuned point of law I (baselines/reference/tuned.py): twice the default K_P, the rest the defaults'.
TUNED_POINT = {"kp_scale": 2.0, "kd_scale": 1.0, "saturated": False, "spring_scale": 1.0, "rate_steps": 0.0}


def write_tuned_file(folder: Path, scenario: str = "planar_square", laws: dict[str, Any] | None = None,
                     **changes: Any) -> Path:
    """A tuned-gains file of built-in ``scenario`` in ``folder`` (monkeypatched as ``tuned.TUNED_DIR``): ``laws``
    (default: ``gradient`` at :data:`TUNED_POINT`, improved), the file's other fields replaced by ``changes``."""
    import json

    from ee_formation_env.baselines.reference import tuned

    data = {"schema": tuned.TUNED_SCHEMA, "scenario": scenario,
            "scenario_digest": tuned.scenario_digest(builtin_scenario(scenario)),
            "laws": laws if laws is not None else {"gradient": {"point": dict(TUNED_POINT), "improved": True}},
            **changes}
    Path(folder).mkdir(parents=True, exist_ok=True)
    path = Path(folder) / f"{scenario}.json"
    path.write_text(json.dumps(data))
    return path

"""The PhysicsWorld wrapper: held torques over several physics steps in one call are the per-step loop, bit for bit."""

from __future__ import annotations

import numpy as np
import pybullet
import pytest

import ee_formation_env


def _joint_states(world, arms):
    return np.array([s[:2] for arm in arms
                     for s in pybullet.getJointStates(arm.body, arm.joint_indices, physicsClientId=world.client)])


# (scenario, reset seed, whether the arms touch under the torques below: contacts are part of what must match)
CASES = [("planar_square", 0, False), ("spatial_random", 1, True)]


@pytest.mark.parametrize("scenario, seed, touching", CASES)
def test_one_call_with_substeps_is_the_loop_of_single_steps_bit_for_bit(scenario, seed, touching):
    env = ee_formation_env.vector_env(scenario, num_envs=1)
    try:
        env.reset(seed=seed)
        world, arms = env.world(0), env.arm_set(0).arms
        frame_skip = env.scenario.frame_skip
        start = pybullet.saveState(physicsClientId=world.client)
        rng = np.random.default_rng(1)
        # half the effort limit (at most 50 N m), a random sign per joint and step: the arms swing widely
        torques = [[np.sign(rng.normal(size=arm.n_joints)) * 0.5 * np.minimum(arm.model.effort_limits, 50.0)
                    for arm in arms] for _ in range(150)]
        trajectories, contacts = [], []
        for substeps in (False, True, False):
            pybullet.restoreState(stateId=start, physicsClientId=world.client)
            states, contact_points = [], 0
            for command in torques:
                commands = [arm.torque_command(t.tolist()) for arm, t in zip(arms, command)]
                if substeps:
                    world.step_with_torques(commands, frame_skip)
                else:  # what the env did before: the torques re-sent before every single step
                    for _ in range(frame_skip):
                        for body, joints, values in commands:
                            pybullet.setJointMotorControlArray(body, joints, pybullet.TORQUE_CONTROL, forces=values,
                                                               physicsClientId=world.client)
                        world.step()
                states.append(_joint_states(world, arms))
                contact_points += len(world.contact_pairs())
            trajectories.append(np.array(states))
            contacts.append(contact_points)
        assert (contacts[0] > 0) == touching and contacts[0] == contacts[1] == contacts[2]
        assert np.abs(trajectories[0][-1] - trajectories[0][0]).max() > 0.1  # the arms moved
        np.testing.assert_array_equal(trajectories[1], trajectories[0])
        np.testing.assert_array_equal(trajectories[2], trajectories[0])  # single steps again after substeps
    finally:
        env.close()

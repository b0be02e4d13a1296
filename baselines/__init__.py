"""Baselines of ee-formation-env: the reference policies (this module's registry), the metrics, and the wings
``reference`` (the paper's three laws, their gains rule, nominal dynamics) and ``learned`` (training).

    import ee_formation_env
    from ee_formation_env.baselines import make_policies
    env = ee_formation_env.parallel_env("planar_square")
    policies = make_policies("adaptive_jacobian", env)   # one per agent; also "gradient", "approx_jacobian", ...

The policies: :data:`POLICIES` (the laws of :data:`REFERENCE_CONTROLLERS`, plus ``zero`` and ``random``). The laws
are in :mod:`ee_formation_env.baselines.reference.controllers`, the gains rule in
:mod:`ee_formation_env.baselines.reference.gains`; docs/controllers.md explains both.
"""

from __future__ import annotations

if __name__ != "ee_formation_env.baselines":  # the folder is installed inside the env's package, under one name
    raise ImportError(f"this folder is the package ee_formation_env.baselines: import that, not {__name__!r}")

import inspect
from typing import Any, Mapping

import numpy as np

from ee_formation_env.baselines.reference.controllers import (AdaptiveJacobianController, AgentModel,
                                                              ApproxJacobianController, FormationController, Gains,
                                                              GradientController)
from ee_formation_env.baselines.reference.team import RandomPolicy, ZeroPolicy
from ee_formation_env.baselines.reference.dynamics import nominal_dynamics
from ee_formation_env.baselines.reference.gains import default_gains
from ee_formation_env.env import FormationEnv

#: The paper's laws I, II and III by name: the one registry of reference controllers (each class's ``name``).
REFERENCE_CONTROLLERS: dict[str, type[FormationController]] = {
    cls.name: cls for cls in (GradientController, ApproxJacobianController, AdaptiveJacobianController)}
MODEL_BASED_POLICIES: tuple[str, ...] = tuple(REFERENCE_CONTROLLERS)
POLICIES: tuple[str, ...] = (*MODEL_BASED_POLICIES, ZeroPolicy.name, RandomPolicy.name)


def controller_options(name: str) -> tuple[str, ...]:
    """The options of reference controller ``name``: the keyword arguments of its class after the gains and
    the initial estimate (read from the class, so a new option needs no registration)."""
    parameters = list(inspect.signature(REFERENCE_CONTROLLERS[name].__init__).parameters)
    return tuple(parameters[parameters.index("a_hat0") + 1:])


__all__ = ["POLICIES", "MODEL_BASED_POLICIES", "REFERENCE_CONTROLLERS", "Gains", "make_policy", "make_policies",
           "make_controller", "controller_options", "agent_model", "default_gains"]


def agent_model(env: FormationEnv, agent: str) -> AgentModel:
    """What ``agent`` knows about itself in ``env``: nominal models, mounting, limits and control step."""
    task = env.task
    i = task.agent_index(agent)
    chain = task.models[i]
    return AgentModel(
        layout=env.observation_layout(agent),
        formation_kind=task.formation.kind,
        chain=chain,
        dynamics=nominal_dynamics(task.scenario.arms[i].urdf, chain.joint_names),
        gravity_in_base=task.gravity_in_base_frame(i),
        torque_limits=task.torque_limits[i],
        control_dt=task.scenario.control_dt,
    )


def make_policy(name: str, env: FormationEnv, agent: str, gains: Gains | Mapping[str, Any] | str | None = None,
                a_hat0: Any = None, seed: int = 0, **options: Any):
    """A reference policy for one agent: ``reset()`` and ``__call__(observation) -> action``.

    ``gains``: a :class:`Gains`, or a dict of overrides of the defaults for this scenario
    (:func:`ee_formation_env.baselines.reference.gains.default_gains`); on a scenario distribution the defaults
    are those of the env's current draw, taken again at every ``reset()`` of the policy (after the env's);
    ``"tuned"``: the law's tuned gains for the env's built-in scenario
    (:mod:`ee_formation_env.baselines.reference.tuned`; ``ValueError`` where there are none), per draw on a
    distribution. ``a_hat0``: initial kinematic estimate (default: the nominal
    URDF's parameters). ``options``: controller options: ``anti_windup`` (``approx_jacobian`` and
    ``adaptive_jacobian``), ``projection`` and ``parameter_bounds`` (``adaptive_jacobian``; default box
    ``[0.5, 2] x`` the nominal parameters), see :mod:`ee_formation_env.baselines.reference.controllers`. ``seed`` seeds ``random``.
    """
    if name not in POLICIES:
        raise ValueError(f"policy: unknown policy {name!r}; available: {list(POLICIES)}")
    model = agent_model(env, agent)
    if name == "zero":
        return ZeroPolicy(model.chain.n_joints)
    if name == "random":
        return RandomPolicy(model.chain.n_joints, seed=seed + env.task.agent_index(agent))
    if env.scenario.gravity_compensation:  # the env would add g(q) to a torque that already holds the law's own
        raise ValueError(f"policy: {name} sends the paper's raw joint torques; evaluate it on the scenario with "
                         "gravity_compensation: false")
    index = env.task.agent_index(agent)
    if isinstance(gains, str):
        if gains != "tuned":
            raise ValueError(f"gains: expected a Gains, a dict, None or 'tuned', got {gains!r}")
        from ee_formation_env.baselines.reference.tuned import tuned_gains_source

        source = tuned_gains_source(env, index, name)
        controller = make_controller(name, model, source(), a_hat0, **options)
        if env.scenario.distribution.active:  # each draw its own gains, taken at every reset
            controller.gains_source = source
        return controller
    follow = gains is None or isinstance(gains, Mapping)
    if follow:
        updates = dict(gains or {})
        gains = default_gains(env.task, index).with_updates(**updates)
    elif not isinstance(gains, Gains):
        raise TypeError(f"gains: expected a Gains, a dict, None or 'tuned', got {type(gains).__name__}")
    controller = make_controller(name, model, gains, a_hat0, **options)
    if follow and env.scenario.distribution.active:  # each draw its own gains, taken at every reset
        controller.gains_source = lambda: default_gains(env.task, index).with_updates(**updates)
    return controller


def make_controller(name: str, model: AgentModel, gains: Gains, a_hat0: Any = None, **options: Any
                    ) -> FormationController:
    """Reference controller ``name`` on an explicit agent model and gains: the seam for a controller whose
    nominal model differs from the env's (model-mismatch studies). :func:`make_policy` builds on it."""
    if name not in REFERENCE_CONTROLLERS:
        raise ValueError(f"controller: unknown controller {name!r}; available: {list(REFERENCE_CONTROLLERS)}")
    allowed = controller_options(name)
    unknown = set(options) - set(allowed)
    if unknown:
        raise ValueError(f"options: {name} takes {list(allowed) or 'no options'}, got {sorted(unknown)}")
    return REFERENCE_CONTROLLERS[name](model, gains, None if a_hat0 is None else np.asarray(a_hat0, dtype=np.float64),
                                       **options)


def make_policies(name: str, env: FormationEnv, **kwargs: Any) -> dict[str, Any]:
    """One policy of kind ``name`` per agent of ``env`` (same arguments as :func:`make_policy`)."""
    return {agent: make_policy(name, env, agent, **kwargs) for agent in env.possible_agents}

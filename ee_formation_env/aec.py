"""The AEC (agent-by-agent) form of the env: PettingZoo's ``parallel_to_aec`` conversion, checking each action
when it is given.

PettingZoo's converter buffers each agent's action and steps the parallel env at the last agent, so a bad
action (NaN, wrong shape, strings) of the first agent surfaced one call later, at the last agent, and then on
every step until ``reset()``. :class:`FormationAECEnv` checks each action with the env's own check
(:meth:`~ee_formation_env.env.FormationEnv.check_action`) before buffering it: the error is raised at the call
that received it, names that agent, and changes nothing, so the next valid action continues the episode.
"""

from __future__ import annotations

from typing import Any

from pettingzoo.utils.conversions import parallel_to_aec_wrapper

from ee_formation_env.env import FormationEnv


class FormationAECEnv(parallel_to_aec_wrapper):
    """``parallel_to_aec_wrapper`` over a :class:`FormationEnv` whose ``step`` refuses a bad action at once."""

    def __init__(self, parallel_env: FormationEnv):
        super().__init__(parallel_env)

    def step(self, action: Any) -> None:
        agent = self.agent_selection
        if action is not None and not (self.terminations[agent] or self.truncations[agent]):
            self.env.check_action(agent, action)  # ValueError naming the agent; nothing buffered
        super().step(action)

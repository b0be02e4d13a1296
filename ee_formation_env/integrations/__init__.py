"""Adapters of the env to other frameworks, each importing its framework only when used.

- :mod:`ee_formation_env.integrations.centralized`: a Gymnasium single-agent view (one joint observation and action);
- :mod:`ee_formation_env.integrations.sb3`: the Stable-Baselines3 VecEnv with one slot per agent (parameter sharing);
- :mod:`ee_formation_env.integrations.torchrl`: TorchRL's ``PettingZooWrapper`` with agents grouped by robot;
- :mod:`ee_formation_env.integrations.benchmarl`: a BenchMARL task.

None of them imports the reference controllers or the learning tools (``ee_formation_env.baselines``): where a
framework needs a learning tool (a residual env), the learning wing hands it a wrapped env.

Usage: see docs/training.md; import paths, old and new: docs/api.md.
"""

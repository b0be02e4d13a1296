"""Deprecated alias of :mod:`ee_formation_env.integrations.benchmarl` (kept until 2027-06-01, removed in version 0.3)."""

from ee_formation_env._deprecated import forward

__getattr__ = forward(__name__, "ee_formation_env.integrations.benchmarl")

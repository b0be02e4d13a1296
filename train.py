"""Train a shared formation policy and compare it with the reference controllers on the same metrics.

    python train.py                                   # default: residual PPO on planar_square, 3-9 min on 2 cores
    python train.py --mode torque                     # the policy outputs the torques itself
    python train.py --backend rllib --total-timesteps 20000
    python train.py --eval-only runs/<name>           # re-evaluate a saved run

The same command as ``ee-formation train``; ``python train.py --help`` lists the flags. The training code is the
library :mod:`ee_formation_env.baselines.learned` (configuration, backends, imitation, loading, comparison);
docs/training.md describes the modes, the presets and what a run writes.
"""

import sys

from ee_formation_env.baselines.cli import train_command

if __name__ == "__main__":
    sys.exit(train_command())

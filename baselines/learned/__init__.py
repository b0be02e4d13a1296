"""Learning tools: training envs (residual, features, shaping), imitation, backends, loading and comparison."""

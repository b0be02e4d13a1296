"""Interval statistics of the studies: the interquartile mean and the stratified bootstrap (rliable's
estimators, in a few lines of numpy), one (scenario, method) metric aggregated over training runs, and the
Wilson score interval of a success rate.
docs/scoreboard.md says how the board uses them."""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

BOOTSTRAP_REPS = 2000  # bootstrap replicates per interval


def interquartile_mean(values: np.ndarray, axis: int | None = None) -> np.ndarray:
    """The mean of the middle 50 % (``int(n / 4)`` values trimmed at each end, as ``scipy.stats.trim_mean(x,
    0.25)`` and rliable's IQM), over the flattened array or along ``axis``."""
    values = np.sort(np.asarray(values, dtype=np.float64), axis=axis)
    if axis is None:
        values = values.ravel()
        axis = 0
    n = values.shape[axis]
    cut = int(0.25 * n)
    return np.take(values, np.arange(cut, n - cut), axis=axis).mean(axis=axis)


def stratified_bootstrap(scores: np.ndarray, reps: int = BOOTSTRAP_REPS, seed: int = 0, confidence: float = 0.95
                         ) -> dict[str, tuple[float, float]]:
    """95 % percentile intervals of the mean and the IQM of ``scores`` (runs, strata): each replicate resamples
    the runs with replacement within every stratum independently (rliable's ``StratifiedBootstrap``).
    ``{"mean": (low, high), "iqm": (low, high)}``."""
    scores = np.asarray(scores, dtype=np.float64)
    if scores.ndim != 2 or not scores.size:
        raise ValueError(f"scores: expected a non-empty (runs, strata) array, got shape {scores.shape}")
    runs, strata = scores.shape
    rng = np.random.default_rng(seed)
    picks = rng.integers(0, runs, size=(reps, runs, strata))
    samples = scores[picks, np.arange(strata)]  # (reps, runs, strata)
    flat = samples.reshape(reps, -1)
    tail = 100 * (1 - confidence) / 2
    out = {}
    for name, values in (("mean", flat.mean(axis=1)), ("iqm", interquartile_mean(flat, axis=1))):
        low, high = np.percentile(values, [tail, 100 - tail])
        out[name] = (float(low), float(high))
    return out


def aggregate(per_run: Sequence[Sequence[float]]) -> dict[str, Any]:
    """One metric of one (scenario, method): ``per_run`` holds each training run's per-episode values (all of
    the same evaluation episodes). Mean, IQM, their 95 % intervals and each run's mean."""
    scores = np.array(per_run, dtype=np.float64)
    # One run (a reference controller): the episodes are what varies, so they are resampled.
    strata = scores.T if len(scores) == 1 else scores
    intervals = stratified_bootstrap(strata)
    return {"mean": float(scores.mean()), "iqm": float(interquartile_mean(scores)),
            "ci_low": intervals["mean"][0], "ci_high": intervals["mean"][1],
            "iqm_ci_low": intervals["iqm"][0], "iqm_ci_high": intervals["iqm"][1],
            "per_seed": [float(np.mean(run)) for run in scores]}


def wilson_interval(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """The 95 % Wilson score interval of a success rate (a fraction in [0, 1]); (nan, nan) for n = 0."""
    if n == 0:
        return math.nan, math.nan
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return max(0.0, centre - half), min(1.0, centre + half)

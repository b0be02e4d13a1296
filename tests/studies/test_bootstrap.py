"""studies.bootstrap: the interquartile mean, the stratified bootstrap and the aggregate of one metric."""

from __future__ import annotations

import numpy as np
import pytest

from studies import bootstrap


def test_interquartile_mean_trims_a_quarter_at_each_end():
    assert bootstrap.interquartile_mean(np.arange(8.0)) == pytest.approx(np.mean([2, 3, 4, 5]))
    assert bootstrap.interquartile_mean(np.array([[0, 1, 2, 100.0]]), axis=1)[0] == pytest.approx(1.5)


def test_stratified_bootstrap_resamples_runs_within_each_stratum():
    # Every stratum holds the same two values across runs: any resample's mean lies between them.
    scores = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    intervals = bootstrap.stratified_bootstrap(scores, reps=500)
    low, high = intervals["mean"]
    assert 0.0 <= low < 0.5 < high <= 1.0
    constant = bootstrap.stratified_bootstrap(np.full((3, 4), 2.5), reps=50)
    assert constant["mean"] == (2.5, 2.5) and constant["iqm"] == (2.5, 2.5)
    # Strata are never mixed: with one run per stratum nothing varies.
    assert bootstrap.stratified_bootstrap(np.array([[0.0, 10.0]]), reps=50)["mean"] == (5.0, 5.0)
    with pytest.raises(ValueError, match="scores: expected a non-empty"):
        bootstrap.stratified_bootstrap(np.zeros(3))


def test_aggregate_resamples_episodes_of_a_single_run():
    metric = bootstrap.aggregate([[0.0, 1.0, 1.0, 1.0]])
    assert metric["mean"] == 0.75 and metric["per_seed"] == [0.75]
    assert metric["ci_low"] < 0.75 < metric["ci_high"] or metric["ci_high"] == 1.0

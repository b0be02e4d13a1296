"""The verdict rule (baselines/verdict.py): who beats a law, and the trade-offs and shortfalls it names."""

from __future__ import annotations

import pytest

from ee_formation_env.baselines.verdict import VERDICT_METRICS, best_law, estimates, judge, shortfalls


def _estimates(**means):
    values = {"success": 1.0, "settle_1mm": 1.0, "steady_worst": 1e-9, "contacts": 0.0, "energy": 6000.0,
              "min_sigma": 0.2, "return": 5000.0, **means}
    spread = {"settle_1mm": 0.05, "return": 50.0}
    return {key: {"mean": value, "ci_low": value - spread.get(key, 0.0), "ci_high": value + spread.get(key, 0.0)}
            for key, value in values.items()}


def test_a_faster_precise_frugal_candidate_beats_the_law():
    verdict = judge(_estimates(settle_1mm=0.5, energy=8000.0), _estimates())
    assert verdict.beats and verdict.text() == "yes"


@pytest.mark.parametrize("candidate, loss", [
    (dict(settle_1mm=0.95), "intervals overlap"),
    (dict(settle_1mm=1.5), "(slower)"),
    (dict(settle_1mm=0.5, success=0.9), "success 90% < 100%"),
    (dict(settle_1mm=0.5, steady_worst=4.5e-3), "steady worst edge 4.5 mm > 1 mm"),
    (dict(settle_1mm=0.5, contacts=3.0), "contacts 3.0 > 0.0"),
    (dict(settle_1mm=0.5, energy=9001.0), "energy 1.5x the law's"),
])
def test_each_condition_of_the_rule_is_a_named_loss(candidate, loss):
    verdict = judge(_estimates(**candidate), _estimates())
    assert not verdict.beats and any(loss in item for item in verdict.losses), verdict.losses


def test_a_trade_off_is_named_both_ways():
    # torque-ppo on planar_square's archived cells: slower to 1 mm but a fraction of the law's energy
    verdict = judge(_estimates(settle_1mm=2.0, energy=650.0), _estimates(energy=6600.0))
    assert "to 1 mm 2.00 s vs 1.00 s (slower)" in verdict.text() and "better: energy 0.098x the law's" in verdict.text()


def test_shortfalls_name_each_threshold_and_nothing_when_none_is_crossed():
    assert shortfalls(_estimates(), _estimates()) == []
    found = shortfalls(_estimates(steady_worst=9e-3, min_sigma=5.8e-6, **{"return": 4068.0}, energy=10_000.0,
                                  contacts=1.0), _estimates(**{"return": 5856.0}))
    assert [item["metric"] for item in found] == ["steady_worst", "min_sigma", "return", "energy", "contacts"]
    # a law that is itself imprecise does not make precision a shortfall
    assert shortfalls(_estimates(steady_worst=9e-3), _estimates(steady_worst=2e-2)) == []


def test_estimates_and_the_best_law_from_episode_records():
    episodes = [{"success": True, "success_1mm": True, "settling_time_1mm": t, "steady_worst_edge_error": 1e-6,
                 "contact_steps": 0, "control_energy": 1.0, "min_singularity_margin": 0.1, "mean_return": 1.0}
                for t in (1.0, 2.0, 3.0)]
    never = [{**e, "success_1mm": False, "settling_time_1mm": float("nan")} for e in episodes]
    fast, slow = estimates(episodes, 10.0), estimates(never, 10.0)
    assert set(fast) == set(VERDICT_METRICS)
    assert fast["settle_1mm"]["mean"] == 2.0 and 1.0 <= fast["settle_1mm"]["ci_low"] <= 2.0 <= fast["settle_1mm"]["ci_high"]
    assert slow["settle_1mm"]["mean"] == 10.0  # a band never held counts the episode length
    assert best_law({"a": slow, "b": fast}) == "b"

"""The soak benchmark runs and samples memory (its figures are read by people, not asserted on)."""

from benchmarks.soak import soak


def test_soak_samples_memory_along_the_run():
    rows = soak("planar_square", physics_steps=4_000, samples=4)
    assert len(rows) == 4
    assert rows[-1]["physics_steps"] == 4_000
    assert all(row["pybullet_clients"] >= 1 and row["rss_mb"] > 0 for row in rows)

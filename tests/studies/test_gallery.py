"""studies.gallery renders one image per built-in scenario and the two animations, with the env's own renderer."""

from __future__ import annotations

import pytest

import ee_formation_env

pytest.importorskip("imageio")

from studies import gallery  # noqa: E402


def test_quick_gallery_writes_every_image(tmp_path):
    written = gallery.main(["--quick", "--out", str(tmp_path)])
    names = {path.name for path in written}
    assert names == ({f"scenario_{name}.png" for name in ee_formation_env.BUILTIN_SCENARIOS}
                     | {"episode_planar_square.gif", "episode_spatial_tetrahedron.gif"})
    import imageio.v3 as iio
    start_and_formed = iio.imread(tmp_path / "scenario_planar_square.png")
    assert start_and_formed.shape == (48, 2 * 64 + gallery.GAP, 3)
    assert iio.imread(tmp_path / "episode_planar_square.gif", index=None).shape[0] > 2  # several frames


def test_committed_gallery_exists_and_animations_are_small():
    figures = gallery.Path(__file__).resolve().parents[2] / "docs" / "figures"
    for name in ee_formation_env.BUILTIN_SCENARIOS:
        assert (figures / f"scenario_{name}.png").is_file()
    for name in gallery.ANIMATED:
        assert (figures / f"episode_{name}.gif").stat().st_size < 2e6

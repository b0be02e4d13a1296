"""Robot descriptions shipped with ee-formation-env.

This folder is installed as the package ``ee_formation_env.assets`` so that the URDFs are found
from a wheel as well as from a source checkout. See ``README.md`` here for sources and assumptions.
"""

from pathlib import Path

ASSETS_DIR = Path(__file__).resolve().parent


def asset_path(file_name: str) -> Path:
    """Absolute path of a shipped asset file, e.g. ``asset_path("planar_2link.urdf")``."""
    return ASSETS_DIR / file_name

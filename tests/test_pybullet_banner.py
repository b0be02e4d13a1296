"""PyBullet's first import prints no banner, on standard output or error, in any process that imports the package."""

from __future__ import annotations

import subprocess
import sys


def test_importing_the_package_prints_nothing_though_pybullet_prints_a_banner_when_imported_plainly():
    plain = subprocess.run([sys.executable, "-c", "import pybullet"], capture_output=True, text=True, timeout=120)
    assert "pybullet build time" in plain.stdout + plain.stderr  # what there is to silence
    quiet = subprocess.run([sys.executable, "-c", "import ee_formation_env, pybullet; print('imported')"],
                           capture_output=True, text=True, timeout=120)
    assert quiet.returncode == 0
    assert quiet.stdout == "imported\n" and quiet.stderr == ""


def test_output_written_after_the_quiet_import_still_reaches_both_streams():
    code = ("import sys, os; import ee_formation_env; print('out'); print('err', file=sys.stderr); "
            "sys.stdout.flush(); os.write(1, b'fd1\\n'); os.write(2, b'fd2\\n')")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.stdout == "out\nfd1\n" and result.stderr == "err\nfd2\n"

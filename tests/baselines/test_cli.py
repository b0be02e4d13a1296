"""The ``ee-formation`` command: the library's subcommands and their flags (the lab's: tests/studies/test_main.py)."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import pytest

import ee_formation_env
from ee_formation_env.baselines.cli import COMMANDS, main, train_command
from ee_formation_env.baselines.evaluate import main as evaluate_main
from ee_formation_env.builtin import builtin_scenario


def test_help_lists_every_command(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--help"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    assert set(COMMANDS) == {"train", "evaluate", "validate"}  # the library's; the lab's are python -m studies
    for name in COMMANDS:
        assert name in out
    assert "python -m studies" in out


@pytest.mark.parametrize("command, flag", [("train", "--total-timesteps"), ("evaluate", "--episodes")])
def test_each_command_documents_its_own_flags(command, flag, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main([command, "--help"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    assert flag in out and f"ee-formation {command}" in out


def test_train_flags_are_those_of_train_py(capsys):
    for argv in (["train", "--help"], None):
        with pytest.raises(SystemExit):
            if argv is None:
                from ee_formation_env.baselines.cli import train_command

                train_command(["--help"])
            else:
                main(argv)
    first, second = capsys.readouterr().out.split("usage: train.py")
    flags = lambda text: sorted(word for word in text.split() if word.startswith("--"))  # noqa: E731
    assert flags(first) == flags(second)


def test_unknown_command_is_a_usage_error(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["fly"])
    assert exit_info.value.code == 2
    assert "fly" in capsys.readouterr().err


def test_the_installed_command_runs(tmp_path):
    script = subprocess.run([sys.executable, "-c", "import shutil; print(shutil.which('ee-formation') or '')"],
                            capture_output=True, text=True).stdout.strip()
    if not script:
        pytest.skip("the ee-formation script is not on PATH (package not installed)")
    result = subprocess.run([script, "--help"], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert result.returncode == 0 and "evaluate" in result.stdout


REPO = Path(__file__).resolve().parents[2]


# ------------------------------------------------------------------------------------------ every flag has help
class _Parsed(Exception):
    """Raised instead of parsing: carries the parser a command built."""


def _command_parsers(monkeypatch) -> dict[str, argparse.ArgumentParser]:
    """Each command's own parser (and the top-level one), captured as the command is about to parse."""
    import argparse as _argparse

    def capture(self, args=None, namespace=None):
        raise _Parsed(self)

    monkeypatch.setattr(_argparse.ArgumentParser, "parse_known_args", capture)
    builders = {"ee-formation": lambda: main([]), "train": lambda: train_command([]),
                "evaluate": lambda: evaluate_main([]), "validate": lambda: COMMANDS["validate"][1]([])}
    parsers = {}
    for name, build in builders.items():
        with pytest.raises(_Parsed) as parsed:
            build()
        parsers[name] = parsed.value.args[0]
    return parsers


def test_every_flag_of_every_command_has_help_text(monkeypatch):
    parsers = _command_parsers(monkeypatch)
    assert set(parsers) == {"ee-formation", *COMMANDS}
    assert any("--episodes" in action.option_strings for action in parsers["evaluate"]._actions)  # walked
    missing = [f"{name} {'/'.join(action.option_strings) or action.dest}"
               for name, parser in parsers.items() for action in parser._actions
               if not (action.help or "").strip() and not isinstance(action, argparse._SubParsersAction)]
    assert not missing, f"flags without help: {missing}"


def test_version_prints_the_package_version(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--version"])
    assert exit_info.value.code == 0
    assert capsys.readouterr().out.strip() == f"ee-formation {ee_formation_env.__version__}"


def test_validate_prints_one_ok_line_for_a_valid_scenario_and_the_error_with_status_2_otherwise(tmp_path, capsys):
    assert main(["validate", "planar_square"]) == 0
    assert capsys.readouterr().out.splitlines() == ["OK: planar_square: 4 arms, dim 2, distance formation, 5 edges"]
    unreachable = tmp_path / "far.json"
    data = builtin_scenario("planar_square")
    data["shape"] = [[0.0, 0.0], [40.0, 0.0], [40.0, 40.0], [0.0, 40.0]]
    unreachable.write_text(json.dumps(data), encoding="utf-8")
    assert main(["validate", str(unreachable)]) == 2  # load_scenario accepts it; the reach check does not
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err.startswith("error: shape: the formation is out of reach")


def test_an_interrupted_run_names_the_program_that_was_run_to_resume_it(monkeypatch, capsys):
    import ee_formation_env.baselines.learned.run as run
    from ee_formation_env.baselines.learned.interruption import TrainingInterrupted

    def stopped(config):
        raise TrainingInterrupted("runs/x", "SIGINT", 12)

    monkeypatch.setattr(run, "train", stopped)
    assert main(["train"]) == 130
    assert "`ee-formation train --resume runs/x` continues it" in capsys.readouterr().err
    assert train_command([], prog="train.py") == 130
    assert "`python train.py --resume runs/x` continues it" in capsys.readouterr().err


def test_no_command_prints_the_pybullet_banner():
    for argv in (["--help"], ["evaluate", "--help"], ["--version"]):
        result = subprocess.run([sys.executable, "-m", "ee_formation_env.baselines.cli", *argv], capture_output=True,
                                text=True, timeout=120, cwd=REPO)
        assert result.returncode == 0
        assert "pybullet build time" not in result.stdout + result.stderr, argv


def test_evaluate_refuses_json_into_a_folder_in_one_line_naming_the_flag(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["evaluate", "--policy", "zero", "--json", str(tmp_path)])
    assert exit_info.value.code == 2
    captured = capsys.readouterr()
    assert f"ee-formation evaluate: error: --json: {tmp_path} is a folder; expected the path of a file" in captured.err
    assert "Traceback" not in captured.err and captured.out == ""  # refused before the header, before any episode

"""The ``ee-formation`` command: its subcommands, their flags, and the studies' checkout rule."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from ee_formation_env.baselines.cli import COMMANDS, main


def test_help_lists_every_command(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--help"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    for name in ("train", "evaluate", "reproduce", "robustness", "random-scenarios", "sensing", "manoeuvres",
                 "scoreboard"):
        assert name in out and name in COMMANDS


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


def test_a_study_outside_a_checkout_says_where_it_runs(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["reproduce"]) == 2
    assert capsys.readouterr().err.startswith("error: reproduce: the study runs from the root of a checkout")


def test_the_installed_command_runs(tmp_path):
    script = subprocess.run([sys.executable, "-c", "import shutil; print(shutil.which('ee-formation') or '')"],
                            capture_output=True, text=True).stdout.strip()
    if not script:
        pytest.skip("the ee-formation script is not on PATH (package not installed)")
    result = subprocess.run([script, "--help"], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert result.returncode == 0 and "evaluate" in result.stdout


REPO = Path(__file__).resolve().parents[2]


def test_a_study_runs_in_a_child_process_from_the_checkout_and_reports_bad_input_in_one_line(monkeypatch, capfd):
    monkeypatch.chdir(REPO)
    path_before = list(sys.path)
    assert main(["random-scenarios", "--seeds", "0"]) == 2
    assert capfd.readouterr().err.splitlines()[-1] == "error: --seeds: expected 1 to 50, got 0"
    assert main(["sensing", "--help"]) == 0
    assert "usage: python -m studies.sensing" in capfd.readouterr().out
    assert sys.path == path_before  # the command's own import path is left as it was

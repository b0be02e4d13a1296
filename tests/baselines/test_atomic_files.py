"""baselines.atomic_files: a file is written whole or not at all, and a refused write is one line naming it."""

from __future__ import annotations

import errno
import os

import pytest

from ee_formation_env.baselines import atomic_files
from ee_formation_env.baselines.atomic_files import WriteRefused, replacing, write_text
from ee_formation_env.baselines.cli_errors import report_errors


def test_a_file_is_replaced_whole_and_no_temporary_file_is_left(tmp_path):
    path = tmp_path / "out.json"
    path.write_text("old")
    write_text(path, "new")
    assert path.read_text() == "new" and sorted(p.name for p in tmp_path.iterdir()) == ["out.json"]


@pytest.mark.parametrize("code, words", [
    (errno.EFBIG, "file too large: over this process's file-size limit (ulimit -f): raise it"),
    (errno.ENOSPC, "no space left on the device: free some room"),
    (errno.EROFS, "read-only file system"),
])
def test_a_refused_write_names_the_file_and_leaves_what_was_there(tmp_path, code, words):
    path = tmp_path / "out.json"
    path.write_text("old")
    with pytest.raises(WriteRefused) as refused:
        with replacing(path) as temporary:
            temporary.write_text("half")
            raise OSError(code, os.strerror(code))  # as write(2) says it: no file name
    assert str(refused.value) == f"cannot write {path} ({words})"
    assert refused.value.errno == code and refused.value.filename == str(path)
    assert path.read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == ["out.json"]


def test_a_refused_rename_names_the_file(tmp_path, monkeypatch):
    def read_only(source, target):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(source))

    monkeypatch.setattr(atomic_files.os, "replace", read_only)
    with pytest.raises(WriteRefused, match=f"cannot write {tmp_path / 'out.md'} \\(read-only file system\\)"):
        write_text(tmp_path / "out.md", "text")
    assert list(tmp_path.iterdir()) == []


def test_a_folder_where_the_file_goes_is_refused_before_anything_is_written(tmp_path):
    (tmp_path / "out.json").mkdir()
    written = []
    with pytest.raises(WriteRefused, match="out.json \\(a folder stands at that path: move it away\\)"):
        with replacing(tmp_path / "out.json") as temporary:
            written.append(temporary)
    assert not written and sorted(p.name for p in tmp_path.iterdir()) == ["out.json"]


def test_a_file_where_a_folder_of_the_path_goes_is_named(tmp_path):
    (tmp_path / "results").write_text("a file")
    with pytest.raises(WriteRefused, match="a file stands where a folder of that path is expected"):
        write_text(tmp_path / "results" / "out.json", "{}")
    with pytest.raises(WriteRefused, match=f"cannot write {tmp_path / 'results' / 'sub'}"):
        atomic_files.make_folder(tmp_path / "results" / "sub")


def test_the_tools_print_a_refused_write_in_one_line_with_status_1(tmp_path, capsys):
    def command() -> int:
        write_text(tmp_path / "missing" / "out.json", "{}")
        return 0

    assert report_errors(command, debug=False) == 1
    err = capsys.readouterr().err
    assert err == f"error: cannot write {tmp_path / 'missing' / 'out.json'} (No such file or directory)\n"
    with pytest.raises(WriteRefused):
        report_errors(command, debug=True)

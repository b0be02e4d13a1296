"""The board's methods as data (studies/board_methods.yaml, read by studies.scoreboard_methods.load_methods)."""

import dataclasses
import hashlib
import json

import pytest

from studies.scoreboard_methods import METHODS, METHODS_FILE, load_methods

#: sha256 of every method's definition (``dataclasses.asdict``, keys sorted) as the methods were written in code
#: before they became data: a method's definition is part of each of its cells' key, so moving the methods into
#: the data file must leave every one of them (and the board order) as it was.
DEFINITIONS_DIGEST = "ba0eba1b4ce3fe6593b39f14f3324f1a5e75e8bc07ea431ad7de1fb1723370ce"


def test_the_methods_read_from_the_data_file_are_the_ones_the_cells_were_keyed_by():
    definitions = {name: dataclasses.asdict(method) for name, method in METHODS.items()}
    digest = hashlib.sha256(json.dumps(definitions, sort_keys=True).encode()).hexdigest()
    assert digest == DEFINITIONS_DIGEST, "a method's definition changed: its cells will be recomputed"
    assert list(METHODS)[:6] == ["gradient", "approx_jacobian", "adaptive_jacobian", "gradient-tuned",
                                 "approx_jacobian-tuned", "adaptive_jacobian-tuned"]
    assert list(METHODS).index("position-ppo") < list(METHODS).index("torque-gc-copy-ppo")  # a teacher first


@pytest.mark.parametrize("entry, message", [
    ("x: {about: a, train_flags: [--mode, torque], flags: []}", "method 'x': unknown key(s) ['flags']"),
    ("x: {about: a, train_flags: [--mode, torque, --max-train-seconds, 1800]}", "method 'x': train_flags: expected"),
    ("x: {train_flags: [--mode, torque]}", "method 'x': about: expected"),
    ("x: {about: a}", "method 'x': expected train_flags (a train.py method) or benchmarl"),
    ("x: {about: a, train_flags: [--mode, torque], benchmarl: {algorithm: mappo, mode: torque, minutes: 1}}",
     "exactly one of them"),
    ("x: {about: a, benchmarl: {algorithm: mappo, mode: torque}}", "method 'x': benchmarl: expected algorithm"),
    ("x: {about: a, benchmarl: {algorithm: mappo, mode: torque, minutes: 1, lr: 3}}", "only fields of"),
    ("x: {about: a, train_flags: [--mode, torque], teacher: y}\ny: {about: b, train_flags: [--mode, position]}",
     "method 'x': teacher: 'y' is not a learned method defined before it"),
    ("gradient: {about: a, train_flags: [--mode, torque]}", "method 'gradient': a name that is not a string, or "
                                                            "one given twice"),
    ("x: {about: a, train_flags: [--mode, torque], needs_invariant_arms: 1}", "needs_invariant_arms: expected"),
    ("- x", "expected a mapping of method name"),
    ("x: [", "cannot read the board's methods"),
])
def test_a_bad_method_entry_is_refused_naming_the_file_the_method_and_the_key(tmp_path, entry, message):
    path = tmp_path / "methods.yaml"
    path.write_text(entry + "\n", encoding="utf-8")
    with pytest.raises(ValueError) as error:
        load_methods(path)
    assert str(error.value).startswith(str(path)) and message in str(error.value)


def test_a_new_method_is_one_entry(tmp_path):
    path = tmp_path / "methods.yaml"
    path.write_text(METHODS_FILE.read_text(encoding="utf-8") + "position-ppo-long:\n  about: a longer budget.\n"
                    "  train_flags: [--mode, position, --max-train-seconds, '3600']\n", encoding="utf-8")
    methods = load_methods(path)
    assert methods["position-ppo-long"].train_flags == ("--mode", "position", "--max-train-seconds", "3600")
    assert methods["position-ppo-long"].kind == "from scratch" and len(methods) == len(METHODS) + 1

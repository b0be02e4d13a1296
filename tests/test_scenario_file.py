"""Reading scenario files: the YAML 1.2 core schema, keys given twice, nesting and readable parse errors."""

from __future__ import annotations

import json

import pytest
import yaml

from ee_formation_env.builtin import BUILTIN_SCENARIOS, _FILES
from ee_formation_env.inputs import MAX_INTEGER_DIGITS, MAX_NESTING_DEPTH
from ee_formation_env.scenario import load_scenario
from ee_formation_env.scenario_file import BoundedSafeLoader, read_scenario_file

from conftest import scenario_dict


def _yaml(text: str):
    return yaml.load(text, Loader=BoundedSafeLoader)  # noqa: S506 (a SafeLoader subclass)


def test_yaml_scalars_follow_yaml_1_2_so_010_is_ten_1e3_a_number_and_1_30_not_ninety():
    data = _yaml("a: 010\nb: 1e3\nc: 1:30\nd: 0o17\ne: 0x10\nf: yes\ng: 2001-12-14\nh: -.5e-2\ni: .inf\nj: true\n"
                 "k: ~\n")
    assert data == {"a": 10, "b": 1000.0, "c": "1:30", "d": 15, "e": 16, "f": "yes", "g": "2001-12-14",
                    "h": -0.005, "i": float("inf"), "j": True, "k": None}
    assert type(data["a"]) is int and type(data["b"]) is float


def test_a_yaml_1_1_sexagesimal_time_is_refused_by_its_field_not_read_as_ninety(tmp_path):
    path = tmp_path / "clock.yaml"
    path.write_text(yaml.safe_dump(scenario_dict()) + "episode_seconds: 1:30\n", encoding="utf-8")
    with pytest.raises(ValueError, match=r"^episode_seconds: expected a positive number, got '1:30'"):
        load_scenario(path)


def test_an_exponent_without_a_dot_is_a_number_in_a_yaml_scenario(tmp_path):
    path = tmp_path / "exponent.yaml"
    path.write_text(yaml.safe_dump(scenario_dict()) + "physics_hz: 1e3\n", encoding="utf-8")
    assert load_scenario(path).physics_hz == 1000.0


def test_the_builtin_scenarios_read_the_same_under_yaml_1_2_as_under_pyyaml_1_1():
    for name in BUILTIN_SCENARIOS:
        text = (_FILES / f"{name}.yaml").read_text(encoding="utf-8")
        assert _yaml(text) == yaml.safe_load(text), name


def test_a_yaml_key_given_twice_is_refused_naming_the_key_the_file_and_both_lines(tmp_path):
    path = tmp_path / "twice.yaml"
    path.write_text("name: first\narms: []\nname: second\n", encoding="utf-8")
    with pytest.raises(ValueError, match=r"(?s)^scenario: .*twice\.yaml' is not valid YAML:\n.*key 'name' is given "
                                         r"twice \(lines 1 and 3\).*twice\.yaml\", line 3"):
        read_scenario_file(path)


def test_a_yaml_merge_key_may_be_overridden_since_that_is_what_a_merge_is_for():
    assert _yaml("base: &b {x: 1, y: 2}\nother:\n  <<: *b\n  x: 5\n")["other"] == {"x": 5, "y": 2}


def test_a_json_key_given_twice_is_refused_naming_the_key_and_the_file(tmp_path):
    path = tmp_path / "twice.json"
    path.write_text('{"arms": [], "shape": [], "arms": [1]}', encoding="utf-8")
    with pytest.raises(ValueError, match=r"^scenario: .*twice\.json' is not valid JSON: key 'arms' is given twice"):
        read_scenario_file(path)


@pytest.mark.parametrize("suffix", [".yaml", ".json"])
def test_a_file_nested_20000_deep_is_a_value_error_naming_the_key_not_a_recursion_error(tmp_path, suffix):
    deep = "[" * 20_000 + "]" * 20_000
    path = tmp_path / f"deep{suffix}"
    path.write_text(json.dumps({"shape": []})[:-1] + f', "arms": {deep}}}', encoding="utf-8")
    with pytest.raises(ValueError, match=rf"^scenario: .*deep{suffix}': arms: lists and dicts nest more than "
                                         rf"{MAX_NESTING_DEPTH} levels"):
        load_scenario(path)


def test_a_shape_nested_20000_deep_names_shape_and_for_yaml_its_line(tmp_path):
    deep = "[" * 20_000 + "]" * 20_000
    (tmp_path / "deep.yaml").write_text(f"arms: []\nshape: {deep}\n", encoding="utf-8")
    with pytest.raises(ValueError, match=r"^scenario: .*deep\.yaml': shape: lists and dicts nest more than "
                                         rf"{MAX_NESTING_DEPTH} levels deep \(line 2;"):
        load_scenario(tmp_path / "deep.yaml")
    (tmp_path / "deep.json").write_text(f'{{"arms": [], "shape": {deep}}}', encoding="utf-8")
    with pytest.raises(ValueError, match=r"^scenario: .*deep\.json': shape: lists and dicts nest more than"):
        load_scenario(tmp_path / "deep.json")
    # Block-style YAML nests a sequence per "- " on one line: refused while composed, naming the key too.
    (tmp_path / "block.yaml").write_text("shape: [[0, 0]]\narms:\n" + "- " * 20_000 + "1\n", encoding="utf-8")
    with pytest.raises(ValueError, match=r"^scenario: .*block\.yaml': arms: lists and dicts nest more than "
                                         rf"{MAX_NESTING_DEPTH} levels deep \(line 3;"):
        load_scenario(tmp_path / "block.yaml")


@pytest.mark.parametrize("suffix", [".yaml", ".json"])
def test_an_integer_of_5000_digits_is_refused_naming_the_file_and_the_key(tmp_path, suffix):
    path = tmp_path / f"long{suffix}"
    data = {**scenario_dict(), "frame_skip": 0}
    path.write_text(json.dumps(data).replace('"frame_skip": 0', '"frame_skip": ' + "1" * 5000), encoding="utf-8")
    line = r" \(line 1\)" if suffix == ".yaml" else ""
    with pytest.raises(ValueError, match=rf"^scenario: .*long{suffix}': frame_skip: expected an integer of at most "
                                         rf"{MAX_INTEGER_DIGITS} digits, got one of 5000{line}$"):
        load_scenario(path)
    nested = json.dumps(data).replace('"frame_skip": 0', '"sensing": {"seed": -' + "9" * 5000 + "}")
    path.write_text(nested, encoding="utf-8")
    with pytest.raises(ValueError, match=rf"^scenario: .*long{suffix}': sensing\.seed: expected an integer"):
        load_scenario(path)
    path.write_text(json.dumps(data).replace('"frame_skip": 0', '"frame_skip": ' + "1" * MAX_INTEGER_DIGITS),
                    encoding="utf-8")
    with pytest.raises(ValueError, match=r"^frame_skip: expected at most 1000000 physics steps"):
        load_scenario(path)  # a long integer Python reads is the field's to refuse


def test_a_file_nested_past_the_bound_but_within_the_parser_is_refused_as_nesting_too(tmp_path):
    path = tmp_path / "deep.json"
    nested: list = []
    for _ in range(MAX_NESTING_DEPTH):
        nested = [nested]
    path.write_text(json.dumps({**scenario_dict(), "gravity": nested}), encoding="utf-8")
    with pytest.raises(ValueError, match=rf"^scenario: .*deep\.json'.*nest more than {MAX_NESTING_DEPTH} levels"):
        load_scenario(path)


def test_a_yaml_syntax_error_is_shown_as_readable_lines_with_the_file_line_and_caret(tmp_path):
    path = tmp_path / "broken.yaml"
    path.write_text("arms:\n  - robot: planar_2link\n    base_position: [0, 0\nshape: [[0, 0]]\n", encoding="utf-8")
    with pytest.raises(ValueError) as info:
        read_scenario_file(path)
    message = str(info.value)
    lines = message.splitlines()
    assert lines[0].startswith("scenario: ") and lines[0].endswith("broken.yaml' is not valid YAML:")
    assert f'in "{path}", line 3' in message and any(line.strip() == "^" for line in lines)
    assert "\\n" not in message  # real line breaks, not an escaped string

"""The shared input layer: text files (size, encoding), YAML and JSON hazards, output paths, option
types, and a run that reports every problem of every input at once."""

from __future__ import annotations

import argparse
import os
import stat
from pathlib import Path

import pytest
import yaml

from palletpilot.cli import main
from palletpilot.executor.apps import cli_args
from palletpilot.geometry import OutputError, PalletpilotError
from palletpilot.geometry.fileio import (
    bundled_path,
    output_problems,
    parse_json,
    read_text,
    read_yaml,
    write_atomic,
)

MISSIONS = bundled_path("missions")


def test_text_files_must_be_utf8_and_say_where_they_are_not(tmp_path: Path) -> None:
    path = tmp_path / "m.yaml"
    path.write_bytes("name: ok\nnote: caf\xe9\n".encode("latin-1"))
    with pytest.raises(PalletpilotError, match=r"m\.yaml: not UTF-8 text: byte 0xe9 at offset 18 \(line 2\)"):
        read_text(path)
    path.write_bytes(b"\xef\xbb\xbfname: bom\n")  # a byte-order mark is fine
    assert read_yaml(path) == {"name": "bom"}


def test_oversized_files_are_refused_before_parsing(tmp_path: Path) -> None:
    path = tmp_path / "big.yaml"
    path.write_text("x: 1\n" * 1000)
    with pytest.raises(PalletpilotError, match=r"big\.yaml: too large"):
        read_text(path, max_bytes=1000)
    assert read_text(path, max_bytes=5000).count("\n") == 1000


def test_yaml_hazards_are_one_line_each(tmp_path: Path) -> None:
    cases = {
        "bomb.yaml": 'a: &a ["x","x","x","x","x","x","x","x","x","x"]\n'
        + "".join(f"{chr(98 + i)}: &{chr(98 + i)} [{','.join([f'*{chr(97 + i)}'] * 10)}]\n" for i in range(9)),
        "deep.yaml": "[" * 3000 + "]" * 3000,
        "python.yaml": "!!python/object/apply:os.system ['true']\n",
        "syntax.yaml": "a: [1, 2\nb: {\n",
    }
    expected = {
        "bomb.yaml": "too large: more than",
        "deep.yaml": "nested deeper than",
        "python.yaml": "could not determine a constructor",
        "syntax.yaml": "not valid YAML: line",
    }
    for name, text in cases.items():
        (tmp_path / name).write_text(text)
        with pytest.raises(PalletpilotError) as info:
            read_yaml(tmp_path / name)
        assert expected[name] in str(info.value) and len(info.value.problems) == 1


def test_json_is_strict_and_json_maps_read_like_yaml(tmp_path: Path) -> None:
    with pytest.raises(PalletpilotError, match="NaN is not a number in JSON"):
        parse_json('{"x": NaN}', "c.json")
    with pytest.raises(PalletpilotError, match=r"c\.json: not valid JSON: line 1 column 7"):
        parse_json('{"x": }', "c.json")
    doc = yaml.safe_load((MISSIONS / "warehouse.yaml").read_text())
    (tmp_path / "w.json").write_text(__import__("json").dumps(doc))
    assert read_yaml(tmp_path / "w.json") == doc


def test_output_paths_are_checked_before_work(tmp_path: Path) -> None:
    (tmp_path / "file.txt").write_text("x")
    assert output_problems(tmp_path / "a" / "b" / "map.png", (".png",)) == []  # folders are created
    assert "must end in .png" in output_problems(tmp_path / "map.txt", (".png",))[0]
    assert "is a folder" in output_problems(tmp_path, (".png",))[0]
    assert "is a file, not a folder" in output_problems(tmp_path / "file.txt" / "x.png", (".png",))[0]
    assert "not a folder" in output_problems(tmp_path / "file.txt", folder=True)[0]
    assert output_problems(tmp_path / "new_report", folder=True) == []
    if os.path.exists("/dev/null"):
        assert "not a regular file" in output_problems("/dev/null")[0]
        with pytest.raises(OutputError, match="not a regular file"):
            write_atomic("/dev/null", "data")  # never renamed over a device


def test_option_types_are_one_line_and_take_any_64_bit_seed() -> None:
    assert cli_args.seed(str(2**64 - 1)) == 2**64 - 1
    for text in ("-1", str(2**64), "1e3", ""):
        with pytest.raises(argparse.ArgumentTypeError):
            cli_args.seed(text)
    assert cli_args.count(1)("3") == 3
    with pytest.raises(argparse.ArgumentTypeError, match="must be an integer >= 1, got '0'"):
        cli_args.count(1)("0")
    with pytest.raises(argparse.ArgumentTypeError, match="must be a finite number"):
        cli_args.number(0.0, 1.0)("inf")
    assert cli_args.names(("a", "b"))("b, a,b") == ["b", "a"]
    with pytest.raises(argparse.ArgumentTypeError, match="unknown 'c'"):
        cli_args.names(("a", "b"))("a,c")


def test_bad_option_is_one_line_without_usage(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(["bench", "missions", "--runs", "0"])
    assert info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        "palletpilot bench missions: argument --runs: must be an integer >= 1, got '0' "
        "(see palletpilot bench missions --help)"
    ]


def _example_world(folder: Path) -> None:
    for path in MISSIONS.iterdir():
        if path.suffix == ".yaml":
            (folder / path.name).write_bytes(path.read_bytes())


def test_a_run_reports_every_problem_of_every_input_before_moving(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Mission tasks and scenario fields, all at once; nothing is simulated (no report folder appears)."""
    _example_world(tmp_path)
    mission = yaml.safe_load((tmp_path / "pickup_delivery.yaml").read_text())
    mission["tasks"] += [{"type": "pickup", "node": f"ghost_{i}"} for i in range(3)]
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(mission))
    scenario = yaml.safe_load((tmp_path / "scenario_demo.yaml").read_text())
    scenario["pallets"][1]["node"] = "rack_z9"
    scenario["pallets"].append({"x": 12.5, "y": -2.5})  # the truck starts at the charger, on top of it
    (tmp_path / "s.yaml").write_text(yaml.safe_dump(scenario))
    report = tmp_path / "report"
    code = main(["run", str(tmp_path / "m.yaml"), "--scenario", str(tmp_path / "s.yaml"), "--report", str(report)])
    err = capsys.readouterr().err
    assert code == 2 and not report.exists()
    for fragment in (
        "tasks[3] (pickup ghost_0): unknown node",
        "tasks[5] (pickup ghost_2): unknown node",
        "s.yaml: pallets[1].node: unknown node 'rack_z9'",
    ):
        assert fragment in err
    assert "Traceback" not in err


def test_a_bad_mission_with_the_default_scenario_names_its_tasks(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Without --scenario the default warehouse is built from the mission: its tasks are checked first."""
    _example_world(tmp_path)
    doc = {"map": "warehouse.yaml", "tasks": [{"type": "move", "node": f"ghost_{i}"} for i in range(50)]}
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(doc))
    assert main(["run", str(tmp_path / "m.yaml"), "--quiet"]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 50 and all("unknown node 'ghost_" in line for line in lines)


def test_outputs_follow_the_umask_not_mkstemps_private_mode(tmp_path: Path) -> None:
    old = os.umask(0o022)
    try:
        path = write_atomic(tmp_path / "report.json", "{}")
        assert stat.filemode(path.stat().st_mode) == "-rw-r--r--"
        os.umask(0o077)
        assert stat.filemode(write_atomic(tmp_path / "private.json", "{}").stat().st_mode) == "-rw-------"
        os.umask(0o002)
        assert stat.filemode(write_atomic(path, "{}").stat().st_mode) == "-rw-rw-r--"  # a rewrite too
    finally:
        os.umask(old)


def _mission(tmp_path: Path, text: str, name: str = "m.yaml") -> str:
    """A mission file in a folder beside a copy of the example map and vehicle."""
    for example in ("warehouse.yaml", "forklift.yaml"):
        (tmp_path / example).write_bytes((MISSIONS / example).read_bytes())
    (tmp_path / name).write_text(text)
    return str(tmp_path / name)


def test_mistyped_names_get_a_did_you_mean(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    good = "name: m\nmap: warehouse.yaml\ntasks:\n  - {type: pickup, node: floor_b2}\n"
    cases = [
        (good.replace("type: pickup", "type: pickupp"), "tasks[0]: type 'pickupp' is unknown (did you mean 'pickup'?)"),
        (good.replace("name:", "nmae:"), "nmae: Extra inputs are not permitted (did you mean 'name'?)"),
        (good.replace("floor_b2", "floor_b22"), "unknown node 'floor_b22' (did you mean 'floor_b2'?)"),
        (good.replace("map: warehouse", "map: warehous"), "map: 'warehous.yaml': no such file: "),
        (good.replace("\n  - {", "\n\t- {"), "line 4: a tab character (YAML indents with spaces only"),
    ]
    for text, words in cases:
        assert main(["run", _mission(tmp_path, text), "--report", str(tmp_path / "out")]) == 2
        err = capsys.readouterr().err
        assert words in err, err
        assert len(err.splitlines()) == 1 and err.startswith(str(tmp_path / "m.yaml"))
    assert f"{(tmp_path / 'warehous.yaml').resolve()} (relative to the mission's folder) (did you mean" in (
        main(["run", _mission(tmp_path, cases[3][0])]) and capsys.readouterr().err
    )
    assert main(["plan", str(MISSIONS / "warehouse.yaml"), "charger", "dropp"]) == 2
    assert "unknown node 'dropp' (did you mean 'drop'?)" in capsys.readouterr().err


def test_a_map_key_typo_names_the_key_it_meant(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "m.yaml"
    path.write_text("nodes:\n  - {id: a, x: 0, y: 0, tpye: waypoint}\n")
    assert main(["map", "check", str(path)]) == 2
    assert "nodes[0].tpye: Extra inputs are not permitted (did you mean 'type'?)" in capsys.readouterr().err

"""The inputs of a suite travel with its Ray tasks (`executor.apps.suite_inputs`): gathered on the head,
laid out again in a worker's temporary folder, verdicts written with the head's paths. These tests run
the worker's side in this process (no Ray): the head's copy of the suite is deleted before the runs."""

import dataclasses
import json
import os
import shutil
from pathlib import Path

import pytest
import yaml

from palletpilot.executor.apps.suite import load_suite
from palletpilot.executor.apps.suite_inputs import gather_inputs
from palletpilot.executor.apps.suite_ray import _received, run_remote
from palletpilot.executor.apps.suite_run import run_case
from palletpilot.geometry.fileio import bundled_path

MISSIONS = bundled_path("missions")
VERDICT = ("label", "outcome", "met", "reason", "problems", "simulated_s", "drawn")


def make_site(root: Path) -> Path:
    """A copy of the example suite with cases that read files by relative and absolute names, a drawn
    family and two refusals (one naming a file that is missing); returns the suite file."""
    shutil.copytree(MISSIONS / "suite", root / "suite")
    for name in ("warehouse.yaml", "forks.yaml", "forklift.yaml"):
        shutil.copy(MISSIONS / name, root / name)
    aisle = {"map": str(root / "warehouse.yaml"), "forks": str(root / "forks.yaml"), "seed": 5, "start": "b1"}
    (root / "suite" / "aisle_abs.yaml").write_text(yaml.safe_dump(aisle))
    (root / "suite" / "typo_map.yaml").write_text(
        yaml.safe_dump({"map": "../warehous.yaml", "tasks": [{"type": "move", "node": "b_top"}]})
    )
    people = [{"kind": "person", "x": 20.0, "y": 11.0, "yaw_deg": 0}, {"kind": "box", "x": 23.0, "y": 9.0}]
    cases = [
        {"name": "person", "mission": "move_b_top.yaml", "scenario": "person_in_aisle.yaml", "expect": "failure"},
        {
            "name": "aisle",
            "mission": str(root / "suite" / "move_b_top.yaml"),
            "family": {"base": "aisle_abs.yaml", "runs": 2, "seed": 3, "clutter": {"count": [0, 1], "choose": people}},
        },
        {"name": "unknown_node", "mission": "bad_unknown_node.yaml", "expect": "rejected"},
        {"name": "typo", "mission": "typo_map.yaml", "expect": "rejected", "message": "did you mean"},
    ]
    path = root / "suite" / "travel.yaml"
    path.write_text(yaml.safe_dump({"name": "travel", "cases": cases}))
    return path


def test_the_files_the_runs_read_and_no_others_are_gathered():
    suite = bundled_path("missions", "suite", "suite.yaml")
    inputs = gather_inputs(load_suite(suite).runs(["person_on_the_route", "industrial_pallet"]), suite)
    names = {os.path.relpath(p, MISSIONS) for p in inputs.files}
    want = {"suite/suite.yaml", "suite/move_b_top.yaml", "suite/person_in_aisle.yaml", "suite/pickup_industrial.yaml"}
    want |= {"suite/industrial.yaml", "warehouse.yaml", "forks.yaml", "forklift.yaml"}  # forklift: the map's vehicle
    assert names == want
    assert inputs.files[str(MISSIONS / "warehouse.yaml")] == (MISSIONS / "warehouse.yaml").read_bytes()
    assert len(inputs.model_sha256) == 64


def test_a_file_first_sent_for_a_did_you_mean_is_still_followed_when_named(tmp_path):
    from palletpilot.executor.apps.suite import RunSpec

    (tmp_path / "maps").mkdir()
    (tmp_path / "vehicles").mkdir()
    (tmp_path / "typo.yaml").write_text("map: maps/sit.yaml\n")  # missing: maps/*.yaml go for the did-you-mean
    (tmp_path / "good.yaml").write_text("map: maps/site.yaml\n")
    (tmp_path / "maps" / "site.yaml").write_text("vehicle: ../vehicles/truck.yaml\n")
    (tmp_path / "vehicles" / "truck.yaml").write_text("name: truck\n")
    specs = [RunSpec(name, 0, tmp_path / f"{name}.yaml", {}, "rejected") for name in ("typo", "good")]
    names = {os.path.relpath(p, tmp_path) for p in gather_inputs(specs).files}
    assert names == {"typo.yaml", "good.yaml", "maps/site.yaml", "vehicles/truck.yaml"}


def test_runs_from_the_gathered_inputs_give_the_verdicts_of_runs_from_the_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the suite named relative to the working folder, as on a command line
    suite_file = make_site(tmp_path / "site").relative_to(tmp_path)
    specs = load_suite(suite_file).runs()
    local = [run_case(spec, tmp_path / "local").to_json() for spec in specs]
    assert [r["outcome"] for r in local] == ["failure", "failure", "success", "rejected", "rejected"]
    assert [r["met"] for r in local] == [True, False, True, True, True]
    assert "did you mean 'warehouse.yaml'" in local[4]["reason"]

    inputs = gather_inputs(specs, suite_file)
    assert str(tmp_path / "site" / "warehouse.yaml") in inputs.absolute_names  # named so by aisle_abs.yaml
    shutil.rmtree(tmp_path / "site")  # the worker must read its copy: the head's folder is gone
    report = tmp_path / "remote"
    remote = [_received(*run_remote(spec, inputs), report, False).to_json() for spec in specs]
    assert [{k: r[k] for k in VERDICT} for r in remote] == [{k: r[k] for k in VERDICT} for r in local]
    assert remote[3]["reason"].startswith("site/suite/bad_unknown_node.yaml: tasks[0] (pickup floor_z9)")
    assert remote[0]["report_dir"] == str(report / "person" / "0")
    for name in ("report.json", "trajectory.csv", "events.jsonl", "run.mcap"):
        assert (report / "person" / "0" / name).is_file()
    csv = "aisle/1/trajectory.csv"
    assert (report / csv).read_bytes() == (tmp_path / "local" / csv).read_bytes()
    events = (report / "person" / "0" / "events.jsonl").read_text()
    assert "palletpilot-run-" not in events and all(json.loads(line) for line in events.splitlines())


def test_a_node_with_another_segmentation_model_refuses_the_run(tmp_path):
    suite = bundled_path("missions", "suite", "suite.yaml")
    (spec,) = load_suite(suite).runs(["person_on_the_route"])
    inputs = dataclasses.replace(gather_inputs([spec]), model_sha256="0" * 64)
    doc, data = run_remote(spec, inputs)
    assert doc["outcome"] == "error" and not doc["met"] and data == b""
    assert doc["reason"].startswith("internal error: this node's segmentation model (sha256 ")
    assert doc["reason"].endswith("is not the head's (000000000000): install the same palletpilot on every node")


def test_inputs_past_the_limit_are_one_line(monkeypatch):
    from palletpilot.executor.apps import suite_inputs
    from palletpilot.executor.apps.suite import SuiteError

    monkeypatch.setattr(suite_inputs, "MAX_INPUT_BYTES", 1000)
    specs = load_suite(bundled_path("missions", "suite", "suite.yaml")).runs(["person_on_the_route"])
    with pytest.raises(
        SuiteError, match=r"^the suite's input files are 0.0 MiB, more than the 0.0 MiB sent to a cluster$"
    ):
        gather_inputs(specs)

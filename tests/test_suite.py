"""Mission test suites (`palletpilot test`) and the pytest plugin (`palletpilot.testing`)."""

import json
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
import yaml

from palletpilot.cli import main
from palletpilot.executor.apps.suite import SuiteError, load_suite
from palletpilot.geometry.fileio import bundled_path
from palletpilot.testing import assert_checks, assert_failed, assert_succeeded, checks_of

SUITE = bundled_path("missions", "suite")


def copy_suite(tmp_path: Path) -> Path:
    """The example suite folder, with the map and forks beside it as `../` expects."""
    shutil.copytree(SUITE, tmp_path / "suite")
    for name in ("warehouse.yaml", "forks.yaml", "forklift.yaml"):
        shutil.copy(bundled_path("missions", name), tmp_path / name)
    return tmp_path / "suite"


def write_suite(folder: Path, cases: list[dict], **fields: object) -> Path:
    path = folder / "mine.yaml"
    path.write_text(yaml.safe_dump({"name": "mine", "cases": cases, **fields}))
    return path


# -- the suite file --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("cases", "words"),
    [
        ([{"name": "a b", "mission": "pickup_floor_b2.yaml"}], "cases[0].name: Value error, 1..64 letters"),
        ([{"name": "a", "mission": "nowhere.yaml"}], "cases[0].mission: "),
        ([{"name": "a", "mission": "pickup_floor_b2.yaml", "expect": "maybe"}], "cases[0].expect: Input should be"),
        (
            [{"name": "a", "mission": "pickup_floor_b2.yaml", "reasons": ["path_blocked"]}],
            "reasons: only with expect: failure",
        ),
        (
            [{"name": "a", "mission": "pickup_floor_b2.yaml"}, {"name": "a", "mission": "pickup_floor_b2.yaml"}],
            "cases[1].name: 'a' is used twice",
        ),
        (
            [{"name": "a", "mission": "pickup_floor_b2.yaml", "checks": {"max_task_s": -1}}],
            "cases[0].checks: max_task_s: Input should be greater than 0",
        ),
        (
            [{"name": "a", "mission": "pickup_floor_b2.yaml", "checks": {"no_kontact": True}}],
            "cases[0].checks: no_kontact: Extra inputs are not permitted",
        ),
        (
            [
                {
                    "name": "a",
                    "mission": "pickup_floor_b2.yaml",
                    "family": {"base": "floor_b2.yaml", "pallets": {"dy": [0.3, -0.3]}},
                }
            ],
            "dy: low 0.3 is above high -0.3",
        ),
    ],
)
def test_a_bad_suite_is_one_line_per_problem_and_exit_2(tmp_path: Path, capsys, cases: list, words: str) -> None:
    path = write_suite(copy_suite(tmp_path), cases)
    with pytest.raises(SuiteError) as info:
        load_suite(path)
    assert any(words in line and line.startswith(str(path)) for line in info.value.problems), info.value.problems
    assert main(["test", str(path), "--report", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert words in err and "Traceback" not in err


def test_only_names_a_case_of_the_suite(tmp_path: Path, capsys) -> None:
    folder = copy_suite(tmp_path)
    assert main(["test", str(folder / "suite.yaml"), "--only", "floor_envelop"]) == 2
    assert "--only: no case named floor_envelop" in capsys.readouterr().err


def test_families_draw_within_their_ranges_and_the_same_for_a_seed(tmp_path: Path) -> None:
    folder = copy_suite(tmp_path)
    fam = {"base": "floor_b2.yaml", "runs": 6, "seed": 9, "pallets": {"dy": [-0.2, 0.2], "dyaw_deg": [-5, 5]}}
    fam["mount"] = {"tilt_deg": [18, 20]}
    fam["clutter"] = {"count": [1, 1], "choose": [{"kind": "box", "x": 27.5, "y": 13.5, "size": [0.6, 0.4, 0.5]}]}
    path = write_suite(folder, [{"name": "f", "mission": "pickup_floor_b2.yaml", "family": fam}])
    runs = load_suite(path).runs()
    assert runs == load_suite(path).runs() and len(runs) == 6
    assert len({r.seed for r in runs}) == 6
    for r in runs:
        assert r.scenario_doc is not None
        pallet = next(p for p in r.scenario_doc["pallets"] if p.get("node") == "floor_b2")
        assert -0.2 <= pallet["dy"] <= 0.2 and -5 <= pallet["dyaw_deg"] <= 5 and pallet["dx"] == 0.0
        assert 18 <= r.scenario_doc["camera"]["mount"]["tilt_deg"] <= 20
        assert len(r.scenario_doc["clutter"]) == 1
        other = next(p for p in r.scenario_doc["pallets"] if p.get("node") == "floor_b3")
        assert "dy" not in other  # only the named nodes are drawn


# -- running suites --------------------------------------------------------------------------------


def test_an_unmet_expectation_fails_the_suite_with_the_reason_and_the_report(
    tmp_path: Path, capsys, monkeypatch
) -> None:
    folder = copy_suite(tmp_path)
    monkeypatch.chdir(tmp_path)  # the reports land in ./out/test/SUITE by default
    cases = [
        {"name": "blocked", "mission": "move_b_top.yaml", "scenario": "person_in_aisle.yaml", "expect": "success"},
        {"name": "refused", "mission": "bad_unknown_node.yaml", "expect": "rejected", "message": "unknown node"},
        {
            "name": "wrong_reason",
            "mission": "move_b_top.yaml",
            "scenario": "person_in_aisle.yaml",
            "expect": "failure",
            "reasons": ["collision"],
        },
    ]
    path = write_suite(folder, cases)
    junit = tmp_path / "junit.xml"
    code = main(["test", str(path), "--junit", str(junit)])
    out = capsys.readouterr().out
    reports = tmp_path / "out" / "test" / "mine"
    assert code == 1
    assert "1 of 3 runs met their case" in out
    assert "blocked#0: failure (path_blocked)" in out and "expected success, got failure (path_blocked)" in out
    assert "expected a failure with collision, got path_blocked" in out
    assert f"report: {reports / 'blocked' / '0'}/report.json" in out
    assert "trajectory: " in out
    assert out.splitlines()[-2:] == [
        f"reports: {reports}/ (suite.json, campaign.json, CASE/K/report.json)",
        f"JUnit: {junit}",
    ]
    header = next(line for line in out.splitlines() if line.startswith("case "))
    assert header.rstrip().endswith("elapsed s")
    root = ET.parse(junit).getroot()
    cases_xml = root.findall("./testsuite/testcase")
    assert [c.get("name") for c in cases_xml] == ["blocked#0", "refused#0", "wrong_reason#0"]
    assert [c.find("failure") is not None for c in cases_xml] == [True, False, True]
    system_out = cases_xml[0].findtext("system-out") or ""
    assert f"report: {reports / 'blocked' / '0'}" in system_out and "elapsed_s: " in system_out
    assert "{" not in system_out and "'" not in system_out  # plain text lines, no Python dict
    doc = json.loads((reports / "suite.json").read_text())
    assert doc["runs"] == 3 and doc["met"] == 1
    runs = doc["results"]
    assert all(r["started_s"] > 1e9 and r["wall_s"] >= 0 for r in runs)  # a refusal may take under 5 ms


def test_the_example_suite_passes_with_two_jobs(tmp_path: Path) -> None:
    """What CI runs for integrators: the shipped suite, as a real process with two workers."""
    junit = tmp_path / "junit.xml"
    cmd = [sys.executable, "-m", "palletpilot.cli", "test", str(SUITE / "suite.yaml"), "--jobs", "2"]
    proc = subprocess.run(
        [*cmd, "--junit", str(junit), "--report", str(tmp_path / "r")], capture_output=True, text=True, timeout=900
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    root = ET.parse(junit).getroot()
    tests = root.findall("./testsuite/testcase")
    assert len(tests) == len(load_suite(SUITE / "suite.yaml").runs()) and root.get("failures") == "0"
    assert "runs met their case" in proc.stdout


# -- the checks, and the pytest plugin ---------------------------------------------------------------


def test_the_plugin_runs_a_mission_and_checks_it(run_mission) -> None:
    result = run_mission(SUITE / "pickup_floor_b2.yaml", SUITE / "floor_b2.yaml", seed=4)
    assert_succeeded(result)
    assert_checks(result, max_task_s=400, max_replans=3, delivered_within_m=0.05, delivered_yaw_deg=3.0)
    # The checks can fail: the delivered pallet is not within 0.1 mm, and a pallet moved (the target)
    # counts when nothing names it.
    assert any("from the drop node's pallet pose" in p for p in checks_of(result, delivered_within_m=1e-4))
    report = Path(result.report)
    doc = json.loads(report.read_text())
    doc["pallets"][0]["id"] = "someone_else"
    doc["collisions"] = [{"kind": "person", "id": "clutter[0]", "part": "body", "t": 3.0}]
    report.write_text(json.dumps(doc))
    problems = checks_of(result)
    assert any(p.startswith("pallet someone_else moved, but no pickup names it") for p in problems)
    assert any(p.startswith("contact: ") for p in problems)


def test_the_travel_height_check_sees_forks_up_at_speed(run_mission) -> None:
    result = run_mission(SUITE / "pickup_floor_b2.yaml", SUITE / "floor_b2.yaml", seed=4)
    csv_path = Path(result.report).parent / "trajectory.csv"
    rows = csv_path.read_text().splitlines()
    header, body = rows[0], rows[1:]
    fast_loaded = next(k for k, r in enumerate(body) if r.endswith(",1") and abs(float(r.split(",")[4])) > 0.5)
    cells = body[fast_loaded].split(",")
    cells[5] = "0.8000"  # forks at 0.8 m while driving loaded at speed
    body[fast_loaded] = ",".join(cells)
    csv_path.write_text("\n".join([header, *body]) + "\n")
    assert any("drove loaded at" in p for p in checks_of(result))


def test_assert_failed_names_the_reason(run_mission) -> None:
    result = run_mission(SUITE / "move_b_top.yaml", SUITE / "person_in_aisle.yaml")
    assert_failed(result, "path_blocked")
    assert_checks(result)
    with pytest.raises(AssertionError, match="failed with path_blocked"):
        assert_failed(result, "collision")


def test_drawn_values_read_as_text_and_a_case_column_is_its_elapsed_time() -> None:
    from palletpilot.executor.apps.suite_report import drawn_text, summary_table
    from palletpilot.executor.apps.suite_run import RunResult

    drawn = {"floor_b2": {"dx": -0.05, "dy": 0.21, "dyaw_deg": 3.2}, "tilt_deg": 22.4, "clutter": [1]}
    assert drawn_text(drawn) == "floor_b2 dx -0.05 dy 0.21 dyaw_deg 3.2; tilt_deg 22.4; clutter [1]"
    # two runs of one case side by side (--jobs 2): 10 s each, both within 11 s of the first start
    runs = [
        RunResult("a#0", "a", 0, "success", True, simulated_s=60.0, wall_s=10.0, started_s=1000.0),
        RunResult("a#1", "a", 1, "success", True, simulated_s=60.0, wall_s=10.0, started_s=1001.0),
    ]
    row = next(line for line in summary_table("s", runs, 11.0).splitlines() if line.startswith("a "))
    assert row.split()[-2:] == ["120", "11.0"]  # simulated time summed; elapsed, not the 20 s of the sum

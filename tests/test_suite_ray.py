"""`palletpilot test --executor ray`: the same verdicts and reports as the local executor, a worker that
dies retried once then reported, and a clear refusal without Ray. The Ray tests start a local Ray
instance (about 5 s) and are skipped where Ray is not installed (`pip install 'palletpilot[cluster]'`)."""

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from palletpilot.cli import main
from palletpilot.geometry.fileio import bundled_path

SUITE = bundled_path("missions") / "suite" / "suite.yaml"
QUICK = "person_on_the_route,unknown_node"  # a run that drives and fails as expected, one refused


def _results(folder: Path) -> list[dict]:
    return json.loads((folder / "suite.json").read_text())["results"]


def test_without_ray_the_ray_executor_is_one_line_and_exit_2(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    assert main(["test", str(SUITE), "--executor", "ray", "--report", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["--executor ray: the ray package is not installed (pip install 'palletpilot[cluster]')"]
    assert not (tmp_path / "r").exists()  # refused before any work


def test_a_ray_address_needs_the_ray_executor(tmp_path, capsys):
    assert main(["test", str(SUITE), "--ray-address", "auto", "--report", str(tmp_path / "r")]) == 2
    assert "--ray-address: only with --executor ray" in capsys.readouterr().err


def test_a_suite_on_ray_gives_the_local_verdicts_figures_and_reports(tmp_path):
    pytest.importorskip("ray")
    local, on_ray = tmp_path / "local", tmp_path / "ray"
    assert main(["test", str(SUITE), "--only", QUICK, "--report", str(local)]) == 0
    assert main(["test", str(SUITE), "--only", QUICK, "--executor", "ray", "--jobs", "2", "--report", str(on_ray)]) == 0
    a, b = _results(local), _results(on_ray)
    assert [r["label"] for r in a] == [r["label"] for r in b] == ["person_on_the_route#0", "unknown_node#0"]
    for x, y in zip(a, b, strict=True):
        same = ("outcome", "met", "reason", "problems", "simulated_s", "drawn", "retried")
        assert {k: x[k] for k in same} == {k: y[k] for k in same}
    assert json.loads((on_ray / "suite.json").read_text())["jobs"] == 2
    assert b[0]["report_dir"] == str(on_ray / "person_on_the_route" / "0")  # the report came back to the head
    for name in ("report.json", "trajectory.csv", "events.jsonl", "run.mcap"):
        assert (on_ray / "person_on_the_route" / "0" / name).is_file()
    trajectory = "person_on_the_route/0/trajectory.csv"
    assert (local / trajectory).read_bytes() == (on_ray / trajectory).read_bytes()


def test_a_run_whose_worker_dies_is_retried_once_then_an_error_and_the_others_finish(tmp_path):
    pytest.importorskip("ray")
    folder = SUITE.parent
    scenario = yaml.safe_load((folder / "person_in_aisle.yaml").read_text())
    scenario.update(map=str(folder.parent / "warehouse.yaml"), forks=str(folder.parent / "forks.yaml"))
    scenario["faults"] = [{"kind": "kill", "at_s": 1.0}]  # SIGKILL to the worker, as the OOM killer would
    (tmp_path / "killed.yaml").write_text(yaml.safe_dump(scenario))
    suite = {
        "name": "worker deaths",
        "cases": [
            {"name": "killed", "mission": str(folder / "move_b_top.yaml"), "scenario": "killed.yaml"},
            {"name": "fine", "mission": str(folder / "bad_unknown_node.yaml"), "expect": "rejected"},
        ],
    }
    (tmp_path / "suite.yaml").write_text(yaml.safe_dump(suite))
    report = tmp_path / "report"
    junit = tmp_path / "junit.xml"
    args = ["test", str(tmp_path / "suite.yaml"), "--executor", "ray", "--report", str(report), "--junit", str(junit)]
    assert main(args) == 1
    killed, fine = _results(report)
    assert killed["outcome"] == "error" and killed["retried"] and not killed["met"]
    assert killed["reason"].startswith("internal error: the run's worker died twice: ")
    assert fine["outcome"] == "rejected" and fine["met"] and not fine["retried"]
    assert 'errors="1"' in junit.read_text()


def test_ctrl_c_cancels_the_tasks_and_still_writes_the_summary_of_what_finished(tmp_path):
    pytest.importorskip("ray")
    folder = SUITE.parent
    suite = {
        "name": "interrupted",
        "cases": [
            {"name": "quick", "mission": str(folder / "bad_unknown_node.yaml"), "expect": "rejected"},
            {
                "name": "long",
                "mission": str(folder / "pickup_floor_b2.yaml"),
                "scenario": str(folder / "floor_b2.yaml"),
            },
        ],
    }
    (tmp_path / "suite.yaml").write_text(yaml.safe_dump(suite))
    report, junit = tmp_path / "report", tmp_path / "junit.xml"
    cmd = [str(Path(sys.executable).parent / "palletpilot"), "test", str(tmp_path / "suite.yaml"), "--json"]
    cmd += ["--executor", "ray", "--jobs", "1", "--report", str(report), "--junit", str(junit)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stderr is not None
    for line in proc.stderr:  # the quick run's line, then Ctrl-C while the long run is on the cluster
        if line.startswith("[1/2]"):
            break
    time.sleep(1.0)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert "interrupted: 1 of 2 runs finished, the cluster's tasks cancelled" in err
    (quick,) = json.loads(out)["results"]
    assert quick["label"] == "quick#0" and quick["met"]
    assert json.loads((report / "suite.json").read_text())["runs"] == 1
    assert 'tests="1"' in junit.read_text()

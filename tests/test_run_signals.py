"""`palletpilot run` as a real subprocess under real signals: SIGINT / SIGTERM cancel (vehicle stopped,
reason `cancelled`, report written, exit 128 + signal), SIGUSR1 / SIGUSR2 pause and resume (never fatal,
even during start-up), and a report folder never mixes two runs."""

from __future__ import annotations

import itertools
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.skipif(not hasattr(signal, "SIGUSR1"), reason="POSIX signals")

START_TIMEOUT_S = 120.0  # imports and the first plan, on a loaded 2-core CI machine


def start_run(report: Path, *extra: str) -> subprocess.Popen[str]:
    """The bundled demo on the wall clock, in its own process (so a signal reaches only it)."""
    cmd = [sys.executable, "-m", "palletpilot.cli", "run", "--demo", "--clock", "wall", "--report", str(report)]
    return subprocess.Popen([*cmd, *extra], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def events(report: Path) -> list[dict]:
    path = report / "events.jsonl"
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.endswith("}")]


def wait_for_event(proc: subprocess.Popen[str], report: Path, name: str, timeout_s: float = START_TIMEOUT_S) -> dict:
    """The first event `name` of the running process (polls events.jsonl, which the runner flushes)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        found = [e for e in events(report) if e["event"] == name]
        if found:
            return found[0]
        if proc.poll() is not None:
            raise AssertionError(f"run ended (exit {proc.returncode}) before {name}: {proc.stderr.read()}")
        time.sleep(0.05)
    proc.kill()
    raise AssertionError(f"no {name} event within {timeout_s} s")


def finish(proc: subprocess.Popen[str], timeout_s: float = 60.0) -> tuple[int, str, str]:
    out, err = proc.communicate(timeout=timeout_s)
    return proc.returncode, out, err


def driving(proc: subprocess.Popen[str], report: Path) -> None:
    """Wait until the truck has driven for a second (state_start of the first drive plus 1 s of motion)."""
    wait_for_event(proc, report, "state_start")
    time.sleep(1.5)


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_cancel_signal_stops_the_truck_writes_the_report_and_exits_128_plus_the_signal(tmp_path, signum):
    report = tmp_path / "report"
    report.mkdir()
    (report / "report.json").write_text('{"success": true, "stale": "an older run"}')
    (report / "trajectory.png").write_bytes(b"old")
    proc = start_run(report)
    driving(proc, report)
    proc.send_signal(signum)
    code, _out, err = finish(proc)

    assert code == 128 + signum, err
    assert "Traceback" not in err
    doc = json.loads((report / "report.json").read_text())  # strict JSON, the new run's own
    assert "stale" not in doc and doc["success"] is False
    task = doc["tasks"][0]
    assert task["result"] == "failed" and task["reason"] == "cancelled"
    assert signal.Signals(signum).name in task["message"]
    (stop,) = doc["stops"]
    assert stop["reason"] == "cancelled" and abs(stop["speed"]) > 0.05  # it was driving when cancelled
    assert stop["standstill_s"] is not None and stop["standstill_s"] - stop["t_s"] < 2.0
    assert (report / "trajectory.png").read_bytes() != b"old"
    names = [e["event"] for e in events(report)]
    assert names[0] == "run_start" and names.count("run_start") == names.count("mission_start") == 1
    assert "safety_stop" in names and names[-1] == "mission_end"
    assert "vehicle stopped" in err


def test_pause_and_resume_signals_freeze_the_task_and_never_kill_the_process(tmp_path):
    report = tmp_path / "report"
    proc = start_run(report)
    time.sleep(0.3)  # still importing: SIGUSR1 must not be fatal here
    proc.send_signal(signal.SIGUSR1)
    time.sleep(0.3)
    proc.send_signal(signal.SIGUSR2)
    driving(proc, report)
    assert proc.poll() is None, proc.stderr.read() if proc.stderr else ""

    proc.send_signal(signal.SIGUSR1)
    paused = wait_for_event(proc, report, "paused", timeout_s=10.0)
    time.sleep(4.0)  # longer than the no-progress check: a paused task must not fail
    proc.send_signal(signal.SIGUSR2)
    resumed = wait_for_event(proc, report, "resumed", timeout_s=10.0)
    assert resumed["t"] - paused["t"] > 3.5
    time.sleep(1.0)
    assert not [e for e in events(report) if e["event"] == "task_failed"]
    proc.send_signal(signal.SIGINT)
    code, _out, err = finish(proc)

    assert code == 128 + signal.SIGINT, err
    doc = json.loads((report / "report.json").read_text())
    assert doc["tasks"][0]["reason"] == "cancelled"
    pause_events = [e["event"] for e in events(report) if e["event"] in ("paused", "resumed")]
    assert pause_events == ["paused", "resumed"]  # the start-up pair came before the run began


MISSIONS = Path(__file__).resolve().parents[1] / "missions"

# A kill -9 in the middle of every task type: after the lift (the load is on the forks), while the
# delivery enters the drop, while a move drives, while the truck charges.
KILLS = [
    {"kind": "kill", "state": "reverse_out", "task": 0, "after_s": 1.0},
    {"kind": "kill", "state": "enter", "task": 1, "after_s": 2.0},
    {"kind": "kill", "state": "drive", "task": 2, "after_s": 1.0},
    {"kind": "kill", "state": "charge", "task": 3, "after_s": 5.0},
]


def killing_scenario(tmp_path: Path) -> tuple[Path, Path]:
    """The demo world and a pickup, delivery, move and charge mission, with a kill -9 in each task."""
    import yaml

    scenario = yaml.safe_load((MISSIONS / "scenario_demo.yaml").read_text())
    scenario["map"], scenario["forks"] = str(MISSIONS / "warehouse.yaml"), str(MISSIONS / "forks.yaml")
    scenario["faults"] = KILLS
    mission = {
        "name": "kill every task type",
        "map": str(MISSIONS / "warehouse.yaml"),
        "tasks": [
            {"type": "pickup", "node": "floor_b2"},
            {"type": "delivery", "node": "drop"},
            {"type": "move", "node": "c_e"},
            {"type": "charge", "node": "charger", "minutes": 0.2},
        ],
    }
    (tmp_path / "scenario.yaml").write_text(yaml.safe_dump(scenario))
    (tmp_path / "mission.yaml").write_text(yaml.safe_dump(mission))
    return tmp_path / "mission.yaml", tmp_path / "scenario.yaml"


def palletpilot(*args: str, timeout_s: float = 300.0) -> subprocess.CompletedProcess[str]:
    cmd = [sys.executable, "-m", "palletpilot.cli", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)


def test_a_run_killed_in_every_task_type_resumes_from_its_journal_without_repeating_a_lift(tmp_path):
    mission, scenario = killing_scenario(tmp_path)
    journal, report = tmp_path / "run.journal", tmp_path / "report"
    run = palletpilot("run", str(mission), "--scenario", str(scenario), "--journal", str(journal),
                      "--report", str(report), "--quiet")  # fmt: skip
    killed_in = []
    for _ in KILLS:
        assert run.returncode == -signal.SIGKILL, run.stderr
        last = [e for e in events(report) if e["event"] == "state_start"][-1]
        killed_in.append((last["task"], last["state"]))
        run = palletpilot("run", "--resume", str(journal), "--quiet")
    assert killed_in == [(k["task"], k["state"]) for k in KILLS]
    assert run.returncode == 0, run.stderr

    doc = json.loads((report / "report.json").read_text())
    assert doc["success"] is True and doc["resumed"] == len(KILLS)
    assert [t["result"] for t in doc["tasks"]] == ["succeeded"] * 4
    assert doc["collisions"] == []
    names = [e["event"] for e in events(report)]
    assert names.count("mission_resumed") == len(KILLS)
    lifts = [e for e in events(report) if e["event"] == "state_end" and e["state"] == "lift"]
    assert [e["outcome"] for e in lifts] == ["done"]  # lifted once, never again after a resume
    lowered = [e for e in events(report) if e["event"] == "state_end" and e["state"] == "lower"]
    assert [e["outcome"] for e in lowered] == ["done"]  # the resumed delivery knew the load was on the forks

    # trajectory.csv survives the kills: one row per tick, time always increasing, the load seen once.
    import csv

    rows = list(csv.DictReader((report / "trajectory.csv").open()))
    times = [float(r["t_s"]) for r in rows]
    assert all(b > a for a, b in itertools.pairwise(times))
    assert abs(times[-1] - doc["simulated_s"]) < 0.1 and len(rows) > 0.9 * times[-1] / 0.05
    loaded = "".join(r["loaded"] for r in rows)
    assert loaded.strip("0").count("0") == 0 and "1" in loaded  # loaded from the lift to the set-down

    again = palletpilot("run", "--resume", str(journal))
    assert again.returncode == 2
    assert again.stderr.count("\n") == 1 and "nothing to resume" in again.stderr

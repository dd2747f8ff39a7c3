"""palletpilot replay: a run's report from its run.mcap alone, and one line for a recording it cannot read."""

import json

import pytest
from mcap.writer import Writer
from test_recording import _run

from palletpilot.cli import main
from palletpilot.executor.adapters.mcap.recording import RECORDING


@pytest.fixture(scope="module")
def run_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("run")
    r = _run(folder)
    assert r.success and r.write_errors == []
    return folder / "report"


def test_replay_gives_the_runs_report(run_folder, tmp_path, capsys):
    assert main(["replay", str(run_folder / RECORDING), "--report", str(tmp_path / "again")]) == 0
    assert "mission succeeded (replayed)" in capsys.readouterr().out
    original = json.loads((run_folder / "report.json").read_text())
    replayed = json.loads((tmp_path / "again" / "report.json").read_text())
    assert replayed == original  # every figure, the run's id and wall-clock solve times included
    assert (tmp_path / "again" / "trajectory.png").stat().st_size > 10_000


def _foreign_mcap(path):
    with path.open("wb") as f:
        w = Writer(f)
        w.start()
        schema = w.register_schema("other.Thing", "jsonschema", b'{"type": "object"}')
        channel = w.register_channel("/thing", "json", schema)
        w.add_message(channel, log_time=1, publish_time=1, data=b"{}")
        w.finish()


@pytest.mark.parametrize("case", ["missing", "not_mcap", "foreign", "truncated"])
def test_a_bad_recording_is_one_line_exit_2(case, run_folder, tmp_path, capsys):
    path = tmp_path / "run.mcap"
    expected = {
        "missing": "cannot read",
        "not_mcap": "not an MCAP file",
        "foreign": "not a finished palletpilot run's recording",
        "truncated": "truncated or damaged MCAP",
    }[case]
    if case == "not_mcap":
        path.write_text("t_s,x_m\n0,0\n")
    elif case == "foreign":
        _foreign_mcap(path)
    elif case == "truncated":
        data = (run_folder / RECORDING).read_bytes()
        path.write_bytes(data[: len(data) // 3])
    code = main(["replay", str(path), "--report", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and str(path) in err[0] and expected in err[0], err
    assert not (tmp_path / "out" / "report.json").exists()

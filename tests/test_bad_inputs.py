"""The bad-input corpus (`tests/badinputs/`): every case exits with its code and says what is wrong,
in one line per problem, and no command ever prints a traceback.

The cases run in-process through `palletpilot.cli.main` (an uncaught exception fails the case); a
sample also runs as real subprocesses, where a traceback would reach stderr.
"""

from __future__ import annotations

import importlib
import os
import pkgutil
import shutil
import subprocess
import sys
from pathlib import Path

import badinputs
import pytest
from badinputs import Case, Fixtures

from palletpilot.cli import main


def _cases() -> list[Case]:
    cases: list[Case] = []
    for info in pkgutil.iter_modules(badinputs.__path__):
        cases += importlib.import_module(f"badinputs.{info.name}").CASES
    return cases


CASES = _cases()


@pytest.fixture(scope="session")
def fixtures(tmp_path_factory: pytest.TempPathFactory) -> Fixtures:
    root = tmp_path_factory.mktemp("fixtures")
    ex = root / "ex"
    assert main(["examples", "--out", str(ex)]) == 0
    frame = root / "frame.npz"
    assert main(["sim", "render", str(ex / "scenario_demo.yaml"), "--out", str(frame), "--seed", "1"]) == 0
    cal = root / "cal.json"
    assert main(["calibrate", str(frame), "--forks", str(ex / "forks.yaml"), "--out", str(cal)]) == 0
    for path in [*ex.iterdir(), frame, cal]:
        path.chmod(0o444)  # cases must copy before they modify
    return Fixtures(ex=ex, frame=frame, cal=cal)


def _argv(case: Case, fx: Fixtures, folder: Path) -> list[str]:
    return [a.format(case=folder, ex=fx.ex, frame=fx.frame, cal=fx.cal) for a in case.argv]


def test_corpus_is_large_and_names_are_unique() -> None:
    names = [c.name for c in CASES]
    assert len(names) == len(set(names)), "duplicate case names"
    assert len(CASES) >= 150


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.name)
def test_bad_input(
    case: Case, fixtures: Fixtures, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    if case.setup is not None:
        case.setup(fixtures, tmp_path)
    try:
        code = main(_argv(case, fixtures, tmp_path))
    except SystemExit as exc:  # argparse
        code = int(exc.code or 0)
    out, err = capsys.readouterr()
    assert "Traceback" not in out + err
    assert code == case.exit, f"exit {code}, expected {case.exit}; stderr:\n{err}"
    assert case.message.lower() in err.lower(), f"expected '{case.message}' in stderr:\n{err}"
    if case.exit == 2:
        assert err.strip(), "exit 2 without saying why"


SUBPROCESS_SAMPLE = 8


def test_no_traceback_in_a_real_process(fixtures: Fixtures, tmp_path: Path) -> None:
    """A sample of the corpus through the installed console entry (`python -m palletpilot.cli`)."""
    sample = CASES[:: max(1, len(CASES) // SUBPROCESS_SAMPLE)][:SUBPROCESS_SAMPLE]
    for case in sample:
        folder = tmp_path / case.name
        folder.mkdir()
        if case.setup is not None:
            case.setup(fixtures, folder)
        proc = subprocess.run(
            [sys.executable, "-m", "palletpilot.cli", *_argv(case, fixtures, folder)],
            cwd=folder,
            capture_output=True,
            text=True,
            timeout=120,
            env={**os.environ, "PYTHONWARNINGS": ""},
        )
        assert "Traceback" not in proc.stderr, f"{case.name}: {proc.stderr}"
        assert proc.returncode == case.exit, f"{case.name}: exit {proc.returncode}: {proc.stderr}"
        shutil.rmtree(folder, ignore_errors=True)

"""Start-up cost of the command line: `--help`, `--version` and the light commands load no heavy library,
and the lazily built `--help` says what each command's own module says (issue 41)."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import palletpilot
from palletpilot.executor.apps import cli

HEAVY = ("open3d", "casadi", "cv2", "matplotlib", "foxglove", "onnxruntime")


def _loaded(args: list[str]) -> tuple[int, str, list[str]]:
    """Run `palletpilot ARGS` in a fresh interpreter; its exit code, stdout, and the heavy modules it loaded."""
    code = (
        "import contextlib, io, json, sys\n"
        "from palletpilot.cli import main\n"
        "out = io.StringIO()\n"
        "with contextlib.redirect_stdout(out):\n"
        "    try:\n"
        f"        rc = main({args!r})\n"
        "    except SystemExit as exc:\n"
        "        rc = exc.code\n"
        f"print(json.dumps([rc, out.getvalue(), [m for m in {HEAVY!r} if m in sys.modules]]))\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120)
    rc, stdout, heavy = json.loads(done.stdout.splitlines()[-1])
    return rc, stdout, heavy


def test_help_and_version_load_no_heavy_library() -> None:
    rc, out, heavy = _loaded(["--help"])
    assert rc == 0 and "estimate-pallet" in out and "agv" in out and "bench" in out
    assert heavy == []
    rc, out, heavy = _loaded(["--version"])
    assert rc == 0 and out.strip() == f"palletpilot {palletpilot.__version__}"
    assert heavy == []


def test_map_check_plan_and_a_refused_run_load_no_heavy_library(tmp_path: Path) -> None:
    example = str(cli.bundled_path("missions", "warehouse.yaml"))
    rc, out, heavy = _loaded(["map", "check", example])
    assert rc == 0 and "ok" in out and heavy == []  # the vehicle file without CasADi
    rc, _out, heavy = _loaded(["plan", example, "nowhere", "either"])
    assert rc == 2 and heavy == []
    rc, _out, heavy = _loaded(["run", str(tmp_path / "missing.yaml")])
    assert rc == 2 and heavy == ["foxglove"]  # `--foxglove`'s option; no simulator, open3d, CasADi or OpenCV


def test_the_table_of_commands_matches_each_commands_own_help() -> None:
    full = cli.build_parser(command=cli.ALL_COMMANDS)
    lazy = cli.build_parser(command=None)
    helps = []
    for parser in (full, lazy):
        action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        helps.append({c.dest: c.help for c in action._choices_actions})
    assert helps[0] == helps[1]
    assert set(helps[0]) == {name for name, _, _ in cli._COMMANDS}

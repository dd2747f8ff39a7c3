"""The wheel, installed as a user would: one `palletpilot` namespace, the bundled files, next to python-control.

Builds the wheel from the checkout (no build isolation: the installed setuptools, no download), installs
it into a fresh virtual environment that borrows the dependencies already installed here (a path entry
to this environment's site-packages, so nothing large is downloaded again), adds python-control with pip,
and runs the bundled demo mission from a folder outside the checkout.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import sysconfig
import venv
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# Our folder names; `control` is checked apart: there it must be python-control's.
OURS = ("geometry", "roadmap", "perception", "sim", "executor", "bench", "missions")


def _run(cmd: list[str], cwd: Path, timeout: float = 600) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, f"{' '.join(cmd)} exited {proc.returncode}:\n{proc.stdout}\n{proc.stderr}"
    return proc


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A fresh venv with the palletpilot wheel and python-control; returns its bin folder."""
    tmp = tmp_path_factory.mktemp("wheel")
    dist = tmp / "dist"
    _run(
        [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "-w", str(dist), str(ROOT)],
        cwd=tmp,
    )
    wheel = next(dist.glob("palletpilot-*.whl"))
    env_dir = tmp / "venv"
    venv.EnvBuilder(with_pip=False).create(env_dir)
    bin_dir = env_dir / "bin"
    site = Path(
        subprocess.check_output(
            [str(bin_dir / "python"), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], text=True
        ).strip()
    )
    # The dependencies (numpy, open3d, casadi, ...) from this environment, after the fresh one's own
    # site-packages. A plain path entry: the .pth files in there (our editable install) are not run.
    (site / "borrowed_deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    pip = [sys.executable, "-m", "pip", "--python", str(bin_dir / "python"), "install", "-q"]
    _run([*pip, "--no-deps", str(wheel)], cwd=tmp)
    _run([*pip, "control"], cwd=tmp)
    return bin_dir


def test_only_the_palletpilot_namespace_is_installed(installed: Path, tmp_path: Path) -> None:
    code = (
        "import importlib.util, json, palletpilot, control\n"
        f"ours = {OURS!r}\n"
        "print(json.dumps({'palletpilot': palletpilot.__file__, 'control': control.__file__,\n"
        "  'tf': hasattr(control, 'tf'), 'bare': [n for n in ours if importlib.util.find_spec(n) is not None]}))\n"
    )
    out = json.loads(_run([str(installed / "python"), "-c", code], cwd=tmp_path).stdout)
    assert out["palletpilot"].startswith(str(installed.parent)), out
    assert "site-packages" in out["palletpilot"] and str(ROOT) not in out["palletpilot"]
    assert out["tf"] and "palletpilot" not in out["control"], "python-control's `control` is the one imported"
    assert out["bare"] == [], f"bare top-level packages of ours are importable: {out['bare']}"


def test_the_bundled_demo_runs_outside_the_checkout(installed: Path, tmp_path: Path) -> None:
    examples = _run([str(installed / "palletpilot"), "examples"], cwd=tmp_path).stdout
    assert "pickup_delivery.yaml" in examples and "scenario_demo.yaml" in examples
    assert str(ROOT) not in examples
    proc = _run([str(installed / "palletpilot"), "run", "--demo", "--report", "demo", "--json"], cwd=tmp_path)
    summary = json.loads(proc.stdout)
    assert summary["success"] is True
    assert [t["result"] for t in summary["tasks"]] == ["succeeded"] * len(summary["tasks"])
    report = json.loads((tmp_path / "demo" / "report.json").read_text())
    assert report["success"] is True
    assert (tmp_path / "demo" / "trajectory.png").stat().st_size > 0
    # The shipped segmentation model is found through importlib.resources as well.
    code = "from palletpilot.perception.segmentation import DEFAULT_MODEL; print(DEFAULT_MODEL.stat().st_size)"
    assert int(_run([str(installed / "python"), "-c", code], cwd=tmp_path).stdout) > 100_000

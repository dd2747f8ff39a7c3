"""Issue 38: every dependency between the product's modules is an import statement the import linter sees.

`importlib.import_module` hides a dependency from it (an earlier cycle between the robot app and the VDA 5050
app went unseen that way); the places allowed are the command-line tables, which build only the command given
(`executor.apps.cli.build_parser`, `bench.cli.cmd_bench`), and a package's own PEP 562 `__getattr__` that
loads one of its submodules on first use (`f"{__name__}.{module}"`: no dependency outside the package).
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("executor", "perception", "control", "roadmap", "geometry", "sim", "bench")
ALLOWED = {("executor/apps/cli.py", "build_parser"), ("bench/cli.py", "cmd_bench")}


def _import_module_calls() -> list[tuple[str, str]]:
    found = []
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            tree = ast.parse(path.read_text(), str(path))
            for func in ast.walk(tree):
                if not isinstance(func, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Module)):
                    continue
                for node in ast.walk(func):
                    if (
                        isinstance(node, ast.Call)
                        and isinstance(node.func, ast.Attribute)
                        and node.func.attr == "import_module"
                    ):
                        name = func.name if not isinstance(func, ast.Module) else "<module>"
                        own = name == "__getattr__" and "{__name__}." in ast.unparse(node.args[0])
                        if not own:
                            found.append((str(path.relative_to(ROOT)), name))
    return found


def test_import_module_only_in_the_cli_command_table():
    calls = {call for call in _import_module_calls() if call[1] != "<module>"}
    assert calls <= ALLOWED, f"importlib.import_module outside the CLI's command table: {sorted(calls - ALLOWED)}"
    assert ("executor/apps/cli.py", "build_parser") in calls  # the command table still loads lazily

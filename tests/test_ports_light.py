"""`import palletpilot.executor.ports` stays light: no implementation and no heavy library is loaded (issue
38; import-linter checks the static imports, this checks what a fresh interpreter really loads)."""

from __future__ import annotations

import json
import subprocess
import sys

HEAVY = ("numpy", "scipy", "open3d", "cv2", "casadi", "onnxruntime", "zenoh", "mcap", "matplotlib", "sqlite3")


def test_importing_the_ports_loads_no_heavy_library() -> None:
    code = (
        "import json, sys; import palletpilot.executor.ports as p; "
        "print(json.dumps(sorted(m for m in sys.modules if m.split('.')[0] in sys.argv[1:] "
        "or m.startswith(('palletpilot.perception', 'palletpilot.sim', 'palletpilot.control')))))"
    )
    out = subprocess.run([sys.executable, "-c", code, *HEAVY], capture_output=True, text=True, check=True)
    assert json.loads(out.stdout) == []

"""YAML files validated by pydantic models, with errors as one line per problem.

Every package loads its files (maps, vehicle, forks, scenarios, missions) through `load_yaml_model`,
so every bad file is reported the same way: `path: nodes[3].yaw_deg: Input should be a valid number`.
It lives in `geometry` because that is the one package all others may import.

`bundled_path("missions", "warehouse.yaml")` is a file shipped inside the installed package (the
example missions, the ONNX model), found through `importlib.resources`, never relative to a source file.

Every output file is written the one way, `write_atomic` (temporary file in the same folder, fsync,
rename, fsync of the folder): a reader sees the old file or the new one, never a truncated one, and a
failed write (full disk, no permission) leaves the old file and raises `OutputError` with one line.
JSON output is strict RFC 8259 (`strict_json`, `dumps_json`): NaN and infinities become `null`.
"""

from __future__ import annotations

import atexit
import contextlib
import json
import math
import os
import tempfile
from importlib import resources
from pathlib import Path
from typing import TypeVar

import yaml
from pydantic import BaseModel, ValidationError

from palletpilot.geometry.errors import OutputError, PalletpilotError

M = TypeVar("M", bound=BaseModel)

# Keeps files extracted by `importlib.resources.as_file` (a zipped install) until the process ends.
_RESOURCES = contextlib.ExitStack()
atexit.register(_RESOURCES.close)


def bundled_path(*parts: str) -> Path:
    """A file or folder shipped in the `palletpilot` package, e.g. `bundled_path("missions", "forks.yaml")`."""
    ref = resources.files("palletpilot").joinpath(*parts)
    return Path(_RESOURCES.enter_context(resources.as_file(ref)))


def read_yaml(path: str | Path, error: type[PalletpilotError] = PalletpilotError) -> object:
    """Parse a YAML file; a missing file or a syntax error raises `error` with one line naming the file."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise error(f"{path}: cannot read: {exc.strerror or exc}") from None
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}: " if mark is not None else ""
        raise error(f"{path}: not valid YAML: {where}{getattr(exc, 'problem', exc)}") from None


def validation_lines(prefix: str, exc: ValidationError) -> list[str]:
    """One line per pydantic error: `prefix: nodes[3].yaw_deg: Input should be a valid number`."""
    lines = []
    for err in exc.errors():
        loc = ""
        for part in err["loc"]:
            loc += f"[{part}]" if isinstance(part, int) else (f".{part}" if loc else str(part))
        lines.append(f"{prefix}: {loc or 'file'}: {err['msg']}")
    return lines


def validate_model(data: object, model: type[M], where: str, error: type[PalletpilotError] = PalletpilotError) -> M:
    """Validate already-parsed data against `model`; every problem becomes one line of `error.problems`."""
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        lines = validation_lines(where, exc)
        raise error(lines[0] if len(lines) == 1 else f"{where}: {len(lines)} problems", lines) from None


def load_yaml_model(path: str | Path, model: type[M], error: type[PalletpilotError] = PalletpilotError) -> M:
    """Read a YAML file and validate it against `model`, raising `error` (one line per problem)."""
    return validate_model(read_yaml(path, error), model, str(path), error)


def write_atomic(path: str | Path, data: bytes | str) -> Path:
    """Replace `path` with `data` atomically (temp file, fsync, rename); raises `OutputError` on failure."""
    path = Path(path)
    payload = data.encode() if isinstance(data, str) else data
    tmp: str | None = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        with os.fdopen(fd, "wb") as f:
            f.write(payload)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        tmp = None
        _fsync_dir(path.parent)
    except OSError as exc:
        raise OutputError(f"{path}: cannot write: {exc.strerror or exc}") from None
    finally:
        if tmp is not None:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
    return path


def _fsync_dir(folder: Path) -> None:
    """Make a rename in `folder` durable (a no-op where directories cannot be opened, e.g. Windows)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def strict_json(obj: object) -> object:
    """`obj` with NaN and infinities as None and numpy values as plain Python (RFC 8259 has no NaN)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): strict_json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [strict_json(v) for v in obj]
    if hasattr(obj, "tolist"):  # numpy arrays and scalars
        return strict_json(obj.tolist())
    if obj is None or isinstance(obj, (str, int, bool)):
        return obj
    return str(obj)


def dumps_json(obj: object, indent: int | None = None) -> str:
    """Strict JSON text of `obj` (non-finite numbers as null)."""
    return json.dumps(strict_json(obj), indent=indent, allow_nan=False)


def write_json(path: str | Path, obj: object) -> Path:
    """Write `obj` as strict, indented JSON, atomically (`write_atomic`)."""
    return write_atomic(path, dumps_json(obj, indent=2) + "\n")

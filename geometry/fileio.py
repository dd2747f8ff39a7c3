"""YAML files validated by pydantic models, with errors as one line per problem.

Every package loads its files (maps, vehicle, forks, scenarios, missions) through `load_yaml_model`,
so every bad file is reported the same way: `path: nodes[3].yaw_deg: Input should be a valid number`.
It lives in `geometry` because that is the one package all others may import.
"""

from __future__ import annotations

from pathlib import Path
from typing import TypeVar

import yaml
from pydantic import BaseModel, ValidationError

from geometry.errors import PalletpilotError

M = TypeVar("M", bound=BaseModel)


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

"""The corpus of bad inputs: each case is a command line (and the small files it reads) with the exit
code and a fragment of the message the user must see. `tests/test_bad_inputs.py` runs every case.

A case's `argv` may name these placeholders, filled in by the test:
- `{case}`: the case's own folder (its `setup` writes files there; it is the working directory);
- `{ex}`: a copy of the bundled example files (`palletpilot examples --out`): never modify it;
- `{frame}`: a valid labelled frame bundle rendered from `{ex}/scenario_demo.yaml` at the start node;
- `{cal}`: a valid calibration JSON for `{frame}` (written by `palletpilot calibrate`).

`setup(fx, folder)` gets the same paths as a `Fixtures` and writes the case's files into `folder`.
The modules `files`, `options`, `maps` and `frames` each hold a list `CASES`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import yaml


@dataclass(frozen=True)
class Fixtures:
    """The valid files a case may start from."""

    ex: Path
    frame: Path
    cal: Path


@dataclass(frozen=True)
class Case:
    """One bad input: the command, the expected exit code and a fragment of stderr (case-insensitive)."""

    name: str
    argv: tuple[str, ...]
    exit: int
    message: str
    setup: Callable[[Fixtures, Path], None] | None = None


def write(folder: Path, name: str, data: str | bytes) -> Path:
    """Write a case file."""
    path = folder / name
    path.parent.mkdir(parents=True, exist_ok=True)
    if isinstance(data, bytes):
        path.write_bytes(data)
    else:
        path.write_text(data)
    return path


def example(fx: Fixtures, name: str) -> dict:
    """An example YAML file as a dict, to modify into a bad one."""
    return yaml.safe_load((fx.ex / name).read_text())


def dump(doc: object) -> str:
    """YAML text of `doc` (NaN and infinities as .nan / .inf)."""
    return yaml.safe_dump(doc, sort_keys=False)

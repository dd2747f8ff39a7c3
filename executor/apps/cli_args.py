"""Command-line option types: every option is checked when it is parsed, before any work starts.

`Parser` is the `argparse.ArgumentParser` of every `palletpilot` command: a bad option is one line on
stderr (`palletpilot bench missions: argument --runs: must be an integer >= 1, got '0'`) and exit 2,
never a usage dump or a traceback. The type functions below are argparse `type=` callables:

- `count(low)`: an integer >= `low` (`--runs`, `--frames`, `--jobs`, ...);
- `seed`: any integer 0 .. 2**64 - 1 (numpy's generators take all of them);
- `number(low, high)`: a finite float within a range (`--fork-height`, `--kill-rate`);
- `names(choices)`: a comma-separated list of known names (`--modes adaptive,no_adapt`);
- `out_file(*suffixes)`, `out_folder`: an output that can be written (not a folder or a device, the
  right extension, a writable parent), checked by `geometry.fileio.output_problems`.

Input files are checked by the commands themselves, so that every problem of every input is reported.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable, Sequence
from typing import NoReturn

from palletpilot.geometry.fileio import output_problems
from palletpilot.perception.labels_mode import DEFAULT_LABELS_MODE, SIM_TRUTH, LabelsMode

SEED_MAX = 2**64 - 1


def add_labels_argument(parser: argparse.ArgumentParser, sim: bool = False) -> None:
    """`--labels model|geometry|fused` (default fused): which source selects perception's pixels
    (`perception.labels_mode`); `sim`: also `truth`, the simulator's exact labels in the model mode."""
    choices = [str(m) for m in LabelsMode] + ([SIM_TRUTH] if sim else [])
    parser.add_argument(
        "--labels",
        choices=choices,
        default=str(DEFAULT_LABELS_MODE),
        help="which pixels are the pallet's, the floor's and the forks': depth geometry with the segmentation "
        "model's hints (fused, the default), depth alone (geometry: no model), the model alone (model)"
        + (", or the simulator's exact labels as the model's (truth)" if sim else ""),
    )


class Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one line (`prog: problem (see prog --help)`) and exit 2."""

    def error(self, message: str) -> NoReturn:
        """Print the problem on one line and exit with code 2 (bad input)."""
        print(f"{self.prog}: {message} (see {self.prog} --help)", file=sys.stderr)
        raise SystemExit(2)


def _int(text: str) -> int:
    try:
        return int(text, 10)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer, got '{text}'") from None


def count(low: int = 1, high: int | None = None) -> Callable[[str], int]:
    """An argparse type: an integer >= `low` (and <= `high` when given)."""

    def parse(text: str) -> int:
        value = _int(text)
        if value < low or (high is not None and value > high):
            within = f">= {low}" if high is None else f"in {low}..{high}"
            raise argparse.ArgumentTypeError(f"must be an integer {within}, got '{text}'")
        return value

    parse.__name__ = "count"
    return parse


def seed(text: str) -> int:
    """An argparse type: a random seed, any integer 0 .. 2**64 - 1."""
    value = _int(text)
    if not 0 <= value <= SEED_MAX:
        raise argparse.ArgumentTypeError(f"must be an integer in 0..{SEED_MAX} (2**64 - 1), got '{text}'")
    return value


def number(low: float = -math.inf, high: float = math.inf, unit: str = "") -> Callable[[str], float]:
    """An argparse type: a finite float in [low, high]; `unit` is named in the message."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be a number, got '{text}'") from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"must be a finite number, got '{text}'")
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"must be in {low:g}..{high:g}{' ' + unit if unit else ''}, got '{text}'")
        return value

    parse.__name__ = "number"
    return parse


def names(choices: Sequence[str]) -> Callable[[str], list[str]]:
    """An argparse type: a comma-separated, non-empty list of names from `choices` (duplicates dropped)."""

    def parse(text: str) -> list[str]:
        items = [t.strip() for t in text.split(",") if t.strip()]
        unknown = [t for t in items if t not in choices]
        if unknown or not items:
            what = f"unknown {', '.join(repr(u) for u in unknown)}" if unknown else "empty list"
            raise argparse.ArgumentTypeError(f"{what} (known: {','.join(choices)})")
        return list(dict.fromkeys(items))

    parse.__name__ = "names"
    return parse


def out_file(*suffixes: str) -> Callable[[str], str]:
    """An argparse type: a file that can be written, ending in one of `suffixes` (any when none)."""

    def parse(text: str) -> str:
        problems = output_problems(text, tuple(s.lower() for s in suffixes))
        if problems:
            raise argparse.ArgumentTypeError(problems[0])
        return text

    parse.__name__ = "out_file"
    return parse


def out_folder(text: str) -> str:
    """An argparse type: a folder that exists and is writable, or can be created."""
    problems = output_problems(text, folder=True)
    if problems:
        raise argparse.ArgumentTypeError(problems[0])
    return text

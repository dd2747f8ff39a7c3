"""The one error style of palletpilot.

Every package raises a subclass of `PalletpilotError` whose message names the file, node
or frame at fault. The CLI prints the message as one line on stderr and exits with code 2.
`geometry` is the package every other one may import, so the base class lives here.
"""

from __future__ import annotations

import difflib
from collections.abc import Callable, Iterable
from typing import TypeVar

T = TypeVar("T")


class PalletpilotError(Exception):
    """Base of all expected palletpilot errors (bad input, infeasible requests).

    `problems` holds one line per problem when several were found at once (a map check).
    """

    def __init__(self, message: str, problems: list[str] | None = None) -> None:
        super().__init__(message)
        self.problems: list[str] = list(problems) if problems else [message]


class GeometryError(PalletpilotError):
    """A pose or transform that cannot be built (wrong shape, non-rigid matrix)."""


class OutputError(PalletpilotError):
    """An output file could not be written (full disk, no permission); the old file, if any, is intact.

    The CLI exits with code 3 for it, apart from 1 (mission failed) and 2 (bad input).
    """


def collect(problems: list[str], load: Callable[[], T]) -> T | None:
    """`load()`, or None with its problem lines appended to `problems` when it raises a `PalletpilotError`.

    How a command checks all of its inputs before it starts and reports every problem at once:
    collect each input, then `raise_problems`.
    """
    try:
        return load()
    except PalletpilotError as exc:
        problems.extend(p for p in exc.problems if p not in problems)
        return None


def raise_problems(problems: list[str], error: type[PalletpilotError] = PalletpilotError) -> None:
    """Raise `error` with every line of `problems` (message: the first and how many more); no-op when empty."""
    if problems:
        more = len(problems) - 1
        raise error(problems[0] + (f" (and {more} more)" if more else ""), problems)


def did_you_mean(word: str, choices: Iterable[str]) -> str:
    """` (did you mean 'pickup'?)` when one of `choices` is close to a mistyped `word` (difflib), else ``."""
    close = difflib.get_close_matches(word, [c for c in choices if c != word], n=1, cutoff=0.6)
    return f" (did you mean '{close[0]}'?)" if close else ""

"""Live progress of a run on a text stream (stderr), fit for a terminal and for logs alike.

On a terminal one line is rewritten in place (`\\r`) every tick. Anywhere else (CI, a log file, a pipe)
a carriage return makes a mess, so `Progress` prints one plain line whenever the task or state changes
and at most one progress line every `every_s` seconds (wall clock) in between.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TextIO

PLAIN_EVERY_S = 5.0
"""At most one progress line this often (wall clock, seconds) when the stream is not a terminal."""


class Progress:
    """Writes progress lines to `stream`: in place on a terminal, plain lines otherwise."""

    def __init__(
        self,
        stream: TextIO,
        every_s: float = PLAIN_EVERY_S,
        monotonic: Callable[[], float] = time.monotonic,
        tty: bool | None = None,
    ) -> None:
        self.stream = stream
        self.every_s = every_s
        self._monotonic = monotonic
        if tty is None:
            isatty = getattr(stream, "isatty", None)
            tty = bool(isatty()) if callable(isatty) else False
        self.tty = tty
        self._key: object = None
        self._last_plain = -float("inf")
        self._open_line = False

    def show(self, key: object, line: str) -> None:
        """Report `line`; `key` names the phase (task and state): a new key always prints on a log."""
        if self.tty:
            self.stream.write(f"\r{line}   ")
            self._open_line = True
        else:
            now = self._monotonic()
            if key == self._key and now - self._last_plain < self.every_s:
                return
            self.stream.write(line.rstrip() + "\n")
            self._last_plain = now
        self._key = key
        self.stream.flush()

    def note(self, line: str) -> None:
        """A line that always prints on its own (pause, resume, a failure)."""
        self.close()
        self.stream.write(line.rstrip() + "\n")
        self.stream.flush()

    def close(self) -> None:
        """End the in-place line on a terminal."""
        if self._open_line:
            self.stream.write("\n")
            self.stream.flush()
            self._open_line = False

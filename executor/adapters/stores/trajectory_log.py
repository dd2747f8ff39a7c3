"""`trajectory.csv`: the truck's true state every control tick of a simulated run, appended as it goes.

Columns: `t_s, x_m, y_m, yaw_deg, speed_mps, fork_height_m, loaded` (the true pose of the forklift
frame in the world, the true speed, the fork height, `loaded` 0/1 from the load sensor). Like
`events.jsonl` the file is an append-only log, flushed about once a second, so a killed run keeps what
it had; a resume first drops the rows after its checkpoint's time (the world goes back there) with an
atomic rewrite, then appends.

Public API: `TrajectoryLog`, `TRAJECTORY_COLUMNS`.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TextIO

from palletpilot.geometry import OutputError
from palletpilot.geometry.fileio import write_atomic

TRAJECTORY_COLUMNS = ("t_s", "x_m", "y_m", "yaw_deg", "speed_mps", "fork_height_m", "loaded")
_FLUSH_EVERY = 20  # rows: about a second at 20 Hz


class TrajectoryLog:
    """Append rows to `path`; `resume_t` (s): continue a file, dropping rows after that time."""

    def __init__(self, path: Path, resume_t: float | None = None) -> None:
        self.path = path
        try:
            if resume_t is not None and path.exists():
                keep = [line for line in path.read_text().splitlines(keepends=True) if _row_time(line) <= resume_t]
                write_atomic(path, "".join(keep) if keep else _header())
            elif resume_t is None or not path.exists():
                write_atomic(path, _header())
            self._file: TextIO = path.open("a")
        except OSError as exc:
            raise OutputError(f"{path}: cannot write: {exc.strerror or exc}") from None
        self._pending = 0

    def row(self, t_s: float, x: float, y: float, yaw: float, speed: float, fork_height: float, loaded: bool) -> None:
        """One tick: time (s), true pose (m, rad), speed (m/s), fork height (m), load sensor."""
        self._file.write(
            f"{t_s:.3f},{x:.4f},{y:.4f},{math.degrees(yaw):.3f},{speed:.4f},{fork_height:.4f},{int(loaded)}\n"
        )
        self._pending += 1
        if self._pending >= _FLUSH_EVERY:
            self._file.flush()
            self._pending = 0

    def close(self) -> None:
        """Flush and close the file."""
        self._file.close()


def _header() -> str:
    return ",".join(TRAJECTORY_COLUMNS) + "\n"


def _row_time(line: str) -> float:
    """A row's time (s); the header counts as time minus infinity (always kept)."""
    head = line.split(",", 1)[0]
    try:
        return float(head)
    except ValueError:
        return -math.inf

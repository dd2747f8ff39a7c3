"""How one task went, for the report and the journal.

Public API: `TaskResult`.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

from palletpilot.executor.ports.vocabulary import Outcome, Reason


@dataclass
class TaskResult:
    """One task's outcome: result (`pending`, `succeeded`, `failed`), reason code, message, attempts,
    start and end time (s, the runner's clock), its states with their times and outcomes, and what it
    recorded (calibrations, estimates, temporary nodes)."""

    index: int
    type: str
    node: str | None
    result: Outcome = Outcome.PENDING
    reason: Reason | None = None
    message: str | None = None
    attempts: int = 0
    start_s: float = 0.0
    end_s: float = 0.0
    states: list[dict[str, Any]] = field(default_factory=list)
    record: dict[str, Any] = field(default_factory=dict)

    def summary(self) -> dict[str, Any]:
        """`type`, `node`, `result`, `reason`, `attempts` (the `--json` summary)."""
        return {
            "type": self.type,
            "node": self.node,
            "result": self.result,
            "reason": self.reason,
            "attempts": self.attempts,
        }

    def to_json(self) -> dict[str, Any]:
        """Every field, as plain JSON (the journal)."""
        return asdict(self)

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> TaskResult:
        """The inverse of `to_json`."""
        result = cls(**doc)
        result.result = Outcome(result.result)
        result.reason = None if result.reason is None else Reason(result.reason)
        return result

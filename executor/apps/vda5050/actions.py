"""Actions: the ones this AGV supports, their parameters, and the action state machine.

Supported actions (the factsheet's `agvActions` is built from `CATALOGUE`):

| action | scopes | parameters | what runs |
| --- | --- | --- | --- |
| `pick` | NODE (pallet node) | `loadType`, `stationType`; opt. `height`, `loadId`, `lhd`, `stationName` | Pickup |
| `drop` | NODE (drop or pallet node) | opt. `loadType`, `stationType`, `stationName`, `height`, `loadId` | Delivery |
| `startCharging`, `stopCharging` | INSTANT, NODE (charging node) | - | `batteryState.charging` |
| `startPause`, `stopPause` | INSTANT | - | the runner's pause (`paused`) |
| `cancelOrder` | INSTANT | - | the runner's cancel |
| `initPosition` | INSTANT | `x`, `y`, `theta`, `mapId`; optional `lastNodeId` | confirms the pose |
| `stateRequest`, `factsheetRequest` | INSTANT | - | publishes the state / factsheet |

The state machine (Figure 16) allows WAITING -> INITIALIZING | RUNNING | FINISHED | FAILED,
INITIALIZING -> RUNNING | PAUSED | FINISHED | FAILED, RUNNING -> PAUSED | FINISHED | FAILED, PAUSED ->
INITIALIZING | RUNNING | FAILED; FINISHED and FAILED are final. Anything else is a bug
(`IllegalTransitionError`).

Public API: `ParamSpec`, `ActionSpec`, `CATALOGUE`, `INSTANT`, `NODE`, `EDGE`, `check_parameters`,
`TRANSITIONS`, `IllegalTransitionError`, `ActionRecord`, `ActionTable`, `LOAD_HANDLING_DEVICE`.
"""

from __future__ import annotations

import threading
from collections.abc import Collection, Iterator
from dataclasses import dataclass
from typing import Any

from palletpilot.executor.apps.vda5050.models import Action, ActionStatus, ErrorRef

INSTANT, NODE, EDGE = "INSTANT", "NODE", "EDGE"
LOAD_HANDLING_DEVICE = "FORKS"
"""The one load handling device (`lhd`, `loads[].loadPosition`)."""

_TYPES: dict[str, tuple[type, ...]] = {
    "STRING": (str,),
    "FLOAT": (int, float),
    "NUMBER": (int, float),
    "INTEGER": (int,),
    "BOOL": (bool,),
}


@dataclass(frozen=True)
class ParamSpec:
    """A parameter of an action: key, `valueDataType` (factsheet enum), optional, description."""

    key: str
    value_type: str
    optional: bool
    description: str

    def to_json(self) -> dict[str, Any]:
        """The factsheet's `actionParameter` object."""
        return {
            "key": self.key,
            "valueDataType": self.value_type,
            "description": self.description,
            "isOptional": self.optional,
        }


@dataclass(frozen=True)
class ActionSpec:
    """An action type this AGV performs: scopes, parameters, blocking types it accepts."""

    action_type: str
    scopes: tuple[str, ...]
    description: str
    parameters: tuple[ParamSpec, ...] = ()
    blocking_types: tuple[str, ...] = ("NONE", "SOFT", "HARD")
    result: str | None = None

    def to_json(self) -> dict[str, Any]:
        """The factsheet's `agvAction` object."""
        out: dict[str, Any] = {
            "actionType": self.action_type,
            "actionDescription": self.description,
            "actionScopes": list(self.scopes),
            "blockingTypes": list(self.blocking_types),
        }
        if self.parameters:
            out["actionParameters"] = [p.to_json() for p in self.parameters]
        if self.result:
            out["resultDescription"] = self.result
        return out


_HEIGHT = "bottom of the load above the floor (m); default: the node's height"
CATALOGUE: dict[str, ActionSpec] = {
    spec.action_type: spec
    for spec in (
        ActionSpec(
            "pick",
            (NODE,),
            "adaptive pallet pickup at a pallet node, entered from its pre-pallet node (the order's node before "
            "and after it): calibrate the camera, estimate the pallet, re-plan to it when misplaced, enter, lift",
            (
                ParamSpec("loadType", "STRING", False, "pallet type: eur (EPAL), industrial, half, plastic, ..."),
                ParamSpec("stationType", "STRING", False, "e.g. floor or rack (informative)"),
                ParamSpec("stationName", "STRING", True, "informative"),
                ParamSpec("height", "FLOAT", True, _HEIGHT),
                ParamSpec("loadId", "STRING", True, "reported in loads[].loadId while carried"),
                ParamSpec("lhd", "STRING", True, f"load handling device: {LOAD_HANDLING_DEVICE}"),
            ),
            ("SOFT", "HARD"),
            "FINISHED once the load sensor feels the pallet on the forks",
        ),
        ActionSpec(
            "drop",
            (NODE,),
            "checked delivery at a drop or pallet node, entered from its pre-pallet node: the slot is checked "
            "free before the forks enter",
            (
                ParamSpec("loadType", "STRING", True, "the carried pallet's type (default: the picked one's)"),
                ParamSpec("stationType", "STRING", True, "informative"),
                ParamSpec("stationName", "STRING", True, "informative"),
                ParamSpec("height", "FLOAT", True, _HEIGHT),
                ParamSpec("loadId", "STRING", True, "informative"),
                ParamSpec("lhd", "STRING", True, f"load handling device: {LOAD_HANDLING_DEVICE}"),
            ),
            ("SOFT", "HARD"),
            "FINISHED once the load sensor feels no load",
        ),
        ActionSpec("startPause", (INSTANT,), "stop driving and pause the running actions (paused: true)"),
        ActionSpec("stopPause", (INSTANT,), "resume driving and the paused actions (paused: false)"),
        ActionSpec("startCharging", (INSTANT, NODE), "start charging at a charging node (batteryState.charging: true)"),
        ActionSpec("stopCharging", (INSTANT, NODE), "stop charging (batteryState.charging: false)"),
        ActionSpec(
            "cancelOrder",
            (INSTANT,),
            "stop where the truck is, fail the order's waiting and running actions, delete the order",
        ),
        ActionSpec(
            "initPosition",
            (INSTANT,),
            "confirm the truck's pose on the map (it must agree with localization) and set lastNodeId",
            (
                ParamSpec("x", "FLOAT", False, "m, map frame"),
                ParamSpec("y", "FLOAT", False, "m, map frame"),
                ParamSpec("theta", "FLOAT", False, "rad"),
                ParamSpec("mapId", "STRING", False, "the map's id"),
                ParamSpec("lastNodeId", "STRING", True, "a roadmap node the truck stands at"),
            ),
        ),
        ActionSpec("stateRequest", (INSTANT,), "publish the state now"),
        ActionSpec("factsheetRequest", (INSTANT,), "publish the factsheet now"),
    )
}


def check_parameters(action: Action, spec: ActionSpec) -> list[tuple[str, list[ErrorRef]]]:
    """Problems of an action's parameters against its spec: missing required ones, wrong value types,
    unknown keys, duplicates; each with the `actionParameter` references that name the keys."""
    out: list[tuple[str, list[ErrorRef]]] = []
    known = {p.key: p for p in spec.parameters}
    seen: set[str] = set()
    for key, value in action.parameters:
        ref = [("actionParameter", key)]
        if key in seen:
            out.append((f"parameter '{key}' is given twice", ref))
            continue
        seen.add(key)
        p = known.get(key)
        if p is None:
            out.append((f"parameter '{key}' is not supported by action '{spec.action_type}'", ref))
        elif not isinstance(value, _TYPES[p.value_type]) or (isinstance(value, bool) and p.value_type != "BOOL"):
            out.append((f"parameter '{key}' must be a {p.value_type.lower()}, got {value!r}", ref))
    for p in spec.parameters:
        if not p.optional and p.key not in seen:
            out.append(
                (f"parameter '{p.key}' is required by action '{spec.action_type}'", [("actionParameter", p.key)])
            )
    return out


A = ActionStatus
TRANSITIONS: dict[ActionStatus, frozenset[ActionStatus]] = {
    A.WAITING: frozenset({A.INITIALIZING, A.RUNNING, A.FINISHED, A.FAILED}),
    A.INITIALIZING: frozenset({A.RUNNING, A.PAUSED, A.FINISHED, A.FAILED}),
    A.RUNNING: frozenset({A.PAUSED, A.FINISHED, A.FAILED}),
    A.PAUSED: frozenset({A.INITIALIZING, A.RUNNING, A.FAILED}),
    A.FINISHED: frozenset(),
    A.FAILED: frozenset(),
}
"""Allowed `actionStatus` changes (Figure 16)."""
FINAL = frozenset({A.FINISHED, A.FAILED})


class IllegalTransitionError(RuntimeError):
    """An action status change the state machine does not allow (a bug in the caller)."""


@dataclass
class ActionRecord:
    """The state of one received action: `actionState` plus where it came from (`scope`) and, while PAUSED,
    the status to return to."""

    action: Action
    scope: str
    status: ActionStatus = ActionStatus.WAITING
    result: str | None = None
    resume_to: ActionStatus | None = None

    @property
    def final(self) -> bool:
        """FINISHED or FAILED."""
        return self.status in FINAL

    def to_json(self) -> dict[str, Any]:
        """The `actionState` object."""
        out: dict[str, Any] = {
            "actionId": self.action.action_id,
            "actionType": self.action.action_type,
            "actionStatus": self.status.value,
        }
        if self.action.description is not None:
            out["actionDescription"] = self.action.description
        if self.result is not None:
            out["resultDescription"] = self.result
        return out


class ActionTable:
    """The `actionStates` of the AGV, in the order received; every change goes through the state machine."""

    def __init__(self) -> None:
        self._records: dict[str, ActionRecord] = {}
        self._lock = threading.RLock()

    def __contains__(self, action_id: object) -> bool:
        return action_id in self._records

    def __iter__(self) -> Iterator[ActionRecord]:
        return iter(list(self._records.values()))

    def __len__(self) -> int:
        return len(self._records)

    def get(self, action_id: str) -> ActionRecord:
        """The record of an action id (KeyError when unknown)."""
        return self._records[action_id]

    def record_of(self, action: Action) -> ActionRecord | None:
        """The record of exactly this action object, or None when it is gone (a new order replaced the action
        states, perhaps reusing its actionId for another action)."""
        record = self._records.get(action.action_id)
        return record if record is not None and record.action is action else None

    def add(self, action: Action, scope: str, status: ActionStatus = ActionStatus.WAITING) -> ActionRecord:
        """Record a received action in its first status (WAITING for order actions)."""
        with self._lock:
            record = ActionRecord(action, scope, status)
            self._records[action.action_id] = record
            return record

    def set(self, action_id: str, status: ActionStatus, result: str | None = None) -> bool:
        """Move an action to `status` (unchanged: no-op, False); raises `IllegalTransitionError` when the machine
        forbids it. True when the status changed."""
        with self._lock:
            record = self._records[action_id]
            if record.status is status:
                if result is not None:
                    record.result = result
                return False
            if status not in TRANSITIONS[record.status]:
                raise IllegalTransitionError(
                    f"action '{action_id}' ({record.action.action_type}): {record.status.value} -> {status.value} "
                    "is not an allowed transition"
                )
            record.status = status
            if result is not None:
                record.result = result
            return True

    def remove(self, action_ids: Collection[str]) -> None:
        """Forget these actions (a replaced horizon's)."""
        with self._lock:
            self._records = {k: r for k, r in self._records.items() if k not in action_ids}

    def pause(self) -> bool:
        """Every INITIALIZING or RUNNING action to PAUSED (remembering which); True when any changed."""
        changed = False
        with self._lock:
            for r in self._records.values():
                if r.status in (A.INITIALIZING, A.RUNNING) and r.action.action_type not in (
                    "startPause",
                    "cancelOrder",
                ):
                    r.resume_to, r.status, changed = r.status, A.PAUSED, True
        return changed

    def unpause(self) -> bool:
        """Every PAUSED action back to the status it had; True when any changed."""
        changed = False
        with self._lock:
            for r in self._records.values():
                if r.status is A.PAUSED:
                    r.status, r.resume_to, changed = r.resume_to or A.RUNNING, None, True
        return changed

    def active(self, scopes: tuple[str, ...] = (NODE, EDGE)) -> list[ActionRecord]:
        """Actions of the given scopes that are neither FINISHED nor FAILED."""
        return [r for r in self._records.values() if r.scope in scopes and not r.final]

    def fail_pending(self, scopes: tuple[str, ...] = (NODE, EDGE), result: str | None = None) -> list[str]:
        """Every unfinished action of the scopes to FAILED (a cancel); the ids that changed."""
        ids = []
        with self._lock:
            for r in self._records.values():
                if r.scope in scopes and not r.final:
                    r.status, r.resume_to = A.FAILED, None
                    if result is not None:
                        r.result = result
                    ids.append(r.action.action_id)
        return ids

    def new_order(self) -> None:
        """A new order: drop every state except the instant actions still running (section 6.10.6)."""
        with self._lock:
            self._records = {k: r for k, r in self._records.items() if r.scope == INSTANT and not r.final}

    def to_json(self) -> list[dict[str, Any]]:
        """The `actionStates` array."""
        with self._lock:
            return [r.to_json() for r in self._records.values()]

"""The run recording's event side: a runner's events as `/log` and `/events`, and what they imply.

`RecorderEvents` is a base of `executor.recording.Recorder`: `_event` logs every event (a `Log` with the
event's level, and the JSON of `/events`) and calls its handler, if any: the task being run and its
state machine's states (`/report/task` at each task's end), the calibration (`/perception/calibration`)
and every pallet estimate against its nominal pose and the alignment tolerances
(`/scene/pallet_estimates`).

Public API: `RecorderEvents` (for `Recorder` only).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from foxglove.channels import LogChannel
from foxglove.messages import Log, SceneUpdate

from palletpilot.executor.adapters.mcap import recording_scene as scene
from palletpilot.executor.adapters.mcap.recording_channels import level, log_text
from palletpilot.geometry import SE3
from palletpilot.geometry.fileio import strict_json
from palletpilot.perception.alignment import AlignmentTolerances
from palletpilot.perception.specs import pallet_pose_at_node

if TYPE_CHECKING:
    from collections.abc import Callable

    from palletpilot.executor.core.runner import Runner


class RecorderEvents:
    """The event handlers of `Recorder` (module docstring); the attributes below are the recorder's."""

    ch_log: LogChannel
    runner: Runner | None
    _calibration: SE3 | None
    _state: str
    _task_index: int
    _task: dict[str, Any] | None
    _state_started: dict[str, float]
    _estimates: list[Any]
    ns: Callable[[float | None], int]
    count_message: Callable[[str], None]
    log_json: Callable[[str, Any, int], None]
    log_scene: Callable[[str, Any, int], None]

    def _event(self, event: str, data: dict[str, Any], t: float) -> None:
        ns = self.ns(t)
        self.ch_log.log(
            Log(
                timestamp=scene.stamp(ns),
                level=level(event),
                message=log_text(event, data),
                name="palletpilot.executor",
            ),
            log_time=ns,
        )
        self.count_message("/log")
        self.log_json("/events", {"t": round(t, 3), "event": event, **data}, ns)
        handler = getattr(self, f"_on_{event}", None)
        if handler is not None:
            handler(data, t, ns)

    def _on_task_start(self, data: dict[str, Any], t: float, ns: int) -> None:
        self._task_index = int(data.get("index", -1))
        self._task = {
            "index": data.get("index"),
            "type": data.get("type"),
            "node": data.get("node"),
            "result": "pending",
            "reason": None,
            "message": None,
            "attempts": 0,
            "start_s": t,
            "end_s": t,
            "states": [],
            "record": {},
        }

    def _on_state_start(self, data: dict[str, Any], t: float, ns: int) -> None:
        self._state = str(data.get("state", ""))
        self._state_started[self._state] = t

    def _on_state_end(self, data: dict[str, Any], t: float, ns: int) -> None:
        state = str(data.get("state", ""))
        if self._task is not None:
            start = self._state_started.get(state, t)
            self._task["states"].append(
                {"state": state, "start_s": round(start, 3), "end_s": round(t, 3), "outcome": data.get("outcome")}
            )

    def _on_task_failed(self, data: dict[str, Any], t: float, ns: int) -> None:
        if self._task is not None and self._task["reason"] is None:
            self._task["reason"], self._task["message"] = data.get("reason"), data.get("message")

    def _on_task_end(self, data: dict[str, Any], t: float, ns: int) -> None:
        assert self.runner is not None
        if self._task is None:
            return
        ctx = self.runner.ctx
        self._task.update(
            result=data.get("result"),
            reason=data.get("reason"),
            attempts=ctx.memory.attempts,
            end_s=t,
            record=strict_json(ctx.memory.record),
        )
        self.log_json("/report/task", self._task, ns)
        self._task, self._state = None, ""

    def _on_calibrated(self, data: dict[str, Any], t: float, ns: int) -> None:
        assert self.runner is not None
        calibration = self.runner.ctx.memory.calibration
        if calibration is None:
            return
        self._calibration = calibration.T_forklift_camera
        self.log_json("/perception/calibration", calibration.to_json(), ns)

    def _on_pallet_estimate(self, data: dict[str, Any], t: float, ns: int) -> None:
        assert self.runner is not None
        ctx = self.runner.ctx
        est = ctx.memory.estimated_pallet
        node = ctx.roadmap.node(str(data.get("against_node") or ctx.memory.pallet_node))
        if est is None:
            return
        st = ctx.settings
        tol = AlignmentTolerances.from_geometry(
            ctx.forks,
            ctx.pallet_type,
            lateral_margin_m=st.lateral_margin,
            longitudinal_margin_m=st.longitudinal_margin,
            yaw_limit_deg=st.yaw_limit_deg,
        )
        nominal = pallet_pose_at_node(node.pose, node.height)
        entity = scene.estimate_entity(len(self._estimates), data, est, nominal, tol, ctx.pallet_type, ns)
        self._estimates.append(entity)
        update = SceneUpdate(entities=list(self._estimates))
        self.log_scene("/scene/pallet_estimates", update, ns)

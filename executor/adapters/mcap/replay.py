"""Reading a run back from its recording: `run.mcap` to `report.json` and `trajectory.png`.

`read_recording(path)` reads what a report needs from the recording alone (`executor.recording`'s
channels): the roadmap (`/roadmap/graph`), every task's result and the run's figures (`/report/run`),
the driven path (localization on `/vehicle/state`, as the runner samples it: a point every 0.2 s), the
last planned paths (`/scene/planned_paths`), the true pallets and the obstacles (simulator runs:
`/scene/true_pallets`, `/scene/obstacles`). `replay(path, folder)` writes the report with
`executor.report.write_report`, so a truck's recording gives the same report as a simulated run.

What a recording cannot give back exactly: `trajectory.png` draws the planned paths from the scene's
points (every other point of each path) and the driven path from the recorded state (rounded to 0.1 mm);
the figures in report.json are the run's own.

Bad input (a missing or unreadable file, not MCAP, a truncated or damaged file, an MCAP without the
palletpilot channels) raises `ReplayError` with one line naming the file.

Public API: `Recording`, `ReplayError`, `read_recording`, `replay`.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from palletpilot.executor.adapters.mcap.recording_scene import cube_corners, curves_from_json
from palletpilot.executor.adapters.stores.report import write_report
from palletpilot.executor.core.results import TaskResult
from palletpilot.geometry import SE2, PalletpilotError
from palletpilot.roadmap import Direction, Edge, Node, NodeType, Roadmap

TRAJECTORY_STEP_S = 0.2
"""The runner's trajectory keeps a localization fix every 0.2 s (`Runner._record_tick`)."""
_NEEDED = ("/roadmap/graph", "/report/run")
_SCENE = ("/scene/planned_paths", "/scene/true_pallets", "/scene/obstacles")


class ReplayError(PalletpilotError):
    """A recording that cannot be replayed (one line naming the file)."""


@dataclass
class Recording:
    """What a report needs, read from a recording (map frame, m, rad)."""

    roadmap: Roadmap
    run: dict[str, Any]
    trajectory: list[tuple[float, float, float, float]] = field(default_factory=list)
    planned_paths: list[list[tuple[float, float]]] = field(default_factory=list)
    truth_pallets: list[SE2] | None = None
    obstacles: list[tuple[str, str, np.ndarray]] = field(default_factory=list)


def _messages(path: Path) -> Iterator[tuple[str, Any]]:
    """(topic, decoded message) in file order: JSON parsed, protobuf decoded for the scene topics only."""
    factory = DecoderFactory()
    decoders: dict[int, Any] = {}
    try:
        f = path.open("rb")
    except OSError as exc:
        raise ReplayError(f"{path}: cannot read: {exc.strerror or exc}") from None
    with f:
        try:
            if f.read(8) != b"\x89MCAP0\r\n":
                raise ReplayError(f"{path}: not an MCAP file (a recording is the run.mcap of a report folder)")
            f.seek(0)
            reader = make_reader(f)
            for schema, channel, message in reader.iter_messages(log_time_order=False):
                if channel.message_encoding == "json":
                    yield channel.topic, json.loads(message.data)
                elif channel.topic in _SCENE and schema is not None:
                    if schema.id not in decoders:
                        decoders[schema.id] = factory.decoder_for("protobuf", schema)
                    decode = decoders[schema.id]
                    if decode is None:
                        raise ReplayError(f"{path}: {channel.topic}: schema {schema.name} cannot be decoded")
                    yield channel.topic, decode(message.data)
        except ReplayError:
            raise
        except Exception as exc:  # the mcap reader's errors: a cut-off or damaged file
            raise ReplayError(f"{path}: truncated or damaged MCAP ({type(exc).__name__}: {exc})") from None


def _roadmap(doc: dict[str, Any]) -> Roadmap:
    """The roadmap of `/roadmap/graph` (its permanent nodes and edges)."""
    roadmap = Roadmap(doc.get("name", "roadmap"), source="run.mcap")
    for n in doc["nodes"]:
        x, y, yaw = n["pose"]
        roadmap.add_node(
            Node(
                n["id"],
                NodeType(n["type"]),
                SE2(x, y, yaw),
                n["has_heading"],
                n["height"],
                n["pre_pallet"],
                n["temporary"],
            )
        )
    for e in doc["edges"]:
        for curve in curves_from_json(e["curve"]):  # one curve, or a polyline's lines (drawn alike)
            roadmap.add_edge(
                Edge(e["start"], e["end"], curve, Direction(e["direction"]), e["speed_limit"], e["temporary"])
            )
    return roadmap


def read_recording(path: str | Path) -> Recording:
    """Read a recording (see the module docstring); raises `ReplayError`."""
    path = Path(path)
    latest: dict[str, Any] = {}
    trajectory: list[tuple[float, float, float, float]] = []
    for topic, msg in _messages(path):
        if topic == "/vehicle/state":
            if msg.get("x_m") is None:
                continue
            t = float(msg["t_s"])
            if not trajectory or t - trajectory[-1][0] >= TRAJECTORY_STEP_S - 1e-6:
                trajectory.append((t, msg["x_m"], msg["y_m"], math.radians(msg["yaw_deg"])))
        elif topic in _NEEDED or topic in _SCENE:
            latest[topic] = msg
    missing = [t for t in _NEEDED if t not in latest]
    if missing:
        raise ReplayError(
            f"{path}: no {' and no '.join(missing)}: not a finished palletpilot run's recording "
            "(a run that was killed leaves no /report/run)"
        )
    try:
        rec = Recording(_roadmap(latest["/roadmap/graph"]), latest["/report/run"], trajectory)
        rec.planned_paths = _planned(latest.get("/scene/planned_paths"))
        if "/scene/true_pallets" in latest:
            rec.truth_pallets = [_final_pose(e) for e in latest["/scene/true_pallets"].entities]
        rec.obstacles = _obstacles(latest.get("/scene/obstacles"))
    except (KeyError, TypeError, ValueError) as exc:
        raise ReplayError(f"{path}: a palletpilot channel does not hold what it should: {exc!r}") from None
    return rec


def _planned(update: Any) -> list[list[tuple[float, float]]]:
    if update is None:
        return []
    return [[(p.x, p.y) for p in line.points] for e in update.entities for line in e.lines]


def _final_pose(entity: Any) -> SE2:
    record = json.loads(next(kv.value for kv in entity.metadata if kv.key == "record"))
    final = record["final"]
    return SE2(final["x_m"], final["y_m"], math.radians(final["yaw_deg"]))


def _obstacles(update: Any) -> list[tuple[str, str, np.ndarray]]:
    if update is None:
        return []
    out = []
    for e in update.entities:
        meta = {kv.key: kv.value for kv in e.metadata}
        out.append((meta.get("kind", "box"), meta.get("id", e.id), cube_corners(e.cubes[0])))
    return out


def replay(path: str | Path, folder: str | Path) -> Path:
    """Write `report.json` and `trajectory.png` of the recording at `path` into `folder`; returns the JSON
    path. Raises `ReplayError` (bad recording) or `OutputError` (a file cannot be written)."""
    rec = read_recording(path)
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ReplayError(f"{folder}: cannot create the report folder: {exc.strerror or exc}") from None
    run = rec.run
    extra = {k: v for k, v in run.items() if k not in ("mission", "success", "results")}
    return write_report(
        folder,
        run["mission"],
        bool(run["success"]),
        [TaskResult.from_json(r) for r in run["results"]],
        rec.roadmap,
        rec.trajectory,
        rec.planned_paths,
        truth_pallets=rec.truth_pallets,
        extra=extra,
        obstacles=rec.obstacles,
    )

"""The AGV's crash-safe journal: what `palletpilot agv` needs to come back after a kill or a power cut.

A thin layer on `executor.journal` (SQLite, WAL, `synchronous=FULL`, one committed transaction per
checkpoint), the project's one way to write crash-safe state. One journal per AGV (`--journal FILE`,
default `agv.db` in the report folder); its run description (`meta`) names the AGV (`kind`
`vda5050-agv`, manufacturer, serialNumber, mapId), so a journal of another AGV, of another map or of a
`palletpilot run` mission is refused in one line naming the file.

A checkpoint (`Agv.checkpoint_doc`) holds the order as the AGV executes it (orderId, orderUpdateId,
lastNodeId / lastNodeSequenceId and its roadmap node, every node and edge with the cursor of the next node
to traverse, the roadmap node of each, the order messages accepted since the last new order as received),
every action state (status, resultDescription, the status a paused action returns to), the order-related
errors, the load, the headerIds reserved per topic, the master's pause, the protocol version answered,
operatingMode and the pose. It is written on every event that publishes a state (`Agv.changed`: order
accepted or rejected, node traversed, action state change, load change, cancel, leg end), never per tick,
by a writer thread (`Persister`): the control loop only sets a flag, requests that pile up while a write
is under way coalesce into one write of the newest state. So a checkpoint lands a few milliseconds after
its event (`Persister.stats`: the measured write times).

HeaderIds: every topic's headerIds are reserved `HEADER_BLOCK` ahead in each checkpoint, and a new
checkpoint is requested once half a block is used; a restarted AGV continues every topic at its reserved
id, above every id it sent before (gaps are allowed, repeats are not).

Sessions (`open_session`): no file, an empty file or a finished journal start a new session (the file is
replaced; the finished journal's headerIds carry over in `meta`). An unfinished journal (the AGV was killed,
or stopped while an order was still executing) is resumed: its last checkpoint is restored
(`Agv.restore`) and the AGV appends to the same file. A clean stop with no order executing finishes the
journal.

Public API: `open_session`, `Session`, `Persister`, `orders_doc`, `restore_orders`, `agv_meta`,
`JOURNAL_NAME`, `HEADER_BLOCK`, `KIND`, `FORMAT`.
"""

from __future__ import annotations

import statistics
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from palletpilot.executor.adapters.stores.journal import Journal, JournalError
from palletpilot.executor.apps.vda5050.actions import ActionRecord, ActionTable
from palletpilot.executor.apps.vda5050.models import Action, ActionStatus, AgvError, ErrorLevel, OrderEdge, OrderNode
from palletpilot.executor.apps.vda5050.orders import OrderManager
from palletpilot.roadmap import Roadmap

KIND = "vda5050-agv"
"""`meta.kind` of an AGV's journal."""
FORMAT = 1
"""The checkpoint layout written and read here (`meta.format`, `doc.format`)."""
JOURNAL_NAME = "agv.db"
"""The default journal's file name in the report folder."""
HEADER_BLOCK = 1000
"""HeaderIds reserved per topic in each checkpoint (a new checkpoint is requested at half a block)."""
TOPICS = ("state", "visualization", "connection", "factsheet")
"""The topics the AGV publishes (reserved even before their first message)."""


# -- the order manager to and from JSON -------------------------------------------------------------------
def action_json(a: Action) -> dict[str, Any]:
    """An action as the order message gave it."""
    out: dict[str, Any] = {"actionId": a.action_id, "actionType": a.action_type, "blockingType": a.blocking_type.value}
    if a.parameters:
        out["actionParameters"] = [{"key": k, "value": v} for k, v in a.parameters]
    if a.description is not None:
        out["actionDescription"] = a.description
    return out


def node_json(n: OrderNode) -> dict[str, Any]:
    """An order node as the order message gave it."""
    out: dict[str, Any] = {
        "nodeId": n.node_id,
        "sequenceId": n.sequence_id,
        "released": n.released,
        "actions": [action_json(a) for a in n.actions],
    }
    if n.position is not None:
        out["nodePosition"] = n.position
    if n.description is not None:
        out["nodeDescription"] = n.description
    return out


def error_json(e: AgvError) -> dict[str, Any]:
    """An error with its hint (the state's `error` object)."""
    return e.to_json()


def error_from_json(doc: dict[str, Any]) -> AgvError:
    """The inverse of `error_json`."""
    refs = tuple((str(r["referenceKey"]), str(r["referenceValue"])) for r in doc.get("errorReferences", ()))
    return AgvError(
        str(doc["errorType"]),
        ErrorLevel(doc["errorLevel"]),
        str(doc["errorDescription"]),
        refs,
        doc.get("errorHint"),
    )


def orders_doc(o: OrderManager) -> dict[str, Any]:
    """The order manager's state as JSON (see the module docstring); call it holding `o.lock`."""
    return {
        "orderId": o.order_id,
        "orderUpdateId": o.order_update_id,
        "lastNodeId": o.last_node_id,
        "lastNodeSequenceId": o.last_node_seq,
        "lastRoadmapNode": o.last_rm,
        "cursor": o.cursor,
        "nodes": [node_json(n) for n in o.nodes],
        "edges": [dict(e.raw) for e in o.edges],
        "roadmapNodes": list(o.rm),
        "actions": [
            {
                "action": action_json(r.action),
                "scope": r.scope,
                "status": r.status.value,
                "result": r.result,
                "resumeTo": r.resume_to.value if r.resume_to is not None else None,
            }
            for r in o.actions
        ],
        "errors": [error_json(e) for e in o.errors],
        "received": list(o.received),
        "stitchBlock": o.stitch_block,
    }


def restore_orders(o: OrderManager, doc: dict[str, Any], roadmap: Roadmap) -> None:
    """Put a checkpoint's order state (`orders_doc`) back into a fresh order manager. Raises KeyError,
    TypeError or ValueError on a malformed document, ValueError on roadmap nodes this map lacks."""
    nodes = [OrderNode.from_json(n) for n in doc["nodes"]]
    edges = [OrderEdge.from_json(e) for e in doc["edges"]]
    rm = [str(r) for r in doc["roadmapNodes"]]
    cursor = int(doc["cursor"])
    if len(rm) != len(nodes) or len(edges) != max(len(nodes) - 1, 0) or not 0 <= cursor <= len(nodes):
        raise ValueError("the order's nodes, edges and cursor do not fit together")
    last_rm = str(doc.get("lastRoadmapNode") or "")
    for name in [*rm, *([last_rm] if last_rm else [])]:
        if name not in roadmap:
            raise ValueError(f"roadmap node '{name}' is not on this map")
    with o.lock:
        o.order_id, o.order_update_id = str(doc["orderId"]), int(doc["orderUpdateId"])
        o.last_node_id, o.last_node_seq = str(doc["lastNodeId"]), int(doc["lastNodeSequenceId"])
        o.last_rm = last_rm
        o.nodes, o.edges, o.rm, o.cursor = nodes, edges, rm, cursor
        o.actions = ActionTable()
        for item in doc["actions"]:
            record: ActionRecord = o.actions.add(
                Action.from_json(item["action"]), str(item["scope"]), ActionStatus(item["status"])
            )
            record.result = item.get("result")
            resume = item.get("resumeTo")
            record.resume_to = ActionStatus(resume) if resume else None
        o.errors = [error_from_json(e) for e in doc["errors"]]
        o.received = [dict(d) for d in doc.get("received", ())]
        block = doc.get("stitchBlock")
        o.stitch_block = str(block) if block else None


# -- sessions ---------------------------------------------------------------------------------------------
def agv_meta(manufacturer: str, serial_number: str, map_id: str) -> dict[str, Any]:
    """The run description of an AGV's journal."""
    return {
        "kind": KIND,
        "format": FORMAT,
        "manufacturer": manufacturer,
        "serialNumber": serial_number,
        "mapId": map_id,
    }


@dataclass
class Session:
    """An AGV journal ready to be written: `restored` is the last checkpoint of an unfinished session (None
    for a new one), `headers` the headerIds to continue at (a finished session's, carried over)."""

    path: Path
    restored: dict[str, Any] | None = None
    headers: dict[str, int] = field(default_factory=dict)
    resumes: int = 0


def _check_meta(path: Path, meta: dict[str, Any], want: dict[str, Any]) -> None:
    if meta.get("kind") != KIND:
        what = f"kind '{meta['kind']}'" if "kind" in meta else "a `palletpilot run` mission journal?"
        raise JournalError(f"{path}: not the journal of a VDA 5050 AGV ({what}); give `palletpilot agv` its own file")
    if meta.get("format") != FORMAT:
        raise JournalError(f"{path}: AGV journal format {meta.get('format')}, this palletpilot reads format {FORMAT}")
    theirs = f"{meta.get('manufacturer')}/{meta.get('serialNumber')}"
    ours = f"{want['manufacturer']}/{want['serialNumber']}"
    if theirs != ours:
        raise JournalError(
            f"{path}: the journal of AGV {theirs}, not of this AGV {ours}; choose another --journal file"
        )
    if meta.get("mapId") != want["mapId"]:
        raise JournalError(
            f"{path}: the journal's order runs on map '{meta.get('mapId')}', this AGV's map is '{want['mapId']}'; "
            "remove the file or choose another --journal file"
        )


def _headers(doc: Any) -> dict[str, int]:
    if not isinstance(doc, dict):
        return {}
    return {str(k): int(v) for k, v in doc.items() if isinstance(v, int) and not isinstance(v, bool)}


def open_session(path: str | Path, meta: dict[str, Any]) -> Session:
    """Open or create the AGV journal at `path` for the AGV described by `meta` (`agv_meta`); see the module
    docstring. The journal is closed again: the `Persister` opens it in its own thread. Raises `JournalError`
    (one line naming the file) for a file that is not this AGV's journal or cannot be written."""
    path = Path(path)
    carried: dict[str, int] = {}
    if path.is_file() and path.stat().st_size > 0:
        try:
            journal = Journal.open(path)
        except JournalError:
            journal = None  # an empty leftover of a crashed create is replaced; anything else is refused by create
        if journal is not None:
            with journal:
                _check_meta(path, journal.meta, meta)
                last = journal.last_checkpoint()
                if not journal.finished:
                    resumes = journal.mark_resumed()
                    if last is not None and last.get("format") != FORMAT:
                        raise JournalError(f"{path}: the last checkpoint is not an AGV checkpoint of format {FORMAT}")
                    headers = _headers((last or {}).get("headers")) or _headers(journal.meta.get("headers"))
                    return Session(path, last, headers, resumes)
                carried = _headers((last or {}).get("headers")) or _headers(journal.meta.get("headers"))
    Journal.create(path, {**meta, "headers": carried}).close()
    return Session(path, None, carried)


# -- the writer thread ------------------------------------------------------------------------------------
class Persister:
    """Writes checkpoints built by `build()` to the journal at `path` in its own thread (see the module
    docstring): `request()` from any thread, `flush()` to write now and wait, `close()` at the end."""

    def __init__(self, path: Path, build: Callable[[], dict[str, Any]], log: Callable[[str], None] = print) -> None:
        self.path = path
        self.build = build
        self.log = log
        self.write_ms: deque[float] = deque(maxlen=10_000)
        """The durations of the last checkpoint writes (build excluded), ms."""
        self.count = 0
        self.max_ms = 0.0
        self.total_ms = 0.0
        self.errors: list[str] = []
        self._failing: str | None = None
        self._cond = threading.Condition()
        self._requested = 0
        self._done = 0
        self._closing: tuple[bool, str | None] | None = None
        self._opened = threading.Event()
        self._open_failed = False
        self._thread = threading.Thread(target=self._loop, name="vda5050-journal", daemon=True)

    def start(self) -> None:
        """Open the journal in the writer thread; raises `JournalError` when it cannot be opened."""
        self._thread.start()
        self._opened.wait()
        if self._open_failed:
            raise JournalError(self.errors[-1])

    def request(self) -> None:
        """Ask for a checkpoint of the current state (cheap: a flag; writes coalesce)."""
        with self._cond:
            self._requested += 1
            self._cond.notify_all()

    def flush(self, timeout_s: float = 10.0) -> bool:
        """Write a checkpoint of the current state now and wait until it is committed; False on failure."""
        with self._cond:
            self._requested += 1
            target = self._requested
            self._cond.notify_all()
            errors = len(self.errors)
            ok = self._cond.wait_for(lambda: self._done >= target or not self._thread.is_alive(), timeout_s)
            return ok and self._done >= target and len(self.errors) == errors

    def close(self, finish: bool, reason: str | None = None, timeout_s: float = 10.0) -> None:
        """Write the last checkpoint, mark the journal finished when `finish` (a clean stop with no order
        executing), close it and end the thread."""
        with self._cond:
            self._closing = (finish, reason)
            self._cond.notify_all()
        self._thread.join(timeout_s)

    def stats(self) -> dict[str, Any]:
        """Checkpoint writes so far: count, mean / p50 / max milliseconds."""
        w = list(self.write_ms)
        if not w:
            return {"checkpoints": 0}
        return {
            "checkpoints": self.count,
            "mean_ms": round(self.total_ms / self.count, 3),
            "p50_ms": round(statistics.median(w), 3),
            "max_ms": round(self.max_ms, 3),
        }

    def _error(self, line: str) -> None:
        self.errors.append(line)
        self.log(f"agv: {line}")

    def _loop(self) -> None:
        try:
            journal = Journal.open(self.path)
        except JournalError as exc:
            self.errors.append(str(exc))
            self._open_failed = True
            self._opened.set()
            return
        self._opened.set()
        with journal:
            while True:
                with self._cond:
                    self._cond.wait_for(lambda: self._requested > self._done or self._closing is not None)
                    target, closing = self._requested, self._closing
                self._write(journal)
                with self._cond:
                    self._done = max(self._done, target)
                    self._cond.notify_all()
                if closing is not None:
                    finish, reason = closing
                    if finish:
                        try:
                            journal.finish(True, reason)
                        except JournalError as exc:
                            self._error(str(exc))
                    return

    def _write(self, journal: Journal) -> None:
        try:
            doc = self.build()
        except Exception as exc:  # a bug: never kill the writer
            self._error(f"{self.path}: cannot build a checkpoint: {type(exc).__name__}: {exc}")
            return
        t0 = time.perf_counter()
        try:
            journal.checkpoint(doc)
        except JournalError as exc:
            if self._failing != str(exc):  # one line per new failure, not per checkpoint
                self._failing = str(exc)
                self._error(f"{exc} (the AGV drives on; its progress is not crash-safe until the journal writes)")
            return
        ms = (time.perf_counter() - t0) * 1000.0
        self._failing = None
        self.write_ms.append(ms)
        self.count += 1
        self.total_ms += ms
        self.max_ms = max(self.max_ms, ms)

"""The transport of the ROS 2 adapter: publish and subscribe ROS 2 topics, whatever carries them.

`Transport` is the whole interface (`publish`, `advertise`, `subscribe`, `close`); two implementations
share it: `executor.ros.dds.DdsTransport` (Cyclone DDS from PyPI: no ROS installation needed, ROS 2
naming `rt/<topic>` and type names `pkg::msg::dds_::Type_`, the same CDR bytes rclpy puts on the wire)
and `executor.ros.rclpy_transport.RclpyTransport` (rclpy, where a ROS 2 installation provides it);
`MemoryTransport` connects publishers and subscribers inside one process (tests).
`open_transport(kind, ...)` picks one: `auto` takes rclpy when `import rclpy` works, else Cyclone DDS.

Messages are the IDL classes of `executor.ros.messages` with either transport. A `Subscription` keeps
the latest message with its receive time (`time.monotonic()`, s) and the number received; an optional
callback sees every message, on the transport's receive thread (keep it short, never publish from it).

Topic names are ROS 2 names (`/odom`, `/camera/color/image_raw`); `QosSpec` is the part of the QoS a
robot file sets: reliability, history depth and durability (`transient_local` for latched topics such
as `/tf_static`).
"""

from __future__ import annotations

import re
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Generic, Literal, Protocol, TypeVar

from cyclonedds.idl import IdlStruct

from palletpilot.geometry import PalletpilotError

M = TypeVar("M", bound=IdlStruct)
Reliability = Literal["reliable", "best_effort"]
Durability = Literal["volatile", "transient_local"]
TransportKind = Literal["auto", "dds", "rclpy"]

_NAME = re.compile(r"/?[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*")


class TransportError(PalletpilotError):
    """A transport cannot be opened or used (no rclpy, a bad topic name, DDS refused an entity)."""


@dataclass(frozen=True)
class QosSpec:
    """The QoS a robot file sets for a topic: `reliable` or `best_effort`, keep-last `depth`, durability."""

    reliability: Reliability = "reliable"
    depth: int = 10
    durability: Durability = "volatile"


DEFAULT_QOS = QosSpec()
"""Reliable, keep last 10, volatile: the ROS 2 default profile."""


def check_topic_name(name: str) -> str:
    """`name` when it is a valid absolute or relative ROS 2 topic name (`/odom`, `camera/color/image_raw`),
    else `TransportError`. No substitutions (`~`, `{}`) and no trailing slash."""
    if not _NAME.fullmatch(name):
        raise TransportError(
            f"'{name}' is not a ROS 2 topic name (tokens of letters, digits and _ between '/', "
            "not starting with a digit; no '~', no '{}', no trailing '/')"
        )
    return name


def dds_topic_name(name: str) -> str:
    """The DDS topic of a ROS 2 topic: `/odom` -> `rt/odom` (names are taken as absolute)."""
    return "rt/" + check_topic_name(name).lstrip("/")


@dataclass(frozen=True)
class Received(Generic[M]):
    """A message and when it arrived (`received_s`: `time.monotonic()`, s)."""

    msg: M
    received_s: float


class Subscription(Generic[M]):
    """A topic's latest message with its receive time, and how many came; thread-safe."""

    def __init__(self, topic: str, msg_type: type[M], callback: Callable[[M, float], None] | None = None) -> None:
        self.topic = topic
        self.msg_type = msg_type
        self.callback = callback
        self.count = 0
        self._latest: Received[M] | None = None
        self._lock = threading.Lock()

    def latest(self) -> Received[M] | None:
        """The last message and its receive time, or None before the first."""
        with self._lock:
            return self._latest

    def age(self, now_s: float | None = None) -> float:
        """Seconds since the last message arrived (`inf` before the first); `now_s` on `time.monotonic()`."""
        latest = self.latest()
        if latest is None:
            return float("inf")
        return (time.monotonic() if now_s is None else now_s) - latest.received_s

    def deliver(self, msg: M, received_s: float | None = None) -> None:
        """Store a message (the transport's receive thread calls this) and call the callback."""
        when = time.monotonic() if received_s is None else received_s
        with self._lock:
            self._latest = Received(msg, when)
            self.count += 1
        if self.callback is not None:
            self.callback(msg, when)


class Transport(Protocol):
    """Publish and subscribe ROS 2 topics (module docstring)."""

    def advertise(self, topic: str, msg_type: type[IdlStruct], qos: QosSpec | None = None) -> None:
        """Create the writer of `topic` now, so that discovery is done before the first `publish`."""
        ...

    def publish(self, topic: str, msg: IdlStruct, qos: QosSpec | None = None) -> None:
        """Publish `msg` on `topic` (the writer is created on first use with `qos`)."""
        ...

    def subscribe(
        self,
        topic: str,
        msg_type: type[M],
        qos: QosSpec | None = None,
        callback: Callable[[M, float], None] | None = None,
    ) -> Subscription[M]:
        """Subscribe `topic`; the `Subscription` keeps the latest message, `callback(msg, received_s)` sees all."""
        ...

    def close(self) -> None:
        """Stop receiving and release every entity; calling it twice is harmless."""
        ...


class MemoryTransport:
    """A `Transport` inside one process: `publish` hands the message to every subscription of the topic at
    once, on the caller's thread (tests, and a dry run without DDS). `published` keeps every message sent."""

    def __init__(self) -> None:
        self._subs: dict[str, list[Subscription[Any]]] = {}
        self.published: list[tuple[str, IdlStruct]] = []
        self.advertised: dict[str, type[IdlStruct]] = {}
        self.closed = False

    def advertise(self, topic: str, msg_type: type[IdlStruct], qos: QosSpec | None = None) -> None:
        """Remember the topic's type."""
        self.advertised[check_topic_name(topic)] = msg_type

    def publish(self, topic: str, msg: IdlStruct, qos: QosSpec | None = None) -> None:
        """Deliver `msg` to the topic's subscriptions of a matching type."""
        if self.closed:
            raise TransportError("the memory transport is closed")
        self.published.append((topic, msg))
        for sub in self._subs.get(topic, []):
            if isinstance(msg, sub.msg_type):
                sub.deliver(msg)

    def subscribe(
        self,
        topic: str,
        msg_type: type[M],
        qos: QosSpec | None = None,
        callback: Callable[[M, float], None] | None = None,
    ) -> Subscription[M]:
        """Subscribe `topic`."""
        sub: Subscription[M] = Subscription(check_topic_name(topic), msg_type, callback)
        self._subs.setdefault(topic, []).append(sub)
        return sub

    def sent(self, topic: str) -> list[Any]:
        """The messages published on `topic`, oldest first."""
        return [m for t, m in self.published if t == topic]

    def close(self) -> None:
        """Stop accepting messages."""
        self.closed = True


def rclpy_available() -> bool:
    """True when `import rclpy` works (a sourced ROS 2 installation)."""
    try:
        import rclpy  # noqa: F401
    except ImportError:
        return False
    return True


def open_transport(
    kind: TransportKind = "auto", domain_id: int | None = None, node_name: str = "palletpilot"
) -> Transport:
    """A transport: `dds` (Cyclone DDS), `rclpy`, or `auto` (rclpy when importable, else Cyclone DDS).

    `domain_id`: the DDS domain (None: `ROS_DOMAIN_ID`, else 0). `node_name`: the rclpy node's name.
    """
    if kind == "rclpy" or (kind == "auto" and rclpy_available()):
        from palletpilot.executor.adapters.ros.rclpy_transport import RclpyTransport

        return RclpyTransport(domain_id=domain_id, node_name=node_name)
    from palletpilot.executor.adapters.ros.dds import DdsTransport

    return DdsTransport(domain_id=domain_id)

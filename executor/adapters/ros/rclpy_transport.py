"""`RclpyTransport`: the same `Transport` on rclpy, for a truck with a ROS 2 installation (Humble, Jazzy).

Used only where `import rclpy` works (`open_transport("auto")` checks); this module imports without it.
Messages cross the boundary as the IDL classes of `executor.ros.messages`: each is converted field by
field to and from the rosidl class of the same ROS name (`rosidl_runtime_py.utilities.get_message`), so
the adapter above never sees which transport carries its topics. One node (`palletpilot`) spins on a
background thread (a `SingleThreadedExecutor`); subscription callbacks run there.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Callable
from typing import Any

from cyclonedds.idl import IdlStruct

from palletpilot.executor.adapters.ros.messages import MESSAGE_TYPES, ros_type_name
from palletpilot.executor.adapters.ros.transport import (
    DEFAULT_QOS,
    M,
    QosSpec,
    Subscription,
    TransportError,
    check_topic_name,
)


def _ros_qos(spec: QosSpec) -> Any:
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=spec.depth,
        reliability=ReliabilityPolicy.RELIABLE if spec.reliability == "reliable" else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL
        if spec.durability == "transient_local"
        else DurabilityPolicy.VOLATILE,
    )


def _ros_class(cls: type[IdlStruct]) -> Any:
    from rosidl_runtime_py.utilities import get_message

    return get_message(ros_type_name(cls))


def to_ros(msg: Any) -> Any:
    """The rosidl message of an IDL message (recursively; arrays and sequences as lists, `bytes` kept)."""
    if not isinstance(msg, IdlStruct):
        return msg
    out = _ros_class(type(msg))()
    for f in dataclasses.fields(msg):  # type: ignore[arg-type]
        value = getattr(msg, f.name)
        if isinstance(value, list):
            value = [to_ros(v) for v in value]
        setattr(out, f.name, to_ros(value))
    return out


def from_ros(ros_msg: Any, cls: type[M]) -> M:
    """The IDL message of a rosidl message of the same ROS name."""
    import typing

    hints = typing.get_type_hints(cls)
    kwargs: dict[str, Any] = {}
    for f in dataclasses.fields(cls):  # type: ignore[arg-type]
        value = getattr(ros_msg, f.name)
        hint = hints.get(f.name)
        if isinstance(hint, type) and issubclass(hint, IdlStruct):
            kwargs[f.name] = from_ros(value, hint)
        elif hasattr(value, "get_fields_and_field_types"):
            kwargs[f.name] = from_ros(value, MESSAGE_TYPES[_ros_name(value)])
        elif isinstance(value, (list, tuple)) and value and hasattr(value[0], "get_fields_and_field_types"):
            kwargs[f.name] = [from_ros(v, MESSAGE_TYPES[_ros_name(v)]) for v in value]
        elif isinstance(value, (bytes, bytearray)) or (f.name == "data" and cls.__name__ == "Image"):
            kwargs[f.name] = bytes(value)
        elif hasattr(value, "tolist"):  # numpy arrays and array.array
            kwargs[f.name] = list(value.tolist())
        elif isinstance(value, (list, tuple)):
            kwargs[f.name] = list(value)
        else:
            kwargs[f.name] = value
    return cls(**kwargs)


def _ros_name(ros_msg: Any) -> str:
    module = type(ros_msg).__module__.split(".")[0]  # e.g. std_msgs.msg._header -> std_msgs
    return f"{module}/msg/{type(ros_msg).__name__}"


class RclpyTransport:
    """The `Transport` on rclpy (module docstring)."""

    def __init__(self, domain_id: int | None = None, node_name: str = "palletpilot") -> None:
        try:
            import rclpy
            from rclpy.executors import SingleThreadedExecutor
        except ImportError as exc:
            raise TransportError(
                f"rclpy is not importable ({exc}): source a ROS 2 installation (Humble or Jazzy), or use the "
                "Cyclone DDS transport (robot file `transport: dds`)"
            ) from None
        self._rclpy = rclpy
        self._context = rclpy.Context()
        rclpy.init(context=self._context, domain_id=domain_id)
        self._node = rclpy.create_node(node_name, context=self._context)
        self._executor = SingleThreadedExecutor(context=self._context)
        self._executor.add_node(self._node)
        self._publishers: dict[str, Any] = {}
        self._subscriptions: list[Any] = []
        self._lock = threading.Lock()
        self._closed = False
        self._thread = threading.Thread(target=self._spin, name="rclpy-spin", daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        while not self._closed and self._context.ok():
            self._executor.spin_once(timeout_sec=0.1)

    def advertise(self, topic: str, msg_type: type[IdlStruct], qos: QosSpec | None = None) -> None:
        """Create the publisher of `topic` now."""
        self._publisher(topic, msg_type, qos)

    def _publisher(self, topic: str, msg_type: type[IdlStruct], qos: QosSpec | None) -> Any:
        with self._lock:
            if self._closed:
                raise TransportError("the rclpy transport is closed")
            pub = self._publishers.get(topic)
            if pub is None:
                pub = self._node.create_publisher(
                    _ros_class(msg_type), check_topic_name(topic), _ros_qos(qos or DEFAULT_QOS)
                )
                self._publishers[topic] = pub
            return pub

    def publish(self, topic: str, msg: IdlStruct, qos: QosSpec | None = None) -> None:
        """Publish `msg` on `topic`."""
        self._publisher(topic, type(msg), qos).publish(to_ros(msg))

    def subscribe(
        self,
        topic: str,
        msg_type: type[M],
        qos: QosSpec | None = None,
        callback: Callable[[M, float], None] | None = None,
    ) -> Subscription[M]:
        """Subscribe `topic` (see `Transport.subscribe`)."""
        sub: Subscription[M] = Subscription(topic, msg_type, callback)

        def on_message(ros_msg: Any) -> None:
            sub.deliver(from_ros(ros_msg, msg_type), time.monotonic())

        with self._lock:
            handle = self._node.create_subscription(
                _ros_class(msg_type), check_topic_name(topic), on_message, _ros_qos(qos or DEFAULT_QOS)
            )
            self._subscriptions.append(handle)
        return sub

    def close(self) -> None:
        """Stop spinning, destroy the node and shut the context down."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        self._thread.join(timeout=2.0)
        self._executor.shutdown()
        self._node.destroy_node()
        self._rclpy.shutdown(context=self._context)

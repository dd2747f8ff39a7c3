"""`DdsTransport`: ROS 2 topics straight on Cyclone DDS (the `cyclonedds` wheel bundles the C library).

What makes it talk to ROS 2 nodes (rmw_cyclonedds_cpp, and rmw_fastrtps through DDSI-RTPS): the DDS
topic of a ROS topic `/odom` is `rt/odom`, the type names are `pkg::msg::dds_::Type_`, samples are
XCDR1 little-endian (`executor.ros.messages`), and the QoS is the robot file's (reliability, keep-last
depth, durability). The domain is `domain_id`, else `ROS_DOMAIN_ID`, else 0; the DDS configuration is
Cyclone's own (`CYCLONEDDS_URI`: e.g. bind to one interface, or to loopback only in tests).

One receive thread waits on the readers (a DDS `WaitSet`) and takes every new sample; the DDS threads
never run Python (Cyclone's listeners would take the GIL on its receive path).
"""

from __future__ import annotations

import contextlib
import os
import random
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from cyclonedds.core import DDSException, GuardCondition, InstanceState, ReadCondition, SampleState, ViewState, WaitSet
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.pub import DataWriter
from cyclonedds.qos import Policy, Qos
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration

from palletpilot.executor.adapters.ros.transport import (
    DEFAULT_QOS,
    M,
    QosSpec,
    Subscription,
    TransportError,
    dds_topic_name,
)

MAX_DOMAIN_ID = 232
"""The largest DDS domain id whose ports fit (Cyclone's default port mapping)."""
_TAKE_BATCH = 64


def domain_from_env(domain_id: int | None) -> int:
    """`domain_id`, else `ROS_DOMAIN_ID` from the environment, else 0; `TransportError` when out of range."""
    if domain_id is None:
        text = os.environ.get("ROS_DOMAIN_ID", "").strip()
        try:
            domain_id = int(text) if text else 0
        except ValueError:
            raise TransportError(f"ROS_DOMAIN_ID: must be an integer 0..{MAX_DOMAIN_ID}, got '{text}'") from None
    if not 0 <= domain_id <= MAX_DOMAIN_ID:
        raise TransportError(f"DDS domain id must be in 0..{MAX_DOMAIN_ID}, got {domain_id}")
    return domain_id


LOOPBACK_CONFIG = """<?xml version="1.0" encoding="UTF-8"?>
<CycloneDDS xmlns="https://cdds.io/config">
  <Domain Id="any">
    <General>
      <Interfaces><NetworkInterface address="127.0.0.1"/></Interfaces>
      <AllowMulticast>false</AllowMulticast>
    </General>
    <Discovery>
      <ParticipantIndex>auto</ParticipantIndex>
      <MaxAutoParticipantIndex>30</MaxAutoParticipantIndex>
      <Peers><Peer address="127.0.0.1"/></Peers>
    </Discovery>
  </Domain>
</CycloneDDS>
"""
"""Cyclone DDS bound to the loopback interface, unicast discovery of this computer's participants only."""


def loopback_env(folder: str | os.PathLike[str], domain_id: int | None = None) -> dict[str, str]:
    """Environment for DDS on loopback only: writes `folder/cyclonedds-loopback.xml` and returns
    `CYCLONEDDS_URI` pointing at it and `ROS_DOMAIN_ID` (`domain_id`, else a random one in 1..100, so that
    parallel test runs never meet). For tests and a first try on one computer."""
    path = Path(folder) / "cyclonedds-loopback.xml"
    path.write_text(LOOPBACK_CONFIG)
    domain = random.SystemRandom().randint(1, 100) if domain_id is None else domain_id
    return {"CYCLONEDDS_URI": path.resolve().as_uri(), "ROS_DOMAIN_ID": str(domain)}


def dds_qos(spec: QosSpec) -> Qos:
    """The Cyclone DDS QoS of a robot file's `QosSpec`."""
    reliability = (
        Policy.Reliability.Reliable(max_blocking_time=duration(milliseconds=100))
        if spec.reliability == "reliable"
        else Policy.Reliability.BestEffort
    )
    durability = (
        Policy.Durability.TransientLocal if spec.durability == "transient_local" else Policy.Durability.Volatile
    )
    return Qos(reliability, Policy.History.KeepLast(spec.depth), durability)


class DdsTransport:
    """The `Transport` on Cyclone DDS (module docstring)."""

    def __init__(self, domain_id: int | None = None) -> None:
        self.domain_id = domain_from_env(domain_id)
        try:
            self._participant = DomainParticipant(self.domain_id)
        except DDSException as exc:
            raise TransportError(f"Cyclone DDS: cannot join domain {self.domain_id}: {exc}") from None
        self._lock = threading.Lock()
        self._topics: dict[str, Topic[Any]] = {}
        self._writers: dict[str, DataWriter[Any]] = {}
        self._readers: list[tuple[DataReader[Any], ReadCondition, Subscription[Any]]] = []
        self._waitset = WaitSet(self._participant)
        self._wake = GuardCondition(self._participant)
        self._waitset.attach(self._wake)
        self._closed = False
        self._thread = threading.Thread(target=self._receive, name="dds-receive", daemon=True)
        self._thread.start()

    # -- entities ------------------------------------------------------------------------------------
    def _topic(self, name: str, msg_type: type[IdlStruct]) -> Topic[Any]:
        dds_name = dds_topic_name(name)
        topic = self._topics.get(dds_name)
        if topic is None:
            try:
                topic = Topic(self._participant, dds_name, msg_type)
            except DDSException as exc:
                raise TransportError(f"{name}: cannot create DDS topic {dds_name}: {exc}") from None
            self._topics[dds_name] = topic
        elif topic.data_type is not msg_type:
            raise TransportError(
                f"{name}: already used with {topic.data_type.__name__}, not {msg_type.__name__} (one type per topic)"
            )
        return topic

    def advertise(self, topic: str, msg_type: type[IdlStruct], qos: QosSpec | None = None) -> None:
        """Create the writer of `topic` now (discovery starts at once)."""
        self._writer(topic, msg_type, qos)

    def _writer(self, topic: str, msg_type: type[IdlStruct], qos: QosSpec | None) -> DataWriter[Any]:
        with self._lock:
            self._check_open()
            writer = self._writers.get(topic)
            if writer is None:
                try:
                    writer = DataWriter(
                        self._participant, self._topic(topic, msg_type), qos=dds_qos(qos or DEFAULT_QOS)
                    )
                except DDSException as exc:
                    raise TransportError(f"{topic}: cannot create a DDS writer: {exc}") from None
                self._writers[topic] = writer
            return writer

    def publish(self, topic: str, msg: IdlStruct, qos: QosSpec | None = None) -> None:
        """Publish `msg` on `topic`."""
        writer = self._writer(topic, type(msg), qos)
        try:
            writer.write(msg)
        except DDSException as exc:
            raise TransportError(f"{topic}: write failed: {exc}") from None

    def subscribe(
        self,
        topic: str,
        msg_type: type[M],
        qos: QosSpec | None = None,
        callback: Callable[[M, float], None] | None = None,
    ) -> Subscription[M]:
        """Subscribe `topic` (see `Transport.subscribe`)."""
        sub: Subscription[M] = Subscription(topic, msg_type, callback)
        with self._lock:
            self._check_open()
            try:
                reader = DataReader(self._participant, self._topic(topic, msg_type), qos=dds_qos(qos or DEFAULT_QOS))
                condition = ReadCondition(reader, SampleState.NotRead | ViewState.Any | InstanceState.Any)
                self._waitset.attach(condition)
            except DDSException as exc:
                raise TransportError(f"{topic}: cannot create a DDS reader: {exc}") from None
            self._readers.append((reader, condition, sub))
        return sub

    def _check_open(self) -> None:
        if self._closed:
            raise TransportError("the DDS transport is closed")

    # -- receiving ------------------------------------------------------------------------------------
    def _receive(self) -> None:
        """Wait for new samples on any reader and hand them to their subscriptions, until `close`."""
        while not self._closed:
            try:
                self._waitset.wait(duration(milliseconds=200))
            except DDSException:
                if self._closed:
                    return
                time.sleep(0.01)
                continue
            with self._lock:
                readers = list(self._readers)
            for reader, condition, sub in readers:
                if self._closed:
                    return
                try:
                    samples = reader.take(N=_TAKE_BATCH, condition=condition)
                except DDSException:
                    continue
                now = time.monotonic()
                for sample in samples:
                    if isinstance(sample, sub.msg_type):
                        sub.deliver(sample, now)

    def close(self) -> None:
        """Stop the receive thread and delete the participant (and with it every entity)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        self._wake.set(True)
        if self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
        with contextlib.suppress(Exception):
            self._waitset.detach(self._wake)
            for _reader, condition, _sub in self._readers:
                self._waitset.detach(condition)
        self._readers.clear()
        self._writers.clear()
        self._topics.clear()
        with contextlib.suppress(Exception):
            del self._waitset, self._wake
            del self._participant

    def __enter__(self) -> DdsTransport:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

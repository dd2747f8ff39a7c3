"""The AGV's MQTT link (paho-mqtt 2.x, callback API version 2, MQTT 3.1.1).

Topics are `<interfaceName>/v<major>/<manufacturer>/<serialNumber>/<topic>` (section 6.3). QoS and retain
flags as section 6.2 and 6.14-6.15 say:

| topic | direction | QoS | retained |
| --- | --- | --- | --- |
| `order`, `instantActions` (3.0: and `zoneSet`, `responses`) | subscribed | 0 | - |
| `state`, `visualization` | published | 0 | no |
| `factsheet` | published | 0 | yes |
| `connection` | published, and the last will | 1 | yes |

On every (re)connection the last will is `CONNECTIONBROKEN` (3.0: `CONNECTION_BROKEN`; retained, QoS 1);
once connected the link subscribes, publishes `ONLINE`, the factsheet, and calls `on_connected` (the AGV
republishes its state).
A clean `close()` publishes `OFFLINE` and disconnects (no will). Lost connections are retried by paho's
network thread with exponential backoff (`reconnect_min_s` doubling to `reconnect_max_s`). While
disconnected nothing is queued: `send` drops the message (QoS 0 state is current only when fresh) and
no headerId is used up, so the master sees consecutive ids of the messages that were sent.

Public API: `AgvLink`, `topic(prefix, name)`.
"""

from __future__ import annotations

import json
import ssl
import threading
from collections.abc import Callable
from typing import Any

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion

from palletpilot.executor.apps.vda5050.config import AgvConfig
from palletpilot.executor.apps.vda5050.models import ConnectionState
from palletpilot.executor.apps.vda5050.state import Messages

QOS = {"state": 0, "visualization": 0, "factsheet": 0, "connection": 1, "order": 0, "instantActions": 0}
SUBSCRIBED = ("order", "instantActions")
SUBSCRIBED_V3 = (*SUBSCRIBED, "zoneSet", "responses")
"""A 3.0 AGV also takes zone sets and the master's responses (QoS 0)."""
RETAIN = {"state": False, "visualization": False, "factsheet": True, "connection": True}


def topic(prefix: str, name: str) -> str:
    """The full topic of `name` under an AGV's prefix."""
    return f"{prefix}/{name}"


class AgvLink:
    """One AGV's connection to the broker: subscriptions, publications, last will, reconnects."""

    def __init__(
        self,
        config: AgvConfig,
        messages: Messages,
        on_message: Callable[[str, bytes], None],
        on_connected: Callable[[], None] = lambda: None,
        log: Callable[[str], None] = lambda line: None,
        software_version: str = "",
    ) -> None:
        self.config = config
        self.messages = messages
        self.prefix = config.topic_prefix
        self.on_message = on_message
        self.on_connected = on_connected
        self.log = log
        self.software_version = software_version
        self.connected = threading.Event()
        self.connections = 0
        self._send_lock = threading.Lock()
        broker = config.broker
        client = mqtt.Client(
            CallbackAPIVersion.VERSION2,
            client_id=config.client_id,
            protocol=mqtt.MQTTv311,
            clean_session=True,
        )
        if broker.username is not None:
            client.username_pw_set(broker.username, config.password())
        if broker.tls is not None:
            tls = broker.tls
            client.tls_set(
                ca_certs=str(config.path(tls.ca)) if tls.ca else None,
                certfile=str(config.path(tls.cert)) if tls.cert else None,
                keyfile=str(config.path(tls.key)) if tls.key else None,
                tls_version=ssl.PROTOCOL_TLS_CLIENT,
            )
        client.reconnect_delay_set(broker.reconnect_min_s, broker.reconnect_max_s)
        client.on_connect = self._on_connect
        client.on_disconnect = self._on_disconnect
        client.on_message = self._on_message
        client.on_connect_fail = self._on_connect_fail
        self.client = client
        self._set_will()

    # -- lifecycle ----------------------------------------------------------------------------------
    def start(self) -> None:
        """Connect in the background (paho's network thread retries until it gets through)."""
        broker = self.config.broker
        self.client.connect_async(broker.host, broker.port, keepalive=broker.keepalive_s)
        self.client.loop_start()

    def close(self, timeout_s: float = 3.0) -> None:
        """Publish OFFLINE (retained, QoS 1), disconnect cleanly and stop the network thread."""
        if self.connected.is_set():
            with self._send_lock:
                payload = json.dumps(self.messages.connection(ConnectionState.OFFLINE))
                info = self.client.publish(topic(self.prefix, "connection"), payload, qos=1, retain=True)
            try:
                info.wait_for_publish(timeout_s)
            except (RuntimeError, ValueError):
                pass
        self.client.disconnect()
        self.client.loop_stop()

    # -- sending --------------------------------------------------------------------------------------
    def send(self, name: str, build: Callable[[], dict[str, Any]]) -> dict[str, Any] | None:
        """Build and publish one message on topic `name` while connected (QoS and retain per topic); the
        message, or None when offline (nothing is built, no headerId used)."""
        with self._send_lock:
            if not self.connected.is_set():
                return None
            message = build()
            info = self.client.publish(
                topic(self.prefix, name), json.dumps(message), qos=QOS[name], retain=RETAIN.get(name, False)
            )
            return message if info.rc == mqtt.MQTT_ERR_SUCCESS else None

    # -- paho callbacks (network thread) ----------------------------------------------------------
    def _set_will(self) -> None:
        will = self.messages.connection(ConnectionState.CONNECTIONBROKEN)
        self.client.will_set(topic(self.prefix, "connection"), json.dumps(will), qos=1, retain=True)

    def _on_connect(self, client: mqtt.Client, userdata: Any, flags: Any, reason: Any, properties: Any) -> None:
        if getattr(reason, "is_failure", False):
            self.log(f"agv: broker refused the connection: {reason}")
            return
        names = SUBSCRIBED_V3 if self.config.protocol_version.startswith("3.") else SUBSCRIBED
        client.subscribe([(topic(self.prefix, name), 0) for name in names])
        self.connections += 1
        self.connected.set()
        self.log(f"agv: connected to {self.config.broker.host}:{self.config.broker.port} as {self.config.client_id}")
        self.send("connection", lambda: self.messages.connection(ConnectionState.ONLINE))
        self.send("factsheet", lambda: self.messages.factsheet(self.software_version))
        self.on_connected()

    def _on_disconnect(self, client: mqtt.Client, userdata: Any, flags: Any, reason: Any, properties: Any) -> None:
        was = self.connected.is_set()
        self.connected.clear()
        if was:
            self.log(f"agv: disconnected from the broker ({reason}); reconnecting with backoff")
        self._set_will()  # the next connection's will, with a fresh header

    def _on_connect_fail(self, client: mqtt.Client, userdata: Any) -> None:
        self.connected.clear()

    def _on_message(self, client: mqtt.Client, userdata: Any, message: mqtt.MQTTMessage) -> None:
        name = message.topic.rsplit("/", 1)[-1]
        try:
            self.on_message(name, bytes(message.payload))
        except Exception as exc:  # never kill the network thread
            self.log(f"agv: internal error handling a {name} message: {type(exc).__name__}: {exc}")

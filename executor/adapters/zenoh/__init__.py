"""Perception as a service over Eclipse Zenoh: `perception_server` (the service) and `perception_remote`
(the runner's client, a `PerceptionService`); the wire format is `perception.wire`."""

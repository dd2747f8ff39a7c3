"""The AGV's configuration file (`missions/agv.yaml`): broker, identity, protocol, map, vehicle, rates.

```yaml
broker:
  host: localhost            # the MQTT broker
  port: 1883
  client_id: palletpilot-0001   # optional (default: <manufacturer>-<serialNumber>)
  username: agv              # optional
  password_env: AGV_MQTT_PASSWORD   # optional: the environment variable holding the password (never the file)
  tls:                       # optional: TLS with these files (relative to this file); cert and key together
    ca: ca.pem
    cert: agv.pem
    key: agv.key
  keepalive_s: 15            # MQTT keep-alive: the broker's heartbeat (section 6.14: about 15 s)
  reconnect_min_s: 1         # reconnect backoff (s): from this, doubling up to reconnect_max_s
  reconnect_max_s: 30
interface_name: uagv         # topics: <interface_name>/v<major>/<manufacturer>/<serial_number>/<topic>
                             # (default: uagv on 2.x, vda5050 on 3.0.0: vda5050/v3/...)
manufacturer: palletpilot
serial_number: "0001"        # A-Z a-z 0-9 _ . : -
protocol_version: 2.1.0      # the version this AGV speaks: "2.1.0" (2.x masters are read) or "2.0.0", or
                             # "3.0.0" (3.0 only: its topics, fields, zones; the `v3` version layer)
map: warehouse.yaml          # the roadmap (relative to this file)
map_id: warehouse            # optional: the mapId of that map (default: the map file's name without suffix)
vehicle: forklift.yaml       # optional: the vehicle file (default: the map's `vehicle`)
state_interval_s: 30         # a state at least this often (s, at most 30), and on every event
visualization_hz: 2          # visualization messages per second (0: none)
max_load_kg: 1500            # the factsheet's maxLoadMass
```

`load_config(path)` checks everything at once: the schema (one line per problem naming the file and the
field), the map and vehicle files, the TLS files, the password's environment variable, and topic levels
(no `/`, `#`, `+` or `$`). Problems raise `AgvConfigError` (the CLI prints the lines and exits 2).

Public API: `AgvConfig`, `BrokerConfig`, `TlsConfig`, `AgvConfigError`, `load_config`, `Loaded`.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from pydantic import Field, model_validator

from palletpilot.control.vehicle import VehicleParams, load_vehicle
from palletpilot.geometry import PalletpilotError
from palletpilot.geometry.errors import collect, raise_problems
from palletpilot.geometry.fileio import FileModel, load_yaml_model
from palletpilot.roadmap import Roadmap, load_map, map_vehicle_file


class AgvConfigError(PalletpilotError):
    """A configuration file that cannot be used; one line per problem."""


_SERIAL = r"^[A-Za-z0-9_.:\-]+$"
_LEVEL = r"^[^/#+$\s]+$"


class TlsConfig(FileModel):
    """TLS to the broker: the CA to trust, and optionally a client certificate and key (PEM files)."""

    ca: str | None = None
    cert: str | None = None
    key: str | None = None

    @model_validator(mode="after")
    def _pair(self) -> TlsConfig:
        if (self.cert is None) != (self.key is None):
            raise ValueError("give cert and key together")
        return self


class BrokerConfig(FileModel):
    """Where the MQTT broker is and how to log in."""

    host: str = Field("localhost", min_length=1, max_length=253)
    port: int = Field(1883, ge=1, le=65535)
    client_id: str | None = Field(None, min_length=1, max_length=128)
    username: str | None = Field(None, min_length=1, max_length=256)
    password_env: str | None = Field(None, pattern=r"^[A-Za-z_][A-Za-z0-9_]*$")
    tls: TlsConfig | None = None
    keepalive_s: int = Field(15, ge=2, le=600)
    reconnect_min_s: int = Field(1, ge=1, le=60)
    reconnect_max_s: int = Field(30, ge=1, le=600)

    @model_validator(mode="after")
    def _backoff(self) -> BrokerConfig:
        if self.reconnect_max_s < self.reconnect_min_s:
            raise ValueError("reconnect_max_s must be at least reconnect_min_s")
        if self.password_env is not None and self.username is None:
            raise ValueError("password_env needs a username")
        return self


class AgvConfig(FileModel):
    """The `agv.yaml` file (see the module docstring)."""

    broker: BrokerConfig = BrokerConfig()
    interface_name: str | None = Field(None, min_length=1, max_length=64, pattern=_LEVEL)
    manufacturer: str = Field(min_length=1, max_length=64, pattern=_LEVEL)
    serial_number: str = Field(min_length=1, max_length=64, pattern=_SERIAL)
    protocol_version: Literal["2.1.0", "2.0.0", "3.0.0"] = "2.1.0"
    map: str = Field(min_length=1, max_length=4096)
    map_id: str | None = Field(None, min_length=1, max_length=128)
    vehicle: str | None = Field(None, min_length=1, max_length=4096)
    state_interval_s: float = Field(30.0, gt=0.0, le=30.0)
    visualization_hz: float = Field(2.0, ge=0.0, le=50.0)
    max_load_kg: float = Field(1500.0, ge=0.0, le=100_000.0)
    folder: Path = Field(Path("."), exclude=True)

    def path(self, name: str) -> Path:
        """A file named in the config, relative to the config's folder."""
        return self.folder / name

    @property
    def client_id(self) -> str:
        """The MQTT client id (default `<manufacturer>-<serialNumber>`)."""
        return self.broker.client_id or f"{self.manufacturer}-{self.serial_number}"

    @property
    def topic_prefix(self) -> str:
        """`<interfaceName>/v<major>/<manufacturer>/<serialNumber>` (section 6.3)."""
        major = self.protocol_version.split(".")[0]
        interface = self.interface_name or ("vda5050" if major == "3" else "uagv")
        return f"{interface}/v{major}/{self.manufacturer}/{self.serial_number}"

    @property
    def map_name(self) -> str:
        """The mapId: `map_id`, else the map file's name without its suffix."""
        return self.map_id or Path(self.map).stem

    def password(self) -> str | None:
        """The broker password from the environment variable `broker.password_env` (None without one)."""
        name = self.broker.password_env
        return None if name is None else os.environ.get(name)


@dataclass(frozen=True)
class Loaded:
    """A checked configuration with its roadmap and vehicle."""

    config: AgvConfig
    roadmap: Roadmap
    vehicle: VehicleParams
    map_path: Path


def load_config(path: str | Path) -> Loaded:
    """Read and check `agv.yaml` and the files it names; `AgvConfigError` lists every problem."""
    config = load_yaml_model(path, AgvConfig, AgvConfigError)
    config.folder = Path(path).parent
    where = str(path)
    problems: list[str] = []
    map_path = config.path(config.map)
    roadmap = collect(problems, lambda: load_map(map_path))
    vehicle_file = config.path(config.vehicle) if config.vehicle else map_vehicle_file(map_path)
    vehicle: VehicleParams | None = None
    if vehicle_file is not None:
        vehicle = collect(problems, lambda: load_vehicle(vehicle_file))
    elif roadmap is not None:
        problems.append(f"{where}: vehicle: the map names no vehicle file; give one here")
    tls = config.broker.tls
    if tls is not None:
        for name in ("ca", "cert", "key"):
            value = getattr(tls, name)
            if value is not None and not config.path(value).is_file():
                problems.append(f"{where}: broker.tls.{name}: {config.path(value)}: no such file")
    env = config.broker.password_env
    if env is not None and env not in os.environ:
        problems.append(f"{where}: broker.password_env: the environment variable {env} is not set")
    if not re.fullmatch(r"[A-Za-z0-9_.:\-]+", config.map_name):
        problems.append(f"{where}: map_id: '{config.map_name}' must use only A-Z a-z 0-9 _ . : - (give map_id)")
    raise_problems(problems, AgvConfigError)
    assert roadmap is not None and vehicle is not None
    return Loaded(config, roadmap, vehicle, map_path)

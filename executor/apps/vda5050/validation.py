"""JSON schema validation of VDA 5050 2.1.0 and 3.0.0 messages, headers and timestamps.

The schemas are the official 2.1.0 files vendored in `schemas/` (MIT licence, `schemas/LICENSE.txt`),
with the three corrections of the specification's errata applied in memory (`schemas/README.md`), and the
official 3.0.0 files in `schemas/3.0.0/` with their trailing commas removed in memory
(`schemas/3.0.0/README.md`). A 2.x version (2.0.0 masters are read with the 2.1.0 schemas) or 3.0.0 picks
the set.
`format: date-time` is checked (RFC 3339) by a format checker of our own, so no optional `jsonschema`
extra is needed.

Public API:
- `TOPICS`: the six topics with a 2.1.0 schema, `TOPICS_V3` the eight of 3.0.0; `load_schema(topic, version=)`
  (errata applied), `validator(topic, version=)`, `schema_set(version)` ("2.1.0" or "3.0.0");
- `problems(topic, message, version=)`: one line per schema violation (`nodes[0].sequenceId: -1 is less than ...`),
  empty when the message is valid; `parse_message(payload)`: strict JSON (no NaN) of an object, or why not;
- `format_timestamp(ms)`, `Stamper` (strictly increasing UTC timestamps with milliseconds and `Z`),
  `STRICT_TIMESTAMP` (the AGV's own format), `is_rfc3339(text)`;
- `Headers`: the protocol header of each outgoing message, with a headerId per topic (+1 per message).
"""

from __future__ import annotations

import copy
import json
import re
import threading
from collections.abc import Callable
from datetime import datetime, timezone
from functools import cache
from typing import Any

from jsonschema import Draft202012Validator, FormatChecker  # type: ignore[import-untyped]

from palletpilot.geometry.fileio import bundled_path

TOPICS = ("order", "instantActions", "state", "visualization", "connection", "factsheet")
"""Topics with a JSON schema (`schemas/<topic>.schema`)."""
TOPICS_V3 = (*TOPICS, "zoneSet", "responses")
"""Topics with a 3.0.0 JSON schema (`schemas/3.0.0/<topic>.schema`)."""
V2, V3 = "2.1.0", "3.0.0"
"""The schema sets."""
TRAILING_COMMAS_V3 = {"factsheet": 4, "order": 1, "visualization": 2}
"""ERRATA.md of 3.0.0: the trailing commas of the published files (none in the others)."""
_TRAILING_COMMA = re.compile(r",(\s*[}\]])")

STRICT_TIMESTAMP = re.compile(r"\d{4}-\d{2}-\d{2}T\d{2}:\d{2}:\d{2}\.\d{3}Z")
"""The AGV's own timestamps: ISO 8601 in UTC with milliseconds and `Z` (`2017-04-15T11:40:03.120Z`)."""
_RFC3339 = re.compile(
    r"(\d{4})-(\d{2})-(\d{2})[Tt ](\d{2}):(\d{2}):(\d{2})(\.\d+)?([Zz]|[+-](\d{2}):(\d{2}))",
)
UINT32 = 2**32


def is_rfc3339(text: object) -> bool:
    """True for an RFC 3339 date-time (`format: date-time`): date, time, optional fraction, Z or an offset."""
    if not isinstance(text, str):
        return True  # formats constrain strings only; the schema's `type` catches the rest
    m = _RFC3339.fullmatch(text)
    if m is None:
        return False
    year, month, day, hour, minute, second = (int(g) for g in m.groups()[:6])
    try:
        datetime(year, month, day)
    except ValueError:
        return False
    if hour > 23 or minute > 59 or second > 60:  # 60: a leap second
        return False
    if m.group(9) is not None and (int(m.group(9)) > 23 or int(m.group(10)) > 59):
        return False
    return True


_FORMATS = FormatChecker(formats=())
_FORMATS.checks("date-time")(is_rfc3339)


def _apply_errata(topic: str, schema: dict[str, Any]) -> dict[str, Any]:
    """The corrections of ERRATA.md (VDA5050 issue #354, PR #360) on a loaded 2.1.0 schema."""
    schema = copy.deepcopy(schema)
    if topic == "factsheet":
        actions = schema["properties"]["protocolFeatures"]["properties"]["agvActions"]["items"]["properties"]
        blocking = actions["blockingTypes"]
        enum = blocking.pop("enum", ["NONE", "SOFT", "HARD"])
        blocking["items"] = {"type": "string", "enum": enum}
        envelope = schema["properties"]["agvGeometry"]["properties"]["envelopes3d"]["items"]["properties"]
        envelope["description"]["type"] = "string"
    elif topic == "state":
        status = schema["properties"]["actionStates"]["items"]["properties"]["actionStatus"]
        if "PAUSED" not in status["enum"]:
            status["enum"] = [*status["enum"][:3], "PAUSED", *status["enum"][3:]]
    return schema


def schema_set(version: str) -> str:
    """The schema set of a protocol version: `V3` for 3.x, else `V2` (2.0 and 2.1 masters alike)."""
    return V3 if str(version).split(".")[0] == "3" else V2


@cache
def _schema_text(topic: str, version: str = V2) -> str:
    topics, folder = (TOPICS_V3, ("3.0.0",)) if schema_set(version) == V3 else (TOPICS, ())
    if topic not in topics:
        raise KeyError(f"no VDA 5050 {schema_set(version)} schema for topic '{topic}' (one of {', '.join(topics)})")
    path = bundled_path("executor", "apps", "vda5050", "schemas", *folder, f"{topic}.schema")
    return path.read_text(encoding="utf-8")


def _repair_v3(topic: str, text: str) -> str:
    """ERRATA.md of 3.0.0: remove the trailing commas, exactly as many as the published file has."""
    fixed, count = _TRAILING_COMMA.subn(r"\1", text)
    expected = TRAILING_COMMAS_V3.get(topic, 0)
    if count != expected:
        raise ValueError(f"3.0.0 {topic}.schema: {count} trailing commas, the published file has {expected}")
    return fixed


def load_schema(topic: str, errata: bool = True, version: str = V2) -> dict[str, Any]:
    """The schema of a topic in the set of `version`, with the errata applied unless `errata=False` (the
    file as published: a 3.0.0 file with trailing commas then raises `json.JSONDecodeError`)."""
    text = _schema_text(topic, schema_set(version))
    if schema_set(version) == V3:
        return json.loads(_repair_v3(topic, text) if errata else text)
    schema = json.loads(text)
    return _apply_errata(topic, schema) if errata else schema


@cache
def validator(topic: str, version: str = V2) -> Draft202012Validator:
    """A cached validator of a topic's schema in the set of `version` (errata applied, date-time checked)."""
    schema = load_schema(topic, version=schema_set(version))
    Draft202012Validator.check_schema(schema)
    return Draft202012Validator(schema, format_checker=_FORMATS)


def _path(parts: Any) -> str:
    out = ""
    for part in parts:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or "message"


def problems(topic: str, message: object, version: str = V2) -> list[str]:
    """Every violation of the topic's schema (the set of `version`), one line each (`field.path: what`);
    empty when valid."""
    check = validator(topic, schema_set(version))
    errors = sorted(check.iter_errors(message), key=lambda e: [str(p) for p in e.absolute_path])
    return [f"{_path(e.absolute_path)}: {e.message}" for e in errors]


def _reject_constant(name: str) -> float:
    raise ValueError(f"{name} is not a number in JSON")


def parse_message(payload: bytes) -> tuple[dict[str, Any] | None, str | None]:
    """Strict JSON of a message (UTF-8, no NaN or Infinity, an object): `(message, None)` or `(None, why)`."""
    try:
        doc = json.loads(payload.decode("utf-8"), parse_constant=_reject_constant)
    except UnicodeDecodeError:
        return None, "the payload is not UTF-8"
    except (ValueError, RecursionError) as exc:
        return None, f"not valid JSON: {exc}"
    if not isinstance(doc, dict):
        return None, "not a JSON object"
    return doc, None


def format_timestamp(ms: int) -> str:
    """Milliseconds since the epoch as `YYYY-MM-DDTHH:MM:SS.mmmZ` (UTC)."""
    moment = datetime.fromtimestamp(ms // 1000, tz=timezone.utc)
    return moment.strftime("%Y-%m-%dT%H:%M:%S") + f".{ms % 1000:03d}Z"


class Stamper:
    """Timestamps of outgoing messages: UTC with milliseconds, strictly increasing even when the clock steps
    back (NTP) or two messages fall in one millisecond."""

    def __init__(self, now_ms: Callable[[], int] | None = None) -> None:
        self._now_ms = now_ms or (lambda: int(datetime.now(timezone.utc).timestamp() * 1000))
        self._last = 0
        self._lock = threading.Lock()

    def __call__(self) -> str:
        """The next timestamp."""
        with self._lock:
            self._last = max(self._now_ms(), self._last + 1)
            return format_timestamp(self._last)


class Headers:
    """The protocol header of outgoing messages: `headerId` counts per topic (+1 with each message, wrapping
    at 2^32 as a uint32), `timestamp` from a shared `Stamper`, `version`, `manufacturer`, `serialNumber`."""

    def __init__(self, version: str, manufacturer: str, serial_number: str, stamper: Stamper | None = None) -> None:
        self.version = version
        self.manufacturer = manufacturer
        self.serial_number = serial_number
        self.stamp = stamper or Stamper()
        self._next: dict[str, int] = {}
        self._lock = threading.Lock()
        self.on_header: Callable[[str, int], None] | None = None
        """Called with (topic, headerId) after every header taken, outside the lock (the AGV's journal
        reserves headerIds ahead with it)."""

    def header(self, topic: str) -> dict[str, Any]:
        """The header of the next message on `topic` (takes its headerId)."""
        with self._lock:
            header_id = self._next.get(topic, 0)
            self._next[topic] = (header_id + 1) % UINT32
            out = {
                "headerId": header_id,
                "timestamp": self.stamp(),
                "version": self.version,
                "manufacturer": self.manufacturer,
                "serialNumber": self.serial_number,
            }
        if self.on_header is not None:
            self.on_header(topic, header_id)
        return out

    def counters(self) -> dict[str, int]:
        """The next headerId of every topic used so far."""
        with self._lock:
            return dict(self._next)

    def start_at(self, counters: dict[str, int]) -> None:
        """Continue every topic in `counters` at (at least) its headerId: after a restart, above every id sent."""
        with self._lock:
            for topic, next_id in counters.items():
                self._next[topic] = max(self._next.get(topic, 0), int(next_id) % UINT32)

"""VDA 5050 3.0 RELEASE zones: the truck's zone requests and the master's responses (sections 6.4.3, 6.9).

Before the truck's contour enters a RELEASE zone of the enabled zone set it needs the master's grant:
- a `zoneRequest` (requestType ACCESS, requestStatus REQUESTED) is stated as soon as the zone lies on the
  order's path ahead (the rest of the base), one per zone, each with a requestId of its own;
- the truck holds before the zone (its braking distance and a margin ahead, `v3.ZoneGuard`) until the
  request is GRANTED; QUEUED keeps it REQUESTED (the state's requestStatus has no QUEUED); REJECTED removes
  the request and the truck holds for good, with a CRITICAL `NODE_UNREACHABLE` naming the zone, until the
  order changes (no new request for that zone meanwhile); REVOKED before entering removes the request (a new
  one follows while the zone is still ahead);
- a `leaseExpiry` that passes makes a GRANTED request EXPIRED; EXPIRED or REVOKED after the truck entered
  follows the zone's `releaseLossBehavior`: STOP (the default) holds the truck where it is with a CRITICAL
  `RELEASE_LOST`; CONTINUE drives on, the request kept as it is until the truck has left the zone (EVACUATE is
  refused with the zone set, `zones.ZoneStore.add`: the truck has no evacuation behaviour);
- once the contour has left the zone (and it is not ahead any more) the request is removed.

Thread safety: responses come on the network thread, ticks on the executor thread, the state is built on the
publisher thread: everything under `lock`.

Public API: `RequestStatus`, `ZoneRequest`, `ReleaseGate`.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from datetime import datetime
from enum import Enum
from typing import Any

from palletpilot.executor.apps.vda5050.models import AgvError, ErrorLevel
from palletpilot.executor.apps.vda5050.zones import Zone


class RequestStatus(str, Enum):
    """`zoneRequests[].requestStatus`."""

    REQUESTED = "REQUESTED"
    GRANTED = "GRANTED"
    REVOKED = "REVOKED"
    EXPIRED = "EXPIRED"


@dataclass
class ZoneRequest:
    """One access request for a RELEASE zone."""

    request_id: str
    zone_id: str
    zone_set_id: str
    status: RequestStatus = RequestStatus.REQUESTED
    lease_expiry_s: float | None = None
    """UTC seconds since the epoch the grant lasts until (None: no lease)."""
    entered: bool = False

    def to_json(self) -> dict[str, Any]:
        """The state's `zoneRequest` object."""
        return {
            "requestId": self.request_id,
            "requestType": "ACCESS",
            "zoneId": self.zone_id,
            "zoneSetId": self.zone_set_id,
            "requestStatus": self.status.value,
        }


def _epoch_s(stamp: str) -> float | None:
    try:
        return datetime.fromisoformat(stamp.replace("Z", "+00:00").replace("z", "+00:00")).timestamp()
    except ValueError:
        return None


class ReleaseGate:
    """The RELEASE zones' requests of one AGV (see the module docstring)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.requests: dict[str, ZoneRequest] = {}
        self._next = 0
        self._rejected: set[str] = set()
        self._order_key: tuple[str, int] | None = None
        self._errors: dict[str, AgvError] = {}
        """Active errors by zoneId (NODE_UNREACHABLE, RELEASE_LOST)."""

    def respond(self, response: dict[str, Any]) -> bool:
        """A schema-valid `response` from the master; False when it answers no request of this truck."""
        with self.lock:
            request = self.requests.get(str(response["requestId"]))
            if request is None:
                return False
            grant = str(response["grantType"])
            if grant == "GRANTED":
                request.status = RequestStatus.GRANTED
                expiry = response.get("leaseExpiry")
                request.lease_expiry_s = _epoch_s(expiry) if isinstance(expiry, str) else None
            elif grant == "REJECTED":
                del self.requests[request.request_id]
                self._rejected.add(request.zone_id)
                what = f"the master rejected access to RELEASE zone '{request.zone_id}': the truck holds before it"
                refs = (("zoneId", request.zone_id), ("requestId", request.request_id))
                self._errors[request.zone_id] = AgvError("NODE_UNREACHABLE", ErrorLevel.CRITICAL, what, refs)
            elif grant == "REVOKED":
                if request.entered:
                    request.status = RequestStatus.REVOKED
                else:
                    del self.requests[request.request_id]
            return True

    def tick(
        self,
        order_key: tuple[str, int],
        ahead: dict[str, tuple[Zone, float]],
        inside: list[Zone],
        reach: float,
        zone_set_id: str,
        now_s: float,
    ) -> bool:
        """One control tick: `ahead` the RELEASE zones on the path ahead (by zoneId: the zone and the distance
        to it, m), `inside` those the contour is in now, `reach` the distance the truck needs to stop (m).
        Returns True while the truck must hold."""
        with self.lock:
            if order_key != self._order_key:
                self._order_key, self._rejected = order_key, set()
                self._errors = {k: e for k, e in self._errors.items() if e.error_type != "NODE_UNREACHABLE"}
            by_zone = {r.zone_id: r for r in self.requests.values()}
            for r in by_zone.values():
                if r.status is RequestStatus.GRANTED and r.lease_expiry_s is not None and now_s > r.lease_expiry_s:
                    r.status = RequestStatus.EXPIRED
            inside_ids = {z.zone_id for z in inside}
            for zone in [*inside, *(z for z, _ in ahead.values())]:
                if zone.zone_id not in by_zone and zone.zone_id not in self._rejected:
                    self._next += 1
                    by_zone[zone.zone_id] = ZoneRequest(f"zone-{self._next}", zone.zone_id, zone_set_id)
            for zone_id, r in list(by_zone.items()):
                if zone_id in inside_ids and r.status is RequestStatus.GRANTED:
                    r.entered = True
                if zone_id not in inside_ids and zone_id not in ahead:
                    del by_zone[zone_id]  # left the zone, or no longer on the way
                    self._errors.pop(zone_id, None)
            self.requests = {r.request_id: r for r in by_zone.values()}
            hold = False
            for zone in inside:
                got = by_zone.get(zone.zone_id)
                lost = got is None or got.status is not RequestStatus.GRANTED
                if (
                    not lost
                    and zone.zone_id in self._errors
                    and self._errors[zone.zone_id].error_type == "RELEASE_LOST"
                ):
                    del self._errors[zone.zone_id]  # granted again
                if lost and (got is None or not got.entered or (zone.release_loss or "STOP") == "STOP"):
                    hold = True
                    if got is not None and got.entered and zone.zone_id not in self._errors:
                        what = f"the release of RELEASE zone '{zone.zone_id}' was {got.status.value}: the truck stopped"
                        refs = (("zoneId", zone.zone_id), ("requestId", got.request_id))
                        self._errors[zone.zone_id] = AgvError("RELEASE_LOST", ErrorLevel.CRITICAL, what, refs)
            for zone_id, (_zone, distance) in ahead.items():
                ahead_request = by_zone.get(zone_id)
                if (
                    zone_id not in inside_ids
                    and distance <= reach
                    and (ahead_request is None or ahead_request.status is not RequestStatus.GRANTED)
                ):
                    hold = True
            return hold

    def to_json(self) -> list[dict[str, Any]]:
        """The state's `zoneRequests`."""
        with self.lock:
            return [r.to_json() for r in self.requests.values()]

    def errors(self) -> list[AgvError]:
        """The active RELEASE errors (NODE_UNREACHABLE after a rejection, RELEASE_LOST)."""
        with self.lock:
            return list(self._errors.values())

"""Exact, JSON-able snapshots of a running `Simulator`, for crash-safe resume.

`Simulator.snapshot()` and `Simulator.restore(doc)` call `take_snapshot` and `restore_snapshot` here.
A snapshot is plain JSON (dict, list, str, int, float, bool, None) and restores bit for bit: floats
go through Python's `json` exactly (shortest round-trip repr), rotations as their stored quaternion
(never re-normalized), numpy generators as `bit_generator.state` (large ints are fine in `json`).

Layout (version `SNAPSHOT_VERSION`; poses in the world frame, SI units):

```
format, version                          "palletpilot-sim-snapshot", 1
seed, map, pallet_nodes                  the run's identity; pallet_nodes must match the scenario
time                                     simulated time (s)
battery_level                            state of charge 0..1 (null without a battery model)
forklift   pose {x, y, yaw}              T_world_forklift (m, rad)
           v, steering, fork_height      speed (m/s), steering angle (rad), fork height (m)
           speed_cmd, steering_cmd, fork_height_cmd, odometer (m)
pallets    [{node, id, loaded, carried, T_world_pallet, T_forks_pallet, lifted, initial}]
           SE3 as {xyz: [m], quat_xyzw: [...]}; T_forks_pallet (relative to the fork bottoms) or null
collisions                               the contacts recorded so far (t_s, kind, id, part, message)
rng        {sim, forklift, localization, camera}: numpy bit-generator states
T_forklift_camera_true                   the perturbed camera mount (drawn at construction)
```

The evolving parts are `time`, `forklift`, `pallets`, `collisions` and `rng`. The seed and the camera
mount are fixed once the simulator is built: restoring onto a `Simulator(scenario, seed)` built like
the snapshot's only needs the evolving parts, but `restore_snapshot` sets the seed and mount too, so
the restored simulator is the snapshot's whatever seed it was built with.

Public API: `SNAPSHOT_FORMAT`, `SNAPSHOT_VERSION`, `take_snapshot(sim)`, `restore_snapshot(sim, doc)`,
and the codecs `se2_to_doc` / `se2_from_doc`, `se3_to_doc` / `se3_from_doc`, `rng_to_doc` /
`rng_state_from_doc`. Bad snapshots and fields raise `SimError` with one line.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.spatial.transform import Rotation

from palletpilot.geometry import SE2, SE3
from palletpilot.sim.scenario import SimError

if TYPE_CHECKING:
    from palletpilot.sim.simulator import Simulator

SNAPSHOT_FORMAT = "palletpilot-sim-snapshot"
"""The `format` tag of every simulator snapshot."""

SNAPSHOT_VERSION = 1
"""The snapshot layout this module writes and reads; any other version is refused."""

_WHERE = "simulator snapshot"


class _FieldError(SimError):
    """A malformed field (a `SimError`); `restore_snapshot` prefixes it with where it was read."""


# -- codecs ---------------------------------------------------------------------------------------
def _float(value: object, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise _FieldError(f"{what} must be a finite number, got {value!r}")
    return float(value)


def _field(doc: object, key: str, what: str) -> Any:
    if not isinstance(doc, dict):
        raise _FieldError(f"{what} must be an object, got {type(doc).__name__}")
    if key not in doc:
        raise _FieldError(f"{what} has no '{key}'")
    return doc[key]


def se2_to_doc(pose: SE2) -> dict[str, float]:
    """A planar pose as `{x, y, yaw}` (m, rad)."""
    return {"x": pose.x, "y": pose.y, "yaw": pose.yaw}


def se2_from_doc(doc: object, what: str = "pose") -> SE2:
    """The exact `SE2` of `se2_to_doc`: the stored yaw is kept bit for bit (it was wrapped already)."""
    x, y = _float(_field(doc, "x", what), f"{what}.x"), _float(_field(doc, "y", what), f"{what}.y")
    yaw = _float(_field(doc, "yaw", what), f"{what}.yaw")
    if not -math.pi <= yaw <= math.pi:
        raise _FieldError(f"{what}.yaw must be within [-pi, pi], got {yaw!r}")
    pose = SE2(x, y, yaw)
    if pose.yaw != yaw:  # re-wrapping may move the last bit; the stored value is the wrapped one
        object.__setattr__(pose, "yaw", yaw)
    return pose


def se3_to_doc(T: SE3) -> dict[str, list[float]]:
    """A spatial transform as `{xyz: [m], quat_xyzw: [...]}`: its translation and stored quaternion."""
    return {"xyz": [float(v) for v in T.t], "quat_xyzw": [float(v) for v in T.rotation.as_quat()]}


def se3_from_doc(doc: object, what: str = "transform") -> SE3:
    """The exact `SE3` of `se3_to_doc` (the quaternion is used as stored, not re-normalized)."""
    xyz, quat = _field(doc, "xyz", what), _field(doc, "quat_xyzw", what)
    if not isinstance(xyz, list) or len(xyz) != 3 or not isinstance(quat, list) or len(quat) != 4:
        raise _FieldError(f"{what} needs xyz (3 numbers) and quat_xyzw (4 numbers)")
    t = [_float(v, f"{what}.xyz") for v in xyz]
    q = np.array([_float(v, f"{what}.quat_xyzw") for v in quat])
    if abs(float(np.linalg.norm(q)) - 1.0) > 1e-9:
        raise _FieldError(f"{what}.quat_xyzw is not a unit quaternion")
    return SE3(Rotation(q, normalize=False), t)


def rng_to_doc(rng: np.random.Generator) -> dict[str, Any]:
    """The generator's `bit_generator.state` (JSON-able; its large ints survive Python's `json`)."""
    return dict(rng.bit_generator.state)


def rng_state_from_doc(rng: np.random.Generator, doc: object, what: str = "rng") -> dict[str, Any]:
    """Check that `doc` is a state `rng` can take (same bit generator); return it without setting it."""
    name = type(rng.bit_generator).__name__
    got = _field(doc, "bit_generator", what)
    assert isinstance(doc, dict)  # `_field` checked it
    if got != name:
        raise _FieldError(f"{what} is a {got!r} state, the simulator uses {name}")
    trial = np.random.Generator(type(rng.bit_generator)())
    try:
        trial.bit_generator.state = doc
    except (TypeError, ValueError, KeyError) as exc:
        raise _FieldError(f"{what} is not a valid {name} state ({exc})") from None
    return dict(trial.bit_generator.state)


# -- the simulator ----------------------------------------------------------------------------------
def _generators(sim: Simulator) -> dict[str, np.random.Generator]:
    """Every random generator of the simulator, by snapshot key."""
    return {"sim": sim.rng, "forklift": sim.forklift.rng, "localization": sim._loc_rng, "camera": sim._cam_rng}


def take_snapshot(sim: Simulator) -> dict[str, Any]:
    """Everything that evolves while `sim` runs, plus its seed and camera mount, as plain JSON."""
    fl, st = sim.forklift, sim.forklift.state
    return {
        "format": SNAPSHOT_FORMAT,
        "version": SNAPSHOT_VERSION,
        "seed": int(sim.seed),
        "map": str(sim.scenario.map),
        "pallet_nodes": [p.node for p in sim.pallets],
        "time": float(sim.time),
        "walk_t": [float(t) for t in sim.walk_t],
        "battery_level": sim.battery_level,
        "forklift": {
            "pose": se2_to_doc(st.pose),
            "v": float(st.v),
            "steering": float(st.steering),
            "fork_height": float(st.fork_height),
            "speed_cmd": float(fl.speed_cmd),
            "steering_cmd": float(fl.steering_cmd),
            "fork_height_cmd": float(fl.fork_height_cmd),
            "odometer": float(fl.odometer),
            "emergency": bool(fl.emergency),
        },
        "pallets": [
            {
                "node": p.node,
                "id": p.id,
                "loaded": bool(p.loaded),
                "carried": bool(p.carried),
                "T_world_pallet": se3_to_doc(p.T_world_pallet),
                "T_forks_pallet": None if p.T_forks_pallet is None else se3_to_doc(p.T_forks_pallet),
                "lifted": bool(p.lifted),
                "initial": se3_to_doc(p.initial if p.initial is not None else p.T_world_pallet),
            }
            for p in sim.pallets
        ],
        "collisions": [dict(c) for c in sim.collisions],
        "safety": {
            "field_set": sim.scanner.field_set,
            "direction": sim.scanner.direction,
            "held": sim.scanner.held,
            "clear_s": float(sim.scanner.clear_s),
        },
        "rng": {key: rng_to_doc(g) for key, g in _generators(sim).items()},
        "T_forklift_camera_true": se3_to_doc(sim.T_forklift_camera_true),
    }


def restore_snapshot(sim: Simulator, doc: object) -> None:
    """Put `sim` in the state of `doc` (from `take_snapshot`), all or nothing.

    Refused with one-line `SimError`: another format or version, pallets other than the scenario's
    (count or nodes), malformed fields. Caches that depend on the pallets (renderer, beam scene) are
    dropped.
    """
    if not isinstance(doc, dict) or doc.get("format") != SNAPSHOT_FORMAT:
        raise SimError(f"{_WHERE}: not a palletpilot simulator snapshot (format must be '{SNAPSHOT_FORMAT}')")
    if doc.get("version") != SNAPSHOT_VERSION:
        raise SimError(
            f"{_WHERE}: format version {doc.get('version')!r}, this simulator restores version {SNAPSHOT_VERSION}"
        )
    ours = [p.node for p in sim.pallets]
    theirs = doc.get("pallet_nodes")
    if theirs != ours:
        raise SimError(f"{_WHERE}: pallets {theirs!r} do not match the scenario's {ours!r}")
    try:
        state = _parse(sim, doc)
    except _FieldError as exc:
        raise SimError(f"{_WHERE}: {exc}") from None
    _apply(sim, state)


def _parse(sim: Simulator, doc: dict[str, Any]) -> dict[str, Any]:
    """Validate and decode every field before anything is changed."""
    seed = doc.get("seed")
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise _FieldError(f"seed must be an integer, got {seed!r}")
    time = _float(_field(doc, "time", "snapshot"), "time")
    walk = doc.get("walk_t", [time] * len(sim.walk_t))
    if not isinstance(walk, list) or len(walk) != len(sim.walk_t):
        raise _FieldError(f"walk_t must be a list of {len(sim.walk_t)} numbers")
    walk_t = [_float(t, "walk_t") for t in walk]
    battery = _field(doc, "battery_level", "snapshot")
    if battery is not None and (not isinstance(battery, int | float) or not 0.0 <= battery <= 1.0):
        raise _FieldError("battery_level must be null or a number in 0..1")
    f = _field(doc, "forklift", "snapshot")
    forklift: dict[str, Any] = {"pose": se2_from_doc(_field(f, "pose", "forklift"), "forklift.pose")}
    for key in ("v", "steering", "fork_height", "speed_cmd", "steering_cmd", "fork_height_cmd", "odometer"):
        forklift[key] = _float(_field(f, key, "forklift"), f"forklift.{key}")
    emergency = _field(f, "emergency", "forklift")
    if not isinstance(emergency, bool):
        raise _FieldError("forklift.emergency must be true or false")
    forklift["emergency"] = emergency
    pallets = _field(doc, "pallets", "snapshot")
    if not isinstance(pallets, list) or len(pallets) != len(sim.pallets):
        raise _FieldError(f"pallets must be a list of {len(sim.pallets)}")
    decoded = []
    for k, (p, sim_p) in enumerate(zip(pallets, sim.pallets, strict=True)):
        what = f"pallets[{k}]"
        if _field(p, "node", what) != sim_p.node or _field(p, "id", what) != sim_p.id:
            raise _FieldError(f"{what} is {p['id']!r} at {p['node']!r}, the scenario's is {sim_p.id!r}")
        loaded, carried, lifted = (_field(p, key, what) for key in ("loaded", "carried", "lifted"))
        if not all(isinstance(v, bool) for v in (loaded, carried, lifted)):
            raise _FieldError(f"{what}: loaded, carried and lifted must be true or false")
        T_forks = _field(p, "T_forks_pallet", what)
        if carried != (T_forks is not None):
            raise _FieldError(f"{what}: a carried pallet needs T_forks_pallet, a resting one none")
        decoded.append(
            {
                "loaded": loaded,
                "carried": carried,
                "T_world_pallet": se3_from_doc(_field(p, "T_world_pallet", what), f"{what}.T_world_pallet"),
                "T_forks_pallet": None if T_forks is None else se3_from_doc(T_forks, f"{what}.T_forks_pallet"),
                "lifted": lifted,
                "initial": se3_from_doc(_field(p, "initial", what), f"{what}.initial"),
            }
        )
    collisions = _field(doc, "collisions", "snapshot")
    if not isinstance(collisions, list) or not all(isinstance(c, dict) and "message" in c for c in collisions):
        raise _FieldError("collisions must be a list of contact records (t_s, kind, id, part, message)")
    safety = doc.get("safety", {"field_set": "normal", "direction": "forward", "held": False, "clear_s": 0.0})
    if (
        not isinstance(safety, dict)
        or safety.get("field_set") not in ("normal", "narrow")
        or safety.get("direction") not in ("forward", "reverse")
        or not isinstance(safety.get("held"), bool)
    ):
        raise _FieldError("safety must hold field_set (normal|narrow), direction (forward|reverse), held, clear_s")
    safety = {**safety, "clear_s": _float(safety.get("clear_s"), "safety.clear_s")}
    rng_doc = _field(doc, "rng", "snapshot")
    rngs = {
        key: rng_state_from_doc(g, _field(rng_doc, key, "rng"), f"rng.{key}") for key, g in _generators(sim).items()
    }
    mount = se3_from_doc(_field(doc, "T_forklift_camera_true", "snapshot"), "T_forklift_camera_true")
    return {
        "seed": seed,
        "time": time,
        "walk_t": walk_t,
        "battery_level": None if battery is None else float(battery),
        "forklift": forklift,
        "pallets": decoded,
        "collisions": list(collisions),
        "safety": safety,
        "rng": rngs,
        "mount": mount,
    }


def _apply(sim: Simulator, state: dict[str, Any]) -> None:
    sim.seed = state["seed"]
    sim.time = state["time"]
    sim.walk_t = list(state["walk_t"])
    sim.battery_level = state["battery_level"]
    f, fl = state["forklift"], sim.forklift
    fl.state.pose, fl.state.v, fl.state.steering, fl.state.fork_height = (
        f["pose"],
        f["v"],
        f["steering"],
        f["fork_height"],
    )
    fl.speed_cmd, fl.steering_cmd, fl.fork_height_cmd, fl.odometer = (
        f["speed_cmd"],
        f["steering_cmd"],
        f["fork_height_cmd"],
        f["odometer"],
    )
    fl.emergency = f["emergency"]
    for p, d in zip(sim.pallets, state["pallets"], strict=True):
        p.loaded, p.carried = d["loaded"], d["carried"]
        p.T_world_pallet, p.T_forks_pallet = d["T_world_pallet"], d["T_forks_pallet"]
        p.lifted, p.initial = d["lifted"], d["initial"]
    sim.collisions = state["collisions"]
    sc = sim.scanner
    sc.field_set, sc.direction = state["safety"]["field_set"], state["safety"]["direction"]
    sc.held, sc.clear_s = state["safety"]["held"], state["safety"]["clear_s"]
    for key, g in _generators(sim).items():
        g.bit_generator.state = state["rng"][key]
    sim.T_forklift_camera_true = state["mount"]
    sim._static_changed()  # the render and beam scenes hold the resting pallets

"""Bad mission, scenario and vehicle files, through `run`, `sim render` and `map check --vehicle`.

Each case copies the example files into its folder and spoils one thing.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from badinputs import Case, Fixtures, dump, example, write

MISSION = "pickup_delivery.yaml"
SCENARIO = "scenario_demo.yaml"
RUN = ("run", "{case}/" + MISSION, "--quiet", "--report", "{case}/out")
RUN_SC = (*RUN, "--scenario", "{case}/" + SCENARIO)
RENDER = ("sim", "render", "{case}/" + SCENARIO, "--out", "{case}/f.npz")
VEHICLE = ("map", "check", "{case}/warehouse.yaml", "--vehicle", "{case}/forklift.yaml")

NAN, INF = math.nan, math.inf


def world(fx: Fixtures, folder: Path) -> None:
    """Writable copies of the example files."""
    for path in fx.ex.iterdir():
        if path.is_file():  # the example suite's folder is not needed here
            write(folder, path.name, path.read_bytes())


def spoil(name: str, change: Callable[[dict], Any]) -> Callable[[Fixtures, Path], None]:
    """A setup: the example world with `change(doc)` applied to the example file `name`."""

    def setup(fx: Fixtures, folder: Path) -> None:
        world(fx, folder)
        doc = example(fx, name)
        change(doc)
        write(folder, name, dump(doc))

    return setup


def raw(name: str, data: str | bytes) -> Callable[[Fixtures, Path], None]:
    """A setup: the example world with the file `name` replaced by `data`."""

    def setup(fx: Fixtures, folder: Path) -> None:
        world(fx, folder)
        write(folder, name, data)

    return setup


def task(**fields: Any) -> Callable[[dict], None]:
    return lambda d: d["tasks"].append(fields)


def first_task(**fields: Any) -> Callable[[dict], None]:
    return lambda d: d["tasks"][0].update(fields)


def pallet(i: int, **fields: Any) -> Callable[[dict], None]:
    return lambda d: d["pallets"][i].update(fields)


def clutter(**fields: Any) -> Callable[[dict], None]:
    return lambda d: d["clutter"].append(fields)


def camera(part: str, **fields: Any) -> Callable[[dict], None]:
    return lambda d: d["camera"].setdefault(part, {}).update(fields)


def top(**fields: Any) -> Callable[[dict], None]:
    return lambda d: d.update(fields)


def vehicle(path: str, value: Any) -> Callable[[dict], None]:
    def change(d: dict) -> None:
        *parents, key = path.split(".")
        for p in parents:
            d = d.setdefault(p, {})
        d[key] = value

    return change


def _fifty_unknown(d: dict) -> None:
    d["tasks"] = [{"type": "pickup", "node": f"nowhere_{i}"} for i in range(50)]


BOMB = 'a: &a ["x","x","x","x","x","x","x","x","x","x"]\n' + "".join(
    f"{chr(98 + i)}: &{chr(98 + i)} [{','.join([f'*{chr(97 + i)}'] * 10)}]\n" for i in range(9)
)

MISSIONS: list[Case] = [
    Case(
        "mission_wait_inf",
        RUN,
        2,
        "tasks[3].wait.seconds: Input should be a finite number",
        spoil(MISSION, task(type="wait", seconds=INF)),
    ),
    Case(
        "mission_wait_nan",
        RUN,
        2,
        "tasks[3].wait.seconds: Input should be a finite number",
        spoil(MISSION, task(type="wait", seconds=NAN)),
    ),
    Case(
        "mission_wait_1e12",
        RUN,
        2,
        "tasks[3].wait.seconds: Input should be less than or equal to 86400",
        spoil(MISSION, task(type="wait", seconds=1e12)),
    ),
    Case(
        "mission_wait_text",
        RUN,
        2,
        "tasks[3].wait.seconds: Input should be a valid number",
        spoil(MISSION, task(type="wait", seconds="ten")),
    ),
    Case(
        "mission_wait_nan_text",
        RUN,
        2,
        "tasks[3].wait.seconds: Input should be a finite number",
        spoil(MISSION, task(type="wait", seconds="nan")),
    ),
    Case(
        "mission_wait_zero",
        RUN,
        2,
        "tasks[3].wait.seconds: Input should be greater than 0",
        spoil(MISSION, task(type="wait", seconds=0)),
    ),
    Case(
        "mission_height_nan",
        RUN,
        2,
        "tasks[0].pickup.height: Input should be a finite number",
        spoil(MISSION, first_task(height=NAN)),
    ),
    Case(
        "mission_height_negative",
        RUN,
        2,
        "tasks[0].pickup.height: Input should be greater than or equal to 0",
        spoil(MISSION, first_task(height=-1.0)),
    ),
    Case("mission_height_above_mast", RUN, 2, "outside the mast's range", spoil(MISSION, first_task(height=5.0))),
    Case(
        "mission_unknown_node",
        RUN,
        2,
        "tasks[0] (pickup nowhere): unknown node 'nowhere'",
        spoil(MISSION, first_task(node="nowhere")),
    ),
    Case("mission_50_bad_tasks", RUN, 2, "tasks[49] (pickup nowhere_49): unknown node", spoil(MISSION, _fifty_unknown)),
    Case(
        "mission_wrong_node_type",
        RUN,
        2,
        "node 'charger' is a charging node, a pickup needs a pallet node",
        spoil(MISSION, first_task(node="charger")),
    ),
    Case(
        "mission_unknown_key",
        RUN,
        2,
        "tasks[0].pickup.speed: Extra inputs are not permitted",
        spoil(MISSION, first_task(speed=2)),
    ),
    Case(
        "mission_unknown_type",
        RUN,
        2,
        "tasks[3]: type 'fly' is unknown; known: pickup, ",
        spoil(MISSION, task(type="fly")),
    ),
    Case("mission_no_tasks", RUN, 2, "tasks: List should have at least 1 item", spoil(MISSION, top(tasks=[]))),
    Case("mission_no_map", RUN, 2, "map: Field required", spoil(MISSION, lambda d: d.pop("map"))),
    Case(
        "mission_missing_map_file",
        RUN,
        2,
        "map: 'nothere.yaml': no such file: ",
        spoil(MISSION, top(map="nothere.yaml")),
    ),
    Case("mission_map_is_folder", RUN, 2, "cannot read: Is a directory", spoil(MISSION, top(map="."))),
    Case(
        "mission_latin1",
        RUN,
        2,
        "not UTF-8 text",
        raw(MISSION, "name: caf\xe9\nmap: warehouse.yaml\n".encode("latin-1")),
    ),
    Case("mission_binary", RUN, 2, "not UTF-8 text", raw(MISSION, bytes(range(256)) * 4)),
    Case("mission_utf16", RUN, 2, "not UTF-8 text", raw(MISSION, "name: x\nmap: warehouse.yaml\n".encode("utf-16"))),
    Case("mission_empty_file", RUN, 2, "Input should be a valid dictionary", raw(MISSION, "")),
    Case("mission_a_list", RUN, 2, "Input should be a valid dictionary", raw(MISSION, "[1, 2, 3]\n")),
    Case("mission_is_folder", ("run", "{case}", "--quiet"), 2, "cannot read: Is a directory"),
    Case("mission_missing", ("run", "{case}/nothere.yaml", "--quiet"), 2, "cannot read: No such file"),
    Case(
        "mission_python_tag",
        RUN,
        2,
        "could not determine a constructor",
        raw(MISSION, '!!python/object/apply:os.system ["echo hacked"]\n'),
    ),
    Case("mission_anchor_bomb", RUN, 2, "too large", raw(MISSION, BOMB)),
    Case("mission_deep_nesting", RUN, 2, "nested", raw(MISSION, "[" * 5000 + "]" * 5000)),
    Case("mission_yaml_syntax", RUN, 2, "not valid YAML: line", raw(MISSION, "map: [warehouse.yaml\ntasks: {\n")),
    Case(
        "mission_delivery_first",
        RUN,
        2,
        "a delivery with empty forks",
        spoil(MISSION, lambda d: d["tasks"].insert(0, {"type": "delivery", "node": "drop"})),
    ),
    Case(
        "mission_charge_both_ends",
        RUN,
        2,
        "give either minutes or until_level",
        spoil(MISSION, task(type="charge", node="charger", minutes=1, until_level=0.9)),
    ),
    Case(
        "mission_charge_inf",
        RUN,
        2,
        "tasks[3].charge.minutes: Input should be a finite number",
        spoil(MISSION, task(type="charge", node="charger", minutes=INF)),
    ),
    Case(
        "mission_charge_level_2",
        RUN,
        2,
        "until_level: Input should be less than or equal to 1",
        spoil(MISSION, task(type="charge", node="charger", until_level=2)),
    ),
    Case(
        "mission_blocked_wait_nan",
        RUN,
        2,
        "blocked_wait_s: Input should be a finite number",
        spoil(MISSION, top(blocked_wait_s=NAN)),
    ),
    Case(
        "mission_blocked_wait_huge",
        RUN,
        2,
        "blocked_wait_s: Input should be less than or equal to 3600",
        spoil(MISSION, top(blocked_wait_s=1e9)),
    ),
    Case(
        "mission_return_on_failure_text",
        RUN,
        2,
        "return_on_failure: Input should be a valid boolean",
        spoil(MISSION, top(return_on_failure="maybe")),
    ),
    Case("mission_name_mapping", RUN, 2, "name: Input should be a valid string", spoil(MISSION, top(name={"a": 1}))),
    Case(
        "mission_too_many_tasks",
        RUN,
        2,
        "tasks: List should have at most 10000 items",
        spoil(MISSION, lambda d: d.update(tasks=[{"type": "wait", "seconds": 1}] * 10001)),
    ),
    Case(
        "mission_json_nan",
        ("run", "{case}/m.json", "--quiet"),
        2,
        "not valid JSON: NaN",
        lambda fx, folder: (
            world(fx, folder),
            write(folder, "m.json", '{"map": "warehouse.yaml", "tasks": [{"type": "wait", "seconds": NaN}]}'),
        ),
    ),
    Case(
        "mission_json_syntax",
        ("run", "{case}/m.json", "--quiet"),
        2,
        "not valid JSON: line 1",
        lambda fx, folder: (world(fx, folder), write(folder, "m.json", '{"map": "warehouse.yaml",')),
    ),
    Case(
        "mission_map_nan_node",
        RUN,
        2,
        "Input should be a finite number",
        spoil("warehouse.yaml", lambda d: d["nodes"][5].update(x=NAN)),
    ),
    Case(
        "mission_and_scenario_both_bad",
        RUN_SC,
        2,
        "tasks[0] (pickup nowhere): unknown node",
        lambda fx, folder: (
            spoil(MISSION, first_task(node="nowhere"))(fx, folder),
            write(folder, SCENARIO, dump({**example(fx, SCENARIO), "start": "nowhere"})),
        ),
    ),
    Case(
        "mission_scenario_other_map",
        RUN_SC,
        2,
        "is not the mission's map",
        lambda fx, folder: (
            world(fx, folder),
            write(folder, "other.yaml", (fx.ex / "warehouse.yaml").read_text() + "\n# other\n"),
            write(folder, SCENARIO, dump({**example(fx, SCENARIO), "map": "other.yaml"})),
        ),
    ),
]

SCENARIOS: list[Case] = [
    Case(
        "scenario_dx_nan",
        RENDER,
        2,
        "pallets[0].dx: Input should be a finite number",
        spoil(SCENARIO, pallet(0, dx=NAN)),
    ),
    Case(
        "scenario_dy_inf",
        RENDER,
        2,
        "pallets[0].dy: Input should be a finite number",
        spoil(SCENARIO, pallet(0, dy=INF)),
    ),
    Case(
        "scenario_dyaw_nan",
        RENDER,
        2,
        "pallets[0].dyaw_deg: Input should be a finite number",
        spoil(SCENARIO, pallet(0, dyaw_deg=NAN)),
    ),
    Case(
        "scenario_dx_far",
        RENDER,
        2,
        "pallets[0].dx: Input should be less than or equal to 2",
        spoil(SCENARIO, pallet(0, dx=50.0)),
    ),
    Case(
        "scenario_dyaw_huge",
        RENDER,
        2,
        "pallets[0].dyaw_deg: Input should be less than or equal to 180",
        spoil(SCENARIO, pallet(0, dyaw_deg=1e6)),
    ),
    Case(
        "scenario_free_x_nan",
        RENDER,
        2,
        "pallets[4].x: Input should be a finite number",
        spoil(SCENARIO, lambda d: d["pallets"].append({"x": NAN, "y": 1.0})),
    ),
    Case(
        "scenario_free_far",
        RENDER,
        2,
        "pallets[4].x: Input should be less than or equal to 10000",
        spoil(SCENARIO, lambda d: d["pallets"].append({"x": 1e7, "y": 1.0})),
    ),
    Case(
        "scenario_pallet_chipped_too_many",
        RENDER,
        2,
        "pallets[0].damage.chipped_blocks: Input should be less than or equal to 3",
        spoil(SCENARIO, pallet(0, damage={"chipped_blocks": 7})),
    ),
    Case(
        "scenario_pallet_type_unknown",
        RENDER,
        2,
        "pallets[0].type: crate: not a known pallet type",
        spoil(SCENARIO, pallet(0, type="crate")),
    ),
    Case(
        "scenario_pallet_overhang_empty",
        RENDER,
        2,
        "overhang_m: only with a load (loaded: true)",
        spoil(SCENARIO, pallet(0, loaded=False, overhang_m=0.04)),
    ),
    Case(
        "scenario_box_negative",
        RENDER,
        2,
        "clutter[2].size[0]: Input should be greater than 0",
        spoil(SCENARIO, clutter(kind="box", x=10.0, y=2.0, size=[-0.5, 0.4, 0.5])),
    ),
    Case(
        "scenario_box_nan",
        RENDER,
        2,
        "clutter[2].size[2]: Input should be a finite number",
        spoil(SCENARIO, clutter(kind="box", x=10.0, y=2.0, size=[0.5, 0.4, NAN])),
    ),
    Case(
        "scenario_box_huge",
        RENDER,
        2,
        "clutter[2].size[1]: Input should be less than or equal to 20",
        spoil(SCENARIO, clutter(kind="box", x=10.0, y=2.0, size=[0.5, 1e9, 0.5])),
    ),
    Case(
        "scenario_box_two_sides",
        RENDER,
        2,
        "clutter[2].size",
        spoil(SCENARIO, clutter(kind="box", x=10.0, y=2.0, size=[0.5, 0.5])),
    ),
    Case(
        "scenario_person_speed_inf",
        RENDER,
        2,
        "clutter[2].speed: Input should be a finite number",
        spoil(SCENARIO, clutter(kind="person", x=6.0, y=18.0, path=[[6.0, 2.0]], speed=INF)),
    ),
    Case(
        "scenario_person_speed_zero",
        RENDER,
        2,
        "clutter[2].speed: Input should be greater than 0",
        spoil(SCENARIO, clutter(kind="person", x=6.0, y=18.0, path=[[6.0, 2.0]], speed=0)),
    ),
    Case(
        "scenario_person_speed_fast",
        RENDER,
        2,
        "clutter[2].speed: Input should be less than or equal to 3",
        spoil(SCENARIO, clutter(kind="person", x=6.0, y=18.0, path=[[6.0, 2.0]], speed=30)),
    ),
    Case(
        "scenario_person_path_nan",
        RENDER,
        2,
        "clutter[2].path[0][1]: Input should be a finite number",
        spoil(SCENARIO, clutter(kind="person", x=6.0, y=18.0, path=[[6.0, NAN]])),
    ),
    Case(
        "scenario_box_walks",
        RENDER,
        2,
        "path: only people walk",
        spoil(SCENARIO, clutter(kind="box", x=6.0, y=18.0, path=[[6.0, 2.0]])),
    ),
    Case(
        "scenario_clutter_kind",
        RENDER,
        2,
        "clutter[2].kind: Input should be 'person' or 'box'",
        spoil(SCENARIO, clutter(kind="dog", x=6.0, y=18.0)),
    ),
    Case(
        "scenario_two_pallets_one_node",
        RENDER,
        2,
        "two pallets placed at node 'floor_b2'",
        spoil(SCENARIO, lambda d: d["pallets"].append({"node": "floor_b2"})),
    ),
    Case(
        "scenario_free_pallets_overlap",
        RENDER,
        2,
        "pallets[4] overlaps pallets[5]",
        spoil(SCENARIO, lambda d: d["pallets"].extend([{"x": 10.0, "y": 2.0}, {"x": 10.3, "y": 2.2, "yaw_deg": 30}])),
    ),
    Case(
        "scenario_free_pallet_on_node_pallet",
        RENDER,
        2,
        "pallets[0] overlaps pallets[4]",
        spoil(SCENARIO, lambda d: d["pallets"].append({"x": 25.3, "y": 11.3})),
    ),
    Case(
        "scenario_start_inside_pallet",
        RENDER,
        2,
        "start: the truck at 'charger' overlaps pallets[4]",
        spoil(SCENARIO, lambda d: d["pallets"].append({"x": 12.5, "y": -2.5})),
    ),
    Case(
        "scenario_person_in_truck",
        RENDER,
        2,
        "start: the truck at 'charger' overlaps clutter[2]",
        spoil(SCENARIO, clutter(kind="person", x=12.5, y=-2.5)),
    ),
    Case(
        "scenario_box_on_pallet",
        RENDER,
        2,
        "pallets[0] overlaps clutter[2]",
        spoil(SCENARIO, clutter(kind="box", x=25.6, y=11.3)),
    ),
    Case("scenario_start_unknown", RENDER, 2, "start: unknown node 'nowhere'", spoil(SCENARIO, top(start="nowhere"))),
    Case("scenario_start_missing", RENDER, 2, "start: Field required", spoil(SCENARIO, lambda d: d.pop("start"))),
    Case(
        "scenario_pallet_unknown_node",
        RENDER,
        2,
        "pallets[2].node: unknown node 'rack_z9'",
        spoil(SCENARIO, pallet(2, node="rack_z9")),
    ),
    Case(
        "scenario_pallet_wrong_type",
        RENDER,
        2,
        "pallets[1].node: 'drop' is a drop node, not a pallet node",
        spoil(SCENARIO, pallet(1, node="drop")),
    ),
    Case("scenario_pallet_node_and_xy", RENDER, 2, "give either node", spoil(SCENARIO, pallet(1, x=1.0, y=2.0))),
    Case(
        "scenario_camera_width",
        RENDER,
        2,
        "camera.width: Input should be 640 or 848",
        spoil(SCENARIO, top(camera={"width": 1000})),
    ),
    Case(
        "scenario_mount_z_negative",
        RENDER,
        2,
        "camera.mount.z: Input should be greater than 0",
        spoil(SCENARIO, camera("mount", z=-0.2)),
    ),
    Case(
        "scenario_mount_tilt_nan",
        RENDER,
        2,
        "camera.mount.tilt_deg: Input should be a finite number",
        spoil(SCENARIO, camera("mount", tilt_deg=NAN)),
    ),
    Case(
        "scenario_mount_far",
        RENDER,
        2,
        "camera.mount.x: Input should be less than or equal to 3",
        spoil(SCENARIO, camera("mount", x=100.0)),
    ),
    Case(
        "scenario_perturbation_huge",
        RENDER,
        2,
        "camera.perturbation.xyz_sigma: Input should be less than or equal to 0.1",
        spoil(SCENARIO, camera("perturbation", xyz_sigma=5.0)),
    ),
    Case(
        "scenario_camera_noise_nan",
        RENDER,
        2,
        "camera.noise.rgb_sigma: Input should be a finite number",
        spoil(SCENARIO, camera("noise", rgb_sigma=NAN)),
    ),
    Case(
        "scenario_camera_noise_huge",
        RENDER,
        2,
        "camera.noise.disparity_sigma_px: Input should be less than or equal to 5",
        spoil(SCENARIO, camera("noise", disparity_sigma_px=1e9)),
    ),
    Case(
        "scenario_noise_nan",
        RENDER,
        2,
        "noise.slip_sigma: Input should be a finite number",
        spoil(SCENARIO, lambda d: d["noise"].update(slip_sigma=NAN)),
    ),
    Case(
        "scenario_noise_negative",
        RENDER,
        2,
        "noise.localization_xy_sigma: Input should be greater than or equal to 0",
        spoil(SCENARIO, lambda d: d["noise"].update(localization_xy_sigma=-1)),
    ),
    Case(
        "scenario_seed_negative",
        RENDER,
        2,
        "seed: Input should be greater than or equal to 0",
        spoil(SCENARIO, top(seed=-1)),
    ),
    Case(
        "scenario_seed_huge",
        RENDER,
        2,
        "seed: Input should be less than or equal to 18446744073709551615",
        spoil(SCENARIO, top(seed=2**70)),
    ),
    Case("scenario_seed_fraction", RENDER, 2, "seed: Input should be a valid integer", spoil(SCENARIO, top(seed=1.5))),
    Case(
        "scenario_battery_level",
        RENDER,
        2,
        "battery_level: Input should be less than or equal to 1",
        spoil(SCENARIO, top(battery_level=2.0)),
    ),
    Case("scenario_missing_map", RENDER, 2, "nothere.yaml: cannot read", spoil(SCENARIO, top(map="nothere.yaml"))),
    Case("scenario_missing_forks", RENDER, 2, "noforks.yaml: cannot read", spoil(SCENARIO, top(forks="noforks.yaml"))),
    Case("scenario_missing_vehicle", RENDER, 2, "nocar.yaml: cannot read", spoil(SCENARIO, top(vehicle="nocar.yaml"))),
    Case(
        "scenario_latin1",
        RENDER,
        2,
        "not UTF-8 text",
        raw(SCENARIO, "map: warehouse.yaml\nstart: caf\xe9\n".encode("latin-1")),
    ),
    Case("scenario_binary", RENDER, 2, "not UTF-8 text", raw(SCENARIO, bytes(range(255, -1, -1)))),
    Case(
        "scenario_unknown_key",
        RENDER,
        2,
        "clutter[2].colour: Extra inputs are not permitted",
        spoil(SCENARIO, clutter(kind="box", x=10.0, y=2.0, colour="red")),
    ),
    Case("scenario_fault_unknown", RENDER, 2, "faults[0]", spoil(SCENARIO, top(faults=[{"kind": "gremlins"}]))),
    Case(
        "scenario_fault_nan_time",
        RENDER,
        2,
        "Input should be a finite number",
        spoil(SCENARIO, top(faults=[{"kind": "camera_drop", "at_s": NAN, "duration_s": 1.0}])),
    ),
    Case("scenario_render_at_unknown", (*RENDER, "--at", "nowhere"), 2, "--at: unknown node 'nowhere'", world),
    Case("scenario_render_fork_height_mast", (*RENDER, "--fork-height", "5"), 2, "outside the mast's range", world),
    Case(
        "scenario_render_fork_height_nan",
        (*RENDER, "--fork-height", "nan"),
        2,
        "--fork-height: must be a finite number",
        world,
    ),
    Case(
        "scenario_render_fork_height_negative",
        (*RENDER, "--fork-height", "-1"),
        2,
        "--fork-height: must be in 0..20",
        world,
    ),
    Case(
        "scenario_run_start_inside_pallet",
        RUN_SC,
        2,
        "start: the truck at 'charger' overlaps pallets[4]",
        spoil(SCENARIO, lambda d: d["pallets"].append({"x": 12.5, "y": -2.5})),
    ),
]

VEHICLES: list[Case] = [
    Case(
        "vehicle_wheelbase_nan",
        VEHICLE,
        2,
        "wheelbase: Input should be a finite number",
        spoil("forklift.yaml", vehicle("wheelbase", NAN)),
    ),
    Case(
        "vehicle_wheelbase_inf",
        VEHICLE,
        2,
        "wheelbase: Input should be a finite number",
        spoil("forklift.yaml", vehicle("wheelbase", INF)),
    ),
    Case(
        "vehicle_speed_huge",
        VEHICLE,
        2,
        "max_speed_forward: Input should be less than or equal to 10",
        spoil("forklift.yaml", vehicle("max_speed_forward", 1e6)),
    ),
    Case(
        "vehicle_mast_inverted",
        VEHICLE,
        2,
        "mast.max_height must be above mast.min_height",
        spoil("forklift.yaml", vehicle("mast.min_height", 3.0)),
    ),
    Case(
        "vehicle_mast_nan",
        VEHICLE,
        2,
        "mast.max_height: Input should be a finite number",
        spoil("forklift.yaml", vehicle("mast.max_height", NAN)),
    ),
    Case(
        "vehicle_body_nan",
        VEHICLE,
        2,
        "body.width: Input should be a finite number",
        spoil("forklift.yaml", vehicle("body.width", NAN)),
    ),
    Case(
        "vehicle_scanner_nan",
        VEHICLE,
        2,
        "safety_scanner.warning_speed: Input should be a finite number",
        spoil("forklift.yaml", vehicle("safety_scanner.warning_speed", NAN)),
    ),
    Case(
        "vehicle_steering_90",
        VEHICLE,
        2,
        "max_steering_deg: Input should be less than 90",
        spoil("forklift.yaml", vehicle("max_steering_deg", 90)),
    ),
    Case(
        "vehicle_emergency_weak",
        VEHICLE,
        2,
        "emergency_decel must be at least max_decel",
        spoil("forklift.yaml", vehicle("emergency_decel", 0.1)),
    ),
    Case(
        "vehicle_unknown_key",
        VEHICLE,
        2,
        "turbo: Extra inputs are not permitted",
        spoil("forklift.yaml", vehicle("turbo", True)),
    ),
    Case(
        "vehicle_missing_wheelbase",
        VEHICLE,
        2,
        "wheelbase: Field required",
        spoil("forklift.yaml", lambda d: d.pop("wheelbase")),
    ),
    Case(
        "vehicle_latin1",
        VEHICLE,
        2,
        "not UTF-8 text",
        raw("forklift.yaml", "name: gabelstapler \xfc\n".encode("latin-1")),
    ),
    Case(
        "vehicle_in_scenario_bad",
        RENDER,
        2,
        "wheelbase: Input should be a finite number",
        lambda fx, folder: (
            spoil("forklift.yaml", vehicle("wheelbase", NAN))(fx, folder),
            write(folder, "v2.yaml", (folder / "forklift.yaml").read_text()),
            write(folder, SCENARIO, dump({**example(fx, SCENARIO), "vehicle": "v2.yaml"})),
        ),
    ),
]


def fifo(fx: Fixtures, folder: Path) -> None:
    """A named pipe where a mission file should be: reading it would block for ever."""
    os.mkfifo(folder / "fifo.yaml")


SPECIAL: list[Case] = [
    Case("mission_fifo", ("run", "{case}/fifo.yaml", "--quiet"), 2, "fifo.yaml: cannot read: not a regular file", fifo),
    Case(
        "scenario_dev_zero",
        ("sim", "render", "/dev/zero", "--out", "{case}/f.npz"),
        2,
        "/dev/zero: cannot read: not a regular file",
    ),
    Case(
        "forks_dev_zero",
        ("calibrate", "{frame}", "--forks", "/dev/zero"),
        2,
        "/dev/zero: cannot read: not a regular file",
    ),
    Case("map_dev_urandom", ("map", "check", "/dev/urandom"), 2, "/dev/urandom: cannot read: not a regular file"),
]

CASES = MISSIONS + SCENARIOS + VEHICLES + SPECIAL

"""The simulated warehouse: world, pallets, forklift dynamics, RGB-D camera, sensors, scenarios.

- `sim.simulator`: `Simulator(scenario, seed, start)`, what the executor drives: `localization()`,
  `drive(speed, steering)`, `stop()`, `set_fork_height(h)`, `fork_height`, `proximity_ranges()`,
  `grab() -> FrameBundle`, `step(dt)`; truth for tests: `true_pose`, `pallets`, `collisions`,
  `T_forklift_camera_true`, `battery_level`, `pallet_records()`, `obstacle_outlines()`; `snapshot()`,
  `restore(doc)`; the safety scanners: `safety_state()`, `set_safety_field_set(name)`.
- `sim.pallets`: `SimPallet`, `RackSupport`, `PalletPhysics` (forks and backrest against the pallet's
  boards and blocks: entering, lifting, carrying, setting down).
- `sim.scanner`: `SimScanner`, the safety laser scanners and the safety function behind them (warning
  field caps the speed, protective field stops the truck itself; fields from `control.safety`).
- `sim.contacts`: everything else is solid (`Solid`, `first_contact`, `rack_solids`): the truck's
  body, forks and carried load against walls, racks, people (standing or walking), boxes, pallets, loads.
- `sim.scenario`: scenario files (`load_scenario`, `Scenario`, `SimError`): map, start node, pallets
  (at nodes with their misplacement, or free on the floor), clutter (people may walk a path), the
  battery's start level, camera mount and its perturbation, camera and vehicle noise, seed, `faults`.
- `sim.faults`: injected faults (`FaultSpec`, `FaultInjector`); `sim.snapshot`: the exact state as JSON.
- `sim.forklift`: `SimForklift` (kinematic tricycle, actuator lag, slip, rate-limited mast),
  `LocalizationNoise`.

Rendering core (frames as in ARCHITECTURE.md: `T_a_b` maps b into a; the camera frame is optical):

- `sim.world`: triangle meshes with a semantic class, albedo and texture per triangle.
  `LabeledMesh` (`transformed(T)`, `with_class`, `merge`, `from_open3d`, `to_open3d`), `box_mesh`,
  `floor_mesh`, `wall_mesh`, `Rack` (`mesh(T_world_rack)`, `slot_pose(bay, level, slot)`),
  `pallet_mesh(T_world_pallet, pallet, cargo_size)` (EUR pallet from its boards and blocks; loaded
  pallets are pallet-full), `person_mesh`, `object_box_mesh`, `forks_mesh(forks, lift_height,
  T_world_forklift)`, `example_world()` (a small hall for demos, tests and benchmarks).
- `sim.camera`: the D435-like RGB-D camera ray-cast with Open3D's `RaycastingScene`.
  `RaycastRenderer(static).render(T_world_camera, camera, noise, rng, dynamic=..., fork_height=...,
  truth=...) -> FrameBundle` (z-depth float32 m, labels uint8, RGB uint8), `render(...)` for a one-off
  frame, `CameraModel.d435(width, height)`, `CameraNoise` (`off()`, `sigma_z`), `Lighting`,
  `camera_mount_pose(position, tilt, pan, roll) -> T_forklift_camera`, `d435_color_intrinsics`,
  `d435_depth_focal_px`, `perturb_labels` (with label noise the exact labels stay in the truth as
  `labels_true`); its noise model is `sim.camera_noise` (`CameraNoise`, `perturb_labels`).
- `sim.dataset`: seeded segmentation datasets, `render_frame(index, seed, mounts=...)`,
  `generate_dataset(out_dir, n, seed, start, mounts=...)`; `mounts` is `all` or `pickup` (only mounts
  that `palletpilot calibrate` finds fit for the Pickup).
"""

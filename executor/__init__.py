"""The mission executor: missions, task state machines, the fail-safe runner, reports and the CLI.

Modules (public API in each module's docstring):

- `mission`: mission files (`load_mission`, `validate_mission`); `tasks`: the task state machines as
  data (`TASK_SPECS`, `build_machine`) and their behaviours (`behaviour`, `driving`, `pickup`,
  `entry`: the entry and drop-slot checks).
- `ports`: the interfaces the runner drives (`VehiclePort`, `PerceptionService`), apart from their
  implementations (the simulator in `sim`, `local_perception.LocalPerception`, the ROS 2 adapter in `ros`).
- `runner`: `Runner`, the per-tick loop: behaviours, watchdogs, pause / cancel, fail-safe stops,
  checkpoints; `clock` (`SimClock`, `WallClock`), `jobs` (perception off the loop), `watchdog`,
  `controls` (signals), `errors` (`TaskFailed` and the reason codes), `results` (`TaskResult`).
- `journal` (SQLite) and `resume` (`Checkpointer`, `ResumePoint`): crash-safe progress and resuming.
- `app`: `run_simulated`, `resume_simulated` (the simulator wired to the runner); `report`: report.json,
  trajectory.png; `progress`: the progress line.
- `cli`: the `palletpilot` commands (the console script is `palletpilot.cli:main`, which adds `bench`).
"""

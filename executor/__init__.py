"""The mission executor, in four layers; each imports only the layers below it (import-linter, pyproject):

```
apps       composition roots and commands: compose (the one wiring of every run: run, test, robot and
           each AGV leg), app (simulated run), robot (ROS 2 truck), vda5050 (the AGV under a fleet
           manager), standin (`sim serve --ros`), suite* (`palletpilot test`), cli*
adapters   implementations and stores: local_perception, zenoh (perception service client and server),
           ros (the truck over ROS 2), mcap (recording, replay), stores (journal, report, trajectory CSV),
           processes
core       the executor itself: mission, tasks (task specs), behaviour (Settings, and the Context a
           state gets: injected dependencies and the TaskMemory a checkpoint stores) / driving / pickup /
           entry / calibration_trust (the states' behaviours), runner, watchdog, jobs, clock, controls,
           resume (checkpoints), errors, results, progress
ports      VehiclePort, PerceptionService, Clock, PassThroughVehicle, and the typed vocabulary (Reason,
           Outcome and the reason table, `ports.vocabulary`)
```

Rules the linter enforces: apps > adapters > core > ports; the adapters `ros`, `zenoh` and `mcap` do not
import one another, nor do the apps `vda5050`, `robot` and `suite_run`; core never reaches the simulator,
the benchmarks or an I/O library (SQLite, Zenoh, MCAP, Foxglove, DDS, MQTT, matplotlib) and imports no
heavy library itself; `import palletpilot.executor.ports` loads no implementation and no heavy library.

Public API: each module's docstring. The ones used most: `ports` (`VehiclePort`, `PerceptionService`,
`Clock`, `Reason`, `Outcome`), `core.mission` (`load_mission`), `core.runner` (`Runner`), `apps.app`
(`run_simulated`, `resume_simulated`), `apps.robot` (`run_robot`), `apps.cli` (the `palletpilot`
commands; the console script is `palletpilot.cli:main`, which adds `bench`).
"""

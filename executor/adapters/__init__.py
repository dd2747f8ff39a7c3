"""Implementations of the ports and the executor's stores: in-process perception (`local_perception`),
the Zenoh perception service (`zenoh`), ROS 2 (`ros`), MCAP recording and replay (`mcap`), the SQLite
journal, report.json and the trajectory CSV (`stores`), child processes (`processes`). They depend on
`core` and `ports`, never on `apps`; `ros`, `zenoh` and `mcap` do not import one another."""

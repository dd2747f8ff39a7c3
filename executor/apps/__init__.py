"""The composition roots and commands: `app` (a simulated run), `robot` (a run on the truck over ROS 2),
`vda5050` (the AGV under a fleet manager), the `cli*` commands and the mission test suite (`suite*`)."""

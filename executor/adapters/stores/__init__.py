"""What a run leaves on disk: `journal` (SQLite, for resuming), `report` (report.json, trajectory.png),
`trajectory_log` (trajectory.csv)."""

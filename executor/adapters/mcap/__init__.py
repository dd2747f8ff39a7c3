"""Recording a run (run.mcap, the Foxglove live view) and replaying it: `recording` and its channels,
camera, events, scene and simulator feeds; `replay`."""

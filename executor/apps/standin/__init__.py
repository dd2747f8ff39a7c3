"""The simulator playing the truck on the ROS 2 topics (`palletpilot sim serve --ros`): a test stand-in,
composed of the simulator and the ROS 2 adapter, not one of the product's adapters.

- `truck`: `StandIn`, the simulated truck on the robot file's topics.
- `camera`: the stand-in's camera in a child process (`CameraProcess`) and its image messages.
- `foxglove`: `StandInView`, the stand-in's live Foxglove view.
"""

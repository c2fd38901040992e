"""Where a mission meets the ROS ecosystem's own tools, fed by the mission's messages as they
travel (:mod:`rovergate.taps`); nothing flows back from them into the mission:

- :mod:`ecosystem.recorder`: the flight recorder, a rosbag2 bag with MCAP storage, written by
  a process of its own (:mod:`ecosystem.bag_writer`);
- :mod:`ecosystem.replay`: a recorded mission, published again over Zenoh;
- :mod:`ecosystem.live_view`: a Foxglove WebSocket server, and :mod:`ecosystem.layout` its
  Foxglove layout;
- :mod:`ecosystem.ros2`: the topics in the ROS 2 graph, as rmw_zenoh publishes them.
"""

"""Where a mission meets the ROS ecosystem's own tools, fed by the mission's messages as they
travel (:mod:`ecosystem.taps`):

- :mod:`ecosystem.recorder`: the flight recorder, a rosbag2 bag with MCAP storage;
- :mod:`ecosystem.replay`: a recorded mission, published again over Zenoh.
"""

"""`semmap ros2`: the ROS 2 bridge (its own process; needs the `semmap[ros2]` extra). See docs/ROS2.md.

Only `semmap.services.ros2.bridge` imports rclpy; `semmap.services.ros2.sync` (the frame matching) is plain Python.
"""

"""`semmap ros2`: the ROS 2 bridge (semmap/services/ros2/bridge.py parses its own options, so that listing the
commands does not import it)."""

from __future__ import annotations

import argparse

ORDER = 20


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "ros2",
        add_help=False,
        help="ROS 2 bridge: camera + SLAM topics in, landmarks and trajectory out "
        "(needs the ros2 extra; see docs/ROS2.md)",
        description="Feed a running `semmap run external` from ROS 2 topics and publish the map "
        "back. ROS arguments follow --ros-args (remap topics with -r FROM:=TO, parameters with "
        "-p NAME:=VALUE). `semmap ros2 --help` lists the options.",
    )
    p.set_defaults(func=_ros2, passthrough=True)


def _ros2(args: argparse.Namespace) -> int:
    from semmap.services.ros2.bridge import main

    return main([*args.extra, *args.ros_args])

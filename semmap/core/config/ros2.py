"""The ROS 2 bridge's settings (`semmap ros2`, semmap/services/ros2/bridge.py): one typed section, like every
other part of the configuration, instead of a dictionary of its own in the bridge.

The bridge declares each field as a ROS parameter (`-p name:=value`) with the field's default and description,
and validates what ROS hands back through this section (strict types, no unknown keys).
"""

from __future__ import annotations

from pydantic import Field

from .base import Section


class Ros2BridgeConfig(Section):
    """The ROS 2 bridge: topics in, matching, the link to semmap and the outputs (ROS parameters)."""

    pose_type: str = Field('odometry', description='type on the pose topic: odometry | pose | pose_with_covariance')
    pose_to_optical: str = Field(
        'identity',
        description="pose frame -> camera optical frame: identity (the pose is the optical frame's) | ros (a REP 103 "
        "frame at the camera, x forward) | 'x y z qx qy qz qw'",
    )
    sync_tolerance_s: float = Field(0.02, description='largest header-stamp difference between colour, depth and pose')
    pose_max_gap_s: float = Field(
        0.5,
        description="longest gap between two poses that a frame's pose is interpolated over",
    )
    max_wait_s: float = Field(2.0, description='how long an unmatched colour image waits for its depth and pose')
    sigma_translation_m: float = Field(
        0.01,
        description="per-frame 1-sigma motion noise declared to semmap's backend (metres)",
    )
    sigma_rotation_deg: float = Field(0.5, description='... and rotation (degrees)')
    lockstep: bool = Field(
        False,
        description='wait until semmap has processed each frame before sending the next (no drops; for bags and '
        'tests); false: real time, the oldest waiting frame is dropped when semmap is busy',
    )
    queue_size: int = Field(
        2,
        description='real time: frames waiting for semmap before the oldest is dropped (counted)',
    )
    map_frame: str = Field(
        '',
        description='frame of the outputs ("" = the pose messages\' header.frame_id, else \'map\')',
    )
    corrected_frame: str = Field('semmap_map', description='parent frame of /semmap/correction (the corrected world)')
    output_period_s: float = Field(
        1.0,
        description='publish the map and the trajectory at most this often (the latest state)',
    )
    path_max_poses: int = Field(
        500,
        description='the Path holds at most this many poses, evenly spread, the newest always',
    )
    topic_timeout_s: float = Field(
        5.0,
        description='report an input topic by name when nothing arrived on it for this long',
    )
    end_after_idle_s: float = Field(
        0.0,
        description='send semmap end-of-stream (it writes its files) after this long without a frame; 0 = only '
        'when the bridge stops',
    )
    reliable_input: bool = Field(
        False,
        description='subscribe to the inputs with reliable QoS (default best effort: matches any publisher, never '
        'blocks the camera)',
    )
    input_depth: int = Field(
        0,
        description='input QoS history depth; 0 = sized for you: reliable input keeps all (nothing is dropped by the '
        "bridge's reader; a reliable camera is slowed instead), best effort keeps camera_rate_hz x "
        'input_latency_s',
    )
    camera_rate_hz: float = Field(30.0, description="the camera's frame rate (sizes the best-effort input history)")
    input_latency_s: float = Field(
        1.0,
        description="longest the bridge's ROS thread may fall behind its inputs before a best-effort reader drops "
        'messages',
    )
    flush_after_s: float = Field(
        0.5,
        description='when no input arrived for this long (wall time), frames held for a closer depth image or a newer '
        'pose are matched with what there is (the last frame of a recording is sent)',
    )
    dynamic_lifetime_s: float = Field(
        0.5,
        description='lifetime of a dynamic-object box in RViz: it vanishes unless a newer detected frame renews it',
    )

"""Run control, progress and health: `Control` (key `control`), `Progress` (`progress/<service>`) and
`ServiceStatus` (`status/<service>/<instance>`)."""

from __future__ import annotations

from typing import ClassVar, Literal

import msgspec

from .base import Finite, Message, RobotName, Timings


class Control(Message, tag="semmap.control/1"):
    """Run control from the player / CLI: `end_of_stream` after the last frame, `stop` to shut down,
    `frame_unreadable` for a dataset frame that could not be read (`last_frame_id`: that frame; it never comes)."""

    COMMANDS: ClassVar[tuple[str, ...]] = ("end_of_stream", "stop", "frame_unreadable")
    robot: RobotName
    command: Literal["end_of_stream", "stop", "frame_unreadable"]
    last_frame_id: int = 0
    frames: int = 0
    sent_at: Finite = 0.0
    # end_of_stream from an external source (the ROS 2 bridge): what it counted on its side, e.g. frames lost
    # before semmap by reason; the run keeps them in stats.json ("source"). Optional: absent reads empty.
    counters: dict[str, int] = msgspec.field(default_factory=dict)


class Progress(Message, tag="semmap.progress/1"):
    """A service finished everything that `frame_id` caused: lockstep playback waits on these."""

    robot: RobotName
    service: str
    frame_id: int
    sent_at: Finite = 0.0


class ServiceStatus(Message, tag="semmap.status/1"):
    """A service's health and counters, sent periodically and once more when it finishes."""

    STATES: ClassVar[tuple[str, ...]] = ("starting", "running", "finished", "failed", "stopped")
    robot: RobotName
    service: str
    instance: str
    state: Literal["starting", "running", "finished", "failed", "stopped"]
    last_frame_id: int = -1
    counters: dict[str, int] = msgspec.field(default_factory=dict)
    timings: dict[str, Timings] = msgspec.field(default_factory=dict)
    rss_mb: Finite = 0.0
    cpu_s: Finite = 0.0
    message: str = ""
    sent_at: Finite = 0.0

"""Every environment variable semmap reads, with what it means: the one place they are read.

Settings belong in the configuration tree (semmap/core/config); the environment carries only what cannot travel
there: where things are on this machine (data, models), how to reach the bus (containers set these instead of
flags), and what `semmap run` hands its children privately (the run's identity and secret: not on a command
line others can read). `read(name)` refuses a name not listed here, so a new variable is documented or fails.
"""

from __future__ import annotations

import os
from dataclasses import dataclass


@dataclass(frozen=True)
class Variable:
    name: str
    meaning: str
    default: str = ""


ZENOH_CONNECT = "SEMMAP_ZENOH_CONNECT"
ZENOH_LISTEN = "SEMMAP_ZENOH_LISTEN"
ZENOH_MODE = "SEMMAP_ZENOH_MODE"
ZENOH_CONFIG = "SEMMAP_ZENOH_CONFIG"
RUN_ID = "SEMMAP_RUN_ID"
RUN_KEY = "SEMMAP_RUN_KEY"
RUN_OPEN_KEYS = "SEMMAP_RUN_OPEN_KEYS"
PARENT_PID = "SEMMAP_PARENT_PID"
ROBOT = "SEMMAP_ROBOT"
HEALTH_FILE = "SEMMAP_HEALTH_FILE"
MODEL_DIR = "SEMMAP_MODEL_DIR"
CHOICE_DIR = "SEMMAP_CHOICE_DIR"
DATA = "SEMMAP_DATA"
XDG_RUNTIME_DIR = "XDG_RUNTIME_DIR"
ROS_DISCOVERY_RANGE = "ROS_AUTOMATIC_DISCOVERY_RANGE"
DISPLAY = "DISPLAY"
WAYLAND_DISPLAY = "WAYLAND_DISPLAY"

VARIABLES: tuple[Variable, ...] = (
    Variable(ZENOH_CONNECT, "Zenoh endpoints to connect to, comma-separated (flag --connect wins)"),
    Variable(ZENOH_LISTEN, "Zenoh endpoints to listen on (flag --listen wins; also semmap's router)"),
    Variable(ZENOH_MODE, "Zenoh mode: peer | client | router (flag --zenoh-mode wins)"),
    Variable(ZENOH_CONFIG, "a Zenoh configuration file (TLS, access control; docs/SECURITY.md)"),
    Variable(RUN_ID, "set by `semmap run` for its children: the run's id (signed messages name it)"),
    Variable(RUN_KEY, "set by `semmap run` for its children: the run's secret signing key (hex)"),
    Variable(RUN_OPEN_KEYS, "set by `semmap run` for its children: topics taking unsigned messages (external)"),
    Variable(PARENT_PID, "set by `semmap run` for its children: a child whose parent is gone stops"),
    Variable(ROBOT, "a service started by hand or by compose: the robot name (flag --robot wins; run.robot)"),
    Variable(HEALTH_FILE, "containers: the heartbeat file a service touches (semmap.runtime.transport.health)",
             "/tmp/semmap.health"),
    Variable(MODEL_DIR, "where detector models and the ORB vocabulary live", "~/.cache/semmap/models"),
    Variable(CHOICE_DIR, "where this machine's detector measurement (`semmap models doctor`) is kept, where the "
             "model dir is read-only (containers)", "the model dir"),
    Variable(DATA, "where datasets are looked up by name"),
    Variable(XDG_RUNTIME_DIR, "(the desktop's) where the registry of live runs is kept"),
    Variable(ROS_DISCOVERY_RANGE, "(ROS 2's) discovery range; `semmap ros2` defaults it to LOCALHOST", "LOCALHOST"),
    Variable(DISPLAY, "(X11's) whether `semmap view` can open a window"),
    Variable(WAYLAND_DISPLAY, "(Wayland's) whether `semmap view` can open a window"),
)

BY_NAME: dict[str, Variable] = {v.name: v for v in VARIABLES}


def read(name: str) -> str | None:
    """The value of `name` (None when unset). KeyError for a variable not listed above."""
    if name not in BY_NAME:
        raise KeyError(f"{name} is not a listed environment variable (semmap/core/environment.py)")
    return os.environ.get(name)


def set_default(name: str, value: str) -> str:
    """Set `name` for this process (and its children) unless it is set; returns its value."""
    read(name)  # (listed)
    return os.environ.setdefault(name, value)


def describe() -> str:
    """The table of variables, for docs and `--help` texts."""
    return "\n".join(f"{v.name}: {v.meaning}" + (f" (default {v.default})" if v.default else "") for v in VARIABLES)

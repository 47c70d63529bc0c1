"""Fast DDS set up for large images between processes on one host (docs/ROS2.md, "Transport").

Fast DDS defaults (and `ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`) move a 640x480 rgb8 image (~900 KB) as ~14 UDP
fragments over loopback into a socket buffer sized by the kernel's default: at 30 Hz, best effort, most of them
are lost (a do-nothing subscriber received 25-50 %). The profile below gives every participant of a process
that loads it:
  - a shared-memory transport whose segment holds many whole images (no fragmentation, no socket buffer), and
  - UDPv4 on the loopback interface only, with 4 MB socket buffers, for what cannot go through shared memory
    (discovery with processes of other users, a participant without this profile).
Nothing leaves the host. `semmap ros2` loads it unless FASTDDS_DEFAULT_PROFILES_FILE is already set; a camera
node on the same host gets the same by exporting FASTDDS_DEFAULT_PROFILES_FILE to the file that
`semmap ros2 --write-fastdds-profile PATH` writes.
"""

from __future__ import annotations

import os
from pathlib import Path

from semmap.runtime.transport.run_registry import runtime_dir

PROFILE_ENV = "FASTDDS_DEFAULT_PROFILES_FILE"
SHM_SEGMENT_BYTES = 64 * 1024 * 1024  # ~45 colour + depth pairs of 640x480 in flight per writer
SOCKET_BUFFER_BYTES = 4 * 1024 * 1024  # at most net.core.rmem_max / wmem_max (Linux: often 208 KB - 4 MB)

PROFILE_XML = f"""<?xml version="1.0" encoding="UTF-8" ?>
<!-- semmap: Fast DDS on one host for large images (shared memory first, loopback UDP with large buffers).
     Use it for every ROS 2 process on this host that publishes or subscribes to camera images:
       export FASTDDS_DEFAULT_PROFILES_FILE=/path/to/this/file -->
<dds xmlns="http://www.eprosima.com">
  <profiles>
    <transport_descriptors>
      <transport_descriptor>
        <transport_id>semmap_shm</transport_id>
        <type>SHM</type>
        <segment_size>{SHM_SEGMENT_BYTES}</segment_size>
        <port_queue_capacity>1024</port_queue_capacity>
      </transport_descriptor>
      <transport_descriptor>
        <transport_id>semmap_udp_loopback</transport_id>
        <type>UDPv4</type>
        <sendBufferSize>{SOCKET_BUFFER_BYTES}</sendBufferSize>
        <receiveBufferSize>{SOCKET_BUFFER_BYTES}</receiveBufferSize>
        <interfaceWhiteList>
          <address>127.0.0.1</address>
        </interfaceWhiteList>
      </transport_descriptor>
    </transport_descriptors>
    <participant profile_name="semmap_one_host" is_default_profile="true">
      <rtps>
        <useBuiltinTransports>false</useBuiltinTransports>
        <userTransports>
          <transport_id>semmap_shm</transport_id>
          <transport_id>semmap_udp_loopback</transport_id>
        </userTransports>
      </rtps>
    </participant>
  </profiles>
</dds>
"""


def write_profile(path: str | os.PathLike) -> Path:
    """Write the profile to `path` (parents created); return it."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(PROFILE_XML)
    return out


def default_profile_path() -> Path:
    """Where `semmap ros2` keeps its copy: the per-user runtime directory ($XDG_RUNTIME_DIR/semmap, else
    <temp dir>/semmap-<uid>), beside the records of the runs."""
    return runtime_dir() / "fastdds_one_host.xml"


def use_profile(environ: dict | None = None) -> str:
    """Point FASTDDS_DEFAULT_PROFILES_FILE at semmap's profile unless the user set one (theirs wins). Call before
    rclpy creates its first participant. Returns the file in use."""
    env = os.environ if environ is None else environ
    if env.get(PROFILE_ENV):
        return str(env[PROFILE_ENV])
    path = default_profile_path()
    if not path.exists() or path.read_text() != PROFILE_XML:
        write_profile(path)
    env[PROFILE_ENV] = str(path)
    return str(path)

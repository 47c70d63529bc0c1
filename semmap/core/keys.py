"""Every Zenoh key expression semmap uses, built here and nowhere else.

Layout: `semmap/v1/<robot>/<topic>`. `v1` is the key-space version (bumped only when the layout changes;
payload versions live in each message's `schema`). An external SLAM talks to us through these keys alone:
docs/INTERFACE.md describes each one with its payload.
"""

from __future__ import annotations

import re

from semmap.core.dataflow import EXTERNAL_SENDER as EXTERNAL_SENDER  # (re-exported: the role of an open key)
from semmap.core.dataflow import publishers

KEYSPACE = "semmap/v1"
_NAME = re.compile(r"^[A-Za-z0-9_-]{1,64}$")

# Who may publish on each topic (a run's messages are signed with the sender's role; semmap.runtime.transport.bus
# checks it, and
# the secure profile's access-control list grants the same puts): the outputs the dataflow declares
# (semmap/core/dataflow.py). `status/<service>/...` and `progress/<service>` belong to `<service>`. A topic not
# listed here: any member of the run.
PUBLISHERS: dict[str, tuple[str, ...]] = publishers()


class InvalidNameError(ValueError):
    """An invalid robot, service or instance name (it would break or widen a key expression)."""


def _check(name: str, what: str) -> str:
    if not isinstance(name, str) or not _NAME.match(name):
        raise InvalidNameError(f"invalid {what} name {name!r}: use 1-64 letters, digits, '_' or '-'")
    return name


class Keys:
    """The keys of one robot. `Keys("robot1").frames` -> `semmap/v1/robot1/frames`."""

    def __init__(self, robot: str) -> None:
        self.robot = _check(robot, "robot")
        self.root = f"{KEYSPACE}/{robot}"

    # sensor input: from the dataset player or an external SLAM
    @property
    def frames(self) -> str:
        return f"{self.root}/frames"

    @property
    def odometry(self) -> str:
        return f"{self.root}/odometry"

    @property
    def slam(self) -> str:
        """An external SLAM's own poses, for semmap to check before they become odometry (`run external
        --check-slam`; docs/ORBSLAM3.md)."""
        return f"{self.root}/slam"

    # pipeline stages
    @property
    def detections(self) -> str:
        return f"{self.root}/detections"

    @property
    def tracks(self) -> str:
        return f"{self.root}/tracks"

    @property
    def dynamic(self) -> str:
        """Per frame, the boxes of objects dynamic by class or seen moving (for a front end to leave out)."""
        return f"{self.root}/dynamic"

    @property
    def observations(self) -> str:
        return f"{self.root}/observations"

    @property
    def landmark_tags(self) -> str:
        """The observations again as AprilTag-like id + pose detections (RTAB-Map's landmark form)."""
        return f"{self.root}/observations/tags"

    @property
    def map_updates(self) -> str:
        return f"{self.root}/map/updates"

    @property
    def map_query(self) -> str:
        return f"{self.root}/map/query"

    @property
    def corrected_poses(self) -> str:
        return f"{self.root}/poses/corrected"

    # run control and health
    @property
    def control(self) -> str:
        return f"{self.root}/control"

    def progress(self, service: str) -> str:
        return f"{self.root}/progress/{_check(service, 'service')}"

    @property
    def progress_all(self) -> str:
        return f"{self.root}/progress/*"

    def status(self, service: str, instance: str) -> str:
        return f"{self.root}/status/{_check(service, 'service')}/{_check(instance, 'instance')}"

    @property
    def status_all(self) -> str:
        return f"{self.root}/status/**"

    def detector_replica(self, instance: str, run: str = "") -> str:
        """Liveliness token of one detector replica: replicas share frames by rank among the live tokens. Within
        a run (`run` id) the token sits under the run, so a token of another run (or a forged one) is not
        counted as a replica."""
        run_chunk = f"{_check(run, 'run')}/" if run else ""
        return f"{self.root}/detector/replicas/{run_chunk}{_check(instance, 'instance')}"

    def detector_replicas(self, run: str = "") -> str:
        return f"{self.root}/detector/replicas/{_check(run, 'run') + '/' if run else ''}*"

    @property
    def detector_replicas_all(self) -> str:
        return f"{self.root}/detector/replicas/**"

    def key(self, topic: str) -> str:
        """`poses/corrected` -> `semmap/v1/robot1/poses/corrected` (a topic of semmap/core/dataflow.py's table)."""
        return f"{self.root}/{topic}"

    def topic(self, key: str) -> str:
        """`semmap/v1/robot1/poses/corrected` -> `poses/corrected` (the name counters use)."""
        key = str(key)
        return key[len(self.root) + 1:] if key.startswith(self.root + "/") else key

    def publishers(self, key: str) -> tuple[str, ...] | None:
        """The senders allowed to publish on `key` (None: any member of the run)."""
        topic = self.topic(key)
        head, _, rest = topic.partition("/")
        if head in ("status", "progress") and rest:
            return (rest.split("/", 1)[0],)
        return PUBLISHERS.get(topic)

    @staticmethod
    def instance_of(key: str) -> str:
        """The last chunk of a key (a replica's or a status's instance name)."""
        return str(key).rsplit("/", 1)[-1]

"""The dataflow of a semmap run, declared once, as data: every node, the keys it reads and writes, its replicas,
whether lockstep playback waits for it, and the flags that wire it to the nodes around it.

Like a dora dataflow file, but a typed table: everything that used to restate the wiring reads it from here.
- `semmap.core.keys.PUBLISHERS` (who may sign a message on a topic) is `publishers()`;
- the secure profile's access-control list (`semmap.runtime.transport.secure_profile`) grants each identity what its
node
  reads, writes, asks and answers here, and nothing else;
- `semmap run` (`semmap.cli.run.pipeline_specs`) starts the stages in `PIPELINE` order, passes the `flags` whose
  partners run too, and tells the player to wait for the `lockstep` nodes (`player_wait_for`);
- `Service.listen()` / `Service.publisher()` (semmap.runtime.transport.service) refuse a key their node does not
declare;
- tests check that compose.yaml, the service modules and docs/DESIGN.md (`python -m semmap.core.dataflow`
  writes its dataflow section) agree with this table.

Topics are relative to `semmap/v1/<robot>/` (semmap.core.keys). Each service also reads `control` and writes its
own `status/<service>/<instance>` and `progress/<service>` (the base class does it: `SERVICE_INPUTS`,
`service_reports`).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from typing import Literal

EXTERNAL_SENDER = "external"  # the role an external SLAM's messages carry (an unsigned publisher on an open key)
# front ends an external run may pose its frames with (`semmap run external --odometry orbslam3`: a robot's camera
# through `semmap ros2`, posed by semmap's ORB-SLAM3 instead of the robot's own odometry)
OWN_FRONT_ENDS = ("orbslam3", "rgbd")
# front ends that refine their trajectory at their end: the backend waits for their `odometry/refined`
REFINING_FRONT_ENDS = ("orbslam3",)

# every service reads the run's control key (stop, end of stream, unreadable frames) through the base class
SERVICE_INPUTS: tuple[str, ...] = ("control",)


@dataclass(frozen=True)
class Topic:
    """One key under `semmap/v1/<robot>/`: the message it carries (a class of semmap.core.messages)."""

    name: str
    message: str
    meaning: str


@dataclass(frozen=True)
class WiringFlag:
    """A flag `semmap run` passes a node when every node of `with_nodes` runs too (compose passes it always:
    its stack has them all)."""

    flag: str
    with_nodes: tuple[str, ...]
    why: str


@dataclass(frozen=True)
class Port:
    """How a service takes one of its inputs: each message of `topic` goes to its method `handler`. `when` names a
    boolean attribute of the service that must be true for it to subscribe at all (an input only some
    configurations need: a front end that leaves people out reads `dynamic`); `feedback`: the topic comes back
    from a later stage of the same frame (lockstep delivers it after the stages ran, not before)."""

    topic: str
    handler: str
    when: str = ""
    feedback: bool = False


@dataclass(frozen=True)
class Node:
    """One process of the dataflow. `service`: `python -m semmap.services.<name>`, started by `semmap run` or a
    container; `client`: a process outside the pipeline with an identity of its own (the run itself, an external
    SLAM, a map user)."""

    name: str
    kind: Literal["service", "client"]
    summary: str
    ports: tuple[Port, ...] = ()  # a service's inputs and the handlers they go to (Service.subscribe runs them)
    inputs: tuple[str, ...] = ()  # topics it subscribes to (may be wildcards: `status/**`, `progress/*`)
    outputs: tuple[str, ...] = ()  # topics it publishes on
    asks: tuple[str, ...] = ()  # topics it queries (Zenoh get)
    answers: tuple[str, ...] = ()  # topics it answers queries on (a queryable)
    liveliness: tuple[str, ...] = ()  # liveliness tokens it declares and watches
    replicas: str = "1"  # how many run: a number, or the `semmap run` flag that sets it
    lockstep: bool = False  # lockstep playback waits for its progress on every frame
    flags: tuple[WiringFlag, ...] = ()
    sender: str = ""  # the role its messages are signed with (default: its name)
    # where the concept lives (docs/DESIGN.md)
    algorithm: str = ""
    stage: str = ""  # its per-frame policy as a plain stage object (semmap.runtime.pipeline.stages), if it has one
    config: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.ports and not self.inputs:  # (a service's inputs are its ports' topics)
            object.__setattr__(self, "inputs", tuple(p.topic for p in self.ports))

    @property
    def role(self) -> str:
        return self.sender or self.name

    @property
    def module(self) -> str:
        return f"semmap.services.{self.name}" if self.kind == "service" else ""

    def reads(self) -> tuple[str, ...]:
        """Every topic it may subscribe to: its inputs, and `control` for a service."""
        return (*self.inputs, *(SERVICE_INPUTS if self.kind == "service" else ()))


TOPICS: tuple[Topic, ...] = (
    Topic("frames", "Frame", "colour, depth, intrinsics (and ground truth, from a dataset) of one frame"),
    Topic("odometry", "OdometryPose", "the front end's camera pose of a frame"),
    Topic("odometry/refined", "OdometryRefinement", "the odometry of earlier frames again, as the SLAM refined its "
          "own trajectory at its end (once, after the last pose)"),
    Topic("slam", "OdometryPose", "an external SLAM's own pose, checked before it becomes odometry"),
    Topic("detections", "Detections", "a frame's boxes with depth (or `skipped`)"),
    Topic("tracks", "Tracks", "a frame's tracklets and the ones that ended"),
    Topic("dynamic", "DynamicObjects", "a frame's boxes of dynamic objects, for a front end to leave out"),
    Topic("observations", "Observations", "a frame's landmark observations and merges, for the backend"),
    Topic("observations/tags", "TagDetections", "the observations as AprilTag-like id + pose detections"),
    Topic("map/updates", "MapUpdate", "landmarks changed, removed or merged by a frame"),
    Topic("map/query", "(JSON reply)", "the current map, asked for with filters (Zenoh query)"),
    Topic("poses/corrected", "CorrectedPoses", "the pose graph's corrected poses (a delta, or full)"),
    Topic("control", "Control", "stop, end of stream, unreadable frame"),
    Topic("progress/*", "Progress", "a service finished everything a frame caused (real time: the newest such "
          "frame, at most every 0.1 s)"),
    Topic("status/**", "ServiceStatus", "a service instance's state, counters and timings, once a second"),
    Topic("detector/replicas/**", "(liveliness)", "one token per detector replica: they take turns at the frames"),
)

NODES: tuple[Node, ...] = (
    Node("player", "service", "plays a dataset; lockstep: the next frame once every lockstep node is done",
         ports=(Port("progress/*", "_on_progress", when="lockstep"), Port("status/**", "_on_status")),
         outputs=("frames", "control"),
         algorithm="semmap.datasets", stage="frame_message", config=("run", "rosbag")),
    Node("odometry", "service", "a camera pose per frame (or an external SLAM's, checked)",
         ports=(Port("frames", "receive"), Port("dynamic", "on_dynamic", when="uses_dynamic"),
                Port("slam", "on_slam", when="needs_slam")),
         outputs=("odometry", "odometry/refined"), lockstep=True,
         flags=(WiringFlag("--await-dynamic", ("detector", "tracker"),
                           "lockstep: a front end that leaves out dynamic objects waits for each frame's boxes"),),
         algorithm="semmap.algorithms.odometry", config=("odometry",)),
    Node("detector", "service", "boxes with depth per frame; replicas share the frames",
         ports=(Port("frames", "on_frame"),), outputs=("detections",), liveliness=("detector/replicas/**",),
         replicas="--detectors",
         lockstep=True, algorithm="semmap.algorithms.detector", stage="depth_detections", config=("detector",)),
    Node("tracker", "service", "IOU tracklets, and the frame's dynamic objects",
         ports=(Port("detections", "receive"), Port("map/updates", "on_map_update", feedback=True)),
         outputs=("tracks", "dynamic"), lockstep=True,
         algorithm="semmap.algorithms.tracker", stage="TrackerStage", config=("tracker",)),
    Node("associator", "service", "landmarks from tracklets against the best known poses; answers map queries",
         ports=(Port("tracks", "on_tracks"), Port("odometry", "on_odometry"),
                Port("poses/corrected", "on_corrected", feedback=True)),
         outputs=("observations", "observations/tags", "map/updates"),
         answers=("map/query",), lockstep=True,
         flags=(WiringFlag("--await-backend", ("backend",),
                           "lockstep: hold each frame until the backend's corrected poses for it come"),),
         algorithm="semmap.algorithms.associator", stage="AssociatorStage", config=("associator",)),
    Node("backend", "service", "pose graph of odometry and landmark observations; loop closures",
         ports=(Port("odometry", "receive"), Port("odometry/refined", "on_refinement", when="awaits_refinement"),
                Port("observations", "on_observations"),
                Port("frames", "on_frame", when="takes_keyframes"),
                Port("dynamic", "on_dynamic", when="masks_keyframes")),
         outputs=("poses/corrected",), lockstep=True,
         flags=(WiringFlag("--await-keyframe-dynamic", ("detector", "tracker"),
                           "lockstep: a keyframe's cloud waits for its dynamic objects, left out of it"),),
         algorithm="semmap.algorithms.backend", stage="BackendStage",
         config=("backend", "loop_closure", "corrections")),
    Node("viz", "service", "the Rerun recording (run.rrd) and live viewer",
         ports=(Port("frames", "on_frame"), Port("odometry", "on_odometry"), Port("detections", "on_detections"),
                Port("tracks", "on_tracks"), Port("map/updates", "on_map"), Port("poses/corrected", "on_corrected")),
         asks=("map/query",),
         flags=(WiringFlag("--wait-for-map", ("associator",),
                           "finish only after the map update of the last frame"),),
         algorithm="", config=("viz",)),
    Node("orchestrator", "client", "`semmap run`: starts, watches and stops the services; stats.json",
         inputs=("status/**", "progress/*", "control"), outputs=("control",), asks=("map/query",)),
    Node("slam", "client", "an external SLAM (semmap.runtime.client, `semmap ros2`): frames and poses in",
         inputs=("poses/corrected", "observations", "observations/tags", "map/updates", "dynamic", "progress/*",
                 "status/**"),
         outputs=("frames", "odometry", "slam", "control"), asks=("map/query",), sender=EXTERNAL_SENDER),
    Node("query", "client", "a read-only map user (`semmap query`)", inputs=("map/updates",),
         asks=("map/query",)),
)

BY_NAME: dict[str, Node] = {node.name: node for node in NODES}
SOURCE = "player"  # the node that feeds a dataset run (started by the orchestrator after the stages)
# the stages `semmap run` starts, in dataflow order (each `python -m semmap.services.<name>`)
PIPELINE: tuple[str, ...] = tuple(n.name for n in NODES if n.kind == "service" and n.name != SOURCE)
SERVICES: tuple[str, ...] = tuple(n.name for n in NODES if n.kind == "service")
CLIENTS: tuple[str, ...] = tuple(n.name for n in NODES if n.kind == "client")


class UndeclaredKeyError(ValueError):
    """A node subscribed to or published on a topic the dataflow does not give it."""


def node(name: str) -> Node:
    """The declared node `name` (UndeclaredKeyError for a name the dataflow does not know)."""
    try:
        return BY_NAME[name]
    except KeyError:
        raise UndeclaredKeyError(f"{name!r} is not a node of the dataflow (semmap/core/dataflow.py)") from None


def service_reports(name: str) -> tuple[str, ...]:
    """The status and progress topics a service writes (the base class publishes them)."""
    return (f"status/{name}/**", f"progress/{name}")


def publishers() -> dict[str, tuple[str, ...]]:
    """Per topic, the roles that may sign a message on it (semmap.core.keys.PUBLISHERS)."""
    owners: dict[str, list[str]] = {}
    for n in NODES:
        for topic in n.outputs:
            owners.setdefault(topic, []).append(n.role)
    return {topic: tuple(roles) for topic, roles in owners.items()}


def message_class(topic: str) -> type:
    """The message class a topic carries (semmap.core.messages), as TOPICS declares it."""
    from semmap.core import messages

    name = next(t.message for t in TOPICS if t.name == topic)
    return getattr(messages, name)


def lockstep_order() -> tuple[str, ...]:
    """The lockstep stages in the order one frame passes them: each after every stage whose output it reads (a
    feedback port excepted), derived from the ports, never restated. The in-process driver runs them so."""
    stages = [n for n in NODES if n.kind == "service" and n.lockstep]
    writers = {topic: n.name for n in stages for topic in n.outputs}
    after = {n.name: {writers[p.topic] for p in n.ports if p.topic in writers and not p.feedback
                      and writers[p.topic] != n.name} for n in stages}
    order: list[str] = []
    while len(order) < len(stages):
        ready = [n.name for n in stages if n.name not in order and after[n.name] <= set(order)]
        if not ready:
            raise ValueError(f"the lockstep stages' ports form a cycle without a feedback port: {after}")
        order.append(ready[0])
    return tuple(order)


def feedback_ports() -> tuple[tuple[str, Port], ...]:
    """(stage, port) of the lockstep stages' feedback inputs, in the order they come back once a frame passed every
    stage: from the last writer up (the backend's corrected poses reach the associator, whose map update, made
    then, reaches the tracker)."""
    order = lockstep_order()
    writers = {topic: n.name for n in NODES if n.kind == "service" and n.lockstep for topic in n.outputs}
    found = [(n.name, p) for n in NODES if n.name in order for p in n.ports if p.feedback]
    return tuple(sorted(found, key=lambda item: -order.index(writers[item[1].topic])))


def check_input(name: str, topic: str) -> None:
    """Raise UndeclaredKeyError unless node `name` declares `topic` among what it reads."""
    if topic not in node(name).reads():
        raise UndeclaredKeyError(f"{name} subscribes to {topic!r}, which semmap/core/dataflow.py does not list "
                                 f"among its inputs {list(node(name).reads())}")


def check_output(name: str, topic: str) -> None:
    """Raise UndeclaredKeyError unless node `name` declares `topic` among what it publishes."""
    if topic not in node(name).outputs:
        raise UndeclaredKeyError(f"{name} publishes on {topic!r}, which semmap/core/dataflow.py does not list "
                                 f"among its outputs {list(node(name).outputs)}")


def wiring_flags(name: str, running: tuple[str, ...] | list[str]) -> list[str]:
    """The flags node `name` gets when the nodes `running` run with it."""
    return [f.flag for f in node(name).flags if all(partner in running for partner in f.with_nodes)]


def player_wait_for(replicas: dict[str, int | str], running: tuple[str, ...] | list[str] | None = None,
                    lockstep: bool = True) -> str:
    """The player's `--wait-for` (lockstep: True) or `--start-after` (the others) list: `name[:replicas]` of the
    nodes that run (default: every stage). A count given as 1 is left out, as `parse_wait_for` reads it."""
    names = PIPELINE if running is None else [n for n in PIPELINE if n in running]
    items = []
    for name in names:
        if BY_NAME[name].lockstep != lockstep:
            continue
        count = str(replicas.get(name, 1))
        items.append(name if count == "1" else f"{name}:{count}")
    return ",".join(items)


# ------------------------------------------------------------------------------------------- docs/DESIGN.md


DOC_BEGIN = "<!-- dataflow: begin (generated by `python -m semmap.core.dataflow --write docs/DESIGN.md`) -->"
DOC_END = "<!-- dataflow: end -->"


def _mermaid_id(topic: str) -> str:
    return "t_" + "".join(c if c.isalnum() else "_" for c in topic)


def mermaid() -> list[str]:
    """The stages and their data topics as a mermaid graph (control, status and progress left out: every
    service has them)."""
    plumbing = {"control", "progress/*", "status/**", "detector/replicas/**"}
    lines = ["```mermaid", "flowchart LR"]
    used = sorted({t for n in NODES if n.kind == "service" for t in (*n.inputs, *n.outputs, *n.asks, *n.answers)}
                  - plumbing)
    for topic in used:
        lines.append(f"    {_mermaid_id(topic)}([{topic}])")
    for n in NODES:
        if n.kind != "service":
            continue
        label = n.name + (f" ×N ({n.replicas})" if n.replicas != "1" else "") + (", lockstep" if n.lockstep else "")
        lines.append(f'    {n.name}["{label}"]')
        lines += [f"    {n.name} --> {_mermaid_id(t)}" for t in n.outputs if t not in plumbing]
        lines += [f"    {_mermaid_id(t)} --> {n.name}" for t in n.inputs if t not in plumbing]
        lines += [f"    {_mermaid_id(t)} -. query .-> {n.name}" for t in n.asks]
        lines += [f"    {n.name} -. answers .-> {_mermaid_id(t)}" for t in n.answers]
    lines.append("```")
    return lines


def _codes(items: tuple[str, ...] | list[str]) -> str:
    return ", ".join(f"`{i}`" for i in items) or "-"


def markdown() -> str:
    """The docs/DESIGN.md section between DOC_BEGIN and DOC_END: the graph, each node's keys and flags, where
    each concept lives, and the topics' messages."""
    out = [DOC_BEGIN, "", *mermaid(), "",
           "| node | reads | writes | asks / answers | replicas | lockstep | wiring flags |",
           "|---|---|---|---|---|---|---|"]
    for n in NODES:
        flags = "; ".join(f"`{f.flag}` with {', '.join(f.with_nodes)}" for f in n.flags) or "-"
        queries = ", ".join([*(f"asks `{t}`" for t in n.asks), *(f"answers `{t}`" for t in n.answers)]) or "-"
        out.append(f"| {n.name} ({n.kind}) | {_codes(n.inputs)} | {_codes(n.outputs)} | {queries} | {n.replicas} "
                   f"| {'yes' if n.lockstep else 'no'} | {flags} |")
    out += ["", "Every service also reads `control` and writes `status/<service>/<instance>` and "
            "`progress/<service>`.", "",
            "| concept | algorithm | stage (semmap.runtime.pipeline.stages) | service | config section | reads "
            "| writes |",
            "|---|---|---|---|---|---|---|"]
    messages = {t.name: t.message for t in TOPICS}
    for n in NODES:
        if n.kind != "service":
            continue
        reads = sorted({messages[t] for t in n.inputs})
        writes = sorted({messages[t] for t in n.outputs})
        out.append(f"| {n.name} | {_codes([n.algorithm] if n.algorithm else [])} "
                   f"| {_codes([n.stage] if n.stage else [])} | `{n.module}.service` "
                   f"| {_codes(n.config)} | {_codes(reads)} | {_codes(writes)} |")
    out += ["", "| topic | message (semmap.core.messages) | what |", "|---|---|---|"]
    out += [f"| `{t.name}` | `{t.message}` | {t.meaning} |" for t in TOPICS]
    out += ["", DOC_END]
    return "\n".join(out)


def with_section(text: str) -> str:
    """`text` (docs/DESIGN.md) with its dataflow section replaced by a fresh `markdown()`."""
    head, begin, rest = text.partition(DOC_BEGIN)
    _, end, tail = rest.partition(DOC_END)
    if not begin or not end:
        raise ValueError(f"no dataflow section ({DOC_BEGIN} ... {DOC_END}) to replace")
    return head + markdown() + tail


def main(argv: list[str] | None = None) -> int:
    """`python -m semmap.core.dataflow` prints the section; `--write FILE` replaces it in FILE."""
    args = sys.argv[1:] if argv is None else argv
    if args[:1] == ["--write"] and len(args) == 2:
        from pathlib import Path

        path = Path(args[1])
        path.write_text(with_section(path.read_text()))
        return 0
    print(markdown())
    return 0


if __name__ == "__main__":
    sys.exit(main())


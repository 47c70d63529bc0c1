"""A hostile peer on an open bus: replays every kind of forged message against a live run.

`python -m tests.security.hostile_peer ENDPOINT --seconds S [--external]` joins the bus as a Zenoh client and,
until S seconds have passed, puts each forged message several times a second in three disguises: unsigned,
signed by another run (its own key and run id), and carrying the live run's id (sniffed from the run's own
status traffic) with a made-up signature. It also holds fake detector liveliness tokens and sends oversized
control messages. `--external` (a `semmap run external`, whose frames, poses and end of stream are open to
unsigned peers): unsigned frames with absurd ids, an unsigned `stop`, and an end of stream for a frame the run
has already passed. It prints what it sent as one JSON line at the end.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import sys
import time

import numpy as np
import zenoh

from semmap.core.keys import Keys
from semmap.core.messages import (
    CandidateUpdate,
    Control,
    CorrectedPoses,
    DepthPatch,
    Detection,
    Detections,
    Frame,
    Intrinsics,
    Landmark,
    MapUpdate,
    Measurement,
    Message,
    Observation,
    Observations,
    OdometryPose,
    Progress,
    ServiceStatus,
    Tracks,
)
from semmap.runtime.transport.bus import BusConfig, RunTrust

ROBOT = "robot1"
INTR = Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)


_FRAMES: dict[int, Frame] = {}


def _frame(frame_id: int) -> Frame:
    if frame_id in _FRAMES:
        return _FRAMES[frame_id]
    rng = np.random.default_rng(frame_id % 1000)
    rgb = rng.integers(0, 255, (480, 640, 3), dtype=np.uint8)
    depth = np.full((480, 640), 1500, np.uint16)
    frame = _FRAMES[frame_id] = Frame.from_arrays(ROBOT, frame_id, frame_id / 30.0, rgb, depth, 0.001, INTR)
    return frame


def _pose(rng: np.random.Generator) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, 3] = rng.uniform(-5, 5, 3)
    return pose


def forged_messages(rng: np.random.Generator) -> list[tuple[str, Message]]:
    """(topic, message) for every kind of forgery (the data ones with plausible frame ids)."""
    keys = Keys(ROBOT)
    patch = DepthPatch(100, 100, 2, np.full((20, 20), 1200, np.uint16))
    det = Detection((100.0, 100.0, 140.0, 140.0), "cup", 0.95, 1.2, patch)
    measurements = [Measurement(f, f / 30.0, det, INTR, 0.001) for f in range(5, 10)]
    tracks = Tracks(
        ROBOT, 10, 10 / 30.0, [CandidateUpdate(900_000 + int(rng.integers(1000)), "cup", measurements, True)], [], []
    )
    observations = Observations(
        ROBOT,
        12,
        0.4,
        [Observation(int(rng.integers(0, 12)), "chair", tuple(rng.uniform(-2, 2, 3)), 0.01, 0.5)],
        [(0, 1), (2, 3), (4, 5)],
    )
    n = 50
    poses = np.stack([_pose(rng) for _ in range(n)])
    corrected = CorrectedPoses(ROBOT, 10_000, 49, np.arange(n, dtype=np.int64), np.arange(n) / 30.0, poses)
    status = ServiceStatus(
        ROBOT, "associator", "associator", "failed", 3, {}, {}, 100.0, 1.0, "forged: the associator lost its map"
    )
    landmark = Landmark(0, "cup", (9.0, 9.0, 9.0), 0.1, (0.1, 0.1, 0.1), 5, 0.0, 1.0)
    out: list[tuple[str, Message]] = [
        (keys.control, Control(ROBOT, "stop")),
        (keys.control, Control(ROBOT, "end_of_stream", 20, 21)),
        (keys.control, Control(ROBOT, "frame_unreadable", 15, 60)),
        (keys.status("associator", "associator"), status),
        (keys.progress("backend"), Progress(ROBOT, "backend", 10_000)),
        (keys.progress("associator"), Progress(ROBOT, "associator", 10_000)),
        (keys.frames, _frame(5000)),
        (keys.frames, _frame(2**40)),
        (keys.odometry, OdometryPose(ROBOT, 11, 11 / 30.0, _pose(rng))),
        (keys.detections, Detections(ROBOT, 11, 11 / 30.0, INTR, 0.001, [det])),
        (keys.tracks, tracks),
        (keys.observations, observations),
        (keys.corrected_poses, corrected),
        (keys.map_updates, MapUpdate(ROBOT, 10_000, 12, 0.4, [landmark], [1, 2], [(3, 4)], False)),
    ]
    return out


class Hostile:
    def __init__(self, endpoint: str, external: bool) -> None:
        self.keys = Keys(ROBOT)
        self.session = zenoh.open(BusConfig(mode="client", connect=[endpoint], listen=[]).to_zenoh())
        self.external = external
        self.sent: dict[str, int] = {}
        self.live_run = ""
        self.newest_progress = -1
        self._pubs: dict[str, zenoh.Publisher] = {}
        self.foreign = RunTrust("a0foreign0run", bytes.fromhex(RunTrust.new_secret()), "player")
        self.session.declare_subscriber(self.keys.status_all, self._sniff)
        self.session.declare_subscriber(self.keys.progress_all, self._sniff_progress)
        liveliness = self.session.liveliness()
        self.tokens = [
            liveliness.declare_token(self.keys.detector_replica("aaa-fake")),
            liveliness.declare_token(self.keys.detector_replica("aaa-fake", "a0foreign0run")),
        ]

    def _sniff(self, sample: zenoh.Sample) -> None:
        """The run's own traffic gives its id away on an open bus (what an eavesdropper would do)."""
        with contextlib.suppress(Exception):  # a hostile peer does not care
            run = ServiceStatus.decode(sample.payload.to_bytes()).run
            if run and run != self.foreign.run_id:  # (not its own forgeries)
                self.live_run = run

    def _sniff_progress(self, sample: zenoh.Sample) -> None:
        with contextlib.suppress(Exception):
            self.newest_progress = max(self.newest_progress, Progress.decode(sample.payload.to_bytes()).frame_id)

    def _put(self, key: str, payload: bytes, attachment: bytes | None, label: str) -> None:
        pub = self._pubs.get(key)
        if pub is None:
            pub = self._pubs[key] = self.session.declare_publisher(key)
        pub.put(payload, attachment=attachment) if attachment is not None else pub.put(payload)
        self.sent[label] = self.sent.get(label, 0) + 1

    def strict_round(self, rng: np.random.Generator) -> None:
        """Every forgery, unsigned, signed by a foreign run, and with the live run's id but a made-up MAC."""
        for key, message in forged_messages(rng):
            message.run = ""
            self._put(key, message.encode(), None, "unsigned")
            message.run = self.foreign.run_id
            payload = message.encode()
            self._put(key, payload, self.foreign.sign(key, payload), "foreign_run")
            if self.live_run:
                message.run = self.live_run
                payload = message.encode()
                fake = RunTrust(self.live_run, os.urandom(32), "player")  # the id is public, the key is not
                self._put(key, payload, fake.sign(key, payload), "bad_signature")
        self._put(self.keys.control, b"\x81" + b"x" * 200_000, None, "oversize")

    def external_round(self) -> None:
        """Against an open-input run: what an unsigned peer may still try on the open keys."""
        self._put(self.keys.frames, _frame(5000).encode(), None, "frame_5000")
        self._put(self.keys.frames, _frame(2**40).encode(), None, "frame_2^40")
        self._put(self.keys.control, Control(ROBOT, "stop").encode(), None, "stop")
        if self.newest_progress >= 30:  # the stream is past frame 20: an end of stream there is a lie
            self._put(self.keys.control, Control(ROBOT, "end_of_stream", 20, 21).encode(), None, "early_eos")

    def run(self, seconds: float) -> None:
        rng = np.random.default_rng(0)
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            if self.external:
                self.external_round()
            else:
                self.strict_round(rng)
            time.sleep(0.1)

    def close(self) -> None:
        for token in self.tokens:
            token.undeclare()
        self.session.close()


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("endpoint")
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--external", action="store_true")
    args = parser.parse_args()
    hostile = Hostile(args.endpoint, args.external)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))  # the test ends us when the run is over
    print("up", flush=True)
    try:
        hostile.run(args.seconds)
    finally:
        print(json.dumps({"sent": hostile.sent, "live_run": hostile.live_run}), flush=True)
        hostile.close()
        os._exit(0)


if __name__ == "__main__":
    main()

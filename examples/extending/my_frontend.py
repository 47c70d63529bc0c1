"""An odometry front end (docs/EXTENDING.md): ground truth whose position drifts by a seeded random walk.

    python examples/extending/my_frontend.py        # registers it, builds `walk:5` by name, runs it on 3 frames

A front end turns each frame into a camera-to-world pose, in frame order, and declares its per-frame sigmas.
`walk:MM` takes an argument (the walk's step in millimetres), needs ground truth and is a simulation, so the run's
banner and summary say "simulated". `state()` / `restore()` let a restarted odometry service continue the walk.
"""

from __future__ import annotations

import json
import math
import sys

import numpy as np

from semmap.algorithms.odometry import check_mode, create_frontend, register
from semmap.algorithms.odometry.frontends import FrontEnd, OdometryError, OdometryInput
from semmap.core.config import ConfigError, OdometryConfig, load_config

NAME = "walk"


class RandomWalkOdometry(FrontEnd):
    """The ground-truth pose, its position moved by a random walk of `step_m` per axis a frame."""

    needs_images = False  # True: the service decodes `rgb` and `depth` into OdometryInput for it
    uses_dynamic = False  # True: it gets the frame's dynamic objects (people...) in `dynamic`

    def __init__(self, step_m: float, seed: int) -> None:
        self.step_m = step_m
        self.rng = np.random.default_rng(seed)
        self.offset = np.zeros(3)
        self.sigmas = (max(step_m, 1e-4), math.radians(0.01))  # declared per frame: translation m, rotation rad

    def estimate(self, frame: OdometryInput) -> np.ndarray:
        if frame.gt_pose is None:
            raise OdometryError(f"frame {frame.frame_id} has no ground-truth pose")
        self.offset += self.rng.normal(0.0, self.step_m, 3)
        pose = frame.gt_pose.copy()
        pose[:3, 3] += self.offset
        return pose

    def state(self) -> dict:  # plain data (msgpack): the generator's 128-bit state travels as JSON text
        return {"offset": self.offset.tolist(), "rng": json.dumps(self.rng.bit_generator.state)}

    def restore(self, state: dict) -> None:
        self.offset = np.asarray(state["offset"], float)
        self.rng.bit_generator.state = json.loads(state["rng"])


def create(section: OdometryConfig, argument: str) -> FrontEnd:
    """`walk:MM` with the `odometry` section (its `seed`)."""
    try:
        step_mm = float(argument)
    except ValueError:
        raise ConfigError(f"odometry.mode: walk:MM takes a step in millimetres, got {argument!r}") from None
    return RandomWalkOdometry(step_mm / 1000.0, section.seed)


register(NAME, create, "SIMULATED: ground truth with a random walk of MM millimetres a frame (examples/extending)",
         takes_argument=True, needs_groundtruth=True, simulated=True)


def main() -> int:
    section = load_config(None, [f"odometry.mode={NAME}:5", "odometry.seed=3"]).odometry
    kind, argument = check_mode(section.mode)  # what `semmap run` checks before it starts anything
    assert kind.simulated and kind.needs_groundtruth and argument == "5"
    front_end = create_frontend(section.mode, section)
    poses = []
    for i in range(3):
        gt = np.eye(4)
        gt[0, 3] = 0.01 * i  # the camera moves 1 cm a frame along x
        poses.append(front_end.estimate(OdometryInput(frame_id=i, stamp=i / 30.0, gt_pose=gt)))
    again = create_frontend(section.mode, section)
    again.restore(front_end.state())  # a restarted service continues the same walk
    print([p[:3, 3].round(4).tolist() for p in poses], front_end.sigmas)
    assert np.allclose(again.offset, front_end.offset)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""For the tests of map sessions: where a second session's odometry frame lies, drawn at random (seeded),
and what a relocalised map must keep of its prior map.

Why drawn: a check against one fixed offset and drift seed can pass where another rigid offset moves prior
landmarks and loses a class. A draw is a few metres of translation (1-3.5 m on x
and y, up to 0.6 m on z), 25-40 degrees about one axis (which one is drawn too) and 5-15 about the other two,
and a `gt+drift` seed other than the fixed case's (1, benchmarks/bench_sessions.py's default).
"""

from __future__ import annotations

import math

import numpy as np

from semmap.core.messages import Detections, Landmark
from semmap.runtime.pipeline.inprocess import ROBOT, Recording
from tests.associator.helpers import K_SMALL, Sphere, detections, orbit_pose


def orbit_recording(frames: int, spheres: list[Sphere]) -> Recording:
    """The analytic orbit around `spheres` at 30 Hz as the in-process driver's recording (detections, truth)."""
    dets, gt = [], []
    for f in range(frames):
        pose = orbit_pose(f / 30.0)
        dets.append(Detections(ROBOT, f, f / 30.0, K_SMALL, 0.001, detections(pose, spheres)))
        gt.append(pose)
    return Recording("analytic orbit", dets, gt)


def draw_session(rng: np.random.Generator) -> tuple[list[float], int]:
    """(frame offset [x, y, z m, roll, pitch, yaw deg], drift seed): one draw (module docstring)."""
    signs = rng.choice([-1.0, 1.0], 6)
    xyz = rng.uniform(1.0, 3.5, 3) * signs[:3]
    xyz[2] = rng.uniform(-0.6, 0.6)
    angles = rng.uniform(5.0, 15.0, 3) * signs[3:]
    big = int(rng.integers(3))
    angles[big] = rng.uniform(25.0, 40.0) * signs[3 + big]
    seed = int(rng.integers(2, 1000))
    return [round(float(v), 2) for v in (*xyz, *angles)], seed


def draws(seed: int, n: int) -> list[tuple[list[float], int]]:
    """`n` draws from one seeded generator (the tests' seeds are fixed, so a failure reproduces)."""
    rng = np.random.default_rng(seed)
    return [draw_session(rng) for _ in range(n)]


def lined_up(before: list[Landmark], after: list[Landmark]) -> tuple[int, list[tuple[int, int]], list[str]]:
    """(prior landmarks within 10 cm of their prior place, duplicates (new id, prior id), classes lost): a new
    landmark of a prior one's class within 0.3 m of it is a duplicate; a class is lost when no landmark has it."""
    now = {lm.id: lm for lm in after}
    prior = {lm.id for lm in before}
    kept = sum(lm.id in now and math.dist(lm.centroid, now[lm.id].centroid) <= 0.10 for lm in before)
    dup = [
        (n.id, p.id)
        for n in after
        if n.id not in prior
        for p in after
        if p.id in prior and p.class_name == n.class_name and math.dist(p.centroid, n.centroid) < 0.3
    ]
    return kept, dup, sorted({lm.class_name for lm in before} - {lm.class_name for lm in after})

"""Time settings that fall on the 30 Hz frame grid (observation period 1 s = 30 frames, view interval 0.1 s = 3,
tracker max age 0.5 s = 15, ...) give the same decisions however the frames are stamped: n/30 s, ROS nanoseconds,
Unix seconds. Float rounding of a stamp difference must not decide (semmap.core.stamps)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from semmap.algorithms.associator.mapper import LandmarkMapper, MapperParams, MapperStep
from semmap.algorithms.tracker.iou_tracker import IouTracker
from tests.associator.helpers import K_SMALL, Sphere, detections, orbit_pose

RATE = 30.0
T0 = 1311868164.0  # a TUM-like Unix time
THINGS = [Sphere((-0.2, 0.0, 0.8), 0.05, "cup"), Sphere((0.2, 0.1, 0.8), 0.06, "bowl")]
SOURCES: dict[str, Callable[[int], float]] = {
    "n/30": lambda n: n / RATE,
    "ros_ns": lambda n: round(n / RATE * 1e9) / 1e9,
    "unix": lambda n: T0 + n / RATE,
    "unix_us": lambda n: float(f"{T0 + n / RATE:.6f}"),
}


def run(stamp_of: Callable[[int], float], frames: range, params: MapperParams | None = None) -> list[MapperStep]:
    """The scene seen along the orbit (poses from frame numbers, so every source sees the same images); the
    tracker and the mapper get the source's stamps."""
    mapper, tracker = LandmarkMapper(params or MapperParams()), IouTracker()
    steps = []
    for f in frames:
        dets = detections(orbit_pose(f / RATE), THINGS)
        out = tracker.update(f, stamp_of(f), dets, K_SMALL, 0.001)
        steps.append(mapper.process(f, stamp_of(f), out.candidates, out.ended, lambda i: orbit_pose(i / RATE)))
    steps.append(mapper.refine(lambda i: orbit_pose(i / RATE)))
    return steps


def decisions(steps: list[MapperStep]) -> list:
    """Everything the mapper decided, per frame: which landmarks it updated (ids, classes, measurement counts,
    centroids to 0.1 mm), which it removed, which it sent observations of."""
    out = []
    for s in steps:
        out.append(
            (
                sorted((u.id, u.class_name, u.observations, tuple(np.round(u.centroid, 4))) for u in s.updated),
                sorted(s.removed),
                [o.landmark_id for o in s.observations],
            )
        )
    return out


@pytest.mark.parametrize("start", [0, 7, 29])
def test_observations_come_every_30_frames_with_a_1_s_period(start: int) -> None:
    """observation_period_s = 1 s: one observation per landmark every 30 frames, never 31 (float noise once
    read (n + 30) / 30 - n / 30 < 1.0 for 30 of the first 300 frames)."""
    frames = range(start, start + 240)
    steps = run(SOURCES["n/30"], frames, MapperParams(observation_period_s=1.0))
    per_landmark: dict[int, list[int]] = {}
    for f, s in zip(frames, steps, strict=False):  # the last step is the final refine()
        for o in s.observations:
            per_landmark.setdefault(o.landmark_id, []).append(f)
    assert len(per_landmark) == 2
    for sent in per_landmark.values():
        assert len(sent) >= 5
        assert set(np.diff(sent).tolist()) == {30}, sent


def test_the_same_scene_stamped_four_ways_maps_the_same() -> None:
    ref = run(SOURCES["n/30"], range(200))
    assert any(s.observations for s in ref) and any(s.updated for s in ref)
    for name, stamp_of in SOURCES.items():
        if name != "n/30":
            assert decisions(run(stamp_of, range(200))) == decisions(ref), name

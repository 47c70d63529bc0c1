"""A SLAM's refinement of its own trajectory at its end, taken into semmap's odometry where it can be trusted.

ORB-SLAM3 keeps bundle-adjusting its keyframes after it has returned a frame's pose, and at its end it saves each
frame relative to its refined keyframe: better than the poses it returned while tracking (7-Scenes: 0.047 against
0.050 m). That saved trajectory is what a user of ORB-SLAM3 alone gets, so semmap's result must start from it to
be no worse than the SLAM alone. Pure computation on poses.

- **Which steps.** Only the steps the output took from the SLAM itself: a step semmap's registration or the motion
  model decided stays as it was (the SLAM's refinement of a step it got wrong is no better than the step).
- **Which runs.** Not where objects were seen moving and semmap overruled the SLAM: people dragged it, so its map
  held points on them wherever the masks missed some, and the bundle adjustment, which fits the whole map, spreads
  their pull over the trajectory (Bonn crowd: taking its refined steps turned 0.048 m into 0.071 m). Spliced in
  only between the walkers, its steps do not fit the repaired ones around them either: the whole run or none of it.
  An object seen moving that never made semmap overrule a step (a false box flickering on a static scene) is no
  sign of a dragged map, and does not withhold it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from itertools import pairwise

import numpy as np

from semmap.core.messages import OdometryRefinement


@dataclass
class Refinement:
    """The odometry poses of the frames the refinement moved (frame ids ascending; the front end's output frame),
    or none and `withheld`: why it was not taken."""

    frame_ids: list[int] = field(default_factory=list)
    poses: list[np.ndarray] = field(default_factory=list)
    withheld: str = ""

    def message(self, robot: str, source: str, to_session: np.ndarray | None = None) -> OdometryRefinement:
        """As the odometry sends it (`odometry/refined`), its poses in the session's world (`to_session`)."""
        poses = [pose if to_session is None else to_session @ pose for pose in self.poses]
        return OdometryRefinement(robot, source, np.asarray(self.frame_ids, np.int64),
                                  np.array(poses, dtype=np.float64).reshape(-1, 4, 4), withheld=self.withheld)


@dataclass(frozen=True)
class OutputStep:
    """One measured frame of the odometry's output: its pose and whether the step to it was the SLAM's own."""

    frame_id: int
    stamp: float
    pose: np.ndarray
    slam_own: bool


def refine_outputs(outputs: list[OutputStep], refined: list[tuple[float, np.ndarray]], moving_seen: int,
                   overruled: int) -> Refinement:
    """The output chained again with each of the SLAM's own steps replaced by its refined step (both ends in the
    refined trajectory `refined`: (stamp, pose) in the output's world), the others kept; the first pose stays.
    Withheld where `moving_seen` objects were seen moving and semmap `overruled` some of the SLAM's steps, or
    where there is no refinement (module docstring)."""
    if not refined:
        return Refinement(withheld="the SLAM saved no refinement (it lost its map, restarted, or could not save)")
    if moving_seen and overruled:
        return Refinement(withheld=f"{moving_seen} object(s) were seen moving and semmap overruled {overruled} of "
                                   "the SLAM's steps: its map may hold points on them, and its refinement with it")
    by_stamp = {round(t, 6): pose for t, pose in refined}
    result = Refinement()
    if not outputs:
        return result
    chained = outputs[0].pose
    for previous, step in pairwise(outputs):
        a, b = by_stamp.get(round(previous.stamp, 6)), by_stamp.get(round(step.stamp, 6))
        own = step.slam_own and a is not None and b is not None
        chained = chained @ (np.linalg.inv(a) @ b if own else np.linalg.inv(previous.pose) @ step.pose)
        result.frame_ids.append(step.frame_id)
        result.poses.append(chained)
    return result

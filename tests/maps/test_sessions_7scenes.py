"""Two sessions of 7-Scenes redkitchen through the real pipeline (issue 19's first done-when, the part reached).

Session 1 maps frames 0-499 on ground-truth odometry (so the prior map is in the ground truth's frame, and the
recovered transform can be judged against it); session 2 plays frames 500-999 with `gt+drift` odometry in a
frame moved by 2 m, 1.5 m, 0.4 m and 4, -6, 35 degrees, with `--map` session 1. It must relocalise with the
transform within 10 cm and 3 degrees of the truth (the offset, judged at the camera of the fit's frame), map
no duplicate of a prior landmark, and its optimised trajectory must lie in the
prior frame. Measured and documented in docs/MAPS.md ("Measured"); `benchmarks/bench_sessions.py` adds the
comparison with a single 1000-frame run (not yet within 10 cm for every object, so not asserted here).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from semmap.algorithms.odometry.frontends import frame_offset
from semmap.algorithms.relocalize import rotation_angle_deg
from semmap.datasets.trajectory_io import read_tum
from semmap.runtime.map_store import read_map_json

pytestmark = [pytest.mark.slow, pytest.mark.needs_data, pytest.mark.needs_model]
OFFSET = [2.0, -1.5, 0.4, 4.0, -6.0, 35.0]
COMMON = ["--no-viz", "--set", "detector.precision=int8"]


@pytest.fixture(scope="module")
def sessions(kitchen_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    from semmap.runtime.model_store import ModelMissingError, packaged_model
    from tests.conftest import _semmap_run

    try:
        packaged_model("int8")
    except ModelMissingError as exc:
        pytest.skip(str(exc))
    root = tmp_path_factory.mktemp("kitchen_sessions")
    s1, s2 = root / "s1", root / "s2"
    offset = "odometry.frame_offset=[" + ",".join(str(v) for v in OFFSET) + "]"
    second = ["--start-frame", "500", "--seed", "1", "--odometry", "gt+drift", "--set", offset, "--map", str(s1)]
    runs = [
        ("session 1", [str(kitchen_dir), "--out", str(s1), "--max-frames", "500", "--odometry", "gt", *COMMON]),
        ("session 2", [str(kitchen_dir), "--out", str(s2), *second, *COMMON]),
    ]
    for name, args in runs:
        result = _semmap_run(args, timeout=1500)
        assert result.returncode == 0, f"{name}: {result.stderr[-3000:]}"
    return {"s1": s1, "s2": s2}


def test_second_session_relocalises_within_10_cm_and_3_degrees(sessions: dict[str, Path]) -> None:
    """The truth is the rigid transform the session's poses are given in (issue 19: "a rigid transform ... plus
    gt+drift drift"), judged at the camera of the fit's frame. Not the drifted odometry's transform at that frame:
    the fit places landmarks mapped over the frames before it, and the drift jumps by 2 degrees between frames 20
    and 35 of this window (measured: the fit is 1.2 deg / 7 cm off the offset, 3.2 deg off the frame-35 drift)."""
    s2 = sessions["s2"]
    fit = json.loads((s2 / "relocalization.json").read_text())
    assert fit["inliers"] >= 4 and fit["refined_on_clouds"]
    T = np.array(fit["transform"]).reshape(4, 4)
    offset = frame_offset(OFFSET)
    _, pose = read_tum(s2 / "trajectory_odometry.tum")[fit["frame_id"]]
    camera = pose[:3, 3]
    deg = rotation_angle_deg((np.linalg.inv(offset) @ T)[:3, :3])
    metres = float(np.linalg.norm(T[:3, :3] @ camera + T[:3, 3] - (offset[:3, :3] @ camera + offset[:3, 3])))
    assert deg <= 3.0 and metres <= 0.10, (deg, metres, fit["frame_id"])
    # and the session's first pose, where the odometry has not drifted yet, agrees with the truth there
    stamp, first = read_tum(s2 / "trajectory_odometry.tum")[0]
    truth = {round(t, 4): p for t, p in read_tum(s2 / "groundtruth.tum")}
    at_start = truth[round(stamp, 4)] @ np.linalg.inv(first)
    assert rotation_angle_deg((np.linalg.inv(at_start) @ T)[:3, :3]) <= 3.0


def test_no_duplicate_of_a_prior_landmark_and_the_trajectory_in_the_prior_frame(sessions: dict[str, Path]) -> None:
    prior_ids = {lm.id for lm in read_map_json(sessions["s1"] / "map.json")}
    s2 = read_map_json(sessions["s2"] / "map.json")
    assert prior_ids <= {lm.id for lm in s2}
    dup = [
        (n.id, p.id)
        for n in s2
        if n.id not in prior_ids
        for p in s2
        if p.id in prior_ids and p.class_name == n.class_name and math.dist(p.centroid, n.centroid) < 0.3
    ]
    assert dup == []
    gt = {round(t, 4): p for t, p in read_tum(sessions["s2"] / "groundtruth.tum")}
    opt = read_tum(sessions["s2"] / "trajectory_optimized.tum")
    err = [np.linalg.norm(p[:3, 3] - gt[round(t, 4)][:3, 3]) for t, p in opt if round(t, 4) in gt]
    # measured 8-10 cm (docs/MAPS.md); the odometry alone, in its own frame, is metres away
    assert len(err) == 500 and math.sqrt(np.mean(np.square(err))) < 0.15

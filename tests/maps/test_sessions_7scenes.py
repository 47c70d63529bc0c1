"""Two sessions of 7-Scenes redkitchen through the real pipeline.

The first session maps frames 0-499 on ground-truth odometry (so the prior map is in the ground truth's frame, and the
recovered transform can be judged against it); the second session plays frames 500-999 with `gt+drift` odometry in a
frame of its own, with `--map` the first session. The frame offset and the drift seed are drawn at random, seeded
(tests/maps/session_checks.py: a few metres, 25-40 degrees about one axis, 5-15 about the others): one fixed
case (2, -1.5, 0.4 m, 4, -6, 35 degrees, seed 1) can pass where another offset and seed move prior landmarks
12-15 cm and lose the microwave. It must relocalise with the transform within 10 cm and 3 degrees of
the truth, map no duplicate of a prior landmark, keep >= 11 of the first session's 13 objects (the same share of however
many it maps) within 10 cm of their session-1 places and lose none of its classes, its optimised trajectory must
lie in the prior frame, and its final map must hold the objects of one 1000-frame run. The second session run alone and
merged with the first session by `semmap merge` must give the relocalised run's landmarks. Measured and documented in
docs/MAPS.md ("Measured"); `benchmarks/bench_sessions.py` prints the same figures.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from semmap.algorithms.associator.params import MapperParams
from semmap.algorithms.odometry.frontends import frame_offset
from semmap.algorithms.relocalize import rotation_angle_deg
from semmap.datasets.trajectory_io import read_tum
from semmap.runtime.maps.map_store import read_map_json
from tests.maps.session_checks import draws, lined_up

pytestmark = [pytest.mark.slow, pytest.mark.needs_data, pytest.mark.needs_model]
OFFSET, DRIFT_SEED = draws(1934, 1)[0]  # (-3.16, -2.12, 0.51 m, 6.25, -27.01, -8.03 degrees; seed 963)
# fp32 (lockstep's default): int8 agrees with fp32 only on CPUs with VNNI; on an AVX2-only CPU its
# detections lose objects and the two sessions' maps no longer register by their objects
COMMON = ["--no-viz"]


@pytest.fixture(scope="module")
def sessions(kitchen_dir: Path, kitchen_gt_run: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    from semmap.runtime.models.model_store import ModelMissingError, packaged_model
    from tests.conftest import _semmap_run

    try:
        packaged_model("fp32")
    except ModelMissingError as exc:
        pytest.skip(str(exc))
    root = tmp_path_factory.mktemp("kitchen_sessions")
    out = {name: root / name for name in ("s1", "s2", "s2_alone", "merged")}
    out["full"] = kitchen_gt_run  # the 1000-frame run on gt odometry, no viewer: shared with tests/pipeline
    offset = "odometry.frame_offset=[" + ",".join(str(v) for v in OFFSET) + "]"
    second = ["--start-frame", "500", "--seed", str(DRIFT_SEED), "--odometry", "gt+drift", "--set", offset]
    runs = [
        ("first session",
         [str(kitchen_dir), "--out", str(out["s1"]), "--max-frames", "500", "--odometry", "gt", *COMMON]),
        ("second session", [str(kitchen_dir), "--out", str(out["s2"]), *second, "--map", str(out["s1"]), *COMMON]),
        ("second session alone", [str(kitchen_dir), "--out", str(out["s2_alone"]), *second, *COMMON]),
    ]
    for name, args in runs:
        result = _semmap_run(args, timeout=1500)
        assert result.returncode == 0, f"{name}: {result.stderr[-3000:]}"
    merge = subprocess.run(
        [
            sys.executable,
            "-m",
            "semmap.cli",
            "merge",
            str(out["s1"]),
            str(out["s2_alone"]),
            "--out",
            str(out["merged"]),
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert merge.returncode == 0, merge.stderr
    return out


def test_second_session_relocalises_within_10_cm_and_3_degrees(sessions: dict[str, Path]) -> None:
    """The truth is the rigid transform the session's poses are given in (a rigid transform plus the
    gt+drift drift), judged at the camera of the fit's frame. Not the drifted odometry's transform at that frame:
    the fit places landmarks mapped over the frames before it, and the drift can turn fast (with the old fixed
    case, seed 1, by 2 degrees between frames 20 and 35: the fit was 1.2 deg / 7 cm off the offset, 3.2 deg off the
    frame-35 drift)."""
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
    # the transform the session ends with (its keyframes registered to the first session's) places that frame's camera
    # within 10 cm and 3 degrees even against the drift gathered by then (measured on this draw 1.35 deg, 3.0 cm;
    # the object fit alone: 2.5 deg; the old fixed case: 1.7 deg, 3.5 cm, the fit alone 3.2 deg)
    stamp, _ = read_tum(s2 / "trajectory_odometry.tum")[fit["frame_id"]]
    optimised = {round(t, 4): p for t, p in read_tum(s2 / "trajectory_optimized.tum")}[round(stamp, 4)]
    final, at_frame = optimised @ np.linalg.inv(pose), truth[round(stamp, 4)] @ np.linalg.inv(pose)
    assert rotation_angle_deg((np.linalg.inv(at_frame) @ final)[:3, :3]) <= 3.0
    assert np.linalg.norm(final[:3, :3] @ camera + final[:3, 3] - (at_frame[:3, :3] @ camera + at_frame[:3, 3])) < 0.1
    # which the backend writes next to the object fit
    written = json.loads((s2 / "relocalization_final.json").read_text())
    assert written["frame_id"] == fit["frame_id"] and written["prior_keyframe_closures"] >= 10
    np.testing.assert_allclose(np.array(written["transform"]).reshape(4, 4), final, atol=1e-4)
    backend = json.loads((s2 / "stats.json").read_text())["services"]["backend"]["counters"]
    assert backend["prior_keyframes"] >= 40 and backend["loop_prior_accepted"] >= 10, backend


def test_no_duplicate_of_a_prior_landmark_and_the_trajectory_in_the_prior_frame(sessions: dict[str, Path]) -> None:
    s1 = read_map_json(sessions["s1"] / "map.json")
    s2 = read_map_json(sessions["s2"] / "map.json")
    assert {lm.id for lm in s1} <= {lm.id for lm in s2}
    assert lined_up(s1, s2)[1] == []
    gt = {round(t, 4): p for t, p in read_tum(sessions["s2"] / "groundtruth.tum")}
    opt = read_tum(sessions["s2"] / "trajectory_optimized.tum")
    err = [np.linalg.norm(p[:3, 3] - gt[round(t, 4)][:3, 3]) for t, p in opt if round(t, 4) in gt]
    # measured 4.3 cm on this draw (5.2 cm on the old fixed case, 8-10 cm before the keyframes registered to
    # the first session's); the odometry alone, in its own frame, is metres away
    assert len(err) == 500 and math.sqrt(np.mean(np.square(err))) < 0.08


def _paired(a: list, b: list, confusable: bool = False) -> tuple[list[float], list, list]:  # noqa: ANN001
    """One-to-one pairs of one class (or, with `confusable`, of classes the mapper takes for one object:
    `confusable_classes`), nearest first, within 0.5 m: their distances, and what either has left."""
    groups = [set(g.split("|")) for g in MapperParams().confusable_classes.split(";")]

    def same(x: str, y: str) -> bool:
        return x == y or (confusable and any(x in g and y in g for g in groups))

    cand = sorted(
        (math.dist(x.centroid, y.centroid), i, j)
        for i, x in enumerate(a)
        for j, y in enumerate(b)
        if same(x.class_name, y.class_name)
    )
    used_a, used_b, dist = set(), set(), []
    for d, i, j in cand:
        if i not in used_a and j not in used_b and d < 0.5:
            used_a.add(i)
            used_b.add(j)
            dist.append(d)
    return dist, [x for i, x in enumerate(a) if i not in used_a], [y for j, y in enumerate(b) if j not in used_b]


def test_session_1s_objects_keep_their_places_and_classes(sessions: dict[str, Path]) -> None:
    """>= 11 of the first session's 13 objects (that share of however many it maps) within 10 cm of their session-1
    places in the relocalised map, no duplicate, no class of the first session lost. Without the prior anchor, on two
    other
    offsets and seeds: 11 and 10 of 13, the microwave a laptop; with it: 13 of 13 (docs/MAPS.md). Measured
    on this draw: 13 of 13 (the farthest 1.3 cm from its place in process)."""
    s1 = read_map_json(sessions["s1"] / "map.json")
    kept, dup, lost = lined_up(s1, read_map_json(sessions["s2"] / "map.json"))
    assert kept * 13 >= 11 * len(s1) and not dup and not lost, (kept, len(s1), dup, lost)


def test_the_final_map_holds_the_objects_of_one_1000_frame_run(sessions: dict[str, Path]) -> None:
    """Every object of one 1000-frame run is in the relocalised map and nothing else, one to one; the landmarks
    the second session mapped itself lie within 10 cm of the 1000-frame run's (without the prior anchor: 16 of 16,
    median
    1.9, max 9.9 cm, one object over the run-to-run margin allowed). The first session's landmarks hold their session-1
    places, so against the 1000-frame run they are as far as the first session's own partial views put them from all
    1000
    frames' (measured: the screen 23 cm, the table and a book 12 cm): within the 0.5 m pairing, not bounded here.
    Classes pair where the mapper takes them for one object: the 1000-frame run elects the microwave a laptop from
    both halves' boxes, the relocalised map keeps the first session's microwave. Measured on this draw: 16 of 16 paired,
    the second session's own 3 within 8.1 cm."""
    prior = {lm.id for lm in read_map_json(sessions["s1"] / "map.json")}
    s2 = read_map_json(sessions["s2"] / "map.json")
    full = read_map_json(sessions["full"] / "map.json")
    _, only_s2, only_full = _paired(s2, full, confusable=True)
    assert not only_s2 and not only_full, (only_s2, only_full)
    dist, _, _ = _paired([lm for lm in s2 if lm.id not in prior], full, confusable=True)
    assert dist and sum(d > 0.10 for d in dist) <= 1 and max(dist) < 0.15, dist


def test_merge_of_the_two_sessions_gives_the_relocalised_runs_landmarks(sessions: dict[str, Path]) -> None:
    """Without the prior anchor (the fixed offset): 15 paired, all within 10 cm (max 4.4 cm); the relocalised run
    had one more, a laptop seen 13 times at the end of the second session, whose tracklet (7 views in 1 s) missed the
    static
    test for short tracklets by a hair under the second session alone's own poses: a merge fuses only what both maps
    hold. A
    merge holds A's places as the relocalised run holds the prior's, so the pairs agree: measured on this
    draw 16 paired, all within 3.3 cm (median 0.1), and the merge's one more, the laptop below."""
    dist, only_merged, only_s2 = _paired(
        read_map_json(sessions["merged"] / "map.json"), read_map_json(sessions["s2"] / "map.json")
    )
    # a merge pairs one class only: the second session alone calls the microwave a laptop, which joins beside the first
    # session's
    # microwave (the relocalised run, which keeps the microwave, has no such laptop); at most one either side
    assert len(only_merged) <= 1 and len(only_s2) <= 1, (only_merged, only_s2)
    assert max(dist) < 0.10, dist


def test_merging_the_relocalised_run_itself_keeps_its_landmarks(sessions: dict[str, Path], tmp_path: Path) -> None:
    """The second session was started from the first session's map: its odometry is in its own frame, its map in the
    first session's. The
    replay must take its odometry through its own alignment too (measured: 16 of 16 within 4.3 cm; on this draw,
    with the prior places held in both, within 1.4 cm)."""
    merge = subprocess.run(
        [sys.executable, "-m", "semmap.cli", "merge", str(sessions["s1"]), str(sessions["s2"]), "--out", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert merge.returncode == 0 and "re-optimised in A's frame" in merge.stderr, merge.stderr
    dist, only_merged, only_s2 = _paired(
        read_map_json(tmp_path / "map.json"), read_map_json(sessions["s2"] / "map.json")
    )
    # (without the prior anchor the relocalised run loses the first session's microwave, which comes back from the
    # first session's
    # map: one more in the merge)
    assert len(only_merged) <= 1 and not only_s2 and max(dist) < 0.10, (dist, only_merged, only_s2)

"""The pieces of `semmap run --map` without a bus: the pose book's turn to the prior frame, the backend's
rebuild in the prior frame with anchored landmarks, the missing test of prior landmarks, the dataset window,
the session frame offset and the CLI's checks of --map."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from semmap.algorithms.associator.landmark_map import LandmarkMap
from semmap.algorithms.associator.pose_book import PoseBook
from semmap.algorithms.associator.prior_map import PriorParams, PriorSession
from semmap.algorithms.backend.pose_graph import PoseGraph
from semmap.algorithms.backend.prior_alignment import PriorAlignment
from semmap.algorithms.odometry.frontends import OdometryError, frame_offset
from semmap.core.geometry import look_at
from semmap.core.messages import (
    CorrectedPoses,
    Intrinsics,
    MapAlignment,
    Observation,
    Observations,
    OdometryPose,
    TrackedBox,
)
from semmap.datasets import open_dataset
from semmap.datasets.base import DatasetError, WindowDataset
from semmap.runtime.maps.map_store import MapStore

PROJECT = Path(__file__).resolve().parents[2]
OFFSET = frame_offset([1.0, -2.0, 0.5, 0.0, 0.0, 30.0])


def test_frame_offset() -> None:
    assert np.allclose(frame_offset([0] * 6), np.eye(4))
    T = frame_offset([1, 2, 3, 0, 0, 90])
    assert np.allclose(T[:3, 3], [1, 2, 3]) and np.allclose(T[:3, :3] @ [1, 0, 0], [0, 1, 0])
    for bad in ([1, 2, 3], "x", [0, 0, 0, 0, 0, float("nan")], [0, 0, 0, 0, 0, "a"]):
        with pytest.raises(OdometryError):
            frame_offset(bad)


def test_pose_book_turns_to_the_prior_frame() -> None:
    book = PoseBook()
    odom = {f: look_at(np.array([0.1 * f, 0.0, 1.0]), np.array([0.1 * f, 2.0, 1.0])) for f in range(10)}
    book.odometry.update(odom)
    ids = np.arange(5)
    book.set_corrected(CorrectedPoses("r", 1, 4, ids, ids / 30.0, np.stack([odom[f] for f in ids])))
    book.align(OFFSET, from_frame=6)
    for f in range(10):  # corrected, interpolated and plain odometry all land in the prior frame
        assert np.allclose(book(f), OFFSET @ odom[f])
    # a correction the backend sent before it realigned is still in the session frame; one after is not
    book.set_corrected(CorrectedPoses("r", 2, 5, ids, ids / 30.0, np.stack([odom[f] for f in ids])))
    assert np.allclose(book(3), OFFSET @ odom[3])
    book.set_corrected(CorrectedPoses("r", 3, 6, ids, ids / 30.0, np.stack([OFFSET @ odom[f] for f in ids])))
    assert np.allclose(book(3), OFFSET @ odom[3])
    restored = PoseBook.from_state(book.to_state())
    assert np.allclose(restored(9), OFFSET @ odom[9])


def _observe(pose: np.ndarray, point: np.ndarray, lid: int) -> Observation:
    p = pose[:3, :3].T @ (point - pose[:3, 3])
    return Observation(lid, "cup", (float(p[0]), float(p[1]), float(p[2])), 0.02, 0.1)


def test_backend_rebuilds_in_the_prior_frame_and_anchors_pull_the_trajectory() -> None:
    """The session's odometry is in its own frame; the alignment carries a transform 5 cm / 1 degree off the
    truth and the prior landmarks' true places: after the rebuild the trajectory sits in the prior frame, and the
    anchors remove most of what the fit got wrong."""
    landmarks = {i: np.array(p, float) for i, p in enumerate([(0, 3, 1), (2, 3, 0.5), (-2, 3, 1.5), (1, 4, 2)])}
    truth = [look_at(np.array([0.05 * f - 1, 0.0, 1.0]), np.array([0.0, 3.0, 1.0])) for f in range(60)]
    session = [np.linalg.inv(OFFSET) @ p for p in truth]
    fit_error = frame_offset([0.05, 0.0, 0.0, 0.0, 0.0, 1.0])
    alignment = MapAlignment(OFFSET @ fit_error, [(i, tuple(p)) for i, p in landmarks.items()], 0.01, 4, 0.03)
    aligner, graph = PriorAlignment(), PoseGraph()
    for f, pose in enumerate(session):
        obs = Observations("r", f, f / 30, [_observe(truth[f], landmarks[i], i) for i in landmarks])
        if f == 20:
            obs.alignment = alignment
            graph = aligner.realign(graph, alignment)
        aligner.add(graph, OdometryPose("r", f, f / 30, pose, True, 0.001, 0.001, "gt"), obs)
        graph.update()
    ids, _, poses = graph.corrected_poses()
    err = [np.linalg.norm(poses[i][:3, 3] - truth[f][:3, 3]) for i, f in enumerate(ids)]
    assert max(err) < 0.02, max(err)  # the fit was 5 cm and 1 degree (5 cm at 3 m) off
    assert graph.counters["anchors"] == 4


def _prior(n: int = 3) -> LandmarkMap:
    m = LandmarkMap()
    for i in range(n):
        lm = m.create("cup", 0.0)
        lm.centroid = np.array([0.4 * i - 0.4, 0.0, 2.0])
        lm.size = 0.2
    return m


K = Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)


def _session(prior: LandmarkMap, detected_from: np.ndarray | None = None) -> tuple[PriorSession, object]:
    """A relocalised session over `prior`, each landmark with one view: detected by a camera at
    `detected_from` (default: the origin, where the tests' camera stands)."""
    from types import SimpleNamespace

    from semmap.algorithms.associator.mapper import LandmarkMapper

    s = PriorSession(prior, PriorParams(missing_after_frames=3))
    s.transform = np.eye(4)  # relocalised (identity frame) for the test
    mapper = LandmarkMapper()
    mapper.adopt_landmarks(prior.all())
    pose = np.eye(4)
    if detected_from is not None:
        pose[:3, 3] = detected_from
    for lm in mapper.map.all():  # a view so it counts as a mapped object
        lm.views = [SimpleNamespace(pose=pose)]  # type: ignore[list-item]
    return s, mapper


def test_prior_landmark_in_view_and_undetected_goes_missing_only_after_several_frames() -> None:
    s, mapper = _session(_prior())
    camera = np.eye(4)  # looking down +z at the three cups 2 m away
    seen = [TrackedBox(1, "cup", (140.0, 200.0, 260.0, 280.0), 5, True)]  # a box on the first cup only
    for frame in range(2):
        assert s.update(mapper, frame, camera, seen, K, touched=[]) == []
    assert s.update(mapper, 2, camera, seen, K, touched=[]) == [1, 2]
    assert s.status == {0: "prior", 1: "missing", 2: "missing"}
    assert s.update(mapper, 3, camera, seen, K, touched=[2]) == [2]  # associated again: present
    assert s.status[2] == "present"


def test_a_landmark_looked_at_from_a_side_never_detected_is_not_missing() -> None:
    """Detectors find many objects from some sides only: misses count only from directions it was detected from."""
    s, mapper = _session(_prior(), detected_from=np.array([0.0, 0.0, 4.0]))  # seen from behind the cups only
    for frame in range(20):
        s.update(mapper, frame, np.eye(4), [], K, touched=[])
    assert set(s.status.values()) == {"prior"}
    s, mapper = _session(_prior(), detected_from=np.array([0.3, 0.4, -0.5]))  # ~15 degrees off: it counts
    for frame in range(3):
        s.update(mapper, frame, np.eye(4), [], K, touched=[])
    assert set(s.status.values()) == {"missing"}


def test_a_box_of_a_class_the_landmark_was_ever_detected_as_counts_as_seen() -> None:
    s, mapper = _session(_prior(1))  # one cup, in the middle of the view... that was once boxed as a bowl
    mapper.map.all()[0].class_votes = {"cup": 20, "bowl": 3}
    bowl = [TrackedBox(1, "bowl", (200.0, 160.0, 280.0, 260.0), 5, True)]
    vase = [TrackedBox(1, "vase", (200.0, 160.0, 280.0, 260.0), 5, True)]
    for frame in range(10):
        s.update(mapper, frame, np.eye(4), bowl, K, touched=[])
    assert s.status == {0: "prior"}
    for frame in range(10, 13):
        s.update(mapper, frame, np.eye(4), vase, K, touched=[])
    assert s.status == {0: "missing"}


def test_out_of_view_occluded_or_skipped_frames_never_count() -> None:
    s, mapper = _session(_prior())
    away = look_at(np.array([0.0, 0.0, 0.0]), np.array([0.0, -1.0, 0.0]))  # looking away from them
    far = np.eye(4)
    far[2, 3] = -5.0  # 7 m away: beyond missing_max_depth_m
    for frame in range(10):
        s.update(mapper, frame, away, [], K, touched=[])
        s.update(mapper, frame, far, [], K, touched=[])
        s.update(mapper, frame, np.eye(4), None, K, touched=[])  # a frame the detector skipped
    assert set(s.status.values()) == {"prior"}
    # a cup hidden behind a bigger landmark on the line of sight
    m = _prior(1)
    front = m.create("tv", 0.0)
    front.centroid, front.size = np.array([-0.4, 0.0, 1.0]), 0.6
    s, mapper = _session(m)
    s.status.pop(front.id)
    s.streak.pop(front.id)
    for frame in range(10):
        s.update(mapper, frame, np.eye(4), [TrackedBox(1, "tv", (0, 0, 640, 480), 5, True)], K, touched=[])
    assert s.status[0] == "prior"


def test_window_dataset() -> None:
    full = open_dataset("synthetic:frames=20,seed=0,size=64x48,persons=0")
    window = WindowDataset(full, 12)
    assert len(window) == 8 and window[0].index == 0 and window[0].stamp == full[12].stamp
    assert len(window.groundtruth()) == 8 and np.allclose(window.groundtruth()[0][1], full[12].gt_pose)
    with pytest.raises(DatasetError):
        WindowDataset(full, 20)


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "semmap.cli", "run", *args, "--quiet"],
        cwd=PROJECT,
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_cli_checks_the_prior_map_before_starting(tmp_path: Path) -> None:
    out = _run("synthetic:frames=5", "--out", str(tmp_path / "o"), "--map", str(tmp_path / "nothing"))
    assert out.returncode == 2 and "expected a run directory or its map.sqlite" in out.stderr
    MapStore(tmp_path / "empty" / "map.sqlite")
    out = _run("synthetic:frames=5", "--out", str(tmp_path / "o"), "--map", str(tmp_path / "empty"))
    assert out.returncode == 2 and "holds no map" in out.stderr
    MapStore(tmp_path / "o" / "map.sqlite").save({"version": 1})
    out = _run("synthetic:frames=5", "--out", str(tmp_path / "o"), "--map", str(tmp_path / "o"))
    assert out.returncode == 2 and "the output directory's own map" in out.stderr
    import sqlite3

    db = sqlite3.connect(tmp_path / "o" / "map.sqlite")
    with db:
        db.execute("UPDATE meta SET value = 'semmap.mapstore/7'")
    db.close()
    out = _run("synthetic:frames=5", "--out", str(tmp_path / "p"), "--map", str(tmp_path / "o"))
    assert out.returncode == 2 and "newer semmap" in out.stderr
    assert not (tmp_path / "p").exists()


@pytest.mark.parametrize(
    "bad",
    [
        "x",
        {"transform": [1.0] * 16, "anchors": [], "anchor_sigma_m": 0.03, "inliers": 4, "rms_m": 0.01},
        {
            "transform": list(np.eye(4).reshape(16)),
            "anchors": [[1, [0, 0]]],
            "anchor_sigma_m": 0.03,
            "inliers": 4,
            "rms_m": 0.01,
        },
        {
            "transform": list(np.eye(4).reshape(16)),
            "anchors": [[-1, [0, 0, 0]]],
            "anchor_sigma_m": 0.03,
            "inliers": 4,
            "rms_m": 0.01,
        },
        {"transform": list(np.eye(4).reshape(16)), "anchors": [], "anchor_sigma_m": 0.0, "inliers": 4, "rms_m": 0.01},
        {
            "transform": list(np.eye(4).reshape(16)),
            "anchors": [],
            "anchor_sigma_m": 0.03,
            "inliers": 4,
            "rms_m": float("nan"),
        },
    ],
)
def test_malformed_alignments_are_refused(bad: object) -> None:
    from semmap.core.messages import MessageError

    body = Observations("r", 1, 0.0).to_dict()
    body["alignment"] = bad
    with pytest.raises(MessageError):
        Observations.from_dict(body)
    good = MapAlignment(OFFSET, [(3, (1.0, 2.0, 3.0))], 0.03, 5, 0.02)
    back = Observations.decode(Observations("r", 1, 0.0, alignment=good).encode()).alignment
    assert back is not None and np.allclose(back.transform, OFFSET) and back.anchors == good.anchors


def test_a_class_the_detector_often_misses_needs_a_longer_run_to_go_missing() -> None:
    """Two cups, one prior and one of this session (present): the present cup, boxed in plain view one frame
    in five, teaches the detection rate, and the prior cup goes missing only after a run of misses that a cup
    still there would give with probability below 1 % (16 frames at 1 in 4), not after the minimum (3)."""
    s, mapper = _session(_prior(2))
    s.status.pop(1)  # landmark 1 is this session's own (present)
    s.streak.pop(1)
    camera = np.eye(4)
    on_present = [TrackedBox(1, "cup", (245.0, 200.0, 365.0, 280.0), 5, True)]  # a box on landmark 1 only
    assert s.missing_after("cup") == 3  # no evidence yet: Beta(4, 1), the minimum holds
    s.transform = None  # not relocalised yet: the session learns the rate on its own landmarks
    for frame in range(50):
        s.update(mapper, frame, camera, on_present if frame % 5 == 0 else [], K, touched=[])
    assert s.class_seen["cup"] == [10, 50] and s.status[0] == "prior"
    assert s.missing_after("cup") == 16  # rate (10 + 4) / (50 + 5) = 0.25: 0.75^16 < 0.01 < 0.75^15
    s.transform = np.eye(4)  # relocalised: now the prior cup's misses count
    for frame in range(50, 65):
        s.update(mapper, frame, camera, on_present if frame % 5 == 0 else [], K, touched=[])
    assert s.status[0] == "prior"  # 15 misses: a cup still there would give them more than 1 % of the time
    for frame in range(65, 75):
        s.update(mapper, frame, camera, on_present if frame % 5 == 0 else [], K, touched=[])
    assert s.status[0] == "missing" and s.streak[0] in range(16, 19), s.streak[0]
    restored = PriorSession(_prior(2), PriorParams(missing_after_frames=3))
    restored.restore(s.to_state())
    assert restored.class_seen == s.class_seen


def test_only_a_backend_started_for_a_prior_map_keeps_its_frames_and_realigns() -> None:
    """Keeping every handled frame (to rebuild in the prior frame) costs ~1 KB a frame for the whole run: a run
    without a prior map keeps none, and ignores an alignment (forged, or sent to the wrong backend)."""
    from semmap.runtime.pipeline.stages import BackendStage

    landmarks = {i: np.array(p, float) for i, p in enumerate([(0, 3, 1), (2, 3, 0.5), (-2, 3, 1.5)])}
    alignment = MapAlignment(OFFSET, [(i, tuple(p)) for i, p in landmarks.items()], 0.01, 3, 0.03)
    for expected in (False, True):
        stage = BackendStage(expect_alignment=expected)
        for f in range(30):
            truth = look_at(np.array([0.05 * f - 1, 0.0, 1.0]), np.array([0.0, 3.0, 1.0]))
            obs = Observations("r", f, f / 30, [_observe(truth, landmarks[i], i) for i in landmarks])
            obs.alignment = alignment if f == 20 else None
            step = stage.step(OdometryPose("r", f, f / 30, np.linalg.inv(OFFSET) @ truth, True, 0.001, 0.001, "gt"),
                              obs, None)
            assert step.realigned == (expected and f == 20)
            assert len(stage.aligner.handled) == (f + 1 if expected and f < 20 else 0)
        assert stage.graph.counters.get("anchors", 0) == (3 if expected else 0)


def test_a_prior_runs_keyframes_are_read_with_their_optimised_poses(tmp_path: Path) -> None:
    """backend.sqlite's keyframe clouds joined by stamp with trajectory_optimized.tum, read-only; a damaged row or a
    keyframe without a pose is skipped and counted, a run without them says why."""
    from semmap.algorithms.backend.loop_closure import KeyframeCloud, encode_keyframe
    from semmap.core.journal import FrameJournal
    from semmap.datasets.trajectory_io import write_tum
    from semmap.runtime.maps.prior_keyframes import load_prior_keyframes

    run = tmp_path / "run"
    run.mkdir()
    (run / "map.sqlite").write_bytes(b"")
    assert "backend.sqlite" in (load_prior_keyframes(run / "map.sqlite").missing or "")
    rng = np.random.default_rng(0)
    journal = FrameJournal(run / "backend.sqlite")
    poses = [frame_offset([0.1 * i, 0.0, 0.0, 0.0, 0.0, 5.0 * i]) for i in range(4)]
    for i in range(4):
        journal.append(10 * i, b"odometry", b"observations")
        cloud = KeyframeCloud(10 * i, 0.5 * i + 1e6, rng.normal(size=(300, 3)).astype(np.float32))
        journal.append_extra(10 * i, encode_keyframe(cloud, None) if i != 2 else b"\xc1 not msgpack")
    journal.db.close()
    # frame 30's stamp is not in the trajectory (a run that stopped before writing it, say)
    write_tum(run / "trajectory_optimized.tum", [(0.5 * i + 1e6, poses[i]) for i in range(3)])
    before = (run / "backend.sqlite").read_bytes()
    prior = load_prior_keyframes(run / "map.sqlite")
    assert prior.missing is None and prior.unreadable == 1 and prior.without_pose == 1
    assert [c.frame_id for c, _ in prior.keyframes] == [0, 10]
    np.testing.assert_allclose(prior.keyframes[1][1], poses[1], atol=1e-8)
    assert (run / "backend.sqlite").read_bytes() == before
    assert [c.frame_id for c, _ in load_prior_keyframes(run / "map.sqlite", max_keyframes=1).keyframes] == [10]
    (run / "backend.sqlite").write_bytes(b"not a database")
    assert "unreadable" in (load_prior_keyframes(run / "map.sqlite").missing or "")


def test_a_prior_landmark_that_absorbs_a_session_landmark_at_the_relocalisation_is_present() -> None:
    """The session mapped a cup in its provisional frame that the fit did not match; once the session is re-placed
    in the prior frame the mapper's merge pass fuses it into the prior cup. That cup was seen this session: it must
    be `present`, not `prior` (a `prior` one can go missing at the next undetected run; on 7-Scenes in real time a
    book the session had seen went missing that way)."""
    from semmap.algorithms.associator.mapper import LandmarkMapper
    from semmap.algorithms.relocalize import RelocResult
    from tests.associator.helpers import Sphere, orbit_pose
    from tests.associator.test_mapper import RATE, run

    cup = Sphere((0.0, 0.0, 0.8), 0.05, "cup")
    prior_mapper, _ = run(lambda t: [cup], range(60))
    prior = prior_mapper.map
    (prior_cup,) = prior.all()
    session_frame = frame_offset([0.5, -0.3, 0.1, 0.0, 0.0, 20.0])  # the session's odometry frame in the prior's
    session = LandmarkMapper()
    session.map.next_id = prior.next_id  # (as the associator starts a session over a prior map: ids after its)
    session, _ = run(lambda t: [cup], range(60), mapper=session,
                     lookup_at=lambda t: np.linalg.inv(session_frame) @ orbit_pose(t))
    (session_cup,) = session.map.all()
    s = PriorSession(prior, PriorParams())
    fit = RelocResult(session_frame.copy(), [], 4, 0.02, 0, 1, False)  # matched other objects, not this cup
    step, _ = s.adopt(session, fit, 60, 60 / RATE, lambda f: orbit_pose(f / RATE))
    assert (session_cup.id, prior_cup.id) in step.merges
    assert s.status[prior_cup.id] == "present"

"""Every message round-trips, and malformed or wrong-version payloads are rejected with MessageError."""

from __future__ import annotations

import math
import re

import msgpack
import numpy as np
import pytest

from semmap.core.messages import (
    ALL_MESSAGES,
    CandidateUpdate,
    Control,
    CorrectedPoses,
    DepthPatch,
    Detection,
    Detections,
    DynamicBox,
    DynamicObjects,
    Frame,
    GroundTruthInstance,
    Intrinsics,
    Landmark,
    MapUpdate,
    Measurement,
    MessageError,
    Observation,
    Observations,
    OdometryPose,
    OdometryRefinement,
    Progress,
    ServiceStatus,
    TagDetection,
    TagDetections,
    TrackedBox,
    Tracks,
)

K = Intrinsics(585.0, 585.0, 320.0, 240.0, 64, 48)


def _pose(yaw: float = 0.3, t=(1.0, 2.0, 3.0)) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    pose = np.eye(4)
    pose[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    pose[:3, 3] = t
    return pose


def _detection() -> Detection:
    patch = DepthPatch(4, 6, 2, (np.arange(20, dtype=np.uint16).reshape(4, 5) + 1000))
    return Detection((4.0, 6.0, 14.0, 14.0), "cup", 0.8, 1.02, patch)


def _samples() -> list:
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:48, 0:64]
    rgb = np.stack([xx * 4, yy * 5, (xx + yy) * 2], axis=-1).astype(np.uint8)  # smooth: JPEG keeps it
    depth = rng.integers(0, 5000, (48, 64), dtype=np.uint16)
    frame = Frame.from_arrays("robot1", 7, 0.25, rgb, depth, 0.001, K, _pose(),
                              [GroundTruthInstance(3, "cup", (1.0, 2.0, 9.0, 9.0), 40, False)])
    measurement = Measurement(7, 0.25, _detection(), K, 0.001)
    return [
        frame,
        OdometryPose("robot1", 7, 0.25, _pose(), True, 0.003, 0.001, "gt+drift"),
        Detections("robot1", 7, 0.25, K, 0.001, [_detection()], "", "detector-1", {"detect_ms": 31.5}),
        Tracks("robot1", 7, 0.25, [CandidateUpdate(2, "cup", [measurement], True)], [1],
               [TrackedBox(2, "cup", (4.0, 6.0, 14.0, 14.0), 5, True)]),
        Observations("robot1", 7, 0.25, [Observation(4, "cup", (0.1, -0.2, 1.5), 0.03, 0.1)], [(5, 4)],
                     retired=[9]),
        TagDetections("robot1", 7, 0.25, [TagDetection.from_observation(Observation(4, "cup", (0.1, -0.2, 1.5),
                                                                                     0.03, 0.1))]),
        MapUpdate("robot1", 3, 7, 0.25, [Landmark(4, "cup", (1.0, 2.0, 0.8), 0.06, (0.1, 0.1, 0.12), 9, 0.0, 0.25)],
                  [6, 9], [(5, 4)], False, [11, 12], {"association": 0.8}, moved=[9], moving_tracks=[12]),
        CorrectedPoses("robot1", 3, 7, np.array([0, 7]), np.array([0.0, 0.25]), np.stack([_pose(), _pose(0.1)]),
                       np.array([4]), np.array([[1.0, 2.0, 0.8]])),
        Control("robot1", "end_of_stream", 999, 1000),
        Progress("robot1", "tracker", 7),
        ServiceStatus("robot1", "tracker", "tracker-1", "running", 7, {"frames": 8},
                      {"update_ms": {"p50": 0.05, "p95": 0.09}}, 80.0, 1.5),
        DynamicObjects("robot1", 7, 0.25, [DynamicBox(2, "person", (4.0, 6.0, 14.0, 40.0), 1.2, 2.1, "class"),
                                           DynamicBox(3, "chair", (20.0, 6.0, 30.0, 20.0), 0.0, 0.0, "moving")]),
        OdometryRefinement("robot1", "orbslam3", np.array([1, 2]), np.stack([_pose(), _pose(0.1)])),
        OdometryRefinement("robot1", "orbslam3", np.zeros(0, np.int64), np.zeros((0, 4, 4)), "objects seen moving"),
    ]


@pytest.mark.parametrize("message", _samples(), ids=lambda m: type(m).__name__)
def test_round_trip(message) -> None:
    decoded = type(message).decode(message.encode())
    again = decoded.encode()
    assert type(message).decode(again).encode() == again
    assert decoded.to_dict().keys() == message.to_dict().keys()


def test_every_message_kind_has_a_sample_and_a_versioned_schema() -> None:
    kinds = {type(m) for m in _samples()}
    assert kinds == set(ALL_MESSAGES)
    for kind in ALL_MESSAGES:
        assert re.fullmatch(r"semmap\.[a-z_]+/[1-9][0-9]*", kind.SCHEMA)


def test_frame_images_survive_the_trip() -> None:
    frame = _samples()[0]
    decoded = Frame.decode(frame.encode())
    assert np.array_equal(decoded.depth(), frame.depth())
    assert decoded.rgb().shape == (48, 64, 3)
    # JPEG is lossy: close, not equal
    assert np.abs(decoded.rgb().astype(int) - frame.rgb().astype(int)).mean() < 4
    np.testing.assert_allclose(decoded.gt_pose, frame.gt_pose)
    assert decoded.instances[0].class_name == "cup"


def test_depth_as_png_is_accepted() -> None:
    import cv2

    frame = _samples()[0]
    ok, png = cv2.imencode(".png", frame.depth())
    assert ok
    frame.depth_raw = png.tobytes()
    decoded = Frame.decode(frame.encode())
    assert np.array_equal(decoded.depth(), cv2.imdecode(png, cv2.IMREAD_UNCHANGED))


def _mutate(message, **changes) -> bytes:
    body = message.to_dict()
    body["schema"] = message.SCHEMA
    body.update(changes)
    return msgpack.packb(body, use_bin_type=True)


def test_wrong_version_is_rejected_clearly() -> None:
    pose = _samples()[1]
    with pytest.raises(MessageError, match="unsupported version 'semmap.odometry/2'"):
        OdometryPose.decode(_mutate(pose, schema="semmap.odometry/2"))
    with pytest.raises(MessageError, match="expected schema"):
        OdometryPose.decode(_samples()[9].encode())


@pytest.mark.parametrize(
    ("index", "changes", "reason"),
    [
        (1, {"pose": [float("nan")] * 16}, "non-finite"),
        (1, {"pose": [2.0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]}, "orthonormal"),
        (1, {"pose": [1.0] * 15}, "16 numbers"),
        (1, {"frame_id": -1}, ">= 0"),
        (1, {"stamp": float("inf")}, "'stamp' must be a finite number"),
        (9, {"sent_at": float("nan")}, "'sent_at' must be a finite number"),
        (1, {"frame_id": "7"}, "must be"),
        (1, {"robot": "a/b"}, "field 'robot' must be `str` matching regex"),
        (1, {"robot": "**"}, "field 'robot' must be `str` matching regex"),
        (1, {"sigma_translation": 0.0}, "'sigma_translation' must be `float` > 0"),
        (2, {"detections": [{"box": [10, 10, 5, 20], "class": "cup", "score": 0.5, "depth_m": 1.0}]}, "x2 > x1"),
        (2, {"detections": [{"box": [1, 1, 5, 5], "class": "cup", "score": 1.5, "depth_m": 1.0}]},
         r"'detections\[0\].score' must be `float` <= 1.0"),
        (2, {"intrinsics": {"fx": -1, "fy": 1, "cx": 0, "cy": 0, "width": 10, "height": 10}},
         "'intrinsics.fx' must be `float` > 0"),
        (0, {"depth": {"dtype": "uint16", "shape": [48, 64], "data": b"\x00" * 10}}, "do not fit"),
        (0, {"depth": {"dtype": "float32", "shape": [48, 64], "data": b"\x00" * 48 * 64 * 4}}, "dtype"),
        (0, {"depth": {"dtype": "uint16", "shape": [4, 4], "data": b"\x00" * 32}}, "does not match intrinsics"),
        (0, {"depth_scale": 0.0}, "depth_scale"),
        (4, {"merges": [[1]]}, "merge"),
        (8, {"command": "reboot"}, "'command': unknown value 'reboot'"),
        (10, {"state": "confused"}, "'state': unknown value 'confused'"),
        (11, {"boxes": [{"track_id": 1, "class": "person", "box": [1, 2, 3, 4], "depth_min_m": 2.0,
                         "depth_max_m": 1.0, "reason": "class"}]}, "depth_min_m <= depth_max_m"),
    ],
)
def test_malformed_fields_are_rejected(index: int, changes: dict, reason: str) -> None:
    message = _samples()[index]
    with pytest.raises(MessageError, match=reason):
        type(message).decode(_mutate(message, **changes))


def test_corrupt_jpeg_is_an_error_when_decoded_not_a_crash() -> None:
    frame = _samples()[0]
    decoded = Frame.decode(_mutate(frame, rgb_jpeg=b"\xff\xd8garbage"))
    with pytest.raises(MessageError, match="JPEG"):
        decoded.rgb()


DEEP = b"\x83" + msgpack.packb({"schema": "semmap.frame/1", "robot": "r"})[1:] + msgpack.packb("depth") + (
    b"\x91" * 100_000 + b"\x01")  # a depth nested 100,000 lists deep


@pytest.mark.parametrize("payload", [b"", b"\xc1", b"\x93\x01\x02\x03", msgpack.packb("x"), b"\xff" * 100, DEEP])
def test_garbage_is_rejected(payload: bytes) -> None:
    for kind in ALL_MESSAGES:
        with pytest.raises(MessageError):
            kind.decode(payload)


def test_corrected_poses_must_be_rigid() -> None:
    sample = _samples()[7]
    sample.poses[1, 0, 0] = 3.0
    with pytest.raises(MessageError, match="poses\\[1\\]"):
        CorrectedPoses.decode(sample.encode())


def test_corrected_poses_are_deltas_applied_onto_a_copy_and_the_old_version_is_refused() -> None:
    poses: dict[int, np.ndarray] = {}
    landmarks: dict[int, np.ndarray] = {}
    full = CorrectedPoses("robot1", 1, 7, np.array([0, 7]), np.array([0.0, 0.25]), np.stack([_pose(), _pose(0.1)]),
                          np.array([4]), np.array([[1.0, 2.0, 0.8]]))
    assert CorrectedPoses.decode(full.encode()).apply_to(poses, landmarks) == [0, 7]
    delta = CorrectedPoses.decode(CorrectedPoses("robot1", 2, 8, np.array([8]), np.array([0.3]), _pose(0.2)[None],
                                                 full=False, num_frames=3).encode())
    assert (delta.full, delta.num_frames) == (False, 3)
    assert delta.apply_to(poses, landmarks) == [8]
    assert sorted(poses) == [0, 7, 8] and np.allclose(poses[7], _pose(0.1)) and sorted(landmarks) == [4]
    full.frame_ids, full.stamps, full.poses = np.array([3]), np.array([0.1]), _pose()[None]
    full.landmark_ids, full.landmark_positions = np.zeros(0, np.int64), np.zeros((0, 3))
    full.apply_to(poses, landmarks)  # a full one replaces everything
    assert sorted(poses) == [3] and not landmarks
    body = msgpack.unpackb(full.encode())
    for bad, match in (({"schema": "semmap.corrected_poses/1"}, "unsupported version"),
                       ({"num_frames": 0}, "num_frames"), ({"full": True, "num_frames": 5}, "num_frames")):
        with pytest.raises(MessageError, match=match):
            CorrectedPoses.decode(msgpack.packb({**body, **bad}))
    unsorted = CorrectedPoses("robot1", 2, 8, np.array([8, 7]), np.array([0.3, 0.2]), np.stack([_pose(), _pose()]),
                              full=False, num_frames=9)
    with pytest.raises(MessageError, match="ascending"):
        CorrectedPoses.decode(unsorted.encode())


def test_the_committed_json_schema_is_fresh_and_describes_every_message() -> None:
    """docs/interface.schema.json is what `python -m semmap.core.messages.schema` writes, and every sample's wire
    map (bytes as base64, the way the schema says JSON carries msgpack bin) validates against it."""
    import base64
    import json
    from pathlib import Path

    import jsonschema

    from semmap.core.messages.schema import DEFAULT_PATH, render, wire_schema

    assert Path(DEFAULT_PATH).read_text() == render(), "stale: run python -m semmap.core.messages.schema"
    schema = wire_schema()
    validator = jsonschema.Draft202012Validator(schema)

    def as_json(value):
        if isinstance(value, bytes):
            return base64.b64encode(value).decode()
        if isinstance(value, dict):
            return {k: as_json(v) for k, v in value.items()}
        if isinstance(value, list):
            return [as_json(v) for v in value]
        return value

    for message in _samples():
        body = as_json(msgpack.unpackb(message.encode()))
        validator.validate(body)
        assert schema["x-semmap-kinds"][message.SCHEMA] == f"#/$defs/{type(message).__name__}"
        with pytest.raises(jsonschema.ValidationError):
            validator.validate({**body, "schema": "semmap.other/1"})
    json.dumps(schema)  # plain JSON throughout

"""ROS bags as datasets: real bags written with `rosbags` from 7-Scenes frames read back as the folder does, and
`semmap run BAG` maps them as it maps the folder."""

from __future__ import annotations

import copy
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from semmap.datasets import DatasetError, detect_format, open_dataset

sys.path.insert(0, str(Path(__file__).parent))
from bag_writer import COLOR, DEPTH, INFO, ODOM, write_bag  # noqa: E402

FRAMES = 8  # reader tests
RUN_FRAMES = 60  # pipeline runs: the first two seconds show a cup, chairs, a table


@pytest.fixture(scope="module")
def kitchen_frames(kitchen_dir: Path) -> list:
    folder = open_dataset(kitchen_dir)
    return [folder[i] for i in range(FRAMES)]


def _bag(tmp: Path, frames: list, kind: str, **kw) -> Path:
    return write_bag(tmp / ("rec.bag" if kind == "ros1" else f"rec_{kind}"), frames, kind, **kw)


def _same_frames(dataset, frames: list, depth_tolerance: int = 0) -> None:
    assert len(dataset) == len(frames)
    for want in frames:
        got = dataset[want.index]
        assert np.array_equal(got.rgb, want.rgb)
        assert np.abs(got.depth.astype(int) - want.depth.astype(int)).max() <= depth_tolerance
        assert got.depth_scale == 0.001 and got.intrinsics == want.intrinsics
        assert abs(got.stamp - want.stamp) < 1e-8
        assert np.allclose(got.gt_pose, want.gt_pose, atol=1e-9)


@pytest.mark.parametrize(
    "kind,pose,depth",
    [
        ("mcap", "odom", "16UC1"),
        ("ros1", "odom", "16UC1"),
        ("sqlite3", "tf", "16UC1"),
        ("ros1", "tf", "32FC1"),
        ("mcap", "tf", "32FC1"),
    ],
)
def test_bag_reads_the_frames_of_the_folder(
    tmp_path: Path, kitchen_frames: list, kind: str, pose: str, depth: str
) -> None:
    path = _bag(tmp_path, kitchen_frames, kind, pose=pose, depth=depth)
    assert detect_format(path) == "rosbag"
    dataset = open_dataset(path)
    assert (dataset.topics["color"], dataset.topics["depth"], dataset.topics["camera_info"]) == (COLOR, DEPTH, INFO)
    assert dataset.topics["pose"] == (ODOM if pose == "odom" else "/tf")
    # 32FC1 metres -> mm rounds back to the same millimetres
    _same_frames(dataset, kitchen_frames, depth_tolerance=0)
    assert dataset.rate_hz == pytest.approx(30.0)
    assert [s for s, _ in dataset.groundtruth()] == pytest.approx([f.stamp for f in kitchen_frames])


def test_single_mcap_file_and_bgr8(tmp_path: Path, kitchen_frames: list) -> None:
    folder = _bag(tmp_path, kitchen_frames, "mcap", colour_encoding="bgr8")
    single = tmp_path / "alone.mcap"
    shutil.copy(next(folder.glob("*.mcap")), single)
    assert detect_format(single) == "rosbag"
    _same_frames(open_dataset(single), kitchen_frames)


def test_compressed_colour_travels_as_recorded(tmp_path: Path, kitchen_frames: list) -> None:
    """A CompressedImage JPEG stays encoded: the frame message carries the recorded bytes (no decode and
    re-encode in the player), and decodes to the folder's pixels."""
    from semmap.core.messages import Frame
    from semmap.runtime.pipeline.stages import frame_message

    dataset = open_dataset(_bag(tmp_path, kitchen_frames, "mcap", colour_encoding="jpeg"))
    _same_frames(dataset, kitchen_frames)
    for want in kitchen_frames[:2]:
        got = dataset[want.index]
        assert got.rgb_file is not None and got.rgb_file.fmt == "jpeg"
        frame = Frame.decode(frame_message("r", got).encode())
        assert frame.rgb_jpeg == want.rgb_file.data
        assert np.array_equal(frame.rgb(), want.rgb) and np.array_equal(frame.depth(), want.depth)


def test_missing_depth_fails_with_the_topic_list(tmp_path: Path, kitchen_frames: list) -> None:
    path = _bag(tmp_path, kitchen_frames[:2], "mcap", depth=None)
    with pytest.raises(DatasetError) as err:
        open_dataset(path)
    text = str(err.value)
    assert "no depth image topic" in text
    for topic, kind in (
        (COLOR, "sensor_msgs/msg/Image (rgb8)"),
        (INFO, "sensor_msgs/msg/CameraInfo"),
        (ODOM, "nav_msgs/msg/Odometry"),
    ):
        assert f"{topic}  {kind}" in text
    assert "--topics" in text


def test_topics_override_and_frames_from_tf(tmp_path: Path, kitchen_frames: list) -> None:
    """/tf and an odometry topic in one bag: the odometry topic wins unless --topics names /tf; tf frames are
    options (a wrong one is an error naming the frames there are)."""
    odom = _bag(tmp_path, kitchen_frames[:3], "mcap", pose="odom")
    with pytest.raises(DatasetError, match=r"the pose topic /nope is not in the bag"):
        open_dataset(odom, topics="pose=/nope")
    with pytest.raises(DatasetError, match="unknown topic role"):
        open_dataset(odom, topics="colour_image=/x")
    tf = _bag(tmp_path, kitchen_frames[:3], "ros1", pose="tf")
    dataset = open_dataset(tf, tf_parent="world", tf_child="camera_color_optical_frame")
    _same_frames(dataset, kitchen_frames[:3])
    # the pose of camera_link with the documented REP 103 -> optical transform gives the same optical poses
    via_link = open_dataset(tf, tf_child="camera_link", pose_to_optical="ros")
    _same_frames(via_link, kitchen_frames[:3])
    with pytest.raises(DatasetError, match=r"camera frame base_link not in /tf \(frames: camera_color_optical"):
        open_dataset(tf, tf_child="base_link")


def test_a_bad_image_is_an_error_of_that_frame_only(tmp_path: Path, kitchen_frames: list) -> None:
    frames = [*kitchen_frames[:3]]
    bad = copy.copy(frames[1])
    bad.rgb = frames[1].rgb[:, :320].copy()  # narrower than the info
    path = _bag(tmp_path, [frames[0], bad, frames[2]], "mcap")
    dataset = open_dataset(path)
    assert np.array_equal(dataset[0].rgb, frames[0].rgb) and np.array_equal(dataset[2].rgb, frames[2].rgb)
    with pytest.raises(DatasetError, match="differ"):
        dataset[1]


def test_run_on_a_bag_without_depth_fails_at_once(tmp_path: Path, kitchen_frames: list, semmap_run) -> None:
    path = _bag(tmp_path, kitchen_frames[:2], "ros1", depth=None)
    started = time.monotonic()
    result = semmap_run([str(path), "--out", str(tmp_path / "out"), "--no-viz"], timeout=60)
    assert result.returncode == 2
    assert time.monotonic() - started < 30  # before any service starts (mostly interpreter start-up here)
    assert "no depth image topic" in result.stderr and f"{COLOR}  sensor_msgs/msg/Image (rgb8)" in result.stderr
    assert not (tmp_path / "out" / "logs").exists()


def _landmarks(out: Path) -> list[tuple[int, str, np.ndarray]]:
    return [
        (lm["id"], lm["class"], np.array(lm["centroid"]))
        for lm in json.loads((out / "map.json").read_text())["landmarks"]
    ]


@pytest.mark.needs_model
def test_bags_map_the_same_as_the_folder(tmp_path: Path, kitchen_dir: Path, semmap_run) -> None:
    folder = open_dataset(kitchen_dir)
    frames = [folder[i] for i in range(RUN_FRAMES)]
    runs = {
        "folder": kitchen_dir,
        "mcap": _bag(tmp_path, frames, "mcap", colour_encoding="jpeg"),  # the folder's JPEGs, as recorded
        "ros1": _bag(tmp_path, frames, "ros1", pose="tf"),
    }
    maps = {}
    for name, data in runs.items():
        out = tmp_path / f"out_{name}"
        result = semmap_run(
            [str(data), "--out", str(out), "--odometry", "gt", "--max-frames", str(RUN_FRAMES), "--no-viz"],
            timeout=400,
        )
        assert result.returncode == 0, result.stderr[-3000:]
        maps[name] = _landmarks(out)
    assert len(maps["folder"]) >= 3, "the first two seconds show several objects"
    # compressed colour travels as recorded, like the folder's JPEG files: the same pixels, the same map
    assert [(i, c) for i, c, _ in maps["mcap"]] == [(i, c) for i, c, _ in maps["folder"]]
    for (_, _, got), (_, _, want) in zip(maps["mcap"], maps["folder"], strict=True):
        assert np.allclose(got, want, atol=1e-3)
    # raw colour is JPEG-encoded for the wire: pixels a JPEG generation apart, the same objects within centimetres
    assert [c for _, c, _ in maps["ros1"]] == [c for _, c, _ in maps["folder"]]
    for (_, _, got), (_, _, want) in zip(maps["ros1"], maps["folder"], strict=True):
        assert np.allclose(got, want, atol=0.05)

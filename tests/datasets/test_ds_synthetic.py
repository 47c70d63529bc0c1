"""The synthetic scene's ground truth: deterministic, geometrically exact, with moving people and a closed loop."""

from __future__ import annotations

import numpy as np
import pytest

from semmap.datasets import DatasetError
from semmap.datasets.synthetic import SyntheticConfig, SyntheticDataset, SyntheticRender

COCO = {"person", "cup", "bottle", "bowl", "laptop", "tv", "chair", "potted plant", "book", "dining table",
        "refrigerator", "clock"}  # fmt: skip
SAMPLED = (0, 45, 90, 150, 210)


@pytest.fixture(scope="module")
def scene() -> SyntheticDataset:
    return SyntheticDataset()


@pytest.fixture(scope="module")
def renders(scene: SyntheticDataset) -> dict[int, SyntheticRender]:
    return {i: scene.render(i) for i in SAMPLED}


def test_frame_format(scene: SyntheticDataset, renders: dict[int, SyntheticRender]) -> None:
    assert len(scene) == 300 and scene.rate_hz == 30.0 and scene.has_groundtruth
    frame = renders[90].frame
    assert frame.index == 90 and frame.stamp == pytest.approx(3.0)
    assert frame.rgb.shape == (480, 640, 3) and frame.rgb.dtype == np.uint8
    assert frame.depth.shape == (480, 640) and frame.depth.dtype == np.uint16 and frame.depth_scale == 0.001
    k = frame.intrinsics
    assert (k.fx, k.fy, k.cx, k.cy, k.width, k.height) == (525.0, 525.0, 319.5, 239.5, 640, 480)
    assert np.all(frame.depth > 0)  # a closed room: every ray hits something
    assert frame.rgb.std() > 20 and len(np.unique(frame.rgb.reshape(-1, 3), axis=0)) > 1000  # not flat
    assert renders[90].labels.shape == (480, 640)
    for render in renders.values():
        for box in render.frame.instances:
            assert box.class_name in COCO and box.visible_pixels >= 150
            assert 0 <= box.box[0] < box.box[2] <= 640 and 0 <= box.box[1] < box.box[3] <= 480
            assert box.visible_pixels == int((render.labels == box.instance_id).sum())
    with pytest.raises(IndexError):
        scene[300]


def test_deterministic_for_a_seed(renders: dict[int, SyntheticRender]) -> None:
    again = SyntheticDataset().render(150)
    first = renders[150]
    np.testing.assert_array_equal(again.frame.rgb, first.frame.rgb)
    np.testing.assert_array_equal(again.frame.depth, first.frame.depth)
    np.testing.assert_array_equal(again.labels, first.labels)
    np.testing.assert_array_equal(again.frame.gt_pose, first.frame.gt_pose)
    assert again.frame.instances == first.frame.instances
    other = SyntheticDataset(seed=1).render(150).frame
    assert not np.array_equal(other.rgb, first.frame.rgb)


def test_objects(scene: SyntheticDataset) -> None:
    objects = scene.objects()
    classes = [o.class_name for o in objects]
    assert classes.count("dining table") == 1 and classes.count("cup") >= 3 and classes.count("bottle") == 2
    assert classes.count("chair") >= 2 and classes.count("person") == 2
    assert {"bowl", "laptop", "tv", "potted plant", "book"} <= set(classes)
    assert len({o.instance_id for o in objects}) == len(objects) and 0 not in {o.instance_id for o in objects}
    for obj in objects:
        assert obj.moving == (obj.class_name == "person")
        if obj.class_name == "person":
            assert obj.extent[2] == pytest.approx(1.72) and 0.3 <= max(obj.extent[:2]) <= 0.6
    table = next(o for o in objects if o.class_name == "dining table")
    assert table.centroid == pytest.approx((0.0, 0.0, 0.385))
    cup = next(o for o in objects if o.class_name == "cup")
    assert cup.centroid[2] == pytest.approx(0.77 + 0.05)  # standing on the table top


def _project(pose: np.ndarray, k, point: np.ndarray) -> tuple[float, float, float]:
    p = pose[:3, :3].T @ (point - pose[:3, 3])
    return k.fx * p[0] / p[2] + k.cx, k.fy * p[1] / p[2] + k.cy, p[2]


def _occluded(render: SyntheticRender, instance_id: int, centroid: np.ndarray, extent: np.ndarray) -> bool:
    """Whether anything else lies in front of the object inside the image rectangle of its 3D box."""
    frame = render.frame
    corners = centroid + (np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T * extent / 2)
    projected = np.array([_project(frame.gt_pose, frame.intrinsics, c) for c in corners])
    if np.any(projected[:, 2] <= 0.1):
        return True
    x1, y1 = np.floor(projected[:, :2].min(0)).astype(int)
    x2, y2 = np.ceil(projected[:, :2].max(0)).astype(int)
    if x1 < 0 or y1 < 0 or x2 > frame.intrinsics.width or y2 > frame.intrinsics.height:
        return True  # cut by the image border
    labels = render.labels[y1:y2, x1:x2]
    depth = frame.depth[y1:y2, x1:x2] * frame.depth_scale
    return bool(np.any((labels != instance_id) & (labels != 0) & (depth < projected[:, 2].min() - 0.02)))


def test_gt_centroid_projects_inside_the_box(scene: SyntheticDataset, renders: dict[int, SyntheticRender]) -> None:
    truth = {o.instance_id: o for o in scene.objects()}
    checked = 0
    for render in renders.values():
        frame = render.frame
        for box in frame.instances:
            obj = truth[box.instance_id]
            if box.moving or _occluded(render, box.instance_id, np.array(obj.centroid), np.array(obj.extent)):
                continue
            x1, y1, x2, y2 = box.box
            u, v, z = _project(frame.gt_pose, frame.intrinsics, np.array(obj.centroid))
            assert z > 0 and x1 <= u <= x2 and y1 <= v <= y2, (frame.index, box)
            checked += 1
    assert checked >= 10


def test_depth_backprojects_onto_the_object(scene: SyntheticDataset, renders: dict[int, SyntheticRender]) -> None:
    truth = {o.instance_id: o for o in scene.objects()}
    checked = 0
    for render in renders.values():
        frame, k = render.frame, render.frame.intrinsics
        centroids = scene.object_centroids(frame.index)
        for box in frame.instances:
            # the object's own pixel nearest the box centre
            vs, us = np.nonzero(render.labels == box.instance_id)
            cu, cv = (box.box[0] + box.box[2]) / 2, (box.box[1] + box.box[3]) / 2
            j = int(np.argmin((us - cu) ** 2 + (vs - cv) ** 2))
            u, v = int(us[j]), int(vs[j])
            z = frame.depth[v, u] * frame.depth_scale
            camera_point = np.array([(u - k.cx) / k.fx * z, (v - k.cy) / k.fy * z, z])
            world = frame.gt_pose[:3, :3] @ camera_point + frame.gt_pose[:3, 3]
            half = np.array(truth[box.instance_id].extent) / 2
            if box.moving:  # a person turns as it walks: its box extent changes, so only check the centre
                assert np.linalg.norm(world[:2] - centroids[box.instance_id][:2]) < 0.5
                continue
            outside = np.maximum(np.abs(world - centroids[box.instance_id]) - half, 0.0)
            assert np.linalg.norm(outside) < 0.03 + 0.002 * z * z, (frame.index, box)  # pixel + depth noise
            checked += 1
    assert checked >= 30


def test_people_move_and_are_seen(scene: SyntheticDataset, renders: dict[int, SyntheticRender]) -> None:
    people = [o.instance_id for o in scene.objects() if o.class_name == "person"]
    start, later = scene.object_centroids(0), scene.object_centroids(90)
    for pid in people:
        assert np.linalg.norm(start[pid] - later[pid]) > 0.5  # walked at least half a metre in 3 s
    seen = {b.instance_id for r in renders.values() for b in r.frame.instances if b.moving}
    assert seen == set(people)
    boxes = [next(b.box for b in renders[i].frame.instances if b.instance_id == people[0]) for i in (0, 45)]
    assert boxes[0] != boxes[1]


def test_camera_path_closes_the_loop(scene: SyntheticDataset) -> None:
    poses = [p for _, p in scene.groundtruth()]
    assert len(poses) == 300
    positions = np.array([p[:3, 3] for p in poses])
    assert np.linalg.norm(positions[-1] - positions[0]) < 0.1
    radius = np.linalg.norm(positions[:, :2], axis=1)
    assert np.allclose(radius, 2.0) and np.all(np.abs(positions[:, 2] - 1.4) <= 0.1)
    assert np.ptp(positions[:, 2]) > 0.05  # vertical waves
    for pose in poses[::37]:
        np.testing.assert_allclose(pose[:3, :3].T @ pose[:3, :3], np.eye(3), atol=1e-12)
        forward = pose[:3, 2]
        assert np.dot(forward, -pose[:3, 3] / np.linalg.norm(pose[:3, 3])) > 0.9  # looking at the table
    assert (scene.groundtruth()[1][0], scene.groundtruth()[-1][0]) == pytest.approx((1 / 30, 299 / 30))


def test_config_options_and_noise() -> None:
    small = SyntheticDataset(frames=3, size="160x120", depth_noise=0.0)
    k = small.intrinsics
    assert (k.width, k.height, k.fx, k.cx, k.cy) == (160, 120, 131.25, 79.5, 59.5)
    exact = small[1]
    assert exact.rgb.shape == (120, 160, 3) and exact.depth.shape == (120, 160)
    noisy = SyntheticDataset(frames=3, size="160x120")[1]
    diff = noisy.depth.astype(int) - exact.depth.astype(int)
    assert 0 < np.abs(diff).mean() < 20 and np.array_equal(noisy.rgb, exact.rgb)
    assert SyntheticConfig.from_options({"frames": "600", "seed": "3"}) == SyntheticConfig(frames=600, seed=3)
    with pytest.raises(DatasetError, match="persons"):
        SyntheticConfig(persons=3)
    with pytest.raises(DatasetError, match="too small"):
        SyntheticConfig(room_size=(5.0, 5.0, 2.8))
    with pytest.raises(DatasetError):
        SyntheticDataset(SyntheticConfig(), seed=2)

"""The street world: a generated street along a trajectory file, rendered by the synthetic renderer."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from semmap.datasets import DatasetError, open_dataset
from semmap.datasets.street import STATIC_CLASSES, StreetDataset
from semmap.datasets.trajectory_io import pose_to_tum

CLASSES = set(STATIC_CLASSES) | {"person"}
LAP = 60  # poses per lap of the circle
SMALL = "size=310x94,fx=180,fy=180"  # a cheap camera for the tests


def _circle(laps: int = 2, radius: float = 20.0) -> list[np.ndarray]:
    """KITTI-style camera-to-world poses (y down, z forward) driving `laps` times round a circle."""
    poses = []
    for i in range(laps * LAP):
        a = 2 * math.pi * i / LAP
        pose = np.eye(4)
        pose[:3, 0] = (math.cos(a), 0.0, -math.sin(a))
        pose[:3, 1] = (0.0, 1.0, 0.0)
        pose[:3, 2] = (math.sin(a), 0.0, math.cos(a))
        pose[:3, 3] = (radius - radius * math.cos(a), 0.0, radius * math.sin(a))
        poses.append(pose)
    return poses


@pytest.fixture(scope="module")
def kitti_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("street") / "loop.txt"
    path.write_text("".join(" ".join(f"{v:.9e}" for v in p[:3, :].ravel()) + "\n" for p in _circle()))
    return path


@pytest.fixture(scope="module")
def street(kitti_file: Path) -> StreetDataset:
    ds = open_dataset(f"synthetic:trajectory={kitti_file},{SMALL}")
    assert isinstance(ds, StreetDataset)
    return ds


def test_opens_a_kitti_file(street: StreetDataset, kitti_file: Path) -> None:
    assert len(street) == 2 * LAP and street.rate_hz == pytest.approx(10.0) and street.has_groundtruth
    assert street.stamps()[:3] == pytest.approx([0.0, 0.1, 0.2])
    frame = street[7]
    assert frame.index == 7 and frame.stamp == pytest.approx(0.7)
    np.testing.assert_allclose(frame.gt_pose, _circle()[7], atol=1e-8)
    assert frame.rgb.shape == (94, 310, 3) and frame.depth.shape == (94, 310) and frame.depth_scale == 0.001
    k = frame.intrinsics
    assert (k.fx, k.fy, k.cx, k.cy) == (180.0, 180.0, 154.5, 46.5)
    assert frame.depth.max() <= 42_000 and (frame.depth > 0).mean() > 0.3  # depth to 40 m (+ noise), sky: none
    default = open_dataset(f"synthetic:trajectory={kitti_file},frames=3")
    k = default.intrinsics
    assert len(default) == 3 and (k.width, k.height, k.fx, k.fy) == (620, 188, 359.0, 359.0)


def test_objects_of_the_street_classes_appear(street: StreetDataset) -> None:
    truths = street.objects()
    assert {o.class_name for o in truths} == CLASSES
    assert {o.class_name for o in truths if o.moving} == {"car", "person"}
    assert len({o.instance_id for o in truths}) == len(truths) and 0 not in {o.instance_id for o in truths}
    seen: set[str] = set()
    truth = {o.instance_id: o for o in truths}
    inside = checked = 0
    for i in range(0, LAP, 4):
        render = street.render(i)
        frame = render.frame
        for box in frame.instances:
            assert box.class_name in CLASSES and box.moving == truth[box.instance_id].moving
            assert 0 <= box.box[0] < box.box[2] <= 310 and 0 <= box.box[1] < box.box[3] <= 94
            assert box.visible_pixels == int((render.labels == box.instance_id).sum())
            seen.add(box.class_name)
            if not box.moving and box.visible_pixels >= 150:  # ground truth in the file's frame: projects inside
                pose, k = frame.gt_pose, frame.intrinsics
                p = pose[:3, :3].T @ (np.asarray(truth[box.instance_id].centroid) - pose[:3, 3])
                u, v = k.fx * p[0] / p[2] + k.cx, k.fy * p[1] / p[2] + k.cy
                checked += 1
                inside += box.box[0] - 5 <= u <= box.box[2] + 5 and box.box[1] - 5 <= v <= box.box[3] + 5
    assert len(seen) >= 5 and "car" in seen
    assert checked >= 10 and inside >= 0.8 * checked


def test_a_revisit_sees_the_same_objects(street: StreetDataset) -> None:
    for i in (5, 23, 41):
        first, again = street.render(i), street.render(i + LAP)  # the same pose, one lap (6 s) later
        np.testing.assert_array_equal(first.frame.gt_pose, again.frame.gt_pose)
        movers = {b.instance_id for r in (first, again) for b in r.frame.instances if b.moving}
        moving = street._moving_ids | movers
        still = ~np.isin(first.labels, list(moving)) & ~np.isin(again.labels, list(moving))
        assert still.mean() > 0.7
        np.testing.assert_array_equal(first.labels[still], again.labels[still])
        ids_first = {b.instance_id for b in first.frame.instances if not b.moving}
        ids_again = {b.instance_id for b in again.frame.instances if not b.moving}
        assert ids_first and len(ids_first & ids_again) >= 0.8 * len(ids_first | ids_again)


def test_same_seed_same_frames(street: StreetDataset, kitti_file: Path) -> None:
    twin = StreetDataset(trajectory=str(kitti_file), size="310x94", fx=180, fy=180)
    a, b = street.render(30), twin.render(30)
    np.testing.assert_array_equal(a.frame.rgb, b.frame.rgb)
    np.testing.assert_array_equal(a.frame.depth, b.frame.depth)
    np.testing.assert_array_equal(a.labels, b.labels)
    assert a.frame.instances == b.frame.instances
    other = StreetDataset(trajectory=str(kitti_file), size="310x94", fx=180, fy=180, seed=1)
    layout = [(o.class_name, o.centroid) for o in street.objects()]
    assert [(o.class_name, o.centroid) for o in other.objects()] != layout


def test_opens_a_tum_file(tmp_path: Path) -> None:
    # The same circle as a TUM file in a z-up world (x forward): stamps from the file, poses as written.
    flip = np.array([[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
    poses = [flip @ p for p in _circle(laps=1)]
    lines = [f"{100 + 0.05 * i:.6f} " + " ".join(f"{v:.9f}" for v in pose_to_tum(p)) for i, p in enumerate(poses)]
    path = tmp_path / "loop.tum"
    path.write_text("# timestamp tx ty tz qx qy qz qw\n" + "\n".join(lines) + "\n")
    ds = open_dataset(f"synthetic:trajectory={path},{SMALL}")
    assert len(ds) == LAP and ds.rate_hz == pytest.approx(20.0)
    frame = ds[12]
    assert frame.stamp == pytest.approx(100.6)
    np.testing.assert_allclose(frame.gt_pose, poses[12], atol=1e-6)
    assert frame.instances and {b.class_name for b in frame.instances} <= CLASSES
    truth = {o.instance_id: o for o in ds.objects()}
    on_ground = [o for o in truth.values() if o.class_name == "car" and not o.moving]
    assert on_ground and all(-1.0 < o.centroid[2] < -0.8 for o in on_ground)  # z up here: on the ground at -1.65


def test_bad_trajectory_files(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="does not exist"):
        open_dataset(f"synthetic:trajectory={tmp_path / 'nope.txt'}")
    garbage = tmp_path / "garbage.txt"
    garbage.write_text("this is not a trajectory\n")
    with pytest.raises(DatasetError, match="neither a TUM trajectory .* nor a KITTI pose file"):
        open_dataset(f"synthetic:trajectory={garbage}")
    broken = tmp_path / "broken.txt"
    broken.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 x 0 1 0 0 0 0 1 0\n")
    with pytest.raises(DatasetError, match="bad KITTI pose line"):
        open_dataset(f"synthetic:trajectory={broken}")
    one = tmp_path / "one.txt"
    one.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(DatasetError, match="at least 2"):
        open_dataset(f"synthetic:trajectory={one}")
    with pytest.raises(DatasetError, match="unknown option"):
        open_dataset(f"synthetic:trajectory={one},colour=red")

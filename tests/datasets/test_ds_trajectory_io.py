"""TUM / KITTI trajectory files: the real files in shared/data read back with the right counts and round trip."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from semmap.datasets import DatasetError
from semmap.datasets.trajectory_io import (
    orthonormalize_pose,
    pose_from_tum,
    pose_to_tum,
    read_kitti_poses,
    read_timestamps,
    read_tum,
    write_kitti_poses,
    write_tum,
)

TUM_FILES = [
    "fr2_desk_groundtruth.txt",
    "fr2_desk_ORB.txt",
    "freiburg1_xyz-groundtruth.txt",
    "freiburg1_xyz-rgbdslam.txt",
    "fr3_walking_xyz_groundtruth.txt",
    "fr3_walking_xyz_DynORBSLAM.txt",
]


def _data_lines(path: Path) -> int:
    return sum(1 for line in path.read_text().splitlines() if line.strip() and not line.lstrip().startswith("#"))


def _assert_rigid(pose: np.ndarray, tol: float = 1e-9) -> None:
    assert pose.shape == (4, 4)
    np.testing.assert_allclose(pose[:3, :3].T @ pose[:3, :3], np.eye(3), atol=tol)
    assert np.linalg.det(pose[:3, :3]) == pytest.approx(1.0, abs=tol)
    np.testing.assert_array_equal(pose[3], [0, 0, 0, 1])


@pytest.fixture(scope="module")
def trajectories(data_root: Path) -> Path:
    path = data_root / "trajectories"
    if not path.is_dir():
        pytest.skip(f"no trajectories/ in {data_root}")
    return path


@pytest.mark.needs_data
@pytest.mark.parametrize("name", sorted(TUM_FILES))
def test_read_tum_real_files_and_round_trip(trajectories: Path, tmp_path: Path, name: str) -> None:
    path = trajectories / name
    poses = read_tum(path)
    assert len(poses) == _data_lines(path) > 100
    stamps = np.array([s for s, _ in poses])
    assert np.all(np.diff(stamps) >= 0) and stamps[0] > 1e9  # unix seconds; fr2_desk gt repeats one stamp
    for _, pose in poses[:: max(1, len(poses) // 20)]:
        _assert_rigid(pose)

    out = tmp_path / "out.txt"
    assert write_tum(out, poses) == len(poses)
    again = read_tum(out)
    assert len(again) == len(poses)
    np.testing.assert_allclose([s for s, _ in again], stamps, atol=1e-6)
    np.testing.assert_allclose(np.stack([p for _, p in again]), np.stack([p for _, p in poses]), atol=1e-7)


@pytest.mark.needs_data
def test_read_tum_matches_file_values(trajectories: Path) -> None:
    stamp, pose = read_tum(trajectories / "fr2_desk_groundtruth.txt")[0]
    # first line: 1311868163.8697 -0.1357 -1.4217 1.4764 0.6453 -0.5498 0.3363 -0.4101
    assert stamp == pytest.approx(1311868163.8697)
    np.testing.assert_allclose(pose[:3, 3], [-0.1357, -1.4217, 1.4764])
    quat = Rotation.from_matrix(pose[:3, :3]).as_quat()
    expected = np.array([0.6453, -0.5498, 0.3363, -0.4101])
    expected /= np.linalg.norm(expected)
    assert min(np.abs(quat - expected).max(), np.abs(quat + expected).max()) < 1e-9


@pytest.mark.needs_data
def test_read_kitti_poses_and_times(trajectories: Path, tmp_path: Path) -> None:
    gt = read_kitti_poses(trajectories / "KITTI_00_gt.txt")
    orb = read_kitti_poses(trajectories / "KITTI_00_ORB.txt")
    times = read_timestamps(trajectories / "KITTI_00_gt_times.txt")
    assert len(gt) == len(orb) == len(times) == 4541
    np.testing.assert_allclose(gt[0], np.eye(4), atol=1e-6)
    np.testing.assert_allclose(gt[1][:3, 3], [-4.690294e-02, -2.839928e-02, 8.586941e-01])
    for pose in gt[::500]:
        _assert_rigid(pose, tol=1e-5)
    assert times[0] == 0.0 and times[-1] > 400  # ~10 Hz over 7.5 min

    out = tmp_path / "kitti.txt"
    assert write_kitti_poses(out, gt[:50]) == 50
    np.testing.assert_allclose(np.stack(read_kitti_poses(out)), np.stack(gt[:50]), atol=1e-8)


def test_tum_round_trip_generated(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    poses = []
    for i in range(20):
        pose = np.eye(4)
        pose[:3, :3] = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
        pose[:3, 3] = rng.normal(size=3) * 5
        poses.append((1000.0 + i / 30, pose))
    path = tmp_path / "t.tum"
    write_tum(path, poses, header="generated\nsecond line")
    assert path.read_text().startswith("# generated\n# second line\n")
    back = read_tum(path)
    for (s0, p0), (s1, p1) in zip(poses, back, strict=True):
        assert s1 == pytest.approx(s0, abs=1e-6)
        np.testing.assert_allclose(p1, p0, atol=1e-8)


def test_pose_helpers() -> None:
    assert pose_to_tum(np.eye(4)) == (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    flipped = pose_from_tum([1, 2, 3, 0, 0, 0, -2.0])  # unnormalised, negative-w identity
    expected = np.eye(4)
    expected[:3, 3] = [1, 2, 3]
    np.testing.assert_allclose(flipped, expected)
    assert pose_to_tum(flipped)[6] == pytest.approx(1.0)  # canonical sign: qw >= 0
    with pytest.raises(ValueError):
        pose_from_tum([0, 0, 0, 0, 0, 0, 0])

    drifted = np.eye(4)
    drifted[:3, :3] = Rotation.from_rotvec([0.1, 0.2, 0.3]).as_matrix() * 1.0004
    drifted[:3, 3] = [1, 2, 3]
    fixed = orthonormalize_pose(drifted)
    _assert_rigid(fixed, tol=1e-12)
    np.testing.assert_allclose(fixed[:3, :3], Rotation.from_rotvec([0.1, 0.2, 0.3]).as_matrix(), atol=1e-12)
    np.testing.assert_array_equal(fixed[:3, 3], [1, 2, 3])


def test_bad_files_raise_dataset_error(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="cannot read"):
        read_tum(tmp_path / "missing.txt")
    bad = tmp_path / "bad.txt"
    bad.write_text("# header\n1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 1\n")
    with pytest.raises(DatasetError, match=r"bad.txt:3: expected 8 values"):
        read_tum(bad)
    bad.write_text("0 0 0 0 0 0 0 0 0 0 0 x\n")
    with pytest.raises(DatasetError, match=r"bad.txt:1: bad KITTI pose"):
        read_kitti_poses(bad)
    comma = tmp_path / "comma.txt"
    comma.write_text("1.5,1,2,3,0,0,0,1\n")  # TUM tools accept commas too
    assert read_tum(comma)[0][0] == 1.5

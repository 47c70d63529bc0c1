"""Trajectory files in the formats the evaluation tools read (TUM, KITTI), as (stamp, 4x4) lists.

Kept dependency-light (numpy + scipy) so every service can write its output trajectory in a format
`evo` and the TUM/KITTI scripts understand, and read ground truth back for tests.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from semmap.core.outputs import atomic_write_text

from .base import DatasetError

Pose = np.ndarray  # 4x4 float64 homogeneous transform


def _data_lines(path: Path) -> Iterable[tuple[int, list[str]]]:
    """(line number, fields) of every non-empty, non-comment line; commas count as separators (TUM tools do)."""
    try:
        text = path.read_text()
    except OSError as exc:
        raise DatasetError(f"cannot read trajectory file {path}: {exc}") from exc
    for number, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        yield number, line.replace(",", " ").split()


def pose_from_tum(values: Iterable[float]) -> Pose:
    """4x4 from tx ty tz qx qy qz qw (the quaternion is normalised; scipy's scalar-last order matches TUM)."""
    tx, ty, tz, qx, qy, qz, qw = (float(v) for v in values)
    quat = np.array([qx, qy, qz, qw])
    norm = np.linalg.norm(quat)
    if not np.isfinite(norm) or norm < 1e-9:
        raise ValueError("zero or non-finite quaternion")
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_quat(quat / norm).as_matrix()
    pose[:3, 3] = (tx, ty, tz)
    return pose


def pose_to_tum(pose: Pose) -> tuple[float, float, float, float, float, float, float]:
    """tx ty tz qx qy qz qw of a 4x4 (the rotation part is projected to the nearest rotation first)."""
    pose = np.asarray(pose, dtype=float)
    if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
        raise ValueError(f"expected a finite 4x4 pose, got shape {pose.shape}")
    qx, qy, qz, qw = Rotation.from_matrix(pose[:3, :3]).as_quat()
    if qw < 0:  # one canonical sign keeps written files diff-stable
        qx, qy, qz, qw = -qx, -qy, -qz, -qw
    tx, ty, tz = pose[:3, 3]
    return float(tx), float(ty), float(tz), float(qx), float(qy), float(qz), float(qw)


def read_tum(path: str | Path) -> list[tuple[float, Pose]]:
    """Read `stamp tx ty tz qx qy qz qw` lines ('#' comments skipped) into (stamp, 4x4 camera-to-world)."""
    path = Path(path)
    rows: list[list[float]] = []
    for number, fields in _data_lines(path):
        if len(fields) != 8:
            raise DatasetError(f"{path}:{number}: expected 8 values (stamp tx ty tz qx qy qz qw), got {len(fields)}")
        try:
            rows.append([float(f) for f in fields])
        except ValueError as exc:
            raise DatasetError(f"{path}:{number}: bad TUM pose line: {exc}") from exc
        norm = np.linalg.norm(rows[-1][4:])
        if not np.isfinite(norm) or norm < 1e-9:
            raise DatasetError(f"{path}:{number}: bad TUM pose line: zero or non-finite quaternion")
    if not rows:
        return []
    table = np.array(rows)
    poses = np.tile(np.eye(4), (len(table), 1, 1))
    quats = table[:, 4:] / np.linalg.norm(table[:, 4:], axis=1, keepdims=True)
    poses[:, :3, :3] = Rotation.from_quat(quats).as_matrix()  # one vectorised call: 20k poses in ~10 ms
    poses[:, :3, 3] = table[:, 1:4]
    return [(float(stamp), pose) for stamp, pose in zip(table[:, 0], poses, strict=True)]


def write_tum(path: str | Path, poses: Iterable[tuple[float, Pose]], header: str | None = None) -> int:
    """Write (stamp, 4x4) pairs as a TUM trajectory file; returns the number of poses written."""
    lines = [f"# {line}" for line in (header or "timestamp tx ty tz qx qy qz qw").splitlines()]
    items = list(poses)
    if items:
        matrices = np.stack([np.asarray(p, dtype=float) for _, p in items])
        if matrices.shape[1:] != (4, 4) or not np.all(np.isfinite(matrices)):
            raise ValueError(f"expected finite 4x4 poses, got shape {matrices.shape[1:]}")
        quats = Rotation.from_matrix(matrices[:, :3, :3]).as_quat()
        quats[quats[:, 3] < 0] *= -1  # one canonical sign keeps written files diff-stable
        for (stamp, _), t, q in zip(items, matrices[:, :3, 3], quats, strict=True):
            values = (*t, *q)
            lines.append(f"{float(stamp):.6f} " + " ".join(f"{v:.9f}" for v in values))
    atomic_write_text(path, "\n".join(lines) + "\n")  # never a truncated trajectory (full disk, kill)
    return len(items)


def read_kitti_poses(path: str | Path) -> list[Pose]:
    """Read a KITTI odometry pose file (12 numbers a line: the top 3x4 of camera-0-to-world) into 4x4s."""
    path = Path(path)
    poses: list[Pose] = []
    for number, fields in _data_lines(path):
        if len(fields) != 12:
            raise DatasetError(f"{path}:{number}: expected 12 values (3x4 row-major), got {len(fields)}")
        try:
            top = np.array([float(f) for f in fields]).reshape(3, 4)
        except ValueError as exc:
            raise DatasetError(f"{path}:{number}: bad KITTI pose line: {exc}") from exc
        pose = np.eye(4)
        pose[:3, :] = top
        poses.append(pose)
    return poses


def write_kitti_poses(path: str | Path, poses: Iterable[Pose]) -> int:
    """Write 4x4 poses as KITTI lines (12 numbers, row-major 3x4); returns the number written."""
    lines = []
    for pose in poses:
        pose = np.asarray(pose, dtype=float)
        if pose.shape != (4, 4):
            raise ValueError(f"expected a 4x4 pose, got shape {pose.shape}")
        lines.append(" ".join(f"{v:.9e}" for v in pose[:3, :].ravel()))
    atomic_write_text(path, "\n".join(lines) + ("\n" if lines else ""))
    return len(lines)


KITTI_RATE_HZ = 10.0  # KITTI pose files carry no stamps: pose i is at i / rate (the sequences' nominal rate)


def read_trajectory(path: str | Path, fmt: str = "auto", rate_hz: float = KITTI_RATE_HZ) -> list[tuple[float, Pose]]:
    """(stamp, 4x4 camera-to-world) from a TUM file or a KITTI pose file (stamps i / rate_hz), the format told by
    `fmt` or, with "auto", by the first data line (8 fields: TUM, 12: KITTI). Why both: SLAM systems write either
    (ORB-SLAM writes KITTI files for stereo sequences), and a user should not have to convert one."""
    path = Path(path).expanduser()
    if fmt not in ("auto", "kitti", "tum"):
        raise DatasetError(f"trajectory format must be auto, kitti or tum, got {fmt!r}")
    if not path.is_file():
        raise DatasetError(f"trajectory file {path} does not exist")
    if fmt == "auto":
        first = next(iter(_data_lines(path)), (0, []))[1]
        if len(first) not in (8, 12):
            raise DatasetError(f"{path} is neither a TUM trajectory (stamp tx ty tz qx qy qz qw) nor a KITTI pose file "
                               f"(12 numbers a line): its first data line has {len(first)} fields")
        fmt = "kitti" if len(first) == 12 else "tum"
    if fmt == "tum":
        return read_tum(path)
    if not rate_hz > 0:
        raise DatasetError(f"a KITTI pose file needs a positive rate for its stamps, got {rate_hz!r}")
    return [(i / rate_hz, pose) for i, pose in enumerate(read_kitti_poses(path))]


def read_timestamps(path: str | Path) -> list[float]:
    """One stamp per line (KITTI times.txt); '#' comments and blank lines skipped."""
    path = Path(path)
    stamps: list[float] = []
    for number, fields in _data_lines(path):
        try:
            stamps.append(float(fields[0]))
        except ValueError as exc:
            raise DatasetError(f"{path}:{number}: bad timestamp: {exc}") from exc
    return stamps


def orthonormalize_pose(pose: Pose) -> Pose:
    """Project the rotation block onto SO(3) (SVD) so drifted ground truth (7-Scenes: det ~0.9995) is rigid."""
    pose = np.array(pose, dtype=float)
    u, _, vt = np.linalg.svd(pose[:3, :3])
    rotation = u @ vt
    if np.linalg.det(rotation) < 0:
        u[:, -1] *= -1
        rotation = u @ vt
    pose[:3, :3] = rotation
    pose[3] = (0.0, 0.0, 0.0, 1.0)
    return pose

"""Small rigid-body helpers shared across the project."""

from __future__ import annotations

import numpy as np


def inv_rigid(t: np.ndarray) -> np.ndarray:
    """Inverse of (..., 4, 4) rigid transforms without a general matrix inverse."""
    out = np.zeros_like(t)
    rt = np.swapaxes(t[..., :3, :3], -1, -2)
    out[..., :3, :3] = rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", rt, t[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def rotation_angle(rot_a: np.ndarray, rot_b: np.ndarray) -> np.ndarray:
    """The angle between (..., 3, 3) rotations, radians (the loop closer's gates, the backend's closure errors)."""
    cos = (np.einsum("...ij,...ij->...", rot_a, rot_b) - 1.0) / 2.0
    return np.arccos(np.clip(cos, -1.0, 1.0))


def correction(corrected: np.ndarray, odometry: np.ndarray) -> np.ndarray:
    """The correction of (..., 4, 4) frames: what takes their odometry pose to their corrected pose
    (`corrected @ inv(odometry)`, in the world frame)."""
    return corrected @ inv_rigid(odometry)


def carry_correction(corrected_ref: np.ndarray, odometry_ref: np.ndarray, odometry: np.ndarray) -> np.ndarray:
    """Corrected pose = correction x odometry: a frame's odometry moved by a reference frame's correction (the
    newest corrected frame before it, or the pose-graph node it rides on). The one place this is computed: the
    backend's pose graph, the associator's pose book and the viz sink all call it."""
    return correction(corrected_ref, odometry_ref) @ odometry


def interpolate_pose(a: np.ndarray, b: np.ndarray, w: float) -> np.ndarray:
    """The pose a fraction `w` (0..1) of the way from `a` to `b` (4x4): slerp on rotation, linear on translation.
    The one place poses are interpolated: ground truth between samples, bag poses between messages, frames a SLAM
    lost between the poses around the gap."""
    from scipy.spatial.transform import Rotation, Slerp

    w = min(max(float(w), 0.0), 1.0)
    out = np.eye(4)
    out[:3, :3] = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([a[:3, :3], b[:3, :3]])))([w]).as_matrix()[0]
    out[:3, 3] = (1.0 - w) * a[:3, 3] + w * b[:3, 3]
    return out


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray | None = None) -> np.ndarray:
    """Camera-to-world pose of an OpenCV camera (x right, y down, z forward) at `eye` looking at `target`."""
    up = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, float)
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    forward = target - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    pose = np.eye(4)
    pose[:3, :3] = np.column_stack([right, down, forward])
    pose[:3, 3] = eye
    return pose

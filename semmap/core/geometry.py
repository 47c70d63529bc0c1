"""Small rigid-body helpers shared across the project."""

from __future__ import annotations

import math

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


def rotation_log(rot: np.ndarray) -> np.ndarray:
    """The rotation vectors (..., 3) of (..., 3, 3) rotations (the log map), as scipy's
    `Rotation.from_matrix(rot).as_rotvec()` to ~1e-12 on proper rotations.

    Why not scipy's: the odometry's repair takes a few of these per frame on the front end's critical path, and a
    scipy `Rotation` costs ~0.1-0.3 ms a call to build (its orthogonalisation and checks); this is plain numpy."""
    rot = np.asarray(rot, dtype=np.float64)
    if rot.ndim == 2:  # one rotation away from pi (the usual case): scalar arithmetic, no array overhead
        (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = rot.tolist()
        vx, vy, vz = r21 - r12, r02 - r20, r10 - r01
        theta = math.atan2(math.sqrt(vx * vx + vy * vy + vz * vz) / 2.0, (r00 + r11 + r22 - 1.0) / 2.0)
        if theta <= math.pi - 1e-3:
            scale = 0.5 + theta * theta / 12.0 if theta < 1e-4 else theta / (2.0 * math.sin(theta))
            return np.array([vx * scale, vy * scale, vz * scale])
    vee = np.stack(
        [rot[..., 2, 1] - rot[..., 1, 2], rot[..., 0, 2] - rot[..., 2, 0], rot[..., 1, 0] - rot[..., 0, 1]], axis=-1
    )  # 2 sin(theta) axis
    sin = np.linalg.norm(vee, axis=-1) / 2.0
    cos = (np.trace(rot, axis1=-2, axis2=-1) - 1.0) / 2.0
    theta = np.arctan2(sin, cos)  # (precise at every angle, where arccos loses half the digits near 0)
    small = theta < 1e-4
    scale = np.where(small, 0.5 + theta * theta / 12.0, theta / (2.0 * np.where(small, 1.0, np.maximum(sin, 1e-300))))
    out = vee * scale[..., None]
    near_pi = theta > np.pi - 1e-3  # (sin ~ 0: the axis from the symmetric part, its sign from vee)
    if np.any(near_pi):
        c = np.clip(cos[near_pi], -1.0, 1.0)[..., None, None]
        sym = (rot[near_pi] + np.swapaxes(rot[near_pi], -1, -2)) / 2.0
        outer = (sym - c * np.eye(3)) / (1.0 - c)  # the axis' outer product
        column = np.argmax(np.diagonal(outer, axis1=-2, axis2=-1), axis=-1)
        axis = np.take_along_axis(outer, column[..., None, None].repeat(3, axis=-1), axis=-2)[..., 0, :]
        axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
        sign = np.where(np.einsum("...i,...i->...", axis, vee[near_pi]) < 0.0, -1.0, 1.0)
        out[near_pi] = axis * (sign * theta[near_pi])[..., None]
    return out


def rotation_exp(rotvec: np.ndarray) -> np.ndarray:
    """The (..., 3, 3) rotations of rotation vectors (..., 3) (Rodrigues' formula; the inverse of
    `rotation_log`)."""
    v = np.asarray(rotvec, dtype=np.float64)
    theta = np.linalg.norm(v, axis=-1)
    small = theta < 1e-4
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta * theta / 6.0, np.sin(theta) / safe)
    b = np.where(small, 0.5 - theta * theta / 24.0, (1.0 - np.cos(theta)) / (safe * safe))
    k = np.zeros(v.shape[:-1] + (3, 3))
    k[..., 0, 1], k[..., 0, 2], k[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    k[..., 1, 0], k[..., 2, 0], k[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    return np.eye(3) + a[..., None, None] * k + b[..., None, None] * (k @ k)


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

"""The rotation log and exp maps of core.geometry against scipy's, at every angle (0, tiny, ordinary, near pi)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from semmap.core.geometry import rotation_exp, rotation_log


def _rotation_vectors() -> np.ndarray:
    rng = np.random.default_rng(3)
    axes = rng.normal(size=(200, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = [0.0, 1e-12, 1e-7, 1e-4, 1e-3, 0.3, 2.0, np.pi - 1e-2, np.pi - 1e-4, np.pi - 1e-9, np.pi]
    return np.concatenate([Rotation.random(2000, random_state=4).as_rotvec()] + [axes * a for a in angles])


def test_log_matches_scipy_and_exp_inverts_it() -> None:
    vectors = _rotation_vectors()
    matrices = Rotation.from_rotvec(vectors).as_matrix()
    logs = rotation_log(matrices)
    assert logs.shape == vectors.shape
    reference = Rotation.from_matrix(matrices).as_rotvec()
    away_from_pi = np.linalg.norm(reference, axis=1) < np.pi - 1e-3  # (at pi, v and -v are the same rotation)
    np.testing.assert_allclose(logs[away_from_pi], reference[away_from_pi], atol=1e-11)
    np.testing.assert_allclose(rotation_exp(logs), matrices, atol=1e-11)
    np.testing.assert_allclose(rotation_exp(vectors), matrices, atol=1e-12)
    assert np.all(np.linalg.norm(logs, axis=1) <= np.pi + 1e-12)
    one_by_one = np.stack([rotation_log(m) for m in matrices])  # (a single rotation takes a scalar path)
    np.testing.assert_allclose(rotation_exp(one_by_one), matrices, atol=1e-11)
    np.testing.assert_allclose(one_by_one[away_from_pi], logs[away_from_pi], atol=1e-12)


def test_single_rotations_keep_their_shape() -> None:
    rot = Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix()
    assert rotation_log(rot).shape == (3,)
    np.testing.assert_allclose(rotation_log(rot), [0.1, -0.2, 0.3], atol=1e-14)
    assert rotation_exp(np.zeros(3)).shape == (3, 3)
    np.testing.assert_array_equal(rotation_exp(np.zeros(3)), np.eye(3))

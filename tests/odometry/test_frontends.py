"""Odometry front ends on real 7-Scenes data: drift strength as documented, RGB-D odometry, trajectory files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from semmap.algorithms.evaluation import ate_rmse
from semmap.algorithms.odometry.frontends import OdometryError, OdometryInput, make_frontend
from semmap.core.config import ConfigError, load_config
from semmap.datasets import open_dataset
from semmap.datasets.trajectory_io import write_tum


@pytest.fixture(scope="module")
def kitchen(kitchen_dir: Path):  # noqa: ANN201
    return open_dataset(str(kitchen_dir))


def _drifted(seed: int, gt: list) -> list:
    cfg = load_config(None, [f"odometry.seed={seed}"]).odometry
    frontend = make_frontend("gt+drift", cfg)
    return [(t, frontend.estimate(OdometryInput(i, t, pose))) for i, (t, pose) in enumerate(gt)]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_default_drift_ends_a_7scenes_run_near_the_documented_ate(kitchen, seed: int) -> None:
    gt = kitchen.groundtruth()
    ate = ate_rmse(gt, _drifted(seed, gt))
    assert 0.08 <= ate <= 0.35, ate


def test_drift_is_seeded(kitchen) -> None:
    gt = kitchen.groundtruth()[:200]
    a, b, c = _drifted(4, gt), _drifted(4, gt), _drifted(5, gt)
    assert all(np.array_equal(x[1], y[1]) for x, y in zip(a, b, strict=True))
    assert not np.allclose(a[-1][1], c[-1][1])


def test_rgbd_odometry_follows_the_real_camera(kitchen) -> None:
    frontend = make_frontend("rgbd", load_config().odometry)
    est, gt = [], []
    for i in range(25):
        f = kitchen[i]
        est.append((f.stamp, frontend.estimate(OdometryInput(i, f.stamp, f.gt_pose, f.rgb, f.depth, f.depth_scale,
                                                             f.intrinsics.matrix))))
        gt.append((f.stamp, f.gt_pose))
    assert ate_rmse(gt, est) < 0.03
    moved = np.linalg.norm(gt[-1][1][:3, 3] - gt[0][1][:3, 3])
    assert moved > 0.02, "the camera moves in these frames"


def test_rgbd_repeats_the_last_trusted_step_over_a_pair_it_barely_registers(kitchen) -> None:
    """A frame whose depth is almost all gone (as when people fill the view and are left out) registers on a few
    pixels: its pair is not trusted, the previous step is repeated and counted; with the gate off (0) the same
    pair is taken as Open3D returns it."""
    config = load_config().odometry

    def frame(i: int, blank: bool = False) -> OdometryInput:
        f = kitchen[i]
        depth = f.depth.copy()
        if blank:
            keep = np.zeros_like(depth)
            keep[180:240, 280:340] = depth[180:240, 280:340]  # 3600 of 307,200 pixels
            depth = keep
        return OdometryInput(i, f.stamp, f.gt_pose, f.rgb, depth, f.depth_scale, f.intrinsics.matrix)

    gated = make_frontend("rgbd", config)
    assert gated.min_fitness == config.rgbd_min_fitness > 0
    p0, p1 = gated.estimate(frame(0)), gated.estimate(frame(1))
    p2 = gated.estimate(frame(2, blank=True))
    assert gated.counters["pairs_low_fitness"] == 1
    np.testing.assert_allclose(p2, p1 @ np.linalg.inv(p0) @ p1, atol=1e-9)  # constant velocity
    trusting = make_frontend("rgbd", config.model_copy(update={"rgbd_min_fitness": 0.0}))
    for i in (0, 1):
        trusting.estimate(frame(i))
    trusting.estimate(frame(2, blank=True))
    assert trusting.counters["pairs_low_fitness"] == 0


def test_trajectory_file_is_matched_by_timestamp(tmp_path: Path) -> None:
    poses = []
    for i in range(10):
        pose = np.eye(4)
        pose[0, 3] = i
        poses.append((i * 0.1, pose))
    write_tum(tmp_path / "t.tum", poses)
    frontend = make_frontend(f"file:{tmp_path / 't.tum'}", load_config(None, ["odometry.repair=false"]).odometry)
    assert not frontend.needs_images
    assert frontend.estimate(OdometryInput(0, 0.31, None))[0, 3] == 3.0
    # checked by default: then it needs the frames' images and their dynamic objects
    checked = make_frontend(f"file:{tmp_path / 't.tum'}", load_config().odometry)
    assert checked.needs_images and checked.uses_dynamic
    with pytest.raises(OdometryError, match="needs RGB, depth and intrinsics"):
        checked.estimate(OdometryInput(0, 0.31, None))


def test_unusable_modes_are_clear_errors() -> None:
    for mode in ("lidar", "file:", "gt:x", "rgbd:"):
        with pytest.raises(ConfigError, match="expected auto, gt, gt[+]drift, rgbd, file:PATH, external, orbslam3"):
            make_frontend(mode, load_config().odometry)
    frontend = make_frontend("gt", load_config().odometry)
    with pytest.raises(OdometryError, match="no ground-truth pose"):
        frontend.estimate(OdometryInput(3, 0.1, None))
    synthetic = open_dataset("synthetic:frames=2")
    assert synthetic[0].gt_pose is not None


def test_file_trajectory_on_another_clock_is_refused_and_an_offset_fixes_it(tmp_path: Path) -> None:
    from semmap.algorithms.odometry.frontends import FileOdometry, check_trajectory_overlap, match_trajectory

    poses = []
    for i in range(30):
        pose = np.eye(4)
        pose[0, 3] = 0.01 * i
        poses.append((1000.0 + i / 30, pose))
    path = tmp_path / "slam.tum"
    write_tum(path, poses)
    frames = [i / 30 for i in range(30)]
    with pytest.raises(OdometryError, match=r"matches only 0 of 30 frames.*1000\.000 \.\. 1000\.967 s.*0\.000 \.\. "
                                            r"0\.967 s.*--time-offset -1000\.000"):
        check_trajectory_overlap(path, frames)
    assert check_trajectory_overlap(path, frames, offset_s=-1000.0).startswith(f"odometry {path}: 30 of 30 frames")
    nearest, matched = match_trajectory(np.array([0.0, 1.0, 2.0]), np.array([-5.0, 0.9, 1.6, 9.0]))
    assert nearest.tolist() == [0, 1, 2, 2] and matched.tolist() == [False, False, False, False]
    front = FileOdometry(path, 0.01, 0.5, time_offset_s=-1000.0)
    got = front.estimate(OdometryInput(7, 7 / 30, None))
    assert got[0, 3] == pytest.approx(0.07) and front.far_matches == 0


def test_dynamic_objects_are_left_out_of_the_depth() -> None:
    from semmap.algorithms.dynamic_mask import mask_dynamic
    from semmap.core.messages import DynamicBox

    depth = np.full((40, 60), 2000, np.uint16)  # a wall at 2 m (units of 1 mm)
    depth[10:30, 20:30] = 1000  # a person at 1 m in front of it
    person = DynamicBox(3, "person", (18.0, 8.0, 32.0, 32.0), 0.9, 1.1, "class")
    whole = mask_dynamic(depth, [person], 0.001, "box")
    assert np.count_nonzero(whole[8:32, 18:32]) == 0 and np.count_nonzero(whole) == 40 * 60 - 24 * 14
    only = mask_dynamic(depth, [person], 0.001, "range")  # the wall behind the person stays
    assert np.count_nonzero(only[10:30, 20:30]) == 0 and np.count_nonzero(only) == 40 * 60 - 20 * 10
    assert mask_dynamic(depth, [person], 0.001, "none") is depth and depth.min() == 1000  # input untouched
    with pytest.raises(ConfigError, match="odometry.dynamic_mask: expected 'box', 'range' or 'none'"):
        load_config(None, ["odometry.dynamic_mask=blur"])

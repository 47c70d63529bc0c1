"""ORB-SLAM3 (RGB-D) as a built-in front end, through the PyPI wheel `pyorbslam3` (an optional extra: GPL-3.0).

Per frame: semmap's dynamic objects (people, animals, things seen moving) are blanked in the colour and depth
images *before* ORB-SLAM3 tracks them, so it neither tracks features on a walking person nor maps them; then the
pose it returns is checked against semmap's own people-masked RGB-D registration (repair.py) and its wrong steps
are overruled. Why both: blanking alone leaves ORB-SLAM3 at ~0.5 m on the Bonn crowd window (a person the
detector misses for a few frames, or whose box lags, drags it), the check alone cannot tell small biases.

Masks: `range` (default) blanks only the pixels of a box whose depth lies in the object's depth band (the person,
not the desk behind it: a box blanks ~35 % of a Bonn frame, the band a third of that); `box` the whole box; `none`
nothing. Blanked colour is set to the image's mean grey, so its straight borders give FAST few corners.

ORB-SLAM3 needs two files: the vocabulary (`odometry.orbslam3_vocabulary`, ORBvoc.txt or one built with
`semmap models vocabulary`: it is never downloaded) and a settings file, written from the frames' own camera
(intrinsics, size, depth scale) unless `odometry.orbslam3_settings` names the user's own. The vocabulary loads once
per process (seconds for a 14 MB vocabulary, tens of seconds for the 145 MB ORBvoc.txt).
"""

from __future__ import annotations

import importlib.util
import math
import tempfile
from pathlib import Path

import numpy as np

from semmap.algorithms.dynamic_mask import dynamic_pixels
from semmap.core.config import OdometryConfig
from semmap.core.messages import DynamicBox

from . import motion_params, repair_params
from .base import OdometryError, OdometryInput, flat
from .checked import CheckedSlam
from .frontends import CheckedSlamFrontEnd

MASKS = ("range", "box", "none")


def installed() -> bool:
    """Whether the `pyorbslam3` wheel can be imported here (without importing it)."""
    return importlib.util.find_spec("pyorbslam3") is not None


def settings_text(fx: float, fy: float, cx: float, cy: float, width: int, height: int, depth_scale: float,
                  fps: float = 30.0, features: int = 1000) -> str:
    """ORB-SLAM3's settings (`File.version: "1.0"` format) for an undistorted pinhole RGB-D camera."""
    return "\n".join([
        "%YAML:1.0",
        'File.version: "1.0"',
        'Camera.type: "PinHole"',
        f"Camera1.fx: {fx:.6f}", f"Camera1.fy: {fy:.6f}", f"Camera1.cx: {cx:.6f}", f"Camera1.cy: {cy:.6f}",
        "Camera1.k1: 0.0", "Camera1.k2: 0.0", "Camera1.p1: 0.0", "Camera1.p2: 0.0", "Camera1.k3: 0.0",
        f"Camera.width: {int(width)}", f"Camera.height: {int(height)}", f"Camera.fps: {max(1, round(fps))}",
        "Camera.RGB: 1",
        "Stereo.ThDepth: 40.0", "Stereo.b: 0.0773",  # close/far point threshold 40 x 7.7 cm = 3.1 m
        f"RGBD.DepthMapFactor: {1.0 / depth_scale:.6f}",
        f"ORBextractor.nFeatures: {int(features)}",
        "ORBextractor.scaleFactor: 1.2", "ORBextractor.nLevels: 8",
        "ORBextractor.iniThFAST: 20", "ORBextractor.minThFAST: 7",
        "Viewer.KeyFrameSize: 0.05", "Viewer.KeyFrameLineWidth: 1.0", "Viewer.GraphLineWidth: 0.9",
        "Viewer.PointSize: 2.0", "Viewer.CameraSize: 0.08", "Viewer.CameraLineWidth: 3.0",
        "Viewer.ViewpointX: 0.0", "Viewer.ViewpointY: -0.7", "Viewer.ViewpointZ: -1.8", "Viewer.ViewpointF: 500.0",
        "",
    ])


def blank_dynamic(rgb: np.ndarray, depth: np.ndarray, boxes: list[DynamicBox], depth_scale: float,
                  how: str) -> tuple[np.ndarray, np.ndarray, float]:
    """Copies of colour and depth with the dynamic objects blanked (grey, depth 0); the blanked fraction. With
    `range`, a box's pixels without depth go too (a person's edges and hair read no depth on most sensors)."""
    if how == "none" or not boxes:
        return rgb, depth, 0.0
    mask = dynamic_pixels(depth, boxes, depth_scale, how, depthless=True)
    if not mask.any():
        return rgb, depth, 0.0
    rgb_out, depth_out = rgb.copy(), depth.copy()
    rgb_out[mask] = np.uint8(np.clip(rgb.mean(), 0, 255))
    depth_out[mask] = 0
    return rgb_out, depth_out, float(mask.mean())


class OrbSlam3Odometry(CheckedSlamFrontEnd):
    """ORB-SLAM3 RGB-D tracking with semmap's dynamic masks and step check (module docstring).

    Not restartable mid-run (ORB-SLAM3's map lives in its process): after a restart the new instance starts a new
    map at the saved pose and the repair chains its steps from there. The SLAM's own word on a frame counts too:
    a pose it tracked on fewer than `orbslam3_weak_points` map points is a weak one, which semmap's registration
    overrules where the two disagree."""

    needs_images = True
    uses_dynamic = True

    def __init__(self, config: OdometryConfig, rate_hz: float = 30.0) -> None:
        if not installed():
            raise OdometryError("odometry orbslam3 needs the pyorbslam3 wheel: pip install 'semmap[orbslam3]' "
                                "(./dev.sh setup installs it)")
        vocabulary = Path(config.orbslam3_vocabulary) if config.orbslam3_vocabulary else None
        if vocabulary is None or not vocabulary.is_file():
            raise OdometryError(
                "odometry orbslam3 needs a vocabulary file: --set odometry.orbslam3_vocabulary=PATH (ORBvoc.txt, or "
                "one built from your images with `semmap models vocabulary IMAGES --out FILE`)"
                + (f"; {vocabulary} does not exist" if vocabulary is not None else ""))
        if config.orbslam3_mask not in MASKS:
            raise OdometryError(f"odometry.orbslam3_mask must be one of {MASKS}, got {config.orbslam3_mask!r}")
        self.vocabulary = vocabulary
        self.user_settings = Path(config.orbslam3_settings) if config.orbslam3_settings else None
        self.features = config.orbslam3_features
        self.mask = config.orbslam3_mask
        self.rate_hz = rate_hz
        super().__init__((config.orbslam3_sigma_translation_m, math.radians(config.orbslam3_sigma_rotation_deg)),
                         CheckedSlam(repair_params(config), config.dynamic_mask, config.repair, motion_params(config)))
        self.needs_images = self.uses_dynamic = True  # (ORB-SLAM3 tracks the images, its masks need the boxes)
        self.weak_points = config.orbslam3_weak_points
        self.refines_at_end = config.orbslam3_refinement  # (its steps as refined: `refinement`, refinement.py)
        self._slam = None
        self._tmp: tempfile.TemporaryDirectory | None = None
        self._anchor: np.ndarray | None = None  # world <- ORB-SLAM3's map of the first frame
        self._restored = False
        self.counters.update({"orb_lost": 0, "orb_recently_lost": 0, "orb_not_initialized": 0,
                              "orb_blanked_permille": 0, "orb_weak": 0})
        self._blanked_sum, self._frames = 0.0, 0  # the blanked share of the image, summed (a running mean)

    def _start(self, frame: OdometryInput) -> None:
        import pyorbslam3  # heavy (ORB-SLAM3 and its own OpenCV): only when this front end runs

        settings = self.user_settings
        if settings is None:
            k = np.asarray(frame.intrinsics, float)
            h, w = frame.depth.shape
            self._tmp = tempfile.TemporaryDirectory(prefix="semmap-orbslam3-")
            settings = Path(self._tmp.name) / "camera.yaml"
            settings.write_text(settings_text(k[0, 0], k[1, 1], k[0, 2], k[1, 2], w, h, frame.depth_scale,
                                              self.rate_hz, self.features))
        try:
            self._slam = pyorbslam3.Slam(str(self.vocabulary), str(settings), sensor=pyorbslam3.Sensor.RGBD,
                                         use_viewer=False)
        except Exception as exc:  # the wheel raises plain exceptions for unreadable files
            raise OdometryError(f"ORB-SLAM3 could not start with vocabulary {self.vocabulary} and settings "
                                f"{settings}: {exc}") from None

    def estimate(self, frame: OdometryInput) -> np.ndarray:
        if frame.rgb is None or frame.depth is None or frame.intrinsics is None:
            raise OdometryError("odometry orbslam3 needs RGB, depth and intrinsics")
        if self._slam is None:
            self._start(frame)
        pose = self.checked_pose(frame, track=lambda: self._track(frame))
        self.counters["orb_blanked_permille"] = int(1000 * self._blanked_sum / self._frames)
        return pose

    def _track(self, frame: OdometryInput) -> tuple[np.ndarray | None, bool, bool]:
        """ORB-SLAM3's reading of one frame, its dynamic objects blanked first (in a thread of the check's: beside
        semmap's registration of the frame)."""
        boxes = list(frame.dynamic or [])
        rgb, depth, blanked = blank_dynamic(frame.rgb, frame.depth, boxes, frame.depth_scale, self.mask)
        self._blanked_sum += blanked
        self._frames += 1
        result = self._slam.track_rgbd(np.ascontiguousarray(rgb), np.ascontiguousarray(depth), float(frame.stamp))
        state = str(result.state).rsplit(".", 1)[-1]
        slam_pose = None
        weak = False
        if result.pose_valid and state == "OK":
            slam_pose = np.asarray(result.pose_wc, dtype=np.float64)
            if self._anchor is None:
                # semmap's world: the first ground-truth pose where the data has one (as `rgbd`), else ORB's map
                start = frame.gt_pose if (frame.gt_pose is not None and not self._restored) else None
                self._anchor = (start @ np.linalg.inv(slam_pose)) if start is not None else np.eye(4)
            slam_pose = self._anchor @ slam_pose
            weak = int(getattr(result, "num_tracked_points", self.weak_points)) < self.weak_points
            self.counters["orb_weak"] += int(weak)
        elif state == "NOT_INITIALIZED":
            self.counters["orb_not_initialized"] += 1
        elif state == "RECENTLY_LOST":  # (it may find its map again: the gap is then bridged by its own motion)
            self.counters["orb_recently_lost"] += 1
        else:  # LOST: its next map starts anew, in a frame of its own
            self.counters["orb_lost"] += 1
            self.check.repair.break_chain()
        return slam_pose, weak, True

    def _refined(self) -> list[tuple[float, np.ndarray]]:
        """After `shutdown`: ORB-SLAM3's own trajectory as it saves it, after its last bundle adjustments, for the
        frames it posed itself, in semmap's world (`SLAM_REFINED_TRAJECTORY`). Why keep it: it is what ORB-SLAM3
        alone gives a user, so semmap's result is held against it too. It is not always the better one (7-Scenes
        0.048 against 0.051 m as tracked; the fr1_rpy window 0.023-0.050 against 0.025-0.029 m). Empty where its
        poses are in more than one map (it lost track for good and started anew, or restarted): one anchor cannot
        place them."""
        if not self.slam_trajectory or self._anchor is None or self._restored or self.counters["orb_lost"]:
            return []
        from semmap.datasets.trajectory_io import read_tum

        if self._tmp is None:
            self._tmp = tempfile.TemporaryDirectory(prefix="semmap-orbslam3-")
        path = Path(self._tmp.name) / "refined.tum"
        try:  # (after every other output of the run is written: see the odometry service's `write_outputs`)
            self._slam.save_trajectory_tum(str(path))
            saved = read_tum(path)
        except Exception:  # (the wheel raises plain exceptions; a missing refinement loses nothing of the run)
            return []
        if not saved:
            return []
        saved.sort(key=lambda row: row[0])
        stamps = np.array([t for t, _ in saved])
        wanted = np.array([t for t, _ in self.slam_trajectory])
        # each frame's nearest saved stamp (ORB-SLAM3 writes them to the microsecond), by bisection: a run of hours
        # has a hundred thousand frames
        after = np.searchsorted(stamps, wanted)
        lo, hi = np.clip(after - 1, 0, len(stamps) - 1), np.clip(after, 0, len(stamps) - 1)
        nearest = np.where(np.abs(stamps[lo] - wanted) <= np.abs(stamps[hi] - wanted), lo, hi)
        return [(float(t), self._anchor @ saved[i][1]) for t, i in zip(wanted, nearest, strict=True)
                if abs(stamps[i] - t) < 1e-3]

    def state(self) -> dict:
        return {**self.check.state(), "anchor": flat(self._anchor)}

    def restore(self, state: dict) -> None:
        self.check.restore(state)
        self.check.break_chain()  # a new ORB-SLAM3 instance starts a new map: its first step says nothing
        self._restored = True

    def close(self) -> None:
        self.check.close()
        if self._slam is not None:
            try:
                self._slam.shutdown()
                self.refined_trajectory = self._refined()
            finally:
                self._slam = None
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None

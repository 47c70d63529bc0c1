"""Odometry front ends, picked by name (`odometry.mode`) the way datasets are (semmap/datasets/__init__.py).

A mode is `auto` (the default, `resolve_mode`: a real front end), a registered name (`orbslam3`, `rgbd`, and the
simulations `gt`, `gt+drift`) or `name:ARGUMENT` for a front end that takes one
(`file:PATH`). `create_frontend(mode, section)` builds it from the `odometry` section; `check_mode` is the one
place a mode is parsed and refused (a ConfigError naming `odometry.mode`, before a run starts). New front ends
join via `register`; their module is imported only when one is built.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from semmap.core.config import ConfigError, OdometryConfig

if TYPE_CHECKING:
    from semmap.algorithms.odometry.frontends import FrontEnd

__all__ = ["AUTO", "FrontEndKind", "available", "check_mode", "create_frontend", "motion_params", "register",
           "repair_params", "resolve_mode"]

AUTO = "auto"  # the default: a real front end (see resolve_mode)


@dataclass(frozen=True)
class FrontEndKind:
    name: str
    description: str
    create: Callable[[OdometryConfig, str], FrontEnd]  # (section, argument) -> front end
    takes_argument: bool  # `name:ARGUMENT`
    needs_groundtruth: bool  # every frame must carry a ground-truth pose
    simulated: bool = False  # made from ground truth, not measured: the banner and summary say so


_REGISTRY: dict[str, FrontEndKind] = {}


def register(
    name: str,
    create: Callable[[OdometryConfig, str], FrontEnd],
    description: str,
    takes_argument: bool = False,
    needs_groundtruth: bool = False,
    simulated: bool = False,
) -> None:
    _REGISTRY[name] = FrontEndKind(name, description, create, takes_argument, needs_groundtruth, simulated)


def available() -> dict[str, str]:
    """{mode as written: description} of every registered front end."""
    modes = {f"{k.name}:PATH" if k.takes_argument else k.name: k.description for k in _REGISTRY.values()}
    return {AUTO: "orbslam3 where the pyorbslam3 wheel is installed (with a vocabulary set, in the model dir, or built "
                  "from the recording's frames), else rgbd", **modes}


def check_mode(mode: str) -> tuple[FrontEndKind, str]:
    """The front end `mode` names and its argument; a ConfigError naming `odometry.mode` otherwise."""
    if mode == AUTO:
        mode = resolve_mode(mode, None)
    name, sep, argument = mode.partition(":")
    kind = _REGISTRY.get(name)
    if kind is None or kind.takes_argument != bool(sep) or (sep and not argument):
        raise ConfigError(f"odometry.mode: expected {', '.join(available())} (registered front ends), got {mode!r}")
    return kind, argument


def resolve_mode(mode: str, section: OdometryConfig | None, synthetic: bool = False) -> str:
    """The front end `auto` stands for: on the synthetic world its simulated odometry (`gt+drift`: the whole world
    is simulated there); elsewhere ORB-SLAM3 where the pyorbslam3 wheel is installed and a vocabulary file is set
    (`odometry.orbslam3_vocabulary`), else the built-in `rgbd`. Never a simulation of real data. Other modes
    are returned as they are."""
    if mode != AUTO:
        return mode
    if synthetic:
        return "gt+drift"
    from .orbslam3 import installed

    vocabulary = section.orbslam3_vocabulary if section is not None else ""
    if installed() and vocabulary and Path(vocabulary).is_file():
        return "orbslam3"
    return "rgbd"


def create_frontend(mode: str, section: OdometryConfig) -> FrontEnd:
    kind, argument = check_mode(resolve_mode(mode, section))
    return kind.create(section, argument)


def _gt(c: OdometryConfig, _: str) -> FrontEnd:
    from .frontends import GroundTruthOdometry

    return GroundTruthOdometry(c.gt_sigma_translation_m, c.gt_sigma_rotation_deg)


def _drift(c: OdometryConfig, _: str) -> FrontEnd:
    from .frontends import DriftingOdometry

    if c.drift_profile == "vehicle":  # (auto is pinned to the data's platform by `semmap run`; unpinned: handheld)
        return DriftingOdometry(c.seed, c.drift_vehicle_translation_sigma, c.drift_vehicle_yaw_sigma_deg,
                                c.drift_vehicle_yaw_bias_deg, bias_horizon_frames=c.drift_bias_horizon_frames,
                                per_metre=True)
    return DriftingOdometry(
        c.seed,
        c.drift_translation_sigma_m,
        c.drift_yaw_sigma_deg,
        c.drift_yaw_bias_deg,
        bias_horizon_frames=c.drift_bias_horizon_frames,
    )


def _rgbd(c: OdometryConfig, _: str) -> FrontEnd:
    from .frontends import RgbdOdometry

    return RgbdOdometry(c.rgbd_sigma_translation_m, c.rgbd_sigma_rotation_deg, c.dynamic_mask, c.rgbd_min_fitness)


def _file(c: OdometryConfig, path: str) -> FrontEnd:
    from .frontends import FileOdometry

    return FileOdometry(path, c.file_sigma_translation_m, c.file_sigma_rotation_deg, c.file_time_offset_s,
                        repair=c.repair, dynamic_mask=c.dynamic_mask, repair_gates=repair_params(c),
                        rate_hz=c.file_rate_hz, measured_sigmas_after=_measured(c), motion=motion_params(c))


def repair_params(c: OdometryConfig):  # noqa: ANN201 - RepairParams (imported only when a front end checks)
    """The step check's settings (`odometry.repair_*`, `odometry.arbiter_*`) as the repair takes them."""
    from .arbiter import ArbiterParams
    from .repair import RepairParams

    arbiter = ArbiterParams(window_frames=c.arbiter_window_frames, long_window_frames=c.arbiter_long_window_frames,
                            min_t=c.arbiter_min_t, min_matches=c.arbiter_min_matches,
                            sparse_min_inliers=c.arbiter_sparse_min_inliers)
    return RepairParams(c.repair_translation_m, c.repair_rotation_deg, c.repair_min_fitness, scope=c.repair_scope,
                        hold_s=c.repair_hold_s, arbiter=arbiter, witness_every=c.repair_witness_every,
                        registration_scale=2 if c.registration_resolution == "half" else 1,
                        witness=c.repair_witness, behind_check_every=c.repair_behind_check_every,
                        gap_half_life_s=c.repair_gap_half_life_s)


def motion_params(c: OdometryConfig):  # noqa: ANN201 - MotionParams
    """When a dynamic object counts as moving (`odometry.motion_*`): what opens the repair's scope."""
    from .motion import MotionParams

    return MotionParams(c.motion_window_s, c.motion_min_spread_m, c.motion_min_views, c.motion_persist_views)


def _external(c: OdometryConfig, _: str) -> FrontEnd:
    from .frontends import ExternalSlamOdometry

    return ExternalSlamOdometry(c.file_sigma_translation_m, c.file_sigma_rotation_deg, c.repair, c.dynamic_mask,
                                repair_params(c), measured_sigmas_after=_measured(c), motion=motion_params(c))


def _measured(c: OdometryConfig) -> int:
    """Steps semmap must have witnessed before the SLAM's declared sigmas are measured ones (0: never)."""
    return c.file_sigma_measured_after if c.file_sigma_measured else 0


def _orbslam3(c: OdometryConfig, _: str) -> FrontEnd:
    from .orbslam3 import OrbSlam3Odometry

    return OrbSlam3Odometry(c)


register("gt", _gt, "SIMULATED: the dataset's ground truth (tight declared covariance)", needs_groundtruth=True,
         simulated=True)
register(
    "gt+drift", _drift, "SIMULATED: ground truth with seeded drift that grows like a visual odometry's",
    needs_groundtruth=True, simulated=True,
)
register("rgbd", _rgbd, "Open3D RGB-D odometry between consecutive frames (dynamic objects left out)")
register("file", _file, "a TUM trajectory written by any SLAM, matched to frames by time, its steps checked by "
         "semmap where objects move (odometry.repair)", takes_argument=True)
register("external", _external, "a live SLAM's poses from the `slam` key (client, ROS 2), its steps checked by "
         "semmap where objects move (semmap run external --check-slam)")
register("orbslam3", _orbslam3, "ORB-SLAM3 RGB-D (pyorbslam3 wheel) with semmap's dynamic masks and step check")

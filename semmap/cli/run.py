"""`semmap run`: validate the configuration and the dataset, then start every service as its own process."""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from semmap.core import dataflow, environment
from semmap.core.dataflow import OWN_FRONT_ENDS

if TYPE_CHECKING:
    from semmap.core.config import Config
    from semmap.datasets.base import Dataset
    from semmap.runtime.orchestrator import RunPlan

ORDER = 0  # first in `semmap --help`

# services a run starts, in data-flow order; each is `python -m semmap.services.<name>` (semmap/core/dataflow.py)
PIPELINE = dataflow.PIPELINE


def pipeline_specs(data: str, config: Config, detectors: int, viz: bool, only: list[str] | None = None,
                   serve: bool = False, prior_map: Path | None = None, check_slam: bool = False) -> list:
    """What `semmap run` starts: every stage (or `only` these), the detector `detectors` times, the Rerun sink
    unless disabled. An external run has no odometry service, unless it checks the SLAM's poses (`check_slam`:
    the odometry service repairs what the SLAM publishes on the `slam` key) or poses the frames itself
    (`--odometry orbslam3` or `rgbd`: the robot's own poses are then not sent). The wiring (which stage waits for
    which, who lockstep playback waits for) is the dataflow's; the flags added here are this run's options."""
    from semmap.runtime.orchestrator import ServiceSpec

    own_front_end = data == "external" and config.odometry.mode in OWN_FRONT_ENDS  # (it poses the frames itself)
    chosen = [n for n in PIPELINE if (only is None or n in only)
              and not (data == "external" and n == "odometry" and not (check_slam or own_front_end))]
    if not (viz and config.viz.enabled):
        chosen = [n for n in chosen if n != "viz"]
    specs = []
    for name in chosen:
        extra = dataflow.wiring_flags(name, chosen)
        if name == "associator" and prior_map is not None:
            extra += ["--prior-map", str(prior_map)]
        elif name == "backend":
            extra += (["--write-odometry"] if data == "external" else []) + (  # external: record the SLAM's poses
                ["--prior-map", str(prior_map)] if prior_map is not None else [])
        elif name == "viz" and serve:
            extra += ["--serve"]
        node = dataflow.node(name)
        specs.append(ServiceSpec(name, extra, replicas=detectors if node.replicas == "--detectors" else 1,
                                 lockstep=node.lockstep))
    return specs


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", help="run the whole pipeline on a dataset (or 'synthetic')",
                       description="Start every service as its own process over Zenoh and play DATA through them.")
    p.add_argument("data", help="dataset path (7-Scenes, TUM RGB-D, KITTI odometry), 'synthetic[:frames=N,seed=S]', "
                   "'synthetic:trajectory=PATH' (a generated street along a KITTI/TUM trajectory file) "
                   "or 'external' (no player or odometry: a SLAM publishes frames and poses, "
                   "see semmap.runtime.client)")
    p.add_argument("--out", default="out", help="output directory (default: out)")
    p.add_argument("--odometry", default=None, help="auto (default: orbslam3 where installed, else rgbd) | orbslam3 | "
                   "rgbd | file:PATH | gt | gt+drift (the last two SIMULATE odometry from ground truth)")
    p.add_argument("--check-slam", action="store_true",
                   help="external: the SLAM publishes its own poses on the `slam` key (SemmapClient(check_slam=True), "
                   "semmap ros2 check_slam:=true) and semmap checks each step against its own people-masked "
                   "registration before they become odometry (docs/ORBSLAM3.md)")
    p.add_argument("--seed", type=int, default=None, help="seed of the drifting odometry")
    p.add_argument("--time-offset", type=float, default=None, metavar="SECONDS",
                   help="with --odometry file:PATH: added to the trajectory's stamps before matching them to frames")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--lockstep", dest="mode", action="store_const", const="lockstep",
                      help="wait for the pipeline after every frame: deterministic (default)")
    mode.add_argument("--realtime", dest="mode", action="store_const", const="realtime",
                      help="play at the dataset rate; services drop what they cannot keep up with")
    p.add_argument("--config", default=None, help="YAML config (the layout `semmap config show` prints; any subset)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE")
    p.add_argument("--robot", default=None, help="robot name used in the key expressions")
    p.add_argument("--max-frames", type=int, default=None, help="play at most N frames")
    p.add_argument("--topics", default=None, metavar="ROLE=TOPIC,...",
                   help="ROS bags: topics to use (color, depth, camera_info, pose, groundtruth; default: found by "
                   "message type), e.g. color=/camera/color/image_raw,pose=/odom")
    p.add_argument("--start-frame", type=int, default=None,
                   help="begin at this frame of the dataset (a later session of the same recording)")
    p.add_argument("--map", default=None, metavar="PRIOR",
                   help="start from a saved map (a run directory or its map.sqlite): relocalise against its objects, "
                        "then map in its frame (docs/MAPS.md)")
    p.add_argument("--detectors", type=int, default=None,
                   help="detector replicas (default 1; in real time, as many as this machine's measured layout "
                        "detects most often with: `semmap models doctor`)")
    p.add_argument("--connect", default=None, help="join a Zenoh router (e.g. tcp/127.0.0.1:7447) instead of "
                   "hosting the bus; env SEMMAP_ZENOH_CONNECT")
    p.add_argument("--zenoh-mode", default=None, choices=("peer", "client"))
    p.add_argument("--zenoh-config", default=environment.read(environment.ZENOH_CONFIG), metavar="FILE_OR_DIR",
                   help="Zenoh configuration (TLS, access control; env SEMMAP_ZENOH_CONFIG): one file for every "
                   "process, or a folder with one <service>.json5 per identity (docs/SECURITY.md)")
    p.add_argument("--deadline", type=float, default=None, metavar="S",
                   help="fail the run if it takes longer than S seconds (default: run.deadline_s, 0 = none)")
    existing = p.add_mutually_exclusive_group()
    existing.add_argument("--resume", action="store_true",
                          help="continue the interrupted run in a non-empty --out (services from their journals)")
    existing.add_argument("--overwrite", action="store_true",
                          help="replace the previous run in a non-empty --out")
    p.add_argument("--no-viz", action="store_true", help="do not record run.rrd")
    p.add_argument("--serve", action="store_true",
                   help="serve the Rerun web viewer for the live run (http://localhost:9090)")
    p.add_argument("--only", default=None, metavar="SERVICES",
                   help=f"start only these services (comma-separated; the player always runs): {','.join(PIPELINE)}")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("-v", "--verbose", action="store_true")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    found = preflight(args)
    if isinstance(found, int):
        return found
    return _start(found.plan, args, found.config, found.dataset, found.dataset_camera, found.odometry_line)


@dataclasses.dataclass
class Preflight:
    """What `semmap run` decided before any process starts: the run plan, the effective configuration (the user's
    settings with every decision made for this run: front end, detector, real time), the dataset opened for the
    checks and the banner's lines."""

    plan: RunPlan
    config: Config
    dataset: Dataset | None
    dataset_camera: str
    odometry_line: str


def _user_overrides(args: argparse.Namespace) -> tuple[list[str], Path | None] | int:
    """The `section.key=value` overrides the command line says, and the prior map (or an exit status)."""
    overrides = list(args.overrides)
    for flag, key in ((args.odometry, "odometry.mode"), (args.seed, "odometry.seed"),
                      (args.max_frames, "run.max_frames"), (args.topics, "rosbag.topics"),
                      (args.start_frame, "run.start_frame"), (args.time_offset, "odometry.file_time_offset_s")):
        if flag is not None and flag != "":
            overrides.append(f"{key}={flag}")
    prior_map = None
    if args.map is not None:
        from semmap.cli.diff_merge import prior_map_path

        try:
            prior_map = prior_map_path(args.map, Path(args.out))
        except ValueError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
    if args.check_slam:
        if args.odometry in OWN_FRONT_ENDS:
            print(f"error: --check-slam checks the SLAM's own poses; --odometry {args.odometry} poses the frames with "
                  "semmap's front end instead: choose one", file=sys.stderr)
            return 2
        if args.data != "external":
            print("error: --check-slam is for `semmap run external` (a dataset's SLAM: --odometry file:TRAJ.tum, "
                  "checked by default)", file=sys.stderr)
            return 2
        overrides.append("odometry.mode=external")
    return overrides, prior_map


def preflight(args: argparse.Namespace) -> Preflight | int:
    """Every check and decision before a process starts, each once: the configuration validated as the user gave
    it, the decisions for this run appended as overrides (the front end, real time's settings, the detector), the
    effective configuration validated once more with them. An exit status (2) where something is wrong, said."""
    from semmap.core.config import ConfigError, load_config
    from semmap.runtime.orchestrator import RunPlan

    found = _user_overrides(args)
    if isinstance(found, int):
        return found
    overrides, prior_map = found
    try:
        config = load_config(args.config, overrides)  # the user's settings, before anything starts
        check_plugins(config)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.resume:  # before the lock or anything else touches the folder: a finished run stays as it is
        done = completed_run(Path(args.out))
        if done:
            print(f"error: --out {args.out} holds a completed run ({done}): nothing to resume; nothing was "
                  "changed (--overwrite runs it again, or choose another --out)", file=sys.stderr)
            return 2
    special = args.data in ("synthetic", "external") or args.data.startswith("synthetic:")
    odometry_line = ""
    if args.data != "external":
        chosen, odometry_line = choose_odometry(config, synthetic=special, data=args.data)
        overrides += chosen
    elif config.odometry.mode in OWN_FRONT_ENDS:  # (a camera's frames posed by semmap's own front end)
        chosen, odometry_line = choose_odometry(config, synthetic=False)
        if config.odometry.mode == "orbslam3" and not any(o.startswith("odometry.orbslam3_vocabulary") for o in chosen)\
                and not config.odometry.orbslam3_vocabulary:
            print("error: --odometry orbslam3 on an external run needs an ORB vocabulary (there are no frames to "
                  "build one from before the run): build one from your camera's images with `semmap models "
                  "vocabulary IMAGES --out FILE`, then --set odometry.orbslam3_vocabulary=FILE (or keep it as "
                  "orbvoc.txt in the model directory)", file=sys.stderr)
            return 2
        overrides += chosen
    realtime = (args.mode or config.run.mode) == "realtime"
    overrides += realtime_front_end(config, realtime)
    if config.detector.kind == "auto":  # decided here, for this dataset, once for every process of the run
        from semmap.algorithms.detector import AUTO, resolve_kind

        synthetic = args.data == "synthetic" or args.data.startswith("synthetic:")
        overrides.append(f"detector.kind={resolve_kind(AUTO, synthetic)}")
    config = load_config(args.config, overrides)  # the effective configuration, with this run's decisions
    try:  # (after `special`: the detector `auto` picks depends on the data)
        check_detector_classes(config, args.data, args.mode or config.run.mode)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    checked = _check_inputs(args, config, special)
    if isinstance(checked, int):
        return checked
    dataset, dataset_camera, only = checked
    with_detector = "detector" in (only or PIPELINE)
    budget = (detector_budget(config, dataset, args.data, overrides, args.detectors)
              if realtime and with_detector else None)  # fmt: skip
    detectors = args.detectors or int((budget or {}).get("replicas", 1))
    specs = pipeline_specs(args.data, config, detectors, not args.no_viz, only, args.serve, prior_map,
                           args.check_slam)
    run = config.run
    deadline = args.deadline if args.deadline is not None else run.deadline_s
    plan = RunPlan(data=args.data, out_dir=Path(args.out), robot=args.robot or run.robot,
                   mode=args.mode or run.mode, services=specs, config_path=args.config,
                   overrides=overrides, connect=args.connect, zenoh_mode=args.zenoh_mode,
                   zenoh_config=args.zenoh_config, verbose=args.verbose, quiet=args.quiet, deadline_s=deadline,
                   # (an external SLAM may connect whenever it likes: no stall limit without a player)
                   stall_s=0.0 if args.data == "external" else
                   run.start_timeout_s + 2 * run.frame_timeout_s + 30.0,
                   resume=args.resume, budget=budget)
    mode = config.odometry.mode
    plan.odometry = mode if args.data != "external" or args.check_slam or mode in OWN_FRONT_ENDS else "unchecked"
    if args.data != "external":
        plan.simulated_odometry = simulated_odometry(mode)
        plan.camera = dataset_camera
    return Preflight(plan, config, dataset, dataset_camera, odometry_line)


def _check_inputs(args: argparse.Namespace, config: Config,
                  special: bool) -> tuple[Dataset | None, str, list[str] | None] | int:
    """The dataset (opened once for every check), a trajectory file's clock, the services asked for and the
    Zenoh config file: (dataset, its camera line, the services to start) or an exit status."""
    if not special and not Path(args.data).exists():
        print(f"error: dataset path {args.data} does not exist", file=sys.stderr)
        return 2
    dataset = None
    dataset_camera = ""  # the camera line of the banner (calibration checked in preflight_dataset)
    if not special:  # opened once for every check before the run (a bag's missing topic fails here, listing them)
        opened = _open_dataset(args.data, config)
        if opened is None:
            return 2
        dataset, dataset_camera = opened
    if args.detectors is not None and args.detectors < 1:
        print("error: --detectors must be at least 1", file=sys.stderr)
        return 2
    mode = config.odometry.mode
    if mode.startswith("file:") and args.data != "external":
        message = _check_file_odometry(dataset, args.data, mode[5:], config)
        if message.startswith("error:"):
            print(message, file=sys.stderr)
            return 2
        print(f"semmap: {message}", file=sys.stderr)
    only = [s.strip() for s in args.only.split(",")] if args.only else None
    unknown = sorted(set(only or []) - set(PIPELINE))
    if unknown:
        print(f"error: unknown service(s) {', '.join(unknown)}; known: {', '.join(PIPELINE)}", file=sys.stderr)
        return 2
    if args.zenoh_config and not Path(args.zenoh_config).exists():
        print(f"error: --zenoh-config {args.zenoh_config} does not exist", file=sys.stderr)
        return 2
    return dataset, dataset_camera, only


def _open_dataset(data: str, config: Config) -> tuple[Dataset, str] | None:
    """The dataset, opened once for every check before the run (a bag's missing topic fails here, listing them),
    and the banner's camera line (the camera stated and checked against the frames before anything starts);
    None, said on stderr, when it cannot be read."""
    from semmap.datasets import DatasetError, open_dataset, reader_options
    from semmap.datasets.calibration import check_dataset_camera

    dataset = None
    try:
        dataset = open_dataset(data, **reader_options(data, config))
        camera = ""
        if len(dataset) > 0:
            camera, warnings = check_dataset_camera(dataset)
            for warning in warnings:
                print(f"semmap: warning: {warning}", file=sys.stderr)
    except DatasetError as exc:
        if dataset is not None and hasattr(dataset, "close"):
            dataset.close()
        print(f"error: {exc}", file=sys.stderr)
        return None
    return dataset, camera


def _start(plan: RunPlan, args: argparse.Namespace, config: Config, dataset: Dataset | None, dataset_camera: str,
           odometry_line: str) -> int:
    """Take the output directory (locked, prepared, writable, the dataset's first frame read), say the odometry
    and the camera, then run the services until the run ends."""
    from semmap.core.outputs import OutputError, OutputLock, check_writable, prepare_output_dir
    from semmap.runtime.orchestrator import Orchestrator

    lock = OutputLock(plan.out_dir)
    try:  # before any process starts: the output directory is ours, empty (or meant to be reused), writable
        try:
            plan.out_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputError(f"cannot create --out {plan.out_dir}: {exc.strerror or exc}") from None
        lock.acquire()
        prepare_output_dir(plan.out_dir, args.resume, args.overwrite)
        check_writable(plan.out_dir, config.run.min_free_mb)
        if dataset is not None:
            preflight_dataset(dataset, args.data, config)
    except OutputError as exc:
        lock.release(refused=True)
        print(f"error: {exc}", file=sys.stderr)
        return 2
    finally:
        if dataset is not None and hasattr(dataset, "close"):  # (bags hold their file open)
            dataset.close()
    plan.lock_fd = lock.fd
    # the odometry (a simulated one above all) and the camera are said even with --quiet: two lines
    for line in start_banner(plan, dataset_camera, odometry_line, config.odometry.drift_profile):
        print(f"semmap: {line}", file=sys.stderr, flush=True)
    try:
        return Orchestrator(plan).run()
    finally:
        lock.release()


def realtime_front_end(config: Config, realtime: bool) -> list[str]:
    """The front end's settings for the run's mode, decided once for every process: in real time it must pose every
    frame on its share of two cores, so semmap's registration works on half-size images and ORB-SLAM3 extracts
    `orbslam3_realtime_features` (where the user left `orbslam3_features` at its default)."""
    section = config.odometry
    out = []
    if section.registration_resolution == "auto":
        out.append(f"odometry.registration_resolution={'half' if realtime else 'full'}")
    default_features = type(section).model_fields["orbslam3_features"].default
    if realtime and section.orbslam3_features == default_features:
        out.append(f"odometry.orbslam3_features={section.orbslam3_realtime_features}")
    return out


def choose_odometry(config: Config, synthetic: bool, data: str = "") -> tuple[list[str], str]:
    """The front end this run uses, decided once, here, and named: `auto` becomes orbslam3 (where the pyorbslam3
    wheel is installed and a vocabulary is set or lies in the model dir as orbvoc.txt) or rgbd; on the synthetic
    world its simulated odometry, whose drift profile `auto` becomes the data's platform (a car drifts per metre).
    Returns the overrides that pin it for every service, and the line that says it."""
    from semmap.algorithms.odometry import AUTO, check_mode, resolve_mode
    from semmap.algorithms.odometry.orbslam3 import installed
    from semmap.runtime.models.model_store import default_vocabulary

    section = config.odometry
    overrides: list[str] = []
    vocabulary, vocabulary_how, no_vocabulary = section.orbslam3_vocabulary, "", ""
    if not vocabulary and installed() and not synthetic and section.mode in (AUTO, "orbslam3"):
        found = default_vocabulary()
        if found is None and data and Path(data).exists():
            from semmap.runtime.models.model_store import VOCABULARY_NAME, get_model_dir
            from semmap.runtime.models.orb_vocabulary import vocabulary_for

            print("semmap: no ORB vocabulary here: building one from this recording's frames (once) ...",
                  file=sys.stderr, flush=True)
            found, vocabulary_how = vocabulary_for(data, get_model_dir() / VOCABULARY_NAME)
            no_vocabulary = vocabulary_how if found is None else ""
        if found is not None:
            vocabulary = str(found)
            overrides.append(f"odometry.orbslam3_vocabulary={vocabulary}")
    mode = resolve_mode(section.mode, section.model_copy(update={"orbslam3_vocabulary": vocabulary}), synthetic)
    if section.mode == AUTO:
        overrides.append(f"odometry.mode={mode}")
    kind, _ = check_mode(mode)
    if kind.name == "gt+drift" and section.drift_profile == "auto":
        from semmap.datasets import platform_of

        overrides.append(f"odometry.drift_profile={platform_of(data) if data else 'handheld'}")
    if kind.simulated:
        return overrides, (f"odometry: {mode} -- SIMULATED odometry made from the data's ground truth, not measured: "
                           "its drift and the correction of it are semmap's own invention (a real front end: "
                           "--odometry orbslam3, rgbd or file:TRAJ.tum)")
    how = {"orbslam3": f"ORB-SLAM3 RGB-D, {vocabulary_how or f'vocabulary {vocabulary}'}",
           "rgbd": "Open3D RGB-D odometry"}.get(kind.name, kind.description)
    repair = (", its steps checked by semmap where objects are seen moving, each disagreement judged on the static "
              "scene (odometry.repair)") if (
        kind.name in ("orbslam3", "file") and section.repair) else ""
    why = ""
    if section.mode == AUTO and mode == "rgbd":
        why = f" (auto: {no_vocabulary if installed() and no_vocabulary else 'no pyorbslam3 wheel here'})"
    return overrides, f"odometry: {mode} ({how}{repair}){why}"


def completed_run(out_dir: Path) -> str:
    """What a run folder's stats.json says of a run that completed ('' if none did there, or it cannot tell)."""
    import json

    try:
        stats = json.loads((out_dir / "stats.json").read_text())
    except (OSError, ValueError):
        return ""
    if not isinstance(stats, dict) or stats.get("outcome") != "completed":
        return ""
    frames = stats.get("frames") if isinstance(stats.get("frames"), dict) else {}
    return f"{frames.get('processed', '?')} frames processed, stats.json says completed"


def simulated_odometry(mode: str) -> bool:
    """gt / gt+drift (front ends that need ground truth): poses made from the ground truth, not measured."""
    from semmap.algorithms.odometry import check_mode

    return check_mode(mode)[0].needs_groundtruth


def start_banner(plan: RunPlan, camera: str, odometry_line: str = "", drift_profile: str = "handheld") -> list[str]:
    """What the run says before its first frame: the odometry (simulated said out loud; a real front end named
    with why it was chosen: `choose_odometry`) and the camera."""
    if plan.data == "external" and plan.odometry in OWN_FRONT_ENDS:
        lines = [f"{odometry_line or f'odometry: {plan.odometry}'} (posing the external camera's frames; the "
                 "robot's own poses are not used)"]
    elif plan.data == "external":
        checked = "checked step by step (--check-slam)" if plan.odometry == "external" else "as they are"
        lines = [f"odometry: the external SLAM's poses, {checked}"]
    elif plan.simulated_odometry:
        per = "per metre driven, a vehicle's" if drift_profile == "vehicle" else "per frame, a hand-held camera's"
        drift = f" with seeded drift ({per})" if "drift" in plan.odometry else ""
        lines = [f"odometry {plan.odometry}: simulated odometry (from ground truth){drift}, not a real front end "
                 "(a real one: --odometry orbslam3, rgbd or file:TRAJ.tum)"]
    else:
        lines = [odometry_line or f"odometry: {plan.odometry}"]
    if camera:
        lines.append(camera)
    return lines


def check_detector_classes(config: Config, data: str, mode: str) -> None:
    """`detector.classes` / `detector.exclude` name classes the detector this run starts can report (ConfigError
    listing the known ones): 'unicorn' would otherwise give an empty map without a word."""
    from semmap.algorithms.detector import check_classes, needs_model, resolve_kind
    from semmap.core.config import ConfigError
    from semmap.runtime.models.model_store import packaged_model

    cfg = config.detector
    if not cfg.classes and not cfg.exclude:
        return
    kind = resolve_kind(cfg.kind, synthetic=data == "synthetic" or data.startswith("synthetic:"))
    model = None
    if needs_model(kind):
        # (the classes a model knows do not depend on its precision: the fp32 copy answers for both)
        model = Path(cfg.model or packaged_model("fp32" if cfg.precision == "auto" else cfg.precision))
    try:
        check_classes(kind, cfg, model)
    except ConfigError:
        raise
    except (OSError, ValueError):
        return  # (an unreadable model or names file: the detector says so when it starts, naming the file)


def detector_budget(config: Config, dataset: Dataset | None, data: str, overrides: list[str],
                    detectors: int | None = None) -> dict | None:  # fmt: skip
    """Real time with the packaged detector: this machine's measured configuration (measured now if this machine
    never was) and the detection cadence the frame budget allows; printed now, in stats.json at the end. Adds
    `detector.every_n_frames=N` to `overrides` when the cadence is auto (0), and where this machine's measured
    layout is single-thread replicas (`detectors` not set), `detector.threads` and the budget's `replicas`."""
    from semmap.algorithms.detector import AUTO, resolve_kind
    from semmap.runtime.models import detector_choice as dc

    det = config.detector
    synthetic = data == "synthetic" or data.startswith("synthetic:")
    kind = resolve_kind(det.kind, synthetic) if det.kind == AUTO else det.kind
    if kind != "onnx" or det.model or data == "external":
        return None
    try:
        if det.precision == "auto" and dc.load_choice() is None:
            print("semmap: the detector was never measured on this machine: measuring its configurations now "
                  "(about a minute, once; `semmap models doctor` shows the table)", file=sys.stderr)
            dc.measure_and_save()
        setup = dc.resolve_setup(det.precision, det.threads, det.input_size, realtime=True)
        chosen = dc.for_front_end(setup, config.odometry.mode)
        if chosen is not setup:  # (pinned, so that every detector process builds this one)
            setup = chosen
            overrides += [f"detector.precision={setup.precision}", f"detector.threads={setup.threads}",
                          f"detector.input_size={setup.hw[1]}x{setup.hw[0]}"]
    except (OSError, ValueError) as exc:  # no model yet: the detector itself reports that when it starts
        print(f"semmap: no frame budget: {exc}", file=sys.stderr)
        return None
    fps = float(getattr(dataset, "rate_hz", 30.0) or 30.0) * float(config.run.speed)
    # replicas by measurement unless they or the cadence were set by hand
    plan, source = dc.setup_plan(setup, fps, config.odometry.mode,
                                 replicas=detectors is None and not det.every_n_frames,
                                 replicas_set=detectors or 1)
    budget: dict = {"detector": setup.label(), "origin": setup.origin, "odometry": config.odometry.mode,
                    "speed": float(config.run.speed)}
    if plan is None:
        print(f"semmap: real time, detector {setup.label()} ({setup.origin}); its cost was not measured here: "
              "no frame budget (`semmap models doctor`)", file=sys.stderr)
        return budget
    every_n = det.every_n_frames or plan.every_n
    if det.every_n_frames == 0:
        overrides.append(f"detector.every_n_frames={plan.every_n}")
    if plan.replicas > 1:
        setup = dataclasses.replace(setup, threads=plan.threads)
        budget["detector"] = f"{setup.label()} x {plan.replicas} replicas"
        budget["replicas"] = plan.replicas
        overrides.append(f"detector.threads={plan.threads}")
    expected = plan.detections_per_s if every_n == plan.every_n else min(fps / every_n, 1e3 / plan.interval_ms)
    budget["planned"] = {**plan.to_dict(), "every_n_frames": every_n, "expected_detections_per_s": round(expected, 2)}
    last = dc.last_achieved(config.odometry.mode, budget["detector"])
    print(f"semmap: real time, detector {budget['detector']} ({setup.origin}); frame budget: "
          f"{dc.describe_plan(plan, source)}" + (f"; every_n_frames set to {every_n}" if det.every_n_frames else "")
          + (f" (the last real-time run here with it achieved {last:.1f}/s)" if last else ""), file=sys.stderr)
    if setup.measured is not None:  # (always, where there is a plan)
        budget["fidelity"] = dc.fidelity(setup.measured)
        told = dc.describe_fidelity(budget["fidelity"])
        if told:
            print(f"semmap: real time's detector {told}", file=sys.stderr)
    return budget


def check_plugins(config: Config) -> None:
    """The detector back end and the odometry front end the configuration names are registered (ConfigError
    naming the key otherwise): checked with the rest of the configuration, before anything starts."""
    from semmap.algorithms.detector import resolve_kind
    from semmap.algorithms.odometry import check_mode

    resolve_kind(config.detector.kind, synthetic=False)
    check_mode(config.odometry.mode)


def preflight_dataset(dataset: Dataset, data: str, config: Config) -> None:
    """The dataset's first frame reads, and it has ground truth where the odometry needs it (else a run would
    wait for a frame that never comes and blame 'no progress')."""
    from semmap.core.outputs import OutputError
    from semmap.datasets import DatasetError

    try:
        if len(dataset) == 0:
            raise OutputError(f"dataset {data} has no frames")
        dataset[0]
    except DatasetError as exc:
        raise OutputError(f"dataset {data}: its first frame cannot be read: {exc}") from None
    from semmap.algorithms.odometry import check_mode

    mode = config.odometry.mode
    if check_mode(mode)[0].needs_groundtruth and not dataset.has_groundtruth:
        raise OutputError(f"--odometry {mode} needs ground-truth poses, and dataset {data} has no ground-truth "
                          "poses: use --odometry rgbd or file:PATH")


def _check_file_odometry(dataset: Dataset | None, data: str, path: str, config: Config) -> str:
    """Match a `file:` trajectory's stamps against the frames' before starting anything: a report, or 'error: ...'
    when too few frames find a pose (two clocks that do not overlap)."""
    from semmap.algorithms.odometry.frontends import OdometryError, check_trajectory_overlap
    from semmap.datasets import DatasetError, open_dataset

    if not Path(path).is_file():
        return f"error: trajectory file {path} does not exist"
    try:
        stamps = (dataset if dataset is not None else open_dataset(data)).stamps()  # (synthetic: opened here)
        if config.run.max_frames:
            stamps = stamps[: config.run.max_frames]
        return check_trajectory_overlap(path, stamps, config.odometry.file_time_offset_s,
                                        rate_hz=config.odometry.file_rate_hz)
    except (DatasetError, OdometryError) as exc:
        return f"error: {exc}"
